//! Rollouts of any [`Policy`] on Aligning, and their aggregate metrics: success, D3IL's mean
//! distance, task entropy per test context (log base 2, as D3IL), the entropy of the
//! pooled modes, and the mode histogram.
//!
//! # Seeding, stepping and contexts
//!
//! The shared engine's ([`crate::episodes`]; [`AligningEnv`] is its [`Env`]), with one
//! difference: [`EnvConfig::episodes_per_context`] consecutive episodes share a start (D3IL's
//! test contexts, each rolled out several times), so episode `i` of an evaluation with root
//! seed `s` starts from [`start_seed`]`(s, i / episodes_per_context)`. The policy is seeded per
//! episode or per lockstep chunk as everywhere; the results do not depend on the number of
//! threads.
//!
//! ```
//! use vdd_tasks::aligning::oracle::{AligningOracle, OracleConfig};
//! use vdd_tasks::aligning::rollout::{evaluate_cloned, EvalConfig, Stepping};
//! let oracle = AligningOracle::new(OracleConfig::default()).unwrap();
//! let cfg = EvalConfig { n_rollouts: 8, seed: 0, stepping: Stepping::PerEpisode, record: false };
//! let eval = evaluate_cloned(&oracle, 2, &cfg, 4).unwrap();
//! assert!(eval.metrics.success_rate > 0.6);
//! assert_eq!(eval.metrics.contexts, 2);
//! ```

use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Policy};

use crate::episodes::{self, Env, SeedStreams, TaskMetrics};
pub use crate::episodes::{EvalConfig, Stepping, Trajectory};

use super::{ACTION_DIM, AligningEnv, AligningMode, EnvConfig, N_MODES, OBS_DIM, Status};
use crate::{Result, TaskError, normalized_entropy};

/// What Aligning records of an episode beyond its status.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Outcome {
    /// The mode at the last step ([`AligningEnv::mode`]).
    pub mode: AligningMode,
    /// D3IL's mean distance at the last step ([`AligningEnv::mean_distance`]).
    pub mean_distance: f32,
    /// The start seed: the episode's test context.
    pub context: u64,
}

impl Env for AligningEnv {
    type Status = Status;
    type Info = Outcome;
    const OBS_DIM: usize = OBS_DIM;
    const ACTION_DIM: usize = ACTION_DIM;
    const STREAMS: SeedStreams = SeedStreams {
        episode: "aligning-episode",
        chunk: "aligning-chunk",
        start: "aligning-context",
    };

    type Config = EnvConfig;

    fn build(config: &EnvConfig) -> Result<Self> {
        AligningEnv::new(config.clone())
    }

    fn reset(&mut self, seed: u64) {
        AligningEnv::reset(self, seed);
    }

    fn observe(&self, out: &mut [f32]) -> std::result::Result<(), CoreError> {
        vdd_core::check_len("observation buffer", out.len(), OBS_DIM)?;
        out.copy_from_slice(&self.observation());
        Ok(())
    }

    fn apply(&mut self, action: &[f32], applied: &mut [f32]) -> std::result::Result<(), CoreError> {
        episodes::check_apply(self, action, applied)?;
        let a = AligningEnv::clip_action([action[0], action[1], action[2]]);
        applied.copy_from_slice(&a);
        self.step_clipped(a);
        Ok(())
    }

    fn status(&self) -> Status {
        AligningEnv::status(self)
    }

    fn is_done(&self) -> bool {
        AligningEnv::status(self).is_done()
    }

    fn steps(&self) -> usize {
        AligningEnv::steps(self)
    }

    fn info(&self) -> Outcome {
        Outcome { mode: self.mode(), mean_distance: self.mean_distance(), context: self.context() }
    }

    fn start_of(config: &EnvConfig, seed: u64, episode: usize) -> u64 {
        start_seed(seed, episode / config.episodes_per_context.max(1))
    }
}

/// The outcome of one Aligning episode: its [`Status`] (never [`Status::Running`]), its mode,
/// mean distance and context in `info`, its steps and, when asked for, its trajectory.
pub type Rollout = episodes::Rollout<AligningEnv>;

/// Every rollout of a Aligning evaluation, in episode order, and their [`Metrics`].
pub type Evaluation = episodes::Evaluation<AligningEnv, Metrics>;

impl episodes::Rollout<AligningEnv> {
    /// Whether the episode succeeded.
    pub fn success(&self) -> bool {
        self.status == Status::Success
    }
}

/// The policy seed of episode `episode` under per-episode stepping.
pub fn episode_seed(seed: u64, episode: usize) -> u64 {
    episodes::episode_seed::<AligningEnv>(seed, episode)
}

/// The policy seed of chunk `chunk` under lockstep stepping.
pub fn chunk_seed(seed: u64, chunk: usize) -> u64 {
    episodes::chunk_seed::<AligningEnv>(seed, chunk)
}

/// The start seed of test context `context` of an evaluation with root seed `seed`.
pub fn start_seed(seed: u64, context: usize) -> u64 {
    episodes::start_seed::<AligningEnv>(seed, context)
}

/// Aggregate metrics of a set of rollouts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Metrics {
    /// Episodes run.
    pub rollouts: usize,
    /// Distinct test contexts (start states) among them.
    pub contexts: usize,
    /// Successful episodes (the tray matches the target pose).
    pub successes: usize,
    /// Episodes that hit the step limit.
    pub timeouts: usize,
    /// Episodes ended by a fault ([`Status::OffTable`], [`Status::PhysicsFault`]).
    pub faults: usize,
    /// `successes / rollouts`.
    pub success_rate: f64,
    /// D3IL's mean distance at the last step, averaged over the episodes.
    pub mean_distance: f64,
    /// D3IL's task entropy: per context, `−Σ_m p(m|c) log p(m|c) / log 2` over the modes of its
    /// successful episodes (0 for a context without success), averaged over the contexts.
    pub task_entropy: f64,
    /// The entropy (log base 2) of the modes of all successful episodes pooled.
    pub mode_entropy: f64,
    /// Successful episodes per mode ([`AligningMode::index`]), 2 entries.
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

impl TaskMetrics<AligningEnv> for Metrics {
    fn from_rollouts(rollouts: &[Rollout]) -> Result<Self> {
        Metrics::from_rollouts(rollouts)
    }
}

impl Metrics {
    /// Summarises `rollouts` (an empty slice is an error). Contexts are told apart by
    /// [`Outcome::context`].
    pub fn from_rollouts(rollouts: &[Rollout]) -> Result<Self> {
        if rollouts.is_empty() {
            return Err(TaskError::InvalidArgument("metrics of zero rollouts".into()));
        }
        let mut mode_counts = vec![0usize; N_MODES];
        // Per context, in order of first appearance: its successes per mode.
        let mut contexts: Vec<(u64, [usize; N_MODES])> = Vec::new();
        let mut index = std::collections::HashMap::new();
        let (mut successes, mut timeouts, mut faults) = (0, 0, 0);
        let (mut success_steps, mut max_success_steps, mut total_steps) = (0usize, 0usize, 0usize);
        let mut distance = 0.0f64;
        for r in rollouts {
            total_steps += r.steps;
            distance += f64::from(r.info.mean_distance);
            let c = *index.entry(r.info.context).or_insert_with(|| {
                contexts.push((r.info.context, [0; N_MODES]));
                contexts.len() - 1
            });
            match r.status {
                Status::Success => {
                    successes += 1;
                    success_steps += r.steps;
                    max_success_steps = max_success_steps.max(r.steps);
                    let m = r.info.mode;
                    mode_counts[m.index()] += 1;
                    contexts[c].1[m.index()] += 1;
                }
                Status::Timeout => timeouts += 1,
                Status::OffTable | Status::PhysicsFault => faults += 1,
                Status::Running => {
                    return Err(TaskError::InvalidArgument("a rollout still running".into()));
                }
            }
        }
        let n = rollouts.len() as f64;
        let task_entropy =
            contexts.iter().map(|(_, counts)| f64::from(normalized_entropy(counts))).sum::<f64>()
                / contexts.len() as f64;
        Ok(Self {
            rollouts: rollouts.len(),
            contexts: contexts.len(),
            successes,
            timeouts,
            faults,
            success_rate: successes as f64 / n,
            mean_distance: distance / n,
            task_entropy,
            mode_entropy: f64::from(normalized_entropy(&mode_counts)),
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

    /// The figures a results row reports: success rate, mean distance, task entropy
    /// (per context) and the pooled mode entropy, rollouts, contexts, modes reached and their
    /// histogram (`mode_counts`), timeouts, faults and the mean length of successful episodes.
    ///
    /// ```
    /// # use vdd_tasks::aligning::rollout::Metrics;
    /// let m = Metrics { rollouts: 2, contexts: 1, successes: 1, timeouts: 1, faults: 0,
    ///     success_rate: 0.5, mean_distance: 0.02, task_entropy: 0.0, mode_entropy: 0.0,
    ///     mode_counts: vec![0, 1], modes_reached: 1, mean_success_steps: 90.0,
    ///     max_success_steps: 90, total_steps: 490 };
    /// assert_eq!(m.row_fields()["success_rate"], 0.5);
    /// ```
    pub fn row_fields(&self) -> serde_json::Map<String, serde_json::Value> {
        use serde_json::json;
        let fields = [
            ("success_rate", json!(self.success_rate)),
            ("mean_distance", json!(self.mean_distance)),
            ("task_entropy", json!(self.task_entropy)),
            ("mode_entropy", json!(self.mode_entropy)),
            ("rollouts", json!(self.rollouts)),
            ("contexts", json!(self.contexts)),
            ("modes_reached", json!(self.modes_reached)),
            ("timeouts", json!(self.timeouts)),
            ("faults", json!(self.faults)),
            ("mean_success_steps", json!(self.mean_success_steps)),
            ("mode_counts", json!(self.mode_counts)),
        ];
        fields.into_iter().map(|(k, v)| (k.to_owned(), v)).collect()
    }
}

/// Runs one episode from start seed `start` with the default environment: seeds the policy
/// with `policy_seed`, resets it, and acts through [`Policy::act_into`] until the episode ends.
pub fn rollout<P: Policy + ?Sized>(
    policy: &mut P,
    start: u64,
    policy_seed: u64,
    record: bool,
) -> Result<Rollout> {
    episodes::rollout::<AligningEnv, P>(&EnvConfig::default(), policy, policy_seed, start, record)
}

/// Runs `cfg.n_rollouts` episodes on the calling thread in an environment with `env` settings
/// and summarises them.
pub fn evaluate_with<P: Policy + ?Sized>(
    policy: &mut P,
    cfg: &EvalConfig,
    env: &EnvConfig,
) -> Result<Evaluation> {
    env.validate()?;
    episodes::evaluate(env, policy, cfg)
}

/// Like [`evaluate_with`], with the episodes spread over one thread per policy in `policies`
/// (dynamic scheduling); the result equals [`evaluate_with`]'s. On failure, the error of the
/// lowest failing unit is returned.
pub fn evaluate_parallel_with<P: Policy + Send>(
    policies: &mut [P],
    cfg: &EvalConfig,
    env: &EnvConfig,
) -> Result<Evaluation> {
    env.validate()?;
    episodes::evaluate_parallel(env, policies, cfg)
}

/// [`evaluate_parallel_with`] with `threads` clones of `policy` in the default environment,
/// `episodes_per_context` episodes per test context.
pub fn evaluate_cloned<P: Policy + Clone + Send>(
    policy: &P,
    threads: usize,
    cfg: &EvalConfig,
    episodes_per_context: usize,
) -> Result<Evaluation> {
    let env = EnvConfig { episodes_per_context, ..EnvConfig::default() };
    env.validate()?;
    episodes::evaluate_cloned(&env, policy, threads, cfg)
}
