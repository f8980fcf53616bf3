//! The library's errors as Python exceptions: bad input is `ValueError`, a failed
//! estimation `RuntimeError`, a file that cannot be written `OSError`; the message is the
//! library's one line (the CLI prints the same).
//!
//! Which is which: [`AlignError::InvalidOption`], [`AlignError::Images`],
//! [`AlignError::Recording`] and [`AlignError::Observations`] (a malformed or empty
//! session) are the caller's input, as is every [`FileError::File`] (a path that cannot
//! be read or holds no views); [`AlignError::Output`] is a write; everything else
//! (too few tracks, a motion the method cannot use, a failed geometric step) is the
//! estimation's.

use headalign::AlignError;
use headalign_io::FileError;
use pyo3::PyErr;
use pyo3::exceptions::{PyOSError, PyRuntimeError, PyValueError};

/// The Python exception of a library error (module docs).
pub fn align_error(e: AlignError) -> PyErr {
    let message = e.to_string();
    exception(e, message)
}

/// [`align_error`] with its message after `context` (`context: message`).
pub fn align_error_in(e: AlignError, context: &str) -> PyErr {
    let message = format!("{context}: {e}");
    exception(e, message)
}

/// The exception of `e`'s kind with `message`.
fn exception(e: AlignError, message: String) -> PyErr {
    match e {
        AlignError::InvalidOption(_)
        | AlignError::Images(_)
        | AlignError::Recording(_)
        | AlignError::Observations(_) => PyValueError::new_err(message),
        AlignError::Output(_) => PyOSError::new_err(message),
        _ => PyRuntimeError::new_err(message),
    }
}

/// The Python exception of a reader's error (module docs).
pub fn file_error(e: FileError) -> PyErr {
    match e {
        FileError::File(m) => PyValueError::new_err(m),
        FileError::Align(e) => align_error(e),
    }
}

/// A `ValueError` with `message`.
pub fn value_error(message: impl Into<String>) -> PyErr {
    PyValueError::new_err(message.into())
}
