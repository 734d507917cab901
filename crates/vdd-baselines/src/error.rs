//! The baselines crate's error type.

/// Errors from setting up and running the baselines.
#[derive(Debug, thiserror::Error)]
pub enum BaselineError {
    /// Invalid configuration or data (shapes, empty data, non-finite inputs).
    #[error(transparent)]
    Core(#[from] vdd_core::CoreError),
    /// The mixture of experts failed (bad shapes, I/O).
    #[error(transparent)]
    Moe(#[from] vdd_moe::MoeError),
    /// Network or checkpoint I/O failed.
    #[error(transparent)]
    Nn(#[from] vdd_nn::NnError),
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

impl From<vdd_moe::step::StepError> for BaselineError {
    fn from(e: vdd_moe::step::StepError) -> Self {
        use vdd_moe::step::StepError;
        match e {
            StepError::NonFinite { iteration, quantity } => Self::NonFinite { iteration, quantity },
            StepError::Core(e) => Self::Core(e),
            StepError::Moe(e) => Self::Moe(e),
        }
    }
}
