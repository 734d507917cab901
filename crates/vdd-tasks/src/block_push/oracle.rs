//! The scripted multimodal Block-Push oracle (after IBC's `oriented_push_oracle` and
//! `multimodal_push_oracle`) with human-like noise, and demonstration generation.
//!
//! # What the oracle does
//!
//! It acts on the observation alone (plus its per-episode state). At the first call after
//! [`Policy::reset`](vdd_core::Policy::reset) it draws one of the four orders uniformly from its
//! own seeded stream (or uses [`OracleConfig::fixed_mode`]): first block → first target, then the
//! other block → the other target; it stores the commanded effector target as its `origin`.
//! Then, with `ee` = the commanded target (obs 10–11), `b` the current block, `t` its target,
//! `u = (t − b)/|t − b|` and `θ_err = atan2(u) − yaw` wrapped into `[−π/4, π/4]`, the phases
//! (checked one after another in the same call, as in the original) are:
//!
//! | phase | aims at | speed cap | leaves when |
//! |---|---|---|---|
//! | `MoveToPreBlock` | `b − 0.05u` | 0.30 m/s | within 1 mm → `MoveToBlock` (first time: store `first_preblock`) |
//! | `MoveToBlock` | `b − 0.03u` | 0.35 m/s | within 1 mm → `Push`; `θ_err > 0.2` → `OrientLeft`, `< −0.2` → `OrientRight` |
//! | `Push` | `b − 0.01u` (inside the block) | 0.35 m/s | `|θ_err| > 0.2` → `MoveToPreBlock` |
//! | `OrientLeft/Right` | `b + 0.025·R(±0.2)·dir(b → ee)` | 0.15 m/s | `θ_err < 0.03` (left) / `> −0.03` (right) → `MoveToPreBlock` |
//! | `ReturnToFirstPreBlock` | `first_preblock` | 0.30 m/s | within 1 mm → `ReturnToOrigin` |
//! | `ReturnToOrigin` | `origin` | 0.30 m/s | within 1 mm → `MoveToPreBlock` (second block) |
//!
//! When the first block is within [`OracleConfig::switch_distance`] `= 0.04` of its target,
//! the oracle switches to the second pair through the two return phases (the detour keeps it
//! from knocking the first block out).
//!
//! # Human-like noise (not in the original, whose demonstrations are noise-free)
//!
//! * Each step `Δ` (already clipped to the phase's cap) is perturbed by `|Δ| · e_t`, where
//!   `e_t` is a 2-D Ornstein–Uhlenbeck process `e_t = (1 − κ) e_{t−1} + σ ξ_t` with
//!   `κ =` [`OracleConfig::ou_reversion`] and stationary standard deviation
//!   [`OracleConfig::ou_std`] per component: smooth, slowly wandering deviations proportional
//!   to the motion, which vanish near the waypoints so that the 1 mm phase switches still
//!   happen. The result is clipped to the cap again.
//! * Each episode's caps are scaled by a factor drawn from
//!   `U(1 − speed_jitter, 1 + speed_jitter)` (so at most 0.385 m/s by default, below the
//!   pusher's 0.5 m/s).
//!
//! The measured success, mode spread and episode lengths are in the module docs of [`super`].
//!
//! ```
//! use vdd_tasks::block_push::oracle::{generate_demonstrations, OracleConfig};
//! let demos = generate_demonstrations(4, 0, &OracleConfig::default()).unwrap();
//! assert_eq!(demos.observations.len(), 4);
//! assert_eq!(demos.mode_counts().iter().sum::<usize>(), 4);
//! ```

use rand::Rng as _;
use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Rng, standard_normal};

use super::rollout::episode_seed;
use super::{
    ACTION_DIM, BlockPushEnv, BlockPushMode, CONTROL_DT, EnvConfig, N_MODES, OBS_DIM, env_seed,
};
use crate::scripted::{Mode, Script, Scripted, collect};
use crate::{Result, TaskError};

/// Parameters of the oracle.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct OracleConfig {
    /// Distance of the first block to its target at which the oracle turns to the second.
    pub switch_distance: f32,
    /// Mean reversion `κ` per step of the Ornstein–Uhlenbeck perturbation (in `(0, 1]`).
    pub ou_reversion: f32,
    /// Stationary standard deviation of each perturbation component, relative to the step.
    pub ou_std: f32,
    /// Half-width of the relative per-episode variation of the speed caps.
    pub speed_jitter: f32,
    /// Always demonstrate this order instead of drawing one uniformly.
    pub fixed_mode: Option<BlockPushMode>,
}

impl Default for OracleConfig {
    fn default() -> Self {
        Self {
            switch_distance: 0.04,
            ou_reversion: 0.15,
            ou_std: 0.15,
            speed_jitter: 0.1,
            fixed_mode: None,
        }
    }
}

impl OracleConfig {
    /// The noise-free oracle of the original (no perturbation, no speed variation).
    pub fn noise_free() -> Self {
        Self { ou_std: 0.0, speed_jitter: 0.0, ..Self::default() }
    }

    /// Checks every field's range.
    pub fn validate(&self) -> Result<()> {
        let bad = |m: String| Err(TaskError::InvalidArgument(format!("block-push oracle: {m}")));
        if !(self.switch_distance > 0.0 && self.switch_distance <= super::GOAL_TOLERANCE) {
            return bad(format!("switch_distance {} must be in (0, 0.05]", self.switch_distance));
        }
        if !(self.ou_reversion > 0.0 && self.ou_reversion <= 1.0) {
            return bad(format!("ou_reversion {} must be in (0, 1]", self.ou_reversion));
        }
        if !(self.ou_std >= 0.0 && self.ou_std <= 1.0) {
            return bad(format!("ou_std {} must be in [0, 1]", self.ou_std));
        }
        if !(self.speed_jitter >= 0.0 && self.speed_jitter <= 0.4) {
            return bad(format!("speed_jitter {} must be in [0, 0.4]", self.speed_jitter));
        }
        Ok(())
    }
}

/// The oracle's phases.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Phase {
    /// Go to 5 cm behind the block on the line to its target.
    MoveToPreBlock,
    /// Go to 3 cm behind the block.
    MoveToBlock,
    /// Push through a point 1 cm behind the block's centre.
    Push,
    /// Circle the block (counter-clockwise) to twist it.
    OrientLeft,
    /// Circle the block (clockwise) to twist it.
    OrientRight,
    /// After the first block: back to the first pre-block point.
    ReturnToFirstPreBlock,
    /// Then back to the start.
    ReturnToOrigin,
}

/// Per-episode state of one environment: the oracle's plan.
#[derive(Debug, Clone)]
pub struct EpisodeState {
    order: BlockPushMode,
    phase: Phase,
    origin: [f32; 2],
    first_preblock: Option<[f32; 2]>,
    switched: bool,
    speed_scale: f32,
    ou: [f32; 2],
}

/// The scripted multimodal oracle: a [`Policy`](vdd_core::Policy) for Block-Push
/// ([`OBS_DIM`] → [`ACTION_DIM`]), the [`Scripted`] demonstrator of [`OracleScript`].
///
/// Like the Avoiding demonstrator it keeps one state per environment between
/// [`Policy::reset`](vdd_core::Policy::reset)s
/// ([`Policy::act_batch`](vdd_core::Policy::act_batch) row `i` is environment `i`), and draws
/// from its own stream, which [`Policy::seed`](vdd_core::Policy::seed) resets.
pub type BlockPushOracle = Scripted<OracleScript>;

/// The Block-Push oracle's script: an order and a speed per episode, then the phases above.
#[derive(Debug, Clone)]
pub struct OracleScript {
    config: OracleConfig,
}

impl Scripted<OracleScript> {
    /// An oracle with a validated `config`, seeded with 0.
    pub fn new(config: OracleConfig) -> Result<Self> {
        config.validate()?;
        Ok(Self::with_script(OracleScript { config }))
    }

    /// The configuration.
    pub fn config(&self) -> &OracleConfig {
        &self.script().config
    }

    /// The order planned for environment (row) `row` of the current episode, once it has acted.
    pub fn planned_mode(&self, row: usize) -> Option<BlockPushMode> {
        self.plan(row).map(|s| s.order)
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
    const STREAM: &'static str = "block-push-oracle";

    fn start(&self, obs: &[f32], rng: &mut Rng) -> std::result::Result<EpisodeState, CoreError> {
        let order = match self.config.fixed_mode {
            Some(m) => m,
            None => BlockPushMode::from_index(rng.random_range(0..N_MODES))
                .map_err(CoreError::implementor)?,
        };
        let j = self.config.speed_jitter;
        let speed_scale = 1.0 + j * (2.0 * rng.random::<f32>() - 1.0);
        Ok(EpisodeState {
            order,
            phase: Phase::MoveToPreBlock,
            origin: [obs[10], obs[11]],
            first_preblock: None,
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

/// `x` wrapped into `[−π/4, π/4]` (the block's 4-fold symmetry).
fn wrap_quarter(x: f32) -> f32 {
    let q = std::f32::consts::FRAC_PI_2;
    x - q * (x / q).round()
}

/// One oracle step for one environment.
fn act(c: &OracleConfig, s: &mut EpisodeState, rng: &mut Rng, o: &[f32; OBS_DIM]) -> [f32; 2] {
    let (first, second) =
        (s.order, BlockPushMode { block: 1 - s.order.block, target: 1 - s.order.target });
    let block_xy = |k: usize| [o[4 * k], o[4 * k + 1]];
    let target_xy = |k: usize| [o[12 + 2 * k], o[13 + 2 * k]];
    if !s.switched
        && norm(sub(block_xy(first.block()), target_xy(first.target()))) < c.switch_distance
    {
        s.switched = true;
        s.phase = Phase::ReturnToFirstPreBlock;
    }
    let cur = if s.switched { second } else { first };
    let (k, b, t) = (cur.block(), block_xy(cur.block()), target_xy(cur.target()));
    let yaw = super::yaw_from_encoding(o[4 * k + 2], o[4 * k + 3]);
    let ee = [o[10], o[11]];
    let bt = sub(t, b);
    let d = norm(bt).max(1e-6);
    let u = [bt[0] / d, bt[1] / d];
    let theta_error = wrap_quarter(u[1].atan2(u[0]) - yaw);
    let pre_block = along(b, u, -0.05);
    let mut cap = 0.35;
    let mut delta = [0.0f32; 2];
    if s.phase == Phase::MoveToPreBlock {
        cap = 0.30;
        delta = sub(pre_block, ee);
        if norm(delta) < 0.001 {
            s.phase = Phase::MoveToBlock;
            s.first_preblock.get_or_insert(pre_block);
        }
    }
    if s.phase == Phase::ReturnToFirstPreBlock {
        cap = 0.30;
        delta = sub(s.first_preblock.unwrap_or(s.origin), ee);
        if norm(delta) < 0.001 {
            s.phase = Phase::ReturnToOrigin;
        }
    }
    if s.phase == Phase::ReturnToOrigin {
        cap = 0.30;
        delta = sub(s.origin, ee);
        if norm(delta) < 0.001 {
            s.phase = Phase::MoveToPreBlock;
        }
    }
    if s.phase == Phase::MoveToBlock {
        delta = sub(along(b, u, -0.03), ee);
        if norm(delta) < 0.001 {
            s.phase = Phase::Push;
        }
        if theta_error > 0.2 {
            s.phase = Phase::OrientLeft;
        }
        if theta_error < -0.2 {
            s.phase = Phase::OrientRight;
        }
    }
    if s.phase == Phase::Push {
        if theta_error.abs() > 0.2 {
            s.phase = Phase::MoveToPreBlock;
        }
        delta = sub(along(b, u, -0.01), ee);
    }
    if matches!(s.phase, Phase::OrientLeft | Phase::OrientRight) {
        cap = 0.15;
        let left = s.phase == Phase::OrientLeft;
        let be = sub(ee, b);
        let n = norm(be).max(1e-6);
        let (sn, cs) = (if left { 0.2f32 } else { -0.2f32 }).sin_cos();
        let dir = [(cs * be[0] - sn * be[1]) / n, (sn * be[0] + cs * be[1]) / n];
        delta = sub(along(b, dir, 0.025), ee);
        if (left && theta_error < 0.03) || (!left && theta_error > -0.03) {
            s.phase = Phase::MoveToPreBlock;
        }
    }
    let max_step = cap * s.speed_scale * CONTROL_DT;
    let clip = |d: [f32; 2]| {
        let n = norm(d);
        if n > max_step { [d[0] * max_step / n, d[1] * max_step / n] } else { d }
    };
    let delta = clip(delta);
    if c.ou_std == 0.0 {
        return delta;
    }
    // Stationary std of e = (1 − κ) e + σ ξ is σ / sqrt(1 − (1 − κ)²).
    let keep = 1.0 - c.ou_reversion;
    let sigma = c.ou_std * (1.0 - keep * keep).sqrt();
    for e in &mut s.ou {
        *e = keep * *e + sigma * standard_normal(rng);
    }
    let m = norm(delta);
    clip([delta[0] + m * s.ou[0], delta[1] + m * s.ou[1]])
}

/// Block-Push's demonstrations: one `T x 16` observation (see the module docs of [`super`])
/// and `T x 2` action (change of the commanded effector target) matrix per successful episode.
pub type Demonstrations = crate::scripted::Demonstrations<BlockPushMode>;

impl Mode for BlockPushMode {
    const COUNT: usize = N_MODES;
    fn index(&self) -> usize {
        BlockPushMode::index(self)
    }
}

/// Runs the oracle until `n` episodes have succeeded and returns them (failed episodes are
/// skipped; [`Demonstrations::success_rate`] reports how many). Episode `i` starts from
/// [`env_seed`]`(seed, i)` and the oracle is seeded with [`episode_seed`]`(seed, i)`, so the
/// result is deterministic. More than `2n + 16` episodes without `n` successes is an error.
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
    let mut oracle = BlockPushOracle::new(config.clone())?;
    env.validate()?;
    let seeds = |i| (episode_seed(seed, i), env_seed(seed, i));
    let kept = |r: &super::rollout::Rollout| r.success().then_some(r.info.mode).flatten();
    collect::<BlockPushEnv, _, _>(&mut oracle, env.clone(), (n, env.max_steps), seeds, kept)
}
