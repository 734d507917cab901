//! Progress of long runs, without printing: the layer reports bars, spinners and lines to a
//! process-wide [`Sink`] (as the `log` crate's facade does), which the program running the
//! layer installs once ([`set_sink`]); `cargo xtask` installs terminal bars. Without a sink,
//! nothing is shown.

use std::sync::{Arc, OnceLock, RwLock};

/// A progress bar or spinner handed out by a [`Sink`].
pub trait Bar: Send + Sync {
    /// Sets the steps done.
    fn set_position(&self, _pos: u64) {}
    /// Adds `n` steps done.
    fn inc(&self, _n: u64) {}
    /// Sets the message shown beside the bar.
    fn set_message(&self, _msg: String) {}
    /// Removes the bar.
    fn finish_and_clear(&self) {}
}

/// Where the layer's progress goes.
pub trait Sink: Send + Sync {
    /// A bar of `len` steps labelled `what`.
    fn bar(&self, _len: u64, _what: &str) -> Box<dyn Bar> {
        Box::new(Silent)
    }
    /// A spinner labelled `what` with message `msg`, for stages without a step count.
    fn spinner(&self, _what: &str, _msg: &str) -> Box<dyn Bar> {
        Box::new(Silent)
    }
    /// A log line (the command's diagnostics: stderr in a terminal program).
    fn log(&self, _line: &str) {}
    /// A line of the run's results (a table, the acceptance lines: stdout in a terminal
    /// program).
    fn print(&self, _line: &str) {}
}

/// The sink and bar that show nothing.
#[derive(Debug, Clone, Copy, Default)]
pub struct Silent;

impl Bar for Silent {}
impl Sink for Silent {}

fn slot() -> &'static RwLock<Arc<dyn Sink>> {
    static SINK: OnceLock<RwLock<Arc<dyn Sink>>> = OnceLock::new();
    SINK.get_or_init(|| RwLock::new(Arc::new(Silent)))
}

/// Installs the process-wide sink (replacing any earlier one).
pub fn set_sink(new: Arc<dyn Sink>) {
    match slot().write() {
        Ok(mut s) => *s = new,
        Err(e) => *e.into_inner() = new,
    }
}

fn current() -> Arc<dyn Sink> {
    slot().read().map(|s| s.clone()).unwrap_or_else(|e| e.into_inner().clone())
}

/// A bar of `len` steps labelled `what`.
pub fn bar(len: u64, what: &str) -> Box<dyn Bar> {
    current().bar(len, what)
}

/// A spinner labelled `what` with message `msg`.
pub fn spinner(what: &str, msg: &str) -> Box<dyn Bar> {
    current().spinner(what, msg)
}

/// A log line.
pub fn log(line: impl AsRef<str>) {
    current().log(line.as_ref());
}

/// A line of results.
pub fn print(line: impl AsRef<str>) {
    current().print(line.as_ref());
}
