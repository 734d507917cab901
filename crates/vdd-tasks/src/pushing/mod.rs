//! D3IL Pushing (after `gym_pushing` of D3IL) on a 2-D rigid-body engine (`rapier2d`): a round
//! pusher seen from above pushes a red and a green box into a red and a green target zone, one
//! box per zone; which box arrives first and whether the boxes go to their own colour's zone or
//! swap gives the four behaviour modes.
//!
//! # Facts copied from the original (`docs/contact-tasks.md`, sections 1, 2 and 6; metres, radians)
//!
//! * Two cubes of side [`BOX_SIZE`] `= 0.06` and mass [`BOX_MASS`] `= 0.05` kg, MuJoCo's default
//!   sliding friction 1. Red box at `x ∈ U[0.40, 0.50]`, green at `x ∈ U[0.55, 0.65]`, both at
//!   `y ∈ U[−0.15, 0]`, yaw `∈ U[−π/2, π/2]` ([`StartState::sample`]; the `x` ranges are
//!   disjoint, so the boxes never overlap at the start).
//! * Two fixed target zones (visual only): red at [`TARGETS`]`[0] = (0.42, 0.30)`, green at
//!   [`TARGETS`]`[1] = (0.63, 0.30)`, 0.10 squares ([`TARGET_HALF`]).
//! * A rod end effector of radius 0.01 ([`PUSHER_RADIUS`]) starting at [`EFFECTOR_START`]
//!   `= (0.525, −0.28)`.
//! * Control step [`CONTROL_DT`] `= 0.035` s (35 MuJoCo steps of 1 ms, 28.6 Hz). The action is
//!   the change `Δ` of the *desired* effector `xy`; the new desired position is the previous
//!   desired one plus `Δ` (not the measured one), tracked by the robot's controller.
//! * Success: `(d(r,R) ≤ 0.05 ∧ d(g,G) ≤ 0.05) ∨ (d(r,G) ≤ 0.05 ∧ d(g,R) ≤ 0.05)` with
//!   [`GOAL_TOLERANCE`] `= 0.05`; it ends the episode. Time limit [`MAX_STEPS`] `= 400` steps.
//! * Partial metric: `mean_distance = ½ (min(d_rR, d_rG) + min(d_gR, d_gG))` at the last step.
//! * Modes ([`PushingMode`], D3IL's indices): 0 = red→red then green→green, 1 = green→green then
//!   red→red, 2 = red→green then green→red, 3 = green→red then red→green. Task entropy per
//!   test context with log base 4, averaged over contexts ([`rollout::Metrics`]).
//!
//! # Observation ([`OBS_DIM`] = 12)
//!
//! D3IL's order `[des_xy, ee_xy, red_xy, red_yaw, green_xy, green_yaw]` (targets are fixed and
//! not observed), with one change: D3IL encodes each yaw as `tan(yaw)`, which is singular at
//! ±90° (inside the start range) and ignores the cube's 4-fold symmetry; here each yaw becomes
//! `(sin 4θ, cos 4θ)`, continuous and invariant under the symmetry, as Block-Push does
//! ([`crate::block_push`]), so the dimension is 12 instead of 10.
//!
//! | idx | field |
//! |---|---|
//! | 0–1 | desired effector `xy` (the last commanded setpoint) |
//! | 2–3 | effector `xy` (measured: the pusher's position) |
//! | 4–5 | red box `xy` |
//! | 6–7 | red box `sin 4θ, cos 4θ` |
//! | 8–9 | green box `xy` |
//! | 10–11 | green box `sin 4θ, cos 4θ` |
//!
//! # Choices this crate makes (planar substitutes for 3-D details)
//!
//! * **Table friction.** The plane is top-down with zero gravity; sliding friction is applied by
//!   hand before every substep as a Coulomb-like deceleration of each box's speed
//!   ([`PhysicsConfig::friction_decel`], default `μg = 9.81` m/s², MuJoCo's friction 1) and
//!   spin ([`PhysicsConfig::spin_decel`], 170 rad/s²: Block-Push's 250 scaled by its 4 cm over
//!   these 6 cm boxes), never reversing the velocity, plus a light damping (2 /s): quasi-static
//!   pushing, as Block-Push. Contact friction pusher–box and box–box 0.5.
//! * **Robot.** The Panda's Cartesian impedance controller becomes a kinematic disc that moves
//!   straight towards the desired position by at most [`PhysicsConfig::pusher_speed`] `· dt`
//!   in each substep (default 0.5 m/s, above the teleoperator's ≈ 0.24 m/s): a position servo
//!   with a speed limit, not stopped by the boxes. The rod's height (its tip 2 cm above the
//!   table) has no planar counterpart: the disc always touches the boxes.
//! * **Substeps.** [`PhysicsConfig::substeps`] physics steps of `0.035 / substeps` s per
//!   control step (default 10, i.e. 3.5 ms: about Block-Push's 1/240 s; MuJoCo's 1 ms would
//!   cost 3.5 times as much).
//! * **Action bounds.** Each action component is clipped to `±`[`ACTION_LIMIT`] `= 0.01`, the
//!   original's declared action space (declared there, not enforced). The desired position is
//!   not clipped (the original's workspace clip is commented out).
//! * **Table and faults.** There are no walls (none near the objects in the original). A box or
//!   the pusher whose centre leaves the table ([`TABLE`]: `x ∈ [−0.09, 0.89]`,
//!   `y ∈ [−0.98, 0.98]`) ends the episode as [`Status::OffTable`]; non-finite body states end
//!   it as [`Status::PhysicsFault`]. Both are failures recorded with the episode, never
//!   panics. A non-finite or misshapen action is an error of the step (the shared rollout
//!   engine's rule, [`crate::episodes::check_apply`]), reported with its episode and step.
//! * **Not reproduced:** the one-step observation lag of D3IL's `step` (its observation is
//!   taken before the substeps run); the 3-D distance of the success check (the box centre
//!   rests 1.1 cm above the target's, so the planar tolerance there is about 0.049).
//! * **Determinism.** `rapier2d` is built with `enhanced-determinism` and run single-threaded,
//!   one world per environment: the same seed gives a bit-identical episode on any thread.
//!
//! Rollouts of any [`vdd_core::Policy`] with success, p1, mean distance, task entropy and mode
//! histogram are in [`rollout`]; the scripted demonstrator in [`oracle`]; the training
//! matrices in [`dataset`]; a run's evaluation ([`EvalProtocol`]: test contexts × rollouts per
//! context, as D3IL's 30 × 16). The settings, the protocol, the metrics, the physics helpers and
//! the rollout engine's [`Env`](crate::episodes::Env) are the D3IL tasks' shared ones
//! ([`crate::d3il`]: [`PushingEnv`] is a [`crate::d3il::ContextEnv`]).
//!
//! ```
//! use vdd_tasks::pushing::{PushingEnv, Status, EFFECTOR_START, OBS_DIM};
//! let mut env = PushingEnv::new(Default::default()).unwrap();
//! let obs = env.reset(7);
//! assert_eq!(obs.len(), OBS_DIM);
//! assert_eq!([obs[0], obs[1]], EFFECTOR_START);
//! // Standing still never succeeds.
//! assert_eq!(env.step(&[0.0, 0.0]).unwrap(), Status::Running);
//! assert!(env.step(&[f32::NAN, 0.0]).is_err());
//! ```

use rand::Rng as _;
use rapier2d::prelude::{ColliderBuilder, PhysicsWorld, RigidBodyBuilder, RigidBodyHandle, Vector};
use serde::{Deserialize, Serialize};
use vdd_core::Seeds;

use crate::d3il::{planar_world, servo, table_friction};
use crate::{Result, TaskError};

pub use crate::d3il::{PhysicsConfig, Status};

/// A Pushing evaluation ([`crate::d3il::EvalProtocol`]; D3IL's benchmark scripts: 30 test
/// contexts × 16 rollouts).
pub type EvalProtocol = crate::d3il::EvalProtocol<PushingEnv>;

pub mod dataset;
pub mod oracle;
pub mod rollout;
#[cfg(test)]
mod tests;

/// Side of each cube.
pub const BOX_SIZE: f32 = 0.06;
/// Mass of each cube (kg).
pub const BOX_MASS: f32 = 0.05;
/// Radius of the pusher disc (the rod).
pub const PUSHER_RADIUS: f32 = 0.01;
/// Duration of one control step (35 × 1 ms).
pub const CONTROL_DT: f32 = 0.035;
/// The table top: `[[x_min, y_min], [x_max, y_max]]` (centre (0.4, 0), half-size 0.49 × 0.98).
pub const TABLE: [[f32; 2]; 2] = [[-0.09, -0.98], [0.89, 0.98]];
/// Start of the effector and of its desired position.
pub const EFFECTOR_START: [f32; 2] = [0.525, -0.28];
/// Target centres: red (0), green (1).
pub const TARGETS: [[f32; 2]; 2] = [[0.42, 0.30], [0.63, 0.30]];
/// A box is in a target when its centre is at most this far from the target's centre.
pub const GOAL_TOLERANCE: f32 = 0.05;
/// Half the side of a target zone (a 0.10 square; visual only).
pub const TARGET_HALF: f32 = 0.05;
/// Default episode step limit (D3IL's `max_steps_per_episode`).
pub const MAX_STEPS: usize = 400;
/// Per-component bound on the action (the original's declared action space).
pub const ACTION_LIMIT: f32 = 0.01;
/// Observation dimension (see the module docs' table).
pub const OBS_DIM: usize = 12;
/// Action dimension: change of the desired effector `xy`.
pub const ACTION_DIM: usize = 2;
/// Number of behaviour modes (which box first × same or swapped targets).
pub const N_MODES: usize = 4;

/// The default physics of Pushing (see the module docs): what [`EnvConfig::default`] uses.
pub const PHYSICS: PhysicsConfig = PhysicsConfig {
    substeps: 10,
    pusher_speed: 0.5,
    friction_decel: 9.81,
    spin_decel: 170.0,
    linear_damping: 2.0,
    angular_damping: 2.0,
    contact_friction: 0.5,
};

/// Settings of a [`PushingEnv`]: [`crate::d3il::EnvConfig`] with Pushing's defaults.
pub type EnvConfig = crate::d3il::EnvConfig<PushingEnv>;

/// A behaviour mode: which box reached its target first, and whether the boxes went to their
/// own colour's targets or swapped.
///
/// The index is D3IL's: `first + 2 · swapped` (0 = red→red then green→green, 1 = green→green
/// then red→red, 2 = red→green then green→red, 3 = green→red then red→green).
///
/// ```
/// use vdd_tasks::pushing::PushingMode;
/// let m = PushingMode::new(1, true).unwrap();
/// assert_eq!(m.index(), 3);
/// assert_eq!(m.first_target(), 0); // green first, to the red target
/// assert_eq!(PushingMode::from_index(3).unwrap(), m);
/// assert!(PushingMode::new(2, false).is_err());
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct PushingMode {
    first: u8,
    swapped: bool,
}

impl PushingMode {
    /// The mode "box `first` (0 red, 1 green) arrives first; the boxes swap targets if
    /// `swapped`".
    pub fn new(first: u8, swapped: bool) -> Result<Self> {
        if first > 1 {
            return Err(TaskError::InvalidArgument(format!("box {first} must be 0 or 1")));
        }
        Ok(Self { first, swapped })
    }

    /// The mode with index `index` in `0..4`.
    pub fn from_index(index: usize) -> Result<Self> {
        if index >= N_MODES {
            return Err(TaskError::InvalidArgument(format!(
                "mode index {index} out of range 0..{N_MODES}"
            )));
        }
        Ok(Self { first: (index % 2) as u8, swapped: index >= 2 })
    }

    /// The box pushed first (0 red, 1 green).
    pub fn first(&self) -> usize {
        usize::from(self.first)
    }

    /// Whether the boxes swap targets (red → green target, green → red target).
    pub fn swapped(&self) -> bool {
        self.swapped
    }

    /// The target of box `b`.
    pub fn target_of(&self, b: usize) -> usize {
        if self.swapped { 1 - b.min(1) } else { b.min(1) }
    }

    /// The target of the first box.
    pub fn first_target(&self) -> usize {
        self.target_of(self.first())
    }

    /// D3IL's index `first + 2 · swapped`.
    pub fn index(&self) -> usize {
        self.first() + 2 * usize::from(self.swapped)
    }
}

/// The start of an episode drawn from a seed: box poses `(x, y, yaw)`, red then green.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct StartState {
    /// Box poses `(x, y, yaw)`: red, green.
    pub boxes: [[f32; 3]; 2],
}

impl StartState {
    /// The start drawn from `seed` (see the module docs for the distribution).
    pub fn sample(seed: u64) -> Self {
        let mut rng = Seeds::new(seed).stream("pushing-start");
        let mut u = |lo: f32, hi: f32| lo + (hi - lo) * rng.random::<f32>();
        let h = std::f32::consts::FRAC_PI_2;
        let red = [u(0.40, 0.50), u(-0.15, 0.0), u(-h, h)];
        let green = [u(0.55, 0.65), u(-0.15, 0.0), u(-h, h)];
        Self { boxes: [red, green] }
    }
}

/// One Pushing environment: a rapier world with two boxes and a kinematic pusher, the desired
/// position, and the target visits recorded so far.
pub struct PushingEnv {
    config: EnvConfig,
    world: PhysicsWorld,
    boxes: [RigidBodyHandle; 2],
    pusher: RigidBodyHandle,
    pusher_xy: [f32; 2],
    desired: [f32; 2],
    steps: usize,
    status: Status,
    /// The step at which box `b` first came within [`GOAL_TOLERANCE`] of target `t`.
    visits: [[Option<usize>; 2]; 2],
    context: u64,
}

impl std::fmt::Debug for PushingEnv {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("PushingEnv")
            .field("observation", &self.observation())
            .field("steps", &self.steps)
            .field("status", &self.status)
            .field("visits", &self.visits)
            .finish_non_exhaustive()
    }
}

impl PushingEnv {
    /// An environment with a validated `config`, reset with seed 0.
    pub fn new(config: EnvConfig) -> Result<Self> {
        config.validate()?;
        let start = StartState::sample(0);
        let (world, boxes, pusher) = build_world(&config.physics, &start);
        let mut env = Self {
            config,
            world,
            boxes,
            pusher,
            pusher_xy: EFFECTOR_START,
            desired: EFFECTOR_START,
            steps: 0,
            status: Status::Running,
            visits: [[None; 2]; 2],
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
        let (world, boxes, pusher) = build_world(&self.config.physics, start);
        self.world = world;
        self.boxes = boxes;
        self.pusher = pusher;
        self.pusher_xy = EFFECTOR_START;
        self.desired = EFFECTOR_START;
        self.steps = 0;
        self.status = Status::Running;
        self.visits = [[None; 2]; 2];
        self.context = 0;
        self.observation()
    }

    /// Box `i`'s pose `(x, y, yaw)`, yaw in `(−π, π]` (`i` 0 red, 1 green; larger means 1).
    pub fn box_pose(&self, i: usize) -> [f32; 3] {
        let b = &self.world.bodies[self.boxes[i.min(1)]];
        let t = b.translation();
        [t.x, t.y, b.rotation().angle()]
    }

    /// Box `i`'s linear velocity (`i` is 0 or 1; larger means 1).
    pub fn box_velocity(&self, i: usize) -> [f32; 2] {
        let v = self.world.bodies[self.boxes[i.min(1)]].linvel();
        [v.x, v.y]
    }

    /// The pusher's position.
    pub fn pusher(&self) -> [f32; 2] {
        let p = self.world.bodies[self.pusher].translation();
        [p.x, p.y]
    }

    /// The observation (see the module docs' table).
    pub fn observation(&self) -> [f32; OBS_DIM] {
        let mut o = [0.0f32; OBS_DIM];
        o[0..2].copy_from_slice(&self.desired);
        o[2..4].copy_from_slice(&self.pusher());
        for i in 0..2 {
            let [x, y, yaw] = self.box_pose(i);
            let (s, c) = (4.0 * yaw).sin_cos();
            o[4 + 4 * i..8 + 4 * i].copy_from_slice(&[x, y, s, c]);
        }
        o
    }

    /// The desired effector position.
    pub fn desired(&self) -> [f32; 2] {
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

    /// The start seed of the episode ([`PushingEnv::reset`]; 0 after [`PushingEnv::reset_to`]):
    /// its test context.
    pub fn context(&self) -> u64 {
        self.context
    }

    /// The step at which box `b` first came within [`GOAL_TOLERANCE`] of target `t`, per
    /// `[b][t]`.
    pub fn visits(&self) -> [[Option<usize>; 2]; 2] {
        self.visits
    }

    /// p1: whether at least one box has reached a target.
    pub fn p1(&self) -> bool {
        self.visits.iter().flatten().any(Option::is_some)
    }

    /// D3IL's partial metric: `½ (min(d_rR, d_rG) + min(d_gR, d_gG))` now.
    pub fn mean_distance(&self) -> f32 {
        let d = self.distances();
        0.5 * (d[0][0].min(d[0][1]) + d[1][0].min(d[1][1]))
    }

    /// The behaviour mode, once both boxes have visited complementary targets (D3IL's
    /// `check_mode`): the pairing completed first, ordered by which of its two visits came
    /// first (red on a tie).
    pub fn mode(&self) -> Option<PushingMode> {
        let v = &self.visits;
        let mut best: Option<(usize, PushingMode)> = None;
        for swapped in [false, true] {
            let t = |b: usize| if swapped { 1 - b } else { b };
            if let (Some(r), Some(g)) = (v[0][t(0)], v[1][t(1)]) {
                let done = r.max(g);
                let mode = PushingMode { first: u8::from(g < r), swapped };
                if best.is_none_or(|(d, _)| done < d) {
                    best = Some((done, mode));
                }
            }
        }
        best.map(|(_, m)| m)
    }

    /// The action actually applied for `action`: each component clipped to `±ACTION_LIMIT`.
    pub fn clip_action(action: [f32; ACTION_DIM]) -> [f32; ACTION_DIM] {
        action.map(|a| a.clamp(-ACTION_LIMIT, ACTION_LIMIT))
    }

    /// Applies `action` (length 2, finite; clipped to `±ACTION_LIMIT`, added to the desired
    /// position) and returns the status after the step. Stepping an ended episode is an error.
    pub fn step(&mut self, action: &[f32]) -> Result<Status> {
        if self.status.is_done() {
            return Err(TaskError::EpisodeOver(self.status.as_str()));
        }
        crate::episodes::Env::apply(self, action, &mut [0.0; ACTION_DIM])?;
        Ok(self.status)
    }

    /// Planar distances `[box][target]`.
    fn distances(&self) -> [[f32; 2]; 2] {
        let mut d = [[0.0f32; 2]; 2];
        for (b, row) in d.iter_mut().enumerate() {
            let [x, y, _] = self.box_pose(b);
            for (t, dt) in row.iter_mut().enumerate() {
                *dt = (x - TARGETS[t][0]).hypot(y - TARGETS[t][1]);
            }
        }
        d
    }

    /// One step with an already validated and clipped action.
    pub(crate) fn step_clipped(&mut self, a: [f32; ACTION_DIM]) -> Status {
        debug_assert!(!self.status.is_done());
        self.desired = [self.desired[0] + a[0], self.desired[1] + a[1]];
        let p = &self.config.physics;
        let dt = CONTROL_DT / p.substeps as f32;
        let (max_move, dv, dw) = (p.pusher_speed * dt, p.friction_decel * dt, p.spin_decel * dt);
        for _ in 0..p.substeps {
            self.pusher_xy = servo(self.pusher_xy, self.desired, max_move);
            let next = Vector::new(self.pusher_xy[0], self.pusher_xy[1]);
            self.world.bodies[self.pusher].set_next_kinematic_translation(next);
            for &h in &self.boxes {
                table_friction(&mut self.world.bodies[h], dv, dw);
            }
            self.world.step();
        }
        self.steps += 1;
        let poses = [self.box_pose(0), self.box_pose(1)];
        let pusher = self.pusher();
        if !poses.iter().flatten().chain(&pusher).all(|v| v.is_finite()) {
            self.status = Status::PhysicsFault;
            return self.status;
        }
        let on_table = |x: f32, y: f32| {
            (TABLE[0][0]..=TABLE[1][0]).contains(&x) && (TABLE[0][1]..=TABLE[1][1]).contains(&y)
        };
        if !(poses.iter().all(|b| on_table(b[0], b[1])) && on_table(pusher[0], pusher[1])) {
            self.status = Status::OffTable;
            return self.status;
        }
        let d = self.distances();
        let inside = d.map(|row| row.map(|x| x <= GOAL_TOLERANCE));
        for (b, row) in inside.iter().enumerate() {
            for (t, &i) in row.iter().enumerate() {
                if i && self.visits[b][t].is_none() {
                    self.visits[b][t] = Some(self.steps);
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

/// A fresh world: zero gravity, two dynamic boxes and the kinematic pusher.
fn build_world(
    p: &PhysicsConfig,
    start: &StartState,
) -> (PhysicsWorld, [RigidBodyHandle; 2], RigidBodyHandle) {
    let mut world = planar_world(CONTROL_DT / p.substeps as f32, BOX_SIZE);
    let half = BOX_SIZE / 2.0;
    let boxes = start.boxes.map(|[x, y, yaw]| {
        let body = RigidBodyBuilder::dynamic()
            .translation(Vector::new(x, y))
            .rotation(yaw)
            .linear_damping(p.linear_damping)
            .angular_damping(p.angular_damping)
            .can_sleep(false);
        let collider =
            ColliderBuilder::cuboid(half, half).mass(BOX_MASS).friction(p.contact_friction);
        world.insert(body, collider).0
    });
    let body = RigidBodyBuilder::kinematic_position_based()
        .translation(Vector::new(EFFECTOR_START[0], EFFECTOR_START[1]));
    let collider = ColliderBuilder::ball(PUSHER_RADIUS).friction(p.contact_friction);
    let pusher = world.insert(body, collider).0;
    (world, boxes, pusher)
}

/// Pushing's per-episode start seed for demonstrations: the start of episode `episode` of a
/// set with root seed `seed`.
pub fn env_seed(seed: u64, episode: usize) -> u64 {
    crate::d3il::env_seed::<PushingEnv>(seed, episode)
}

/// The box yaw modulo `π/2`, in `[−π/4, π/4]`, from its `(sin 4θ, cos 4θ)` encoding.
pub fn yaw_from_encoding(sin4: f32, cos4: f32) -> f32 {
    sin4.atan2(cos4) / 4.0
}
