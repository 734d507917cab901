//! The scripted, multimodal Avoiding demonstrator and demonstration generation.
//!
//! # How a demonstration is planned
//!
//! At the start of an episode the [`AvoidingDemonstrator`] draws a behaviour mode uniformly from
//! the 24 (or uses [`DemonstratorConfig::fixed_mode`]) and plans a smooth path:
//!
//! 1. Via points: the start; for each level, a straight passage through the chosen gap from
//!    [`GAP_HALF_HEIGHT`] below the level to as far above it, centred on the gap's centre
//!    ([`gap_centre`]) shifted sideways by `U(±lateral_offset)` and up/down by
//!    `U(±level_jitter)`, with a random slope `dx/dy ∈ U(±tilt)`; and an end point [`END_Y`]
//!    high (past the finish line) at the last passage's `x` `+ U(±end_offset)`.
//! 2. A cubic Hermite spline through the via points with the passages' slopes as tangent
//!    directions (vertical at the start and end) and tangent lengths [`TANGENT_SCALE`] times
//!    each segment's height: the passages are straight, `y` increases along the whole path (it
//!    never turns back down), and `x` follows a smooth S-curve from gap to gap.
//! 3. The spline is tabulated by arc length. A plan whose polyline comes closer to an obstacle
//!    than `radius + EE_RADIUS + clearance_margin` is rejected and redrawn (at most
//!    [`MAX_PLAN_TRIES`] times; then the nominal plan without random offsets, which clears every
//!    obstacle for all 24 modes, is used).
//!
//! Each step the path is followed at a speed drawn per episode from `U(speed)` metres per step,
//! ramped up linearly over the first `ramp_steps` steps. The action moves the desired position
//! to the path point plus Gaussian noise of `noise_std` (the noise does not accumulate: the next
//! action corrects it) and is clipped to `max_speed` in norm. Because the end effector lags the
//! desired position (gain 0.5), it trails the path by about one step's length.
//!
//! ```
//! use vdd_tasks::avoiding::demonstrator::{generate_demonstrations, DemonstratorConfig};
//! let demos = generate_demonstrations(3, 0, &DemonstratorConfig::default()).unwrap();
//! assert_eq!(demos.observations.len(), 3);
//! for (o, a) in demos.observations.iter().zip(&demos.actions) {
//!     assert_eq!((o.ncols(), a.ncols()), (4, 2));
//!     assert_eq!(o.nrows(), a.nrows());
//!     assert!(o.nrows() <= 250);
//! }
//! ```

use rand::Rng as _;
use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Rng, standard_normal};

use super::AvoidingEnv;
use super::rollout::episode_seed;
use super::{
    ACTION_DIM, ACTION_LIMIT, AvoidingMode, EE_RADIUS, LEVEL_Y, MAX_STEPS, N_LEVELS, N_MODES,
    OBS_DIM, OBSTACLES, START, gap_centre, segment_disc_distance,
};
use crate::scripted::{Mode, Script, Scripted, collect};
use crate::{Result, TaskError};

/// Height of the end point of every planned path (past the finish line at 0.35).
pub const END_Y: f32 = 0.42;
/// How many random plans are tried before falling back to the nominal plan.
pub const MAX_PLAN_TRIES: usize = 64;

/// Half the height of the straight passage the planned path takes through each gap.
pub const GAP_HALF_HEIGHT: f32 = 0.02;
/// Length of the spline's tangents at the via points, in units of the segment's height. Above
/// 1 it spreads the turn from a gap's passage towards the next gap over more of the segment
/// (smallest turning radius ≈ 3 cm instead of ≈ 1 cm for the widest swings); below 3 it keeps
/// `y` increasing along every segment (`dy/du ≥ h (3 − TANGENT_SCALE) / 2`, here `h/2`).
pub const TANGENT_SCALE: f32 = 2.0;

const SEGMENTS: usize = 2 * N_LEVELS + 1;
const SAMPLES_PER_SEGMENT: usize = 64;
const TABLE: usize = SEGMENTS * SAMPLES_PER_SEGMENT + 1;

/// Parameters of the scripted demonstrator (lengths in metres, speeds in metres per step).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DemonstratorConfig {
    /// Range `[min, max]` of the per-episode path speed.
    pub speed: [f32; 2],
    /// Steps over which the speed ramps up from zero.
    pub ramp_steps: usize,
    /// Half-width of the uniform sideways offset of each gap via point.
    pub lateral_offset: f32,
    /// Half-width of the uniform vertical offset of each gap via point.
    pub level_jitter: f32,
    /// Largest path slope `|dx/dy|` when crossing a gap.
    pub tilt: f32,
    /// Half-width of the uniform sideways offset of the end point.
    pub end_offset: f32,
    /// Standard deviation of the Gaussian noise added to each desired position.
    pub noise_std: f32,
    /// Largest norm of an action.
    pub max_speed: f32,
    /// Extra clearance a plan must keep from every obstacle beyond `radius + EE_RADIUS`.
    pub clearance_margin: f32,
    /// Always demonstrate this mode instead of drawing one uniformly.
    pub fixed_mode: Option<AvoidingMode>,
}

impl Default for DemonstratorConfig {
    fn default() -> Self {
        Self {
            speed: [0.0055, 0.0075],
            ramp_steps: 8,
            lateral_offset: 0.02,
            level_jitter: 0.015,
            tilt: 0.25,
            end_offset: 0.03,
            noise_std: 0.0005,
            max_speed: 0.01,
            clearance_margin: 0.012,
            fixed_mode: None,
        }
    }
}

impl DemonstratorConfig {
    /// Checks every field's range.
    pub fn validate(&self) -> Result<()> {
        let bad = |msg: String| Err(TaskError::InvalidArgument(format!("demonstrator: {msg}")));
        let fields = [
            ("speed[0]", self.speed[0]),
            ("speed[1]", self.speed[1]),
            ("lateral_offset", self.lateral_offset),
            ("level_jitter", self.level_jitter),
            ("tilt", self.tilt),
            ("end_offset", self.end_offset),
            ("noise_std", self.noise_std),
            ("max_speed", self.max_speed),
            ("clearance_margin", self.clearance_margin),
        ];
        if let Some((name, v)) = fields.iter().find(|(_, v)| !(v.is_finite() && *v >= 0.0)) {
            return bad(format!("{name} must be finite and non-negative, got {v}"));
        }
        if !(self.speed[0] > 0.0 && self.speed[0] <= self.speed[1]) {
            return bad(format!("speed range {:?} must satisfy 0 < min <= max", self.speed));
        }
        if !(self.speed[1] < self.max_speed && self.max_speed <= ACTION_LIMIT) {
            return bad(format!(
                "need speed max {} < max_speed {} <= ACTION_LIMIT {ACTION_LIMIT}",
                self.speed[1], self.max_speed
            ));
        }
        if self.ramp_steps == 0 {
            return bad("ramp_steps must be at least 1".into());
        }
        // Beyond these the via points leave their gaps or the path turns back on itself.
        if self.lateral_offset > 0.05 || self.level_jitter > 0.05 || self.tilt > 2.0 {
            return bad(format!(
                "lateral_offset {} and level_jitter {} must be <= 0.05, tilt {} <= 2",
                self.lateral_offset, self.level_jitter, self.tilt
            ));
        }
        Ok(())
    }
}

/// The scripted multimodal demonstrator: a [`Policy`](vdd_core::Policy) for the Avoiding task, the
/// [`Scripted`] demonstrator of [`AvoidingScript`].
///
/// It keeps one plan per environment between [`Policy::reset`](vdd_core::Policy::reset)s: [`Policy::act_into`](vdd_core::Policy::act_into) drives a
/// single environment; [`Policy::act_batch`](vdd_core::Policy::act_batch) drives one environment per row (row `i` must stay
/// the same environment until the next reset, as lockstep rollouts guarantee). Plans are drawn
/// from the demonstrator's own stream, which [`Policy::seed`](vdd_core::Policy::seed) resets.
///
/// ```
/// use vdd_tasks::avoiding::demonstrator::{AvoidingDemonstrator, DemonstratorConfig};
/// use vdd_tasks::avoiding::rollout::{evaluate, EvalConfig};
/// let mut demo = AvoidingDemonstrator::new(DemonstratorConfig::default()).unwrap();
/// let eval = evaluate(&mut demo, &EvalConfig { n_rollouts: 48, ..EvalConfig::default() }).unwrap();
/// assert!(eval.metrics.success_rate >= 0.95);
/// assert!(eval.metrics.modes_reached >= 16);
/// ```
pub type AvoidingDemonstrator = Scripted<AvoidingScript>;

/// The Avoiding demonstrator's script: a mode and a smooth path per episode, followed at the
/// episode's speed.
#[derive(Debug, Clone)]
pub struct AvoidingScript {
    config: DemonstratorConfig,
}

impl Scripted<AvoidingScript> {
    /// A demonstrator with a validated `config`, seeded with 0.
    pub fn new(config: DemonstratorConfig) -> Result<Self> {
        config.validate()?;
        Ok(Self::with_script(AvoidingScript { config }))
    }

    /// The configuration.
    pub fn config(&self) -> &DemonstratorConfig {
        &self.script().config
    }

    /// The mode planned for environment (row) `row` of the current episode, once it has acted.
    pub fn planned_mode(&self, row: usize) -> Option<AvoidingMode> {
        self.plan(row).map(|p| p.mode)
    }
}

impl Script for AvoidingScript {
    type Plan = Plan;
    const OBS_DIM: usize = OBS_DIM;
    const ACTION_DIM: usize = ACTION_DIM;
    const STREAM: &'static str = "avoiding-demonstrator";

    /// Every episode starts at [`START`]: the plan does not depend on the observation.
    fn start(&self, _: &[f32], rng: &mut Rng) -> std::result::Result<Plan, CoreError> {
        Ok(Plan::sample(&self.config, rng))
    }

    fn act(&self, plan: &mut Plan, rng: &mut Rng, obs: &[f32], action: &mut [f32]) {
        action.copy_from_slice(&plan.act(&self.config, rng, [obs[0], obs[1]]));
    }
}

/// Random perturbations of the nominal plan of a mode.
#[derive(Debug, Clone, Copy, Default)]
struct Offsets {
    dx: [f32; N_LEVELS],
    dy: [f32; N_LEVELS],
    slope: [f32; N_LEVELS],
    end_dx: f32,
}

impl Offsets {
    fn sample(c: &DemonstratorConfig, rng: &mut Rng) -> Self {
        let mut u = |h: f32| h * (2.0 * rng.random::<f32>() - 1.0);
        let mut o = Offsets::default();
        for l in 0..N_LEVELS {
            o.dx[l] = u(c.lateral_offset);
            o.dy[l] = u(c.level_jitter);
            o.slope[l] = u(c.tilt);
        }
        o.end_dx = u(c.end_offset);
        o
    }
}

/// One episode's plan: a path tabulated by arc length, and the progress along it.
#[derive(Debug, Clone)]
pub struct Plan {
    mode: AvoidingMode,
    points: [[f32; 2]; TABLE],
    arc: [f32; TABLE],
    speed: f32,
    travelled: f32,
    t: usize,
    cursor: usize,
}

impl Plan {
    fn sample(c: &DemonstratorConfig, rng: &mut Rng) -> Self {
        let mode = match c.fixed_mode {
            Some(m) => m,
            None => AvoidingMode::from_index(rng.random_range(0..N_MODES))
                .expect("index drawn in range"),
        };
        let speed = c.speed[0] + (c.speed[1] - c.speed[0]) * rng.random::<f32>();
        for _ in 0..MAX_PLAN_TRIES {
            let plan = Self::build(mode, &Offsets::sample(c, rng), speed);
            if plan.clears(EE_RADIUS + c.clearance_margin) {
                return plan;
            }
        }
        Self::build(mode, &Offsets::default(), speed)
    }

    fn build(mode: AvoidingMode, o: &Offsets, speed: f32) -> Self {
        let half = GAP_HALF_HEIGHT;
        // Via points and path slopes dx/dy there: the start, a straight passage through each
        // gap from `GAP_HALF_HEIGHT` below the level to as far above it, and the end point.
        let mut via = [START; SEGMENTS + 1];
        let mut slope = [0.0f32; SEGMENTS + 1];
        for l in 0..N_LEVELS {
            let g = mode.gaps()[l];
            let x = gap_centre(l, g).expect("modes only hold valid gaps") + o.dx[l];
            let y = LEVEL_Y[l] + o.dy[l];
            let k = o.slope[l];
            via[2 * l + 1] = [x - k * half, y - half];
            via[2 * l + 2] = [x + k * half, y + half];
            slope[2 * l + 1] = k;
            slope[2 * l + 2] = k;
        }
        via[SEGMENTS] = [via[SEGMENTS - 1][0] + o.end_dx, END_Y];
        let mut points = [[0.0f32; 2]; TABLE];
        for s in 0..SEGMENTS {
            let (p0, p1) = (via[s], via[s + 1]);
            let h = p1[1] - p0[1];
            let t = TANGENT_SCALE * h;
            let (m0, m1) = (slope[s] * t, slope[s + 1] * t);
            for k in 0..SAMPLES_PER_SEGMENT {
                let u = k as f32 / SAMPLES_PER_SEGMENT as f32;
                let (u2, u3) = (u * u, u * u * u);
                let h00 = 2.0 * u3 - 3.0 * u2 + 1.0;
                let h10 = u3 - 2.0 * u2 + u;
                let h01 = -2.0 * u3 + 3.0 * u2;
                let h11 = u3 - u2;
                points[s * SAMPLES_PER_SEGMENT + k] = [
                    h00 * p0[0] + h10 * m0 + h01 * p1[0] + h11 * m1,
                    h00 * p0[1] + (h10 + h11) * t + h01 * p1[1],
                ];
            }
        }
        points[TABLE - 1] = via[SEGMENTS];
        let mut arc = [0.0f32; TABLE];
        for k in 1..TABLE {
            let d = [points[k][0] - points[k - 1][0], points[k][1] - points[k - 1][1]];
            arc[k] = arc[k - 1] + (d[0] * d[0] + d[1] * d[1]).sqrt();
        }
        Self { mode, points, arc, speed, travelled: 0.0, t: 0, cursor: 0 }
    }

    /// Whether the path keeps at least `needed` from every obstacle's edge.
    fn clears(&self, needed: f32) -> bool {
        OBSTACLES.iter().all(|o| {
            // `y` increases along the table, so only the points within `reach` of the
            // obstacle's height (and the segments leading in and out of that band) can come
            // closer than `reach`.
            let reach = o.radius + needed;
            let lo = self.points.partition_point(|p| p[1] <= o.centre[1] - reach).max(1);
            let hi = self.points.partition_point(|p| p[1] < o.centre[1] + reach).min(TABLE - 1);
            (lo..=hi).all(|k| {
                segment_disc_distance(self.points[k - 1], self.points[k], o.centre) >= reach
            })
        })
    }

    /// Smallest distance from the path to an obstacle's edge.
    #[cfg(test)]
    fn clearance(&self) -> f32 {
        let mut best = f32::INFINITY;
        for k in 1..TABLE {
            for o in &OBSTACLES {
                let d = segment_disc_distance(self.points[k - 1], self.points[k], o.centre);
                best = best.min(d - o.radius);
            }
        }
        best
    }

    fn length(&self) -> f32 {
        self.arc[TABLE - 1]
    }

    /// The path point `s` along the path (monotone in `s` between calls).
    fn point_at(&mut self, s: f32) -> [f32; 2] {
        while self.cursor + 2 < TABLE && self.arc[self.cursor + 1] < s {
            self.cursor += 1;
        }
        let k = self.cursor;
        let (a0, a1) = (self.arc[k], self.arc[k + 1]);
        let u = if a1 > a0 { ((s - a0) / (a1 - a0)).clamp(0.0, 1.0) } else { 0.0 };
        let (p, q) = (self.points[k], self.points[k + 1]);
        [p[0] + u * (q[0] - p[0]), p[1] + u * (q[1] - p[1])]
    }

    fn act(&mut self, c: &DemonstratorConfig, rng: &mut Rng, desired: [f32; 2]) -> [f32; 2] {
        self.t += 1;
        let ramp = (self.t as f32 / c.ramp_steps as f32).min(1.0);
        self.travelled = (self.travelled + self.speed * ramp).min(self.length());
        let target = self.point_at(self.travelled);
        let mut a = [
            target[0] + c.noise_std * standard_normal(rng) - desired[0],
            target[1] + c.noise_std * standard_normal(rng) - desired[1],
        ];
        let norm = a[0].hypot(a[1]);
        if norm > c.max_speed {
            let k = c.max_speed / norm;
            a = [a[0] * k, a[1] * k];
        }
        a
    }
}

/// Avoiding's demonstrations: one `T x 4` observation (previous desired position, current
/// position) and `T x 2` action (change of desired position) matrix per successful episode.
pub type Demonstrations = crate::scripted::Demonstrations<AvoidingMode>;

impl Mode for AvoidingMode {
    const COUNT: usize = super::N_MODES;
    fn index(&self) -> usize {
        AvoidingMode::index(self)
    }
}

/// Runs the demonstrator until `n` episodes have succeeded and returns them (failed episodes,
/// rare, are skipped). Episode `i` is seeded with
/// [`episode_seed`]`(seed, i)`, so the result is deterministic.
/// More than `2n + 16` episodes without `n` successes is an error.
pub fn generate_demonstrations(
    n: usize,
    seed: u64,
    config: &DemonstratorConfig,
) -> Result<Demonstrations> {
    let mut demo = AvoidingDemonstrator::new(config.clone())?;
    let seeds = |i| (episode_seed(seed, i), 0);
    collect::<AvoidingEnv, _, _>(&mut demo, (), (n, MAX_STEPS), seeds, |r| {
        r.success().then(|| r.mode()).flatten()
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::avoiding::rollout::{EvalConfig, Stepping, evaluate, rollout};
    use crate::avoiding::{AvoidingEnv, FINISH_Y, MAX_STEPS, TRACKING_GAIN};
    use faer::Mat;
    use vdd_core::{Policy, Seeds};

    fn demo() -> AvoidingDemonstrator {
        AvoidingDemonstrator::new(DemonstratorConfig::default()).unwrap()
    }

    #[test]
    fn nominal_plans_of_all_modes_clear_the_obstacles() {
        let c = DemonstratorConfig::default();
        for m in 0..N_MODES {
            let mode = AvoidingMode::from_index(m).unwrap();
            let plan = Plan::build(mode, &Offsets::default(), 0.005);
            assert!(
                plan.clearance() >= EE_RADIUS + c.clearance_margin,
                "mode {:?}: clearance {}",
                mode.gaps(),
                plan.clearance()
            );
            // The path ends past the finish line and never turns back down.
            assert!(plan.points[TABLE - 1][1] > FINISH_Y);
            assert!(plan.points.windows(2).all(|w| w[1][1] > w[0][1]));
        }
    }

    #[test]
    fn random_plans_are_rarely_rejected() {
        // If offsets were too wide most draws would fall back to the nominal plan; count them.
        let c = DemonstratorConfig::default();
        let mut rng = Seeds::new(5).stream("t");
        let (mut ok, n) = (0, 2000);
        for _ in 0..n {
            let mode = AvoidingMode::from_index(rng.random_range(0..N_MODES)).unwrap();
            let plan = Plan::build(mode, &Offsets::sample(&c, &mut rng), 0.005);
            let needed = EE_RADIUS + c.clearance_margin;
            // The fast test agrees with the exhaustive one (it relies on y increasing).
            assert!(plan.points.windows(2).all(|w| w[1][1] > w[0][1]));
            assert_eq!(plan.clears(needed), plan.clearance() >= needed);
            ok += usize::from(plan.clears(needed));
        }
        assert!(ok as f64 / n as f64 > 0.95, "accepted {ok} of {n}");
    }

    #[test]
    fn every_mode_is_demonstrated_as_planned() {
        for m in 0..N_MODES {
            let mode = AvoidingMode::from_index(m).unwrap();
            let config = DemonstratorConfig { fixed_mode: Some(mode), ..Default::default() };
            let mut d = AvoidingDemonstrator::new(config).unwrap();
            for seed in 0..3 {
                let r = rollout(&mut d, seed, false).unwrap();
                assert!(r.success(), "mode {m} seed {seed}: {:?}", r.status);
                assert_eq!(r.mode(), Some(mode));
                assert_eq!(d.planned_mode(0), Some(mode));
            }
        }
    }

    #[test]
    fn demonstrator_succeeds_with_high_task_entropy() {
        // 500 rollouts are measured by `cargo xtask demos`; 150 here keep the test fast.
        let cfg = EvalConfig { n_rollouts: 150, seed: 1, ..EvalConfig::default() };
        let e = evaluate(&mut demo(), &cfg).unwrap();
        assert!(e.metrics.success_rate >= 0.99, "{:?}", e.metrics);
        assert!(e.metrics.task_entropy >= 0.95, "{:?}", e.metrics);
        assert_eq!(e.metrics.modes_reached, 24);
        let steps = e.metrics.mean_success_steps;
        assert!((80.0..200.0).contains(&steps), "mean length {steps}");
        assert!(e.rollouts.iter().all(|r| r.steps < MAX_STEPS));
        // Lockstep (one plan per row) works as well.
        let cfg = EvalConfig { stepping: Stepping::Lockstep { batch_size: 32 }, ..cfg };
        let e = evaluate(&mut demo(), &cfg).unwrap();
        assert!(e.metrics.success_rate >= 0.99, "{:?}", e.metrics);
        assert!(e.metrics.task_entropy >= 0.95, "{:?}", e.metrics);
    }

    #[test]
    fn demonstrations_are_smooth_bounded_and_consistent_with_the_dynamics() {
        let c = DemonstratorConfig::default();
        let d = generate_demonstrations(12, 3, &c).unwrap();
        assert_eq!(d, generate_demonstrations(12, 3, &c).unwrap());
        assert_ne!(d.observations, generate_demonstrations(12, 4, &c).unwrap().observations);
        assert_eq!(d.modes.len(), 12);
        let mut lengths = Vec::new();
        for (o, a) in d.observations.iter().zip(&d.actions) {
            let t = o.nrows();
            lengths.push(t);
            assert_eq!((o.ncols(), a.nrows(), a.ncols()), (4, t, 2));
            for i in 0..t {
                assert!(a[(i, 0)].hypot(a[(i, 1)]) <= c.max_speed + 1e-6);
                if i + 1 < t {
                    // Desired position integrates the action; position lags it with gain 0.5.
                    for j in 0..2 {
                        assert!((o[(i + 1, j)] - o[(i, j)] - a[(i, j)]).abs() < 1e-6);
                        let lag = o[(i, 2 + j)] + TRACKING_GAIN * (o[(i + 1, j)] - o[(i, 2 + j)]);
                        assert!((o[(i + 1, 2 + j)] - lag).abs() < 1e-6);
                    }
                }
            }
            // The episode ends when the finish line is crossed.
            let mut env = AvoidingEnv::new();
            for i in 0..t {
                env.step(&[a[(i, 0)], a[(i, 1)]]).unwrap();
            }
            assert!(env.position()[1] > FINISH_Y);
        }
        // Speeds are randomised, so lengths vary.
        let (lo, hi) = (lengths.iter().min().unwrap(), lengths.iter().max().unwrap());
        assert!(hi - lo > 10, "lengths {lengths:?}");
        assert!(generate_demonstrations(0, 0, &c).is_err());
        // Smooth: without noise, consecutive actions differ by little: at most ≈ speed · speed /
        // (smallest turning radius ≈ 0.03) ≈ 0.0019, i.e. the step turns by at most ≈ 15°.
        let quiet = DemonstratorConfig { noise_std: 0.0, ..c };
        let d = generate_demonstrations(24, 3, &quiet).unwrap();
        let mut worst = 0.0f32;
        for a in &d.actions {
            for i in 1..a.nrows() {
                worst = worst.max((a[(i, 0)] - a[(i - 1, 0)]).hypot(a[(i, 1)] - a[(i - 1, 1)]));
            }
        }
        assert!(worst < 0.0025, "largest change of consecutive actions {worst}");
    }

    #[test]
    fn batch_size_changes_mid_episode_and_bad_configs_are_errors() {
        let mut d = demo();
        d.act(&[0.525, -0.28, 0.525, -0.28]).unwrap();
        let obs = Mat::<f32>::zeros(2, 4);
        let mut act = Mat::<f32>::zeros(2, 2);
        assert!(d.act_batch(obs.as_ref(), act.as_mut()).is_err());
        d.reset();
        assert!(d.act_batch(obs.as_ref(), act.as_mut()).is_ok());
        assert!(d.act(&[0.0; 4]).is_err());
        assert!(d.act(&[0.0; 3]).is_err());
        assert!(d.act(&[f32::NAN, 0.0, 0.0, 0.0]).is_err());
        let nan = Mat::from_fn(2, 4, |_, _| f32::NAN);
        assert!(d.act_batch(nan.as_ref(), act.as_mut()).is_err());
        let bad = |f: fn(&mut DemonstratorConfig)| {
            let mut c = DemonstratorConfig::default();
            f(&mut c);
            AvoidingDemonstrator::new(c).is_err()
        };
        assert!(bad(|c| c.speed = [0.0, 0.005]));
        assert!(bad(|c| c.speed = [0.006, 0.005]));
        assert!(bad(|c| c.max_speed = 0.005));
        assert!(bad(|c| c.max_speed = 0.05));
        assert!(bad(|c| c.noise_std = f32::NAN));
        assert!(bad(|c| c.tilt = -1.0));
        assert!(bad(|c| c.lateral_offset = 0.2));
        assert!(bad(|c| c.ramp_steps = 0));
    }

    #[test]
    fn seeding_controls_the_demonstrator() {
        let mut d = demo();
        let a = rollout(&mut d, 9, true).unwrap();
        let b = rollout(&mut d, 9, true).unwrap();
        let c = rollout(&mut d, 10, true).unwrap();
        assert_eq!(a, b);
        assert_ne!(a.trajectory, c.trajectory);
    }
}
