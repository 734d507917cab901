//! Multimodal Block-Push (after the IBC / Diffusion Policy / BET / BESO / VDD task) on a 2-D
//! rigid-body engine (`rapier2d`): a round pusher seen from above pushes two square blocks into
//! two target zones, one block per zone; which block goes first and to which zone gives the
//! four behaviour modes.
//!
//! # Facts copied from the original (`docs/contact-tasks.md`, section 5; metres, radians)
//!
//! * Two square blocks of side [`BLOCK_SIZE`] `= 0.04` and mass 0.01 kg. Two target zones
//!   (visual only, no collision).
//! * Control at 10 Hz ([`CONTROL_DT`] `= 0.1` s). The action is the change `Δ` of the
//!   *commanded* effector target `xy`; the new target is clipped to the workspace
//!   [`WORKSPACE`]: `x ∈ [0.15, 0.70]`, `y ∈ [−0.50, 0.50]`.
//! * Reset: effector (and its commanded target) at [`EFFECTOR_START`] `= (0.30, −0.40)`;
//!   each block at `x = 0.4 + U(±0.1)`, `y = −0.2 + U(±0.15)`, both redrawn until
//!   `|x₀ − x₁| > 0.1` (only `x` is compared, as in the original). Targets: a coin flip
//!   `add = ±0.12`; target 0 at `x = 0.4 + add + U(±0.005)`, target 1 at
//!   `x = 0.4 − add + U(±0.005)`, both at `y = 0.2 + U(±0.0075)` (which zone is left is the
//!   coin flip).
//! * Success (p2): both blocks closer than [`GOAL_TOLERANCE`] `= 0.05` to *distinct* targets;
//!   it ends the episode. p1: at least one block came closer than 0.05 to a target at some
//!   step. Time limit [`MAX_STEPS`] `= 350` steps (Diffusion Policy's), configurable.
//! * Mode ([`BlockPushMode`]): the first `(block, target)` pair that came within 0.05 (the
//!   original's first `TARGET_i_j` event); for a success the other block went to the other
//!   target, so the four modes are the four orders of the oracle.
//!
//! # Observation ([`OBS_DIM`] = 16)
//!
//! The original's 16-D layout with two changes: each block's raw yaw becomes
//! `(sin 4θ, cos 4θ)`, continuous and invariant under the block's 4-fold symmetry (the oracle
//! recovers `θ mod π/2` from it); the targets' yaws (visual only, never used by success or the
//! oracle) are dropped, so the dimension stays 16.
//!
//! | idx | field |
//! |---|---|
//! | 0–1 | block 0 `xy` |
//! | 2–3 | block 0 `sin 4θ₀, cos 4θ₀` |
//! | 4–5 | block 1 `xy` |
//! | 6–7 | block 1 `sin 4θ₁, cos 4θ₁` |
//! | 8–9 | effector `xy` (measured: the pusher's position) |
//! | 10–11 | effector *target* `xy` (commanded) |
//! | 12–13 | target 0 `xy` |
//! | 14–15 | target 1 `xy` |
//!
//! # Choices this crate makes (not fixed by the original)
//!
//! * **Table friction.** The plane is top-down with zero gravity; rapier has no table, so
//!   sliding friction is applied by hand before every substep as a Coulomb-like deceleration
//!   of each block's speed ([`PhysicsConfig::friction_decel`], default `μg = 9.81` m/s², the
//!   original's lateral friction 1) and spin ([`PhysicsConfig::spin_decel`], 250 rad/s²),
//!   never reversing the velocity, plus a light linear and angular damping (2 /s). A pushed
//!   block therefore moves with the pusher and stops once the pusher leaves, after sliding
//!   `v²/2μg` (6 mm from the oracle's fastest 0.35 m/s): quasi-static pushing, as on the
//!   original's table. Contact friction pusher–block and block–block is 0.5.
//! * **Pusher.** A disc of radius [`PUSHER_RADIUS`] `= 0.008` (the original's suction head is
//!   0.005; a little more keeps contact robust) on a kinematic, position-based body. In each
//!   substep it moves straight towards the commanded target by at most
//!   [`PhysicsConfig::pusher_speed`] `· dt` (default 0.5 m/s, above the oracle's fastest 0.35
//!   m/s), i.e. a position servo with a speed limit; it is not stopped by the blocks.
//! * **Substeps.** [`PhysicsConfig::substeps`] physics steps of `0.1 / substeps` s per
//!   control step (default 24, i.e. 1/240 s as in PyBullet).
//! * **Yaw at reset** is uniform in `[0, π/2)`: with the 4-fold symmetry every orientation
//!   is covered, uniformly (the original's `uniform(π)` quirk draws from `(1, π]`).
//! * **Action bounds.** Each action component is clipped to `±`[`ACTION_LIMIT`] `= 0.1` (the
//!   original's declared action space) before the commanded target is moved and clipped to the
//!   workspace. Non-finite actions are errors.
//! * **No walls**: blocks may leave the workspace; the pusher cannot (its target is clipped).
//! * **Determinism.** `rapier2d` is built with `enhanced-determinism` and run single-threaded,
//!   one world per environment: the same seed gives a bit-identical episode on any thread.
//!
//! # Measured (release build, 2-core machine shared with other jobs)
//!
//! `cargo run --release -p vdd-tasks --example block_push_oracle -- 200` (the noisy oracle,
//! [`oracle::OracleConfig::default`], per-episode stepping, evaluation seed 0):
//!
//! | substeps | success (p2) | p1 | task entropy | modes `[b0→t0, b0→t1, b1→t0, b1→t1]` | steps mean / max | µs per env step |
//! |---|---|---|---|---|---|---|
//! | **24** (default) | **1.000** | 1.000 | 0.997 | `[56, 50, 50, 44]` | 124.7 / 184 | ≈ 57 |
//! | 12 | 1.000 | 1.000 | 0.998 | `[55, 50, 51, 44]` | 136.9 / 216 | ≈ 35 |
//! | 8 | 1.000 | 1.000 | 0.998 | `[55, 50, 51, 44]` | 155.5 / 253 | ≈ 21 |
//! | 6 | 1.000 | 1.000 | 0.998 | `[55, 50, 51, 44]` | 169.4 / 281 | ≈ 18 |
//!
//! Over 1000 episodes (seed 1, 24 substeps): success 0.993 (7 timeouts), p1 0.999, entropy
//! 0.999, modes `[269, 244, 253, 227]`, mean 123.2 / max 206 steps of successes; identical with
//! 1 and 2 threads. The noise-free oracle (the original's, [`oracle::OracleConfig::noise_free`]):
//! success 1.000 over 200, mean 102.5 / max 181 steps. For comparison, the original's BET
//! dataset has mean 116.8 / max 201 steps (under a 200-step cap). Fewer substeps keep the
//! success but lengthen the episodes (the cause was not investigated); 24 is kept to match
//! PyBullet's 1/240 s. The µs include the oracle's own step (a few dozen arithmetic operations).
//!
//! The 7 failures of the 1000 are timeouts; in each, a block (or the pusher chasing it) ended
//! at or beyond a workspace bound (`x ≈ 0.15`, `x ≈ 0.7` or `y ≈ −0.5`), where the pre-block
//! point lies outside the bounds the commanded target is clipped to, so the oracle never gets
//! within 1 mm of it; in several, long alternations of `OrientLeft`/`OrientRight` had walked the
//! block there. In 6 of the 1000 (mostly these failures) the first block→target visit differs
//! from the order the oracle planned.
//!
//! The environment's own step allocates nothing; rapier's `PhysicsWorld::step` allocates about
//! twice per substep (≈ 48 allocations per control step, measured with a counting allocator).
//!
//! Rollouts of any [`vdd_core::Policy`] with success (p2), p1, task entropy and mode histogram
//! are in [`rollout`]; the scripted oracle and demonstration generation in [`oracle`]; the
//! training matrices in [`dataset`]; the `.npz` demonstrations in [`demos`]; a run's evaluation
//! ([`EvalProtocol`]: episodes, seed, lockstep batch) like Avoiding's. Trajectory figures are drawn by `vdd-report`'s `plots`
//! (no plotting lives in this crate).
//!
//! ```
//! use vdd_tasks::block_push::{BlockPushEnv, Status, EFFECTOR_START, OBS_DIM};
//! let mut env = BlockPushEnv::new(Default::default()).unwrap();
//! let obs = env.reset(7);
//! assert_eq!(obs.len(), OBS_DIM);
//! assert_eq!([obs[10], obs[11]], EFFECTOR_START);
//! // Standing still never succeeds.
//! assert_eq!(env.step(&[0.0, 0.0]).unwrap(), Status::Running);
//! assert!(env.step(&[f32::NAN, 0.0]).is_err());
//! ```

use rand::Rng as _;
use rapier2d::prelude::{ColliderBuilder, PhysicsWorld, RigidBodyBuilder, RigidBodyHandle, Vector};
use serde::{Deserialize, Serialize};
use vdd_core::Seeds;

use crate::{Result, TaskError};

pub use protocol::EvalProtocol;

pub mod dataset;
pub mod demos;
pub mod oracle;
mod protocol;
pub mod rollout;
#[cfg(test)]
mod tests;

/// Side of each square block.
pub const BLOCK_SIZE: f32 = 0.04;
/// Mass of each block (kg).
pub const BLOCK_MASS: f32 = 0.01;
/// Radius of the pusher disc.
pub const PUSHER_RADIUS: f32 = 0.008;
/// Duration of one control step (10 Hz).
pub const CONTROL_DT: f32 = 0.1;
/// Workspace bounds of the commanded effector target: `[[x_min, y_min], [x_max, y_max]]`.
pub const WORKSPACE: [[f32; 2]; 2] = [[0.15, -0.5], [0.70, 0.5]];
/// Start of the effector and of its commanded target.
pub const EFFECTOR_START: [f32; 2] = [0.30, -0.40];
/// A block is in a target when its centre is closer than this to the target's centre.
pub const GOAL_TOLERANCE: f32 = 0.05;
/// Half the side of a target zone as the original draws it (a 0.12 square; visual only:
/// success is [`GOAL_TOLERANCE`] from its centre).
pub const TARGET_HALF: f32 = 0.06;
/// Default episode step limit (Diffusion Policy's).
pub const MAX_STEPS: usize = 350;
/// Per-component bound on the action (the original's declared action space).
pub const ACTION_LIMIT: f32 = 0.1;
/// Observation dimension (see the module docs' table).
pub const OBS_DIM: usize = 16;
/// Action dimension: change of the commanded effector target `xy`.
pub const ACTION_DIM: usize = 2;
/// Number of behaviour modes (first block × its target).
pub const N_MODES: usize = 4;

/// Physics parameters of the planar analogue (see the module docs).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PhysicsConfig {
    /// Physics substeps per control step.
    pub substeps: usize,
    /// Largest pusher speed (m/s) while it tracks the commanded target.
    pub pusher_speed: f32,
    /// Sliding-friction deceleration of a block's speed (m/s²).
    pub friction_decel: f32,
    /// Friction deceleration of a block's spin (rad/s²).
    pub spin_decel: f32,
    /// Rapier linear damping of the blocks (1/s).
    pub linear_damping: f32,
    /// Rapier angular damping of the blocks (1/s).
    pub angular_damping: f32,
    /// Contact friction coefficient of the pusher and the blocks.
    pub contact_friction: f32,
}

impl Default for PhysicsConfig {
    fn default() -> Self {
        Self {
            substeps: 24,
            pusher_speed: 0.5,
            friction_decel: 9.81,
            spin_decel: 250.0,
            linear_damping: 2.0,
            angular_damping: 2.0,
            contact_friction: 0.5,
        }
    }
}

/// Settings of a [`BlockPushEnv`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EnvConfig {
    /// Episode step limit.
    pub max_steps: usize,
    /// Physics parameters.
    pub physics: PhysicsConfig,
}

impl Default for EnvConfig {
    /// [`MAX_STEPS`] steps and the default physics.
    fn default() -> Self {
        Self { max_steps: MAX_STEPS, physics: PhysicsConfig::default() }
    }
}

impl EnvConfig {
    /// Checks every field's range.
    pub fn validate(&self) -> Result<()> {
        let p = &self.physics;
        let bad = |m: String| Err(TaskError::InvalidArgument(format!("block-push env: {m}")));
        if self.max_steps == 0 || !(1..=1000).contains(&p.substeps) {
            return bad(format!(
                "max_steps {} must be >= 1 and substeps {} in 1..=1000",
                self.max_steps, p.substeps
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

/// A behaviour mode: the block that reached a target first, and that target.
///
/// The index is `2 · block + target` in `0..4`.
///
/// ```
/// use vdd_tasks::block_push::BlockPushMode;
/// let m = BlockPushMode::new(1, 0).unwrap();
/// assert_eq!(m.index(), 2);
/// assert_eq!(BlockPushMode::from_index(2).unwrap(), m);
/// assert!(BlockPushMode::new(2, 0).is_err());
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct BlockPushMode {
    block: u8,
    target: u8,
}

impl BlockPushMode {
    /// The mode "block `block` reaches target `target` first" (both 0 or 1).
    pub fn new(block: u8, target: u8) -> Result<Self> {
        if block > 1 || target > 1 {
            return Err(TaskError::InvalidArgument(format!(
                "block {block} and target {target} must be 0 or 1"
            )));
        }
        Ok(Self { block, target })
    }

    /// The mode with index `index` in `0..4`.
    pub fn from_index(index: usize) -> Result<Self> {
        if index >= N_MODES {
            return Err(TaskError::InvalidArgument(format!(
                "mode index {index} out of range 0..{N_MODES}"
            )));
        }
        Ok(Self { block: (index / 2) as u8, target: (index % 2) as u8 })
    }

    /// The block pushed first.
    pub fn block(&self) -> usize {
        usize::from(self.block)
    }

    /// The target the first block goes to.
    pub fn target(&self) -> usize {
        usize::from(self.target)
    }

    /// `2 · block + target`.
    pub fn index(&self) -> usize {
        2 * self.block() + self.target()
    }
}

/// State of an episode.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Status {
    /// Still going.
    Running,
    /// Both blocks are in distinct targets.
    Success,
    /// The step limit was reached without success.
    Timeout,
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
        }
    }
}

/// One Block-Push environment: a rapier world with two blocks and a kinematic pusher, the
/// commanded target, the targets, and the events recorded so far.
pub struct BlockPushEnv {
    config: EnvConfig,
    world: PhysicsWorld,
    blocks: [RigidBodyHandle; 2],
    pusher: RigidBodyHandle,
    pusher_xy: [f32; 2],
    commanded: [f32; 2],
    targets: [[f32; 2]; 2],
    steps: usize,
    status: Status,
    first: Option<BlockPushMode>,
    reached: [[bool; 2]; 2],
}

impl std::fmt::Debug for BlockPushEnv {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("BlockPushEnv")
            .field("observation", &self.observation())
            .field("steps", &self.steps)
            .field("status", &self.status)
            .field("first", &self.first)
            .finish_non_exhaustive()
    }
}

/// The start of an episode drawn from a seed: block poses `(x, y, yaw)` and targets.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StartState {
    /// Block poses `(x, y, yaw)`.
    pub blocks: [[f32; 3]; 2],
    /// Target centres.
    pub targets: [[f32; 2]; 2],
}

impl StartState {
    /// The start drawn from `seed` (see the module docs for the distribution).
    pub fn sample(seed: u64) -> Self {
        let mut rng = Seeds::new(seed).stream("block-push-start");
        let mut u = |h: f32| h * (2.0 * rng.random::<f32>() - 1.0);
        let mut blocks = [[0.0f32; 3]; 2];
        loop {
            for b in &mut blocks {
                *b = [0.4 + u(0.1), -0.2 + u(0.15), 0.0];
            }
            if (blocks[0][0] - blocks[1][0]).abs() > 0.1 {
                break;
            }
        }
        for b in &mut blocks {
            b[2] = std::f32::consts::FRAC_PI_4 * (1.0 + u(1.0));
        }
        let add = if u(1.0) < 0.0 { -0.12 } else { 0.12 };
        let y = 0.2 + u(0.0075);
        let targets = [[0.4 + add + u(0.005), y], [0.4 - add + u(0.005), y]];
        Self { blocks, targets }
    }
}

impl BlockPushEnv {
    /// An environment with a validated `config`, reset with seed 0.
    pub fn new(config: EnvConfig) -> Result<Self> {
        config.validate()?;
        let start = StartState::sample(0);
        let (world, blocks, pusher) = build_world(&config.physics, &start);
        let mut env = Self {
            config,
            world,
            blocks,
            pusher,
            pusher_xy: EFFECTOR_START,
            commanded: EFFECTOR_START,
            targets: start.targets,
            steps: 0,
            status: Status::Running,
            first: None,
            reached: [[false; 2]; 2],
        };
        env.reset_to(&start);
        Ok(env)
    }

    /// The configuration.
    pub fn config(&self) -> &EnvConfig {
        &self.config
    }

    /// Starts a new episode from `seed` ([`StartState::sample`]) and returns its first
    /// observation.
    pub fn reset(&mut self, seed: u64) -> [f32; OBS_DIM] {
        self.reset_to(&StartState::sample(seed))
    }

    /// Starts a new episode from `start` and returns its first observation.
    pub fn reset_to(&mut self, start: &StartState) -> [f32; OBS_DIM] {
        let (world, blocks, pusher) = build_world(&self.config.physics, start);
        self.world = world;
        self.blocks = blocks;
        self.pusher = pusher;
        self.pusher_xy = EFFECTOR_START;
        self.commanded = EFFECTOR_START;
        self.targets = start.targets;
        self.steps = 0;
        self.status = Status::Running;
        self.first = None;
        self.reached = [[false; 2]; 2];
        self.observation()
    }

    /// Block `i`'s pose `(x, y, yaw)`, yaw in `(−π, π]` (`i` is 0 or 1; larger means 1).
    pub fn block_pose(&self, i: usize) -> [f32; 3] {
        let b = &self.world.bodies[self.blocks[i.min(1)]];
        let t = b.translation();
        [t.x, t.y, b.rotation().angle()]
    }

    /// Block `i`'s linear velocity (`i` is 0 or 1; larger means 1).
    pub fn block_velocity(&self, i: usize) -> [f32; 2] {
        let v = self.world.bodies[self.blocks[i.min(1)]].linvel();
        [v.x, v.y]
    }

    /// The observation (see the module docs' table).
    pub fn observation(&self) -> [f32; OBS_DIM] {
        let mut o = [0.0f32; OBS_DIM];
        for i in 0..2 {
            let [x, y, yaw] = self.block_pose(i);
            let (s, c) = (4.0 * yaw).sin_cos();
            o[4 * i..4 * i + 4].copy_from_slice(&[x, y, s, c]);
        }
        let p = self.world.bodies[self.pusher].translation();
        o[8..10].copy_from_slice(&[p.x, p.y]);
        o[10..12].copy_from_slice(&self.commanded);
        o[12..14].copy_from_slice(&self.targets[0]);
        o[14..16].copy_from_slice(&self.targets[1]);
        o
    }

    /// The commanded effector target.
    pub fn commanded(&self) -> [f32; 2] {
        self.commanded
    }

    /// The target centres.
    pub fn targets(&self) -> [[f32; 2]; 2] {
        self.targets
    }

    /// Steps taken in this episode.
    pub fn steps(&self) -> usize {
        self.steps
    }

    /// The episode's status.
    pub fn status(&self) -> Status {
        self.status
    }

    /// The behaviour mode: the first `(block, target)` pair that came within
    /// [`GOAL_TOLERANCE`].
    pub fn mode(&self) -> Option<BlockPushMode> {
        self.first
    }

    /// Whether block `i` has come within [`GOAL_TOLERANCE`] of target `j` at some step.
    pub fn reached(&self) -> [[bool; 2]; 2] {
        self.reached
    }

    /// p1: whether at least one block has reached a target.
    pub fn p1(&self) -> bool {
        self.reached.iter().flatten().any(|&r| r)
    }

    /// The action actually applied for `action`: each component clipped to `±ACTION_LIMIT`.
    pub fn clip_action(action: [f32; ACTION_DIM]) -> [f32; ACTION_DIM] {
        action.map(|a| a.clamp(-ACTION_LIMIT, ACTION_LIMIT))
    }

    /// Applies `action` (length 2, finite; clipped to `±ACTION_LIMIT`, the new commanded target
    /// clipped to [`WORKSPACE`]) and returns the status after the step. Stepping an ended
    /// episode is an error.
    pub fn step(&mut self, action: &[f32]) -> Result<Status> {
        if self.status.is_done() {
            return Err(TaskError::EpisodeOver(self.status.as_str()));
        }
        // The rollouts' step (`episodes::Env::apply`): the same checks and clipping.
        crate::episodes::Env::apply(self, action, &mut [0.0; ACTION_DIM])?;
        Ok(self.status)
    }

    /// One step with an already validated and clipped action.
    pub(crate) fn step_clipped(&mut self, a: [f32; ACTION_DIM]) -> Status {
        debug_assert!(!self.status.is_done());
        for k in 0..2 {
            self.commanded[k] = (self.commanded[k] + a[k]).clamp(WORKSPACE[0][k], WORKSPACE[1][k]);
        }
        let p = &self.config.physics;
        let dt = CONTROL_DT / p.substeps as f32;
        let (max_move, dv, dw) = (p.pusher_speed * dt, p.friction_decel * dt, p.spin_decel * dt);
        for _ in 0..p.substeps {
            let d = [self.commanded[0] - self.pusher_xy[0], self.commanded[1] - self.pusher_xy[1]];
            let n = d[0].hypot(d[1]);
            self.pusher_xy = if n > max_move {
                [self.pusher_xy[0] + d[0] * max_move / n, self.pusher_xy[1] + d[1] * max_move / n]
            } else {
                self.commanded
            };
            let next = Vector::new(self.pusher_xy[0], self.pusher_xy[1]);
            self.world.bodies[self.pusher].set_next_kinematic_translation(next);
            for &h in &self.blocks {
                let b = &mut self.world.bodies[h];
                let v = b.linvel();
                let s = v.length();
                let v = if s > dv { v * (1.0 - dv / s) } else { Vector::ZERO };
                b.set_linvel(v, true);
                let w = b.angvel();
                b.set_angvel(if w.abs() > dw { w - dw * w.signum() } else { 0.0 }, true);
            }
            self.world.step();
        }
        self.steps += 1;
        let xy = [self.block_pose(0), self.block_pose(1)];
        let mut inside = [[false; 2]; 2];
        for (i, b) in xy.iter().enumerate() {
            for (j, t) in self.targets.iter().enumerate() {
                inside[i][j] = (b[0] - t[0]).hypot(b[1] - t[1]) < GOAL_TOLERANCE;
                if inside[i][j] {
                    self.reached[i][j] = true;
                    if self.first.is_none() {
                        self.first = Some(BlockPushMode { block: i as u8, target: j as u8 });
                    }
                }
            }
        }
        let success = (inside[0][0] && inside[1][1]) || (inside[0][1] && inside[1][0]);
        self.status = if success {
            Status::Success
        } else if self.steps >= self.config.max_steps {
            Status::Timeout
        } else {
            Status::Running
        };
        self.status
    }
}

/// A fresh world: zero gravity, two dynamic blocks and the kinematic pusher.
fn build_world(
    p: &PhysicsConfig,
    start: &StartState,
) -> (PhysicsWorld, [RigidBodyHandle; 2], RigidBodyHandle) {
    let mut world = PhysicsWorld::new();
    world.gravity = Vector::ZERO;
    world.integration_parameters.dt = CONTROL_DT / p.substeps as f32;
    // Tolerances (allowed penetration, prediction distance) scale with the length unit; the
    // blocks are 4 cm, so 1 m would allow millimetre penetrations.
    world.integration_parameters.length_unit = 0.04;
    let half = BLOCK_SIZE / 2.0;
    let blocks = start.blocks.map(|[x, y, yaw]| {
        let body = RigidBodyBuilder::dynamic()
            .translation(Vector::new(x, y))
            .rotation(yaw)
            .linear_damping(p.linear_damping)
            .angular_damping(p.angular_damping)
            .can_sleep(false);
        let collider =
            ColliderBuilder::cuboid(half, half).mass(BLOCK_MASS).friction(p.contact_friction);
        world.insert(body, collider).0
    });
    let body = RigidBodyBuilder::kinematic_position_based()
        .translation(Vector::new(EFFECTOR_START[0], EFFECTOR_START[1]));
    let collider = ColliderBuilder::ball(PUSHER_RADIUS).friction(p.contact_friction);
    let pusher = world.insert(body, collider).0;
    (world, blocks, pusher)
}

/// Block-Push's per-episode environment seed: the start of episode `episode` of an evaluation
/// or demonstration set with root seed `seed` (the same under every stepping).
pub fn env_seed(seed: u64, episode: usize) -> u64 {
    Seeds::new(seed).stream_indexed(ENV_STREAM, episode as u64).random()
}

/// The seed stream of the episodes' starts ([`env_seed`]).
pub(crate) const ENV_STREAM: &str = "block-push-env";

/// The block yaw modulo `π/2`, in `[−π/4, π/4]`, from its `(sin 4θ, cos 4θ)` encoding.
pub fn yaw_from_encoding(sin4: f32, cos4: f32) -> f32 {
    sin4.atan2(cos4) / 4.0
}
