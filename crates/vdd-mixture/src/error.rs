//! The mixture crate's error type.

use vdd_moe::step::StepError;

/// Errors from setting up and running EM and IMC.
#[derive(Debug, thiserror::Error)]
pub enum MixtureError {
    /// Invalid configuration or data (shapes, empty data, non-finite inputs).
    #[error(transparent)]
    Core(#[from] vdd_core::CoreError),
    /// The mixture of experts failed (bad shapes, I/O).
    #[error(transparent)]
    Moe(#[from] vdd_moe::MoeError),
    /// A loss, gradient or likelihood became NaN or infinite; the update that would have used it
    /// was not applied.
    #[error("non-finite {quantity} at iteration {iteration}; the update was not applied")]
    NonFinite {
        /// Iteration (0-based) at which it happened.
        iteration: usize,
        /// Which quantity.
        quantity: &'static str,
    },
}

impl From<StepError> for MixtureError {
    /// A failed shared step ([`vdd_moe::step`]): a non-finite loss or gradient stays
    /// [`MixtureError::NonFinite`], the other errors keep their source.
    fn from(e: StepError) -> Self {
        match e {
            StepError::NonFinite { iteration, quantity } => Self::NonFinite { iteration, quantity },
            StepError::Core(e) => Self::Core(e),
            StepError::Moe(e) => Self::Moe(e),
        }
    }
}
