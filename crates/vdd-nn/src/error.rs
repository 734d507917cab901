//! The nn crate's error type.

use std::path::PathBuf;

/// Errors from building, saving and loading networks.
#[derive(Debug, thiserror::Error)]
pub enum NnError {
    /// A configuration value is invalid (zero width, unknown activation, ...).
    #[error("invalid network configuration: {0}")]
    Config(String),
    /// Reading or writing a file failed.
    #[error("i/o error on {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// A file is not valid safetensors (truncated, corrupt, wrong dtype).
    #[error("malformed weights file {path}: {reason}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
    /// A file is not valid safetensors, as the `safetensors` crate reports it.
    #[error("malformed weights file {path}: {source}")]
    Malformed {
        /// The file.
        path: PathBuf,
        /// The parser's error.
        #[source]
        source: safetensors::SafeTensorError,
    },
    /// Tensors could not be serialised to safetensors.
    #[error("cannot serialise {what}: {source}")]
    Serialize {
        /// What was being serialised (a tensor's name, or the file).
        what: String,
        /// The serialiser's error.
        #[source]
        source: safetensors::SafeTensorError,
    },
    /// A tensor the model needs is absent from the file.
    #[error("tensor `{name}` is missing from {path}")]
    MissingTensor {
        /// The tensor name.
        name: String,
        /// The file.
        path: PathBuf,
    },
    /// A model does not match the state it is combined with (an EMA or optimiser built for
    /// another architecture).
    #[error("model mismatch: {0}")]
    ModelMismatch(String),
    /// A tensor in the file has a different shape than the model's.
    #[error("tensor `{name}` has shape {got:?} in the file but {expected:?} in the model")]
    ShapeMismatch {
        /// The tensor name.
        name: String,
        /// The model's shape.
        expected: Vec<usize>,
        /// The file's shape.
        got: Vec<usize>,
    },
    /// A value that its loader would refuse (non-finite, beyond a documented bound), caught
    /// before anything is written, so that whatever is written can be read back.
    #[error("refusing to write {what}: {reason} (its loader would refuse it)")]
    Unwritable {
        /// What was being written (a file, an optimiser's state).
        what: String,
        /// The value and the bound it breaks.
        reason: String,
    },
    /// A checkpoint directory is locked by another process that still runs
    /// ([`crate::checkpoint::CheckpointDir`]).
    #[error(
        "{path} is held by another writer (pid and start time: {owner}); stop it, or remove the lock if it is not running"
    )]
    Locked {
        /// The lock file.
        path: PathBuf,
        /// Its contents: the owner's pid and start time.
        owner: String,
    },
}
