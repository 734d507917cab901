//! Progress output of a recipe run: bars and spinners on stderr (hidden when stderr is not a
//! terminal). The bars of concurrent trainings stack in one shared
//! [`MultiProgress`](indicatif::MultiProgress); log lines go through [`log`] so that they print
//! above the bars instead of through them.
//!
//! ```
//! let bar = vdd_recipe::progress::bar(3, "vdd-beso s0");
//! bar.inc(3);
//! bar.finish_and_clear();
//! vdd_recipe::progress::log("[vdd-beso s0] trained");
//! ```

use std::sync::OnceLock;

pub use indicatif::ProgressBar;
use indicatif::{MultiProgress, ProgressStyle};

fn multi() -> &'static MultiProgress {
    static MULTI: OnceLock<MultiProgress> = OnceLock::new();
    MULTI.get_or_init(MultiProgress::new)
}

/// A bar of `len` steps labelled `what`.
pub fn bar(len: u64, what: &str) -> ProgressBar {
    let bar = ProgressBar::new(len);
    bar.set_style(
        ProgressStyle::with_template("{prefix:>14} [{bar:30}] {pos}/{len} {elapsed} {msg}")
            .expect("valid template")
            .progress_chars("=> "),
    );
    bar.set_prefix(what.to_owned());
    multi().add(bar)
}

/// A spinner labelled `what` with message `msg`, for stages without a step count.
pub fn spinner(what: &str, msg: &str) -> ProgressBar {
    let bar = ProgressBar::new_spinner();
    bar.set_style(
        ProgressStyle::with_template("{prefix:>14} {spinner} {elapsed} {msg}")
            .expect("valid template"),
    );
    bar.set_prefix(what.to_owned());
    bar.set_message(msg.to_owned());
    let bar = multi().add(bar);
    bar.enable_steady_tick(std::time::Duration::from_millis(200));
    bar
}

/// Prints a log line to stderr above any active bars.
pub fn log(line: impl AsRef<str>) {
    multi().suspend(|| eprintln!("{}", line.as_ref()));
}
