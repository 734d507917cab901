//! The scripted Pushing demonstrator (D3IL's demonstrations are human teleoperation, not in the
//! repository; this script stands in for the operator) with human-like noise, and
//! demonstration generation.
//!
//! # What the demonstrator does
//!
//! It acts on the observation alone (plus its per-episode state), as Block-Push's oracle
//! ([`crate::block_push::oracle`]) does, with distances scaled to these 6 cm boxes and the
//! 1 cm rod. At the first call after [`Policy::reset`](vdd_core::Policy::reset) it draws one
//! of the four modes uniformly from its own seeded stream (or uses
//! [`OracleConfig::fixed_mode`]): the first box → its target, then the other box → the other
//! target. With `ee` = the desired position (obs 0–1), `b` the current box, `t` its target,
//! `u = (t − b)/|t − b|` and `θ_err = atan2(u) − yaw` wrapped into `[−π/4, π/4]` (the cube's
//! symmetry), the phases (checked one after another in the same call) are:
//!
//! | phase | aims at | speed cap | leaves when |
//! |---|---|---|---|
//! | `MoveToPreBox` | `b − 0.07u` | 0.24 m/s | within 1 mm → `MoveToBox` (first time: store `first_prebox`) |
//! | `MoveToBox` | `b − 0.045u` | 0.24 m/s | within 1 mm → `Push`; `θ_err > 0.35` → `OrientLeft`, `< −0.35` → `OrientRight` |
//! | `Push` | `b − 0.02u` (inside the box) | 0.24 m/s | `|θ_err| > 0.45` → `MoveToPreBox` |
//! | `OrientLeft/Right` | `b + 0.036·R(±0.2)·dir(b → ee)` | 0.12 m/s | `θ_err < 0.1` (left) / `> −0.1` (right) → `MoveToPreBox` |
//! | `Retreat` | `first_prebox` | 0.24 m/s | within 1 mm → `GoBelow` |
//! | `GoBelow` | `(first_prebox.x, b₂.y − 0.12)` | 0.24 m/s | within 1 mm → `MoveToPreBox` (second box) |
//!
//! The yaw thresholds are wider than Block-Push's 0.2: the push aims at the box's centre, so a
//! box off by less than the contact's 26.6° friction cone (friction 0.5) is pushed straight,
//! and orienting these larger boxes costs time the 400-step limit does not leave.
//!
//! When the first box is within [`OracleConfig::switch_distance`] `= 0.04` of its target, the
//! demonstrator turns to the second box: back along the first box's path and then below the
//! second box, so that it neither knocks the first box out nor hits the second from above. The
//! speed caps are near the teleoperator's largest step (the gamepad gives at most 0.0083 m per
//! 0.035 s step, ≈ 0.24 m/s).
//!
//! # Human-like noise
//!
//! As Block-Push's: each step `Δ` (clipped to the phase's cap) is perturbed by `|Δ| · e_t`,
//! `e_t` a 2-D Ornstein–Uhlenbeck process with mean reversion [`OracleConfig::ou_reversion`] per
//! step and stationary standard deviation [`OracleConfig::ou_std`]; each episode's caps are
//! scaled by a factor drawn from `U(1 − speed_jitter, 1 + speed_jitter)` (at most 0.264 m/s,
//! 0.0092 m a step, within the ±0.01 action bound).
//!
//! ```
//! use vdd_tasks::pushing::oracle::{generate_demonstrations, OracleConfig};
//! let demos = generate_demonstrations(2, 0, &OracleConfig::default()).unwrap();
//! assert_eq!(demos.observations.len(), 2);
//! assert_eq!(demos.mode_counts().iter().sum::<usize>(), 2);
//! ```

use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Rng};

use super::{ACTION_DIM, CONTROL_DT, EnvConfig, N_MODES, OBS_DIM, PushingMode, TARGETS};
use crate::d3il::{check_noise, draw_episode, noisy_step};
use crate::scripted::{Mode, Script, Scripted};
use crate::{Result, TaskError};

/// Parameters of the demonstrator.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OracleConfig {
    /// Distance of the first box to its target at which the demonstrator turns to the second.
    pub switch_distance: f32,
    /// Mean reversion `κ` per step of the Ornstein–Uhlenbeck perturbation (in `(0, 1]`).
    pub ou_reversion: f32,
    /// Stationary standard deviation of each perturbation component, relative to the step.
    pub ou_std: f32,
    /// Half-width of the relative per-episode variation of the speed caps.
    pub speed_jitter: f32,
    /// Always demonstrate this mode instead of drawing one uniformly.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fixed_mode: Option<PushingMode>,
}

impl Default for OracleConfig {
    fn default() -> Self {
        Self {
            switch_distance: 0.04,
            ou_reversion: 0.1,
            ou_std: 0.15,
            speed_jitter: 0.1,
            fixed_mode: None,
        }
    }
}

impl OracleConfig {
    /// The demonstrator without noise (no perturbation, no speed variation).
    pub fn noise_free() -> Self {
        Self { ou_std: 0.0, speed_jitter: 0.0, ..Self::default() }
    }

    /// Checks every field's range.
    pub fn validate(&self) -> Result<()> {
        if !(self.switch_distance > 0.0 && self.switch_distance <= super::GOAL_TOLERANCE) {
            return Err(TaskError::InvalidArgument(format!(
                "pushing oracle: switch_distance {} must be in (0, 0.05]",
                self.switch_distance
            )));
        }
        check_noise("pushing oracle", self.ou_reversion, self.ou_std, self.speed_jitter)
    }
}

/// The demonstrator's phases.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Phase {
    /// Go to 7 cm behind the box on the line to its target.
    MoveToPreBox,
    /// Go to 4.5 cm behind the box (just clear of it).
    MoveToBox,
    /// Push through a point 2 cm behind the box's centre.
    Push,
    /// Circle the box (counter-clockwise) to twist it.
    OrientLeft,
    /// Circle the box (clockwise) to twist it.
    OrientRight,
    /// After the first box: back to its first pre-box point.
    Retreat,
    /// Then below the second box.
    GoBelow,
}

/// Per-episode state of one environment: the demonstrator's plan.
#[derive(Debug, Clone)]
pub struct EpisodeState {
    mode: PushingMode,
    phase: Phase,
    first_prebox: Option<[f32; 2]>,
    switched: bool,
    speed_scale: f32,
    ou: [f32; 2],
}

/// The scripted demonstrator: a [`Policy`](vdd_core::Policy) for Pushing ([`OBS_DIM`] →
/// [`ACTION_DIM`]), the [`Scripted`] demonstrator of [`OracleScript`]; one plan per
/// environment of a lockstep batch, its own seeded stream.
pub type PushingOracle = Scripted<OracleScript>;

/// The Pushing demonstrator's script: a mode and a speed per episode, then the phases above.
#[derive(Debug, Clone)]
pub struct OracleScript {
    config: OracleConfig,
}

impl Scripted<OracleScript> {
    /// A demonstrator with a validated `config`, seeded with 0.
    pub fn new(config: OracleConfig) -> Result<Self> {
        config.validate()?;
        Ok(Self::with_script(OracleScript { config }))
    }

    /// The configuration.
    pub fn config(&self) -> &OracleConfig {
        &self.script().config
    }

    /// The mode planned for environment (row) `row` of the current episode, once it has acted.
    pub fn planned_mode(&self, row: usize) -> Option<PushingMode> {
        self.plan(row).map(|s| s.mode)
    }

    /// The current phase of environment (row) `row`, once it has acted.
    pub fn phase(&self, row: usize) -> Option<Phase> {
        self.plan(row).map(|s| s.phase)
    }
}

impl Script for OracleScript {
    type Plan = EpisodeState;
    const OBS_DIM: usize = OBS_DIM;
    const ACTION_DIM: usize = ACTION_DIM;
    const STREAM: &'static str = "pushing-oracle";

    fn start(&self, _obs: &[f32], rng: &mut Rng) -> std::result::Result<EpisodeState, CoreError> {
        let modes = (N_MODES, PushingMode::from_index as fn(usize) -> Result<PushingMode>);
        let (mode, speed_scale) =
            draw_episode(self.config.fixed_mode, modes, self.config.speed_jitter, rng)?;
        Ok(EpisodeState {
            mode,
            phase: Phase::MoveToPreBox,
            first_prebox: None,
            switched: false,
            speed_scale,
            ou: [0.0; 2],
        })
    }

    fn act(&self, plan: &mut EpisodeState, rng: &mut Rng, obs: &[f32], action: &mut [f32]) {
        let mut row = [0.0f32; OBS_DIM];
        row.copy_from_slice(obs);
        action.copy_from_slice(&act(&self.config, plan, rng, &row));
    }
}

fn sub(a: [f32; 2], b: [f32; 2]) -> [f32; 2] {
    [a[0] - b[0], a[1] - b[1]]
}

fn norm(a: [f32; 2]) -> f32 {
    a[0].hypot(a[1])
}

fn along(b: [f32; 2], u: [f32; 2], k: f32) -> [f32; 2] {
    [b[0] + k * u[0], b[1] + k * u[1]]
}

/// `x` wrapped into `[−π/4, π/4]` (the box's 4-fold symmetry).
fn wrap_quarter(x: f32) -> f32 {
    let q = std::f32::consts::FRAC_PI_2;
    x - q * (x / q).round()
}

/// Pre-box, next-to-box and pushing points behind the box, and the orienting radius.
const PRE_BOX: f32 = 0.07;
const NEXT_TO_BOX: f32 = 0.045;
const PUSH_POINT: f32 = 0.02;
const ORIENT_RADIUS: f32 = 0.036;
/// Yaw errors (rad): orient before pushing above the first, stop pushing above the second
/// (both inside the 26.6° friction cone of the contact friction 0.5, so a push at the face's
/// centre sticks), stop orienting below the third.
const ORIENT_ABOVE: f32 = 0.35;
const PUSH_ABOVE: f32 = 0.45;
const ORIENTED_BELOW: f32 = 0.1;
/// Speed caps (m/s): free moves, pushing, orienting.
const MOVE_SPEED: f32 = 0.24;
const PUSH_SPEED: f32 = 0.24;
const ORIENT_SPEED: f32 = 0.12;

/// One demonstrator step for one environment.
fn act(c: &OracleConfig, s: &mut EpisodeState, rng: &mut Rng, o: &[f32; OBS_DIM]) -> [f32; 2] {
    let first = s.mode.first();
    let second = 1 - first;
    let box_xy = |k: usize| [o[4 + 4 * k], o[5 + 4 * k]];
    if !s.switched && norm(sub(box_xy(first), TARGETS[s.mode.target_of(first)])) < c.switch_distance
    {
        s.switched = true;
        s.phase = Phase::Retreat;
    }
    let k = if s.switched { second } else { first };
    let (b, t) = (box_xy(k), TARGETS[s.mode.target_of(k)]);
    let yaw = super::yaw_from_encoding(o[6 + 4 * k], o[7 + 4 * k]);
    let ee = [o[0], o[1]];
    let bt = sub(t, b);
    let d = norm(bt).max(1e-6);
    let u = [bt[0] / d, bt[1] / d];
    let theta_error = wrap_quarter(u[1].atan2(u[0]) - yaw);
    let pre_box = along(b, u, -PRE_BOX);
    let mut cap = PUSH_SPEED;
    let mut delta = [0.0f32; 2];
    if s.phase == Phase::MoveToPreBox {
        cap = MOVE_SPEED;
        delta = sub(pre_box, ee);
        if norm(delta) < 0.001 {
            s.phase = Phase::MoveToBox;
            s.first_prebox.get_or_insert(pre_box);
        }
    }
    if s.phase == Phase::Retreat {
        cap = MOVE_SPEED;
        delta = sub(s.first_prebox.unwrap_or(ee), ee);
        if norm(delta) < 0.001 {
            s.phase = Phase::GoBelow;
        }
    }
    if s.phase == Phase::GoBelow {
        cap = MOVE_SPEED;
        let from = s.first_prebox.unwrap_or(ee);
        delta = sub([from[0], from[1].min(b[1] - 0.12)], ee);
        if norm(delta) < 0.001 {
            s.phase = Phase::MoveToPreBox;
        }
    }
    if s.phase == Phase::MoveToBox {
        delta = sub(along(b, u, -NEXT_TO_BOX), ee);
        if norm(delta) < 0.001 {
            s.phase = Phase::Push;
        }
        if theta_error > ORIENT_ABOVE {
            s.phase = Phase::OrientLeft;
        }
        if theta_error < -ORIENT_ABOVE {
            s.phase = Phase::OrientRight;
        }
    }
    if s.phase == Phase::Push {
        if theta_error.abs() > PUSH_ABOVE {
            s.phase = Phase::MoveToPreBox;
        }
        delta = sub(along(b, u, -PUSH_POINT), ee);
    }
    if matches!(s.phase, Phase::OrientLeft | Phase::OrientRight) {
        cap = ORIENT_SPEED;
        let left = s.phase == Phase::OrientLeft;
        let be = sub(ee, b);
        let n = norm(be).max(1e-6);
        let (sn, cs) = (if left { 0.2f32 } else { -0.2f32 }).sin_cos();
        let dir = [(cs * be[0] - sn * be[1]) / n, (sn * be[0] + cs * be[1]) / n];
        delta = sub(along(b, dir, ORIENT_RADIUS), ee);
        if (left && theta_error < ORIENTED_BELOW) || (!left && theta_error > -ORIENTED_BELOW) {
            s.phase = Phase::MoveToPreBox;
        }
    }
    let max_step = cap * s.speed_scale * CONTROL_DT;
    noisy_step(delta, max_step, norm, (c.ou_std, c.ou_reversion), &mut s.ou, rng)
}

/// Pushing's demonstrations: one `T x 12` observation (see the module docs of [`super`]) and
/// `T x 2` action (change of the desired position) matrix per successful episode.
pub type Demonstrations = crate::scripted::Demonstrations<PushingMode>;

impl Mode for PushingMode {
    const COUNT: usize = N_MODES;
    fn index(&self) -> usize {
        PushingMode::index(self)
    }
}

/// Runs the demonstrator until `n` episodes have succeeded and returns them (failed episodes
/// are skipped; [`Demonstrations::success_rate`] reports how many). Episode `i` starts from
/// [`env_seed`](super::env_seed)`(seed, i)` and the demonstrator is seeded with
/// [`episode_seed`](super::rollout::episode_seed)`(seed, i)`, so the result is deterministic
/// ([`crate::d3il::generate_demonstrations`]). More than `2n + 16` episodes without `n`
/// successes is an error.
pub fn generate_demonstrations(
    n: usize,
    seed: u64,
    config: &OracleConfig,
) -> Result<Demonstrations> {
    generate_demonstrations_with(n, seed, config, &EnvConfig::default())
}

/// [`generate_demonstrations`] in an environment with `env` settings.
pub fn generate_demonstrations_with(
    n: usize,
    seed: u64,
    config: &OracleConfig,
    env: &EnvConfig,
) -> Result<Demonstrations> {
    let mut oracle = PushingOracle::new(config.clone())?;
    crate::d3il::generate_demonstrations(&mut oracle, n, seed, env)
}
