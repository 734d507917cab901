//! Toy tasks with an analytic expert distribution: Gaussian mixtures whose modes sit on a circle.
//!
//! * `toy-gmm` ([`CircleGmm::toy_gmm`]): 2-D actions, 8 modes on a circle of radius 2, isotropic
//!   std 0.5, equal weights, one fixed state (`s = 0`; the state is 1-D so that both toy tasks
//!   share one interface, and its value is ignored).
//! * `toy-conditional` ([`CircleGmm::toy_conditional`]): state `s ∈ [0, 2π)`; mode `k` sits at
//!   angle `s + 2πk/K`, so the mixture rotates with the state.
//!
//! The mixture itself ([`CircleGmm::mixture_at`]) is both the data source and, in the diffusion
//! crate, an exact teacher (the score of a Gaussian mixture smoothed by noise is analytic).

use faer::{Mat, MatRef};
use rand::Rng as _;
use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Seeds, check_finite, check_len, check_shape};

use crate::{Result, TaskError, normalized_entropy};

/// How far (in standard deviations) an action may lie from its nearest mode's mean and still
/// count as "on" that mode in [`CircleGmm::coverage`].
pub const ON_MODE_STDS: f32 = 3.0;

/// Share of its fair count `n · w_k` that mode `k` must receive to count as covered in
/// [`CircleGmm::coverage`].
pub const COVERAGE_SHARE: f32 = 0.25;

/// Data of a toy recipe (the recipes' `[data]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToyData {
    /// Number of states (and mixture samples) VDD distils on; learned teachers train on them.
    /// In `1..=10^8`, and their memory must fit.
    pub points: usize,
}

impl ToyData {
    /// Checks the documented range of `points` and its memory.
    pub fn validate(&self) -> Result<()> {
        let n = self.points;
        if !(1..=100_000_000).contains(&n) {
            return Err(TaskError::InvalidArgument(format!(
                "data.points must be in 1..=1e8, got {n}"
            )));
        }
        let bytes = vdd_core::memory::product(&[n, 3, 4, 4]);
        Ok(vdd_core::memory::check_fits(&format!("data.points = {n}"), bytes)?)
    }
}

/// Figure 2 of a toy recipe: the student's density and the teacher's score (the recipes'
/// `[plots]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToyPlots {
    /// Write the figure.
    pub enabled: bool,
    /// Also PNG.
    pub png: bool,
    /// Density grid cells per side, in `1..=2048`.
    pub grid: usize,
    /// Score arrows per side, in `1..=256`.
    pub arrows: usize,
    /// Half-width of the plotted square (finite, `> 0`).
    pub extent: f32,
    /// Panels of `toy-conditional` (states spread over `[0, 2π)`), in `0..=64`.
    pub states: usize,
}

impl ToyPlots {
    /// Checks the documented ranges of every field.
    pub fn validate(&self) -> Result<()> {
        let bad = |what: String| Err(TaskError::InvalidArgument(format!("plots.{what}")));
        for (name, v, max) in [("grid", self.grid, 2048), ("arrows", self.arrows, 256)] {
            if !(1..=max).contains(&v) {
                return bad(format!("{name} must be in 1..={max}, got {v}"));
            }
        }
        if self.states > 64 {
            return bad(format!("states must be in 0..=64, got {}", self.states));
        }
        if !(self.extent.is_finite() && self.extent > 0.0) {
            return bad(format!("extent must be finite and > 0, got {}", self.extent));
        }
        Ok(())
    }
}

/// A 2-D isotropic Gaussian mixture whose `K` equally weighted modes lie on a circle, optionally
/// rotating with a scalar state.
///
/// ```
/// use vdd_tasks::toy::CircleGmm;
/// let task = CircleGmm::toy_gmm();
/// let mix = task.mixture_at(&[0.0]).unwrap();
/// assert_eq!(mix.means.len(), 8);
/// assert!((mix.means[0][0] - 2.0).abs() < 1e-6);
///
/// let (states, actions) = task.sample(1000, 0).unwrap();
/// let cov = task.coverage(states.as_ref(), actions.as_ref()).unwrap();
/// assert_eq!(cov.covered, 8);
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(try_from = "CircleGmmFields")]
pub struct CircleGmm {
    n_modes: usize,
    radius: f32,
    std: f32,
    rotating: bool,
}

/// The mixture `Σ_k w_k N(μ_k, σ² I)` at one state.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Mixture {
    /// Mixture weights `w_k` (they sum to one).
    pub weights: Vec<f32>,
    /// Mode means `μ_k`.
    pub means: Vec<[f32; 2]>,
    /// The isotropic standard deviation `σ` shared by every mode.
    pub std: f32,
}

/// How a batch of actions spreads over a [`CircleGmm`]'s modes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ModeCoverage {
    /// On-mode samples assigned to each mode (nearest mean, within [`ON_MODE_STDS`]).
    pub counts: Vec<usize>,
    /// Samples farther than [`ON_MODE_STDS`] standard deviations from every mode.
    pub off_mode: usize,
    /// Modes whose count reaches [`COVERAGE_SHARE`] of their fair share `n · w_k` (at least 1).
    pub covered: usize,
    /// Entropy of the on-mode histogram divided by `log K` (1 for a perfectly even spread).
    pub entropy: f32,
}

impl CircleGmm {
    /// A mixture of `n_modes` modes on a circle of `radius`, each with isotropic `std`; with
    /// `rotating`, mode `k` sits at angle `s + 2πk/K` for state `s`, otherwise at `2πk/K`.
    pub fn new(n_modes: usize, radius: f32, std: f32, rotating: bool) -> Result<Self> {
        if n_modes < 2 || !(radius.is_finite() && radius > 0.0) || !(std.is_finite() && std > 0.0) {
            return Err(TaskError::InvalidArgument(format!(
                "circle GMM needs >= 2 modes and positive finite radius and std, got \
                 {n_modes} modes, radius {radius}, std {std}"
            )));
        }
        Ok(Self { n_modes, radius, std, rotating })
    }

    /// The `toy-gmm` task: 8 modes, radius 2, std 0.5, fixed state.
    pub fn toy_gmm() -> Self {
        Self { n_modes: 8, radius: 2.0, std: 0.5, rotating: false }
    }

    /// The `toy-conditional` task: 4 modes, radius 2, std 0.5, rotating with the state.
    ///
    /// `tasks.md` leaves `K` open for this task. Four modes (rather than eight) keep adjacent
    /// modes well separated (`2·2·sin(π/4)/0.5 ≈ 5.7` standard deviations apart, against `≈ 3.1`
    /// for eight), so nearest-mode assignment in [`CircleGmm::coverage`] is unambiguous while the
    /// student must still learn a state-dependent gating and state-dependent means.
    pub fn toy_conditional() -> Self {
        Self { n_modes: 4, radius: 2.0, std: 0.5, rotating: true }
    }

    /// The task's exact teacher: the mixture itself as a [`vdd_core::gmm::GmmTeacher`], whose
    /// noise-smoothed score is exact at every noise level (1-D state, 2-D actions).
    ///
    /// ```
    /// use vdd_core::ScoreModel;
    /// let teacher = vdd_tasks::toy::CircleGmm::toy_gmm().teacher().unwrap();
    /// assert_eq!((teacher.state_dim(), teacher.action_dim()), (1, 2));
    /// ```
    pub fn teacher(&self) -> Result<vdd_core::gmm::GmmTeacher> {
        Ok(if self.rotating {
            vdd_core::gmm::GmmTeacher::rotating_toy(self.n_modes, self.radius, self.std)?
        } else {
            let gmm = vdd_core::gmm::Gmm::circle(self.n_modes, self.radius, self.std, 0.0)?;
            vdd_core::gmm::GmmTeacher::fixed(gmm, 1)
        })
    }

    /// Number of modes `K`.
    pub fn n_modes(&self) -> usize {
        self.n_modes
    }

    /// State dimension (always 1).
    pub fn state_dim(&self) -> usize {
        1
    }

    /// Action dimension (always 2).
    pub fn action_dim(&self) -> usize {
        2
    }

    /// Whether the modes rotate with the state.
    pub fn is_rotating(&self) -> bool {
        self.rotating
    }

    /// The mixture at `state` (a 1-element slice; ignored by a non-rotating task).
    pub fn mixture_at(&self, state: &[f32]) -> Result<Mixture> {
        let s = self.check_state(state)?;
        let w = 1.0 / self.n_modes as f32;
        Ok(Mixture {
            weights: vec![w; self.n_modes],
            means: (0..self.n_modes).map(|k| self.mean(s, k)).collect(),
            std: self.std,
        })
    }

    /// Draws `n` (state, action) pairs: states uniform in `[0, 2π)` for a rotating task (zero
    /// otherwise), actions from the mixture at each state. Returns `(n x 1, n x 2)` matrices.
    pub fn sample(&self, n: usize, seed: u64) -> Result<(Mat<f32>, Mat<f32>)> {
        if n == 0 {
            return Err(TaskError::InvalidArgument("cannot sample 0 (state, action) pairs".into()));
        }
        let bytes = vdd_core::memory::product(&[n, 3, 4]);
        vdd_core::memory::check_fits(&format!("{n} (state, action) pairs"), bytes)?;
        let mut rng = Seeds::new(seed).stream("toy-gmm-sample");
        let mut states = Mat::<f32>::zeros(n, 1);
        let mut actions = Mat::<f32>::zeros(n, 2);
        for i in 0..n {
            let s = if self.rotating { rng.random_range(0.0..std::f32::consts::TAU) } else { 0.0 };
            let k = rng.random_range(0..self.n_modes);
            let m = self.mean(s, k);
            states[(i, 0)] = s;
            actions[(i, 0)] = m[0] + self.std * vdd_core::standard_normal(&mut rng);
            actions[(i, 1)] = m[1] + self.std * vdd_core::standard_normal(&mut rng);
        }
        Ok((states, actions))
    }

    /// The mode nearest to `action` at `state`, and the distance to its mean in standard
    /// deviations.
    pub fn nearest_mode(&self, state: &[f32], action: &[f32]) -> Result<(usize, f32)> {
        let s = self.check_state(state)?;
        check_len("action", action.len(), 2)?;
        if !action.iter().all(|x| x.is_finite()) {
            return Err(CoreError::NonFinite { what: "action" }.into());
        }
        Ok(self.nearest(s, [action[0], action[1]]))
    }

    /// Assigns every row of `actions` (`n x 2`) at the matching row of `states` (`n x 1`) to its
    /// nearest mode and summarises the spread: per-mode counts, off-mode samples, covered modes
    /// and normalised entropy. An empty batch is an error.
    pub fn coverage(
        &self,
        states: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
    ) -> Result<ModeCoverage> {
        let n = actions.nrows();
        if n == 0 {
            return Err(TaskError::InvalidArgument("coverage of an empty batch".into()));
        }
        check_shape("states", states, n, 1)?;
        check_shape("actions", actions, n, 2)?;
        check_finite("states", states)?;
        check_finite("actions", actions)?;
        let mut counts = vec![0usize; self.n_modes];
        let mut off_mode = 0;
        for i in 0..n {
            let (k, d) = self.nearest(states[(i, 0)], [actions[(i, 0)], actions[(i, 1)]]);
            if d <= ON_MODE_STDS {
                counts[k] += 1;
            } else {
                off_mode += 1;
            }
        }
        let need = ((COVERAGE_SHARE * n as f32 / self.n_modes as f32).ceil() as usize).max(1);
        let covered = counts.iter().filter(|&&c| c >= need).count();
        let entropy = normalized_entropy(&counts);
        Ok(ModeCoverage { counts, off_mode, covered, entropy })
    }

    fn check_state(&self, state: &[f32]) -> Result<f32> {
        check_len("state", state.len(), 1)?;
        if !state[0].is_finite() {
            return Err(CoreError::NonFinite { what: "state" }.into());
        }
        Ok(state[0])
    }

    fn angle(&self, s: f32, k: usize) -> f32 {
        let base = std::f32::consts::TAU * k as f32 / self.n_modes as f32;
        if self.rotating { base + s } else { base }
    }

    fn mean(&self, s: f32, k: usize) -> [f32; 2] {
        let a = self.angle(s, k);
        [self.radius * a.cos(), self.radius * a.sin()]
    }

    fn nearest(&self, s: f32, a: [f32; 2]) -> (usize, f32) {
        let mut best = (0, f32::INFINITY);
        for k in 0..self.n_modes {
            let m = self.mean(s, k);
            let d2 = (a[0] - m[0]).powi(2) + (a[1] - m[1]).powi(2);
            if d2 < best.1 {
                best = (k, d2);
            }
        }
        (best.0, best.1.sqrt() / self.std)
    }
}

/// The serialised form of [`CircleGmm`], validated by [`CircleGmm::new`] on deserialisation.
#[derive(Deserialize)]
struct CircleGmmFields {
    n_modes: usize,
    radius: f32,
    std: f32,
    rotating: bool,
}

impl TryFrom<CircleGmmFields> for CircleGmm {
    type Error = TaskError;
    fn try_from(f: CircleGmmFields) -> Result<Self> {
        CircleGmm::new(f.n_modes, f.radius, f.std, f.rotating)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    #[test]
    fn the_exact_teacher_is_the_task_mixture() {
        for task in [CircleGmm::toy_gmm(), CircleGmm::toy_conditional()] {
            let teacher = task.teacher().unwrap();
            for s in [0.0f32, 1.3, 4.0] {
                let mix = task.mixture_at(&[s]).unwrap();
                let g = teacher.mixture_at(&[s]).unwrap();
                assert_eq!(g.num_components(), mix.means.len());
                for (k, m) in mix.means.iter().enumerate() {
                    assert!(
                        (g.mean(k)[0] - m[0]).abs() < 1e-5 && (g.mean(k)[1] - m[1]).abs() < 1e-5
                    );
                }
            }
        }
    }

    #[test]
    fn toy_gmm_means_lie_on_the_circle_and_weights_sum_to_one() {
        let t = CircleGmm::toy_gmm();
        let m = t.mixture_at(&[1.3]).unwrap();
        assert_eq!(m.means.len(), 8);
        assert_relative_eq!(m.weights.iter().sum::<f32>(), 1.0, epsilon = 1e-6);
        for (k, mu) in m.means.iter().enumerate() {
            assert_relative_eq!(mu[0].hypot(mu[1]), 2.0, epsilon = 1e-5);
            let a = std::f32::consts::TAU * k as f32 / 8.0;
            assert_relative_eq!(
                mu[1].atan2(mu[0]).rem_euclid(std::f32::consts::TAU),
                a,
                epsilon = 1e-4
            );
        }
        // The fixed task ignores the state.
        assert_eq!(t.mixture_at(&[0.0]).unwrap(), m);
    }

    #[test]
    fn conditional_modes_rotate_with_the_state() {
        let t = CircleGmm::toy_conditional();
        let s = 0.4f32;
        let m = t.mixture_at(&[s]).unwrap();
        assert_relative_eq!(m.means[0][0], 2.0 * s.cos(), epsilon = 1e-6);
        assert_relative_eq!(m.means[0][1], 2.0 * s.sin(), epsilon = 1e-6);
        assert_ne!(m, t.mixture_at(&[0.0]).unwrap());
    }

    #[test]
    fn samples_match_the_mixture_and_are_seeded() {
        let t = CircleGmm::toy_conditional();
        let (s, a) = t.sample(4000, 3).unwrap();
        let (s2, a2) = t.sample(4000, 3).unwrap();
        assert_eq!(a, a2);
        assert_eq!(s, s2);
        assert_ne!(a, t.sample(4000, 4).unwrap().1);
        // Residuals from the nearest mode have the mixture's std.
        let mut sq = 0.0f64;
        for i in 0..4000 {
            let (_, d) = t.nearest_mode(&[s[(i, 0)]], &[a[(i, 0)], a[(i, 1)]]).unwrap();
            sq += f64::from(d * d);
        }
        // E[d²] = 2 in std units for a 2-D isotropic Gaussian (modes far apart).
        assert!((sq / 4000.0 - 2.0).abs() < 0.15, "mean squared distance {}", sq / 4000.0);
        let cov = t.coverage(s.as_ref(), a.as_ref()).unwrap();
        assert_eq!(cov.covered, 4);
        assert!(cov.entropy > 0.99);
        assert!(cov.off_mode < 100);
    }

    #[test]
    fn coverage_detects_collapse_and_averaging() {
        let t = CircleGmm::toy_gmm();
        let n = 200;
        let states = Mat::<f32>::zeros(n, 1);
        // All samples on mode 3.
        let m3 = t.mixture_at(&[0.0]).unwrap().means[3];
        let collapsed = Mat::from_fn(n, 2, |_, j| m3[j]);
        let cov = t.coverage(states.as_ref(), collapsed.as_ref()).unwrap();
        assert_eq!(cov.covered, 1);
        assert_eq!(cov.counts[3], n);
        assert_eq!(cov.entropy, 0.0);
        // The average of all modes (the origin) is on no mode.
        let origin = Mat::<f32>::zeros(n, 2);
        let cov = t.coverage(states.as_ref(), origin.as_ref()).unwrap();
        assert_eq!(cov.off_mode, n);
        assert_eq!(cov.covered, 0);
    }

    #[test]
    fn bad_inputs_are_errors() {
        let t = CircleGmm::toy_gmm();
        assert!(t.mixture_at(&[]).is_err());
        assert!(t.mixture_at(&[f32::NAN]).is_err());
        assert!(t.nearest_mode(&[0.0], &[1.0]).is_err());
        assert!(t.nearest_mode(&[0.0], &[1.0, f32::INFINITY]).is_err());
        assert!(t.sample(0, 0).is_err());
        let s = Mat::<f32>::zeros(3, 1);
        let a = Mat::<f32>::zeros(2, 2);
        assert!(t.coverage(s.as_ref(), a.as_ref()).is_err());
        assert!(CircleGmm::new(1, 1.0, 0.1, false).is_err());
        assert!(CircleGmm::new(4, 1.0, 0.0, false).is_err());
        assert!(CircleGmm::new(4, f32::NAN, 0.1, false).is_err());
        let empty = Mat::<f32>::zeros(0, 1);
        assert!(t.coverage(empty.as_ref(), Mat::<f32>::zeros(0, 2).as_ref()).is_err());
        let nan = Mat::from_fn(2, 2, |_, _| f32::NAN);
        assert!(t.coverage(Mat::<f32>::zeros(2, 1).as_ref(), nan.as_ref()).is_err());
    }

    #[test]
    fn serde_round_trips_and_validates() {
        let t = CircleGmm::toy_conditional();
        let json = serde_json::to_string(&t).unwrap();
        assert_eq!(serde_json::from_str::<CircleGmm>(&json).unwrap(), t);
        // A deserialised task goes through the same checks as `CircleGmm::new`.
        let bad = r#"{"n_modes":0,"radius":2.0,"std":0.5,"rotating":false}"#;
        assert!(serde_json::from_str::<CircleGmm>(bad).is_err());
        let bad = r#"{"n_modes":4,"radius":2.0,"std":-0.5,"rotating":false}"#;
        assert!(serde_json::from_str::<CircleGmm>(bad).is_err());
    }

    #[test]
    fn entropy_of_histograms() {
        assert_eq!(normalized_entropy(&[0, 0, 0]), 0.0);
        assert_relative_eq!(normalized_entropy(&[5, 5, 5, 5]), 1.0, epsilon = 1e-6);
        assert_relative_eq!(normalized_entropy(&[1, 1, 0, 0]), 0.5, epsilon = 1e-6);
    }
}
