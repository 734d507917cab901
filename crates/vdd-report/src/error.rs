//! The crate's error type.

use std::path::PathBuf;

/// What can go wrong reading runs or writing figures.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum Error {
    /// Reading a file failed.
    #[error("reading {}: {source}", path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// The cause.
        #[source]
        source: std::io::Error,
    },
    /// Creating a directory failed.
    #[error("creating {}: {source}", path.display())]
    CreateDir {
        /// The directory.
        path: PathBuf,
        /// The cause.
        #[source]
        source: std::io::Error,
    },
    /// A file is not valid JSON.
    #[error("parsing {}: {source}", path.display())]
    Parse {
        /// The file.
        path: PathBuf,
        /// The cause.
        #[source]
        source: serde_json::Error,
    },
    /// A `metrics.json` without a `methods` object.
    #[error("{} has no `methods` object", path.display())]
    NoMethods {
        /// The file.
        path: PathBuf,
    },
    /// Runs of different tasks were given to one table.
    #[error("the runs are of different tasks ({}); tabulate them separately", tasks.join(", "))]
    MixedTasks {
        /// The tasks found, in first-seen order.
        tasks: Vec<String>,
    },
    /// Drawing or writing a figure failed (the plotting backend's error is the source).
    #[error("drawing a figure: {0}")]
    Plot(#[source] Box<dyn std::error::Error + Send + Sync + 'static>),
}

impl<E: std::error::Error + Send + Sync + 'static> From<plotters::drawing::DrawingAreaErrorKind<E>>
    for Error
{
    fn from(e: plotters::drawing::DrawingAreaErrorKind<E>) -> Self {
        Error::Plot(Box::new(e))
    }
}

/// `Result` with this crate's [`Error`].
pub type Result<T = (), E = Error> = std::result::Result<T, E>;
