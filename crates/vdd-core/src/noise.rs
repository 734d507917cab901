//! A diffusion's noise process, stated once: what its noise levels mean ([`NoiseProcess`]),
//! the variance-exploding form ([`VeProcess`]) and the interpolated variance-preserving grid
//! ([`VpGrid`]) that in-house DDPM teachers and teachers imported from diffusers share.
//!
//! A teacher states its process through [`crate::ScoreModel::noise_process`]; the score
//! model's noise convention, trained range, valid levels and denoiser form then follow from it,
//! so a wrapper that forwards the process cannot drop one of them.

use crate::error::{CoreError, Result};
use serde::{Deserialize, Serialize};

/// How a teacher's score at one noise level relates to its denoised estimate `D` of the clean
/// action (Tweedie's formula): `D = (a + variance · score) / scale`, and back,
/// `score = (scale · D − a) / variance`.
///
/// * Variance exploding (VE, BESO / EDM) at `σ`: `D = a + σ² s` ([`DenoiserForm::ve`]).
/// * Variance preserving (VP, DDPM) at a time with `ᾱ`: `x̂₀ = (a + (1 − ᾱ) s) / √ᾱ`
///   ([`DenoiserForm::vp`]).
///
/// ```
/// use vdd_core::DenoiserForm;
/// let f = DenoiserForm::ve(0.5);
/// assert_eq!(f.denoise(1.0, -2.0), 0.5);
/// assert_eq!(f.score(1.0, 0.5), -2.0);
/// ```
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct DenoiserForm {
    /// `k` in `D = (a + v s) / k`: 1 for VE, `√ᾱ` for VP.
    pub scale: f32,
    /// `v` in `D = (a + v s) / k`: `σ²` for VE, `1 − ᾱ` for VP.
    pub variance: f32,
}

impl DenoiserForm {
    /// The variance-exploding form at noise level `σ`: scale 1, variance `σ²`.
    pub fn ve(sigma: f32) -> Self {
        Self { scale: 1.0, variance: sigma * sigma }
    }

    /// The variance-preserving form at a time whose cumulative signal fraction is `ᾱ`: scale
    /// `√ᾱ`, variance `1 − ᾱ`.
    pub fn vp(alpha_bar: f32) -> Self {
        Self { scale: alpha_bar.sqrt(), variance: 1.0 - alpha_bar }
    }

    /// Whether both coefficients are positive (at level 0 the score does not determine `D`).
    pub fn is_proper(&self) -> bool {
        self.variance > 0.0 && self.scale > 0.0
    }

    /// The denoised estimate `(a + variance · score) / scale` of one coordinate.
    #[inline]
    pub fn denoise(&self, a: f32, score: f32) -> f32 {
        (a + self.variance * score) / self.scale
    }

    /// The score `(scale · D − a) / variance` of one coordinate with denoised estimate `d`.
    #[inline]
    pub fn score(&self, a: f32, d: f32) -> f32 {
        (self.scale * d - a) / self.variance
    }
}

/// How a teacher names its noise levels.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NoiseConvention {
    /// Variance-exploding (VE / EDM / BESO): the level is the noise standard deviation `σ`.
    Sigma,
    /// Variance-preserving (VP / DDPM): the level is the diffusion time `t` (an index into the
    /// discrete schedule, stored as `f32`).
    Time,
}

/// What a teacher's noise levels mean: their unit, the range it was trained on, how a drawn
/// level maps onto one it accepts, how its score relates to its denoised estimate, and the
/// conversion between its levels and the VE noise level `σ` (`x / scale = a + σ ε`).
///
/// ```
/// use vdd_core::{NoiseConvention, NoiseProcess, VeProcess};
/// let p = VeProcess { min: 0.002, max: 80.0 };
/// assert_eq!(p.convention(), NoiseConvention::Sigma);
/// assert_eq!(p.level_for_sigma(100.0), 80.0);
/// assert_eq!(p.denoiser_form(0.5).variance, 0.25);
/// ```
pub trait NoiseProcess {
    /// The unit of the levels.
    fn convention(&self) -> NoiseConvention;
    /// The levels the teacher was trained at, `(min, max)`, both included; `(0, ∞)` for an
    /// exact score.
    fn range(&self) -> (f32, f32);
    /// The level the teacher is queried at for a level drawn from a schedule (a grid teacher
    /// rounds it; one with a trained range may clamp it). The default keeps it as drawn.
    fn valid_level(&self, level: f32) -> f32 {
        level
    }
    /// How the score at `level` relates to the denoised estimate ([`DenoiserForm`]).
    fn denoiser_form(&self, level: f32) -> DenoiserForm;
    /// The VE noise level `σ` of `level`.
    fn sigma(&self, level: f32) -> f32;
    /// The level whose [`NoiseProcess::sigma`] is `sigma`, inside [`NoiseProcess::range`].
    fn level_for_sigma(&self, sigma: f32) -> f32;
}

/// A variance-exploding process (VE / EDM / BESO): the level is `σ` itself, trained on
/// `[min, max]`; drawn levels are kept as drawn.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct VeProcess {
    /// The smallest trained `σ`.
    pub min: f32,
    /// The largest trained `σ` (`f32::INFINITY` for an exact score).
    pub max: f32,
}

impl NoiseProcess for VeProcess {
    fn convention(&self) -> NoiseConvention {
        NoiseConvention::Sigma
    }
    fn range(&self) -> (f32, f32) {
        (self.min, self.max)
    }
    /// `D = a + σ² s`.
    fn denoiser_form(&self, sigma: f32) -> DenoiserForm {
        DenoiserForm::ve(sigma)
    }
    fn sigma(&self, level: f32) -> f32 {
        level
    }
    fn level_for_sigma(&self, sigma: f32) -> f32 {
        sigma.clamp(self.min, self.max)
    }
}

/// A discrete variance-preserving schedule `ᾱ_0 = 1 ≥ ᾱ_1 ≥ … ≥ ᾱ_N`, extended to continuous
/// time `t ∈ [0, N]` by linear interpolation of `log ᾱ` between grid points, with the VE level
/// `σ(t) = √((1 − ᾱ(t))/ᾱ(t))` and its exact inverse. The one place these conversions live:
/// DDPM's schedule (`vdd_diffusion::VpSchedule`) and diffusers' schedulers (`vdd_import`) are
/// built on it.
///
/// ```
/// use vdd_core::VpGrid;
/// let g = VpGrid::new(vec![0.0, -0.1, -1.0, -5.0]).unwrap();
/// assert_eq!(g.num_steps(), 3);
/// assert!((g.alpha_bar(1.5) - (-0.55f32).exp()).abs() < 1e-6);
/// let t = g.time_for_sigma(g.sigma(2.25));
/// assert!((t - 2.25).abs() < 1e-4);
/// ```
#[derive(Debug, Clone, PartialEq)]
pub struct VpGrid {
    /// `log ᾱ_i` for `i = 0..=N`, in f64 for an accurate interpolation near `t = 0`.
    log_alpha_bars: Vec<f64>,
}

impl VpGrid {
    /// The grid of `log ᾱ_i`, `i = 0..=N`: at least two entries, finite, the first 0 and none
    /// above the one before.
    pub fn new(log_alpha_bars: Vec<f64>) -> Result<Self> {
        let bad = |why: &str| Err(CoreError::Config(format!("a VP grid of log ᾱ {why}")));
        if log_alpha_bars.len() < 2 {
            return bad("needs at least two entries");
        }
        if log_alpha_bars[0] != 0.0 {
            return bad(&format!("starts at log ᾱ_0 = 0, got {}", log_alpha_bars[0]));
        }
        if let Some(i) = log_alpha_bars.iter().position(|l| !l.is_finite()) {
            return bad(&format!("is finite; entry {i} is {}", log_alpha_bars[i]));
        }
        if let Some(i) = log_alpha_bars.windows(2).position(|w| w[1] > w[0]) {
            return bad(&format!("does not increase; entry {} rises above entry {i}", i + 1));
        }
        Ok(Self { log_alpha_bars })
    }

    /// Number of steps `N`.
    pub fn num_steps(&self) -> usize {
        self.log_alpha_bars.len() - 1
    }

    /// `log ᾱ_i` for `i = 0..=N`.
    pub fn log_alpha_bars(&self) -> &[f64] {
        &self.log_alpha_bars
    }

    /// `log ᾱ(t)` for continuous `t`, clamped to `[0, N]`.
    pub fn log_alpha_bar(&self, t: f32) -> f64 {
        let n = self.num_steps();
        let t = f64::from(t).clamp(0.0, n as f64);
        let i = (t.floor() as usize).min(n - 1);
        let w = t - i as f64;
        (1.0 - w) * self.log_alpha_bars[i] + w * self.log_alpha_bars[i + 1]
    }

    /// `ᾱ(t)` for continuous `t ∈ [0, N]`.
    pub fn alpha_bar(&self, t: f32) -> f32 {
        self.log_alpha_bar(t).exp() as f32
    }

    /// The VE level `σ(t) = √((1 − ᾱ)/ᾱ)` (`x_t / √ᾱ = a + σ ε`).
    pub fn sigma(&self, t: f32) -> f32 {
        ((-self.log_alpha_bar(t)).exp_m1()).sqrt() as f32
    }

    /// The time `t ∈ [0, N]` whose [`VpGrid::sigma`] is `sigma` (the exact inverse of the
    /// interpolation; 0 for `σ ≤ 0` or NaN, `N` beyond the last level).
    pub fn time_for_sigma(&self, sigma: f32) -> f32 {
        if sigma.is_nan() || sigma <= 0.0 {
            return 0.0;
        }
        let s = f64::from(sigma);
        let target = -(s * s).ln_1p(); // log ᾱ = −log(1 + σ²)
        let la = &self.log_alpha_bars;
        let n = la.len() - 1;
        if target <= la[n] {
            return n as f32;
        }
        // First grid point at or below the target (log ᾱ does not increase).
        let i = la.partition_point(|&l| l > target).max(1);
        let (hi, lo) = (la[i - 1], la[i]);
        ((i - 1) as f64 + (hi - target) / (hi - lo)) as f32
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_grid_refuses_what_is_not_a_schedule() {
        assert!(VpGrid::new(vec![0.0]).is_err());
        assert!(VpGrid::new(vec![0.1, -1.0]).is_err());
        assert!(VpGrid::new(vec![0.0, f64::NAN]).is_err());
        let e = VpGrid::new(vec![0.0, -1.0, -0.5]).unwrap_err().to_string();
        assert!(e.contains("entry 2"), "{e}");
    }

    #[test]
    fn time_and_sigma_invert_each_other_across_the_grid() {
        let g = VpGrid::new(vec![0.0, -0.01, -0.3, -2.0, -9.0]).unwrap();
        for k in 1..=40 {
            let t = k as f32 * 0.1;
            let back = g.time_for_sigma(g.sigma(t));
            assert!((back - t).abs() < 1e-3, "t {t} -> {back}");
        }
        assert_eq!(g.time_for_sigma(0.0), 0.0);
        assert_eq!(g.time_for_sigma(f32::NAN), 0.0);
        assert_eq!(g.time_for_sigma(1e9), 4.0);
        assert_eq!(g.alpha_bar(0.0), 1.0);
        assert_eq!(g.alpha_bar(10.0), g.alpha_bar(4.0));
    }

    /// A teacher that states only its process.
    struct OnGrid(VpGrid);

    impl NoiseProcess for OnGrid {
        fn convention(&self) -> NoiseConvention {
            NoiseConvention::Time
        }
        fn range(&self) -> (f32, f32) {
            (1.0, self.0.num_steps() as f32)
        }
        fn valid_level(&self, t: f32) -> f32 {
            t.round().clamp(1.0, self.0.num_steps() as f32)
        }
        fn denoiser_form(&self, t: f32) -> DenoiserForm {
            DenoiserForm::vp(self.0.alpha_bar(t))
        }
        fn sigma(&self, t: f32) -> f32 {
            self.0.sigma(t)
        }
        fn level_for_sigma(&self, sigma: f32) -> f32 {
            self.0.time_for_sigma(sigma).clamp(1.0, self.0.num_steps() as f32)
        }
    }

    impl crate::ScoreModel for OnGrid {
        fn action_dim(&self) -> usize {
            1
        }
        fn state_dim(&self) -> usize {
            1
        }
        fn noise_process(&self) -> Option<&dyn NoiseProcess> {
            Some(self)
        }
        fn score(
            &mut self,
            a: faer::MatRef<'_, f32>,
            _s: faer::MatRef<'_, f32>,
            _levels: &[f32],
            mut out: faer::MatMut<'_, f32>,
        ) -> Result<()> {
            out.copy_from(a);
            Ok(())
        }
    }

    #[test]
    fn a_teacher_that_states_its_process_states_everything_through_any_wrapper() {
        use crate::{ClampedDenoiser, NoiseSchedule, ScoreModel};
        let teacher = || OnGrid(VpGrid::new(vec![0.0, -0.1, -1.0, -4.0]).unwrap());
        let boxed: Box<dyn ScoreModel> = Box::new(teacher());
        let clamped = ClampedDenoiser::new(teacher(), vec![-1.0], vec![1.0]).unwrap();
        for t in [&boxed as &dyn ScoreModel, &clamped] {
            assert_eq!(t.noise_convention(), NoiseConvention::Time);
            assert_eq!(t.noise_range(), Some((1.0, 3.0)));
            assert_eq!(t.denoiser_form(2.0), Some(DenoiserForm::vp((-1.0f32).exp())));
            let mut levels = [0.0; 16];
            let schedule = NoiseSchedule::Uniform { min: 0.0, max: 9.0 };
            let mut rng = crate::Seeds::new(3).stream("levels");
            t.draw_noise_levels(&schedule, 0.5, &mut rng, &mut levels);
            assert!(levels.iter().all(|l| [1.0, 2.0, 3.0].contains(l)), "{levels:?}");
            let p = t.noise_process().expect("forwarded");
            assert_eq!(p.level_for_sigma(p.sigma(2.0)), 2.0);
        }
    }

    #[test]
    fn the_ve_process_is_sigma_itself() {
        let p = VeProcess { min: 0.1, max: 2.0 };
        assert_eq!((p.sigma(0.7), p.valid_level(5.0)), (0.7, 5.0));
        assert_eq!((p.level_for_sigma(0.01), p.level_for_sigma(3.0)), (0.1, 2.0));
        assert_eq!(p.denoiser_form(2.0), DenoiserForm::ve(2.0));
    }
}
