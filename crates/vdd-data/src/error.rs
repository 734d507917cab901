//! The data crate's error type.

use std::path::PathBuf;

use vdd_core::CoreError;

/// Everything that can go wrong when building, loading, saving, windowing or batching a dataset.
///
/// Every constructor and loader in this crate validates its whole input before it returns, so an
/// error never leaves a half-built value behind.
#[derive(Debug, thiserror::Error)]
pub enum DataError {
    /// Reading or writing a file failed.
    #[error("i/o error on {path}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// A file is not a valid `.npy` / `.npz` (bad magic, bad header, truncated data, ...).
    #[error("malformed file {path}: {reason}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// An `.npz` archive (a zip file) cannot be read or written: not a zip archive, a corrupt
    /// entry, a failed write.
    #[error("npz archive {path}{}: {source}", in_array(.array.as_deref()))]
    Archive {
        /// The archive.
        path: PathBuf,
        /// The array being read or written, if any.
        array: Option<String>,
        /// The zip reader's or writer's error.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync + 'static>,
    },
    /// An array has a dtype this crate cannot read for its role.
    #[error("array `{array}` in {path} has dtype `{found}`, expected {expected}")]
    Dtype {
        /// The file.
        path: PathBuf,
        /// The array (npz key or file stem).
        array: String,
        /// The numpy type string found, e.g. `<i4`.
        found: String,
        /// What the array may hold.
        expected: &'static str,
    },
    /// A required array is absent from an `.npz` archive or a directory of `.npy` files.
    #[error("array `{key}` is missing from {path} (arrays present: {present})")]
    MissingKey {
        /// The archive or directory.
        path: PathBuf,
        /// The missing array name.
        key: String,
        /// The arrays that are present, comma-separated.
        present: String,
    },
    /// Shapes or lengths that must agree do not.
    #[error("shape mismatch for {what}: expected {expected}, got {got}")]
    Shape {
        /// Which quantity was wrong.
        what: String,
        /// The shape that was expected.
        expected: String,
        /// The shape that was given.
        got: String,
    },
    /// A NaN or infinite value in the data (after conversion to `f32`).
    #[error(
        "non-finite value (NaN, infinite, or beyond the f32 range) in {what} of episode {episode} at step {step}"
    )]
    NonFinite {
        /// `"observations"` or `"actions"`.
        what: &'static str,
        /// Episode index.
        episode: usize,
        /// Time step within the episode.
        step: usize,
    },
    /// The dataset (or an episode of it) holds nothing.
    #[error("empty dataset: {0}")]
    Empty(String),
    /// The existence mask is not a 0/1 prefix mask.
    #[error("invalid existence mask: {0}")]
    Mask(String),
    /// No episode is long enough for one observation window plus one action chunk.
    #[error(
        "an observation window of {obs_window} and an action chunk of {action_chunk} need \
         {needed} valid steps, but the longest episode has {longest}"
    )]
    WindowTooLong {
        /// Observation window length.
        obs_window: usize,
        /// Action chunk length.
        action_chunk: usize,
        /// Valid steps one sample needs.
        needed: usize,
        /// Valid steps of the longest episode.
        longest: usize,
    },
    /// A configuration value is out of range (zero batch size, split fraction outside (0, 1), ...).
    #[error("invalid configuration: {0}")]
    Config(String),
    /// A normalisation could not be written as JSON or parsed from it.
    #[error("malformed normalisation: {0}")]
    Json(#[source] serde_json::Error),
    /// A feature map name and version the [registry](crate::features::registry) does not hold.
    #[error("unknown feature map `{name}` version {version} (known: {known})")]
    UnknownFeatureMap {
        /// The name asked for.
        name: String,
        /// The version asked for.
        version: u32,
        /// The registered maps, comma-separated (`name vN`).
        known: String,
    },
    /// A setting of a deployment spec ([`crate::DeploySpec`]) or a feature map that is out of
    /// range or does not fit the policy: names the setting and its value.
    #[error("`{key}` = {value}: {reason}")]
    Spec {
        /// The setting (`features`, `obs_window`, `action_chunk` or `execute_steps`).
        key: &'static str,
        /// Its value.
        value: String,
        /// What is wrong with it.
        reason: String,
    },
    /// An error from the core crate (e.g. an invalid `Affine`).
    #[error(transparent)]
    Core(#[from] CoreError),
}

/// Result alias for the data crate.
pub type Result<T, E = DataError> = std::result::Result<T, E>;

pub(crate) fn io_err(path: &std::path::Path) -> impl FnOnce(std::io::Error) -> DataError + '_ {
    move |source| DataError::Io { path: path.to_owned(), source }
}

fn in_array(array: Option<&str>) -> String {
    array.map_or(String::new(), |a| format!(", array `{a}`"))
}

pub(crate) fn archive_err<'a, E: std::error::Error + Send + Sync + 'static>(
    path: &'a std::path::Path,
    array: Option<&'a str>,
) -> impl FnOnce(E) -> DataError + 'a {
    move |e| DataError::Archive {
        path: path.to_owned(),
        array: array.map(str::to_owned),
        source: Box::new(e),
    }
}

pub(crate) fn format_err(path: &std::path::Path, reason: impl ToString) -> DataError {
    DataError::Format { path: path.to_owned(), reason: reason.to_string() }
}
