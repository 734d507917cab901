//! The planar Avoiding task (after D3IL's "Avoiding"): an end effector starts below three rows of
//! disc obstacles and must cross the finish line `y > 0.35` without touching any of them.
//!
//! # Facts (from `docs/tasks.md`; lengths in metres)
//!
//! * Start of the end effector: [`START`] `= (0.525, −0.28)`, desired position equal to it.
//! * Obstacles ([`OBSTACLES`]): level 1 at `(0.5, −0.10)`, radius 0.03; level 2 at
//!   `(0.425, 0.08)` and `(0.575, 0.08)`, radius 0.025; level 3 at `(0.35, 0.26)`,
//!   `(0.50, 0.26)` and `(0.65, 0.26)`, radius 0.025.
//! * Observation ([`OBS_DIM`] = 4): previous desired position `(x, y)`, current position `(x, y)`.
//! * Action ([`ACTION_DIM`] = 2): change of the desired position in this step.
//! * Success: the end effector's `y` exceeds [`FINISH_Y`] `= 0.35`. Failure: a collision, or
//!   [`MAX_STEPS`] `= 250` steps without success.
//! * Behaviour mode ([`AvoidingMode`]): the gap used at each level, recorded the first time the
//!   end effector crosses the level's `y` upwards; `2 × 3 × 4 =` [`N_MODES`] modes.
//!
//! # Choices this crate makes (not fixed by the task description)
//!
//! * **Dynamics.** First-order lag: `desired ← desired + clip(action)`, then
//!   `position ← position + TRACKING_GAIN · (desired − position)` with [`TRACKING_GAIN`] `= 0.5`
//!   per step (the position closes half the remaining distance each step).
//! * **Action bounds.** Each action component is clipped to `±`[`ACTION_LIMIT`] `= 0.02` m per
//!   step (an actuator limit: at least twice the scripted demonstrator's fastest step, so it
//!   never binds for demonstrations, yet a diverging policy cannot jump through an obstacle).
//!   Non-finite actions are errors, not clipped.
//! * **End-effector size.** The end effector is a disc of radius [`EE_RADIUS`] `= 0.01` m: it
//!   collides when its centre comes within `obstacle radius + EE_RADIUS` of an obstacle's centre.
//!   Collisions are checked continuously along the straight segment the position moves along in
//!   a step, so no step can tunnel through an obstacle.
//! * **No walls.** The plane is unbounded; a policy that wanders off simply times out.
//! * **Gap boundaries.** At the moment of crossing a level, the gap index is the number of that
//!   level's obstacle centres left of the crossing `x` (linearly interpolated within the step).
//!   A collision-free crossing cannot be ambiguous, since it passes outside every disc.
//!
//! Rollouts of any [`vdd_core::Policy`] live in [`rollout`], and the recipes' evaluation of a
//! run ([`EvalProtocol`]: episodes, seeds, lockstep batches) in [`protocol`]; the observation
//! features the recipes' models see in [`ObsFeatures`]; the scripted multimodal demonstrator
//! and demonstration generation in [`demonstrator`]; the recipes' training data (windows,
//! normalisers) in [`dataset`].
//!
//! ```
//! use vdd_tasks::avoiding::{AvoidingEnv, Status, START};
//! let mut env = AvoidingEnv::new();
//! assert_eq!(env.observation(), [START[0], START[1], START[0], START[1]]);
//! // Straight up runs into the level-1 obstacle.
//! let mut status = Status::Running;
//! while status == Status::Running {
//!     status = env.step(&[0.0, 0.01]).unwrap();
//! }
//! assert_eq!(status, Status::Collision);
//! assert!(env.step(&[0.0, 0.01]).is_err()); // the episode is over
//! ```

use serde::{Deserialize, Serialize};
use vdd_core::CoreError;

use crate::{Result, TaskError};

mod curves;
pub mod dataset;
pub mod demonstrator;
pub mod demos;
mod features;
pub mod protocol;
pub mod rollout;

pub use curves::{CURVE_ENTROPY, CURVE_SUCCESS, CurveProtocol, DeployedCurves, MAX_CURVE_POINTS};
pub use features::ObsFeatures;
pub use protocol::{AvoidingEval, EvalProtocol, PlotSettings};

/// Start position of the end effector (and of the desired position).
pub const START: [f32; 2] = [0.525, -0.28];
/// The finish line: success once the end effector's `y` exceeds it.
pub const FINISH_Y: f32 = 0.35;
/// Episode step limit; an episode still running after this many steps is a timeout.
pub const MAX_STEPS: usize = 250;
/// First-order lag gain per step: `position += TRACKING_GAIN · (desired − position)`.
pub const TRACKING_GAIN: f32 = 0.5;
/// Per-component bound on the action (change of desired position per step), in metres.
pub const ACTION_LIMIT: f32 = 0.02;
/// Radius of the end effector, in metres.
pub const EE_RADIUS: f32 = 0.01;
/// Observation dimension: previous desired `(x, y)`, current position `(x, y)`.
pub const OBS_DIM: usize = 4;
/// Action dimension: change of the desired `(x, y)`.
pub const ACTION_DIM: usize = 2;
/// Number of obstacle levels.
pub const N_LEVELS: usize = 3;
/// Gaps at each level: left/right of one obstacle; around two; around three.
pub const GAPS_PER_LEVEL: [usize; N_LEVELS] = [2, 3, 4];
/// Number of behaviour modes (`2 × 3 × 4`).
pub const N_MODES: usize = 24;
/// The `y` of each level (its obstacles' centres).
pub const LEVEL_Y: [f32; N_LEVELS] = [-0.10, 0.08, 0.26];

/// A disc obstacle.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Obstacle {
    /// Centre `(x, y)`.
    pub centre: [f32; 2],
    /// Radius.
    pub radius: f32,
    /// Level (0, 1 or 2, bottom to top).
    pub level: usize,
}

/// The six obstacles, level by level and left to right.
pub const OBSTACLES: [Obstacle; 6] = [
    Obstacle { centre: [0.5, -0.10], radius: 0.03, level: 0 },
    Obstacle { centre: [0.425, 0.08], radius: 0.025, level: 1 },
    Obstacle { centre: [0.575, 0.08], radius: 0.025, level: 1 },
    Obstacle { centre: [0.35, 0.26], radius: 0.025, level: 2 },
    Obstacle { centre: [0.50, 0.26], radius: 0.025, level: 2 },
    Obstacle { centre: [0.65, 0.26], radius: 0.025, level: 2 },
];

/// Distance of the centre of an outer gap (left of the leftmost or right of the rightmost
/// obstacle of a level) from that obstacle's centre; equal to half the spacing of neighbouring
/// obstacles, so every gap centre is equally far from its obstacles.
pub const OUTER_GAP_OFFSET: f32 = 0.075;

/// The `x` of the obstacle centres of `level`, left to right (the gap boundaries).
pub fn level_boundaries(level: usize) -> &'static [f32] {
    const B0: [f32; 1] = [0.5];
    const B1: [f32; 2] = [0.425, 0.575];
    const B2: [f32; 3] = [0.35, 0.50, 0.65];
    match level {
        0 => &B0,
        1 => &B1,
        _ => &B2,
    }
}

/// The gap that `x` lies in at `level` (the number of obstacle centres left of `x`).
pub fn gap_at(level: usize, x: f32) -> u8 {
    level_boundaries(level).iter().filter(|&&b| b < x).count() as u8
}

/// The `x` of the centre of gap `gap` at `level`: the midpoint of two neighbouring obstacles, or
/// [`OUTER_GAP_OFFSET`] beyond the outermost one.
pub fn gap_centre(level: usize, gap: u8) -> Result<f32> {
    if level >= N_LEVELS || usize::from(gap) >= GAPS_PER_LEVEL[level] {
        return Err(TaskError::InvalidArgument(format!("no gap {gap} at level {level}")));
    }
    let b = level_boundaries(level);
    let g = usize::from(gap);
    Ok(if g == 0 {
        b[0] - OUTER_GAP_OFFSET
    } else if g == b.len() {
        b[b.len() - 1] + OUTER_GAP_OFFSET
    } else {
        0.5 * (b[g - 1] + b[g])
    })
}

/// A behaviour mode: the gap taken at each of the three levels.
///
/// Gaps are numbered left to right from 0. The mode index is
/// `12 · gap₁ + 4 · gap₂ + gap₃` in `0..24`.
///
/// ```
/// use vdd_tasks::avoiding::AvoidingMode;
/// let m = AvoidingMode::new([1, 2, 3]).unwrap();
/// assert_eq!(m.index(), 23);
/// assert_eq!(AvoidingMode::from_index(23).unwrap(), m);
/// assert!(AvoidingMode::new([2, 0, 0]).is_err()); // level 1 has only two gaps
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub struct AvoidingMode {
    gaps: [u8; N_LEVELS],
}

impl AvoidingMode {
    /// The mode with these gaps (level 1, 2, 3).
    pub fn new(gaps: [u8; N_LEVELS]) -> Result<Self> {
        for (l, &g) in gaps.iter().enumerate() {
            if usize::from(g) >= GAPS_PER_LEVEL[l] {
                return Err(TaskError::InvalidArgument(format!(
                    "gap {g} at level {} (it has {} gaps)",
                    l + 1,
                    GAPS_PER_LEVEL[l]
                )));
            }
        }
        Ok(Self { gaps })
    }

    /// The mode with index `index` in `0..24`.
    pub fn from_index(index: usize) -> Result<Self> {
        if index >= N_MODES {
            return Err(TaskError::InvalidArgument(format!(
                "mode index {index} out of range 0..{N_MODES}"
            )));
        }
        Ok(Self { gaps: [(index / 12) as u8, ((index / 4) % 3) as u8, (index % 4) as u8] })
    }

    /// The gap taken at each level.
    pub fn gaps(&self) -> [u8; N_LEVELS] {
        self.gaps
    }

    /// The mode index `12 · gap₁ + 4 · gap₂ + gap₃`.
    pub fn index(&self) -> usize {
        12 * usize::from(self.gaps[0]) + 4 * usize::from(self.gaps[1]) + usize::from(self.gaps[2])
    }
}

/// State of an episode.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Serialize, Deserialize)]
pub enum Status {
    /// Still going.
    Running,
    /// Crossed the finish line without a collision.
    Success,
    /// Touched an obstacle.
    Collision,
    /// Reached [`MAX_STEPS`] without success.
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
            Status::Collision => "collision",
            Status::Timeout => "timeout",
        }
    }
}

/// One Avoiding environment: the end effector, its desired position, the step counter and the
/// gaps recorded so far. Deterministic (the task itself draws no random numbers).
#[derive(Debug, Clone, PartialEq)]
pub struct AvoidingEnv {
    desired: [f32; 2],
    position: [f32; 2],
    steps: usize,
    gaps: [Option<u8>; N_LEVELS],
    status: Status,
}

impl Default for AvoidingEnv {
    fn default() -> Self {
        Self::new()
    }
}

impl AvoidingEnv {
    /// An environment at the start of an episode.
    pub fn new() -> Self {
        Self {
            desired: START,
            position: START,
            steps: 0,
            gaps: [None; N_LEVELS],
            status: Status::Running,
        }
    }

    /// Starts a new episode and returns its first observation.
    pub fn reset(&mut self) -> [f32; OBS_DIM] {
        *self = Self::new();
        self.observation()
    }

    /// The observation: previous desired position, then current position.
    pub fn observation(&self) -> [f32; OBS_DIM] {
        [self.desired[0], self.desired[1], self.position[0], self.position[1]]
    }

    /// Current desired position.
    pub fn desired(&self) -> [f32; 2] {
        self.desired
    }

    /// Current end-effector position.
    pub fn position(&self) -> [f32; 2] {
        self.position
    }

    /// Steps taken in this episode.
    pub fn steps(&self) -> usize {
        self.steps
    }

    /// The episode's status.
    pub fn status(&self) -> Status {
        self.status
    }

    /// The gap recorded at each level so far (`None` until the level is first crossed).
    pub fn gaps(&self) -> [Option<u8>; N_LEVELS] {
        self.gaps
    }

    /// The behaviour mode, once all three levels have been crossed.
    pub fn mode(&self) -> Option<AvoidingMode> {
        mode_of(self.gaps)
    }

    /// The action actually applied for `action`: each component clipped to `±ACTION_LIMIT`.
    pub fn clip_action(action: [f32; ACTION_DIM]) -> [f32; ACTION_DIM] {
        action.map(|a| a.clamp(-ACTION_LIMIT, ACTION_LIMIT))
    }

    /// Applies `action` (length 2, finite; clipped to `±ACTION_LIMIT`) and returns the status
    /// after the step. Stepping an ended episode is an error.
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
        self.desired[0] += a[0];
        self.desired[1] += a[1];
        let p = self.position;
        let q = [
            p[0] + TRACKING_GAIN * (self.desired[0] - p[0]),
            p[1] + TRACKING_GAIN * (self.desired[1] - p[1]),
        ];
        for (l, &y) in LEVEL_Y.iter().enumerate() {
            if self.gaps[l].is_none() && p[1] < y && q[1] >= y {
                let u = (y - p[1]) / (q[1] - p[1]);
                self.gaps[l] = Some(gap_at(l, p[0] + u * (q[0] - p[0])));
            }
        }
        self.position = q;
        self.steps += 1;
        let hit =
            OBSTACLES.iter().any(|o| segment_disc_distance(p, q, o.centre) <= o.radius + EE_RADIUS);
        self.status = if hit {
            Status::Collision
        } else if q[1] > FINISH_Y {
            Status::Success
        } else if self.steps >= MAX_STEPS {
            Status::Timeout
        } else {
            Status::Running
        };
        self.status
    }
}

/// The mode for a complete set of recorded gaps.
pub(crate) fn mode_of(gaps: [Option<u8>; N_LEVELS]) -> Option<AvoidingMode> {
    match gaps {
        [Some(a), Some(b), Some(c)] => Some(AvoidingMode { gaps: [a, b, c] }),
        _ => None,
    }
}

/// Distance from `c` to the segment `[p, q]`.
pub fn segment_disc_distance(p: [f32; 2], q: [f32; 2], c: [f32; 2]) -> f32 {
    let d = [q[0] - p[0], q[1] - p[1]];
    let len2 = d[0] * d[0] + d[1] * d[1];
    let t = if len2 > 0.0 {
        (((c[0] - p[0]) * d[0] + (c[1] - p[1]) * d[1]) / len2).clamp(0.0, 1.0)
    } else {
        0.0
    };
    let x = p[0] + t * d[0] - c[0];
    let y = p[1] + t * d[1] - c[1];
    (x * x + y * y).sqrt()
}

/// A scripted policy that steers the desired position to `x = 0.28` while moving up: the
/// far-left route, at almost no cost per step, so its rollouts time the environment itself
/// (`cargo xtask demos avoiding` reports the environment's steps per second with it).
///
/// ```
/// use vdd_core::Policy;
/// use vdd_tasks::avoiding::FarLeft;
/// let mut p = FarLeft;
/// let a = p.act(&[0.5, -0.2, 0.5, -0.2]).unwrap();
/// assert_eq!(a, vec![-0.01, 0.005]); // left at the step limit, and up
/// ```
#[derive(Debug, Clone, Copy, Default)]
pub struct FarLeft;

impl vdd_core::Policy for FarLeft {
    fn obs_dim(&self) -> usize {
        4
    }
    fn action_dim(&self) -> usize {
        2
    }
    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> std::result::Result<(), CoreError> {
        vdd_core::check_act_args(self, obs, action)?;
        action[0] = (0.28 - obs[0]).clamp(-0.01, 0.01);
        action[1] = 0.005;
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    /// Drives the environment with a memoryless rule "desired x = f(y), move up at `vy`".
    fn drive(f: impl Fn(f32) -> f32, vy: f32) -> AvoidingEnv {
        let mut env = AvoidingEnv::new();
        while env.status() == Status::Running {
            let o = env.observation();
            let ax = (f(o[3]) - o[0]).clamp(-0.01, 0.01);
            env.step(&[ax, vy]).unwrap();
        }
        env
    }

    #[test]
    fn modes_index_round_trip_and_cover_0_to_24() {
        let mut seen = [false; N_MODES];
        for i in 0..N_MODES {
            let m = AvoidingMode::from_index(i).unwrap();
            assert_eq!(m.index(), i);
            assert_eq!(AvoidingMode::new(m.gaps()).unwrap(), m);
            seen[i] = true;
        }
        assert!(seen.iter().all(|&s| s));
        assert!(AvoidingMode::from_index(24).is_err());
        assert!(AvoidingMode::new([0, 3, 0]).is_err());
        assert!(AvoidingMode::new([0, 0, 4]).is_err());
    }

    #[test]
    fn gaps_and_their_centres() {
        assert_eq!(gap_at(0, 0.49), 0);
        assert_eq!(gap_at(0, 0.51), 1);
        assert_eq!(gap_at(1, 0.3), 0);
        assert_eq!(gap_at(1, 0.5), 1);
        assert_eq!(gap_at(1, 0.7), 2);
        assert_eq!(gap_at(2, 0.2), 0);
        assert_eq!(gap_at(2, 0.45), 1);
        assert_eq!(gap_at(2, 0.6), 2);
        assert_eq!(gap_at(2, 0.9), 3);
        assert_relative_eq!(gap_centre(0, 0).unwrap(), 0.425);
        assert_relative_eq!(gap_centre(1, 1).unwrap(), 0.5);
        assert_relative_eq!(gap_centre(2, 3).unwrap(), 0.725);
        for l in 0..N_LEVELS {
            for g in 0..GAPS_PER_LEVEL[l] as u8 {
                assert_eq!(gap_at(l, gap_centre(l, g).unwrap()), g);
            }
        }
        assert!(gap_centre(0, 2).is_err());
        assert!(gap_centre(3, 0).is_err());
    }

    #[test]
    fn dynamics_follow_the_documented_lag_and_clip() {
        let mut env = AvoidingEnv::new();
        env.step(&[0.01, 0.5]).unwrap(); // y clipped to 0.02
        assert_relative_eq!(env.desired()[0], START[0] + 0.01);
        assert_relative_eq!(env.desired()[1], START[1] + ACTION_LIMIT);
        assert_relative_eq!(env.position()[0], START[0] + 0.005);
        assert_relative_eq!(env.position()[1], START[1] + 0.01);
        env.step(&[0.0, 0.0]).unwrap();
        assert_relative_eq!(env.position()[1], START[1] + 0.015);
        assert_eq!(env.steps(), 2);
        assert_eq!(
            env.observation(),
            [env.desired()[0], env.desired()[1], env.position()[0], env.position()[1]]
        );
    }

    #[test]
    fn standing_still_times_out_at_the_step_limit() {
        let mut env = AvoidingEnv::new();
        let mut n = 0;
        while env.step(&[0.0, 0.0]).unwrap() == Status::Running {
            n += 1;
        }
        assert_eq!(n + 1, MAX_STEPS);
        assert_eq!(env.status(), Status::Timeout);
        assert_eq!(env.mode(), None);
    }

    #[test]
    fn straight_up_collides_with_the_first_obstacle() {
        let env = drive(|_| START[0], 0.01);
        assert_eq!(env.status(), Status::Collision);
        // The first contact is where the disc of radius 0.04 around (0.5, -0.1) is reached.
        let y_contact = -0.10 - (0.04f32.powi(2) - 0.025f32.powi(2)).sqrt();
        assert!((env.position()[1] - y_contact).abs() < 0.006, "{:?}", env.position());
        assert_eq!(env.gaps(), [None, None, None]);
    }

    #[test]
    fn scripted_routes_reach_the_expected_modes() {
        // Far left at every level: mode (0, 0, 0).
        let env = drive(|_| 0.28, 0.01);
        assert_eq!(env.status(), Status::Success);
        assert_eq!(env.mode().unwrap().gaps(), [0, 0, 0]);
        // Right, right of both, between the middle and right obstacles: mode (1, 2, 2) = 22.
        let env = drive(|y| if y < 0.17 { 0.65 } else { 0.575 }, 0.01);
        assert_eq!(env.status(), Status::Success);
        assert_eq!(env.mode().unwrap().index(), 22);
        // Left, between, left-middle: (0, 1, 1) = 5.
        let env = drive(
            |y| {
                if y < -0.03 {
                    0.41
                } else if y < 0.17 {
                    0.5
                } else {
                    0.425
                }
            },
            0.008,
        );
        assert_eq!(env.status(), Status::Success, "{:?}", env.position());
        assert_eq!(env.mode().unwrap().index(), 5);
    }

    #[test]
    fn collision_is_checked_along_the_whole_step() {
        // A segment passing through a disc collides even if both ends are outside.
        let c = [0.0, 0.0];
        assert_relative_eq!(segment_disc_distance([-1.0, 0.01], [1.0, 0.01], c), 0.01);
        assert_relative_eq!(segment_disc_distance([1.0, 1.0], [2.0, 1.0], c), 2f32.sqrt());
        assert_relative_eq!(segment_disc_distance([0.3, 0.4], [0.3, 0.4], c), 0.5);
        // Touching distance counts as a collision.
        let mut env = AvoidingEnv::new();
        env.position = [0.5 - 0.04 - 0.004, -0.10];
        env.desired = [0.5, -0.10];
        assert_eq!(env.step_clipped([0.0, 0.0]), Status::Collision);
    }

    #[test]
    fn bad_actions_are_errors() {
        let mut env = AvoidingEnv::new();
        assert!(env.step(&[0.0]).is_err());
        assert!(env.step(&[f32::NAN, 0.0]).is_err());
        assert!(env.step(&[0.0, f32::INFINITY]).is_err());
        assert_eq!(env.steps(), 0);
        assert_eq!(env.reset(), env.observation());
    }
}
