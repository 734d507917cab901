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
    /// A loss or a gradient became NaN or infinite; the update of that step was not applied.
    #[error("non-finite {quantity} at step {iteration}; the update was not applied")]
    NonFinite {
        /// Step (0-based) at which it happened.
        iteration: usize,
        /// Which quantity.
        quantity: &'static str,
    },
}
