//! **BESO** (Reuss et al. 2023): a variance-exploding, EDM-style (Karras et al. 2022) diffusion
//! policy with a preconditioned state-conditioned denoiser `D(x; σ, s)`.

use faer::reborrow::Reborrow;
use faer::{MatMut, MatRef};
use rand::{Rng as _, RngCore};
use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, DenoiserForm, NoiseConvention, NoiseProcess};

use crate::error::{DiffusionError, Result};
use crate::learned::{LearnedTeacher, Process};
use crate::net::{DenoiserNet, NetConfig, RowCoefficients};
use crate::normalize::NormalizerKind;
use crate::sampling::{self, KarrasSampler, SamplerBuffers};
use crate::schedule::{Preconditioning, check_sigma_range, karras_sigmas_into};
use crate::train::{DsmNoise, DsmRow};

/// The distribution of training noise levels `σ`, truncated to `[σ_min, σ_max]`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum SigmaDistribution {
    /// `ln σ ~ N(mean, std²)` (EDM's default is `mean = −1.2`, `std = 1.2`), clamped.
    LogNormal {
        /// Mean of `ln σ`.
        mean: f32,
        /// Standard deviation of `ln σ`.
        std: f32,
    },
    /// `ln σ ~ Logistic(loc, scale)` truncated by inverse-CDF sampling (BESO's default, with
    /// `loc = ln σ_data`, `scale = 0.5`).
    LogLogistic {
        /// Location of `ln σ`.
        loc: f32,
        /// Scale of `ln σ`.
        scale: f32,
    },
}

impl SigmaDistribution {
    /// Checks the numbers.
    pub fn validate(&self) -> Result<()> {
        let ok = match *self {
            SigmaDistribution::LogNormal { mean, std } => {
                mean.is_finite() && std.is_finite() && std > 0.0
            }
            SigmaDistribution::LogLogistic { loc, scale } => {
                loc.is_finite() && scale.is_finite() && scale > 0.0
            }
        };
        if ok {
            Ok(())
        } else {
            Err(DiffusionError::Config(format!("invalid training σ distribution {self:?}")))
        }
    }

    /// One draw in `[sigma_min, sigma_max]`.
    pub fn draw(&self, sigma_min: f32, sigma_max: f32, rng: &mut dyn RngCore) -> f32 {
        match *self {
            SigmaDistribution::LogNormal { mean, std } => {
                (mean + std * vdd_core::standard_normal(rng)).exp().clamp(sigma_min, sigma_max)
            }
            SigmaDistribution::LogLogistic { loc, scale } => {
                let cdf = |s: f32| vdd_core::sigmoid((s.ln() - loc) / scale);
                let (lo, hi) = (cdf(sigma_min), cdf(sigma_max));
                let u: f32 = lo + (hi - lo) * rng.random::<f32>();
                let u = u.clamp(1e-7, 1.0 - 1e-7);
                (loc + scale * (u / (1.0 - u)).ln()).exp().clamp(sigma_min, sigma_max)
            }
        }
    }
}

/// Configuration of a [`Beso`] teacher.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BesoConfig {
    /// The denoiser network.
    pub net: NetConfig,
    /// `σ_data` of the preconditioning (in the normalised action space).
    pub sigma_data: f32,
    /// Distribution of training noise levels. The default is EDM's log-normal
    /// `ln σ ~ N(−1.2, 1.2²)` rather than BESO's log-logistic (`loc = ln σ_data`, scale 0.5):
    /// it trains the small levels VDD queries the score at far more (on the 2-D toy, score
    /// cosine at σ = 0.1 of 0.89 against 0.81 after the same training).
    pub training_sigma: SigmaDistribution,
    /// Smallest noise level: end of the sampling grid, lower truncation of training `σ`.
    pub sigma_min: f32,
    /// Largest noise level: start of the sampling grid, upper truncation of training `σ`.
    pub sigma_max: f32,
    /// The Karras schedule's `ρ`.
    pub rho: f32,
    /// Sampler used by `act` and `sample_actions`.
    pub sampler: KarrasSampler,
    /// Number of sampling steps (any `≥ 1`; 1 is BESO-1).
    pub sampling_steps: usize,
    /// Normaliser fitted to the training states.
    pub state_normalizer: NormalizerKind,
    /// Normaliser fitted to the training actions.
    pub action_normalizer: NormalizerKind,
}

impl Default for BesoConfig {
    fn default() -> Self {
        Self {
            net: NetConfig::default(),
            sigma_data: 0.5,
            training_sigma: SigmaDistribution::LogNormal { mean: -1.2, std: 1.2 },
            sigma_min: 0.002,
            sigma_max: 80.0,
            rho: 7.0,
            sampler: KarrasSampler::Ddim,
            sampling_steps: 16,
            state_normalizer: NormalizerKind::Standard,
            action_normalizer: NormalizerKind::Standard,
        }
    }
}

impl BesoConfig {
    /// The BESO agent of D3IL (`ALRhub/d3il`, `configs/agents/beso_agent.yaml`), the teacher of
    /// the VDD paper: `σ ∈ [0.1, 1]`, `σ_data = 0.5`, training levels log-logistic with
    /// `loc = ln σ_data` and scale 0.5 (BESO's `rand_log_logistic`, truncated to the range),
    /// the Euler-ancestral sampler on D3IL's linear grid from `σ_max` to `σ_min` (a Karras grid
    /// with `ρ = 1`; D3IL's `rho: 5` is not used by its `linear` schedule) and 8 sampling
    /// steps. The network and normalisers are this crate's defaults (D3IL's is a transformer).
    ///
    /// ```
    /// use vdd_diffusion::{karras_sigmas, BesoConfig, KarrasSampler};
    /// let c = BesoConfig::d3il();
    /// c.validate().unwrap();
    /// assert_eq!(c.sampler, KarrasSampler::EulerAncestral);
    /// // One step (BESO-1) denoises from σ_max = 1 in one go; three steps are evenly spaced.
    /// assert_eq!(karras_sigmas(1, c.sigma_min, c.sigma_max, c.rho).unwrap(), vec![1.0, 0.0]);
    /// let g = karras_sigmas(3, c.sigma_min, c.sigma_max, c.rho).unwrap();
    /// assert!((g[1] - 0.55).abs() < 1e-6 && (g[2] - 0.1).abs() < 1e-6);
    /// ```
    pub fn d3il() -> Self {
        let sigma_data = 0.5f32;
        Self {
            sigma_data,
            training_sigma: SigmaDistribution::LogLogistic { loc: sigma_data.ln(), scale: 0.5 },
            sigma_min: 0.1,
            sigma_max: 1.0,
            rho: 1.0,
            sampler: KarrasSampler::EulerAncestral,
            sampling_steps: 8,
            ..Self::default()
        }
    }

    /// Checks the numbers.
    pub fn validate(&self) -> Result<()> {
        self.net.validate()?;
        Preconditioning::new(self.sigma_data)?;
        self.training_sigma.validate()?;
        check_sigma_range(self.sigma_min, self.sigma_max)?;
        if !(self.rho.is_finite() && self.rho > 0.0) {
            return Err(DiffusionError::Config(format!("rho must be positive, got {}", self.rho)));
        }
        if self.sampling_steps == 0 || self.sampling_steps > crate::MAX_SAMPLING_STEPS {
            return Err(DiffusionError::Config(format!(
                "sampling_steps must be in 1..={}, got {}",
                crate::MAX_SAMPLING_STEPS,
                self.sampling_steps
            )));
        }
        Ok(())
    }
}

/// The BESO / EDM part of a [`Beso`] teacher: configuration, preconditioning, the current
/// Karras sampling grid and scratch.
#[derive(Debug, Clone)]
pub struct BesoProcess {
    config: BesoConfig,
    pre: Preconditioning,
    sigmas: Vec<f32>,
    coef: RowCoefficients,
}

/// `D(x; σ, s) = c_skip x + c_out F(c_in x, s, c_noise)` without argument checks (`coef` is
/// scratch).
fn denoise_unchecked(
    net: &mut DenoiserNet,
    pre: &Preconditioning,
    coef: &mut RowCoefficients,
    x: MatRef<'_, f32>,
    sigma: &[f32],
    states: MatRef<'_, f32>,
    out: MatMut<'_, f32>,
) {
    pre.write_coefficients(sigma, coef);
    net.forward_preconditioned_inference(x, states, coef, out);
}

impl DsmNoise for BesoProcess {
    fn draw_level(&self, rng: &mut dyn RngCore) -> f32 {
        let c = &self.config;
        c.training_sigma.draw(c.sigma_min, c.sigma_max, rng)
    }

    /// EDM's regression of `F(c_in x, c_noise)` onto `(a − c_skip x)/c_out`, `x = a + σ ε`:
    /// `(σ/(σ_d r)) a − (σ_d/r) ε` with `r = sqrt(σ² + σ_d²)`, written without cancellation.
    fn dsm_row(&self, sigma: f32) -> DsmRow {
        let sd = self.pre.sigma_data;
        let r = (sigma * sigma + sd * sd).sqrt();
        let c_in = self.pre.c_in(sigma);
        DsmRow {
            c_noise: self.pre.c_noise(sigma),
            input_a: c_in,
            input_eps: c_in * sigma,
            target_a: sigma / (sd * r),
            target_eps: -sd / r,
        }
    }
}

impl Process for BesoProcess {
    type Config = BesoConfig;
    type Sampler = KarrasSampler;
    const KIND: &'static str = "beso";
    const POLICY_STREAM: &'static str = "beso-policy";

    fn validate(config: &BesoConfig) -> Result<()> {
        config.validate()
    }

    fn net_config(config: &BesoConfig) -> &NetConfig {
        &config.net
    }

    fn normalizer_kinds(config: &BesoConfig) -> (NormalizerKind, NormalizerKind) {
        (config.state_normalizer, config.action_normalizer)
    }

    fn build(config: BesoConfig) -> Result<Self> {
        let mut sigmas = Vec::new();
        karras_sigmas_into(
            config.sampling_steps,
            config.sigma_min,
            config.sigma_max,
            config.rho,
            &mut sigmas,
        )?;
        Ok(Self {
            pre: Preconditioning::new(config.sigma_data)?,
            config,
            sigmas,
            coef: RowCoefficients::default(),
        })
    }

    fn config(&self) -> &BesoConfig {
        &self.config
    }

    fn sampler(&self) -> (KarrasSampler, usize) {
        (self.config.sampler, self.config.sampling_steps)
    }

    fn set_sampler(&mut self, sampler: KarrasSampler, steps: usize) -> Result<()> {
        let c = &self.config;
        karras_sigmas_into(steps, c.sigma_min, c.sigma_max, c.rho, &mut self.sigmas)?;
        self.config.sampler = sampler;
        self.config.sampling_steps = steps;
        Ok(())
    }

    fn check_levels(&self, sigma: &[f32], allow_zero: bool) -> Result<(), CoreError> {
        if sigma.iter().all(|s| s.is_finite() && (*s > 0.0 || (allow_zero && *s == 0.0))) {
            Ok(())
        } else {
            Err(CoreError::Config("BESO noise levels σ must be positive and finite".into()))
        }
    }

    fn evaluate(
        &mut self,
        net: &mut DenoiserNet,
        x: MatRef<'_, f32>,
        sigma: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) {
        let Self { pre, coef, .. } = self;
        denoise_unchecked(net, pre, coef, x, sigma, states, out);
    }

    /// `(D(x; σ, s) − x)/σ²`.
    fn prediction_to_score(&self, x: MatRef<'_, f32>, sigma: &[f32], mut out: MatMut<'_, f32>) {
        for j in 0..x.ncols() {
            for i in 0..x.nrows() {
                let s = sigma[i];
                out[(i, j)] = (out[(i, j)] - x[(i, j)]) / (s * s);
            }
        }
    }

    fn sample(
        &mut self,
        net: &mut DenoiserNet,
        buf: &mut SamplerBuffers,
        how: Option<(KarrasSampler, usize)>,
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let Self { config, pre, sigmas, coef } = self;
        let mut grid = Vec::new();
        let (sampler, grid) = match how {
            None => (config.sampler, &sigmas[..]),
            Some((sampler, steps)) => {
                let c = &*config;
                karras_sigmas_into(steps, c.sigma_min, c.sigma_max, c.rho, &mut grid)?;
                (sampler, &grid[..])
            }
        };
        let s0 = grid[0];
        for j in 0..out.ncols() {
            for i in 0..out.nrows() {
                out[(i, j)] = s0 * vdd_core::standard_normal(rng);
            }
        }
        let mut f = |x: MatRef<'_, f32>, s: &[f32], o: MatMut<'_, f32>| {
            denoise_unchecked(net, pre, coef, x, s, states, o);
            Ok(())
        };
        sampling::sample_karras(&mut f, sampler, grid, out.as_mut(), rng, buf)
            .map_err(CoreError::from)
    }
}

/// BESO's levels are VE `σ`, trained on `[σ_min, σ_max]`.
impl NoiseProcess for BesoProcess {
    fn convention(&self) -> NoiseConvention {
        NoiseConvention::Sigma
    }

    /// `[σ_min, σ_max]`.
    fn range(&self) -> (f32, f32) {
        (self.config.sigma_min, self.config.sigma_max)
    }

    /// Clamped to `[σ_min, σ_max]` (a VE score needs `σ > 0`).
    fn valid_level(&self, drawn: f32) -> f32 {
        drawn.clamp(self.config.sigma_min, self.config.sigma_max)
    }

    /// `D = a + σ² s`.
    fn denoiser_form(&self, sigma: f32) -> DenoiserForm {
        DenoiserForm::ve(sigma)
    }

    fn sigma(&self, level: f32) -> f32 {
        level
    }

    /// `σ` clamped to `[σ_min, σ_max]`.
    fn level_for_sigma(&self, sigma: f32) -> f32 {
        self.valid_level(sigma)
    }
}

/// A BESO / EDM diffusion policy: a VE diffusion with Karras preconditioning, the Karras `σ`
/// schedule and Euler, Heun, Euler-ancestral or DDIM-style samplers with any number of steps.
///
/// * As a [`vdd_core::ScoreModel`] (noise convention `σ`), it works in the **normalised**
///   state and action space ([`LearnedTeacher::normalizers`]):
///   `score(a, s, σ) = (D(a; σ, s) − a)/σ²`.
/// * As a [`vdd_core::Policy`], it takes raw observations and returns raw actions: one sample
///   from `σ_max · z` with the configured sampler and steps ([`LearnedTeacher::set_sampler`];
///   1 step is BESO-1).
///
/// Sampling and scores use the exponential-moving-average weights. The methods shared with
/// [`crate::Ddpm`] (training, save / load, normalisers) are [`LearnedTeacher`]'s.
///
/// ```
/// use faer::Mat;
/// use vdd_core::{Policy, ScoreModel};
/// use vdd_diffusion::{Beso, BesoConfig, KarrasSampler, NetConfig, TrainConfig};
///
/// // 400 state-action pairs: the action is ±1 (two modes) plus a little noise.
/// let states = Mat::<f32>::zeros(400, 1);
/// let actions = Mat::from_fn(400, 1, |i, _| if i % 2 == 0 { 1.0 } else { -1.0 } + 0.01 * (i % 7) as f32);
/// let config = BesoConfig {
///     net: NetConfig { hidden_dim: 32, num_blocks: 1, ..Default::default() },
///     ..Default::default()
/// };
/// let train = TrainConfig { steps: 50, batch_size: 64, ..Default::default() };
/// let mut beso = Beso::train(&config, &train, states.as_ref(), actions.as_ref(), 0, &mut |_| {})
///     .unwrap();
/// beso.set_sampler(KarrasSampler::Euler, 1).unwrap(); // BESO-1
/// let a = beso.act(&[0.0]).unwrap();
/// assert!(a[0].is_finite());
/// assert_eq!(beso.action_dim(), 1);
/// ```
pub type Beso = LearnedTeacher<BesoProcess>;

impl LearnedTeacher<BesoProcess> {
    /// The preconditioning.
    pub fn preconditioning(&self) -> Preconditioning {
        self.process.pre
    }

    /// The current sampling grid `σ_0 = σ_max > … > σ_min > 0`, followed by 0.
    pub fn sigmas(&self) -> &[f32] {
        &self.process.sigmas
    }

    /// The denoiser `D(x; σ, s)` for a batch in the normalised space: `x` is `n x d_a`,
    /// `sigma` has one positive level per row, `states` is `n x d_s`, `out` is `n x d_a`.
    pub fn denoise(
        &mut self,
        x: MatRef<'_, f32>,
        sigma: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        self.evaluate_checked(x, sigma, states, out)
    }

    /// One Heun step of the probability-flow ODE `dx/dσ = (x − D(x; σ, s))/σ` from
    /// `sigma_from[i]` to `sigma_to[i]` per row (an Euler step where `sigma_to = 0`), in the
    /// normalised space — the teacher step of Consistency Distillation.
    pub fn heun_step(
        &mut self,
        x: MatRef<'_, f32>,
        sigma_from: &[f32],
        sigma_to: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        self.check_query(x, sigma_from, states, out.rb(), false)?;
        let Self { net, process, sampler_buf, .. } = self;
        let BesoProcess { pre, coef, .. } = process;
        let mut f = |x: MatRef<'_, f32>, s: &[f32], out: MatMut<'_, f32>| {
            denoise_unchecked(net, pre, coef, x, s, states, out);
            Ok(())
        };
        sampling::heun_step(&mut f, x, sigma_from, sigma_to, out, sampler_buf)
            .map_err(CoreError::from)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn dsm_rows_are_edm_input_and_target() {
        let p = BesoProcess::build(BesoConfig { sigma_data: 0.7, ..Default::default() }).unwrap();
        let pre = p.pre;
        for sigma in [0.002f32, 0.1, 0.7, 3.0, 80.0] {
            let r = p.dsm_row(sigma);
            assert_eq!(r.c_noise, pre.c_noise(sigma));
            for (a, eps) in [(0.3f32, -1.1f32), (-2.0, 0.4)] {
                let x = a + sigma * eps;
                let input = r.input_a * a + r.input_eps * eps;
                assert!((input - pre.c_in(sigma) * x).abs() < 1e-5, "σ {sigma}");
                let target = (a - pre.c_skip(sigma) * x) / pre.c_out(sigma);
                let ours = r.target_a * a + r.target_eps * eps;
                assert!(
                    (ours - target).abs() < 1e-3 * (1.0 + target.abs()),
                    "σ {sigma}: {ours} vs {target}"
                );
            }
        }
    }
}
