//! **DDPM** (Ho et al. 2020): a variance-preserving diffusion policy with `N` discrete steps
//! (default 16, as in the paper's Table 3), `ε`-prediction and DDPM / DDIM samplers.

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
use crate::sampling::{self, SamplerBuffers, VpSampler, vp_coefficients};
use crate::schedule::{BetaSchedule, VpSchedule};
use crate::train::{self, DsmObjective, TrainConfig, TrainProgress};

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
    /// Training times.
    pub time_sampling: TimeSampling,
    /// Sampler used by `act` and `sample_actions`.
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
            time_sampling: TimeSampling::Continuous,
            sampler: VpSampler::Ancestral,
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

/// Scratch for noise-prediction evaluations.
#[derive(Debug, Clone)]
struct EpsScratch {
    c_noise: Vec<f32>,
    eps: Mat<f32>,
}

impl Default for EpsScratch {
    fn default() -> Self {
        Self { eps: Mat::zeros(0, 0), c_noise: Default::default() }
    }
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
    out.copy_from(net.forward(x, states, scratch));
}

/// The DDPM objective `||ε̂(sqrt(ᾱ_t) a + sqrt(1 − ᾱ_t) ε, t, s) − ε||²`.
struct EpsObjective {
    schedule: VpSchedule,
    sampling: TimeSampling,
    t: Vec<f32>,
    c_noise: Vec<f32>,
    eps: Mat<f32>,
    x: Mat<f32>,
    grad: Mat<f32>,
}

impl DsmObjective for EpsObjective {
    fn draw(&mut self, n: usize, d: usize, rng: &mut vdd_core::Rng) {
        let big_n = self.schedule.num_steps();
        self.t.resize(n, 0.0);
        for t in self.t.iter_mut() {
            *t = match self.sampling {
                TimeSampling::Discrete => rng.random_range(1..=big_n) as f32,
                // (0, N]: 1 − u with u ∈ [0, 1), kept off 0.
                TimeSampling::Continuous => {
                    (big_n as f32 * (1.0 - rng.random::<f32>())).max(MIN_TIME)
                }
                TimeSampling::LogNormal { mean, std } => {
                    let sigma = (mean + std * vdd_core::standard_normal(rng)).exp();
                    self.schedule.time_for_sigma(sigma).clamp(MIN_TIME, big_n as f32)
                }
            };
        }
        if self.eps.nrows() != n || self.eps.ncols() != d {
            self.eps = Mat::zeros(n, d);
            self.x = Mat::zeros(n, d);
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
        self.c_noise.clear();
        self.c_noise.extend(self.t.iter().map(|&t| c_noise(&self.schedule, t)));
        for i in 0..n {
            let (a, b) =
                (self.schedule.alpha_bar(self.t[i]).sqrt(), self.schedule.noise_std(self.t[i]));
            for j in 0..d {
                self.x[(i, j)] = a * actions[(i, j)] + b * self.eps[(i, j)];
            }
        }
        let f = net.forward(self.x.as_ref(), states, &self.c_noise);
        let scale = 1.0 / (n * d) as f32;
        let mut total = 0.0f64;
        for j in 0..d {
            let (g, e) = (self.grad.col_as_slice_mut(j), self.eps.col_as_slice(j));
            for i in 0..n {
                let r = f[(i, j)] - e[i];
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

/// A DDPM diffusion policy: `ε`-prediction on a [`VpSchedule`] of `N` steps (linear VP or
/// cosine `β`), sampled by DDPM ancestral steps or DDIM over any `k ≤ N` steps.
///
/// * As a [`ScoreModel`] (noise convention `t`, continuous in `(0, N]`), it works in the
///   **normalised** space ([`Ddpm::normalizers`]) and returns
///   `score(a, s, t) = −ε̂(a, t, s)/sqrt(1 − ᾱ(t))`, feeding `a` as `x_t` (vdd-method.md). At
///   non-integer `t`, `ᾱ(t)` is the schedule's log-linear interpolation, which is also what
///   training uses with [`TimeSampling::Continuous`] (the default), so any `t` is a trained one.
///   [`VpSchedule::time_for_sigma`] gives the `t` matching a VE level `σ`.
/// * As a [`Policy`], it takes raw observations and returns raw actions, one sample with the
///   configured sampler and steps ([`Ddpm::set_sampler`]; 1 step is DDPM-1).
///
/// Sampling and scores use the exponential-moving-average weights.
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
#[derive(Debug, Clone)]
pub struct Ddpm {
    config: DdpmConfig,
    train_config: Option<TrainConfig>,
    state_norm: Affine,
    action_norm: Affine,
    schedule: VpSchedule,
    net: DenoiserNet,
    times: Vec<f32>,
    scratch: EpsScratch,
    sampler_buf: SamplerBuffers,
    io: PolicyIo,
    rng: vdd_core::Rng,
}

const POLICY_STREAM: &str = "ddpm-policy";
const KIND: &str = "ddpm";

impl Ddpm {
    /// An untrained teacher with freshly initialised weights and the given normalisers
    /// (their dimensions give the state and action dimensions).
    pub fn new(
        config: &DdpmConfig,
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
        config: DdpmConfig,
        train_config: Option<TrainConfig>,
        state_norm: Affine,
        action_norm: Affine,
        net: DenoiserNet,
        seed: u64,
    ) -> Result<Self> {
        let schedule = VpSchedule::new(config.beta_schedule, config.num_steps)?;
        let times = schedule.sampling_times(config.sampling_steps)?;
        Ok(Self {
            config,
            train_config,
            state_norm,
            action_norm,
            schedule,
            net,
            times,
            scratch: EpsScratch::default(),
            sampler_buf: SamplerBuffers::default(),
            io: PolicyIo::default(),
            rng: Seeds::new(seed).stream(POLICY_STREAM),
        })
    }

    /// Trains a teacher on raw `states` (`n x d_s`) and `actions` (`n x d_a`, action chunks
    /// flattened) by seeded minibatch `ε`-matching with Adam; the returned teacher samples with
    /// the EMA weights. `progress` receives a report every `train.log_every` steps.
    pub fn train(
        config: &DdpmConfig,
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
        let mut objective = EpsObjective {
            schedule: VpSchedule::new(config.beta_schedule, config.num_steps)?,
            sampling: config.time_sampling,
            t: Vec::new(),
            c_noise: Vec::new(),
            eps: Mat::zeros(0, 0),
            x: Mat::zeros(0, 0),
            grad: Mat::zeros(0, 0),
        };
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
    pub fn config(&self) -> &DdpmConfig {
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

    /// The VP schedule.
    pub fn schedule(&self) -> &VpSchedule {
        &self.schedule
    }

    /// The noise-prediction network (EMA weights).
    pub fn net(&self) -> &DenoiserNet {
        &self.net
    }

    /// Selects the sampler and number of steps `1 ≤ k ≤ N` used by `act` and `sample_actions`.
    pub fn set_sampler(&mut self, sampler: VpSampler, steps: usize) -> Result<()> {
        self.times = self.schedule.sampling_times(steps)?;
        self.config.sampler = sampler;
        self.config.sampling_steps = steps;
        Ok(())
    }

    fn check_times(&self, t: &[f32], allow_zero: bool) -> Result<(), CoreError> {
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

    /// The noise prediction `ε̂(x, t, s)` for a batch in the normalised space: `x` is
    /// `n x d_a`, `t` has one time in `(0, N]` per row, `states` is `n x d_s`.
    pub fn predict_noise(
        &mut self,
        x: MatRef<'_, f32>,
        t: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let n = x.nrows();
        check_batch("x", x, n, self.action_dim())?;
        check_batch("states", states, n, self.state_dim())?;
        check_len("t", t.len(), n)?;
        check_shape("noise prediction output", out.rb(), n, self.action_dim())?;
        self.check_times(t, false)?;
        eps_unchecked(&mut self.net, &self.schedule, &mut self.scratch.c_noise, x, t, states, out);
        Ok(())
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
        let n = x.nrows();
        let d = self.action_dim();
        check_len("t_to", t_to.len(), n)?;
        self.check_times(t_to, true)?;
        if t_to.iter().zip(t_from).any(|(a, b)| a > b) {
            return Err(CoreError::Config("DDIM step needs t_to <= t_from".into()));
        }
        check_shape("DDIM step output", out.rb(), n, d)?;
        let mut eps = std::mem::replace(&mut self.scratch.eps, Mat::zeros(0, 0));
        if eps.nrows() != n || eps.ncols() != d {
            eps = Mat::zeros(n, d);
        }
        let r = self.predict_noise(x, t_from, states, eps.as_mut());
        if r.is_ok() {
            for i in 0..n {
                let c = vp_coefficients(&self.schedule, t_from[i], t_to[i], 0.0);
                for j in 0..d {
                    out[(i, j)] = c.apply(x[(i, j)], eps[(i, j)], 0.0, None);
                }
            }
        }
        self.scratch.eps = eps;
        r
    }

    /// Samples one action per row of normalised `states` into `out` with an explicit sampler
    /// and number of steps `1 ≤ k ≤ N` (normalised space).
    pub fn sample_with(
        &mut self,
        sampler: VpSampler,
        steps: usize,
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let n = states.nrows();
        check_batch("states", states, n, self.state_dim())?;
        check_shape("sampled actions", out.rb(), n, self.action_dim())?;
        let times = self.schedule.sampling_times(steps)?;
        let clip = self.config.clip_denoised;
        let Self { net, schedule, scratch, sampler_buf, .. } = self;
        sample_into(
            net,
            schedule,
            &mut scratch.c_noise,
            sampler_buf,
            sampler,
            &times,
            clip,
            states,
            rng,
            out.as_mut(),
        )
    }
}

#[allow(clippy::too_many_arguments)]
fn sample_into(
    net: &mut DenoiserNet,
    schedule: &VpSchedule,
    c_noise: &mut Vec<f32>,
    buf: &mut SamplerBuffers,
    sampler: VpSampler,
    times: &[f32],
    clip: Option<f32>,
    states: MatRef<'_, f32>,
    rng: &mut dyn RngCore,
    mut out: MatMut<'_, f32>,
) -> Result<(), CoreError> {
    for j in 0..out.ncols() {
        for i in 0..out.nrows() {
            out[(i, j)] = vdd_core::standard_normal(rng);
        }
    }
    let mut f = |x: MatRef<'_, f32>, t: &[f32], o: MatMut<'_, f32>| {
        eps_unchecked(net, schedule, c_noise, x, t, states, o);
        Ok(())
    };
    sampling::sample_vp(&mut f, schedule, sampler, times, clip, out, rng, buf)
        .map_err(CoreError::from)
}

impl ScoreModel for Ddpm {
    fn action_dim(&self) -> usize {
        self.action_norm.dim()
    }

    fn state_dim(&self) -> usize {
        self.state_norm.dim()
    }

    fn noise_convention(&self) -> NoiseConvention {
        NoiseConvention::Time
    }

    /// `−ε̂(a, t, s)/sqrt(1 − ᾱ(t))` in the normalised space, `t ∈ (0, N]`.
    fn score(
        &mut self,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        noise_levels: &[f32],
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        check_score_args(self, actions, states, noise_levels, out.rb())?;
        self.predict_noise(actions, noise_levels, states, out.as_mut())?;
        for i in 0..actions.nrows() {
            let inv = -1.0 / self.schedule.noise_std(noise_levels[i]);
            for j in 0..actions.ncols() {
                out[(i, j)] *= inv;
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
        let (sampler, clip) = (self.config.sampler, self.config.clip_denoised);
        let Self { net, schedule, scratch, sampler_buf, times, .. } = self;
        sample_into(
            net,
            schedule,
            &mut scratch.c_noise,
            sampler_buf,
            sampler,
            times,
            clip,
            states,
            rng,
            out.as_mut(),
        )
    }

    /// Draws from `schedule` and maps onto valid times: with [`TimeSampling::Discrete`]
    /// training, rounded to the grid `{1, …, N}`; otherwise clamped to `[MIN_TIME, N]`.
    fn draw_noise_levels(
        &self,
        schedule: &NoiseSchedule,
        progress: f32,
        rng: &mut dyn RngCore,
        out: &mut [f32],
    ) {
        let n = self.schedule.num_steps() as f32;
        for x in out {
            let t = schedule.draw(progress, rng);
            *x = match self.config.time_sampling {
                TimeSampling::Discrete => t.round().clamp(1.0, n),
                _ => t.clamp(MIN_TIME, n),
            };
        }
    }
}

impl Policy for Ddpm {
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
        let (sampler, clip) = (self.config.sampler, self.config.clip_denoised);
        let Self { net, schedule, scratch, sampler_buf, times, io, rng, .. } = self;
        sample_into(
            net,
            schedule,
            &mut scratch.c_noise,
            sampler_buf,
            sampler,
            times,
            clip,
            io.obs.as_ref(),
            rng,
            io.act.as_mut(),
        )?;
        self.io.store_actions(&self.action_norm, actions);
        Ok(())
    }
}

impl Ddpm {
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

    /// Loads a teacher saved by [`Ddpm::save`]; its policy stream is seeded with `seed`.
    pub fn load(path: &Path, seed: u64) -> Result<Self> {
        let meta = vdd_nn::io::read_metadata(path)?;
        let (config, shape, train): (DdpmConfig, SavedShape, Option<TrainConfig>) =
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
        let mut obj = EpsObjective {
            schedule: self.schedule.clone(),
            sampling: self.config.time_sampling,
            t: Vec::new(),
            c_noise: Vec::new(),
            eps: Mat::zeros(0, 0),
            x: Mat::zeros(0, 0),
            grad: Mat::zeros(0, 0),
        };
        move |net, a, s, seed, backward| {
            obj.draw(a.nrows(), a.ncols(), &mut Seeds::new(seed).stream("t"));
            obj.loss(net, a, s, backward)
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn objective(sampling: TimeSampling) -> EpsObjective {
        EpsObjective {
            schedule: VpSchedule::new(BetaSchedule::default(), 16).unwrap(),
            sampling,
            t: Vec::new(),
            c_noise: Vec::new(),
            eps: Mat::zeros(0, 0),
            x: Mat::zeros(0, 0),
            grad: Mat::zeros(0, 0),
        }
    }

    #[test]
    fn training_times_follow_their_distribution() {
        let mut rng = Seeds::new(0).stream("t");
        let mut o = objective(TimeSampling::Discrete);
        o.draw(4000, 1, &mut rng);
        assert!(o.t.iter().all(|t| t.fract() == 0.0 && (1.0..=16.0).contains(t)));
        assert!(o.t.contains(&1.0) && o.t.contains(&16.0));
        let mut o = objective(TimeSampling::Continuous);
        o.draw(4000, 1, &mut rng);
        assert!(o.t.iter().all(|t| *t > 0.0 && *t <= 16.0));
        let mean = o.t.iter().sum::<f32>() / 4000.0;
        assert!((mean - 8.0).abs() < 0.3, "{mean}");
        let mut o = objective(TimeSampling::LogNormal { mean: -1.2, std: 1.2 });
        o.draw(4001, 1, &mut rng);
        let mut sigmas: Vec<f32> = o.t.iter().map(|&t| o.schedule.sigma(t)).collect();
        sigmas.sort_by(f32::total_cmp);
        let median = sigmas[2000];
        assert!((median / (-1.2f32).exp() - 1.0).abs() < 0.1, "median σ {median}");
        assert!(o.t.iter().all(|t| (MIN_TIME..=16.0).contains(t)));
    }
}
