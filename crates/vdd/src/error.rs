//! The VDD trainer's error type.

/// Errors from setting up, running, checkpointing and resuming VDD training.
#[derive(Debug, thiserror::Error)]
pub enum VddError {
    /// Invalid configuration or data (shapes, empty data, non-finite inputs).
    #[error(transparent)]
    Core(#[from] vdd_core::CoreError),
    /// The student failed (bad shapes, I/O).
    #[error(transparent)]
    Moe(#[from] vdd_moe::MoeError),
    /// Network checkpoint I/O failed.
    #[error(transparent)]
    Nn(#[from] vdd_nn::NnError),
    /// The teacher's score, a gradient or a loss became NaN or infinite; the update of that
    /// iteration was not applied.
    #[error("non-finite {quantity} at iteration {iteration}; the update was not applied")]
    NonFinite {
        /// Iteration (0-based) at which it happened.
        iteration: usize,
        /// Which quantity.
        quantity: &'static str,
    },
    /// Checkpoint files or directories could not be written or read.
    #[error("checkpoint {path}: {source}")]
    CheckpointIo {
        /// The file or directory.
        path: std::path::PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
    /// The trainer's state in a checkpoint could not be written or parsed as JSON.
    #[error("checkpoint {path}: trainer state: {source}")]
    CheckpointFormat {
        /// The file.
        path: std::path::PathBuf,
        /// The JSON error.
        #[source]
        source: serde_json::Error,
    },
    /// A checkpoint's trainer state breaks a documented range or does not belong to its
    /// student (an optimiser or average of another model); `what` says which part.
    #[error("checkpoint {path}: {what}: {source}")]
    CheckpointInvalid {
        /// The generation directory.
        path: std::path::PathBuf,
        /// The part of the state (`expert optimiser`, `settings`, ...).
        what: &'static str,
        /// What is wrong.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// A learned gating has no actions to learn from: no dataset actions, and the teacher
    /// cannot sample (its error is the source).
    #[error("a learned gating needs dataset actions or a teacher that samples: {source}")]
    NoGatingActions {
        /// Why the teacher could not sample.
        #[source]
        source: vdd_core::CoreError,
    },
}

impl From<vdd_moe::step::StepError> for VddError {
    /// A failed shared step ([`vdd_moe::step`]) as the trainer's error: a non-finite loss or
    /// gradient stays [`VddError::NonFinite`].
    fn from(e: vdd_moe::step::StepError) -> Self {
        use vdd_moe::step::StepError;
        match e {
            StepError::NonFinite { iteration, quantity } => Self::NonFinite { iteration, quantity },
            StepError::Core(e) => Self::Core(e),
            StepError::Moe(e) => Self::Moe(e),
        }
    }
}
