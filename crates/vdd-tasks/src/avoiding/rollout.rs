//! Rollouts of any [`Policy`] on the Avoiding task, and their aggregate metrics.
//!
//! # Seeding and stepping
//!
//! Everything is deterministic for [`EvalConfig::seed`], and identical whatever the number of
//! threads, provided the policy honours the [`Policy`] contract (after `seed(s)` and `reset()`,
//! its behaviour depends only on `s` and its inputs). Work is split into *units*:
//!
//! * [`Stepping::PerEpisode`]: one unit per episode. Before episode `i` the policy is seeded
//!   with [`episode_seed`]`(seed, i)` and reset, then acts with [`Policy::act_into`] one
//!   observation at a time. Works for every policy, including stateful ones.
//! * [`Stepping::Lockstep`]: one unit per chunk of `batch_size` consecutive episodes. Before
//!   chunk `c` the policy is seeded with [`chunk_seed`]`(seed, c)` and reset once; then all the
//!   chunk's environments advance together with **one [`Policy::act_batch`] call per step**
//!   (one batched network evaluation for neural policies). Row `i` of every batch belongs to
//!   the chunk's `i`-th environment throughout the chunk, and the batch keeps its size: rows of
//!   environments that have already ended carry their final observation, and the policy's
//!   actions for them are ignored. A stateful policy (observation history, action chunks) may
//!   therefore keep per-row state between `reset()`s.
//!
//! Both steppings are valid evaluations, but they seed the policy differently, so a stochastic
//! policy gives different (equally distributed) rollouts under the two.
//!
//! [`evaluate`] runs the units on the calling thread; [`evaluate_parallel`] spreads them over
//! one policy per thread (`std::thread::scope`, dynamic scheduling) and returns exactly what
//! [`evaluate`] would; [`evaluate_cloned`] clones one policy per thread.
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

use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use faer::Mat;
use rand::Rng as _;
use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Policy, Seeds};

use super::{ACTION_DIM, AvoidingEnv, AvoidingMode, N_LEVELS, N_MODES, OBS_DIM, Status, mode_of};
use crate::{Result, TaskError, normalized_entropy};

/// How the policy is driven.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Stepping {
    /// One episode at a time through [`Policy::act_into`].
    PerEpisode,
    /// `batch_size` environments in lockstep through one [`Policy::act_batch`] per step.
    Lockstep {
        /// Environments per batch (at least 1).
        batch_size: usize,
    },
}

/// What to evaluate.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EvalConfig {
    /// Number of episodes (at least 1).
    pub n_rollouts: usize,
    /// Root seed of the policy seeds ([`episode_seed`], [`chunk_seed`]).
    pub seed: u64,
    /// How the policy is driven.
    pub stepping: Stepping,
    /// Whether to keep every episode's observations and actions ([`Rollout::trajectory`]).
    pub record: bool,
}

impl Default for EvalConfig {
    /// 500 episodes, seed 0, per-episode stepping, no trajectories.
    fn default() -> Self {
        Self { n_rollouts: 500, seed: 0, stepping: Stepping::PerEpisode, record: false }
    }
}

impl EvalConfig {
    pub(crate) fn validate(&self) -> Result<()> {
        if self.n_rollouts == 0 {
            return Err(TaskError::InvalidArgument("n_rollouts must be at least 1".into()));
        }
        if let Stepping::Lockstep { batch_size: 0 } = self.stepping {
            return Err(TaskError::InvalidArgument(
                "lockstep batch_size must be at least 1".into(),
            ));
        }
        Ok(())
    }

    pub(crate) fn unit_size(&self) -> usize {
        match self.stepping {
            Stepping::PerEpisode => 1,
            Stepping::Lockstep { batch_size } => batch_size,
        }
    }

    pub(crate) fn n_units(&self) -> usize {
        self.n_rollouts.div_ceil(self.unit_size())
    }
}

/// The policy seed of episode `episode` under per-episode stepping.
pub fn episode_seed(seed: u64, episode: usize) -> u64 {
    Seeds::new(seed).stream_indexed("avoiding-episode", episode as u64).random()
}

/// The policy seed of chunk `chunk` under lockstep stepping.
pub fn chunk_seed(seed: u64, chunk: usize) -> u64 {
    Seeds::new(seed).stream_indexed("avoiding-chunk", chunk as u64).random()
}

/// The observations and actions of one episode.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    /// `T x 4`: the observation before each step.
    pub observations: Mat<f32>,
    /// `T x 2`: the action applied at each step (after clipping to `±ACTION_LIMIT`).
    pub actions: Mat<f32>,
    /// The observation after the last step.
    pub final_observation: [f32; OBS_DIM],
}

/// The outcome of one episode.
#[derive(Debug, Clone, PartialEq)]
pub struct Rollout {
    /// How the episode ended (never [`Status::Running`]).
    pub status: Status,
    /// The gap recorded at each level (`None` for levels never crossed).
    pub gaps: [Option<u8>; N_LEVELS],
    /// Steps taken.
    pub steps: usize,
    /// Observations and actions, when recording was asked for.
    pub trajectory: Option<Trajectory>,
}

impl Rollout {
    /// Whether the episode succeeded.
    pub fn success(&self) -> bool {
        self.status == Status::Success
    }

    /// The behaviour mode, when all three levels were crossed (always, for a success).
    pub fn mode(&self) -> Option<AvoidingMode> {
        mode_of(self.gaps)
    }
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

/// Every rollout of an evaluation, in episode order, and their metrics.
#[derive(Debug, Clone, PartialEq)]
pub struct Evaluation {
    /// Aggregate metrics.
    pub metrics: Metrics,
    /// One entry per episode.
    pub rollouts: Vec<Rollout>,
}

/// Runs one episode: seeds the policy with `seed`, resets it, and acts through
/// [`Policy::act_into`] until the episode ends.
pub fn rollout<P: Policy + ?Sized>(policy: &mut P, seed: u64, record: bool) -> Result<Rollout> {
    check_dims(policy)?;
    Worker::default().episode(policy, 0, seed, record)
}

/// Runs `cfg.n_rollouts` episodes on the calling thread and summarises them.
pub fn evaluate<P: Policy + ?Sized>(policy: &mut P, cfg: &EvalConfig) -> Result<Evaluation> {
    cfg.validate()?;
    check_dims(policy)?;
    let mut worker = Worker::default();
    let mut rollouts = Vec::with_capacity(cfg.n_rollouts);
    for unit in 0..cfg.n_units() {
        rollouts.extend(worker.unit(policy, cfg, unit)?);
    }
    finish(rollouts)
}

/// Like [`evaluate`], with the episodes spread over one thread per policy in `policies`
/// (dynamic scheduling). The result equals [`evaluate`]'s with any one of the policies, as long
/// as they are identical and honour the seeding contract (see the module docs). On failure, the
/// error of the lowest failing unit is returned.
pub fn evaluate_parallel<P: Policy + Send>(
    policies: &mut [P],
    cfg: &EvalConfig,
) -> Result<Evaluation> {
    cfg.validate()?;
    if policies.is_empty() {
        return Err(TaskError::InvalidArgument(
            "evaluate_parallel needs at least one policy".into(),
        ));
    }
    for p in policies.iter() {
        check_dims(p)?;
    }
    let n_units = cfg.n_units();
    let next = AtomicUsize::new(0);
    let failed = AtomicBool::new(false);
    let done: Mutex<Vec<(usize, Result<Vec<Rollout>>)>> = Mutex::new(Vec::with_capacity(n_units));
    let workers = policies.len().min(n_units);
    let panicked = std::thread::scope(|scope| {
        let handles: Vec<_> = policies[..workers]
            .iter_mut()
            .map(|policy| {
                let (next, failed, done) = (&next, &failed, &done);
                scope.spawn(move || {
                    let mut worker = Worker::default();
                    // Stop taking units after a failure, but finish every unit taken: all
                    // units below a failing one were taken before it, so they all run.
                    while !failed.load(Ordering::Relaxed) {
                        let unit = next.fetch_add(1, Ordering::Relaxed);
                        if unit >= n_units {
                            break;
                        }
                        let result = worker.unit(policy, cfg, unit);
                        if result.is_err() {
                            failed.store(true, Ordering::Relaxed);
                        }
                        let stop = result.is_err();
                        done.lock().unwrap_or_else(|e| e.into_inner()).push((unit, result));
                        if stop {
                            break;
                        }
                    }
                })
            })
            .collect();
        // Join every handle (no short-circuit): an unjoined panicked thread makes `scope` panic.
        let joined: Vec<bool> = handles.into_iter().map(|h| h.join().is_err()).collect();
        joined.contains(&true)
    });
    if panicked {
        return Err(TaskError::WorkerPanicked);
    }
    let mut done = done.into_inner().unwrap_or_else(|e| e.into_inner());
    done.sort_by_key(|(unit, _)| *unit);
    // Units are handed out in increasing order and every unit taken is finished, so the first
    // error in unit order is the same for any number of threads and any timing.
    let mut rollouts = Vec::with_capacity(cfg.n_rollouts);
    for (_, result) in done {
        rollouts.extend(result?);
    }
    finish(rollouts)
}

/// [`evaluate_parallel`] with `threads` clones of `policy`.
pub fn evaluate_cloned<P: Policy + Clone + Send>(
    policy: &P,
    threads: usize,
    cfg: &EvalConfig,
) -> Result<Evaluation> {
    if threads == 0 {
        return Err(TaskError::InvalidArgument("threads must be at least 1".into()));
    }
    let mut policies: Vec<P> =
        (0..threads.min(cfg.n_units().max(1))).map(|_| policy.clone()).collect();
    evaluate_parallel(&mut policies, cfg)
}

fn finish(rollouts: Vec<Rollout>) -> Result<Evaluation> {
    Ok(Evaluation { metrics: Metrics::from_rollouts(&rollouts)?, rollouts })
}

fn check_dims<P: Policy + ?Sized>(policy: &P) -> Result<()> {
    if policy.obs_dim() != OBS_DIM || policy.action_dim() != ACTION_DIM {
        return Err(TaskError::PolicyDims {
            obs: OBS_DIM,
            action: ACTION_DIM,
            got_obs: policy.obs_dim(),
            got_action: policy.action_dim(),
        });
    }
    Ok(())
}

/// Appends observations and applied actions of one episode.
#[derive(Default)]
struct Recorder {
    observations: Vec<f32>,
    actions: Vec<f32>,
}

impl Recorder {
    fn push(&mut self, obs: &[f32; OBS_DIM], action: &[f32; ACTION_DIM]) {
        self.observations.extend_from_slice(obs);
        self.actions.extend_from_slice(action);
    }

    fn take(&mut self, final_observation: [f32; OBS_DIM]) -> Trajectory {
        let t = self.actions.len() / ACTION_DIM;
        let (o, a) = (&self.observations, &self.actions);
        let tr = Trajectory {
            observations: Mat::from_fn(t, OBS_DIM, |i, j| o[i * OBS_DIM + j]),
            actions: Mat::from_fn(t, ACTION_DIM, |i, j| a[i * ACTION_DIM + j]),
            final_observation,
        };
        self.observations.clear();
        self.actions.clear();
        tr
    }
}

/// Buffers reused across the units one thread runs.
pub(crate) struct Worker {
    envs: Vec<AvoidingEnv>,
    recorders: Vec<Recorder>,
    obs: Mat<f32>,
    actions: Mat<f32>,
}

impl Default for Worker {
    fn default() -> Self {
        Self {
            envs: Vec::new(),
            recorders: Vec::new(),
            obs: Mat::zeros(0, OBS_DIM),
            actions: Mat::zeros(0, ACTION_DIM),
        }
    }
}

fn policy_error(episode: usize, step: usize) -> impl FnOnce(CoreError) -> TaskError {
    move |source| TaskError::Policy { episode, step, source }
}

impl Worker {
    fn unit<P: Policy + ?Sized>(
        &mut self,
        policy: &mut P,
        cfg: &EvalConfig,
        unit: usize,
    ) -> Result<Vec<Rollout>> {
        match cfg.stepping {
            Stepping::PerEpisode => {
                let r = self.episode(policy, unit, episode_seed(cfg.seed, unit), cfg.record)?;
                Ok(vec![r])
            }
            Stepping::Lockstep { batch_size } => {
                let first = unit * batch_size;
                let n = batch_size.min(cfg.n_rollouts - first);
                self.lockstep(policy, first, n, chunk_seed(cfg.seed, unit), cfg.record)
            }
        }
    }

    pub(crate) fn episode<P: Policy + ?Sized>(
        &mut self,
        policy: &mut P,
        episode: usize,
        seed: u64,
        record: bool,
    ) -> Result<Rollout> {
        policy.seed(seed);
        policy.reset();
        if self.recorders.is_empty() {
            self.recorders.push(Recorder::default());
        }
        let rec = &mut self.recorders[0];
        let mut env = AvoidingEnv::new();
        let mut action = [0.0f32; ACTION_DIM];
        while env.status() == Status::Running {
            let step = env.steps();
            let obs = env.observation();
            policy.act_into(&obs, &mut action).map_err(policy_error(episode, step))?;
            let applied = checked_clip(action).map_err(policy_error(episode, step))?;
            if record {
                rec.push(&obs, &applied);
            }
            env.step_clipped(applied);
        }
        let trajectory = record.then(|| rec.take(env.observation()));
        Ok(Rollout { status: env.status(), gaps: env.gaps(), steps: env.steps(), trajectory })
    }

    fn lockstep<P: Policy + ?Sized>(
        &mut self,
        policy: &mut P,
        first: usize,
        n: usize,
        seed: u64,
        record: bool,
    ) -> Result<Vec<Rollout>> {
        policy.seed(seed);
        policy.reset();
        self.envs.clear();
        self.envs.resize(n, AvoidingEnv::new());
        if self.recorders.len() < n {
            self.recorders.resize_with(n, Recorder::default);
        }
        if self.obs.nrows() < n {
            self.obs = Mat::zeros(n, OBS_DIM);
            self.actions = Mat::zeros(n, ACTION_DIM);
        }
        for step in 0.. {
            for (i, env) in self.envs.iter().enumerate() {
                let o = env.observation();
                for j in 0..OBS_DIM {
                    self.obs[(i, j)] = o[j];
                }
            }
            policy
                .act_batch(self.obs.as_ref().subrows(0, n), self.actions.as_mut().subrows_mut(0, n))
                .map_err(policy_error(first, step))?;
            let mut running = false;
            for (i, env) in self.envs.iter_mut().enumerate() {
                if env.status().is_done() {
                    continue;
                }
                let raw = [self.actions[(i, 0)], self.actions[(i, 1)]];
                let applied = checked_clip(raw).map_err(policy_error(first + i, step))?;
                if record {
                    self.recorders[i].push(&env.observation(), &applied);
                }
                running |= env.step_clipped(applied) == Status::Running;
            }
            if !running {
                break;
            }
        }
        Ok(self
            .envs
            .iter()
            .zip(&mut self.recorders)
            .map(|(env, rec)| Rollout {
                status: env.status(),
                gaps: env.gaps(),
                steps: env.steps(),
                trajectory: record.then(|| rec.take(env.observation())),
            })
            .collect())
    }
}

fn checked_clip(action: [f32; ACTION_DIM]) -> std::result::Result<[f32; ACTION_DIM], CoreError> {
    if action.iter().all(|a| a.is_finite()) {
        Ok(AvoidingEnv::clip_action(action))
    } else {
        Err(CoreError::NonFinite { what: "action" })
    }
}

#[cfg(test)]
mod tests;
