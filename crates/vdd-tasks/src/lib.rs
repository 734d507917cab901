//! # vdd-tasks
//!
//! Benchmark tasks for distilled policies, each deterministic for a seed:
//!
//! * [`toy`]: 2-D Gaussian mixtures on a circle (`toy-gmm`, `toy-conditional`) with their
//!   analytic mixture, samples, and a mode-coverage summary;
//! * [`avoiding`]: the planar Avoiding task (after D3IL): the environment ([`AvoidingEnv`]),
//!   seeded single, batched (lockstep) and parallel rollouts of any [`vdd_core::Policy`] with
//!   success rate, task entropy and mode histogram ([`avoiding::rollout`]), and a scripted
//!   multimodal demonstrator with demonstration generation ([`avoiding::demonstrator`]); the
//!   recipes' evaluation protocol ([`avoiding::EvalProtocol`]) and observation features
//!   ([`avoiding::ObsFeatures`], from the `vdd_data::features` registry);
//! * [`block_push`]: Multimodal Block-Push (after IBC / Diffusion Policy / BET / VDD), the first
//!   contact task, on the `rapier2d` rigid-body engine: the environment
//!   ([`block_push::BlockPushEnv`]: a round pusher, two square blocks, two target zones, 10 Hz
//!   control of the commanded effector target), seeded single, lockstep and parallel rollouts
//!   of any [`vdd_core::Policy`] with success (p2), p1, task entropy over the 4 modes and mode
//!   histogram ([`block_push::rollout`]), and the scripted multimodal oracle with human-like
//!   noise and demonstration generation ([`block_push::oracle`]);
//! * [`pushing`]: D3IL Pushing on `rapier2d`: the environment ([`pushing::PushingEnv`]: a round
//!   pusher, a red and a green box, two fixed target zones, 28.6 Hz control of the desired
//!   effector position), rollouts with success, p1, mean distance, task entropy per test context
//!   over the 4 modes and mode histogram ([`pushing::rollout`]), and a scripted demonstrator
//!   with human-like noise ([`pushing::oracle`]);
//! * [`aligning`]: D3IL Aligning on `rapier2d`: the environment ([`aligning::AligningEnv`]: a
//!   rod with a simulated height that pushes an open tray to a random target pose from inside
//!   or outside it), rollouts with success, mean distance, task entropy per test context over
//!   the 2 modes ([`aligning::rollout`]), and a scripted demonstrator with human-like noise
//!   ([`aligning::oracle`]);
//! * [`d3il`]: what Pushing and Aligning share: the trait their environments implement
//!   ([`d3il::ContextEnv`]), their settings, status, evaluation protocol over test contexts
//!   ([`d3il::EvalProtocol`]), metrics and rollouts ([`d3il::rollout`]), demonstrations and the
//!   planar physics helpers;
//! * [`timing`]: µs per action of policies timed together ([`timing::us_per_action`]).
//!
//! Errors are [`TaskError`]; shape and finiteness violations found by the `vdd_core` helpers are
//! wrapped in [`TaskError::Core`].
//!
//! ```
//! use vdd_tasks::avoiding::demonstrator::{AvoidingDemonstrator, DemonstratorConfig};
//! use vdd_tasks::avoiding::rollout::{evaluate_cloned, EvalConfig, Stepping};
//!
//! let demo = AvoidingDemonstrator::new(DemonstratorConfig::default()).unwrap();
//! let cfg = EvalConfig {
//!     n_rollouts: 64,
//!     seed: 0,
//!     stepping: Stepping::Lockstep { batch_size: 16 },
//!     record: false,
//! };
//! let eval = evaluate_cloned(&demo, 2, &cfg).unwrap();
//! assert!(eval.metrics.success_rate > 0.95);
//! assert!(eval.metrics.task_entropy > 0.9);
//! ```
#![warn(missing_docs)]

pub mod aligning;
pub mod avoiding;
pub mod block_push;
pub mod d3il;
pub mod demo_data;
pub mod episodes;
mod error;
pub mod pushing;
pub mod scripted;
pub mod timing;
pub mod toy;
pub mod visits;

pub use avoiding::demonstrator::{
    AvoidingDemonstrator, DemonstratorConfig, generate_demonstrations,
};
pub use avoiding::rollout::{
    EvalConfig, Metrics, Rollout, Stepping, evaluate, evaluate_cloned, evaluate_parallel,
};
pub use avoiding::{AvoidingEnv, AvoidingMode, Status};
pub use error::{Result, TaskError};
pub use toy::CircleGmm;

/// `−Σ p log p / log K` of a histogram with `K = counts.len()` bins: 1 for an even spread, 0 for
/// a single occupied bin, an empty histogram, or a single bin.
///
/// With the 24 Avoiding modes this is D3IL's task entropy.
///
/// ```
/// use vdd_tasks::normalized_entropy;
/// assert!((normalized_entropy(&[3, 3, 3, 3]) - 1.0).abs() < 1e-6);
/// assert_eq!(normalized_entropy(&[0, 7, 0]), 0.0);
/// ```
pub fn normalized_entropy(counts: &[usize]) -> f32 {
    let total: usize = counts.iter().sum();
    if total == 0 || counts.len() < 2 {
        return 0.0;
    }
    let h: f64 = counts
        .iter()
        .filter(|&&c| c > 0)
        .map(|&c| {
            let p = c as f64 / total as f64;
            p * (1.0 / p).ln()
        })
        .sum();
    (h / (counts.len() as f64).ln()) as f32
}
