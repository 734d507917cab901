//! Seeded rollouts of any [`Policy`] on any task: the [`Env`] trait a task implements, and the
//! evaluation engine every task shares.
//!
//! A task provides its environment ([`Env`]: start from a seed, observe, step, status, its mode)
//! and the metrics it reports ([`TaskMetrics`]); [`evaluate`], [`evaluate_parallel`] and
//! [`evaluate_cloned`] then run its episodes, on one thread or many, with the same results.
//!
//! # Seeding and stepping
//!
//! Everything is deterministic for [`EvalConfig::seed`], and identical whatever the number of
//! threads, provided the policy honours the [`Policy`] contract (after `seed(s)` and `reset()`,
//! its behaviour depends only on `s` and its inputs). Every episode runs on an environment
//! built from the settings the caller passes ([`Env::build`]), and episode `i` starts from
//! [`Env::reset`]`(`[`start_seed`]`(seed, i))` under both steppings, so both see the same start
//! states. Work is split into *units*:
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

use std::sync::Mutex;
use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};

use faer::Mat;
use rand::Rng as _;
use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Policy, Seeds};

use crate::{Result, TaskError};

/// The names of a task's seed streams: one task's episodes never share a stream with another's.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SeedStreams {
    /// The policy seed of each episode under [`Stepping::PerEpisode`].
    pub episode: &'static str,
    /// The policy seed of each chunk under [`Stepping::Lockstep`].
    pub chunk: &'static str,
    /// The environment's start of each episode.
    pub start: &'static str,
}

/// One episode of a task: what the rollout engine drives.
///
/// ```
/// use vdd_tasks::episodes::Env;
/// use vdd_tasks::AvoidingEnv;
///
/// let mut env = AvoidingEnv::build(&()).unwrap();
/// Env::reset(&mut env, 0);
/// let mut obs = [0.0f32; 4];
/// let mut applied = [0.0f32; 2];
/// env.observe(&mut obs).unwrap();
/// env.apply(&[0.0, 0.5], &mut applied).unwrap();
/// assert_eq!(applied, [0.0, 0.02]); // clipped to the task's action limit
/// assert_eq!(env.steps(), 1);
/// assert!(env.apply(&[0.0], &mut applied).is_err()); // a wrong length is an error
/// assert!(env.apply(&[f32::NAN, 0.0], &mut applied).is_err());
/// assert_eq!(env.steps(), 1);
/// ```
pub trait Env: Send + Sized {
    /// The task's settings (time limit, physics, ...).
    type Config: Clone + Send + Sync;
    /// How an episode stands (running, or how it ended).
    type Status: Copy + std::fmt::Debug + PartialEq + Send;
    /// What the task records of an episode beyond its status (e.g. Avoiding's gaps).
    type Info: Clone + std::fmt::Debug + PartialEq + Send;
    /// Observation length.
    const OBS_DIM: usize;
    /// Action length.
    const ACTION_DIM: usize;
    /// The task's seed streams.
    const STREAMS: SeedStreams;

    /// An environment with `config`'s settings, ready for [`Env::reset`]; invalid settings are
    /// an error.
    fn build(config: &Self::Config) -> Result<Self>;
    /// Starts a new episode; `seed` draws its start (a task without random starts ignores it).
    /// What happened in earlier episodes never matters.
    fn reset(&mut self, seed: u64);
    /// Writes the observation into `out` (`OBS_DIM` long, else an error).
    fn observe(&self, out: &mut [f32]) -> std::result::Result<(), CoreError>;
    /// Applies the policy's `action` (`ACTION_DIM` long) as the task's controller would
    /// (clipped to its limits), writes the action applied into `applied` (`ACTION_DIM` long),
    /// and advances one step. A wrong length, a non-finite action or an ended episode is an
    /// error ([`check_apply`]) and leaves the episode unchanged.
    fn apply(&mut self, action: &[f32], applied: &mut [f32]) -> std::result::Result<(), CoreError>;
    /// The episode's status.
    fn status(&self) -> Self::Status;
    /// Whether the episode has ended.
    fn is_done(&self) -> bool;
    /// Steps taken.
    fn steps(&self) -> usize;
    /// What the task records of the episode.
    fn info(&self) -> Self::Info;
    /// The start seed ([`Env::reset`]) of episode `episode` of an evaluation with root seed
    /// `seed` in environments with `config`'s settings: [`start_seed`] by default. A task whose
    /// evaluation repeats each start over several episodes (D3IL's test contexts) overrides it.
    fn start_of(config: &Self::Config, seed: u64, episode: usize) -> u64 {
        let _ = config;
        start_seed::<Self>(seed, episode)
    }
}

/// The checks every [`Env::apply`] makes first: the episode is running, `action` and `applied`
/// are `ACTION_DIM` long, and the action is finite.
pub fn check_apply<E: Env>(
    env: &E,
    action: &[f32],
    applied: &[f32],
) -> std::result::Result<(), CoreError> {
    if env.is_done() {
        return Err(CoreError::implementor(TaskError::EpisodeOver("ended")));
    }
    vdd_core::check_len("action", action.len(), E::ACTION_DIM)?;
    vdd_core::check_len("applied action", applied.len(), E::ACTION_DIM)?;
    if !action.iter().all(|a| a.is_finite()) {
        return Err(CoreError::NonFinite { what: "action" });
    }
    Ok(())
}

/// A task's aggregate metrics of a set of rollouts.
pub trait TaskMetrics<E: Env>: Sized {
    /// Summarises `rollouts` (an empty slice is an error).
    fn from_rollouts(rollouts: &[Rollout<E>]) -> Result<Self>;
}

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
    /// Root seed of the policy seeds ([`episode_seed`], [`chunk_seed`]) and of the starts
    /// ([`start_seed`]).
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
    /// `n_rollouts` episodes from root seed `seed`, in lockstep batches of `lockstep_batch`
    /// (0: one episode at a time), keeping trajectories when `record`: what the tasks'
    /// evaluation protocols build.
    ///
    /// ```
    /// use vdd_tasks::episodes::{EvalConfig, Stepping};
    /// let c = EvalConfig::protocol(500, 50, 7, false);
    /// assert_eq!((c.n_rollouts, c.seed), (500, 7));
    /// assert_eq!(c.stepping, Stepping::Lockstep { batch_size: 50 });
    /// assert_eq!(EvalConfig::protocol(10, 0, 7, true).stepping, Stepping::PerEpisode);
    /// ```
    pub fn protocol(n_rollouts: usize, lockstep_batch: usize, seed: u64, record: bool) -> Self {
        let stepping = match lockstep_batch {
            0 => Stepping::PerEpisode,
            b => Stepping::Lockstep { batch_size: b },
        };
        Self { n_rollouts, seed, stepping, record }
    }

    fn validate(&self) -> Result<()> {
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

    fn unit_size(&self) -> usize {
        match self.stepping {
            Stepping::PerEpisode => 1,
            Stepping::Lockstep { batch_size } => batch_size,
        }
    }

    /// The number of units (episodes, or chunks of episodes) the evaluation runs.
    pub fn n_units(&self) -> usize {
        self.n_rollouts.div_ceil(self.unit_size())
    }
}

/// The policy seed of episode `episode` of task `E` under per-episode stepping.
pub fn episode_seed<E: Env>(seed: u64, episode: usize) -> u64 {
    Seeds::new(seed).stream_indexed(E::STREAMS.episode, episode as u64).random()
}

/// The policy seed of chunk `chunk` of task `E` under lockstep stepping.
pub fn chunk_seed<E: Env>(seed: u64, chunk: usize) -> u64 {
    Seeds::new(seed).stream_indexed(E::STREAMS.chunk, chunk as u64).random()
}

/// The start seed ([`Env::reset`]) of episode `episode` of task `E`, under either stepping.
pub fn start_seed<E: Env>(seed: u64, episode: usize) -> u64 {
    Seeds::new(seed).stream_indexed(E::STREAMS.start, episode as u64).random()
}

/// The observations and actions of one episode.
#[derive(Debug, Clone, PartialEq)]
pub struct Trajectory {
    /// `T x OBS_DIM`: the observation before each step.
    pub observations: Mat<f32>,
    /// `T x ACTION_DIM`: the action applied at each step (after the task's clipping).
    pub actions: Mat<f32>,
    /// The observation after the last step.
    pub final_observation: Vec<f32>,
}

/// The outcome of one episode.
#[derive(Debug, Clone)]
pub struct Rollout<E: Env> {
    /// How the episode ended.
    pub status: E::Status,
    /// What the task recorded of it.
    pub info: E::Info,
    /// Steps taken.
    pub steps: usize,
    /// Observations and actions, when recording was asked for.
    pub trajectory: Option<Trajectory>,
}

// By hand: a derive would ask `E: PartialEq` of the environment itself.
impl<E: Env> PartialEq for Rollout<E> {
    fn eq(&self, other: &Self) -> bool {
        (self.status, &self.info, self.steps, &self.trajectory)
            == (other.status, &other.info, other.steps, &other.trajectory)
    }
}

/// Every rollout of an evaluation, in episode order, and the task's metrics of them.
#[derive(Debug, Clone)]
pub struct Evaluation<E: Env, M> {
    /// Aggregate metrics.
    pub metrics: M,
    /// One entry per episode.
    pub rollouts: Vec<Rollout<E>>,
}

impl<E: Env, M: PartialEq> PartialEq for Evaluation<E, M> {
    fn eq(&self, other: &Self) -> bool {
        self.metrics == other.metrics && self.rollouts == other.rollouts
    }
}

/// Runs one episode on the calling thread in an environment with `env`'s settings: seeds the policy with
/// `policy_seed`, resets it, starts the task from `start` ([`Env::reset`]) and acts through
/// [`Policy::act_into`] until the episode ends.
pub fn rollout<E: Env, P: Policy + ?Sized>(
    env: &E::Config,
    policy: &mut P,
    policy_seed: u64,
    start: u64,
    record: bool,
) -> Result<Rollout<E>> {
    check_dims::<E, P>(policy)?;
    Worker::new(env.clone()).episode(policy, 0, (policy_seed, start), record)
}

/// Runs `cfg.n_rollouts` episodes in environments with `env`'s settings, on the calling
/// thread, and summarises them.
pub fn evaluate<E: Env, M: TaskMetrics<E>, P: Policy + ?Sized>(
    env: &E::Config,
    policy: &mut P,
    cfg: &EvalConfig,
) -> Result<Evaluation<E, M>> {
    cfg.validate()?;
    check_dims::<E, P>(policy)?;
    let mut worker = Worker::new(env.clone());
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
pub fn evaluate_parallel<E: Env, M: TaskMetrics<E>, P: Policy + Send>(
    env: &E::Config,
    policies: &mut [P],
    cfg: &EvalConfig,
) -> Result<Evaluation<E, M>> {
    cfg.validate()?;
    if policies.is_empty() {
        return Err(TaskError::InvalidArgument(
            "evaluate_parallel needs at least one policy".into(),
        ));
    }
    for p in policies.iter() {
        check_dims::<E, P>(p)?;
    }
    let n_units = cfg.n_units();
    let next = AtomicUsize::new(0);
    let failed = AtomicBool::new(false);
    type Done<E> = Vec<(usize, Result<Vec<Rollout<E>>>)>;
    let done: Mutex<Done<E>> = Mutex::new(Vec::with_capacity(n_units));
    let workers = policies.len().min(n_units);
    let panicked = std::thread::scope(|scope| {
        let handles: Vec<_> = policies[..workers]
            .iter_mut()
            .map(|policy| {
                let (next, failed, done) = (&next, &failed, &done);
                scope.spawn(move || {
                    let mut worker = Worker::<E>::new(env.clone());
                    // Stop taking units after a failure, but finish every unit taken: all
                    // units below a failing one were taken before it, so they all run.
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
pub fn evaluate_cloned<E: Env, M: TaskMetrics<E>, P: Policy + Clone + Send>(
    env: &E::Config,
    policy: &P,
    threads: usize,
    cfg: &EvalConfig,
) -> Result<Evaluation<E, M>> {
    if threads == 0 {
        return Err(TaskError::InvalidArgument("threads must be at least 1".into()));
    }
    let mut policies: Vec<P> =
        (0..threads.min(cfg.n_units().max(1))).map(|_| policy.clone()).collect();
    evaluate_parallel(env, &mut policies, cfg)
}

fn finish<E: Env, M: TaskMetrics<E>>(rollouts: Vec<Rollout<E>>) -> Result<Evaluation<E, M>> {
    Ok(Evaluation { metrics: M::from_rollouts(&rollouts)?, rollouts })
}

fn check_dims<E: Env, P: Policy + ?Sized>(policy: &P) -> Result<()> {
    if policy.obs_dim() != E::OBS_DIM || policy.action_dim() != E::ACTION_DIM {
        return Err(TaskError::PolicyDims {
            obs: E::OBS_DIM,
            action: E::ACTION_DIM,
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
    fn push(&mut self, obs: &[f32], action: &[f32]) {
        self.observations.extend_from_slice(obs);
        self.actions.extend_from_slice(action);
    }

    fn take<E: Env>(&mut self, env: &E) -> Trajectory {
        let (od, ad) = (E::OBS_DIM, E::ACTION_DIM);
        let t = self.actions.len() / ad;
        let (o, a) = (&self.observations, &self.actions);
        let mut final_observation = vec![0.0; od];
        // The buffer has the length `observe` asks for: it cannot fail.
        let _ = env.observe(&mut final_observation);
        let tr = Trajectory {
            observations: Mat::from_fn(t, od, |i, j| o[i * od + j]),
            actions: Mat::from_fn(t, ad, |i, j| a[i * ad + j]),
            final_observation,
        };
        self.observations.clear();
        self.actions.clear();
        tr
    }
}

/// Environments and buffers reused across the units one thread runs.
pub(crate) struct Worker<E: Env> {
    config: E::Config,
    envs: Vec<E>,
    recorders: Vec<Recorder>,
    obs: Mat<f32>,
    actions: Mat<f32>,
    row_obs: Vec<f32>,
    row_action: Vec<f32>,
    applied: Vec<f32>,
}

impl<E: Env> Worker<E> {
    /// A worker whose episodes run in environments with `config`'s settings.
    pub(crate) fn new(config: E::Config) -> Self {
        Self {
            config,
            envs: Vec::new(),
            recorders: Vec::new(),
            obs: Mat::zeros(0, E::OBS_DIM),
            actions: Mat::zeros(0, E::ACTION_DIM),
            row_obs: vec![0.0; E::OBS_DIM],
            row_action: vec![0.0; E::ACTION_DIM],
            applied: vec![0.0; E::ACTION_DIM],
        }
    }
}

fn policy_error(episode: usize, step: usize) -> impl FnOnce(CoreError) -> TaskError {
    move |source| TaskError::Policy { episode, step, source }
}

fn finished<E: Env>(env: &E, rec: &mut Recorder, record: bool) -> Rollout<E> {
    Rollout {
        status: env.status(),
        info: env.info(),
        steps: env.steps(),
        trajectory: record.then(|| rec.take(env)),
    }
}

impl<E: Env> Worker<E> {
    /// At least `n` environments and recorders.
    fn ensure(&mut self, n: usize) -> Result<()> {
        while self.envs.len() < n {
            self.envs.push(E::build(&self.config)?);
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
    ) -> Result<Vec<Rollout<E>>> {
        match cfg.stepping {
            Stepping::PerEpisode => {
                let start = E::start_of(&self.config, cfg.seed, unit);
                let seeds = (episode_seed::<E>(cfg.seed, unit), start);
                Ok(vec![self.episode(policy, unit, seeds, cfg.record)?])
            }
            Stepping::Lockstep { batch_size } => {
                let first = unit * batch_size;
                let n = batch_size.min(cfg.n_rollouts - first);
                self.lockstep(policy, cfg.seed, unit, first, n, cfg.record)
            }
        }
    }

    /// One episode (`episode` names it in errors) with the policy seeded by `seeds.0` and the
    /// task started from `seeds.1`.
    pub(crate) fn episode<P: Policy + ?Sized>(
        &mut self,
        policy: &mut P,
        episode: usize,
        (policy_seed, start): (u64, u64),
        record: bool,
    ) -> Result<Rollout<E>> {
        policy.seed(policy_seed);
        policy.reset();
        self.ensure(1)?;
        let (env, rec) = (&mut self.envs[0], &mut self.recorders[0]);
        env.reset(start);
        let (obs, action, applied) = (&mut self.row_obs, &mut self.row_action, &mut self.applied);
        while !env.is_done() {
            let step = env.steps();
            env.observe(obs)?;
            policy.act_into(obs, action).map_err(policy_error(episode, step))?;
            env.apply(action, applied).map_err(policy_error(episode, step))?;
            if record {
                rec.push(obs, applied);
            }
        }
        Ok(finished(env, rec, record))
    }

    fn lockstep<P: Policy + ?Sized>(
        &mut self,
        policy: &mut P,
        seed: u64,
        chunk: usize,
        first: usize,
        n: usize,
        record: bool,
    ) -> Result<Vec<Rollout<E>>> {
        policy.seed(chunk_seed::<E>(seed, chunk));
        policy.reset();
        self.ensure(n)?;
        for (i, env) in self.envs[..n].iter_mut().enumerate() {
            env.reset(E::start_of(&self.config, seed, first + i));
        }
        if self.obs.nrows() < n {
            self.obs = Mat::zeros(n, E::OBS_DIM);
            self.actions = Mat::zeros(n, E::ACTION_DIM);
        }
        let (row_obs, row_action, applied) =
            (&mut self.row_obs, &mut self.row_action, &mut self.applied);
        for step in 0.. {
            for (i, env) in self.envs[..n].iter().enumerate() {
                env.observe(row_obs)?;
                row_obs.iter().enumerate().for_each(|(j, &o)| self.obs[(i, j)] = o);
            }
            policy
                .act_batch(self.obs.as_ref().subrows(0, n), self.actions.as_mut().subrows_mut(0, n))
                .map_err(policy_error(first, step))?;
            let mut running = false;
            for (i, env) in self.envs[..n].iter_mut().enumerate() {
                if env.is_done() {
                    continue;
                }
                row_action.iter_mut().enumerate().for_each(|(j, a)| *a = self.actions[(i, j)]);
                env.observe(row_obs)?;
                env.apply(row_action, applied).map_err(policy_error(first + i, step))?;
                if record {
                    self.recorders[i].push(row_obs, applied);
                }
                running |= !env.is_done();
            }
            if !running {
                break;
            }
        }
        Ok(self.envs[..n]
            .iter()
            .zip(&mut self.recorders)
            .map(|(env, rec)| finished(env, rec, record))
            .collect())
    }
}
