//! Rollouts of any [`Policy`] on Block-Push, and their aggregate metrics: success (p2), p1,
//! task entropy over the four modes and the mode histogram.
//!
//! # Seeding and stepping
//!
//! The shared engine's ([`crate::episodes`]; [`BlockPushEnv`] is its [`Env`]): episode `i` of
//! an evaluation with root seed `s` always starts from [`env_seed`](super::env_seed)`(s, i)`,
//! under either stepping; the policy is seeded with [`episode_seed`]`(s, i)` per episode or
//! [`chunk_seed`]`(s, c)` per lockstep chunk. [`evaluate_parallel`] and [`evaluate_cloned`]
//! return exactly what [`evaluate`] returns, whatever the number of threads: each environment
//! owns its own deterministic physics world.
//!
//! ```
//! use vdd_tasks::block_push::oracle::{BlockPushOracle, OracleConfig};
//! use vdd_tasks::block_push::rollout::{evaluate_cloned, EvalConfig, Stepping};
//! let oracle = BlockPushOracle::new(OracleConfig::default()).unwrap();
//! let cfg = EvalConfig { n_rollouts: 32, seed: 0, stepping: Stepping::PerEpisode, record: false };
//! let eval = evaluate_cloned(&oracle, 2, &cfg).unwrap();
//! assert!(eval.metrics.success_rate > 0.9);
//! ```

use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Policy};

use crate::episodes::{self, Env, SeedStreams, TaskMetrics};
pub use crate::episodes::{EvalConfig, Stepping, Trajectory};

use super::{ACTION_DIM, BlockPushEnv, BlockPushMode, EnvConfig, N_MODES, OBS_DIM, Status};
use crate::{Result, TaskError, normalized_entropy};

/// What Block-Push records of an episode beyond its status.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Outcome {
    /// The mode: the first `(block, target)` visit, if any.
    pub mode: Option<BlockPushMode>,
    /// Whether at least one block reached a target (p1).
    pub p1: bool,
}

impl Env for BlockPushEnv {
    type Status = Status;
    type Info = Outcome;
    const OBS_DIM: usize = OBS_DIM;
    const ACTION_DIM: usize = ACTION_DIM;
    const STREAMS: SeedStreams = SeedStreams {
        episode: "block-push-episode",
        chunk: "block-push-chunk",
        start: super::ENV_STREAM,
    };

    type Config = EnvConfig;

    fn build(config: &EnvConfig) -> Result<Self> {
        BlockPushEnv::new(config.clone())
    }

    fn reset(&mut self, seed: u64) {
        BlockPushEnv::reset(self, seed);
    }

    fn observe(&self, out: &mut [f32]) -> std::result::Result<(), CoreError> {
        vdd_core::check_len("observation buffer", out.len(), OBS_DIM)?;
        out.copy_from_slice(&self.observation());
        Ok(())
    }

    fn apply(&mut self, action: &[f32], applied: &mut [f32]) -> std::result::Result<(), CoreError> {
        episodes::check_apply(self, action, applied)?;
        let a = BlockPushEnv::clip_action([action[0], action[1]]);
        applied.copy_from_slice(&a);
        self.step_clipped(a);
        Ok(())
    }

    fn status(&self) -> Status {
        BlockPushEnv::status(self)
    }

    fn is_done(&self) -> bool {
        BlockPushEnv::status(self).is_done()
    }

    fn steps(&self) -> usize {
        BlockPushEnv::steps(self)
    }

    fn info(&self) -> Outcome {
        Outcome { mode: self.mode(), p1: self.p1() }
    }
}

/// The outcome of one Block-Push episode: its [`Status`] (never [`Status::Running`]), its mode
/// and p1 in `info`, its steps and, when asked for, its trajectory.
pub type Rollout = episodes::Rollout<BlockPushEnv>;

/// Every rollout of a Block-Push evaluation, in episode order, and their [`Metrics`].
pub type Evaluation = episodes::Evaluation<BlockPushEnv, Metrics>;

impl episodes::Rollout<BlockPushEnv> {
    /// Whether the episode succeeded (p2).
    pub fn success(&self) -> bool {
        self.status == Status::Success
    }
}

/// The policy seed of episode `episode` under per-episode stepping.
pub fn episode_seed(seed: u64, episode: usize) -> u64 {
    episodes::episode_seed::<BlockPushEnv>(seed, episode)
}

/// The policy seed of chunk `chunk` under lockstep stepping.
pub fn chunk_seed(seed: u64, chunk: usize) -> u64 {
    episodes::chunk_seed::<BlockPushEnv>(seed, chunk)
}

/// Aggregate metrics of a set of rollouts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Metrics {
    /// Episodes run.
    pub rollouts: usize,
    /// Successful episodes (both blocks in distinct targets).
    pub successes: usize,
    /// Episodes in which at least one block reached a target.
    pub p1_count: usize,
    /// Episodes that hit the step limit.
    pub timeouts: usize,
    /// p2: `successes / rollouts`.
    pub success_rate: f64,
    /// p1: `p1_count / rollouts`.
    pub p1_rate: f64,
    /// `−Σ_m p_m log p_m / log 4` over the modes of successful episodes (0 without successes).
    pub task_entropy: f64,
    /// Successful episodes per mode ([`BlockPushMode::index`]), 4 entries.
    pub mode_counts: Vec<usize>,
    /// Modes reached by at least one successful episode.
    pub modes_reached: usize,
    /// Mean length of successful episodes (0 without successes).
    pub mean_success_steps: f64,
    /// Longest successful episode (0 without successes).
    pub max_success_steps: usize,
    /// Environment steps over all episodes.
    pub total_steps: usize,
}

impl TaskMetrics<BlockPushEnv> for Metrics {
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
        let (mut successes, mut p1_count, mut timeouts) = (0, 0, 0);
        let (mut success_steps, mut max_success_steps, mut total_steps) = (0usize, 0usize, 0usize);
        for r in rollouts {
            total_steps += r.steps;
            p1_count += usize::from(r.info.p1);
            match r.status {
                Status::Success => {
                    successes += 1;
                    success_steps += r.steps;
                    max_success_steps = max_success_steps.max(r.steps);
                    let m = r.info.mode.ok_or_else(|| {
                        TaskError::InvalidArgument("a successful rollout without a mode".into())
                    })?;
                    mode_counts[m.index()] += 1;
                }
                Status::Timeout => timeouts += 1,
                Status::Running => {
                    return Err(TaskError::InvalidArgument("a rollout still running".into()));
                }
            }
        }
        let n = rollouts.len() as f64;
        Ok(Self {
            rollouts: rollouts.len(),
            successes,
            p1_count,
            timeouts,
            success_rate: successes as f64 / n,
            p1_rate: p1_count as f64 / n,
            task_entropy: f64::from(normalized_entropy(&mode_counts)),
            modes_reached: mode_counts.iter().filter(|&&c| c > 0).count(),
            mode_counts,
            mean_success_steps: if successes > 0 {
                success_steps as f64 / successes as f64
            } else {
                0.0
            },
            max_success_steps,
            total_steps,
        })
    }
}

impl Metrics {
    /// The figures a results row reports: success rate (p2), p1 rate, task entropy, rollouts,
    /// modes reached and their histogram (`mode_counts`), timeouts and the mean length of
    /// successful episodes.
    ///
    /// ```
    /// # use vdd_tasks::block_push::rollout::Metrics;
    /// let m = Metrics { rollouts: 2, successes: 1, p1_count: 2, timeouts: 1, success_rate: 0.5,
    ///     p1_rate: 1.0, task_entropy: 0.0, mode_counts: vec![0, 1, 0, 0], modes_reached: 1,
    ///     mean_success_steps: 90.0, max_success_steps: 90, total_steps: 440 };
    /// assert_eq!(m.row_fields()["p1_rate"], 1.0);
    /// ```
    pub fn row_fields(&self) -> serde_json::Map<String, serde_json::Value> {
        use serde_json::json;
        let fields = [
            ("success_rate", json!(self.success_rate)),
            ("p1_rate", json!(self.p1_rate)),
            ("task_entropy", json!(self.task_entropy)),
            ("rollouts", json!(self.rollouts)),
            ("modes_reached", json!(self.modes_reached)),
            ("timeouts", json!(self.timeouts)),
            ("mean_success_steps", json!(self.mean_success_steps)),
            ("mode_counts", json!(self.mode_counts)),
        ];
        fields.into_iter().map(|(k, v)| (k.to_owned(), v)).collect()
    }
}

/// Runs one episode from environment seed `env_seed` with the default environment: seeds the
/// policy with `policy_seed`, resets it, and acts through [`Policy::act_into`] until the
/// episode ends.
pub fn rollout<P: Policy + ?Sized>(
    policy: &mut P,
    env_seed: u64,
    policy_seed: u64,
    record: bool,
) -> Result<Rollout> {
    episodes::rollout::<BlockPushEnv, P>(
        &EnvConfig::default(),
        policy,
        policy_seed,
        env_seed,
        record,
    )
}

/// Runs `cfg.n_rollouts` episodes on the calling thread (default environment) and summarises
/// them.
pub fn evaluate<P: Policy + ?Sized>(policy: &mut P, cfg: &EvalConfig) -> Result<Evaluation> {
    evaluate_with(policy, cfg, &EnvConfig::default())
}

/// [`evaluate`] in an environment with `env` settings.
pub fn evaluate_with<P: Policy + ?Sized>(
    policy: &mut P,
    cfg: &EvalConfig,
    env: &EnvConfig,
) -> Result<Evaluation> {
    env.validate()?;
    episodes::evaluate(env, policy, cfg)
}

/// Like [`evaluate`], with the episodes spread over one thread per policy in `policies`
/// (dynamic scheduling); the result equals [`evaluate`]'s. On failure, the error of the lowest
/// failing unit is returned.
pub fn evaluate_parallel<P: Policy + Send>(
    policies: &mut [P],
    cfg: &EvalConfig,
) -> Result<Evaluation> {
    evaluate_parallel_with(policies, cfg, &EnvConfig::default())
}

/// [`evaluate_parallel`] in an environment with `env` settings.
pub fn evaluate_parallel_with<P: Policy + Send>(
    policies: &mut [P],
    cfg: &EvalConfig,
    env: &EnvConfig,
) -> Result<Evaluation> {
    env.validate()?;
    episodes::evaluate_parallel(env, policies, cfg)
}

/// [`evaluate_parallel`] with `threads` clones of `policy`.
pub fn evaluate_cloned<P: Policy + Clone + Send>(
    policy: &P,
    threads: usize,
    cfg: &EvalConfig,
) -> Result<Evaluation> {
    episodes::evaluate_cloned(&EnvConfig::default(), policy, threads, cfg)
}
