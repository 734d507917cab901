//! The diffusion crate's error type.

use std::path::PathBuf;

use vdd_core::CoreError;
use vdd_nn::NnError;

/// Errors from building, training, sampling, saving and loading diffusion teachers.
#[derive(Debug, thiserror::Error)]
pub enum DiffusionError {
    /// Shape, finiteness or configuration error reported by the core crate.
    #[error(transparent)]
    Core(#[from] CoreError),
    /// Error from the network crate (configuration, weights file).
    #[error(transparent)]
    Nn(#[from] NnError),
    /// A configuration value is invalid.
    #[error("invalid diffusion configuration: {0}")]
    Config(String),
    /// The training data cannot be used (empty, mismatched rows, non-finite values).
    #[error("invalid training data: {0}")]
    Data(String),
    /// Training produced a non-finite loss (diverged).
    #[error("training diverged at step {step}: loss is {loss}")]
    Diverged {
        /// The optimisation step (1-based).
        step: u64,
        /// The offending loss value.
        loss: f32,
    },
    /// A saved teacher's metadata is missing, malformed or of another kind.
    #[error("cannot load teacher from {path}: {reason}")]
    Format {
        /// The file.
        path: PathBuf,
        /// What is wrong.
        reason: String,
    },
}

/// Result alias for this crate.
pub type Result<T, E = DiffusionError> = std::result::Result<T, E>;

impl From<DiffusionError> for CoreError {
    /// Maps any diffusion error onto the core error type, for the trait implementations.
    fn from(e: DiffusionError) -> Self {
        match e {
            DiffusionError::Core(c) => c,
            other => CoreError::Config(other.to_string()),
        }
    }
}
