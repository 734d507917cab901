//! The scripted Aligning demonstrator (D3IL's demonstrations are human teleoperation, not in the
//! repository; this script stands in for the operator) with human-like noise, and
//! demonstration generation.
//!
//! # What the demonstrator does
//!
//! It acts on the observation alone (plus its per-episode state). At the first call after
//! [`Policy::reset`](vdd_core::Policy::reset) it draws the mode, inside or outside, uniformly
//! from its own seeded stream (or uses [`OracleConfig::fixed_mode`]). Each step it picks a
//! *goal* and from it a contact point on a wall (in the tray's frame) and a push direction:
//!
//! * **Rotate** while the yaw error `e_θ = wrap(φ − θ)` exceeds [`ROT_START`] (0.12 rad near the
//!   target, 0.3 farther than 5 cm) until it is below [`ROT_DONE`]: push one wall
//!   perpendicularly near its end (off-centre, so the tray turns), from inside on an inner face
//!   or from outside on an outer face; of the four walls, the one whose push moves the tray most
//!   towards the target, at the end that turns it the right way.
//! * **Translate** otherwise: push through the tray's centre towards the target, from behind
//!   (outside) or from the inner wall ahead (inside), the contact shifted sideways by
//!   `−0.12 · e_θ` (at most 2 cm) so that the push also corrects the yaw; the speed drops near
//!   the target (2 /s times the distance, between 0.04 and 0.24 m/s).
//!
//! The phases move the rod to the contact:
//!
//! | phase | does | leaves when |
//! |---|---|---|
//! | `Approach` | lifted (tip at 0.12), to the pre-contact point 2 cm before the contact | within 3 mm → `Lower` |
//! | `Lower` | lowers the tip to the table over the pre-contact point | desired height ≤ 2 mm → `Move` |
//! | `Move` | lowered, to the pre-contact point; outside, if the straight way crosses the tray → `Lift` | within 3 mm → `Push` |
//! | `Push` | aims 1.5 cm beyond the contact (the rod is kinematic: the tray gives way) | goal changed or contact lost (> 3 cm) → `Move` |
//! | `Lift` | raises the tip to 0.12 | → `Approach` |
//!
//! Inside, the pre-contact point is halfway between the tray's centre and the contact, in the
//! inner clear square, so the rod moves between contacts without lifting. A rod that came to
//! rest on a wall top (its tip above half the wall height while lowered) lifts and tries again.
//!
//! # Human-like noise
//!
//! Pushing's ([`crate::pushing::oracle`]): each step `Δ` (3-D, clipped to the phase's speed
//! cap) is perturbed by `|Δ| · e_t`, `e_t` an Ornstein–Uhlenbeck process with mean reversion
//! [`OracleConfig::ou_reversion`] per step and stationary standard deviation
//! [`OracleConfig::ou_std`]; each episode's caps are scaled by a factor from
//! `U(1 − speed_jitter, 1 + speed_jitter)`.
//!
//! ```
//! use vdd_tasks::aligning::oracle::{generate_demonstrations, OracleConfig};
//! let demos = generate_demonstrations(2, 0, &OracleConfig::default()).unwrap();
//! assert_eq!(demos.observations.len(), 2);
//! assert_eq!(demos.mode_counts().iter().sum::<usize>(), 2);
//! ```

use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Rng};

use super::{
    ACTION_DIM, AligningMode, CONTROL_DT, EnvConfig, N_MODES, OBS_DIM, PUSHER_RADIUS,
    TRAY_INNER_HALF, TRAY_OUTER_HALF, wrap_angle,
};
use crate::Result;
use crate::d3il::{check_noise, draw_episode, noisy_step};
use crate::scripted::{Mode, Script, Scripted};

/// Parameters of the demonstrator.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct OracleConfig {
    /// Mean reversion `κ` per step of the Ornstein–Uhlenbeck perturbation (in `(0, 1]`).
    pub ou_reversion: f32,
    /// Stationary standard deviation of each perturbation component, relative to the step.
    pub ou_std: f32,
    /// Half-width of the relative per-episode variation of the speed caps.
    pub speed_jitter: f32,
    /// Always demonstrate this mode instead of drawing one uniformly.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub fixed_mode: Option<AligningMode>,
}

impl Default for OracleConfig {
    fn default() -> Self {
        Self { ou_reversion: 0.1, ou_std: 0.15, speed_jitter: 0.1, fixed_mode: None }
    }
}

impl OracleConfig {
    /// The demonstrator without noise (no perturbation, no speed variation).
    pub fn noise_free() -> Self {
        Self { ou_std: 0.0, speed_jitter: 0.0, ..Self::default() }
    }

    /// Checks every field's range.
    pub fn validate(&self) -> Result<()> {
        check_noise("aligning oracle", self.ou_reversion, self.ou_std, self.speed_jitter)
    }
}

/// The demonstrator's phases.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Phase {
    /// Lifted, to above the pre-contact point.
    Approach,
    /// Lowering the tip to the table.
    Lower,
    /// Lowered, to the pre-contact point.
    Move,
    /// Pushing the wall.
    Push,
    /// Raising the tip above the walls.
    Lift,
}

/// What the demonstrator is doing to the tray.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum Goal {
    /// Turning it by pushing wall `wall` (0 `+x`, 1 `+y`, 2 `−x`, 3 `−y` of the tray's frame)
    /// near its end; `sign` +1 turns it counter-clockwise.
    Rotate {
        /// The wall pushed.
        wall: usize,
        /// +1 counter-clockwise, −1 clockwise.
        sign: f32,
    },
    /// Pushing it through its centre towards the target.
    Translate,
}

/// Per-episode state of one environment: the demonstrator's plan.
#[derive(Debug, Clone)]
pub struct EpisodeState {
    mode: AligningMode,
    phase: Phase,
    goal: Goal,
    speed_scale: f32,
    ou: [f32; 3],
}

/// The scripted demonstrator: a [`Policy`](vdd_core::Policy) for Aligning ([`OBS_DIM`] →
/// [`ACTION_DIM`]), the [`Scripted`] demonstrator of [`OracleScript`].
pub type AligningOracle = Scripted<OracleScript>;

/// The Aligning demonstrator's script: a mode and a speed per episode, then the phases above.
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
    pub fn planned_mode(&self, row: usize) -> Option<AligningMode> {
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
    const STREAM: &'static str = "aligning-oracle";

    fn start(&self, _obs: &[f32], rng: &mut Rng) -> std::result::Result<EpisodeState, CoreError> {
        let modes = (N_MODES, AligningMode::from_index as fn(usize) -> Result<AligningMode>);
        let (mode, speed_scale) =
            draw_episode(self.config.fixed_mode, modes, self.config.speed_jitter, rng)?;
        Ok(EpisodeState {
            mode,
            phase: Phase::Approach,
            goal: Goal::Translate,
            speed_scale,
            ou: [0.0; 3],
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

fn add_scaled(a: [f32; 2], u: [f32; 2], k: f32) -> [f32; 2] {
    [a[0] + k * u[0], a[1] + k * u[1]]
}

/// `v` rotated by the angle with sine `s` and cosine `c`.
fn rotate(v: [f32; 2], s: f32, c: f32) -> [f32; 2] {
    [c * v[0] - s * v[1], s * v[0] + c * v[1]]
}

/// The larger absolute coordinate (the square's norm).
fn chebyshev(v: [f32; 2]) -> f32 {
    v[0].abs().max(v[1].abs())
}

/// Yaw errors (rad): rotate above `ROT_START` (near the target; far from it, above
/// `ROT_START_FAR`), until below `ROT_DONE`.
pub const ROT_START: f32 = 0.12;
/// Far from the target (more than [`NEAR`]), rotate above this yaw error.
pub const ROT_START_FAR: f32 = 0.3;
/// Rotate until the yaw error is below this.
pub const ROT_DONE: f32 = 0.04;
/// Distance to the target below which [`ROT_START`] applies.
pub const NEAR: f32 = 0.05;
/// Contact offset from a wall's middle when rotating (outside, inside).
const ROT_OFFSET: [f32; 2] = [0.045, 0.034];
/// Sideways contact shift per radian of yaw error when translating, and its bound.
const STEER_GAIN: f32 = 0.12;
const STEER_MAX: f32 = 0.02;
/// Distance of the pre-contact point before the contact, and the push depth beyond it.
const PRE_CONTACT: f32 = 0.02;
const PUSH_DEPTH: f32 = 0.015;
/// Tip height while lifted.
const LIFT_HEIGHT: f32 = 0.12;
/// Speed caps (m/s): free moves, rotating pushes, translating pushes (and its floor), and the
/// gain of the translating push's speed on the distance (1/s).
const MOVE_SPEED: f32 = 0.24;
const ROT_SPEED: f32 = 0.15;
const PUSH_SPEED: f32 = 0.24;
const PUSH_SPEED_MIN: f32 = 0.04;
const PUSH_GAIN: f32 = 2.0;

/// The contact of `goal` in world coordinates (the rod's centre touching the wall) and the
/// push direction, for the tray at `c` with yaw `(s, cs)`, the target direction `u` and the
/// yaw error `e_yaw`.
fn contact(
    goal: Goal,
    inside: bool,
    c: [f32; 2],
    (s, cs): (f32, f32),
    u: [f32; 2],
    e_yaw: f32,
) -> ([f32; 2], [f32; 2]) {
    let r = PUSHER_RADIUS;
    let reach = if inside { TRAY_INNER_HALF - r } else { TRAY_OUTER_HALF + r };
    match goal {
        Goal::Rotate { wall, sign } => {
            let n = [[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]][wall.min(3)];
            let t = [-n[1], n[0]];
            let tau = if inside { -sign * ROT_OFFSET[1] } else { sign * ROT_OFFSET[0] };
            let p = add_scaled([n[0] * reach, n[1] * reach], t, tau);
            let d = if inside { n } else { [-n[0], -n[1]] };
            (add_scaled(c, rotate(p, s, cs), 1.0), rotate(d, s, cs))
        }
        Goal::Translate => {
            let v = if inside { u } else { [-u[0], -u[1]] };
            let w = [-u[1], u[0]];
            let shift = (-STEER_GAIN * e_yaw).clamp(-STEER_MAX, STEER_MAX);
            // The distance along `v` at which the shifted point reaches the wall (tray frame).
            let at = |k: f32| chebyshev(rotate(add_scaled([k * v[0], k * v[1]], w, shift), -s, cs));
            let (mut lo, mut hi) = (0.0f32, 0.2f32);
            for _ in 0..24 {
                let mid = 0.5 * (lo + hi);
                if at(mid) < reach { lo = mid } else { hi = mid }
            }
            let p = add_scaled([lo * v[0], lo * v[1]], w, shift);
            (add_scaled(c, p, 1.0), u)
        }
    }
}

/// The wall (and turning sign) of a rotation: the wall whose push moves the tray most towards
/// the target direction `u` (any, near the target).
fn rotation_goal(inside: bool, (s, cs): (f32, f32), u: [f32; 2], e_yaw: f32) -> Goal {
    let mut best = (0, f32::NEG_INFINITY);
    for wall in 0..4 {
        let score = push_score(inside, (s, cs), u, wall);
        if score > best.1 {
            best = (wall, score);
        }
    }
    Goal::Rotate { wall: best.0, sign: if e_yaw >= 0.0 { 1.0 } else { -1.0 } }
}

/// How far a push on wall `wall` moves the tray along `u` (the cosine of their angle).
fn push_score(inside: bool, (s, cs): (f32, f32), u: [f32; 2], wall: usize) -> f32 {
    let n = [[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]][wall.min(3)];
    let d = rotate(if inside { n } else { [-n[0], -n[1]] }, s, cs);
    d[0] * u[0] + d[1] * u[1]
}

/// Whether the straight way from `from` to `to` passes through the tray at `c` (yaw `(s, cs)`).
fn crosses_tray(from: [f32; 2], to: [f32; 2], c: [f32; 2], (s, cs): (f32, f32)) -> bool {
    (1..=16).any(|i| {
        let p = add_scaled(from, sub(to, from), i as f32 / 16.0);
        chebyshev(rotate(sub(p, c), -s, cs)) < TRAY_OUTER_HALF + PUSHER_RADIUS - 0.004
    })
}

/// One demonstrator step for one environment.
fn act(c: &OracleConfig, st: &mut EpisodeState, rng: &mut Rng, o: &[f32; OBS_DIM]) -> [f32; 3] {
    let inside = st.mode == AligningMode::Inside;
    let (ee, h_des) = ([o[0], o[1]], o[2]);
    let tray = [o[6], o[7]];
    let yaw = (o[8], o[9]);
    let target = [o[10], o[11]];
    let e_yaw = wrap_angle(o[12].atan2(o[13]) - o[8].atan2(o[9]));
    let e = sub(target, tray);
    let dist = norm(e);
    let u = if dist > 1e-6 { [e[0] / dist, e[1] / dist] } else { [0.0, 1.0] };
    // The goal.
    let start = if dist < NEAR { ROT_START } else { ROT_START_FAR };
    let goal = match st.goal {
        Goal::Rotate { .. } if e_yaw.abs() < ROT_DONE => Goal::Translate,
        Goal::Rotate { sign, .. } if sign * e_yaw < 0.0 => rotation_goal(inside, yaw, u, e_yaw),
        Goal::Rotate { wall, .. } if dist > NEAR && push_score(inside, yaw, u, wall) < 0.0 => {
            rotation_goal(inside, yaw, u, e_yaw)
        }
        Goal::Translate if e_yaw.abs() > start => rotation_goal(inside, yaw, u, e_yaw),
        g => g,
    };
    if goal != st.goal {
        st.goal = goal;
        if st.phase == Phase::Push {
            st.phase = Phase::Move;
        }
    }
    let (cp, d) = contact(st.goal, inside, tray, yaw, u, e_yaw);
    // Inside, halfway between the tray's centre and the contact (clear of every wall).
    let pre =
        if inside { add_scaled(tray, sub(cp, tray), 0.5) } else { add_scaled(cp, d, -PRE_CONTACT) };
    // Resting on a wall top instead of the table: lift and try again.
    if matches!(st.phase, Phase::Move | Phase::Push) && o[5] > 0.5 * super::WALL_TOP {
        st.phase = Phase::Lift;
    }
    let mut cap = MOVE_SPEED;
    let mut aim = (ee, 0.0f32);
    if st.phase == Phase::Lift {
        aim = (ee, LIFT_HEIGHT);
        if h_des >= LIFT_HEIGHT - 0.002 {
            st.phase = Phase::Approach;
        }
    }
    if st.phase == Phase::Approach {
        aim = (pre, LIFT_HEIGHT);
        if norm(sub(pre, ee)) < 0.003 {
            st.phase = Phase::Lower;
        }
    }
    if st.phase == Phase::Lower {
        aim = (pre, 0.0);
        if h_des <= 0.002 {
            st.phase = Phase::Move;
        }
    }
    if st.phase == Phase::Move {
        aim = (pre, 0.0);
        if !inside && crosses_tray(ee, pre, tray, yaw) {
            st.phase = Phase::Lift;
            aim = (ee, LIFT_HEIGHT);
        } else if norm(sub(pre, ee)) < 0.003 {
            st.phase = Phase::Push;
        }
    }
    if st.phase == Phase::Push {
        if norm(sub(cp, ee)) > 0.03 {
            st.phase = Phase::Move;
            aim = (pre, 0.0);
        } else {
            aim = (add_scaled(cp, d, PUSH_DEPTH), 0.0);
            cap = match st.goal {
                Goal::Rotate { .. } => ROT_SPEED,
                Goal::Translate => (PUSH_GAIN * dist).clamp(PUSH_SPEED_MIN, PUSH_SPEED),
            };
        }
    }
    let delta = [aim.0[0] - ee[0], aim.0[1] - ee[1], aim.1 - h_des];
    let max_step = cap * st.speed_scale * CONTROL_DT;
    let norm3 = |d: [f32; 3]| (d[0] * d[0] + d[1] * d[1] + d[2] * d[2]).sqrt();
    noisy_step(delta, max_step, norm3, (c.ou_std, c.ou_reversion), &mut st.ou, rng)
}

/// Aligning's demonstrations: one `T x 14` observation and `T x 3` action (change of the
/// desired position) matrix per successful episode.
pub type Demonstrations = crate::scripted::Demonstrations<AligningMode>;

impl Mode for AligningMode {
    const COUNT: usize = N_MODES;
    fn index(&self) -> usize {
        AligningMode::index(self)
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
    let mut oracle = AligningOracle::new(config.clone())?;
    crate::d3il::generate_demonstrations(&mut oracle, n, seed, env)
}
