//! Rollouts of any [`Policy`] on the Avoiding task, and their aggregate metrics: the Avoiding
//! side of the shared engine in [`crate::episodes`] ([`AvoidingEnv`] is its [`Env`]), whose
//! module docs say how episodes are seeded and stepped.
//!
//! [`evaluate`] runs the episodes on the calling thread; [`evaluate_parallel`] spreads them
//! over one policy per thread and returns exactly what [`evaluate`] would; [`evaluate_cloned`]
//! clones one policy per thread.
//!
//! ```
//! use vdd_core::{CoreError, Policy};
//! use vdd_tasks::avoiding::rollout::{evaluate, EvalConfig, Stepping};
//!
//! /// Moves the desired position up while steering it to x = 0.28 (the far-left route).
//! #[derive(Clone)]
//! struct FarLeft;
//! impl Policy for FarLeft {
//!     fn obs_dim(&self) -> usize { 4 }
//!     fn action_dim(&self) -> usize { 2 }
//!     fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> Result<(), CoreError> {
//!         vdd_core::check_act_args(self, obs, action)?;
//!         action[0] = (0.28 - obs[0]).clamp(-0.01, 0.01);
//!         action[1] = 0.01;
//!         Ok(())
//!     }
//! }
//!
//! let cfg = EvalConfig { n_rollouts: 8, stepping: Stepping::Lockstep { batch_size: 4 }, ..EvalConfig::default() };
//! let eval = evaluate(&mut FarLeft, &cfg).unwrap();
//! assert_eq!(eval.metrics.success_rate, 1.0);
//! assert_eq!(eval.metrics.mode_counts[0], 8); // always mode (0, 0, 0)
//! assert_eq!(eval.metrics.task_entropy, 0.0);
//! ```

use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Policy};

use crate::episodes::{self, Env, TaskMetrics};
pub use crate::episodes::{EvalConfig, SeedStreams, Stepping, Trajectory};

use super::{ACTION_DIM, AvoidingEnv, AvoidingMode, N_LEVELS, N_MODES, OBS_DIM, Status, mode_of};
use crate::{Result, TaskError, normalized_entropy};

impl Env for AvoidingEnv {
    type Status = Status;
    type Info = [Option<u8>; N_LEVELS];
    const OBS_DIM: usize = OBS_DIM;
    const ACTION_DIM: usize = ACTION_DIM;
    const STREAMS: SeedStreams = SeedStreams {
        episode: "avoiding-episode",
        chunk: "avoiding-chunk",
        start: "avoiding-start",
    };

    /// Avoiding has no settings.
    type Config = ();

    fn build(_: &()) -> Result<Self> {
        Ok(AvoidingEnv::new())
    }

    /// Every Avoiding episode starts at [`super::START`]: the seed is not used.
    fn reset(&mut self, _: u64) {
        *self = AvoidingEnv::new();
    }

    fn observe(&self, out: &mut [f32]) -> std::result::Result<(), CoreError> {
        vdd_core::check_len("observation buffer", out.len(), OBS_DIM)?;
        out.copy_from_slice(&self.observation());
        Ok(())
    }

    fn apply(&mut self, action: &[f32], applied: &mut [f32]) -> std::result::Result<(), CoreError> {
        episodes::check_apply(self, action, applied)?;
        let a = AvoidingEnv::clip_action([action[0], action[1]]);
        applied.copy_from_slice(&a);
        self.step_clipped(a);
        Ok(())
    }

    fn status(&self) -> Status {
        AvoidingEnv::status(self)
    }

    fn is_done(&self) -> bool {
        AvoidingEnv::status(self).is_done()
    }

    fn steps(&self) -> usize {
        AvoidingEnv::steps(self)
    }

    fn info(&self) -> Self::Info {
        self.gaps()
    }
}

/// The outcome of one Avoiding episode: its [`Status`] (never [`Status::Running`]), the gap
/// recorded at each level in `info` (`None` for levels never crossed), its steps and, when
/// asked for, its trajectory.
pub type Rollout = episodes::Rollout<AvoidingEnv>;

/// Every rollout of an Avoiding evaluation, in episode order, and their [`Metrics`].
pub type Evaluation = episodes::Evaluation<AvoidingEnv, Metrics>;

impl episodes::Rollout<AvoidingEnv> {
    /// Whether the episode succeeded.
    pub fn success(&self) -> bool {
        self.status == Status::Success
    }

    /// The behaviour mode, when all three levels were crossed (always, for a success).
    pub fn mode(&self) -> Option<AvoidingMode> {
        mode_of(self.info)
    }
}

/// The policy seed of episode `episode` under per-episode stepping.
pub fn episode_seed(seed: u64, episode: usize) -> u64 {
    episodes::episode_seed::<AvoidingEnv>(seed, episode)
}

/// The policy seed of chunk `chunk` under lockstep stepping.
pub fn chunk_seed(seed: u64, chunk: usize) -> u64 {
    episodes::chunk_seed::<AvoidingEnv>(seed, chunk)
}

/// Aggregate metrics of a set of rollouts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Metrics {
    /// Episodes run.
    pub rollouts: usize,
    /// Successful episodes.
    pub successes: usize,
    /// Episodes ended by a collision.
    pub collisions: usize,
    /// Episodes that hit the step limit.
    pub timeouts: usize,
    /// `successes / rollouts`.
    pub success_rate: f64,
    /// `−Σ_m p_m log p_m / log 24` over the modes of successful episodes (D3IL's task entropy;
    /// 0 without successes).
    pub task_entropy: f64,
    /// Successful episodes per mode ([`AvoidingMode::index`]), 24 entries.
    pub mode_counts: Vec<usize>,
    /// Modes reached by at least one successful episode.
    pub modes_reached: usize,
    /// Mean length of successful episodes (0 without successes).
    pub mean_success_steps: f64,
    /// Environment steps over all episodes.
    pub total_steps: usize,
}

impl TaskMetrics<AvoidingEnv> for Metrics {
    fn from_rollouts(rollouts: &[Rollout]) -> Result<Self> {
        Metrics::from_rollouts(rollouts)
    }
}

impl Metrics {
    /// Summarises `rollouts` (an empty slice is an error).
    pub fn from_rollouts(rollouts: &[Rollout]) -> Result<Self> {
        if rollouts.is_empty() {
            return Err(TaskError::InvalidArgument("metrics of zero rollouts".into()));
        }
        let mut mode_counts = vec![0usize; N_MODES];
        let (mut successes, mut collisions, mut timeouts) = (0, 0, 0);
        let (mut success_steps, mut total_steps) = (0usize, 0usize);
        for r in rollouts {
            total_steps += r.steps;
            match r.status {
                Status::Success => {
                    successes += 1;
                    success_steps += r.steps;
                    let m = r.mode().ok_or_else(|| {
                        TaskError::InvalidArgument("a successful rollout without a mode".into())
                    })?;
                    mode_counts[m.index()] += 1;
                }
                Status::Collision => collisions += 1,
                Status::Timeout => timeouts += 1,
                Status::Running => {
                    return Err(TaskError::InvalidArgument("a rollout still running".into()));
                }
            }
        }
        Ok(Self {
            rollouts: rollouts.len(),
            successes,
            collisions,
            timeouts,
            success_rate: successes as f64 / rollouts.len() as f64,
            task_entropy: f64::from(normalized_entropy(&mode_counts)),
            modes_reached: mode_counts.iter().filter(|&&c| c > 0).count(),
            mode_counts,
            mean_success_steps: if successes > 0 {
                success_steps as f64 / successes as f64
            } else {
                0.0
            },
            total_steps,
        })
    }

    /// The figures a results row (`metrics.json`, one method and seed) reports: success rate,
    /// task entropy, rollouts, modes reached and their histogram (`mode_counts`), collisions,
    /// timeouts and the mean length of successful episodes.
    ///
    /// ```
    /// # use vdd_tasks::avoiding::rollout::Metrics;
    /// let m = Metrics { rollouts: 2, successes: 0, collisions: 1, timeouts: 1, success_rate: 0.0,
    ///     task_entropy: 0.0, mode_counts: vec![0; 24], modes_reached: 0,
    ///     mean_success_steps: 0.0, total_steps: 9 };
    /// assert_eq!(m.row_fields()["collisions"], 1);
    /// ```
    pub fn row_fields(&self) -> serde_json::Map<String, serde_json::Value> {
        use serde_json::json;
        let fields = [
            ("success_rate", json!(self.success_rate)),
            ("task_entropy", json!(self.task_entropy)),
            ("rollouts", json!(self.rollouts)),
            ("modes_reached", json!(self.modes_reached)),
            ("collisions", json!(self.collisions)),
            ("timeouts", json!(self.timeouts)),
            ("mean_success_steps", json!(self.mean_success_steps)),
            ("mode_counts", json!(self.mode_counts)),
        ];
        fields.into_iter().map(|(k, v)| (k.to_owned(), v)).collect()
    }
}

/// Runs one episode: seeds the policy with `seed`, resets it, and acts through
/// [`Policy::act_into`] until the episode ends.
pub fn rollout<P: Policy + ?Sized>(policy: &mut P, seed: u64, record: bool) -> Result<Rollout> {
    episodes::rollout::<AvoidingEnv, P>(&(), policy, seed, 0, record)
}

/// Runs `cfg.n_rollouts` episodes on the calling thread and summarises them.
pub fn evaluate<P: Policy + ?Sized>(policy: &mut P, cfg: &EvalConfig) -> Result<Evaluation> {
    episodes::evaluate(&(), policy, cfg)
}

/// Like [`evaluate`], with the episodes spread over one thread per policy in `policies`
/// (dynamic scheduling). The result equals [`evaluate`]'s with any one of the policies, as long
/// as they are identical and honour the seeding contract (see [`crate::episodes`]). On failure,
/// the error of the lowest failing unit is returned.
pub fn evaluate_parallel<P: Policy + Send>(
    policies: &mut [P],
    cfg: &EvalConfig,
) -> Result<Evaluation> {
    episodes::evaluate_parallel(&(), policies, cfg)
}

/// [`evaluate_parallel`] with `threads` clones of `policy`.
pub fn evaluate_cloned<P: Policy + Clone + Send>(
    policy: &P,
    threads: usize,
    cfg: &EvalConfig,
) -> Result<Evaluation> {
    episodes::evaluate_cloned(&(), policy, threads, cfg)
}

#[cfg(test)]
mod tests;
