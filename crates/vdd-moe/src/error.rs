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
    /// A saved model's configuration could not be read.
    #[error("invalid saved model configuration: {0}")]
    Config(String),
}
