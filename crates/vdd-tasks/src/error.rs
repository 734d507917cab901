//! The tasks crate's error type.

use vdd_core::CoreError;

/// Errors raised by tasks, rollouts and demonstrators.
///
/// Shape and finiteness violations detected by the shared `vdd_core` helpers arrive as
/// [`TaskError::Core`]; a policy that fails while it is being rolled out is reported with the
/// episode and step it failed at ([`TaskError::Policy`]).
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum TaskError {
    /// A shape, finiteness or configuration check from `vdd_core` failed.
    #[error(transparent)]
    Core(#[from] CoreError),
    /// An argument or configuration value is out of its valid range.
    #[error("invalid argument: {0}")]
    InvalidArgument(String),
    /// The policy's dimensions do not match the task's observation and action.
    #[error(
        "policy dimensions {got_obs} -> {got_action} do not match the task's \
         {obs} -> {action} (observation -> action)"
    )]
    PolicyDims {
        /// Observation dimension the task produces.
        obs: usize,
        /// Action dimension the task consumes.
        action: usize,
        /// The policy's observation dimension.
        got_obs: usize,
        /// The policy's action dimension.
        got_action: usize,
    },
    /// The policy returned an error (or a non-finite action) during a rollout.
    #[error("policy failed in episode {episode} at step {step}: {source}")]
    Policy {
        /// Index of the episode (or, for lockstep rollouts, of its first episode).
        episode: usize,
        /// Step within the episode.
        step: usize,
        /// The underlying error.
        source: CoreError,
    },
    /// [`crate::avoiding::AvoidingEnv::step`] was called after the episode had ended.
    #[error("the episode has ended ({0}); call reset before stepping again")]
    EpisodeOver(&'static str),
    /// The demonstrator was asked for a batch of another size in the middle of an episode
    /// (reported through the `Policy` trait as the source of a
    /// [`CoreError::Implementor`]).
    #[error(
        "the demonstrator is driving {driving} environments in this episode but got {got}; \
         call reset() before changing the batch"
    )]
    DemonstratorBatch {
        /// Environments of the current episode.
        driving: usize,
        /// Batch size of the call.
        got: usize,
    },
    /// A rollout worker thread panicked.
    #[error("a rollout worker thread panicked")]
    WorkerPanicked,
    /// The demonstrator failed too often to collect the requested demonstrations.
    #[error(
        "collected only {collected} successful demonstrations of {wanted} in {attempts} attempts"
    )]
    TooManyFailures {
        /// Successful episodes collected.
        collected: usize,
        /// Episodes requested.
        wanted: usize,
        /// Episodes run.
        attempts: usize,
    },
}

/// Result alias for the tasks crate.
pub type Result<T, E = TaskError> = std::result::Result<T, E>;
