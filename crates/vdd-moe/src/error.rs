//! The MoE crate's error type.

/// Errors from building, running, saving and loading a mixture of experts.
#[derive(Debug, thiserror::Error)]
pub enum MoeError {
    /// Bad shapes, non-finite inputs or invalid configuration values.
    #[error(transparent)]
    Core(#[from] vdd_core::CoreError),
    /// Network construction or checkpoint I/O failed.
    #[error(transparent)]
    Nn(#[from] vdd_nn::NnError),
    /// A saved model lacks a metadata entry it needs.
    #[error("{path} has no `{key}` metadata (not a model saved by `Moe::save`?)")]
    MissingMetadata {
        /// The file.
        path: std::path::PathBuf,
        /// The metadata key.
        key: String,
    },
    /// A metadata entry of a saved model cannot be parsed.
    #[error("{path}: bad `{key}` metadata: {source}")]
    BadMetadata {
        /// The file.
        path: std::path::PathBuf,
        /// The metadata key.
        key: String,
        /// The JSON error.
        #[source]
        source: serde_json::Error,
    },
    /// A metadata entry cannot be written as JSON.
    #[error("cannot serialise the `{key}` metadata: {source}")]
    SerializeMetadata {
        /// The metadata key.
        key: &'static str,
        /// The JSON error.
        #[source]
        source: serde_json::Error,
    },
    /// A saved model was written with a different expert family (kind, dimension or scale
    /// activation) than the one it is being loaded with.
    #[error("expert family mismatch: {0}")]
    FamilyMismatch(String),
    /// A deployment spec that is invalid or does not fit the mixture (the source names the
    /// setting and its value).
    #[error("invalid deployment spec: {0}")]
    Deploy(#[from] vdd_data::DataError),
    /// A backward pass was called before the forward pass whose outputs it differentiates.
    #[error("{0} called before the matching forward pass")]
    NoForward(&'static str),
}
