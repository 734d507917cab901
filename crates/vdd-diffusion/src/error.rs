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
    /// A deployment spec does not fit the teacher (its window, chunk or features against the
    /// teacher's state and action dimensions).
    #[error("the deployment spec does not fit the teacher: {0}")]
    Deploy(#[from] vdd_data::DataError),
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
    /// A metadata entry of a saved teacher cannot be read.
    #[error("cannot load teacher from {path}: bad `{key}` metadata: {source}")]
    BadMetadata {
        /// The file.
        path: PathBuf,
        /// The metadata key.
        key: &'static str,
        /// Why it cannot be read.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync + 'static>,
    },
    /// The teacher's metadata cannot be written as JSON.
    #[error("cannot serialise the teacher's `{key}` metadata: {source}")]
    SerializeMetadata {
        /// The metadata key.
        key: &'static str,
        /// The JSON error.
        #[source]
        source: serde_json::Error,
    },
}

/// Result alias for this crate.
pub type Result<T, E = DiffusionError> = std::result::Result<T, E>;

impl From<DiffusionError> for CoreError {
    /// Maps a diffusion error onto the core error type, for the trait implementations: core
    /// errors stay what they are, the others become [`CoreError::Implementor`] with the
    /// diffusion error as the source.
    fn from(e: DiffusionError) -> Self {
        match e {
            DiffusionError::Core(c) => c,
            other => CoreError::implementor(other),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::error::Error as _;

    /// Through the core traits a diffusion error stays the source of the core error.
    #[test]
    fn diffusion_errors_stay_the_source_of_core_errors() {
        let core = CoreError::from(DiffusionError::Diverged { step: 3, loss: f32::NAN });
        assert!(matches!(core, CoreError::Implementor(_)));
        let source = core.source().unwrap().downcast_ref::<DiffusionError>().unwrap();
        assert!(matches!(source, DiffusionError::Diverged { step: 3, .. }));
        let shape = CoreError::NonFinite { what: "x" };
        assert_eq!(CoreError::from(DiffusionError::Core(shape.clone())), shape);
    }
}
