//! **BESO** (Reuss et al. 2023): a variance-exploding, EDM-style (Karras et al. 2022) diffusion
//! policy with a preconditioned state-conditioned denoiser `D(x; σ, s)`.

use std::path::Path;

use faer::reborrow::Reborrow;
use faer::{Mat, MatMut, MatRef};
use rand::{Rng as _, RngCore};
use serde::{Deserialize, Serialize};
use vdd_core::{
    Affine, CoreError, NoiseConvention, NoiseSchedule, Policy, ScoreModel, Seeds, check_act_args,
    check_len, check_score_args, check_shape,
};

use crate::common::{self, PolicyIo, SavedShape, check_batch};
use crate::error::{DiffusionError, Result};
use crate::net::{DenoiserNet, NetConfig};
use crate::normalize::NormalizerKind;
use crate::sampling::{self, KarrasSampler, SamplerBuffers};
use crate::schedule::{Preconditioning, check_sigma_range, karras_sigmas_into};
use crate::train::{self, DsmObjective, TrainConfig, TrainProgress};

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
    /// Checks the numbers.
    pub fn validate(&self) -> Result<()> {
        self.net.validate()?;
        Preconditioning::new(self.sigma_data)?;
        self.training_sigma.validate()?;
        check_sigma_range(self.sigma_min, self.sigma_max)?;
        if !(self.rho.is_finite() && self.rho > 0.0) {
            return Err(DiffusionError::Config(format!("rho must be positive, got {}", self.rho)));
        }
        if self.sampling_steps == 0 {
            return Err(DiffusionError::Config("sampling_steps must be >= 1".into()));
        }
        Ok(())
    }
}

/// Scratch for denoiser evaluations.
#[derive(Debug, Clone)]
struct DenoiseScratch {
    x_in: Mat<f32>,
    c_noise: Vec<f32>,
}

impl Default for DenoiseScratch {
    fn default() -> Self {
        Self { x_in: Mat::zeros(0, 0), c_noise: Default::default() }
    }
}

/// `D(x; σ, s) = c_skip x + c_out F(c_in x, s, c_noise)` without argument checks.
fn denoise_unchecked(
    net: &mut DenoiserNet,
    pre: &Preconditioning,
    scratch: &mut DenoiseScratch,
    x: MatRef<'_, f32>,
    sigma: &[f32],
    states: MatRef<'_, f32>,
    mut out: MatMut<'_, f32>,
) {
    let (n, d) = (x.nrows(), x.ncols());
    if scratch.x_in.nrows() != n || scratch.x_in.ncols() != d {
        scratch.x_in = Mat::zeros(n, d);
    }
    scratch.c_noise.clear();
    scratch.c_noise.extend(sigma.iter().map(|&s| pre.c_noise(s)));
    for j in 0..d {
        let col = scratch.x_in.col_as_slice_mut(j);
        for i in 0..n {
            col[i] = pre.c_in(sigma[i]) * x[(i, j)];
        }
    }
    let f = net.forward(scratch.x_in.as_ref(), states, &scratch.c_noise);
    for j in 0..d {
        for i in 0..n {
            let s = sigma[i];
            out[(i, j)] = pre.c_skip(s) * x[(i, j)] + pre.c_out(s) * f[(i, j)];
        }
    }
}

/// The EDM training objective `||F − (a − c_skip x)/c_out||²` (= `λ(σ) ||D − a||²`).
struct EdmObjective {
    pre: Preconditioning,
    dist: SigmaDistribution,
    sigma_min: f32,
    sigma_max: f32,
    sigma: Vec<f32>,
    c_noise: Vec<f32>,
    eps: Mat<f32>,
    x_in: Mat<f32>,
    grad: Mat<f32>,
}

impl EdmObjective {
    fn new(config: &BesoConfig) -> Result<Self> {
        Ok(Self {
            pre: Preconditioning::new(config.sigma_data)?,
            dist: config.training_sigma,
            sigma_min: config.sigma_min,
            sigma_max: config.sigma_max,
            sigma: Vec::new(),
            c_noise: Vec::new(),
            eps: Mat::zeros(0, 0),
            x_in: Mat::zeros(0, 0),
            grad: Mat::zeros(0, 0),
        })
    }
}

impl DsmObjective for EdmObjective {
    fn draw(&mut self, n: usize, d: usize, rng: &mut vdd_core::Rng) {
        self.sigma.resize(n, 0.0);
        for s in self.sigma.iter_mut() {
            *s = self.dist.draw(self.sigma_min, self.sigma_max, rng);
        }
        if self.eps.nrows() != n || self.eps.ncols() != d {
            self.eps = Mat::zeros(n, d);
            self.x_in = Mat::zeros(n, d);
            self.grad = Mat::zeros(n, d);
        }
        for j in 0..d {
            vdd_core::fill_standard_normal(rng, self.eps.col_as_slice_mut(j));
        }
    }

    fn loss(
        &mut self,
        net: &mut DenoiserNet,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        backward: bool,
    ) -> f32 {
        let (n, d) = (actions.nrows(), actions.ncols());
        let pre = self.pre;
        self.c_noise.clear();
        self.c_noise.extend(self.sigma.iter().map(|&s| pre.c_noise(s)));
        for j in 0..d {
            let (eps, x_in) = (self.eps.col_as_slice(j), self.x_in.col_as_slice_mut(j));
            for i in 0..n {
                let s = self.sigma[i];
                x_in[i] = pre.c_in(s) * (actions[(i, j)] + s * eps[i]);
            }
        }
        let f = net.forward(self.x_in.as_ref(), states, &self.c_noise);
        let scale = 1.0 / (n * d) as f32;
        let mut total = 0.0f64;
        for j in 0..d {
            let g = self.grad.col_as_slice_mut(j);
            let eps = self.eps.col_as_slice(j);
            for i in 0..n {
                let s = self.sigma[i];
                let a = actions[(i, j)];
                let x = a + s * eps[i];
                let target = (a - pre.c_skip(s) * x) / pre.c_out(s);
                let r = f[(i, j)] - target;
                total += f64::from(r * r);
                g[i] = 2.0 * r * scale;
            }
        }
        if backward {
            net.backward(self.grad.as_ref());
        }
        (total * f64::from(scale)) as f32
    }
}

/// A BESO / EDM diffusion policy: a VE diffusion with Karras preconditioning, the Karras `σ`
/// schedule and Euler, Heun, Euler-ancestral or DDIM-style samplers with any number of steps.
///
/// * As a [`ScoreModel`] (noise convention `σ`), it works in the **normalised** state and
///   action space ([`Beso::normalizers`]): `score(a, s, σ) = (D(a; σ, s) − a)/σ²`.
/// * As a [`Policy`], it takes raw observations and returns raw actions: one sample from
///   `σ_max · z` with the configured sampler and steps ([`Beso::set_sampler`]; 1 step is BESO-1).
///
/// Sampling and scores use the exponential-moving-average weights.
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
#[derive(Debug, Clone)]
pub struct Beso {
    config: BesoConfig,
    train_config: Option<TrainConfig>,
    state_norm: Affine,
    action_norm: Affine,
    pre: Preconditioning,
    net: DenoiserNet,
    sigmas: Vec<f32>,
    scratch: DenoiseScratch,
    sampler_buf: SamplerBuffers,
    io: PolicyIo,
    rng: vdd_core::Rng,
}

const POLICY_STREAM: &str = "beso-policy";
const KIND: &str = "beso";

impl Beso {
    /// An untrained teacher with freshly initialised weights and the given normalisers
    /// (their dimensions give the state and action dimensions).
    pub fn new(
        config: &BesoConfig,
        state_norm: Affine,
        action_norm: Affine,
        seed: u64,
    ) -> Result<Self> {
        config.validate()?;
        let seeds = Seeds::new(seed);
        let net = DenoiserNet::new(
            &config.net,
            action_norm.dim(),
            state_norm.dim(),
            &mut seeds.stream("init"),
        )?;
        Self::from_parts(config.clone(), None, state_norm, action_norm, net, seed)
    }

    fn from_parts(
        config: BesoConfig,
        train_config: Option<TrainConfig>,
        state_norm: Affine,
        action_norm: Affine,
        net: DenoiserNet,
        seed: u64,
    ) -> Result<Self> {
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
            train_config,
            state_norm,
            action_norm,
            net,
            sigmas,
            scratch: DenoiseScratch::default(),
            sampler_buf: SamplerBuffers::default(),
            io: PolicyIo::default(),
            rng: Seeds::new(seed).stream(POLICY_STREAM),
        })
    }

    /// Trains a teacher on raw `states` (`n x d_s`) and `actions` (`n x d_a`, action chunks
    /// flattened) by seeded minibatch denoising score matching with Adam; the returned
    /// teacher samples with the EMA weights. `progress` receives a report every
    /// `train.log_every` steps (nothing is printed).
    pub fn train(
        config: &BesoConfig,
        train: &TrainConfig,
        states: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
        seed: u64,
        progress: &mut dyn FnMut(TrainProgress),
    ) -> Result<Self> {
        config.validate()?;
        train.validate()?;
        let data = train::prepare_data(
            states,
            actions,
            config.state_normalizer,
            config.action_normalizer,
        )?;
        let seeds = Seeds::new(seed);
        let net = DenoiserNet::new(
            &config.net,
            actions.ncols(),
            states.ncols(),
            &mut seeds.stream("init"),
        )?;
        let mut objective = EdmObjective::new(config)?;
        let ema = train::train_dsm(&mut objective, net, train, &data, &seeds, progress)?;
        Self::from_parts(
            config.clone(),
            Some(train.clone()),
            data.state_norm,
            data.action_norm,
            ema,
            seed,
        )
    }

    /// Dimension of one (flattened) action; the same for the score model and the policy.
    pub fn action_dim(&self) -> usize {
        self.action_norm.dim()
    }

    /// Dimension of one state / observation.
    pub fn state_dim(&self) -> usize {
        self.state_norm.dim()
    }

    /// The configuration (including the current sampler and steps).
    pub fn config(&self) -> &BesoConfig {
        &self.config
    }

    /// The training configuration, when the teacher was trained (or loaded from a trained one).
    pub fn train_config(&self) -> Option<&TrainConfig> {
        self.train_config.as_ref()
    }

    /// The `(state, action)` normalisers; the [`ScoreModel`] works in their normalised space.
    pub fn normalizers(&self) -> (&Affine, &Affine) {
        (&self.state_norm, &self.action_norm)
    }

    /// The preconditioning.
    pub fn preconditioning(&self) -> Preconditioning {
        self.pre
    }

    /// The denoiser network (EMA weights).
    pub fn net(&self) -> &DenoiserNet {
        &self.net
    }

    /// The current sampling grid `σ_0 = σ_max > … > σ_min > 0`.
    pub fn sigmas(&self) -> &[f32] {
        &self.sigmas
    }

    /// Selects the sampler and number of steps (`≥ 1`) used by `act` and `sample_actions`.
    pub fn set_sampler(&mut self, sampler: KarrasSampler, steps: usize) -> Result<()> {
        let c = &self.config;
        karras_sigmas_into(steps, c.sigma_min, c.sigma_max, c.rho, &mut self.sigmas)?;
        self.config.sampler = sampler;
        self.config.sampling_steps = steps;
        Ok(())
    }

    fn check_sigmas(sigma: &[f32]) -> Result<(), CoreError> {
        if sigma.iter().all(|s| s.is_finite() && *s > 0.0) {
            Ok(())
        } else {
            Err(CoreError::Config("BESO noise levels σ must be positive and finite".into()))
        }
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
        let n = x.nrows();
        check_batch("x", x, n, self.action_dim())?;
        check_batch("states", states, n, self.state_dim())?;
        check_len("sigma", sigma.len(), n)?;
        check_shape("denoiser output", out.rb(), n, self.action_dim())?;
        Self::check_sigmas(sigma)?;
        denoise_unchecked(&mut self.net, &self.pre, &mut self.scratch, x, sigma, states, out);
        Ok(())
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
        let n = x.nrows();
        check_batch("x", x, n, self.action_dim())?;
        check_batch("states", states, n, self.state_dim())?;
        Self::check_sigmas(sigma_from)?;
        let Self { net, pre, scratch, sampler_buf, .. } = self;
        let mut f = |x: MatRef<'_, f32>, s: &[f32], out: MatMut<'_, f32>| {
            denoise_unchecked(net, pre, scratch, x, s, states, out);
            Ok(())
        };
        sampling::heun_step(&mut f, x, sigma_from, sigma_to, out, sampler_buf)
            .map_err(CoreError::from)
    }

    /// Samples one action per row of normalised `states` into `out` with an explicit sampler
    /// and number of steps (normalised space).
    pub fn sample_with(
        &mut self,
        sampler: KarrasSampler,
        steps: usize,
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let c = &self.config;
        let mut grid = Vec::with_capacity(steps + 1);
        karras_sigmas_into(steps, c.sigma_min, c.sigma_max, c.rho, &mut grid)?;
        self.sample_on_grid(sampler, &grid, states, rng, out)
    }

    fn sample_on_grid(
        &mut self,
        sampler: KarrasSampler,
        grid: &[f32],
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let n = states.nrows();
        check_batch("states", states, n, self.state_dim())?;
        check_shape("sampled actions", out.rb(), n, self.action_dim())?;
        let Self { net, pre, scratch, sampler_buf, .. } = self;
        sample_into(net, pre, scratch, sampler_buf, sampler, grid, states, rng, out.as_mut())
    }
}

#[allow(clippy::too_many_arguments)]
fn sample_into(
    net: &mut DenoiserNet,
    pre: &Preconditioning,
    scratch: &mut DenoiseScratch,
    buf: &mut SamplerBuffers,
    sampler: KarrasSampler,
    grid: &[f32],
    states: MatRef<'_, f32>,
    rng: &mut dyn RngCore,
    mut out: MatMut<'_, f32>,
) -> Result<(), CoreError> {
    let s0 = grid[0];
    for j in 0..out.ncols() {
        for i in 0..out.nrows() {
            out[(i, j)] = s0 * vdd_core::standard_normal(rng);
        }
    }
    let mut f = |x: MatRef<'_, f32>, s: &[f32], o: MatMut<'_, f32>| {
        denoise_unchecked(net, pre, scratch, x, s, states, o);
        Ok(())
    };
    sampling::sample_karras(&mut f, sampler, grid, out, rng, buf).map_err(CoreError::from)
}

impl ScoreModel for Beso {
    fn action_dim(&self) -> usize {
        self.action_norm.dim()
    }

    fn state_dim(&self) -> usize {
        self.state_norm.dim()
    }

    fn noise_convention(&self) -> NoiseConvention {
        NoiseConvention::Sigma
    }

    /// `(D(a; σ, s) − a)/σ²` in the normalised space.
    fn score(
        &mut self,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        noise_levels: &[f32],
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        check_score_args(self, actions, states, noise_levels, out.rb())?;
        self.denoise(actions, noise_levels, states, out.as_mut())?;
        for j in 0..actions.ncols() {
            for i in 0..actions.nrows() {
                let s = noise_levels[i];
                out[(i, j)] = (out[(i, j)] - actions[(i, j)]) / (s * s);
            }
        }
        Ok(())
    }

    /// Samples with the configured sampler and steps (normalised space).
    fn sample_actions(
        &mut self,
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let n = states.nrows();
        check_batch("states", states, n, self.state_dim())?;
        check_shape("sampled actions", out.rb(), n, self.action_dim())?;
        let sampler = self.config.sampler;
        let Self { net, pre, scratch, sampler_buf, sigmas, .. } = self;
        sample_into(net, pre, scratch, sampler_buf, sampler, sigmas, states, rng, out.as_mut())
    }

    /// Draws from `schedule`, clamped to `[σ_min, σ_max]` (a VE score needs `σ > 0`).
    fn draw_noise_levels(
        &self,
        schedule: &NoiseSchedule,
        progress: f32,
        rng: &mut dyn RngCore,
        out: &mut [f32],
    ) {
        for x in out {
            *x = schedule.draw(progress, rng).clamp(self.config.sigma_min, self.config.sigma_max);
        }
    }
}

impl Policy for Beso {
    fn obs_dim(&self) -> usize {
        self.state_norm.dim()
    }

    fn action_dim(&self) -> usize {
        self.action_norm.dim()
    }

    fn seed(&mut self, seed: u64) {
        self.rng = Seeds::new(seed).stream(POLICY_STREAM);
    }

    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> Result<(), CoreError> {
        check_act_args(self, obs, action)?;
        let ds = self.state_norm.dim();
        self.act_batch(
            MatRef::from_row_major_slice(obs, 1, ds),
            MatMut::from_row_major_slice_mut(action, 1, self.action_norm.dim()),
        )
    }

    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        actions: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let n = obs.nrows();
        let (ds, da) = (self.state_norm.dim(), self.action_norm.dim());
        check_batch("observations", obs, n, ds)?;
        check_shape("actions", actions.rb(), n, da)?;
        self.io.prepare(n, ds, da);
        self.io.load_obs(obs, &self.state_norm);
        let sampler = self.config.sampler;
        let Self { net, pre, scratch, sampler_buf, sigmas, io, rng, .. } = self;
        sample_into(
            net,
            pre,
            scratch,
            sampler_buf,
            sampler,
            sigmas,
            io.obs.as_ref(),
            rng,
            io.act.as_mut(),
        )?;
        self.io.store_actions(&self.action_norm, actions);
        Ok(())
    }
}

impl Beso {
    /// Saves the EMA weights (`safetensors`) with the config, dimensions, normalisers and the
    /// training config as JSON metadata; the write is atomic.
    pub fn save(&self, path: &Path) -> Result<()> {
        let shape = SavedShape {
            state_dim: self.state_dim(),
            action_dim: ScoreModel::action_dim(self),
            state_normalizer: self.state_norm.clone(),
            action_normalizer: self.action_norm.clone(),
        };
        let meta = common::metadata(KIND, &self.config, &shape, self.train_config.as_ref())?;
        vdd_nn::io::save_safetensors(path, &self.net, &meta)?;
        Ok(())
    }

    /// Loads a teacher saved by [`Beso::save`]; its policy stream is seeded with `seed`.
    pub fn load(path: &Path, seed: u64) -> Result<Self> {
        let meta = vdd_nn::io::read_metadata(path)?;
        let (config, shape, train): (BesoConfig, SavedShape, Option<TrainConfig>) =
            common::parse_metadata(path, &meta, KIND)?;
        config.validate().map_err(|e| common::format_err(path, e))?;
        let mut net = DenoiserNet::new(
            &config.net,
            shape.action_dim,
            shape.state_dim,
            &mut Seeds::new(0).stream("init"),
        )?;
        vdd_nn::io::load_safetensors(path, &mut net)?;
        Self::from_parts(config, train, shape.state_normalizer, shape.action_normalizer, net, seed)
    }

    pub(crate) fn kind() -> &'static str {
        KIND
    }

    #[cfg(test)]
    pub(crate) fn objective_for_tests(
        &self,
    ) -> impl FnMut(&mut DenoiserNet, MatRef<'_, f32>, MatRef<'_, f32>, u64, bool) -> f32 {
        let mut obj = EdmObjective::new(&self.config).expect("valid config");
        move |net, a, s, seed, backward| {
            obj.draw(a.nrows(), a.ncols(), &mut Seeds::new(seed).stream("t"));
            obj.loss(net, a, s, backward)
        }
    }
}
