//! D3IL Aligning (after `gym_aligning` of D3IL) on a 2-D rigid-body engine (`rapier2d`): a round
//! rod seen from above pushes an open-top square tray until it matches a random target pose,
//! either from inside the tray or from outside it: the two behaviour modes.
//!
//! # Facts copied from the original (`docs/contact-tasks.md`, sections 1, 3 and 6; metres, radians)
//!
//! * The tray: outer footprint 0.11 × 0.11 ([`TRAY_OUTER_HALF`]), walls 0.01 thick, inner clear
//!   0.09 × 0.09 ([`TRAY_INNER_HALF`]), mass [`TRAY_MASS`] `= 1.0` kg plus 0.001 kg per wall,
//!   sliding friction 0.3 (the tray's friction has priority in MuJoCo, so it is also the
//!   rod–tray friction). Start pose `x ∈ U[0.40, 0.60]`, `y ∈ U[−0.25, −0.10]`,
//!   `yaw ∈ U[−π/2, π/2]`; target pose (no collision) `x ∈ U[0.40, 0.60]`, `y ∈ U[0.20, 0.35]`,
//!   `yaw ∈ U[−π/2, π/2]` ([`StartState::sample`]). The walls' colours differ: the orientation
//!   has no symmetry.
//! * A rod of radius 0.01 ([`PUSHER_RADIUS`]) starting at [`EFFECTOR_START`] `= (0.525, −0.35)`,
//!   its tip [`START_HEIGHT`] `= 0.15` above the table, above the wall tops.
//! * Control step [`CONTROL_DT`] `= 0.035` s; the action is the change `Δ` of the *desired*
//!   effector position `(x, y, z)` (D3IL's `action_dim: 3`), added to the previous desired
//!   position; each component clipped to `±`[`ACTION_LIMIT`] `= 0.01` (declared, not enforced,
//!   by the original). Time limit [`MAX_STEPS`] `= 400` steps.
//! * Success (ends the episode): `‖tray_xy − target_xy‖ ≤` [`POS_TOLERANCE`] `= 0.0156` (the
//!   original's 3-D 0.018 with the tray resting 9 mm below the target: the planar tolerance) and
//!   the rotation distance `≤` [`ROT_TOLERANCE`] `= 0.048π` (angle modulo 2π, no symmetry).
//! * Partial metric: `mean_distance = ½ (pos_dist + rot_dist / π)` at the last step.
//! * Modes ([`AligningMode`], read at the **final** step): 0 "inside" if
//!   `‖tray_xy − rod_xy‖ <` [`INSIDE_DISTANCE`] `= 0.051`, else 1 "outside". Task entropy per
//!   test context, log base 2, averaged over contexts ([`rollout::Metrics`]).
//! * Evaluation: 60 test contexts × 8 rollouts ([`EvalProtocol`]).
//!
//! # Observation ([`OBS_DIM`] = 14)
//!
//! D3IL's order (desired position, effector position, tray pose, target pose) with each yaw as
//! `(sin θ, cos θ)` instead of a quaternion (the same information, continuous), and the heights
//! measured from the table top:
//!
//! | idx | field |
//! |---|---|
//! | 0–2 | desired effector `x, y, z` (the last commanded setpoint; `z`: rod tip height) |
//! | 3–5 | effector `x, y, z` (measured: the rod's position and tip height) |
//! | 6–9 | tray `x, y, sin θ, cos θ` |
//! | 10–13 | target `x, y, sin φ, cos φ` |
//!
//! # The planar substitute for the third dimension
//!
//! The original lowers the rod into the tray (or next to it) in 3-D. Here the action keeps its
//! third component and the rod tip's height `z` is simulated as a number: it follows the
//! desired height at the pusher's speed limit, never below the table (`z ≥ 0`). The rod's disc
//! collides with the tray's walls only while its tip is below the wall tops ([`WALL_TOP`]
//! `= 0.10` above the table; a collider toggle); above them it passes over the tray. A rod
//! lowered onto a wall (its disc overlapping a wall when the tip comes down to [`WALL_TOP`])
//! rests on it: its tip stays at [`WALL_TOP`] until it moves clear. So "inside" means lowered
//! within the inner clear square and "outside" lowered next to the tray, as in the original;
//! the base plate does not touch the rod in the plane (the tip rests on the table, not 2 cm
//! higher on the plate, inside the tray).
//!
//! # Other choices (as [`crate::pushing`]; the servo, the table friction and the world builder
//! are the D3IL tasks' shared ones, [`crate::d3il`])
//!
//! * **Table friction** as a Coulomb-like deceleration of the tray's speed
//!   ([`PhysicsConfig::friction_decel`] `= 0.3 · 9.81`) and spin ([`PhysicsConfig::spin_decel`]
//!   `= μg · 0.383 a / (a² / 6) ≈ 67.6` rad/s² for a uniform square plate of side `a = 0.10`:
//!   mean contact radius over radius of gyration squared), plus a light damping (2 /s).
//! * **Robot**: a kinematic disc moving straight towards the desired `xy` by at most
//!   [`PhysicsConfig::pusher_speed`] `· dt` a substep (0.5 m/s), not stopped by the tray; the
//!   height follows at the same speed limit.
//! * **Tray**: one dynamic body with the four wall cuboids as colliders and the base plate's mass
//!   and inertia added (`1.0 · (0.1² + 0.1²) / 12`).
//! * **Faults**: the tray or the rod leaving the table ([`TABLE`], Pushing's) ends the episode as
//!   [`Status::OffTable`], non-finite body states as [`Status::PhysicsFault`]; a non-finite or
//!   misshapen action is an error of the step. Never panics.
//! * **Determinism**: `enhanced-determinism`, single-threaded, one world per environment.
//!
//! ```
//! use vdd_tasks::aligning::{AligningEnv, Status, EFFECTOR_START, OBS_DIM, START_HEIGHT};
//! let mut env = AligningEnv::new(Default::default()).unwrap();
//! let obs = env.reset(7);
//! assert_eq!(obs.len(), OBS_DIM);
//! assert_eq!([obs[0], obs[1], obs[2]], [EFFECTOR_START[0], EFFECTOR_START[1], START_HEIGHT]);
//! assert_eq!(env.step(&[0.0, 0.0, 0.0]).unwrap(), Status::Running);
//! assert!(env.step(&[f32::NAN, 0.0, 0.0]).is_err());
//! ```

use rand::Rng as _;
use rapier2d::prelude::{
    ColliderBuilder, ColliderHandle, MassProperties, PhysicsWorld, RigidBodyBuilder,
    RigidBodyHandle, Vector,
};
use serde::{Deserialize, Serialize};
use vdd_core::Seeds;

use crate::d3il::{planar_world, servo, table_friction};
use crate::{Result, TaskError};

pub use crate::d3il::{PhysicsConfig, Status};

/// An Aligning evaluation ([`crate::d3il::EvalProtocol`]; D3IL's `aligning_config.yaml`: 60
/// test contexts × 8 rollouts).
pub type EvalProtocol = crate::d3il::EvalProtocol<AligningEnv>;

pub mod dataset;
pub mod oracle;
pub mod rollout;
#[cfg(test)]
mod tests;

/// Half the tray's outer side (0.11 / 2).
pub const TRAY_OUTER_HALF: f32 = 0.055;
/// Half the tray's inner clear side (0.09 / 2).
pub const TRAY_INNER_HALF: f32 = 0.045;
/// Mass of the tray's base plate (kg); each wall adds [`WALL_MASS`].
pub const TRAY_MASS: f32 = 1.0;
/// Mass of each wall (kg).
pub const WALL_MASS: f32 = 0.001;
/// Radius of the pusher disc (the rod).
pub const PUSHER_RADIUS: f32 = 0.01;
/// Duration of one control step (35 × 1 ms).
pub const CONTROL_DT: f32 = 0.035;
/// The table top (Pushing's): `[[x_min, y_min], [x_max, y_max]]`.
pub const TABLE: [[f32; 2]; 2] = crate::pushing::TABLE;
/// Start of the effector's `xy` and of its desired position.
pub const EFFECTOR_START: [f32; 2] = [0.525, -0.35];
/// Start height of the rod tip above the table (above the wall tops).
pub const START_HEIGHT: f32 = 0.15;
/// Height of the wall tops above the table: below it the rod collides with the walls.
pub const WALL_TOP: f32 = 0.10;
/// Largest distance of the tray's centre to its target's at success.
pub const POS_TOLERANCE: f32 = 0.0156;
/// Largest rotation distance at success (0.048π).
pub const ROT_TOLERANCE: f32 = 0.048 * std::f32::consts::PI;
/// The rod is inside the tray when its centre is closer than this to the tray's.
pub const INSIDE_DISTANCE: f32 = 0.051;
/// Default episode step limit.
pub const MAX_STEPS: usize = 400;
/// Per-component bound on the action.
pub const ACTION_LIMIT: f32 = 0.01;
/// Observation dimension (see the module docs' table).
pub const OBS_DIM: usize = 14;
/// Action dimension: change of the desired effector `x, y, z`.
pub const ACTION_DIM: usize = 3;
/// Number of behaviour modes (inside, outside).
pub const N_MODES: usize = 2;

/// The default physics of Aligning (see the module docs): what [`EnvConfig::default`] uses.
pub const PHYSICS: PhysicsConfig = PhysicsConfig {
    substeps: 10,
    pusher_speed: 0.5,
    friction_decel: 0.3 * 9.81,
    spin_decel: 67.6,
    linear_damping: 2.0,
    angular_damping: 2.0,
    contact_friction: 0.3,
};

/// Settings of an [`AligningEnv`]: [`crate::d3il::EnvConfig`] with Aligning's defaults.
pub type EnvConfig = crate::d3il::EnvConfig<AligningEnv>;

/// A behaviour mode: the rod inside the tray (index 0) or outside it (1) at the final step.
///
/// ```
/// use vdd_tasks::aligning::AligningMode;
/// assert_eq!(AligningMode::from_index(1).unwrap(), AligningMode::Outside);
/// assert_eq!(AligningMode::Inside.index(), 0);
/// assert!(AligningMode::from_index(2).is_err());
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(rename_all = "lowercase")]
pub enum AligningMode {
    /// Pushing from inside the tray (D3IL's index 0).
    Inside,
    /// Pushing from outside the tray (D3IL's index 1).
    Outside,
}

impl AligningMode {
    /// The mode with index `index` in `0..2`.
    pub fn from_index(index: usize) -> Result<Self> {
        match index {
            0 => Ok(Self::Inside),
            1 => Ok(Self::Outside),
            _ => Err(TaskError::InvalidArgument(format!(
                "mode index {index} out of range 0..{N_MODES}"
            ))),
        }
    }

    /// D3IL's index: 0 inside, 1 outside.
    pub fn index(&self) -> usize {
        match self {
            Self::Inside => 0,
            Self::Outside => 1,
        }
    }
}

/// The start of an episode drawn from a seed: the tray's and the target's poses `(x, y, yaw)`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StartState {
    /// The tray's pose `(x, y, yaw)`.
    pub tray: [f32; 3],
    /// The target's pose `(x, y, yaw)`.
    pub target: [f32; 3],
}

impl StartState {
    /// The start drawn from `seed` (see the module docs for the distribution).
    pub fn sample(seed: u64) -> Self {
        let mut rng = Seeds::new(seed).stream("aligning-start");
        let mut u = |lo: f32, hi: f32| lo + (hi - lo) * rng.random::<f32>();
        let h = std::f32::consts::FRAC_PI_2;
        let tray = [u(0.40, 0.60), u(-0.25, -0.10), u(-h, h)];
        let target = [u(0.40, 0.60), u(0.20, 0.35), u(-h, h)];
        Self { tray, target }
    }
}

/// `x` wrapped into `(−π, π]`.
pub fn wrap_angle(x: f32) -> f32 {
    let tau = std::f32::consts::TAU;
    let y = (x + std::f32::consts::PI).rem_euclid(tau) - std::f32::consts::PI;
    if y <= -std::f32::consts::PI { y + tau } else { y }
}

/// Whether a disc of radius [`PUSHER_RADIUS`] at `p` (in the tray's frame) overlaps a wall.
pub fn overlaps_walls(p: [f32; 2]) -> bool {
    let (a, b, r) = (TRAY_OUTER_HALF, TRAY_INNER_HALF, PUSHER_RADIUS);
    let out = (p[0].abs() - a).max(0.0).hypot((p[1].abs() - a).max(0.0));
    let inside_clear = p[0].abs() <= b - r && p[1].abs() <= b - r;
    out < r && !inside_clear
}

/// One Aligning environment: a rapier world with the tray and a kinematic rod, the desired
/// position and the rod tip's height.
pub struct AligningEnv {
    config: EnvConfig,
    world: PhysicsWorld,
    tray: RigidBodyHandle,
    pusher: RigidBodyHandle,
    pusher_collider: ColliderHandle,
    pusher_xy: [f32; 2],
    height: f32,
    desired: [f32; 3],
    target: [f32; 3],
    steps: usize,
    status: Status,
    context: u64,
}

impl std::fmt::Debug for AligningEnv {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("AligningEnv")
            .field("observation", &self.observation())
            .field("steps", &self.steps)
            .field("status", &self.status)
            .finish_non_exhaustive()
    }
}

impl AligningEnv {
    /// An environment with a validated `config`, reset with seed 0.
    pub fn new(config: EnvConfig) -> Result<Self> {
        config.validate()?;
        let start = StartState::sample(0);
        let (world, tray, pusher, pusher_collider) = build_world(&config.physics, &start);
        let mut env = Self {
            config,
            world,
            tray,
            pusher,
            pusher_collider,
            pusher_xy: EFFECTOR_START,
            height: START_HEIGHT,
            desired: [EFFECTOR_START[0], EFFECTOR_START[1], START_HEIGHT],
            target: start.target,
            steps: 0,
            status: Status::Running,
            context: 0,
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
        let obs = self.reset_to(&StartState::sample(seed));
        self.context = seed;
        obs
    }

    /// Starts a new episode from `start` and returns its first observation.
    pub fn reset_to(&mut self, start: &StartState) -> [f32; OBS_DIM] {
        let (world, tray, pusher, collider) = build_world(&self.config.physics, start);
        self.world = world;
        self.tray = tray;
        self.pusher = pusher;
        self.pusher_collider = collider;
        self.pusher_xy = EFFECTOR_START;
        self.height = START_HEIGHT;
        self.desired = [EFFECTOR_START[0], EFFECTOR_START[1], START_HEIGHT];
        self.target = start.target;
        self.steps = 0;
        self.status = Status::Running;
        self.context = 0;
        self.observation()
    }

    /// The tray's pose `(x, y, yaw)`, yaw in `(−π, π]`.
    pub fn tray_pose(&self) -> [f32; 3] {
        let b = &self.world.bodies[self.tray];
        let t = b.translation();
        [t.x, t.y, b.rotation().angle()]
    }

    /// The target's pose `(x, y, yaw)`.
    pub fn target(&self) -> [f32; 3] {
        self.target
    }

    /// The rod's position.
    pub fn pusher(&self) -> [f32; 2] {
        let p = self.world.bodies[self.pusher].translation();
        [p.x, p.y]
    }

    /// The rod tip's height above the table.
    pub fn height(&self) -> f32 {
        self.height
    }

    /// The observation (see the module docs' table).
    pub fn observation(&self) -> [f32; OBS_DIM] {
        let mut o = [0.0f32; OBS_DIM];
        o[0..3].copy_from_slice(&self.desired);
        let p = self.pusher();
        o[3..6].copy_from_slice(&[p[0], p[1], self.height]);
        for (k, [x, y, yaw]) in [self.tray_pose(), self.target].into_iter().enumerate() {
            let (s, c) = yaw.sin_cos();
            o[6 + 4 * k..10 + 4 * k].copy_from_slice(&[x, y, s, c]);
        }
        o
    }

    /// The desired effector position `(x, y, z)`.
    pub fn desired(&self) -> [f32; 3] {
        self.desired
    }

    /// Steps taken in this episode.
    pub fn steps(&self) -> usize {
        self.steps
    }

    /// The episode's status.
    pub fn status(&self) -> Status {
        self.status
    }

    /// The start seed of the episode (0 after [`AligningEnv::reset_to`]): its test context.
    pub fn context(&self) -> u64 {
        self.context
    }

    /// The tray's distance to the target: position and rotation distance (radians, `[0, π]`).
    pub fn errors(&self) -> (f32, f32) {
        let [x, y, yaw] = self.tray_pose();
        let [tx, ty, tyaw] = self.target;
        ((x - tx).hypot(y - ty), wrap_angle(tyaw - yaw).abs())
    }

    /// D3IL's partial metric: `½ (pos_dist + rot_dist / π)` now.
    pub fn mean_distance(&self) -> f32 {
        let (d, r) = self.errors();
        0.5 * (d + r / std::f32::consts::PI)
    }

    /// The mode now: inside if the rod's centre is within [`INSIDE_DISTANCE`] of the tray's.
    pub fn mode(&self) -> AligningMode {
        let [x, y, _] = self.tray_pose();
        let p = self.pusher();
        if (x - p[0]).hypot(y - p[1]) < INSIDE_DISTANCE {
            AligningMode::Inside
        } else {
            AligningMode::Outside
        }
    }

    /// The action actually applied for `action`: each component clipped to `±ACTION_LIMIT`.
    pub fn clip_action(action: [f32; ACTION_DIM]) -> [f32; ACTION_DIM] {
        action.map(|a| a.clamp(-ACTION_LIMIT, ACTION_LIMIT))
    }

    /// Applies `action` (length 3, finite; clipped, added to the desired position) and returns
    /// the status after the step. Stepping an ended episode is an error.
    pub fn step(&mut self, action: &[f32]) -> Result<Status> {
        if self.status.is_done() {
            return Err(TaskError::EpisodeOver(self.status.as_str()));
        }
        crate::episodes::Env::apply(self, action, &mut [0.0; ACTION_DIM])?;
        Ok(self.status)
    }

    /// The rod's position in the tray's frame.
    fn pusher_in_tray(&self) -> [f32; 2] {
        let [x, y, yaw] = self.tray_pose();
        let (s, c) = yaw.sin_cos();
        let d = [self.pusher_xy[0] - x, self.pusher_xy[1] - y];
        [c * d[0] + s * d[1], -s * d[0] + c * d[1]]
    }

    /// One step with an already validated and clipped action.
    pub(crate) fn step_clipped(&mut self, a: [f32; ACTION_DIM]) -> Status {
        debug_assert!(!self.status.is_done());
        for (d, a) in self.desired.iter_mut().zip(a) {
            *d += a;
        }
        let p = &self.config.physics;
        let dt = CONTROL_DT / p.substeps as f32;
        let (max_move, dv, dw) = (p.pusher_speed * dt, p.friction_decel * dt, p.spin_decel * dt);
        for _ in 0..p.substeps {
            self.pusher_xy = servo(self.pusher_xy, [self.desired[0], self.desired[1]], max_move);
            let goal = self.desired[2].max(0.0);
            let was_above = self.height >= WALL_TOP;
            self.height += (goal - self.height).clamp(-max_move, max_move);
            if was_above && self.height < WALL_TOP && overlaps_walls(self.pusher_in_tray()) {
                self.height = WALL_TOP;
            }
            let collides = self.height < WALL_TOP;
            let collider = &mut self.world.colliders[self.pusher_collider];
            if collider.is_enabled() != collides {
                collider.set_enabled(collides);
            }
            let next = Vector::new(self.pusher_xy[0], self.pusher_xy[1]);
            self.world.bodies[self.pusher].set_next_kinematic_translation(next);
            table_friction(&mut self.world.bodies[self.tray], dv, dw);
            self.world.step();
        }
        self.steps += 1;
        let tray = self.tray_pose();
        let pusher = self.pusher();
        if !tray.iter().chain(&pusher).chain(&[self.height]).all(|v| v.is_finite()) {
            self.status = Status::PhysicsFault;
            return self.status;
        }
        let on_table = |x: f32, y: f32| {
            (TABLE[0][0]..=TABLE[1][0]).contains(&x) && (TABLE[0][1]..=TABLE[1][1]).contains(&y)
        };
        if !(on_table(tray[0], tray[1]) && on_table(pusher[0], pusher[1])) {
            self.status = Status::OffTable;
            return self.status;
        }
        let (d, r) = self.errors();
        self.status = if d <= POS_TOLERANCE && r <= ROT_TOLERANCE {
            Status::Success
        } else if self.steps >= self.config.max_steps {
            Status::Timeout
        } else {
            Status::Running
        };
        self.status
    }
}

/// A fresh world: zero gravity, the tray (four wall colliders on one dynamic body, the base
/// plate's mass added) and the kinematic rod, lifted (its collider off).
fn build_world(
    p: &PhysicsConfig,
    start: &StartState,
) -> (PhysicsWorld, RigidBodyHandle, RigidBodyHandle, ColliderHandle) {
    let mut world = planar_world(CONTROL_DT / p.substeps as f32, 0.05);
    let [x, y, yaw] = start.tray;
    let side = 2.0 * (TRAY_OUTER_HALF - 0.005);
    let plate = MassProperties::new(Vector::ZERO, TRAY_MASS, TRAY_MASS * 2.0 * side * side / 12.0);
    let body = RigidBodyBuilder::dynamic()
        .translation(Vector::new(x, y))
        .rotation(yaw)
        .linear_damping(p.linear_damping)
        .angular_damping(p.angular_damping)
        .additional_mass_properties(plate)
        .can_sleep(false);
    let tray = world.insert_body(body);
    let (t, c) = (0.005, TRAY_OUTER_HALF - 0.005);
    let walls = [([c, 0.0], [t, TRAY_OUTER_HALF]), ([-c, 0.0], [t, TRAY_OUTER_HALF])];
    let walls = walls.into_iter().chain([([0.0, c], [c - t, t]), ([0.0, -c], [c - t, t])]);
    for ([wx, wy], [hx, hy]) in walls {
        let wall = ColliderBuilder::cuboid(hx, hy)
            .translation(Vector::new(wx, wy))
            .mass(WALL_MASS)
            .friction(p.contact_friction);
        world.insert_collider(wall, Some(tray));
    }
    let body = RigidBodyBuilder::kinematic_position_based()
        .translation(Vector::new(EFFECTOR_START[0], EFFECTOR_START[1]));
    let collider = ColliderBuilder::ball(PUSHER_RADIUS).friction(p.contact_friction).enabled(false);
    let (pusher, pusher_collider) = world.insert(body, collider);
    (world, tray, pusher, pusher_collider)
}

/// Aligning's per-episode start seed for demonstrations: the start of episode `episode` of a
/// set with root seed `seed`.
pub fn env_seed(seed: u64, episode: usize) -> u64 {
    crate::d3il::env_seed::<AligningEnv>(seed, episode)
}
