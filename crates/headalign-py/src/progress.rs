//! The library's progress reports passed to a Python callable while the GIL is released:
//! each report takes the GIL back for one call `callback(stage, message, done, total)`.
//!
//! Stages: `tracking` (the front end: `done` of `total` views on the route in `message`),
//! `tracked` (that tracking is over), `solving` (an estimation without steps: `total` 0)
//! and `solved`. The Python package draws them (`headalign._progress`: tqdm when it is
//! installed, otherwise one line on stderr).
//!
//! Pitfall: the callback runs inside the estimation; an exception it raises is printed
//! as unraisable (`sys.unraisablehook`) and the estimation goes on.

use headalign::calibrate::{Route, ViewsProgress};
use pyo3::prelude::*;

/// A Python progress callable, or none.
pub struct Progress(Option<Py<PyAny>>);

impl Progress {
    /// `callback` (`None`: no reports).
    pub fn new(callback: Option<Py<PyAny>>) -> Self {
        Self(callback)
    }

    /// One report (module docs).
    pub fn report(&self, stage: &str, message: &str, done: usize, total: usize) {
        let Some(callback) = &self.0 else { return };
        Python::attach(|py| {
            if let Err(e) = callback.call1(py, (stage, message, done, total)) {
                e.write_unraisable(py, Some(callback.bind(py)));
            }
        });
    }

    /// The report of one step of [`headalign::calibrate::calibrate_views`].
    pub fn views(&self, p: ViewsProgress) {
        match p {
            ViewsProgress::Tracking { corners, progress } => {
                let route = match progress.route {
                    Route::Reference => "against the first",
                    Route::Sequence => "as a sequence",
                };
                let message = format!("tracking ({corners} corners, {route})");
                self.report("tracking", &message, progress.done, progress.total);
            }
            ViewsProgress::Tracked { corners } => {
                self.report("tracked", &format!("tracked ({corners} corners)"), 0, 0);
            }
            ViewsProgress::Solving { views } => {
                self.report("solving", &format!("self-calibration of {views} views"), 0, 0);
            }
            ViewsProgress::Solved => self.report("solved", "", 0, 0),
        }
    }
}
