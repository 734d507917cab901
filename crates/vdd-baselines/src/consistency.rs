//! What Consistency Distillation ([`crate::cd`]) and the Consistency Trajectory Model
//! ([`crate::ctm`]) share: the teacher seen through its denoiser ([`ConsistencyTeacher`]), the
//! noise-conditioned student network ([`ConditionedNet`]), the training settings and progress
//! reports, and the plumbing from raw matrices to normalised minibatches and back.
//!
//! Both students work in the teacher's **normalised** action and state space and map raw
//! observations in and raw actions out with the teacher's normalisers when used as a
//! [`vdd_core::Policy`].
//!
//! The probability-flow ODE of a variance-exploding (EDM / BESO) teacher with denoiser
//! `D(x; σ, s)` is `dx/dσ = (x − D(x; σ, s)) / σ`; the teacher steps of both distillations
//! are Heun steps of it ([`vdd_diffusion::heun_step`]) on the Karras grid
//! ([`vdd_diffusion::karras_sigmas`]).

use std::collections::HashMap;

use faer::reborrow::Reborrow;
use faer::{Mat, MatMut, MatRef};
use serde::{Deserialize, Serialize};
use vdd_core::{Affine, CoreError, Seeds, check_finite, check_len, check_shape};
use vdd_diffusion::{Beso, DenoiserNet, NetConfig, SamplerBuffers};
use vdd_nn::ResidualMlpConfig as MlpCfg;
use vdd_nn::{Adam, AdamConfig, Ema, LrSchedule, Module, Param, Parameters, ResidualMlp};

use crate::dataset::Dataset;
use crate::error::BaselineError;
use crate::fit;

/// A variance-exploding diffusion teacher seen through its denoiser `D(x; σ, s)` in its
/// normalised space: what consistency distillation needs (the probability-flow ODE
/// `dx/dσ = (x − D)/σ` is integrated with Heun steps of it).
///
/// Implemented for the BESO teacher ([`vdd_diffusion::Beso`]) and for closures
/// ([`DenoiserFn`], e.g. the exact denoiser of a Gaussian mixture).
pub trait ConsistencyTeacher {
    /// Dimension of one (normalised) state.
    fn state_dim(&self) -> usize;

    /// Dimension of one (normalised, flattened) action.
    fn action_dim(&self) -> usize;

    /// The `(state, action)` normalisers mapping raw data into the space the denoiser works in.
    fn normalizers(&self) -> (&Affine, &Affine);

    /// Writes `D(x; σ_i, s_i)` of each row into `out`: `x` is `n x action_dim`, `sigma` has `n`
    /// positive levels, `states` is `n x state_dim`, `out` is `n x action_dim`.
    fn denoise(
        &mut self,
        x: MatRef<'_, f32>,
        sigma: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError>;

    /// The teacher's preconditioned denoiser network, when it has one (students of the same
    /// architecture start from its weights). `None` by default.
    fn network(&self) -> Option<&DenoiserNet> {
        None
    }
}

impl<T: ConsistencyTeacher + ?Sized> ConsistencyTeacher for &mut T {
    fn state_dim(&self) -> usize {
        (**self).state_dim()
    }
    fn action_dim(&self) -> usize {
        (**self).action_dim()
    }
    fn normalizers(&self) -> (&Affine, &Affine) {
        (**self).normalizers()
    }
    fn denoise(
        &mut self,
        x: MatRef<'_, f32>,
        sigma: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        (**self).denoise(x, sigma, states, out)
    }
    fn network(&self) -> Option<&DenoiserNet> {
        (**self).network()
    }
}

impl ConsistencyTeacher for Beso {
    fn state_dim(&self) -> usize {
        Beso::state_dim(self)
    }
    fn action_dim(&self) -> usize {
        Beso::action_dim(self)
    }
    fn normalizers(&self) -> (&Affine, &Affine) {
        Beso::normalizers(self)
    }
    fn denoise(
        &mut self,
        x: MatRef<'_, f32>,
        sigma: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        Beso::denoise(self, x, sigma, states, out)
    }
    /// The EMA denoiser network the teacher samples with.
    fn network(&self) -> Option<&DenoiserNet> {
        Some(self.net())
    }
}

/// A teacher given as a closure `denoise(x, σ, states, out)` in the normalised space of the
/// given normalisers — for analytic teachers such as the exact denoiser of a Gaussian mixture,
/// `D(x; σ) = E[a | a + σ z = x]`.
///
/// ```
/// use faer::{MatMut, MatRef};
/// use vdd_baselines::consistency::{ConsistencyTeacher, DenoiserFn};
/// use vdd_core::{Affine, CoreError};
/// // Data N(0, 0.5²) per dimension: D(x; σ) = 0.25 / (0.25 + σ²) · x.
/// let mut teacher = DenoiserFn::new(
///     Affine::identity(1),
///     Affine::identity(2),
///     |x: MatRef<'_, f32>, s: &[f32], _st: MatRef<'_, f32>, mut out: MatMut<'_, f32>| {
///         for j in 0..x.ncols() {
///             for i in 0..x.nrows() {
///                 out[(i, j)] = 0.25 / (0.25 + s[i] * s[i]) * x[(i, j)];
///             }
///         }
///         Ok::<(), CoreError>(())
///     },
/// );
/// let x = faer::mat![[1.0f32, -1.0]];
/// let mut out = faer::Mat::zeros(1, 2);
/// teacher.denoise(x.as_ref(), &[0.5], faer::Mat::zeros(1, 1).as_ref(), out.as_mut()).unwrap();
/// assert_eq!(out[(0, 0)], 0.5);
/// ```
pub struct DenoiserFn<F> {
    state_norm: Affine,
    action_norm: Affine,
    f: F,
}

impl<F> std::fmt::Debug for DenoiserFn<F> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DenoiserFn")
            .field("state_norm", &self.state_norm)
            .field("action_norm", &self.action_norm)
            .finish_non_exhaustive()
    }
}

impl<F> DenoiserFn<F>
where
    F: FnMut(MatRef<'_, f32>, &[f32], MatRef<'_, f32>, MatMut<'_, f32>) -> Result<(), CoreError>,
{
    /// A teacher whose denoiser is `f(x, σ, states, out)`, working in the space normalised by
    /// `state_norm` and `action_norm` (whose dimensions are the teacher's).
    pub fn new(state_norm: Affine, action_norm: Affine, f: F) -> Self {
        Self { state_norm, action_norm, f }
    }
}

impl<F> ConsistencyTeacher for DenoiserFn<F>
where
    F: FnMut(MatRef<'_, f32>, &[f32], MatRef<'_, f32>, MatMut<'_, f32>) -> Result<(), CoreError>,
{
    fn state_dim(&self) -> usize {
        self.state_norm.dim()
    }
    fn action_dim(&self) -> usize {
        self.action_norm.dim()
    }
    fn normalizers(&self) -> (&Affine, &Affine) {
        (&self.state_norm, &self.action_norm)
    }
    fn denoise(
        &mut self,
        x: MatRef<'_, f32>,
        sigma: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let n = x.nrows();
        check_shape("x", x, n, self.action_dim())?;
        check_shape("states", states, n, self.state_dim())?;
        check_len("sigma", sigma.len(), n)?;
        check_shape("denoiser output", out.rb(), n, self.action_dim())?;
        (self.f)(x, sigma, states, out)
    }
}

/// One Heun step of the teacher's probability-flow ODE from `sigma_from[i]` to `sigma_to[i]`
/// per row (normalised space), written into `out`.
pub(crate) fn teacher_heun_step<T: ConsistencyTeacher + ?Sized>(
    teacher: &mut T,
    x: MatRef<'_, f32>,
    sigma_from: &[f32],
    sigma_to: &[f32],
    states: MatRef<'_, f32>,
    out: MatMut<'_, f32>,
    buf: &mut SamplerBuffers,
) -> Result<(), BaselineError> {
    let mut denoise = |x: MatRef<'_, f32>, s: &[f32], o: MatMut<'_, f32>| {
        teacher.denoise(x, s, states, o).map_err(vdd_diffusion::DiffusionError::from)
    };
    vdd_diffusion::heun_step(&mut denoise, x, sigma_from, sigma_to, out, buf)
        .map_err(|e| BaselineError::Core(CoreError::from(e)))
}

/// The consistency-model preconditioning of Song et al. (2023), EDM-style with the boundary
/// condition at `σ_min`:
///
/// * `c_skip(σ) = σ_d² / ((σ − σ_min)² + σ_d²)`,
/// * `c_out(σ) = (σ − σ_min) σ_d / sqrt(σ² + σ_d²)`,
/// * `c_in(σ) = 1 / sqrt(σ² + σ_d²)`, `c_noise(σ) = ln(σ) / 4` (as the EDM teacher),
///
/// so `c_skip(σ_min) = 1` and `c_out(σ_min) = 0` exactly: `f(x, σ_min) = x`.
///
/// ```
/// use vdd_baselines::consistency::BoundaryPreconditioning;
/// let p = BoundaryPreconditioning::new(0.5, 0.002).unwrap();
/// assert_eq!((p.c_skip(0.002), p.c_out(0.002)), (1.0, 0.0));
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BoundaryPreconditioning {
    /// The data standard deviation `σ_d` (normalised space).
    pub sigma_data: f32,
    /// The boundary level `σ_min` where the consistency function is the identity.
    pub sigma_min: f32,
}

impl BoundaryPreconditioning {
    /// The preconditioning for `sigma_data > 0` and `sigma_min > 0`.
    pub fn new(sigma_data: f32, sigma_min: f32) -> Result<Self, CoreError> {
        if !(sigma_data.is_finite() && sigma_data > 0.0 && sigma_min.is_finite() && sigma_min > 0.0)
        {
            return Err(CoreError::Config(format!(
                "need sigma_data > 0 and sigma_min > 0, got {sigma_data}, {sigma_min}"
            )));
        }
        Ok(Self { sigma_data, sigma_min })
    }

    /// `σ_d² / ((σ − σ_min)² + σ_d²)`.
    #[inline]
    pub fn c_skip(&self, sigma: f32) -> f32 {
        let sd2 = self.sigma_data * self.sigma_data;
        let d = sigma - self.sigma_min;
        sd2 / (d * d + sd2)
    }

    /// `(σ − σ_min) σ_d / sqrt(σ² + σ_d²)`.
    #[inline]
    pub fn c_out(&self, sigma: f32) -> f32 {
        (sigma - self.sigma_min) * self.sigma_data
            / (sigma * sigma + self.sigma_data * self.sigma_data).sqrt()
    }

    /// `1 / sqrt(σ² + σ_d²)`.
    #[inline]
    pub fn c_in(&self, sigma: f32) -> f32 {
        1.0 / (sigma * sigma + self.sigma_data * self.sigma_data).sqrt()
    }

    /// `ln(σ) / 4`.
    #[inline]
    pub fn c_noise(&self, sigma: f32) -> f32 {
        0.25 * sigma.ln()
    }
}

/// Per-row coefficients of a preconditioned evaluation
/// `out_i = skip_i x_i + out_i F(c_in_i x_i, s_i, noise_i[, noise_to_i])`.
#[derive(Debug, Clone, Default)]
pub(crate) struct Coefficients {
    pub c_in: Vec<f32>,
    pub noise: Vec<f32>,
    pub noise_to: Vec<f32>,
    pub skip: Vec<f32>,
    pub out: Vec<f32>,
}

impl Coefficients {
    pub(crate) fn clear(&mut self) {
        self.c_in.clear();
        self.noise.clear();
        self.noise_to.clear();
        self.skip.clear();
        self.out.clear();
    }
}

/// The student network `F(x_in, s, c_noise[, c_noise_to])`: a [`ResidualMlp`] over
/// `[x_in (d_a) | state (d_s) | emb(c_noise) | emb(c_noise_to)]`, where `emb` is the teacher's
/// fixed sinusoidal embedding `[sin(ω_k c), cos(ω_k c)]_k` with `ω_k` geometric in
/// `[1, max_frequency]`. With one noise condition (`levels = 1`, Consistency Distillation) it
/// is exactly the BESO teacher's [`DenoiserNet`]; with two (`levels = 2`, CTM's `g(x, t, u)`)
/// the target level `u` gets its own embedding block.
///
/// Parameters are named `net.layers.*` like the teacher's, so
/// [`ConditionedNet::from_teacher`] copies a teacher of the same architecture (for two
/// levels, the input columns of the second embedding start at zero, so the network initially
/// ignores `u` and reproduces the teacher).
///
/// ```
/// use vdd_baselines::consistency::ConditionedNet;
/// use vdd_diffusion::NetConfig;
/// let cfg = NetConfig { hidden_dim: 16, num_blocks: 1, ..Default::default() };
/// let mut rng = vdd_core::Seeds::new(0).stream("init");
/// let mut net = ConditionedNet::new(&cfg, 2, 1, 2, &mut rng).unwrap();
/// let x = faer::Mat::<f32>::zeros(3, 2);
/// let s = faer::Mat::<f32>::zeros(3, 1);
/// let y = net.forward(x.as_ref(), s.as_ref(), &[0.1, 0.2, 0.3], &[0.0, 0.0, 0.1]);
/// assert_eq!((y.nrows(), y.ncols()), (3, 2));
/// ```
#[derive(Debug, Clone)]
pub struct ConditionedNet {
    config: NetConfig,
    action_dim: usize,
    state_dim: usize,
    levels: usize,
    mlp: ResidualMlp,
    freqs: Vec<f32>,
    input: Mat<f32>,
    scaled: Mat<f32>,
}

impl ConditionedNet {
    /// A freshly initialised network (PyTorch's default initialisation) with `levels ∈ {1, 2}`
    /// noise conditions.
    pub fn new(
        config: &NetConfig,
        action_dim: usize,
        state_dim: usize,
        levels: usize,
        rng: &mut vdd_core::Rng,
    ) -> Result<Self, BaselineError> {
        config.validate().map_err(CoreError::from)?;
        if action_dim == 0 {
            return Err(CoreError::Config("action_dim must be positive".into()).into());
        }
        if !(1..=2).contains(&levels) {
            return Err(CoreError::Config(format!(
                "a conditioned network takes 1 or 2 noise levels, got {levels}"
            ))
            .into());
        }
        let mlp_config = MlpCfg {
            in_dim: action_dim + state_dim + levels * config.embed_dim,
            hidden_dim: config.hidden_dim,
            num_blocks: config.num_blocks,
            out_dim: action_dim,
            activation: config.activation,
            layer_norm: false,
        };
        let mlp = ResidualMlp::new(&mlp_config, rng)?;
        let h = config.embed_dim / 2;
        // The teacher's frequencies, computed the same way (bit-identical).
        let freqs =
            (0..h)
                .map(|k| {
                    if h == 1 { 1.0 } else { config.max_frequency.powf(k as f32 / (h - 1) as f32) }
                })
                .collect();
        Ok(Self {
            config: config.clone(),
            action_dim,
            state_dim,
            levels,
            mlp,
            freqs,
            input: Mat::zeros(0, 0),
            scaled: Mat::zeros(0, 0),
        })
    }

    /// A network with the teacher's architecture and weights (`levels = 1`: an exact copy;
    /// `levels = 2`: the second embedding's input weights are zero, so the outputs equal the
    /// teacher's for every second level).
    pub fn from_teacher(teacher: &DenoiserNet, levels: usize) -> Result<Self, BaselineError> {
        let mut net = Self::new(
            teacher.config(),
            teacher.action_dim(),
            teacher.state_dim(),
            levels,
            &mut Seeds::new(0).stream("init"),
        )?;
        let mut src: HashMap<String, (Vec<usize>, Vec<f32>)> = HashMap::new();
        teacher.visit_params("", &mut |name, p| {
            src.insert(name.to_owned(), (p.shape.clone(), p.value.clone()));
        });
        let input_name = "net.layers.0.weight";
        let mut missing = None;
        net.visit_params_mut("", &mut |name, p: &mut Param| {
            let Some((shape, value)) = src.get(name) else {
                missing = Some(name.to_owned());
                return;
            };
            if *shape == p.shape {
                p.value.copy_from_slice(value);
            } else if name == input_name && shape.len() == 2 && shape[0] == p.shape[0] {
                // [hidden, in_teacher] into [hidden, in_teacher + embed_dim]: leading columns.
                let (rows, cin, cout) = (shape[0], shape[1], p.shape[1]);
                for r in 0..rows {
                    let dst = &mut p.value[r * cout..(r + 1) * cout];
                    dst[..cin].copy_from_slice(&value[r * cin..(r + 1) * cin]);
                    dst[cin..].fill(0.0);
                }
            } else {
                missing = Some(name.to_owned());
            }
        });
        if let Some(name) = missing {
            return Err(CoreError::Config(format!(
                "cannot initialise the student from the teacher: parameter `{name}` differs"
            ))
            .into());
        }
        Ok(net)
    }

    /// The architecture.
    pub fn config(&self) -> &NetConfig {
        &self.config
    }

    /// Action (output) dimension.
    pub fn action_dim(&self) -> usize {
        self.action_dim
    }

    /// State dimension.
    pub fn state_dim(&self) -> usize {
        self.state_dim
    }

    /// Number of noise conditions (1 or 2).
    pub fn levels(&self) -> usize {
        self.levels
    }

    /// Forward pass. `x` is `n x action_dim` (already `c_in`-scaled), `states` `n x state_dim`,
    /// `c_noise` has `n` entries, `c_noise_to` has `n` entries for a two-level network (it is
    /// ignored by a one-level network). Returns a view into the network's output buffer.
    ///
    /// # Panics
    /// On mismatched shapes (callers validate user data first).
    pub fn forward(
        &mut self,
        x: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        c_noise: &[f32],
        c_noise_to: &[f32],
    ) -> MatRef<'_, f32> {
        let n = x.nrows();
        assert!(
            x.ncols() == self.action_dim
                && states.nrows() == n
                && states.ncols() == self.state_dim
                && c_noise.len() == n
                && (self.levels == 1 || c_noise_to.len() == n),
            "ConditionedNet: input shapes"
        );
        let (da, ds, e) = (self.action_dim, self.state_dim, self.config.embed_dim);
        let width = da + ds + self.levels * e;
        if self.input.nrows() != n || self.input.ncols() != width {
            self.input = Mat::zeros(n, width);
        }
        self.input.as_mut().subcols_mut(0, da).copy_from(x);
        self.input.as_mut().subcols_mut(da, ds).copy_from(states);
        let h = self.freqs.len();
        for level in 0..self.levels {
            let c = if level == 0 { c_noise } else { c_noise_to };
            let base = da + ds + level * e;
            for (k, &w) in self.freqs.iter().enumerate() {
                for i in 0..n {
                    let (s, co) = (w * c[i]).sin_cos();
                    self.input[(i, base + k)] = s;
                    self.input[(i, base + h + k)] = co;
                }
            }
        }
        self.mlp.forward(self.input.as_ref())
    }

    /// Backward pass for the last forward: accumulates parameter gradients for `grad_out`
    /// (`n x action_dim`).
    pub fn backward(&mut self, grad_out: MatRef<'_, f32>) {
        self.mlp.backward(grad_out);
    }

    /// `out_i = skip_i x_i + out_i F(c_in_i x_i, s_i, noise_i, noise_to_i)` for every row.
    pub(crate) fn forward_preconditioned(
        &mut self,
        x: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        coef: &Coefficients,
        mut out: MatMut<'_, f32>,
    ) {
        let (n, d) = (x.nrows(), x.ncols());
        let mut scaled = std::mem::replace(&mut self.scaled, Mat::zeros(0, 0));
        if scaled.nrows() != n || scaled.ncols() != d {
            scaled = Mat::zeros(n, d);
        }
        for j in 0..d {
            let col = scaled.col_as_slice_mut(j);
            for i in 0..n {
                col[i] = coef.c_in[i] * x[(i, j)];
            }
        }
        let f = self.forward(scaled.as_ref(), states, &coef.noise, &coef.noise_to);
        for j in 0..d {
            for i in 0..n {
                out[(i, j)] = coef.skip[i] * x[(i, j)] + coef.out[i] * f[(i, j)];
            }
        }
        self.scaled = scaled;
    }
}

impl Parameters for ConditionedNet {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        self.mlp.visit_params(&vdd_nn::join_name(prefix, "net"), f);
    }
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        self.mlp.visit_params_mut(&vdd_nn::join_name(prefix, "net"), f);
    }
}

/// Optimisation settings shared by [`crate::cd`] and [`crate::ctm`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ConsistencyTrainConfig {
    /// Optimisation steps.
    pub steps: u64,
    /// Minibatch size (rows drawn uniformly with replacement from the data).
    pub batch_size: usize,
    /// Adam's hyper-parameters.
    pub adam: AdamConfig,
    /// Learning-rate schedule over the steps.
    pub lr_schedule: LrSchedule,
    /// Global gradient-norm clipping threshold (`None`: no clipping).
    pub grad_clip: Option<f32>,
    /// Decay `μ` of the target network `θ⁻ ← μ θ⁻ + (1 − μ) θ` (updated after every step).
    pub target_ema_decay: f32,
    /// Decay of the separate average of the online weights that the returned model samples
    /// with (0: the final online weights).
    pub ema_decay: f32,
    /// Report progress every this many steps (and after the last).
    pub log_every: u64,
    /// Root seed of every random draw of the run.
    pub seed: u64,
}

impl Default for ConsistencyTrainConfig {
    /// 4000 steps of 256 pairs, Adam `2e-4` with a cosine decay to 10%, clipping at norm 1,
    /// target decay 0.95 (Song et al.'s CD setting), evaluation average 0.999.
    fn default() -> Self {
        Self {
            steps: 4000,
            batch_size: 256,
            adam: AdamConfig { lr: 2e-4, ..AdamConfig::default() },
            lr_schedule: LrSchedule::Cosine { total_steps: 4000, final_factor: 0.1 },
            grad_clip: Some(1.0),
            target_ema_decay: 0.95,
            ema_decay: 0.999,
            log_every: 500,
            seed: 0,
        }
    }
}

impl ConsistencyTrainConfig {
    /// Checks the numbers.
    pub fn validate(&self) -> Result<(), CoreError> {
        let a = &self.adam;
        let ok = self.steps > 0
            && self.batch_size > 0
            && self.log_every > 0
            && a.lr.is_finite()
            && a.lr > 0.0
            && (0.0..1.0).contains(&a.beta1)
            && (0.0..1.0).contains(&a.beta2)
            && a.eps > 0.0
            && a.weight_decay.is_finite()
            && a.weight_decay >= 0.0
            && (0.0..1.0).contains(&self.target_ema_decay)
            && (0.0..1.0).contains(&self.ema_decay)
            && self.grad_clip.is_none_or(|g| g.is_finite() && g > 0.0);
        if !ok {
            return Err(CoreError::Config(format!("invalid training configuration {self:?}")));
        }
        self.lr_schedule
            .validate()
            .map_err(|e| CoreError::Config(format!("learning-rate schedule: {e}")))
    }
}

/// A progress report of a consistency training run.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ConsistencyProgress {
    /// Steps done so far.
    pub step: u64,
    /// Total steps.
    pub total_steps: u64,
    /// Mean total loss over the steps since the previous report.
    pub loss: f32,
    /// Mean consistency term (CD's loss, CTM's soft consistency matching).
    pub consistency_loss: f32,
    /// Mean denoising-score-matching term (CTM; 0 for CD).
    pub dsm_loss: f32,
    /// Learning rate of the last step.
    pub lr: f32,
    /// Wall-clock seconds since training started.
    pub elapsed_secs: f64,
}

/// Validates raw `states`/`actions` against the teacher and normalises them with its
/// normalisers.
pub(crate) fn normalised_data<T: ConsistencyTeacher + ?Sized>(
    teacher: &T,
    states: MatRef<'_, f32>,
    actions: MatRef<'_, f32>,
) -> Result<Dataset, CoreError> {
    let (sn, an) = teacher.normalizers();
    check_len("teacher state normaliser", sn.dim(), teacher.state_dim())?;
    check_len("teacher action normaliser", an.dim(), teacher.action_dim())?;
    check_len("data state columns vs teacher state_dim", states.ncols(), teacher.state_dim())?;
    check_len("data action columns vs teacher action_dim", actions.ncols(), teacher.action_dim())?;
    check_finite("training states", states)?;
    check_finite("training actions", actions)?;
    let norm = |m: MatRef<'_, f32>, a: &Affine| {
        Mat::from_fn(m.nrows(), m.ncols(), |i, j| (m[(i, j)] - a.offset[j]) / a.scale[j])
    };
    Dataset::new(norm(states, sn), norm(actions, an))
}

/// Checks the σ grid settings shared by both distillations.
pub(crate) fn validate_levels(
    sigma_data: f32,
    sigma_min: f32,
    sigma_max: f32,
    rho: f32,
    num_scales: usize,
) -> Result<(), CoreError> {
    BoundaryPreconditioning::new(sigma_data, sigma_min)?;
    if !(sigma_max.is_finite() && sigma_max > sigma_min) {
        return Err(CoreError::Config(format!(
            "need sigma_max > sigma_min, got {sigma_max} <= {sigma_min}"
        )));
    }
    if !(rho.is_finite() && rho > 0.0) {
        return Err(CoreError::Config(format!("rho must be positive, got {rho}")));
    }
    if num_scales < 2 {
        return Err(CoreError::Config(format!("num_scales must be >= 2, got {num_scales}")));
    }
    Ok(())
}

/// The `n ≥ 1` Karras levels from `σ_max` down to `σ_min` (without the trailing 0).
pub(crate) fn karras_levels(
    n: usize,
    sigma_min: f32,
    sigma_max: f32,
    rho: f32,
) -> Result<Vec<f32>, CoreError> {
    let mut v = vdd_diffusion::karras_sigmas(n, sigma_min, sigma_max, rho)?;
    v.pop();
    Ok(v)
}

/// The student's initial weights: the teacher's network when asked (it must exist and match),
/// or a fresh network from the seed's `"init"` stream.
pub(crate) fn initial_network<T: ConsistencyTeacher + ?Sized>(
    teacher: &T,
    config: &NetConfig,
    init_from_teacher: bool,
    levels: usize,
    seed: u64,
) -> Result<ConditionedNet, BaselineError> {
    if !init_from_teacher {
        return ConditionedNet::new(
            config,
            teacher.action_dim(),
            teacher.state_dim(),
            levels,
            &mut Seeds::new(seed).stream("init"),
        );
    }
    let Some(net) = teacher.network() else {
        return Err(CoreError::Config(
            "init_from_teacher is set but the teacher exposes no network".into(),
        )
        .into());
    };
    if net.config() != config
        || net.action_dim() != teacher.action_dim()
        || net.state_dim() != teacher.state_dim()
    {
        return Err(CoreError::Config(format!(
            "init_from_teacher is set but the student architecture {config:?} differs from the \
             teacher's {:?}",
            net.config()
        ))
        .into());
    }
    ConditionedNet::from_teacher(net, levels)
}

/// Adam, the learning-rate schedule, the target network's and the evaluation average.
#[derive(Debug, Clone)]
pub(crate) struct Optimisation {
    adam: Adam,
    schedule: LrSchedule,
    grad_clip: Option<f32>,
    target_ema: Ema,
    eval_ema: Ema,
    base_lr: f32,
}

impl Optimisation {
    pub(crate) fn new(
        config: &ConsistencyTrainConfig,
        online: &ConditionedNet,
    ) -> Result<Self, BaselineError> {
        Ok(Self {
            adam: Adam::new(config.adam),
            schedule: config.lr_schedule.clone(),
            grad_clip: config.grad_clip,
            target_ema: Ema::new(online, config.target_ema_decay)?,
            eval_ema: Ema::new(online, config.ema_decay)?,
            base_lr: config.adam.lr,
        })
    }

    /// Clips (or rejects non-finite) gradients, takes one Adam step on `online`, moves the
    /// target network and the evaluation average. Returns the learning rate used.
    pub(crate) fn apply(
        &mut self,
        online: &mut ConditionedNet,
        target: &mut ConditionedNet,
        step: u64,
    ) -> Result<f32, BaselineError> {
        fit::clip_or_fail(online, self.grad_clip, step as usize, "consistency gradient")?;
        let factor = self.schedule.factor(step);
        self.adam.step(online, factor);
        self.target_ema.update(online)?;
        self.target_ema.copy_to(target)?;
        self.eval_ema.update(online)?;
        Ok(self.base_lr * factor)
    }

    /// A copy of `online` carrying the evaluation average.
    pub(crate) fn averaged(
        &self,
        online: &ConditionedNet,
    ) -> Result<ConditionedNet, BaselineError> {
        let mut net = online.clone();
        self.eval_ema.copy_to(&mut net)?;
        Ok(net)
    }
}

/// Accumulates the loss terms between progress reports.
#[derive(Debug, Clone, Default)]
pub(crate) struct LossMeter {
    total: f64,
    consistency: f64,
    dsm: f64,
    count: u64,
}

impl LossMeter {
    pub(crate) fn add(&mut self, consistency: f32, dsm: f32, total: f32) {
        self.total += f64::from(total);
        self.consistency += f64::from(consistency);
        self.dsm += f64::from(dsm);
        self.count += 1;
    }

    /// The report for `step` of `total_steps`, resetting the averages.
    pub(crate) fn report(
        &mut self,
        step: u64,
        total_steps: u64,
        lr: f32,
        elapsed_secs: f64,
    ) -> ConsistencyProgress {
        let c = self.count.max(1) as f64;
        let p = ConsistencyProgress {
            step,
            total_steps,
            loss: (self.total / c) as f32,
            consistency_loss: (self.consistency / c) as f32,
            dsm_loss: (self.dsm / c) as f32,
            lr,
            elapsed_secs,
        };
        *self = Self::default();
        p
    }
}

/// Minibatch buffers: row indices, states, actions.
#[derive(Debug, Clone)]
pub(crate) struct Minibatch {
    pub idx: Vec<usize>,
    pub states: Mat<f32>,
    pub actions: Mat<f32>,
}

impl Default for Minibatch {
    fn default() -> Self {
        Self { idx: Vec::new(), states: Mat::zeros(0, 0), actions: Mat::zeros(0, 0) }
    }
}

impl Minibatch {
    pub(crate) fn draw(
        &mut self,
        data: &Dataset,
        sampler: &fit::RowSampler,
        size: usize,
        rng: &mut vdd_core::Rng,
    ) {
        sampler.draw(rng, size, &mut self.idx);
        fit::gather_rows(data.states(), &self.idx, &mut self.states);
        fit::gather_rows(data.actions(), &self.idx, &mut self.actions);
    }
}

/// Resizes `m` to `r x c` when its shape differs.
pub(crate) fn ensure(m: &mut Mat<f32>, r: usize, c: usize) {
    if m.nrows() != r || m.ncols() != c {
        *m = Mat::zeros(r, c);
    }
}

/// Fills `m` with standard normal draws.
pub(crate) fn fill_normal(m: &mut Mat<f32>, rng: &mut vdd_core::Rng) {
    for j in 0..m.ncols() {
        vdd_core::fill_standard_normal(rng, m.col_as_slice_mut(j));
    }
}

/// Reused raw ↔ normalised buffers of a policy.
#[derive(Debug, Clone)]
pub(crate) struct PolicyIo {
    pub obs: Mat<f32>,
    pub act: Mat<f32>,
}

impl Default for PolicyIo {
    fn default() -> Self {
        Self { obs: Mat::zeros(0, 0), act: Mat::zeros(0, 0) }
    }
}

impl PolicyIo {
    /// Normalises raw observations into `self.obs` and sizes `self.act`.
    pub(crate) fn load(&mut self, obs: MatRef<'_, f32>, norm: &Affine, action_dim: usize) {
        let n = obs.nrows();
        ensure(&mut self.obs, n, obs.ncols());
        ensure(&mut self.act, n, action_dim);
        for j in 0..obs.ncols() {
            let (o, s) = (norm.offset[j], norm.scale[j]);
            let dst = self.obs.col_as_slice_mut(j);
            for i in 0..n {
                dst[i] = (obs[(i, j)] - o) / s;
            }
        }
    }

    /// Writes `self.act`, denormalised, into `out`.
    pub(crate) fn store(&self, norm: &Affine, mut out: MatMut<'_, f32>) {
        for j in 0..out.ncols() {
            let (o, s) = (norm.offset[j], norm.scale[j]);
            let src = self.act.col_as_slice(j);
            for i in 0..out.nrows() {
                out[(i, j)] = src[i] * s + o;
            }
        }
    }
}

/// Checks a policy batch: `obs` `n x obs_dim` finite, `actions` `n x action_dim`.
pub(crate) fn check_policy_batch(
    obs: MatRef<'_, f32>,
    actions: MatRef<'_, f32>,
    obs_dim: usize,
    action_dim: usize,
) -> Result<(), CoreError> {
    let n = obs.nrows();
    check_shape("observations", obs, n, obs_dim)?;
    check_finite("observations", obs)?;
    check_shape("actions", actions, n, action_dim)
}

/// Checks normalised model inputs: `x` `n x d_a` and `states` `n x d_s` finite, `out`
/// `n x d_a`, and positive finite levels of length `n`.
pub(crate) fn check_model_batch(
    x: MatRef<'_, f32>,
    states: MatRef<'_, f32>,
    levels: &[&[f32]],
    out: MatRef<'_, f32>,
    action_dim: usize,
    state_dim: usize,
) -> Result<(), CoreError> {
    let n = x.nrows();
    check_shape("x", x, n, action_dim)?;
    check_shape("states", states, n, state_dim)?;
    check_shape("output", out, n, action_dim)?;
    check_finite("x", x)?;
    check_finite("states", states)?;
    for l in levels {
        check_len("noise levels", l.len(), n)?;
        if !l.iter().all(|s| s.is_finite() && *s > 0.0) {
            return Err(CoreError::Config("noise levels must be positive and finite".into()));
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn student_from_teacher_reproduces_the_teacher_network() {
        let cfg = NetConfig { hidden_dim: 8, num_blocks: 1, embed_dim: 4, ..Default::default() };
        let mut teacher = DenoiserNet::new(&cfg, 2, 1, &mut Seeds::new(3).stream("init")).unwrap();
        let x = Mat::from_fn(3, 2, |i, j| 0.3 * i as f32 - 0.2 * j as f32);
        let s = Mat::from_fn(3, 1, |i, _| i as f32);
        let c = [0.1f32, -0.4, 0.9];
        let want = teacher.forward(x.as_ref(), s.as_ref(), &c).to_owned();
        let mut one = ConditionedNet::from_teacher(&teacher, 1).unwrap();
        assert_eq!(one.forward(x.as_ref(), s.as_ref(), &c, &[]).to_owned(), want);
        let mut two = ConditionedNet::from_teacher(&teacher, 2).unwrap();
        assert_eq!(two.forward(x.as_ref(), s.as_ref(), &c, &[2.0, -1.0, 0.0]).to_owned(), want);
        assert_eq!(two.mlp.in_dim(), 3 + 2 * 4);
        // A fresh network differs.
        let mut fresh =
            ConditionedNet::new(&cfg, 2, 1, 1, &mut Seeds::new(4).stream("init")).unwrap();
        assert_ne!(fresh.forward(x.as_ref(), s.as_ref(), &c, &[]).to_owned(), want);
        assert!(ConditionedNet::new(&cfg, 2, 1, 3, &mut Seeds::new(4).stream("i")).is_err());
    }

    #[test]
    fn boundary_preconditioning_is_the_identity_at_sigma_min() {
        let p = BoundaryPreconditioning::new(0.5, 0.002).unwrap();
        assert_eq!(p.c_skip(0.002), 1.0);
        assert_eq!(p.c_out(0.002), 0.0);
        // Far from σ_min it approaches EDM's coefficients.
        let edm = vdd_diffusion::Preconditioning::new(0.5).unwrap();
        assert!((p.c_skip(10.0) - edm.c_skip(10.0)).abs() < 1e-4);
        assert!((p.c_out(10.0) - edm.c_out(10.0)).abs() < 1e-3);
        assert!(BoundaryPreconditioning::new(0.0, 0.002).is_err());
        assert!(BoundaryPreconditioning::new(0.5, -1.0).is_err());
    }
}
