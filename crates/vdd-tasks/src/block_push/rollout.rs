//! Rollouts of any [`Policy`] on Block-Push, and their aggregate metrics: success (p2), p1,
//! task entropy over the four modes and the mode histogram.
//!
//! # Seeding and stepping
//!
//! The same scheme as Avoiding's ([`crate::avoiding::rollout`], whose [`EvalConfig`] and
//! [`Stepping`] are reused): episode `i` of an evaluation with root seed `s` always starts from
//! [`env_seed`]`(s, i)`, under either stepping. Under [`Stepping::PerEpisode`] the policy is
//! seeded with [`episode_seed`]`(s, i)` and reset before episode `i`; under
//! [`Stepping::Lockstep`] it is seeded with [`chunk_seed`]`(s, c)` and reset once per chunk `c`
//! of `batch_size` consecutive episodes, which advance together through one
//! [`Policy::act_batch`] per step (rows of ended episodes carry their final observation; their
//! actions are ignored). [`evaluate_parallel`] and [`evaluate_cloned`] return exactly what
//! [`evaluate`] returns, whatever the number of threads: each environment owns its own
//! deterministic physics world.
//!
//! ```
//! use vdd_tasks::block_push::oracle::{BlockPushOracle, OracleConfig};
//! use vdd_tasks::block_push::rollout::{evaluate_cloned, EvalConfig, Stepping};
//! let oracle = BlockPushOracle::new(OracleConfig::default()).unwrap();
//! let cfg = EvalConfig { n_rollouts: 32, seed: 0, stepping: Stepping::PerEpisode, record: false };
//! let eval = evaluate_cloned(&oracle, 2, &cfg).unwrap();
//! assert!(eval.metrics.success_rate > 0.9);
//! ```

use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use faer::Mat;
use rand::Rng as _;
use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Policy, Seeds};

pub use crate::avoiding::rollout::{EvalConfig, Stepping};

use super::{
    ACTION_DIM, BlockPushEnv, BlockPushMode, EnvConfig, N_MODES, OBS_DIM, Status, env_seed,
};
use crate::{Result, TaskError, normalized_entropy};

/// The policy seed of episode `episode` under per-episode stepping.
pub fn episode_seed(seed: u64, episode: usize) -> u64 {
    Seeds::new(seed).stream_indexed("block-push-episode", episode as u64).random()
}

/// The policy seed of chunk `chunk` under lockstep stepping.
pub fn chunk_seed(seed: u64, chunk: usize) -> u64 {
    Seeds::new(seed).stream_indexed("block-push-chunk", chunk as u64).random()
}

/// The observations and actions of one episode.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    /// `T x 16`: the observation before each step.
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
    /// The first `(block, target)` visit, if any.
    pub mode: Option<BlockPushMode>,
    /// Whether at least one block reached a target (p1).
    pub p1: bool,
    /// Steps taken.
    pub steps: usize,
    /// The environment seed the episode started from.
    pub env_seed: u64,
    /// Observations and actions, when recording was asked for.
    pub trajectory: Option<Trajectory>,
}

impl Rollout {
    /// Whether the episode succeeded (p2).
    pub fn success(&self) -> bool {
        self.status == Status::Success
    }
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
            p1_count += usize::from(r.p1);
            match r.status {
                Status::Success => {
                    successes += 1;
                    success_steps += r.steps;
                    max_success_steps = max_success_steps.max(r.steps);
                    let m = r.mode.ok_or_else(|| {
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

/// Every rollout of an evaluation, in episode order, and their metrics.
#[derive(Debug, Clone, PartialEq)]
pub struct Evaluation {
    /// Aggregate metrics.
    pub metrics: Metrics,
    /// One entry per episode.
    pub rollouts: Vec<Rollout>,
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
    check_dims(policy)?;
    Worker::new(EnvConfig::default())?.episode(policy, 0, env_seed, policy_seed, record)
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
    cfg.validate()?;
    check_dims(policy)?;
    let mut worker = Worker::new(env.clone())?;
    let mut rollouts = Vec::with_capacity(cfg.n_rollouts);
    for unit in 0..cfg.n_units() {
        rollouts.extend(worker.unit(policy, cfg, unit)?);
    }
    finish(rollouts)
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
    cfg.validate()?;
    env.validate()?;
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
                    let Ok(mut worker) = Worker::new(env.clone()) else { return };
                    // Finish every unit taken, so the lowest failing unit is deterministic.
                    while !failed.load(Ordering::Relaxed) {
                        let unit = next.fetch_add(1, Ordering::Relaxed);
                        if unit >= n_units {
                            break;
                        }
                        let result = worker.unit(policy, cfg, unit);
                        let stop = result.is_err();
                        if stop {
                            failed.store(true, Ordering::Relaxed);
                        }
                        done.lock().unwrap_or_else(|e| e.into_inner()).push((unit, result));
                        if stop {
                            break;
                        }
                    }
                })
            })
            .collect();
        let joined: Vec<bool> = handles.into_iter().map(|h| h.join().is_err()).collect();
        joined.contains(&true)
    });
    if panicked {
        return Err(TaskError::WorkerPanicked);
    }
    let mut done = done.into_inner().unwrap_or_else(|e| e.into_inner());
    done.sort_by_key(|(unit, _)| *unit);
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

/// Environments and buffers reused across the units one thread runs.
pub(crate) struct Worker {
    env_config: EnvConfig,
    envs: Vec<BlockPushEnv>,
    recorders: Vec<Recorder>,
    obs: Mat<f32>,
    actions: Mat<f32>,
}

fn policy_error(episode: usize, step: usize) -> impl FnOnce(CoreError) -> TaskError {
    move |source| TaskError::Policy { episode, step, source }
}

impl Worker {
    pub(crate) fn new(env_config: EnvConfig) -> Result<Self> {
        env_config.validate()?;
        Ok(Self {
            env_config,
            envs: Vec::new(),
            recorders: Vec::new(),
            obs: Mat::zeros(0, OBS_DIM),
            actions: Mat::zeros(0, ACTION_DIM),
        })
    }

    fn ensure_envs(&mut self, n: usize) -> Result<()> {
        while self.envs.len() < n {
            self.envs.push(BlockPushEnv::new(self.env_config.clone())?);
        }
        if self.recorders.len() < n {
            self.recorders.resize_with(n, Recorder::default);
        }
        Ok(())
    }

    fn unit<P: Policy + ?Sized>(
        &mut self,
        policy: &mut P,
        cfg: &EvalConfig,
        unit: usize,
    ) -> Result<Vec<Rollout>> {
        match cfg.stepping {
            Stepping::PerEpisode => {
                let (es, ps) = (env_seed(cfg.seed, unit), episode_seed(cfg.seed, unit));
                Ok(vec![self.episode(policy, unit, es, ps, cfg.record)?])
            }
            Stepping::Lockstep { batch_size } => {
                let first = unit * batch_size;
                let n = batch_size.min(cfg.n_rollouts - first);
                self.lockstep(policy, cfg.seed, first, n, chunk_seed(cfg.seed, unit), cfg.record)
            }
        }
    }

    pub(crate) fn episode<P: Policy + ?Sized>(
        &mut self,
        policy: &mut P,
        episode: usize,
        env_seed: u64,
        policy_seed: u64,
        record: bool,
    ) -> Result<Rollout> {
        policy.seed(policy_seed);
        policy.reset();
        self.ensure_envs(1)?;
        let (env, rec) = (&mut self.envs[0], &mut self.recorders[0]);
        let mut obs = env.reset(env_seed);
        let mut action = [0.0f32; ACTION_DIM];
        while env.status() == Status::Running {
            let step = env.steps();
            policy.act_into(&obs, &mut action).map_err(policy_error(episode, step))?;
            let applied = checked_clip(action).map_err(policy_error(episode, step))?;
            if record {
                rec.push(&obs, &applied);
            }
            env.step_clipped(applied);
            obs = env.observation();
        }
        Ok(finished(env, rec, env_seed, record))
    }

    fn lockstep<P: Policy + ?Sized>(
        &mut self,
        policy: &mut P,
        root: u64,
        first: usize,
        n: usize,
        seed: u64,
        record: bool,
    ) -> Result<Vec<Rollout>> {
        policy.seed(seed);
        policy.reset();
        self.ensure_envs(n)?;
        let seeds: Vec<u64> = (0..n).map(|i| env_seed(root, first + i)).collect();
        for (env, &s) in self.envs.iter_mut().zip(&seeds) {
            env.reset(s);
        }
        if self.obs.nrows() < n {
            self.obs = Mat::zeros(n, OBS_DIM);
            self.actions = Mat::zeros(n, ACTION_DIM);
        }
        for step in 0.. {
            for (i, env) in self.envs[..n].iter().enumerate() {
                let o = env.observation();
                for j in 0..OBS_DIM {
                    self.obs[(i, j)] = o[j];
                }
            }
            policy
                .act_batch(self.obs.as_ref().subrows(0, n), self.actions.as_mut().subrows_mut(0, n))
                .map_err(policy_error(first, step))?;
            let mut running = false;
            for (i, env) in self.envs[..n].iter_mut().enumerate() {
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
        Ok(self.envs[..n]
            .iter()
            .zip(&mut self.recorders)
            .zip(seeds)
            .map(|((env, rec), s)| finished(env, rec, s, record))
            .collect())
    }
}

fn finished(env: &BlockPushEnv, rec: &mut Recorder, env_seed: u64, record: bool) -> Rollout {
    Rollout {
        status: env.status(),
        mode: env.mode(),
        p1: env.p1(),
        steps: env.steps(),
        env_seed,
        trajectory: record.then(|| rec.take(env.observation())),
    }
}

fn checked_clip(action: [f32; ACTION_DIM]) -> std::result::Result<[f32; ACTION_DIM], CoreError> {
    if action.iter().all(|a| a.is_finite()) {
        Ok(BlockPushEnv::clip_action(action))
    } else {
        Err(CoreError::NonFinite { what: "action" })
    }
}
