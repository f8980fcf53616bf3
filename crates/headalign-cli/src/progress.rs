//! Progress on stderr for long steps (reading a folder's images or a recording,
//! tracking a folder's views, the self-calibration of `calibrate`): a bar over views, a
//! spinner for a step of unknown length. Drawn only when stderr is a terminal (indicatif
//! hides them otherwise), so scripts, pipes and `--json` consumers see nothing; cleared
//! when the step ends or its function returns early with an error, so the results print
//! as before. No degrees of freedom, no units but views.

use std::time::Duration;

use indicatif::{ProgressBar, ProgressFinish, ProgressStyle};

/// A bar over `total` views, named `what`.
pub fn views(what: &str, total: usize) -> ProgressBar {
    let bar = ProgressBar::new(total as u64).with_finish(ProgressFinish::AndClear);
    if let Ok(style) = ProgressStyle::with_template("{prefix} [{wide_bar}] {pos}/{len} views {msg} {elapsed}")
    {
        bar.set_style(style.progress_chars("=> "));
    }
    bar.set_prefix(what.to_string());
    bar
}

/// A spinner with a message, ticking on its own while a step runs.
pub fn spinner(message: String) -> ProgressBar {
    let spin = ProgressBar::new_spinner().with_finish(ProgressFinish::AndClear);
    if let Ok(style) = ProgressStyle::with_template("{spinner} {msg} {elapsed}") {
        spin.set_style(style);
    }
    spin.set_message(message);
    spin.enable_steady_tick(Duration::from_millis(200));
    spin
}
