//! **DDPM** (Ho et al. 2020): a variance-preserving diffusion policy with `N` discrete steps
//! (default 16, as in the paper's Table 3), `ε`-prediction and DDPM / DDIM samplers.

use faer::reborrow::Reborrow;
use faer::{Mat, MatMut, MatRef};
use rand::{Rng as _, RngCore};
use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, DenoiserForm, NoiseConvention, NoiseProcess, check_len, check_shape};

use crate::error::{DiffusionError, Result};
use crate::learned::{LearnedTeacher, Process};
use crate::net::{DenoiserNet, NetConfig};
use crate::normalize::NormalizerKind;
use crate::sampling::{self, SamplerBuffers, VpSampler, vp_coefficients};
use crate::schedule::{BetaSchedule, VpSchedule};
use crate::train::{DsmNoise, DsmRow};

/// Which diffusion times training draws.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum TimeSampling {
    /// `t` uniform on the grid `{1, …, N}` (Ho et al.).
    Discrete,
    /// `t` uniform in `(0, N]` with `ᾱ(t)` interpolated ([`VpSchedule::alpha_bar`]), so the
    /// score is trained at every time, including the small `t < 1` VDD queries. The discrete
    /// samplers only visit grid times, which this covers as well.
    Continuous,
    /// Continuous `t` whose equivalent VE level `σ(t) = sqrt((1 − ᾱ)/ᾱ)` is log-normal,
    /// `ln σ ~ N(mean, std²)` (EDM's training distribution, clamped to `[σ(MIN_TIME), σ(N)]`).
    /// It trains far more at small noise than uniform `t`, where distillation queries the
    /// score, and still covers the whole range the samplers visit.
    LogNormal {
        /// Mean of `ln σ`.
        mean: f32,
        /// Standard deviation of `ln σ`.
        std: f32,
    },
}

/// The smallest time a continuous-time teacher is queried at (`ᾱ(t) < 1` is needed for the
/// score conversion).
pub const MIN_TIME: f32 = 1e-3;

/// Configuration of a [`Ddpm`] teacher.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DdpmConfig {
    /// The noise-prediction network.
    pub net: NetConfig,
    /// The `β` schedule.
    pub beta_schedule: BetaSchedule,
    /// Number of discrete diffusion steps `N`.
    pub num_steps: usize,
    /// Training times. The default is log-normal in the equivalent `σ(t)`, `ln σ ~ N(−1.2,
    /// 1.2²)` (EDM's, as [`crate::BesoConfig`]'s): 18% of the draws have `σ(t) < 0.1`, where
    /// distillation queries the score, against 5% for `t` uniform in `(0, 16]`.
    pub time_sampling: TimeSampling,
    /// Sampler used by `act` and `sample_actions`. The default is DDPM ancestral sampling
    /// with `σ_t² = β_t` ([`VpSampler::AncestralLarge`]), the variance choice that stays
    /// unbiased with the paper's 16 coarse steps.
    pub sampler: VpSampler,
    /// Number of sampling steps `1 ≤ k ≤ N` (1 is DDPM-1).
    pub sampling_steps: usize,
    /// Clamp the predicted clean action to `[−c, c]` (normalised units) at every step.
    pub clip_denoised: Option<f32>,
    /// Normaliser fitted to the training states.
    pub state_normalizer: NormalizerKind,
    /// Normaliser fitted to the training actions.
    pub action_normalizer: NormalizerKind,
}

impl Default for DdpmConfig {
    fn default() -> Self {
        Self {
            net: NetConfig::default(),
            beta_schedule: BetaSchedule::default(),
            num_steps: 16,
            time_sampling: TimeSampling::LogNormal { mean: -1.2, std: 1.2 },
            sampler: VpSampler::AncestralLarge,
            sampling_steps: 16,
            clip_denoised: Some(5.0),
            state_normalizer: NormalizerKind::Standard,
            action_normalizer: NormalizerKind::Standard,
        }
    }
}

impl DdpmConfig {
    /// Checks the numbers.
    pub fn validate(&self) -> Result<()> {
        self.net.validate()?;
        let sched = VpSchedule::new(self.beta_schedule, self.num_steps)?;
        sched.sampling_times(self.sampling_steps)?;
        if let TimeSampling::LogNormal { mean, std } = self.time_sampling {
            if !(mean.is_finite() && std.is_finite() && std > 0.0) {
                return Err(DiffusionError::Config(format!(
                    "log-normal time sampling needs a finite mean and positive std, got {mean}, {std}"
                )));
            }
        }
        if let Some(c) = self.clip_denoised {
            if !(c.is_finite() && c > 0.0) {
                return Err(DiffusionError::Config(format!(
                    "clip_denoised must be positive, got {c}"
                )));
            }
        }
        Ok(())
    }
}

/// The DDPM part of a [`Ddpm`] teacher: configuration, the VP schedule, the current sampling
/// times and scratch.
#[derive(Debug, Clone)]
pub struct DdpmProcess {
    config: DdpmConfig,
    schedule: VpSchedule,
    times: Vec<f32>,
    c_noise: Vec<f32>,
    eps: Mat<f32>,
}

/// The network's noise condition at time `t`: `ln σ(t) / 4` with `σ(t) = sqrt((1 − ᾱ)/ᾱ)`,
/// the same scale as EDM's `c_noise`.
fn c_noise(schedule: &VpSchedule, t: f32) -> f32 {
    0.25 * schedule.sigma(t).ln()
}

fn eps_unchecked(
    net: &mut DenoiserNet,
    schedule: &VpSchedule,
    scratch: &mut Vec<f32>,
    x: MatRef<'_, f32>,
    t: &[f32],
    states: MatRef<'_, f32>,
    mut out: MatMut<'_, f32>,
) {
    scratch.clear();
    scratch.extend(t.iter().map(|&t| c_noise(schedule, t)));
    out.copy_from(net.forward_inference(x, states, scratch));
}

impl DsmNoise for DdpmProcess {
    fn draw_level(&self, rng: &mut dyn RngCore) -> f32 {
        let big_n = self.schedule.num_steps();
        match self.config.time_sampling {
            TimeSampling::Discrete => rng.random_range(1..=big_n) as f32,
            // (0, N]: 1 − u with u ∈ [0, 1), kept off 0.
            TimeSampling::Continuous => (big_n as f32 * (1.0 - rng.random::<f32>())).max(MIN_TIME),
            TimeSampling::LogNormal { mean, std } => {
                let sigma = (mean + std * vdd_core::standard_normal(rng)).exp();
                // The log-normal times are continuous: the trained range is [MIN_TIME, N].
                self.level_for_sigma(sigma)
            }
        }
    }

    /// `||ε̂(sqrt(ᾱ_t) a + sqrt(1 − ᾱ_t) ε, t, s) − ε||²`.
    fn dsm_row(&self, t: f32) -> DsmRow {
        DsmRow {
            c_noise: c_noise(&self.schedule, t),
            input_a: self.schedule.alpha_bar(t).sqrt(),
            input_eps: self.schedule.noise_std(t),
            target_a: 0.0,
            target_eps: 1.0,
        }
    }
}

impl Process for DdpmProcess {
    type Config = DdpmConfig;
    type Sampler = VpSampler;
    const KIND: &'static str = "ddpm";
    const POLICY_STREAM: &'static str = "ddpm-policy";

    fn validate(config: &DdpmConfig) -> Result<()> {
        config.validate()
    }

    fn net_config(config: &DdpmConfig) -> &NetConfig {
        &config.net
    }

    fn normalizer_kinds(config: &DdpmConfig) -> (NormalizerKind, NormalizerKind) {
        (config.state_normalizer, config.action_normalizer)
    }

    fn build(config: DdpmConfig) -> Result<Self> {
        let schedule = VpSchedule::new(config.beta_schedule, config.num_steps)?;
        let times = schedule.sampling_times(config.sampling_steps)?;
        Ok(Self { config, schedule, times, c_noise: Vec::new(), eps: Mat::zeros(0, 0) })
    }

    fn config(&self) -> &DdpmConfig {
        &self.config
    }

    fn sampler(&self) -> (VpSampler, usize) {
        (self.config.sampler, self.config.sampling_steps)
    }

    fn set_sampler(&mut self, sampler: VpSampler, steps: usize) -> Result<()> {
        self.times = self.schedule.sampling_times(steps)?;
        self.config.sampler = sampler;
        self.config.sampling_steps = steps;
        Ok(())
    }

    fn check_levels(&self, t: &[f32], allow_zero: bool) -> Result<(), CoreError> {
        let n = self.schedule.num_steps() as f32;
        let ok =
            t.iter().all(|&t| t.is_finite() && (t > 0.0 || (allow_zero && t == 0.0)) && t <= n);
        if ok {
            Ok(())
        } else {
            Err(CoreError::Config(format!(
                "DDPM times must be in (0, {n}]{}",
                if allow_zero { " (or 0 as a target)" } else { "" }
            )))
        }
    }

    fn evaluate(
        &mut self,
        net: &mut DenoiserNet,
        x: MatRef<'_, f32>,
        t: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) {
        eps_unchecked(net, &self.schedule, &mut self.c_noise, x, t, states, out);
    }

    /// `−ε̂(x, t, s)/sqrt(1 − ᾱ(t))`.
    fn prediction_to_score(&self, x: MatRef<'_, f32>, t: &[f32], mut out: MatMut<'_, f32>) {
        for i in 0..x.nrows() {
            let inv = -1.0 / self.schedule.noise_std(t[i]);
            for j in 0..x.ncols() {
                out[(i, j)] *= inv;
            }
        }
    }

    fn sample(
        &mut self,
        net: &mut DenoiserNet,
        buf: &mut SamplerBuffers,
        how: Option<(VpSampler, usize)>,
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let Self { config, schedule, times, c_noise, .. } = self;
        let other;
        let (sampler, times) = match how {
            None => (config.sampler, &times[..]),
            Some((sampler, steps)) => {
                other = schedule.sampling_times(steps)?;
                (sampler, &other[..])
            }
        };
        for j in 0..out.ncols() {
            for i in 0..out.nrows() {
                out[(i, j)] = vdd_core::standard_normal(rng);
            }
        }
        let mut f = |x: MatRef<'_, f32>, t: &[f32], o: MatMut<'_, f32>| {
            eps_unchecked(net, schedule, c_noise, x, t, states, o);
            Ok(())
        };
        sampling::sample_vp(
            &mut f,
            schedule,
            sampler,
            times,
            config.clip_denoised,
            out.as_mut(),
            rng,
            buf,
        )
        .map_err(CoreError::from)
    }
}

/// DDPM's levels are the diffusion time `t` of its [`VpSchedule`].
impl NoiseProcess for DdpmProcess {
    fn convention(&self) -> NoiseConvention {
        NoiseConvention::Time
    }

    /// `[MIN_TIME, N]`, or `[1, N]` with [`TimeSampling::Discrete`] training.
    fn range(&self) -> (f32, f32) {
        let n = self.schedule.num_steps() as f32;
        match self.config.time_sampling {
            TimeSampling::Discrete => (1.0, n),
            _ => (MIN_TIME, n),
        }
    }

    /// Clamped to `[MIN_TIME, N]`; rounded to the grid `{1, …, N}` with
    /// [`TimeSampling::Discrete`] training.
    fn valid_level(&self, t: f32) -> f32 {
        let n = self.schedule.num_steps() as f32;
        match self.config.time_sampling {
            TimeSampling::Discrete => t.round().clamp(1.0, n),
            _ => t.clamp(MIN_TIME, n),
        }
    }

    /// `x̂₀ = (a + (1 − ᾱ(t)) s)/√ᾱ(t)`, `a` fed as `x_t`.
    fn denoiser_form(&self, t: f32) -> DenoiserForm {
        DenoiserForm::vp(self.schedule.alpha_bar(t))
    }

    /// [`VpSchedule::sigma`].
    fn sigma(&self, t: f32) -> f32 {
        self.schedule.sigma(t)
    }

    /// [`VpSchedule::time_for_sigma`], clamped to the trained range.
    fn level_for_sigma(&self, sigma: f32) -> f32 {
        let (lo, hi) = self.range();
        self.schedule.time_for_sigma(sigma).clamp(lo, hi)
    }
}

/// A DDPM diffusion policy: `ε`-prediction on a [`VpSchedule`] of `N` steps (linear VP or
/// cosine `β`), sampled by DDPM ancestral steps or DDIM over any `k ≤ N` steps.
///
/// * As a [`vdd_core::ScoreModel`] (noise convention `t`, continuous in `(0, N]`), it works in
///   the **normalised** space ([`LearnedTeacher::normalizers`]) and returns
///   `score(a, s, t) = −ε̂(a, t, s)/sqrt(1 − ᾱ(t))`, feeding `a` as `x_t` (vdd-method.md). At
///   non-integer `t`, `ᾱ(t)` is the schedule's log-linear interpolation, which is also what
///   training uses with the continuous [`TimeSampling`]s (the default is log-normal), so any
///   `t` is a trained one.
///   [`VpSchedule::time_for_sigma`] gives the `t` matching a VE level `σ`.
/// * As a [`vdd_core::Policy`], it takes raw observations and returns raw actions, one sample
///   with the configured sampler and steps ([`LearnedTeacher::set_sampler`]; 1 step is DDPM-1).
///
/// Sampling and scores use the exponential-moving-average weights. The methods shared with
/// [`crate::Beso`] (training, save / load, normalisers) are [`LearnedTeacher`]'s.
///
/// ```
/// use faer::Mat;
/// use vdd_core::{Policy, ScoreModel};
/// use vdd_diffusion::{Ddpm, DdpmConfig, NetConfig, TrainConfig, VpSampler};
///
/// let states = Mat::from_fn(400, 1, |i, _| (i % 4) as f32);
/// let actions = Mat::from_fn(400, 2, |i, j| (i % 4) as f32 * if j == 0 { 1.0 } else { -1.0 });
/// let config = DdpmConfig {
///     net: NetConfig { hidden_dim: 32, num_blocks: 1, ..Default::default() },
///     ..Default::default()
/// };
/// let train = TrainConfig { steps: 50, batch_size: 64, ..Default::default() };
/// let mut ddpm = Ddpm::train(&config, &train, states.as_ref(), actions.as_ref(), 0, &mut |_| {})
///     .unwrap();
/// ddpm.set_sampler(VpSampler::Ddim, 4).unwrap();
/// let a = ddpm.act(&[2.0]).unwrap();
/// assert_eq!(a.len(), 2);
/// assert!(ddpm.set_sampler(VpSampler::Ddim, 17).is_err()); // more than N = 16 steps
/// ```
pub type Ddpm = LearnedTeacher<DdpmProcess>;

impl LearnedTeacher<DdpmProcess> {
    /// The VP schedule.
    pub fn schedule(&self) -> &VpSchedule {
        &self.process.schedule
    }

    /// The noise prediction `ε̂(x, t, s)` for a batch in the normalised space: `x` is
    /// `n x d_a`, `t` has one time in `(0, N]` per row, `states` is `n x d_s`.
    pub fn predict_noise(
        &mut self,
        x: MatRef<'_, f32>,
        t: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        self.evaluate_checked(x, t, states, out)
    }

    /// One deterministic DDIM step (η = 0, no clipping) from `t_from[i]` to `t_to[i]` per row,
    /// `0 ≤ t_to ≤ t_from`, in the normalised space: the VP counterpart of
    /// [`crate::Beso::heun_step`] for distillation baselines.
    pub fn ddim_step(
        &mut self,
        x: MatRef<'_, f32>,
        t_from: &[f32],
        t_to: &[f32],
        states: MatRef<'_, f32>,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let (n, d) = (x.nrows(), self.action_dim());
        check_len("t_to", t_to.len(), n)?;
        self.process.check_levels(t_to, true)?;
        if t_to.iter().zip(t_from).any(|(a, b)| a > b) {
            return Err(CoreError::Config("DDIM step needs t_to <= t_from".into()));
        }
        check_shape("DDIM step output", out.rb(), n, d)?;
        let mut eps = std::mem::replace(&mut self.process.eps, Mat::zeros(0, 0));
        if eps.nrows() != n || eps.ncols() != d {
            eps = Mat::zeros(n, d);
        }
        let r = self.predict_noise(x, t_from, states, eps.as_mut());
        if r.is_ok() {
            for i in 0..n {
                let c = vp_coefficients(&self.process.schedule, t_from[i], t_to[i], 0.0);
                for j in 0..d {
                    out[(i, j)] = c.apply(x[(i, j)], eps[(i, j)], 0.0, None);
                }
            }
        }
        self.process.eps = eps;
        r
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use vdd_core::Seeds;

    fn process(time_sampling: TimeSampling) -> DdpmProcess {
        DdpmProcess::build(DdpmConfig { time_sampling, ..Default::default() }).unwrap()
    }

    #[test]
    fn training_times_follow_their_distribution() {
        let mut rng = Seeds::new(0).stream("t");
        let p = process(TimeSampling::Discrete);
        let t: Vec<f32> = (0..4000).map(|_| p.draw_level(&mut rng)).collect();
        assert!(t.iter().all(|t| t.fract() == 0.0 && (1.0..=16.0).contains(t)));
        assert!(t.contains(&1.0) && t.contains(&16.0));
        let p = process(TimeSampling::Continuous);
        let t: Vec<f32> = (0..4000).map(|_| p.draw_level(&mut rng)).collect();
        assert!(t.iter().all(|t| *t > 0.0 && *t <= 16.0));
        let mean = t.iter().sum::<f32>() / 4000.0;
        assert!((mean - 8.0).abs() < 0.3, "{mean}");
        let p = process(TimeSampling::LogNormal { mean: -1.2, std: 1.2 });
        let t: Vec<f32> = (0..4001).map(|_| p.draw_level(&mut rng)).collect();
        let mut sigmas: Vec<f32> = t.iter().map(|&t| p.schedule.sigma(t)).collect();
        sigmas.sort_by(f32::total_cmp);
        let median = sigmas[2000];
        assert!((median / (-1.2f32).exp() - 1.0).abs() < 0.1, "median σ {median}");
        assert!(t.iter().all(|t| (MIN_TIME..=16.0).contains(t)));
    }

    #[test]
    fn dsm_rows_are_the_forward_process() {
        let p = process(TimeSampling::Continuous);
        for t in [0.01f32, 1.0, 7.5, 16.0] {
            let r = p.dsm_row(t);
            let ab = p.schedule.alpha_bar(t);
            assert!((r.input_a * r.input_a + r.input_eps * r.input_eps - 1.0).abs() < 1e-5);
            assert!((r.input_a - ab.sqrt()).abs() < 1e-6);
            assert_eq!((r.target_a, r.target_eps), (0.0, 1.0));
            assert!((r.c_noise - 0.25 * p.schedule.sigma(t).ln()).abs() < 1e-6);
        }
    }
}
