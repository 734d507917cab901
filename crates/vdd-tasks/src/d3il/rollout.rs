//! Rollouts of any [`Policy`] on a D3IL contact task, and their aggregate metrics: success, p1
//! (on a task that counts it), D3IL's mean distance, task entropy per test context (log base
//! the number of modes, as D3IL), the entropy of the pooled modes, and the mode histogram.
//!
//! # Seeding, stepping and contexts
//!
//! The shared engine's ([`crate::episodes`]; every [`ContextEnv`] is its [`Env`](crate::episodes::Env)), with one
//! difference: [`EnvConfig::episodes_per_context`] consecutive episodes share a start (D3IL's
//! test contexts, each rolled out several times), so episode `i` of an evaluation with root
//! seed `s` starts from the start seed ([`crate::episodes::start_seed`]) of context
//! `i / episodes_per_context`. The policy is seeded per episode or per lockstep chunk as
//! everywhere; the results do not depend on the number of threads.

use serde::{Deserialize, Serialize};
use vdd_core::Policy;

use crate::episodes::{self, TaskMetrics};
pub use crate::episodes::{EvalConfig, Stepping, Trajectory};

use super::{ContextEnv, ContextOutcome, EnvConfig, Status};
use crate::scripted::Mode as _;
use crate::{Result, TaskError, normalized_entropy};

/// Every rollout of an evaluation of the task of `E`, in episode order, and their [`Metrics`].
pub type Evaluation<E> = episodes::Evaluation<E, Metrics>;

impl<E: ContextEnv> episodes::Rollout<E> {
    /// Whether the episode succeeded.
    pub fn success(&self) -> bool {
        self.status == Status::Success
    }
}

/// Aggregate metrics of a set of rollouts of a D3IL contact task.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Metrics {
    /// Episodes run.
    pub rollouts: usize,
    /// Distinct test contexts (start states) among them.
    pub contexts: usize,
    /// Successful episodes.
    pub successes: usize,
    /// Episodes in which at least one object reached a target, on a task that counts p1
    /// (Pushing; `None` on Aligning).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub p1_count: Option<usize>,
    /// Episodes that hit the step limit.
    pub timeouts: usize,
    /// Episodes ended by a fault ([`Status::OffTable`], [`Status::PhysicsFault`]).
    pub faults: usize,
    /// `successes / rollouts`.
    pub success_rate: f64,
    /// p1: `p1_count / rollouts`, on a task that counts it.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub p1_rate: Option<f64>,
    /// D3IL's mean distance at the last step, averaged over the episodes.
    pub mean_distance: f64,
    /// D3IL's task entropy: per context, `−Σ_m p(m|c) log p(m|c) / log M` (`M` modes) over the
    /// modes of its successful episodes (0 for a context without success), averaged over the
    /// contexts.
    pub task_entropy: f64,
    /// The entropy (log base `M`) of the modes of all successful episodes pooled.
    pub mode_entropy: f64,
    /// Successful episodes per mode (the task's mode index), `M` entries.
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

impl<E: ContextEnv> TaskMetrics<E> for Metrics {
    fn from_rollouts(rollouts: &[episodes::Rollout<E>]) -> Result<Self> {
        Metrics::from_rollouts(rollouts)
    }
}

impl Metrics {
    /// Summarises `rollouts` (an empty slice is an error). Contexts are told apart by
    /// [`ContextOutcome::test_context`]; p1 is counted when every outcome has it.
    pub fn from_rollouts<E: ContextEnv>(rollouts: &[episodes::Rollout<E>]) -> Result<Self> {
        if rollouts.is_empty() {
            return Err(TaskError::InvalidArgument("metrics of zero rollouts".into()));
        }
        let mut mode_counts = vec![0usize; E::N_MODES];
        // Per context, in order of first appearance: its successes per mode.
        let mut contexts: Vec<(u64, Vec<usize>)> = Vec::new();
        let mut index = std::collections::HashMap::new();
        let (mut successes, mut timeouts, mut faults) = (0, 0, 0);
        let mut p1_count = Some(0usize);
        let (mut success_steps, mut max_success_steps, mut total_steps) = (0usize, 0usize, 0usize);
        let mut distance = 0.0f64;
        for r in rollouts {
            total_steps += r.steps;
            p1_count = p1_count.zip(r.info.reached_p1()).map(|(n, p1)| n + usize::from(p1));
            distance += f64::from(r.info.final_distance());
            let context = r.info.test_context();
            let c = *index.entry(context).or_insert_with(|| {
                contexts.push((context, vec![0; E::N_MODES]));
                contexts.len() - 1
            });
            match r.status {
                Status::Success => {
                    successes += 1;
                    success_steps += r.steps;
                    max_success_steps = max_success_steps.max(r.steps);
                    let m = r.info.reached_mode().ok_or_else(|| {
                        TaskError::InvalidArgument("a successful rollout without a mode".into())
                    })?;
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
            p1_count,
            timeouts,
            faults,
            success_rate: successes as f64 / n,
            p1_rate: p1_count.map(|p1| p1 as f64 / n),
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

    /// The figures a results row reports: success rate, p1 rate (on a task that counts it),
    /// mean distance, task entropy (per context) and the pooled mode entropy, rollouts,
    /// contexts, modes reached and their histogram (`mode_counts`), timeouts, faults and the
    /// mean length of successful episodes.
    ///
    /// ```
    /// # use vdd_tasks::pushing::rollout::Metrics;
    /// let m = Metrics { rollouts: 2, contexts: 1, successes: 1, p1_count: Some(2), timeouts: 1,
    ///     faults: 0, success_rate: 0.5, p1_rate: Some(1.0), mean_distance: 0.02,
    ///     task_entropy: 0.0, mode_entropy: 0.0, mode_counts: vec![0, 1, 0, 0], modes_reached: 1,
    ///     mean_success_steps: 90.0, max_success_steps: 90, total_steps: 490 };
    /// assert_eq!(m.row_fields()["p1_rate"], 1.0);
    /// let aligning = Metrics { p1_count: None, p1_rate: None, mode_counts: vec![0, 1], ..m };
    /// assert!(!aligning.row_fields().contains_key("p1_rate"));
    /// ```
    pub fn row_fields(&self) -> serde_json::Map<String, serde_json::Value> {
        use serde_json::json;
        let p1 = self.p1_rate.map(|p1| ("p1_rate", json!(p1)));
        let fields = [("success_rate", json!(self.success_rate))].into_iter().chain(p1).chain([
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
        ]);
        fields.map(|(k, v)| (k.to_owned(), v)).collect()
    }
}

/// Runs one episode from start seed `start` with the default environment of `E`: seeds the
/// policy with `policy_seed`, resets it, and acts through [`Policy::act_into`] until the
/// episode ends.
pub fn rollout<E: ContextEnv, P: Policy + ?Sized>(
    policy: &mut P,
    start: u64,
    policy_seed: u64,
    record: bool,
) -> Result<episodes::Rollout<E>> {
    episodes::rollout::<E, P>(&EnvConfig::default(), policy, policy_seed, start, record)
}

/// Runs `cfg.n_rollouts` episodes on the calling thread in an environment with `env` settings
/// and summarises them.
pub fn evaluate_with<E: ContextEnv, P: Policy + ?Sized>(
    policy: &mut P,
    cfg: &EvalConfig,
    env: &EnvConfig<E>,
) -> Result<Evaluation<E>> {
    env.validate()?;
    episodes::evaluate(env, policy, cfg)
}

/// Like [`evaluate_with`], with the episodes spread over one thread per policy in `policies`
/// (dynamic scheduling); the result equals [`evaluate_with`]'s. On failure, the error of the
/// lowest failing unit is returned.
pub fn evaluate_parallel_with<E: ContextEnv, P: Policy + Send>(
    policies: &mut [P],
    cfg: &EvalConfig,
    env: &EnvConfig<E>,
) -> Result<Evaluation<E>> {
    env.validate()?;
    episodes::evaluate_parallel(env, policies, cfg)
}

/// [`evaluate_parallel_with`] with `threads` clones of `policy` in the default environment of
/// `E`, `episodes_per_context` episodes per test context.
pub fn evaluate_cloned<E: ContextEnv, P: Policy + Clone + Send>(
    policy: &P,
    threads: usize,
    cfg: &EvalConfig,
    episodes_per_context: usize,
) -> Result<Evaluation<E>> {
    let env = EnvConfig::with_episodes_per_context(episodes_per_context);
    env.validate()?;
    episodes::evaluate_cloned(&env, policy, threads, cfg)
}
