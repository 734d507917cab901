//! What the D3IL contact tasks ([`crate::pushing`], [`crate::aligning`]) share: an environment
//! evaluated over D3IL's *test contexts* (each start rolled out several times, the task entropy
//! taken per context), on the same planar physics.
//!
//! A task implements [`ContextEnv`] for its environment (its names, dimensions and defaults, a
//! seeded start, its observation, a step with an already checked action, its status and what
//! it records of an episode, a [`ContextOutcome`]); this module gives it the rest once:
//!
//! * the rollout engine's [`Env`] (a blanket implementation: episode `i` of an evaluation
//!   starts from test context `i / episodes_per_context`, see [`EnvConfig::episodes_per_context`]),
//! * its settings ([`EnvConfig`], [`PhysicsConfig`]) and the episode [`Status`],
//! * the evaluation a run reports ([`EvalProtocol`]: contexts × rollouts per context),
//! * the metrics and rollouts ([`rollout`]: success, p1 where the task counts it, D3IL's mean
//!   distance, the task entropy per context),
//! * the demonstrations of a scripted demonstrator ([`generate_demonstrations`]) and the
//!   demonstrator's human-like noise,
//! * the planar physics (a top-down `rapier2d` world, the pusher's position servo, the
//!   table's sliding friction).
//!
//! The names of a task's seed streams are its own ([`ContextEnv::STREAMS`] and the others), so
//! no two tasks share a stream. What every task must do (bit-identical episodes on any thread,
//! bad input reported as errors) is checked on both in `crates/vdd-tasks/tests/d3il_tasks.rs`.

use std::marker::PhantomData;

use rand::Rng as _;
use rapier2d::prelude::{PhysicsWorld, RigidBody, Vector};
use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Rng, Seeds, standard_normal};

use crate::episodes::{self, Env, SeedStreams};
use crate::scripted::{Demonstrations, Mode, Script, Scripted, collect};
use crate::{Result, TaskError};

pub use protocol::EvalProtocol;

mod protocol;
pub mod rollout;

/// An environment of a D3IL contact task, evaluated over test contexts: what the shared
/// settings, rollouts, metrics, protocol and demonstrations need of it. Implementing it makes
/// the environment an [`Env`] of the rollout engine.
pub trait ContextEnv: Send + Sized + std::fmt::Debug + 'static {
    /// The task's name in error messages (`pushing`).
    const NAME: &'static str;
    /// Observation length.
    const OBS_DIM: usize;
    /// Action length.
    const ACTION_DIM: usize;
    /// Number of behaviour modes (the entropies' log base).
    const N_MODES: usize;
    /// The default episode step limit ([`EnvConfig::default`]).
    const MAX_STEPS: usize;
    /// The default physics ([`EnvConfig::default`]).
    const PHYSICS: PhysicsConfig;
    /// D3IL's benchmark, [`EvalProtocol::default`]: test contexts × rollouts per context.
    const BENCHMARK: (usize, usize);
    /// The seed streams of evaluations (policy seeds per episode and per lockstep chunk, test
    /// contexts).
    const STREAMS: SeedStreams;
    /// The stream of a run's evaluation seed ([`EvalProtocol::seed`]).
    const EVAL_STREAM: &'static str;
    /// The stream of the demonstrations' starts ([`env_seed`]).
    const DEMO_STREAM: &'static str;
    /// What the task records of an episode beyond its status.
    type Outcome: ContextOutcome;

    /// An environment with `config`'s settings (invalid settings are an error).
    fn from_config(config: EnvConfig<Self>) -> Result<Self>;
    /// Starts a new episode from the test context `seed`.
    fn start(&mut self, seed: u64);
    /// Writes the observation into `out` (`OBS_DIM` long).
    fn observe_into(&self, out: &mut [f32]);
    /// Applies `action` (`ACTION_DIM` long, finite, the episode running: checked by the
    /// caller) clipped as the task's controller clips it, writes the action applied into
    /// `applied`, and advances one step.
    fn step_checked(&mut self, action: &[f32], applied: &mut [f32]);
    /// The episode's status and the steps taken.
    fn progress(&self) -> (Status, usize);
    /// What the task records of the episode now.
    fn outcome(&self) -> Self::Outcome;
}

/// What a D3IL contact task records of an episode, as the shared metrics read it.
pub trait ContextOutcome: Clone + std::fmt::Debug + PartialEq + Send {
    /// The task's behaviour mode.
    type Mode: Mode + std::fmt::Debug + PartialEq + Send;
    /// The mode the episode reached, if any (a successful episode without one is an error of
    /// the metrics).
    fn reached_mode(&self) -> Option<Self::Mode>;
    /// Whether at least one object reached a target (p1), on a task that counts it; `None` on
    /// a task without p1.
    fn reached_p1(&self) -> Option<bool>;
    /// D3IL's mean distance at the last step.
    fn final_distance(&self) -> f32;
    /// The start seed: the episode's test context.
    fn test_context(&self) -> u64;
}

impl<T: ContextEnv> Env for T {
    type Config = EnvConfig<T>;
    type Status = Status;
    type Info = T::Outcome;
    const OBS_DIM: usize = <T as ContextEnv>::OBS_DIM;
    const ACTION_DIM: usize = <T as ContextEnv>::ACTION_DIM;
    const STREAMS: SeedStreams = <T as ContextEnv>::STREAMS;

    fn build(config: &EnvConfig<T>) -> Result<Self> {
        T::from_config(config.clone())
    }

    fn reset(&mut self, seed: u64) {
        self.start(seed);
    }

    fn observe(&self, out: &mut [f32]) -> std::result::Result<(), CoreError> {
        vdd_core::check_len("observation buffer", out.len(), <T as ContextEnv>::OBS_DIM)?;
        self.observe_into(out);
        Ok(())
    }

    fn apply(&mut self, action: &[f32], applied: &mut [f32]) -> std::result::Result<(), CoreError> {
        episodes::check_apply(self, action, applied)?;
        self.step_checked(action, applied);
        Ok(())
    }

    fn status(&self) -> Status {
        self.progress().0
    }

    fn is_done(&self) -> bool {
        self.progress().0.is_done()
    }

    fn steps(&self) -> usize {
        self.progress().1
    }

    fn info(&self) -> T::Outcome {
        self.outcome()
    }

    fn start_of(config: &EnvConfig<T>, seed: u64, episode: usize) -> u64 {
        episodes::start_seed::<T>(seed, episode / config.episodes_per_context.max(1))
    }
}

/// State of an episode of a D3IL contact task.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Status {
    /// Still going.
    Running,
    /// The task's goal is met (Pushing: both boxes in distinct targets; Aligning: the tray at
    /// its target pose).
    Success,
    /// The step limit was reached without success.
    Timeout,
    /// An object or the pusher left the table (a failure).
    OffTable,
    /// A body's state became non-finite (a failure).
    PhysicsFault,
}

impl Status {
    /// Whether the episode has ended.
    pub fn is_done(self) -> bool {
        self != Status::Running
    }

    /// A short lowercase name.
    pub fn as_str(self) -> &'static str {
        match self {
            Status::Running => "running",
            Status::Success => "success",
            Status::Timeout => "timeout",
            Status::OffTable => "off-table",
            Status::PhysicsFault => "physics-fault",
        }
    }
}

/// Physics parameters of a planar D3IL task (see the task's module docs; its defaults are
/// [`ContextEnv::PHYSICS`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PhysicsConfig {
    /// Physics substeps per control step.
    pub substeps: usize,
    /// Largest pusher speed (m/s) while it tracks the desired position.
    pub pusher_speed: f32,
    /// Sliding-friction deceleration of a pushed object's speed (m/s²).
    pub friction_decel: f32,
    /// Friction deceleration of a pushed object's spin (rad/s²).
    pub spin_decel: f32,
    /// Rapier linear damping of the pushed objects (1/s).
    pub linear_damping: f32,
    /// Rapier angular damping of the pushed objects (1/s).
    pub angular_damping: f32,
    /// Contact friction coefficient of the pusher and the pushed objects.
    pub contact_friction: f32,
}

/// Settings of the environment `E` (`pushing::EnvConfig` is `EnvConfig<PushingEnv>`).
///
/// ```
/// use vdd_tasks::pushing::{EnvConfig, MAX_STEPS};
/// let mut c = EnvConfig::default();
/// assert_eq!((c.max_steps, c.episodes_per_context), (MAX_STEPS, 1));
/// c.episodes_per_context = 0;
/// assert!(c.validate().is_err());
/// ```
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields, bound = "")]
pub struct EnvConfig<E> {
    /// Episode step limit.
    pub max_steps: usize,
    /// Episodes in a row that share one start (a test context) in evaluations
    /// ([`crate::episodes::Env::start_of`]): episode `i` starts from context
    /// `i / episodes_per_context`.
    pub episodes_per_context: usize,
    /// Physics parameters.
    pub physics: PhysicsConfig,
    #[serde(skip)]
    task: PhantomData<fn() -> E>,
}

impl<E: ContextEnv> Default for EnvConfig<E> {
    /// [`ContextEnv::MAX_STEPS`] steps, one episode per start, the task's default physics.
    fn default() -> Self {
        Self::with_episodes_per_context(1)
    }
}

impl<E> Clone for EnvConfig<E> {
    fn clone(&self) -> Self {
        Self {
            max_steps: self.max_steps,
            episodes_per_context: self.episodes_per_context,
            physics: self.physics.clone(),
            task: PhantomData,
        }
    }
}

impl<E> PartialEq for EnvConfig<E> {
    fn eq(&self, other: &Self) -> bool {
        (self.max_steps, self.episodes_per_context, &self.physics)
            == (other.max_steps, other.episodes_per_context, &other.physics)
    }
}

impl<E> std::fmt::Debug for EnvConfig<E> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EnvConfig")
            .field("max_steps", &self.max_steps)
            .field("episodes_per_context", &self.episodes_per_context)
            .field("physics", &self.physics)
            .finish()
    }
}

impl<E: ContextEnv> EnvConfig<E> {
    /// The default settings with `episodes_per_context` episodes per test context.
    pub fn with_episodes_per_context(episodes_per_context: usize) -> Self {
        Self {
            max_steps: E::MAX_STEPS,
            episodes_per_context,
            physics: E::PHYSICS,
            task: PhantomData,
        }
    }

    /// Checks every field's range.
    pub fn validate(&self) -> Result<()> {
        let p = &self.physics;
        let bad = |m: String| Err(TaskError::InvalidArgument(format!("{} env: {m}", E::NAME)));
        if self.max_steps == 0 || !(1..=1000).contains(&p.substeps) {
            return bad(format!(
                "max_steps {} must be >= 1 and substeps {} in 1..=1000",
                self.max_steps, p.substeps
            ));
        }
        if !(1..=100_000).contains(&self.episodes_per_context) {
            return bad(format!(
                "episodes_per_context {} must be in 1..=100000",
                self.episodes_per_context
            ));
        }
        let fields = [
            ("pusher_speed", p.pusher_speed),
            ("friction_decel", p.friction_decel),
            ("spin_decel", p.spin_decel),
            ("linear_damping", p.linear_damping),
            ("angular_damping", p.angular_damping),
            ("contact_friction", p.contact_friction),
        ];
        if let Some((name, v)) = fields.iter().find(|(_, v)| !(v.is_finite() && *v >= 0.0)) {
            return bad(format!("{name} must be finite and non-negative, got {v}"));
        }
        if p.pusher_speed <= 0.0 {
            return bad("pusher_speed must be positive".into());
        }
        Ok(())
    }
}

/// The start seed of demonstration `episode` of a set with root seed `seed`, on the task's
/// [`ContextEnv::DEMO_STREAM`].
pub fn env_seed<E: ContextEnv>(seed: u64, episode: usize) -> u64 {
    Seeds::new(seed).stream_indexed(E::DEMO_STREAM, episode as u64).random()
}

/// Runs the scripted `demonstrator` in environments with `env`'s settings until `n` episodes
/// have succeeded and returns them with the modes they reached (failed episodes are skipped;
/// [`Demonstrations::success_rate`] reports how many). Episode `i` starts from
/// [`env_seed`]`(seed, i)` and the demonstrator is seeded with the per-episode policy seed
/// ([`crate::episodes::episode_seed`]) of `(seed, i)`, so the result is deterministic. More
/// than `2n + 16` episodes without `n` successes is an error.
pub fn generate_demonstrations<E: ContextEnv, S: Script>(
    demonstrator: &mut Scripted<S>,
    n: usize,
    seed: u64,
    env: &EnvConfig<E>,
) -> Result<Demonstrations<<E::Outcome as ContextOutcome>::Mode>> {
    env.validate()?;
    let seeds = |i| (episodes::episode_seed::<E>(seed, i), env_seed::<E>(seed, i));
    let kept = |r: &episodes::Rollout<E>| r.success().then(|| r.info.reached_mode()).flatten();
    collect::<E, _, _>(demonstrator, env.clone(), (n, env.max_steps), seeds, kept)
}

/// Checks a demonstrator's noise settings (the message names `what`, e.g. `pushing oracle`):
/// `ou_reversion` in `(0, 1]`, `ou_std` in `[0, 1]`, `speed_jitter` in `[0, 0.1]`.
pub(crate) fn check_noise(
    what: &str,
    ou_reversion: f32,
    ou_std: f32,
    speed_jitter: f32,
) -> Result<()> {
    let bad = |m: String| Err(TaskError::InvalidArgument(format!("{what}: {m}")));
    if !(ou_reversion > 0.0 && ou_reversion <= 1.0) {
        return bad(format!("ou_reversion {ou_reversion} must be in (0, 1]"));
    }
    if !(0.0..=1.0).contains(&ou_std) {
        return bad(format!("ou_std {ou_std} must be in [0, 1]"));
    }
    if !(0.0..=0.1).contains(&speed_jitter) {
        return bad(format!("speed_jitter {speed_jitter} must be in [0, 0.1]"));
    }
    Ok(())
}

/// A demonstrator's step with human-like noise: `delta` clipped to length `max_step` (lengths
/// by `norm`), perturbed by `|Δ| · e_t` with `e_t` (the episode's `ou`, advanced here) an
/// Ornstein–Uhlenbeck process of mean reversion `ou_reversion` per step and stationary
/// standard deviation `ou_std`, and clipped again. With `ou_std = 0` the clipped `delta`,
/// drawing nothing.
pub(crate) fn noisy_step<const N: usize>(
    delta: [f32; N],
    max_step: f32,
    norm: fn([f32; N]) -> f32,
    (ou_std, ou_reversion): (f32, f32),
    ou: &mut [f32; N],
    rng: &mut Rng,
) -> [f32; N] {
    let clip = |d: [f32; N]| {
        let n = norm(d);
        if n > max_step { d.map(|x| x * max_step / n) } else { d }
    };
    let delta = clip(delta);
    if ou_std == 0.0 {
        return delta;
    }
    // Stationary std of e = (1 − κ) e + σ ξ is σ / sqrt(1 − (1 − κ)²).
    let keep = 1.0 - ou_reversion;
    let sigma = ou_std * (1.0 - keep * keep).sqrt();
    for e in ou.iter_mut() {
        *e = keep * *e + sigma * standard_normal(rng);
    }
    let m = norm(delta);
    clip(std::array::from_fn(|i| delta[i] + m * ou[i]))
}

/// A demonstrator's per-episode draw: the mode (`fixed`, or one of `n_modes` uniformly by
/// `from_index`), then the factor of the speed caps from `U(1 − jitter, 1 + jitter)`.
pub(crate) fn draw_episode<M>(
    fixed: Option<M>,
    (n_modes, from_index): (usize, fn(usize) -> Result<M>),
    jitter: f32,
    rng: &mut Rng,
) -> std::result::Result<(M, f32), CoreError> {
    let mode = match fixed {
        Some(m) => m,
        None => from_index(rng.random_range(0..n_modes)).map_err(CoreError::implementor)?,
    };
    Ok((mode, 1.0 + jitter * (2.0 * rng.random::<f32>() - 1.0)))
}

/// A fresh top-down world: zero gravity, physics step `dt`, and the tolerances (allowed
/// penetration, prediction distance) scaled to `length_unit`.
pub(crate) fn planar_world(dt: f32, length_unit: f32) -> PhysicsWorld {
    let mut world = PhysicsWorld::new();
    world.gravity = Vector::ZERO;
    world.integration_parameters.dt = dt;
    world.integration_parameters.length_unit = length_unit;
    world
}

/// One substep of the pusher's position servo: `at` moved straight towards `desired` by at
/// most `max_move`.
pub(crate) fn servo(at: [f32; 2], desired: [f32; 2], max_move: f32) -> [f32; 2] {
    let d = [desired[0] - at[0], desired[1] - at[1]];
    let n = d[0].hypot(d[1]);
    if n > max_move { [at[0] + d[0] * max_move / n, at[1] + d[1] * max_move / n] } else { desired }
}

/// The table's sliding friction on a body for one substep: its speed reduced by `dv` and its
/// spin by `dw`, never reversed.
pub(crate) fn table_friction(b: &mut RigidBody, dv: f32, dw: f32) {
    let v = b.linvel();
    let s = v.length();
    let v = if s > dv { v * (1.0 - dv / s) } else { Vector::ZERO };
    b.set_linvel(v, true);
    let w = b.angvel();
    b.set_angvel(if w.abs() > dw { w - dw * w.signum() } else { 0.0 }, true);
}
