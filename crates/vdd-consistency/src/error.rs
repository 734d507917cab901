//! The consistency crate's error type.

/// Errors from setting up and running consistency distillation and from the distilled
/// policies.
#[derive(Debug, thiserror::Error)]
pub enum ConsistencyError {
    /// Invalid configuration or data (shapes, empty data, non-finite inputs), or an error the
    /// teacher reported.
    #[error(transparent)]
    Core(#[from] vdd_core::CoreError),
    /// The diffusion side failed: the network's architecture or construction, the noise
    /// levels, an integration step of the teacher's probability-flow ODE.
    #[error(transparent)]
    Diffusion(#[from] vdd_diffusion::DiffusionError),
    /// The moving averages of the network's weights failed.
    #[error(transparent)]
    Nn(#[from] vdd_nn::NnError),
    /// A deployment spec does not fit the policy (its window, chunk or features against the
    /// policy's state and action dimensions).
    #[error("the deployment spec does not fit the policy: {0}")]
    Deploy(#[from] vdd_data::DataError),
    /// A saved policy's metadata is missing, malformed, of another kind or out of range.
    #[error("cannot load a distilled policy from {path}: `{key}`: {reason}")]
    Format {
        /// The file.
        path: std::path::PathBuf,
        /// The metadata key (or the value inside it) that is wrong.
        key: String,
        /// What is wrong.
        reason: String,
    },
    /// A loss or a gradient became NaN or infinite; the update of that step was not applied.
    #[error("non-finite {quantity} at step {iteration}; the update was not applied")]
    NonFinite {
        /// Step (0-based) at which it happened.
        iteration: usize,
        /// Which quantity.
        quantity: &'static str,
    },
}
