//! Noise schedules: the variance-preserving `ᾱ_t` schedule of DDPM and the Karras `σ` schedule
//! and preconditioning of EDM / BESO.

use serde::{Deserialize, Serialize};
use vdd_core::VpGrid;

use crate::error::{DiffusionError, Result};
use crate::net::RowCoefficients;

/// The `β` schedule of a variance-preserving (DDPM) diffusion with `N` discrete steps.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum BetaSchedule {
    /// `β(τ)` linear in continuous time `τ ∈ [0, 1]` from `beta_min` to `beta_max` (the VP SDE
    /// of Song et al. 2021, as in Diffusion-QL's `vp_beta_schedule`), discretised exactly:
    /// `ᾱ_i = exp(−β_min τ_i − ½ (β_max − β_min) τ_i²)` with `τ_i = i / N`. Unlike the 1000-step
    /// DDPM constants, it gives `ᾱ_N ≈ 0` for any `N`, including the paper's 16.
    Linear {
        /// `β(0)` (default 0.1).
        beta_min: f32,
        /// `β(1)` (default 20).
        beta_max: f32,
    },
    /// Ho et al.'s (2020) discrete linear schedule: `β_i` evenly spaced from `beta_start`
    /// (`i = 1`) to `beta_end` (`i = N`), `ᾱ_i = Π_{j ≤ i} (1 − β_j)`. Sampling starts from
    /// `N(0, I)`, so `ᾱ_N` must be small: Ho et al.'s `1e-4 … 0.02` needs about 1000 steps;
    /// with 16 steps use e.g. `0.05 … 0.7` (or [`BetaSchedule::Linear`], which stays
    /// consistent for any `N`).
    LinearBetas {
        /// `β_1`.
        beta_start: f32,
        /// `β_N`.
        beta_end: f32,
    },
    /// The cosine schedule of Nichol & Dhariwal (2021):
    /// `ᾱ_i = f(i/N) / f(0)`, `f(τ) = cos²(π/2 · (τ + s)/(1 + s))`, with `β_i` clipped at 0.999.
    Cosine {
        /// The offset `s` (default 0.008).
        s: f32,
    },
}

impl Default for BetaSchedule {
    /// The cosine schedule: with the paper's 16 steps its ancestral sampler is far less biased
    /// than the linear one's (whose last steps have `β ≈ 0.7`), and its first step is a small
    /// noise level (`σ(1) ≈ 0.11`).
    fn default() -> Self {
        BetaSchedule::Cosine { s: 0.008 }
    }
}

/// A discrete variance-preserving schedule: `ᾱ_0 = 1 > ᾱ_1 > … > ᾱ_N`, extended to continuous
/// `t ∈ [0, N]` by linear interpolation of `log ᾱ` between grid points.
///
/// The forward process is `x_t = sqrt(ᾱ_t) a + sqrt(1 − ᾱ_t) ε`.
///
/// ```
/// use vdd_diffusion::{BetaSchedule, VpSchedule};
/// let s = VpSchedule::new(BetaSchedule::default(), 16).unwrap();
/// assert_eq!(s.alpha_bar(0.0), 1.0);
/// assert!(s.alpha_bar(16.0) < 1e-3);
/// // The interpolation agrees with the grid.
/// assert!((s.alpha_bar(3.0) - s.alpha_bars()[3]).abs() < 1e-6);
/// ```
#[derive(Debug, Clone, PartialEq)]
pub struct VpSchedule {
    kind: BetaSchedule,
    /// `ᾱ_i` for `i = 0..=N` (`ᾱ_0 = 1`).
    alpha_bars: Vec<f32>,
    /// `log ᾱ_i` and the conversions between `t` and `σ` ([`vdd_core::VpGrid`]).
    grid: VpGrid,
}

/// Largest number of discrete steps `N` of a VP schedule (DDPM uses 16 to 1000).
pub const MAX_DIFFUSION_STEPS: usize = 100_000;

/// Largest number of sampling steps of a teacher (each is a network evaluation per action;
/// the paper's teachers use 16).
pub const MAX_SAMPLING_STEPS: usize = 10_000;

impl VpSchedule {
    /// Builds the schedule with `1 ≤ num_steps = N ≤ `[`MAX_DIFFUSION_STEPS`] discrete steps.
    pub fn new(kind: BetaSchedule, num_steps: usize) -> Result<Self> {
        if num_steps == 0 || num_steps > MAX_DIFFUSION_STEPS {
            return Err(DiffusionError::Config(format!(
                "a VP schedule needs 1..={MAX_DIFFUSION_STEPS} steps, got {num_steps}"
            )));
        }
        let n = num_steps as f64;
        let mut log_ab = Vec::with_capacity(num_steps + 1);
        log_ab.push(0.0f64);
        match kind {
            BetaSchedule::Linear { beta_min, beta_max } => {
                let (b0, b1) = (f64::from(beta_min), f64::from(beta_max));
                if !(b0.is_finite() && b1.is_finite() && b0 >= 0.0 && b1 > b0) {
                    return Err(DiffusionError::Config(format!(
                        "linear β schedule needs 0 <= beta_min < beta_max, got {beta_min}, {beta_max}"
                    )));
                }
                for i in 1..=num_steps {
                    let tau = i as f64 / n;
                    log_ab.push(-(b0 * tau + 0.5 * (b1 - b0) * tau * tau));
                }
            }
            BetaSchedule::LinearBetas { beta_start, beta_end } => {
                let (b0, b1) = (f64::from(beta_start), f64::from(beta_end));
                if !(b0.is_finite() && b1.is_finite() && b0 > 0.0 && b0 <= b1 && b1 < 1.0) {
                    return Err(DiffusionError::Config(format!(
                        "linear betas need 0 < beta_start <= beta_end < 1, got {beta_start}, {beta_end}"
                    )));
                }
                let mut log_acc = 0.0f64;
                for i in 1..=num_steps {
                    let r = if num_steps == 1 { 1.0 } else { (i - 1) as f64 / (n - 1.0) };
                    log_acc += (-(b0 + r * (b1 - b0))).ln_1p();
                    log_ab.push(log_acc);
                }
            }
            BetaSchedule::Cosine { s } => {
                let s = f64::from(s);
                if !(s.is_finite() && s > 0.0 && s < 1.0) {
                    return Err(DiffusionError::Config(format!(
                        "cosine schedule offset must be in (0, 1), got {s}"
                    )));
                }
                let f = |tau: f64| {
                    let c = (std::f64::consts::FRAC_PI_2 * (tau + s) / (1.0 + s)).cos();
                    c * c
                };
                let f0 = f(0.0);
                let mut prev = 1.0f64;
                let mut log_acc = 0.0f64;
                for i in 1..=num_steps {
                    let ab = f(i as f64 / n) / f0;
                    let beta = (1.0 - ab / prev).clamp(0.0, 0.999);
                    log_acc += (1.0 - beta).ln();
                    prev = ab;
                    log_ab.push(log_acc);
                }
            }
        }
        let alpha_bars = log_ab.iter().map(|l| l.exp() as f32).collect();
        let grid = VpGrid::new(log_ab).map_err(|e| DiffusionError::Config(e.to_string()))?;
        Ok(Self { kind, alpha_bars, grid })
    }

    /// The `β` schedule it was built from.
    pub fn kind(&self) -> BetaSchedule {
        self.kind
    }

    /// Number of discrete steps `N`.
    pub fn num_steps(&self) -> usize {
        self.alpha_bars.len() - 1
    }

    /// `ᾱ_i` for `i = 0..=N`.
    pub fn alpha_bars(&self) -> &[f32] {
        &self.alpha_bars
    }

    /// `β_i = 1 − ᾱ_i / ᾱ_{i−1}` for `i = 1..=N` (index 0 of the result is `β_1`).
    pub fn betas(&self) -> Vec<f32> {
        let la = self.grid.log_alpha_bars();
        la.windows(2).map(|w| (1.0 - (w[1] - w[0]).exp()) as f32).collect()
    }

    /// The grid of `log ᾱ` and its conversions ([`VpGrid`]).
    pub fn grid(&self) -> &VpGrid {
        &self.grid
    }

    /// `log ᾱ(t)` for continuous `t`, clamped to `[0, N]`.
    pub fn log_alpha_bar(&self, t: f32) -> f64 {
        self.grid.log_alpha_bar(t)
    }

    /// `ᾱ(t)` for continuous `t ∈ [0, N]` (log-linear between grid points).
    pub fn alpha_bar(&self, t: f32) -> f32 {
        self.grid.alpha_bar(t)
    }

    /// `sqrt(1 − ᾱ(t))`, the noise standard deviation of `x_t`, computed without cancellation.
    pub fn noise_std(&self, t: f32) -> f32 {
        (-(self.log_alpha_bar(t).exp_m1())).sqrt() as f32
    }

    /// `sqrt(1 − ᾱ(t)/ᾱ(s))` for `s ≤ t`: the standard deviation of the forward process's noise
    /// from `s` to `t` (`sqrt(β_t)` for one grid step).
    pub fn step_noise_std(&self, t: f32, s: f32) -> f32 {
        (-(self.log_alpha_bar(t) - self.log_alpha_bar(s)).exp_m1()).max(0.0).sqrt() as f32
    }

    /// The equivalent VE noise level `σ(t) = sqrt((1 − ᾱ)/ᾱ)` (`x_t / sqrt(ᾱ) = a + σ ε`).
    pub fn sigma(&self, t: f32) -> f32 {
        self.grid.sigma(t)
    }

    /// The continuous time `t` whose [`VpSchedule::sigma`] equals `sigma` (the exact inverse of
    /// the log-linear interpolation; clamped to `[0, N]`). Lets a VP teacher be queried at the
    /// noise level a VE teacher would use.
    pub fn time_for_sigma(&self, sigma: f32) -> f32 {
        self.grid.time_for_sigma(sigma)
    }

    /// The `k + 1` times `τ_0 = 0 < τ_1 < … < τ_k = N` a `k`-step sampler visits (in increasing
    /// order), `τ_i = round(i N / k)`; `1 ≤ k ≤ min(N, `[`MAX_SAMPLING_STEPS`]`)`.
    pub fn sampling_times(&self, k: usize) -> Result<Vec<f32>> {
        let n = self.num_steps().min(MAX_SAMPLING_STEPS);
        if k == 0 || k > n {
            return Err(DiffusionError::Config(format!(
                "sampling steps must be in 1..={n} for this schedule, got {k}"
            )));
        }
        Ok((0..=k).map(|i| ((i * n) as f64 / k as f64).round() as f32).collect())
    }
}

/// The Karras et al. (2022) noise levels for `1 ≤ n ≤ `[`MAX_SAMPLING_STEPS`] sampling steps, followed by a final 0:
/// `σ_i = (σ_max^{1/ρ} + i/(n−1) (σ_min^{1/ρ} − σ_max^{1/ρ}))^ρ`, `i = 0..n−1` (for `n = 1`
/// just `σ_max`). The result has `n + 1` entries, decreasing, ending in 0.
///
/// ```
/// let s = vdd_diffusion::karras_sigmas(5, 0.002, 80.0, 7.0).unwrap();
/// assert_eq!(s.len(), 6);
/// assert!((s[0] - 80.0).abs() < 1e-3 && (s[4] - 0.002).abs() < 1e-6 && s[5] == 0.0);
/// assert_eq!(vdd_diffusion::karras_sigmas(1, 0.002, 80.0, 7.0).unwrap(), vec![80.0, 0.0]);
/// ```
pub fn karras_sigmas(n: usize, sigma_min: f32, sigma_max: f32, rho: f32) -> Result<Vec<f32>> {
    let mut out = Vec::with_capacity(n + 1);
    karras_sigmas_into(n, sigma_min, sigma_max, rho, &mut out)?;
    Ok(out)
}

/// [`karras_sigmas`] into a reused vector.
pub fn karras_sigmas_into(
    n: usize,
    sigma_min: f32,
    sigma_max: f32,
    rho: f32,
    out: &mut Vec<f32>,
) -> Result<()> {
    if n == 0 || n > MAX_SAMPLING_STEPS {
        return Err(DiffusionError::Config(format!(
            "the Karras schedule needs 1..={MAX_SAMPLING_STEPS} steps, got {n}"
        )));
    }
    check_sigma_range(sigma_min, sigma_max)?;
    if !(rho.is_finite() && rho > 0.0) {
        return Err(DiffusionError::Config(format!("rho must be positive, got {rho}")));
    }
    out.clear();
    if n == 1 {
        out.push(sigma_max);
    } else {
        let (rho, lo, hi) = (f64::from(rho), f64::from(sigma_min), f64::from(sigma_max));
        let (a, b) = (hi.powf(1.0 / rho), lo.powf(1.0 / rho));
        for i in 0..n {
            let r = i as f64 / (n - 1) as f64;
            out.push((a + r * (b - a)).powf(rho) as f32);
        }
    }
    out.push(0.0);
    Ok(())
}

/// Smallest noise level σ (and data standard deviation σ_d) a Karras/EDM configuration may
/// state: `1/σ²` (the score's scale) stays far below `f32::MAX`.
pub const MIN_SIGMA: f32 = 1e-6;
/// Largest noise level σ (and data standard deviation σ_d) a Karras/EDM configuration may
/// state: `σ² + σ_d²` (the preconditioning's denominator) and `σ⁴` (the ancestral step) stay
/// far below `f32::MAX`. At `σ_d` of 1.8e19, `σ_d²` overflows and the denoiser is NaN.
pub const MAX_SIGMA: f32 = 1e6;

/// Checks a Karras/EDM noise range: `MIN_SIGMA ≤ sigma_min < sigma_max ≤ MAX_SIGMA`
/// ([`MIN_SIGMA`], [`MAX_SIGMA`]).
///
/// ```
/// use vdd_diffusion::check_sigma_range;
/// assert!(check_sigma_range(0.002, 80.0).is_ok());
/// assert!(check_sigma_range(80.0, 0.002).is_err());
/// assert!(check_sigma_range(1e-45, 1.0).is_err()); // σ² is 0 in f32
/// assert!(check_sigma_range(0.1, 1.8e19).is_err()); // σ² overflows
/// ```
pub fn check_sigma_range(sigma_min: f32, sigma_max: f32) -> Result<()> {
    let in_range = |s: f32| (MIN_SIGMA..=MAX_SIGMA).contains(&s);
    if !(in_range(sigma_min) && in_range(sigma_max) && sigma_max > sigma_min) {
        return Err(DiffusionError::Config(format!(
            "need {MIN_SIGMA} <= sigma_min < sigma_max <= {MAX_SIGMA}, got {sigma_min}, \
             {sigma_max}"
        )));
    }
    Ok(())
}

/// The EDM preconditioning of Karras et al. (2022), used by BESO:
/// `D(x; σ) = c_skip(σ) x + c_out(σ) F(c_in(σ) x, c_noise(σ))` with
///
/// * `c_skip = σ_d² / (σ² + σ_d²)`,
/// * `c_out = σ σ_d / sqrt(σ² + σ_d²)`,
/// * `c_in = 1 / sqrt(σ² + σ_d²)`,
/// * `c_noise = ln(σ) / 4`,
///
/// where `σ_d` is the data standard deviation.
///
/// ```
/// use vdd_diffusion::Preconditioning;
/// let p = Preconditioning::new(0.5).unwrap();
/// // At σ = 0 the denoiser is the identity; at σ = σ_d, c_skip = 1/2.
/// assert_eq!(p.c_skip(0.0), 1.0);
/// assert!((p.c_skip(0.5) - 0.5).abs() < 1e-6);
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct Preconditioning {
    /// The data standard deviation `σ_d`.
    pub sigma_data: f32,
}

impl Preconditioning {
    /// Preconditioning for data of standard deviation `sigma_data` in
    /// `[MIN_SIGMA, MAX_SIGMA]` ([`MIN_SIGMA`], [`MAX_SIGMA`]).
    pub fn new(sigma_data: f32) -> Result<Self> {
        if !(MIN_SIGMA..=MAX_SIGMA).contains(&sigma_data) {
            return Err(DiffusionError::Config(format!(
                "sigma_data must lie in [{MIN_SIGMA}, {MAX_SIGMA}], got {sigma_data}"
            )));
        }
        Ok(Self { sigma_data })
    }

    /// `σ_d² / (σ² + σ_d²)`.
    #[inline]
    pub fn c_skip(&self, sigma: f32) -> f32 {
        let sd2 = self.sigma_data * self.sigma_data;
        sd2 / (sigma * sigma + sd2)
    }

    /// `σ σ_d / sqrt(σ² + σ_d²)`.
    #[inline]
    pub fn c_out(&self, sigma: f32) -> f32 {
        sigma * self.sigma_data / self.noisy_std(sigma)
    }

    /// `1 / sqrt(σ² + σ_d²)`.
    #[inline]
    pub fn c_in(&self, sigma: f32) -> f32 {
        1.0 / self.noisy_std(sigma)
    }

    /// `ln(σ) / 4`.
    #[inline]
    pub fn c_noise(&self, sigma: f32) -> f32 {
        0.25 * sigma.ln()
    }

    /// `sqrt(σ² + σ_d²)`: the standard deviation of noisy data `a + σ ε` (the denominator of
    /// `c_in` and `c_out`; preconditionings derived from EDM's, e.g. a consistency model's
    /// boundary-shifted `c_out`, share it).
    #[inline]
    pub fn noisy_std(&self, sigma: f32) -> f32 {
        (sigma * sigma + self.sigma_data * self.sigma_data).sqrt()
    }

    /// Writes EDM's coefficients of every level of `sigma` into `coef` (cleared first, one noise
    /// condition): the denoiser `D(x; σ) = c_skip(σ) x + c_out(σ) F(c_in(σ) x, c_noise(σ))` as
    /// [`DenoiserNet::forward_preconditioned`](crate::DenoiserNet::forward_preconditioned).
    ///
    /// ```
    /// use vdd_diffusion::{Preconditioning, RowCoefficients};
    /// let p = Preconditioning::new(0.5).unwrap();
    /// let mut coef = RowCoefficients::default();
    /// p.write_coefficients(&[0.1, 2.0], &mut coef);
    /// assert_eq!(coef.len(), 2);
    /// assert_eq!((coef.c_skip[1], coef.c_noise[0][0]), (p.c_skip(2.0), p.c_noise(0.1)));
    /// ```
    pub fn write_coefficients(&self, sigma: &[f32], coef: &mut RowCoefficients) {
        coef.clear(1);
        for &s in sigma {
            coef.push(self.c_in(s), &[self.c_noise(s)], self.c_skip(s), self.c_out(s));
        }
    }

    /// The EDM loss weight `λ(σ) = 1 / c_out(σ)²`, which makes the denoiser loss
    /// `λ ||D − a||²` equal to `||F − (a − c_skip x)/c_out||²`.
    #[inline]
    pub fn loss_weight(&self, sigma: f32) -> f32 {
        let c = self.c_out(sigma);
        1.0 / (c * c)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn vp_schedules_hit_their_end_points() {
        let linear = BetaSchedule::Linear { beta_min: 0.1, beta_max: 20.0 };
        for kind in [linear, BetaSchedule::Cosine { s: 0.008 }] {
            for n in [1usize, 16, 100] {
                let s = VpSchedule::new(kind, n).unwrap();
                assert_eq!(s.alpha_bars().len(), n + 1);
                assert_eq!(s.alpha_bars()[0], 1.0);
                assert!(
                    s.alpha_bar(n as f32) < 1.001e-3,
                    "{kind:?} {n}: {}",
                    s.alpha_bar(n as f32)
                );
                assert!(s.alpha_bars().windows(2).all(|w| w[1] < w[0]), "{kind:?} not decreasing");
                let betas = s.betas();
                let cap =
                    if matches!(kind, BetaSchedule::Cosine { .. }) { 0.999 + 1e-6 } else { 1.0 };
                assert!(betas.iter().all(|&b| b > 0.0 && b <= cap), "{betas:?}");
                // ᾱ_i = Π (1 − β_j).
                let prod: f64 = betas.iter().map(|&b| 1.0 - f64::from(b)).product();
                let last = f64::from(s.alpha_bars()[n]);
                assert!((prod - last).abs() <= 1e-3 * last.max(1e-6), "{prod} vs {last}");
            }
        }
        // Linear: the closed form at the end point.
        let s = VpSchedule::new(linear, 16).unwrap();
        assert!((s.alpha_bar(16.0) - (-(0.1f32 + 9.95)).exp()).abs() < 1e-7);
        // Cosine: the first step follows the formula (no clipping there).
        let c = VpSchedule::new(BetaSchedule::Cosine { s: 0.008 }, 16).unwrap();
        let f = |t: f32| ((t + 0.008) / 1.008 * std::f32::consts::FRAC_PI_2).cos().powi(2);
        assert!((c.alpha_bars()[1] - f(1.0 / 16.0) / f(0.0)).abs() < 1e-6);
        assert!(VpSchedule::new(BetaSchedule::Linear { beta_min: 1.0, beta_max: 0.5 }, 4).is_err());
        // Ho et al.'s linear betas: evenly spaced β_i.
        let ho = VpSchedule::new(BetaSchedule::LinearBetas { beta_start: 0.05, beta_end: 0.7 }, 16)
            .unwrap();
        let betas = ho.betas();
        assert!((betas[0] - 0.05).abs() < 1e-6 && (betas[15] - 0.7).abs() < 1e-5, "{betas:?}");
        assert!(betas.windows(2).all(|w| ((w[1] - w[0]) - 0.65 / 15.0).abs() < 1e-5));
        assert!(ho.alpha_bar(16.0) < 1e-3);
        for bad in [(0.0, 0.5), (0.5, 0.1), (0.1, 1.0)] {
            let kind = BetaSchedule::LinearBetas { beta_start: bad.0, beta_end: bad.1 };
            assert!(VpSchedule::new(kind, 4).is_err(), "{bad:?}");
        }
        assert!(VpSchedule::new(BetaSchedule::default(), 0).is_err());
    }

    #[test]
    fn continuous_time_interpolates_and_inverts() {
        let s = VpSchedule::new(BetaSchedule::default(), 16).unwrap();
        let l = s.log_alpha_bar(2.5);
        let expect = 0.5 * (s.log_alpha_bar(2.0) + s.log_alpha_bar(3.0));
        assert!((l - expect).abs() < 1e-12);
        for t in [0.05f32, 0.5, 1.0, 7.3, 15.9] {
            let ab = s.alpha_bar(t);
            assert!((s.noise_std(t) - (1.0 - ab).sqrt()).abs() < 1e-4);
            assert!((s.sigma(t) - ((1.0 - ab) / ab).sqrt()).abs() < 1e-3 * s.sigma(t).max(1.0));
            let back = s.time_for_sigma(s.sigma(t));
            assert!((back - t).abs() < 1e-3, "{t} -> {back}");
        }
        assert_eq!(s.sampling_times(4).unwrap(), vec![0.0, 4.0, 8.0, 12.0, 16.0]);
        assert_eq!(s.sampling_times(1).unwrap(), vec![0.0, 16.0]);
        let t12 = s.sampling_times(12).unwrap();
        assert!(t12.windows(2).all(|w| w[1] > w[0]) && t12[12] == 16.0);
        assert!(s.sampling_times(0).is_err() && s.sampling_times(17).is_err());
    }

    #[test]
    fn karras_schedule_end_points_and_errors() {
        let s = karras_sigmas(10, 0.002, 80.0, 7.0).unwrap();
        assert_eq!(s.len(), 11);
        assert!((s[0] - 80.0).abs() < 1e-3);
        assert!((s[9] - 0.002).abs() < 1e-6);
        assert_eq!(s[10], 0.0);
        assert!(s.windows(2).all(|w| w[1] < w[0]));
        // ρ = 1 is a linear ramp.
        let lin = karras_sigmas(3, 1.0, 3.0, 1.0).unwrap();
        assert!((lin[1] - 2.0).abs() < 1e-6);
        assert!(karras_sigmas(0, 0.002, 80.0, 7.0).is_err());
        assert!(karras_sigmas(4, 0.0, 80.0, 7.0).is_err());
        assert!(karras_sigmas(4, 1.0, 0.5, 7.0).is_err());
        assert!(karras_sigmas(4, 0.1, 1.0, f32::NAN).is_err());
    }

    #[test]
    fn preconditioning_identities() {
        let p = Preconditioning::new(0.7).unwrap();
        for sigma in [1e-3f32, 0.1, 0.7, 2.0, 80.0] {
            let (cs, co, ci) = (p.c_skip(sigma), p.c_out(sigma), p.c_in(sigma));
            let sd = 0.7f32;
            // Unit variance of the network input: c_in² (σ² + σ_d²) = 1.
            assert!((ci * ci * (sigma * sigma + sd * sd) - 1.0).abs() < 1e-5);
            // c_out² = σ_d² (1 − c_skip), and the effective training target
            // (a − c_skip x)/c_out has unit variance for data of std σ_d (EDM, appendix B.6).
            assert!((co * co - sd * sd * (1.0 - cs)).abs() < 1e-5 * (1.0 + co * co));
            let target_var = ((1.0 - cs).powi(2) * sd * sd + cs * cs * sigma * sigma) / (co * co);
            assert!((target_var - 1.0).abs() < 1e-4, "σ {sigma}: {target_var}");
            assert!((p.loss_weight(sigma) * co * co - 1.0).abs() < 1e-5);
            assert!((p.c_noise(sigma) - sigma.ln() / 4.0).abs() < 1e-7);
        }
        assert_eq!(p.c_skip(0.0), 1.0);
        assert_eq!(p.c_out(0.0), 0.0);
        assert!(Preconditioning::new(0.0).is_err());
        // σ_d² overflows f32 (a fuzzed BESO config's 18446744073709551615): refused, not NaN.
        assert!(Preconditioning::new(18446744073709551615.0).is_err());
        assert!(Preconditioning::new(1e-45).is_err());
        assert!(Preconditioning::new(MAX_SIGMA).is_ok() && Preconditioning::new(MIN_SIGMA).is_ok());
    }
}
