//! diffusers' `DDPMScheduler` and `DDIMScheduler` conventions, in f32 as diffusers computes
//! them: the `β` schedules, `alphas_cumprod`, the "leading" inference timesteps and one step of
//! each sampler, so an imported teacher samples as its package does.

use serde::{Deserialize, Serialize};

use vdd_core::{DenoiserForm, NoiseConvention, NoiseProcess, VpGrid};

use crate::error::ImportError;

/// diffusers' `beta_schedule`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BetaSchedule {
    /// `linspace(beta_start, beta_end, N)`.
    Linear,
    /// `linspace(√beta_start, √beta_end, N)²`.
    ScaledLinear,
    /// `squaredcos_cap_v2`: Nichol & Dhariwal's cosine `ᾱ` with `s = 0.008`, `β ≤ 0.999`.
    SquaredcosCapV2,
}

/// What the network predicts (`prediction_type`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Prediction {
    /// The noise `ε`.
    Epsilon,
    /// The clean sample `x₀`.
    Sample,
}

/// Which sampler the teacher's policy runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SamplerKind {
    /// `DDPMScheduler.step` (ancestral, `variance_type = "fixed_small"`).
    Ddpm,
    /// `DDIMScheduler.step` with `eta = 0`, `set_alpha_to_one = True`.
    Ddim,
}

/// A diffusers scheduler configuration as the packages store it.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct SchedulerConfig {
    /// DDPM or DDIM stepping.
    pub sampler: SamplerKind,
    /// `num_train_timesteps` `N`.
    pub num_train_timesteps: usize,
    /// `beta_start`.
    pub beta_start: f32,
    /// `beta_end`.
    pub beta_end: f32,
    /// `beta_schedule`.
    pub beta_schedule: BetaSchedule,
    /// `prediction_type`.
    pub prediction: Prediction,
    /// `clip_sample`.
    pub clip_sample: bool,
    /// `clip_sample_range`.
    pub clip_sample_range: f32,
    /// Inference steps (`num_inference_steps`; `N` when the package leaves it unset).
    pub num_inference_steps: usize,
}

impl SchedulerConfig {
    /// Checks the values against what diffusers accepts (`what` names the source in errors).
    pub fn validate(&self, what: &str) -> Result<(), ImportError> {
        let bad = |key: &str, value: String| {
            Err(ImportError::BadValue { file: what.into(), key: key.into(), value })
        };
        let n = self.num_train_timesteps;
        if n == 0 || n > 100_000 {
            return bad("num_train_timesteps", n.to_string());
        }
        if !(self.beta_start.is_finite() && self.beta_start > 0.0 && self.beta_start < 1.0) {
            return bad("beta_start", self.beta_start.to_string());
        }
        if !(self.beta_end.is_finite() && self.beta_end >= self.beta_start && self.beta_end < 1.0) {
            return bad("beta_end", self.beta_end.to_string());
        }
        if !(self.clip_sample_range.is_finite() && self.clip_sample_range > 0.0) {
            return bad("clip_sample_range", self.clip_sample_range.to_string());
        }
        if self.num_inference_steps == 0 || self.num_inference_steps > n {
            return bad("num_inference_steps", self.num_inference_steps.to_string());
        }
        Ok(())
    }
}

/// The schedule's tables and the sampler's steps.
///
/// ```
/// use vdd_import::diffusers::{BetaSchedule, Prediction, SamplerKind, SchedulerConfig, Scheduler};
/// let config = SchedulerConfig {
///     sampler: SamplerKind::Ddpm, num_train_timesteps: 100, beta_start: 1e-4, beta_end: 0.02,
///     beta_schedule: BetaSchedule::SquaredcosCapV2, prediction: Prediction::Epsilon,
///     clip_sample: true, clip_sample_range: 1.0, num_inference_steps: 10,
/// };
/// let s = Scheduler::new(config).unwrap();
/// assert_eq!(s.timesteps(), [90, 80, 70, 60, 50, 40, 30, 20, 10, 0]);
/// assert!(s.alphas_cumprod()[99] < 1e-3);
/// ```
#[derive(Debug, Clone, PartialEq)]
pub struct Scheduler {
    config: SchedulerConfig,
    alphas_cumprod: Vec<f32>,
    /// `log ᾱ` on our time grid `t = 0..=N` (`t = k + 1` is diffusers' step `k`; `ᾱ(0) = 1`)
    /// and its conversions.
    grid: VpGrid,
    timesteps: Vec<usize>,
}

impl Scheduler {
    /// Builds the tables (as diffusers: `β` in f64 turned f32 for the cosine schedule, `α`
    /// and their running product in f32).
    pub fn new(config: SchedulerConfig) -> Result<Self, ImportError> {
        config.validate("scheduler config")?;
        let n = config.num_train_timesteps;
        let betas: Vec<f32> = match config.beta_schedule {
            BetaSchedule::Linear => linspace(config.beta_start, config.beta_end, n),
            BetaSchedule::ScaledLinear => {
                linspace(config.beta_start.sqrt(), config.beta_end.sqrt(), n)
                    .into_iter()
                    .map(|b| b * b)
                    .collect()
            }
            BetaSchedule::SquaredcosCapV2 => {
                let f = |t: f64| ((t + 0.008) / 1.008 * std::f64::consts::FRAC_PI_2).cos().powi(2);
                (0..n)
                    .map(|i| {
                        let (t1, t2) = (i as f64 / n as f64, (i + 1) as f64 / n as f64);
                        (1.0 - f(t2) / f(t1)).min(0.999) as f32
                    })
                    .collect()
            }
        };
        let mut acc = 1.0f32;
        let alphas_cumprod: Vec<f32> = betas
            .iter()
            .map(|b| {
                acc *= 1.0 - b;
                acc
            })
            .collect();
        let mut log_ab = vec![0.0f64];
        log_ab.extend(alphas_cumprod.iter().map(|&a| f64::from(a).ln()));
        // ᾱ underflows to 0 in f32 when the β are large for many steps.
        let grid = VpGrid::new(log_ab).map_err(|e| {
            let value = format!("{:?} over {n} steps ({e})", config.beta_schedule);
            ImportError::BadValue {
                file: "scheduler config".into(),
                key: "beta_schedule".into(),
                value,
            }
        })?;
        // "leading" spacing: (arange(0, k) · (N // k)) reversed.
        let k = config.num_inference_steps;
        let ratio = n / k;
        let timesteps = (0..k).rev().map(|i| i * ratio).collect();
        Ok(Self { config, alphas_cumprod, grid, timesteps })
    }

    /// The configuration.
    pub fn config(&self) -> &SchedulerConfig {
        &self.config
    }

    /// diffusers' `alphas_cumprod` (index = diffusers' timestep).
    pub fn alphas_cumprod(&self) -> &[f32] {
        &self.alphas_cumprod
    }

    /// The inference timesteps, first to last.
    pub fn timesteps(&self) -> &[usize] {
        &self.timesteps
    }

    /// `ᾱ` at our continuous time `t ∈ [0, N]` (log-linear between grid points; `t = k + 1` is
    /// diffusers' step `k`, `t = 0` the clean data; [`VpGrid::alpha_bar`]).
    pub fn alpha_bar(&self, t: f32) -> f32 {
        self.grid.alpha_bar(t)
    }

    /// The time `t` (our convention) whose VE level `√((1 − ᾱ)/ᾱ)` is `sigma`, clamped to the
    /// trained range `[1, N]` ([`VpGrid::time_for_sigma`]).
    pub fn time_for_sigma(&self, sigma: f32) -> f32 {
        if sigma.is_nan() {
            return 1.0;
        }
        self.grid.time_for_sigma(sigma.abs()).max(1.0)
    }

    /// The previous timestep of `t` in the inference grid (negative: the end).
    fn prev(&self, t: usize) -> isize {
        t as isize - (self.config.num_train_timesteps / self.config.num_inference_steps) as isize
    }

    /// One sampler step at diffusers timestep `t` on one sequence, in place: `sample` becomes
    /// the previous sample. `noise` supplies the DDPM variance noise (drawn only when `t > 0`;
    /// DDIM draws none).
    pub fn step(
        &self,
        model_output: &[f32],
        t: usize,
        sample: &mut [f32],
        noise: &mut dyn FnMut(&mut [f32]),
        scratch: &mut Vec<f32>,
    ) {
        let c = &self.config;
        let prev = self.prev(t);
        let at = self.alphas_cumprod[t];
        let one_prev = match c.sampler {
            SamplerKind::Ddpm => 1.0,
            SamplerKind::Ddim => 1.0, // set_alpha_to_one
        };
        let ap = if prev >= 0 { self.alphas_cumprod[prev as usize] } else { one_prev };
        let bt = 1.0 - at;
        let (sa, sb) = (at.sqrt(), bt.sqrt());
        let clip = |x: f32| {
            if c.clip_sample { x.clamp(-c.clip_sample_range, c.clip_sample_range) } else { x }
        };
        match c.sampler {
            SamplerKind::Ddpm => {
                let bp = 1.0 - ap;
                let cur_alpha = at / ap;
                let cur_beta = 1.0 - cur_alpha;
                let c0 = ap.sqrt() * cur_beta / bt;
                let ct = cur_alpha.sqrt() * bp / bt;
                for (x, &m) in sample.iter_mut().zip(model_output) {
                    let x0 = match c.prediction {
                        Prediction::Epsilon => (*x - sb * m) / sa,
                        Prediction::Sample => m,
                    };
                    *x = c0 * clip(x0) + ct * *x;
                }
                if t > 0 {
                    let var = (bp / bt * cur_beta).max(1e-20);
                    let std = var.sqrt();
                    scratch.resize(sample.len(), 0.0);
                    noise(scratch);
                    for (x, z) in sample.iter_mut().zip(scratch.iter()) {
                        *x += std * z;
                    }
                }
            }
            SamplerKind::Ddim => {
                let dir = (1.0 - ap).sqrt();
                let sap = ap.sqrt();
                for (x, &m) in sample.iter_mut().zip(model_output) {
                    let (x0, eps) = match c.prediction {
                        Prediction::Epsilon => ((*x - sb * m) / sa, m),
                        Prediction::Sample => (m, (*x - sa * m) / sb),
                    };
                    *x = sap * clip(x0) + dir * eps;
                }
            }
        }
    }
}

/// An imported teacher's levels: diffusers' timesteps as our time `t ∈ [1, N]` (`t = k + 1` is
/// step `k`), drawn levels rounded onto the trained grid, queries outside it clamped.
impl NoiseProcess for Scheduler {
    fn convention(&self) -> NoiseConvention {
        NoiseConvention::Time
    }

    /// The trained steps `[1, N]` (`N = num_train_timesteps`).
    fn range(&self) -> (f32, f32) {
        (1.0, self.config.num_train_timesteps as f32)
    }

    /// Rounded onto the trained grid `{1, …, N}`.
    fn valid_level(&self, t: f32) -> f32 {
        t.round().clamp(1.0, self.config.num_train_timesteps as f32)
    }

    /// `x̂₀ = (a + (1 − ᾱ(t)) s)/√ᾱ(t)` at `t` clamped to `[1, N]`.
    fn denoiser_form(&self, t: f32) -> DenoiserForm {
        let n = self.config.num_train_timesteps as f32;
        DenoiserForm::vp(self.alpha_bar(t.clamp(1.0, n)))
    }

    fn sigma(&self, t: f32) -> f32 {
        self.grid.sigma(t)
    }

    /// [`Scheduler::time_for_sigma`].
    fn level_for_sigma(&self, sigma: f32) -> f32 {
        self.time_for_sigma(sigma)
    }
}

/// `torch.linspace(start, end, n)` in f32 (computed in f64 and rounded; the tables agree with
/// PyTorch's to an ulp).
fn linspace(start: f32, end: f32, n: usize) -> Vec<f32> {
    if n == 1 {
        return vec![start];
    }
    let (a, b) = (f64::from(start), f64::from(end));
    (0..n).map(|i| (a + (b - a) * i as f64 / (n - 1) as f64) as f32).collect()
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(sampler: SamplerKind, schedule: BetaSchedule) -> SchedulerConfig {
        SchedulerConfig {
            sampler,
            num_train_timesteps: 100,
            beta_start: 1e-4,
            beta_end: 0.02,
            beta_schedule: schedule,
            prediction: Prediction::Epsilon,
            clip_sample: false,
            clip_sample_range: 1.0,
            num_inference_steps: 100,
        }
    }

    #[test]
    fn a_schedule_whose_alpha_bar_underflows_is_refused_by_name() {
        let c = SchedulerConfig {
            num_train_timesteps: 2000,
            beta_start: 0.5,
            beta_end: 0.9,
            ..config(SamplerKind::Ddpm, BetaSchedule::Linear)
        };
        let e = Scheduler::new(c).unwrap_err().to_string();
        assert!(e.contains("beta_schedule") && e.contains("2000 steps"), "{e}");
    }

    #[test]
    fn time_for_sigma_inverts_the_interpolated_alpha_bar() {
        let s = Scheduler::new(config(SamplerKind::Ddpm, BetaSchedule::SquaredcosCapV2)).unwrap();
        for &t in &[1.0f32, 1.5, 7.25, 50.0, 99.9] {
            let ab = s.alpha_bar(t);
            let sigma = ((1.0 - ab) / ab).sqrt();
            assert!((s.time_for_sigma(sigma) - t).abs() < 1e-3, "{t}");
        }
        assert_eq!(s.time_for_sigma(0.0), 1.0);
        assert_eq!(s.time_for_sigma(1e9), 100.0);
    }

    #[test]
    fn a_perfect_epsilon_brings_ddim_back_to_the_clean_sample() {
        let s = Scheduler::new(config(SamplerKind::Ddim, BetaSchedule::Linear)).unwrap();
        let (x0, eps) = (0.3f32, -1.2f32);
        let t = 60;
        let ab = s.alphas_cumprod()[t];
        let mut x = [ab.sqrt() * x0 + (1.0 - ab).sqrt() * eps];
        // The step to t − 1 keeps the same (x0, eps) decomposition.
        s.step(&[eps], t, &mut x, &mut |_| unreachable!(), &mut Vec::new());
        let ap = s.alphas_cumprod()[t - 1];
        assert!((x[0] - (ap.sqrt() * x0 + (1.0 - ap).sqrt() * eps)).abs() < 1e-5);
    }
}
