//! Errors of the BESO/D3IL importer and teacher.

use std::path::PathBuf;

/// What can go wrong importing, loading or running a BESO/D3IL teacher.
#[derive(Debug, thiserror::Error)]
pub enum BesoError {
    /// Reading a file failed.
    #[error("cannot read {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// A YAML file could not be parsed.
    #[error("malformed YAML in {path}: {source}")]
    Yaml {
        /// The file.
        path: PathBuf,
        /// The parser's error.
        #[source]
        source: serde_yaml_ng::Error,
    },
    /// A JSON file or metadata entry could not be parsed.
    #[error("malformed JSON in {what}: {source}")]
    Json {
        /// The file or entry.
        what: String,
        /// The parser's error.
        #[source]
        source: serde_json::Error,
    },
    /// A configuration key the importer needs is absent.
    #[error("{path}: missing key `{key}`")]
    MissingKey {
        /// The file.
        path: PathBuf,
        /// The dotted key.
        key: String,
    },
    /// A configuration value is of the wrong type, out of range or not supported.
    #[error("{path}: key `{key}` has unsupported value {value}: {reason}")]
    BadValue {
        /// The file.
        path: PathBuf,
        /// The dotted key.
        key: String,
        /// The value as found.
        value: String,
        /// What is wrong.
        reason: String,
    },
    /// The weights file holds a tensor the configured network does not have.
    #[error("{path}: unexpected tensor `{name}` (the config describes another layout)")]
    UnexpectedTensor {
        /// The weights file.
        path: PathBuf,
        /// The tensor name.
        name: String,
    },
    /// Building or loading the network failed (a missing tensor names its key here).
    #[error(transparent)]
    Nn(#[from] vdd_nn::NnError),
    /// A shape or value check of the core crate failed.
    #[error(transparent)]
    Core(#[from] vdd_core::CoreError),
    /// The noise process rejected its configuration.
    #[error(transparent)]
    Diffusion(#[from] vdd_diffusion::DiffusionError),
}

impl From<BesoError> for vdd_core::CoreError {
    fn from(e: BesoError) -> Self {
        match e {
            BesoError::Core(c) => c,
            other => vdd_core::CoreError::implementor(other),
        }
    }
}
