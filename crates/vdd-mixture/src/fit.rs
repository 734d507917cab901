//! Shared pieces of the likelihood-based mixture baselines (EM, IMC): the weighted Gaussian
//! negative log-likelihood with closed-form gradients, the gating's soft cross-entropy,
//! dataset evaluation, minibatch sampling and one optimiser step for experts or gating — and,
//! inside the crate, the loop around them that both trainers run (the state they carry, the
//! expert and gating steps of an iteration with their batches, learning rates and settings
//! checks), to which each adds only its E-step and how it weights a batch row.
//!
//! ## Weighted Gaussian NLL
//!
//! For an expert `N(μ, Σ)`, `Σ = L Lᵀ` (`L` lower-triangular, positive diagonal) and an action
//! `a`, with `u = L⁻¹(a − μ)` and `v = L⁻ᵀ u = Σ⁻¹(a − μ)`:
//!
//! * `NLL = ½ uᵀu + Σ_i log L_ii + (d/2) log 2π`,
//! * `∂NLL/∂μ = −v`,
//! * `∂NLL/∂L = −tril(v uᵀ) + diag(1 / L_ii)` (a diagonal family reads the diagonal only:
//!   `∂NLL/∂σ_i = −v_i u_i + 1/σ_i = (1 − u_i²)/σ_i`).
//!
//! (From `du = −L⁻¹ dL u`, so `d(½uᵀu) = −vᵀ dL u`.) [`weighted_nll_gradients`] sums
//! `Σ_{b,z} w_{bz} NLL_z(a_b | s_b)` over a batch and pushes each `(∂/∂μ, ∂/∂L)` through
//! [`Expert::backward`] to gradients of the experts' raw network outputs, ready for
//! [`Moe::backward_experts`].
//!
//! ## Gating
//!
//! [`soft_cross_entropy`] ([`vdd_moe::step`], shared with VDD) is `−Σ_b c_b Σ_z t_{bz} log q(z|s_b)` for per-row weights `c_b` and
//! targets `t_b` (responsibilities or curriculum posteriors); its gradient with respect to the
//! gating logits is `c_b (q(z|s_b) Σ_k t_{bk} − t_{bz})`.

use faer::{Mat, MatRef};
use rand::Rng as _;
use vdd_core::gaussian::{self, solve_lower_in_place, solve_upper_t_in_place};
use vdd_core::{CoreError, Expert, Rng, Seeds, check_finite_slice, check_len, check_shape};
use vdd_moe::step::{clip_or_fail, soft_cross_entropy};
use vdd_moe::{Moe, MoeOutput};
use vdd_nn::parallel::Workers;
use vdd_nn::{Adam, AdamConfig, LrSchedule, Parameters};

use crate::dataset::Dataset;
use crate::error::MixtureError;

mod eval;
pub use eval::evaluate_dataset;
pub(crate) use eval::{ParallelEval, Scoring};

/// Rows per forward pass when a whole dataset is evaluated.
pub const EVAL_CHUNK: usize = 2048;

/// `−log N(a; μ, L Lᵀ)` and its gradients: `d_mean = ∂/∂μ` (`d`) and `d_scale_tril = ∂/∂L`
/// (`d·d`, row-major, zero above the diagonal). `work` is scratch of length `d`.
///
/// ```
/// use vdd_mixture::fit::gaussian_nll_and_grad;
/// let (mut dm, mut dl, mut w) = ([0.0f32; 1], [0.0f32; 1], [0.0f32; 1]);
/// // N(0, 2²) at a = 2: u = 1, v = 1/2.
/// let nll = gaussian_nll_and_grad(&[2.0], &[0.0], &[2.0], &mut dm, &mut dl, &mut w);
/// assert!((nll - (0.5 + 2.0f32.ln() + 0.5 * vdd_core::gaussian::LN_2PI)).abs() < 1e-6);
/// assert!((dm[0] + 0.5).abs() < 1e-6); // −v
/// assert!(dl[0].abs() < 1e-6);         // (1 − u²)/σ
/// ```
#[inline]
pub fn gaussian_nll_and_grad(
    a: &[f32],
    mean: &[f32],
    scale_tril: &[f32],
    d_mean: &mut [f32],
    d_scale_tril: &mut [f32],
    work: &mut [f32],
) -> f32 {
    let d = a.len();
    for i in 0..d {
        work[i] = a[i] - mean[i];
    }
    solve_lower_in_place(scale_tril, work); // u
    let maha: f32 = work.iter().map(|u| u * u).sum();
    d_mean.copy_from_slice(work);
    solve_upper_t_in_place(scale_tril, d_mean); // v
    for i in 0..d {
        let vi = d_mean[i];
        for j in 0..d {
            d_scale_tril[i * d + j] = if j <= i { -vi * work[j] } else { 0.0 };
        }
        d_scale_tril[i * d + i] += 1.0 / scale_tril[i * d + i];
    }
    for g in d_mean.iter_mut() {
        *g = -*g;
    }
    0.5 * maha + gaussian::half_log_det(scale_tril, d) + 0.5 * d as f32 * gaussian::LN_2PI
}

/// Buffers reused across fitting steps (no allocation in the steady state).
#[derive(Debug, Clone, Default)]
pub struct FitBuffers {
    /// Gradient of the weighted NLL with respect to the raw outputs, `n·Z·raw_dim`.
    pub grad_raw: Vec<f32>,
    action: Vec<f32>,
    d_mean: Vec<f32>,
    d_scale: Vec<f32>,
    work: Vec<f32>,
}

/// The weighted negative log-likelihood `Σ_{b,z} w_{bz} NLL_z(a_b | s_b)` of the batch whose
/// expert outputs are in `out` (from [`Moe::forward_experts`] on the batch's states), and its
/// gradient with respect to the raw outputs, written into `buf.grad_raw` (row-major
/// `n·Z·raw_dim`, for [`Moe::backward_experts`]).
///
/// `actions` is `n x d`; `weights` is `n·Z` row-major, finite and typically non-negative. Pairs
/// of zero weight are skipped (their gradient is zero).
pub fn weighted_nll_gradients<E: Expert>(
    expert: &E,
    out: &MoeOutput,
    actions: MatRef<'_, f32>,
    weights: &[f32],
    buf: &mut FitBuffers,
) -> Result<f64, CoreError> {
    let (n, z_n, d, r) = (out.n, out.num_experts, out.action_dim, expert.raw_dim());
    check_shape("actions", actions, n, d)?;
    check_len("weights", weights.len(), n * z_n)?;
    check_len("expert family action_dim", expert.action_dim(), d)?;
    check_len("raw outputs", out.raw.len(), n * z_n * r)?;
    check_finite_slice("weights", weights)?;
    buf.grad_raw.resize(n * z_n * r, 0.0);
    buf.action.resize(d, 0.0);
    buf.d_mean.resize(d, 0.0);
    buf.d_scale.resize(d * d, 0.0);
    buf.work.resize(d, 0.0);
    let mut loss = 0.0f64;
    for b in 0..n {
        for j in 0..d {
            buf.action[j] = actions[(b, j)];
        }
        for k in 0..z_n {
            let bz = b * z_n + k;
            let w = weights[bz];
            let g = &mut buf.grad_raw[bz * r..(bz + 1) * r];
            if w == 0.0 {
                g.fill(0.0);
                continue;
            }
            let nll = gaussian_nll_and_grad(
                &buf.action,
                out.mean(b, k),
                out.scale(b, k),
                &mut buf.d_mean,
                &mut buf.d_scale,
                &mut buf.work,
            );
            loss += f64::from(w) * f64::from(nll);
            expert.backward(&out.raw[bz * r..(bz + 1) * r], &buf.d_mean, &buf.d_scale, g);
            for x in g.iter_mut() {
                *x *= w;
            }
        }
    }
    Ok(loss)
}

/// [`weighted_nll_gradients`] with every expert's covariance fixed to the identity:
/// `Σ_{b,z} w_{bz} ½‖a_b − μ_z(s_b)‖²` (the constant `(d/2) log 2π` left out), gradients to
/// the means only (the scales get zero gradient).
pub(crate) fn weighted_unit_nll_gradients<E: Expert>(
    expert: &E,
    out: &MoeOutput,
    actions: MatRef<'_, f32>,
    weights: &[f32],
    buf: &mut FitBuffers,
) -> Result<f64, CoreError> {
    let (n, z_n, d, r) = (out.n, out.num_experts, out.action_dim, expert.raw_dim());
    check_shape("actions", actions, n, d)?;
    check_len("weights", weights.len(), n * z_n)?;
    check_len("raw outputs", out.raw.len(), n * z_n * r)?;
    check_finite_slice("weights", weights)?;
    buf.grad_raw.resize(n * z_n * r, 0.0);
    buf.d_mean.resize(d, 0.0);
    buf.d_scale.resize(d * d, 0.0);
    buf.d_scale.fill(0.0);
    let mut loss = 0.0f64;
    for b in 0..n {
        for k in 0..z_n {
            let bz = b * z_n + k;
            let w = weights[bz];
            let g = &mut buf.grad_raw[bz * r..(bz + 1) * r];
            if w == 0.0 {
                g.fill(0.0);
                continue;
            }
            let mean = out.mean(b, k);
            let mut half_sq = 0.0f32;
            for j in 0..d {
                let diff = actions[(b, j)] - mean[j];
                half_sq += 0.5 * diff * diff;
                buf.d_mean[j] = -diff;
            }
            loss += f64::from(w) * f64::from(half_sq);
            expert.backward(&out.raw[bz * r..(bz + 1) * r], &buf.d_mean, &buf.d_scale, g);
            for x in g.iter_mut() {
                *x *= w;
            }
        }
    }
    Ok(loss)
}

/// Draws dataset row indices for minibatches: uniformly, or in proportion to weights.
///
/// ```
/// use vdd_mixture::fit::RowSampler;
/// let s = RowSampler::weighted(&[0.0, 1.0, 0.0]).unwrap();
/// let mut idx = Vec::new();
/// s.draw(&mut vdd_core::Seeds::new(0).stream("batch"), 5, &mut idx);
/// assert_eq!(idx, vec![1; 5]);
/// ```
#[derive(Debug, Clone, PartialEq)]
pub enum RowSampler {
    /// Every row equally likely.
    Uniform {
        /// Number of rows.
        n: usize,
    },
    /// Row `i` with probability `w_i / Σ w`.
    Weighted {
        /// Running sums of the weights.
        cumulative: Vec<f64>,
    },
    /// Every row of a subset equally likely.
    Subset {
        /// The rows drawn from (not empty).
        rows: Vec<usize>,
    },
}

impl RowSampler {
    /// Uniform over `n > 0` rows.
    pub fn uniform(n: usize) -> Result<Self, CoreError> {
        if n == 0 {
            return Err(CoreError::Config("cannot sample from zero rows".into()));
        }
        Ok(Self::Uniform { n })
    }

    /// In proportion to `weights` (non-negative, finite, not all zero).
    pub fn weighted(weights: &[f64]) -> Result<Self, CoreError> {
        let mut cumulative = Vec::with_capacity(weights.len());
        let mut acc = 0.0f64;
        for &w in weights {
            if !(w.is_finite() && w >= 0.0) {
                return Err(CoreError::Config(format!("sampling weight {w} is not >= 0")));
            }
            acc += w;
            cumulative.push(acc);
        }
        if !(acc > 0.0 && acc.is_finite()) {
            return Err(CoreError::Config("sampling weights sum to zero".into()));
        }
        Ok(Self::Weighted { cumulative })
    }

    /// Uniform over `rows` (not empty).
    pub fn subset(rows: Vec<usize>) -> Result<Self, CoreError> {
        if rows.is_empty() {
            return Err(CoreError::Config("cannot sample from zero rows".into()));
        }
        Ok(Self::Subset { rows })
    }

    /// Replaces the contents of `out` with `size` independent draws.
    pub fn draw(&self, rng: &mut Rng, size: usize, out: &mut Vec<usize>) {
        out.clear();
        match self {
            Self::Uniform { n } => out.extend((0..size).map(|_| rng.random_range(0..*n))),
            Self::Weighted { cumulative } => {
                let total = *cumulative.last().expect("weighted sampler has rows");
                let last = cumulative.len() - 1;
                out.extend((0..size).map(|_| {
                    let u = rng.random::<f64>() * total;
                    cumulative.partition_point(|&c| c <= u).min(last)
                }));
            }
            Self::Subset { rows } => {
                out.extend((0..size).map(|_| rows[rng.random_range(0..rows.len())]));
            }
        }
    }
}

/// Copies rows `idx` of `src` into `dst` (resized to `idx.len() x src.ncols()` if needed).
pub fn gather_rows(src: MatRef<'_, f32>, idx: &[usize], dst: &mut Mat<f32>) {
    if dst.nrows() != idx.len() || dst.ncols() != src.ncols() {
        *dst = Mat::zeros(idx.len(), src.ncols());
    }
    for j in 0..src.ncols() {
        let col = dst.col_as_slice_mut(j);
        for (b, &i) in idx.iter().enumerate() {
            col[b] = src[(i, j)];
        }
    }
}

/// One optimiser step of the experts on the weighted NLL `Σ_{b,z} w_{bz} NLL_z(a_b|s_b)` of a
/// batch (`states` `n x d_s`, `actions` `n x d`, `weights` `n·Z`). Returns the loss before the
/// step. Nothing is updated when the loss or a gradient is not finite.
#[allow(clippy::too_many_arguments)]
pub fn expert_step<E: Expert>(
    student: &mut Moe<E>,
    states: MatRef<'_, f32>,
    actions: MatRef<'_, f32>,
    weights: &[f32],
    optimizer: &mut Adam,
    lr_factor: f32,
    max_grad_norm: Option<f32>,
    iteration: usize,
    buf: &mut FitBuffers,
) -> Result<f64, MixtureError> {
    let step = StepArgs { lr_factor, max_grad_norm, iteration, unit_variance: false };
    expert_step_with(student, states, actions, weights, optimizer, step, buf)
}

/// The per-step settings of [`expert_step_with`].
#[derive(Debug, Clone, Copy)]
pub(crate) struct StepArgs {
    pub(crate) lr_factor: f32,
    pub(crate) max_grad_norm: Option<f32>,
    pub(crate) iteration: usize,
    /// Score the experts as `N(μ_z, I)` (their scales neither used nor trained).
    pub(crate) unit_variance: bool,
}

/// [`expert_step`], optionally with unit-variance experts.
fn expert_step_with<E: Expert>(
    student: &mut Moe<E>,
    states: MatRef<'_, f32>,
    actions: MatRef<'_, f32>,
    weights: &[f32],
    optimizer: &mut Adam,
    step: StepArgs,
    buf: &mut FitBuffers,
) -> Result<f64, MixtureError> {
    let StepArgs { lr_factor, max_grad_norm, iteration, unit_variance } = step;
    student.forward_experts(states)?;
    let (expert, out) = (student.expert(), student.output());
    let loss = if unit_variance {
        weighted_unit_nll_gradients(expert, out, actions, weights, buf)?
    } else {
        weighted_nll_gradients(expert, out, actions, weights, buf)?
    };
    if !loss.is_finite() {
        return Err(MixtureError::NonFinite { iteration, quantity: "expert loss" });
    }
    student.expert_networks_mut().zero_grad();
    let grad_raw = std::mem::take(&mut buf.grad_raw);
    let r = student.backward_experts(&grad_raw);
    buf.grad_raw = grad_raw;
    r?;
    let nets = student.expert_networks_mut();
    clip_or_fail(nets, max_grad_norm, iteration, "expert gradient")?;
    optimizer.step(nets, lr_factor).map_err(vdd_moe::MoeError::from)?;
    Ok(loss)
}

/// One optimiser step of the gating on the soft cross-entropy towards `targets` (`n·Z`) with
/// per-row weights `row_weights` (`n`): [`vdd_moe::step::gating_step`] with
/// [`soft_cross_entropy`]. Returns the loss before the step, or `None` (and does nothing) when
/// the mixture's gating is not learned. `grad_logits` is a reusable buffer.
#[allow(clippy::too_many_arguments)]
pub fn gating_step<E: Expert>(
    student: &mut Moe<E>,
    states: MatRef<'_, f32>,
    targets: &[f32],
    row_weights: &[f32],
    optimizer: &mut Adam,
    lr_factor: f32,
    max_grad_norm: Option<f32>,
    iteration: usize,
    grad_logits: &mut Mat<f32>,
) -> Result<Option<f64>, MixtureError> {
    Ok(vdd_moe::step::gating_step(
        student,
        states,
        optimizer,
        lr_factor,
        max_grad_norm,
        iteration,
        grad_logits,
        |out, grad| soft_cross_entropy(&out.log_gating, targets, row_weights, grad),
    )?)
}

/// The settings of one phase of an EM / IMC iteration: its expert or its gating steps.
pub(crate) struct PhaseSettings<'a> {
    /// Gradient steps per iteration.
    pub steps_per_iter: usize,
    /// Rows per step; `None` (or at least the dataset size) uses the whole dataset.
    pub batch_size: Option<usize>,
    /// Adam's settings (`lr` is the base learning rate).
    pub optimizer: &'a AdamConfig,
    /// The learning-rate schedule, over the phase's optimiser steps of the run
    /// (`iterations · steps_per_iter`).
    pub schedule: &'a LrSchedule,
}

/// The loop settings EM and IMC share, read from their configs by [`loop_settings!`].
pub(crate) struct LoopSettings<'a> {
    /// Number of iterations.
    pub iterations: usize,
    /// The expert steps.
    pub expert: PhaseSettings<'a>,
    /// The gating steps.
    pub gating: PhaseSettings<'a>,
    /// Clip each network's gradient to this global norm.
    pub max_grad_norm: Option<f32>,
}

/// The [`LoopSettings`] of a reference to a config with the loop fields that
/// [`crate::EmConfig`] and [`crate::ImcConfig`] share by name (the names are serialised in
/// recipes, so the two configs keep them flat rather than nesting a shared struct).
macro_rules! loop_settings {
    ($config:expr) => {{
        let c = $config;
        $crate::fit::LoopSettings {
            iterations: c.iterations,
            expert: $crate::fit::PhaseSettings {
                steps_per_iter: c.expert_steps_per_iter,
                batch_size: c.batch_size,
                optimizer: &c.expert_optimizer,
                schedule: &c.expert_lr_schedule,
            },
            gating: $crate::fit::PhaseSettings {
                steps_per_iter: c.gating_steps_per_iter,
                batch_size: c.gating_batch_size,
                optimizer: &c.gating_optimizer,
                schedule: &c.gating_lr_schedule,
            },
            max_grad_norm: c.max_grad_norm,
        }
    }};
}
pub(crate) use loop_settings;

/// Checks the ranges of the shared loop settings; `frozen_experts` allows
/// `expert_steps_per_iter = 0`.
pub(crate) fn validate_loop(s: &LoopSettings<'_>, frozen_experts: bool) -> Result<(), CoreError> {
    // Frozen experts: any number of expert steps, zero included, is accepted.
    let expert_steps = if frozen_experts { 1 } else { s.expert.steps_per_iter };
    for (name, v) in [
        ("iterations", s.iterations),
        ("expert_steps_per_iter", expert_steps),
        ("batch_size", s.expert.batch_size.unwrap_or(1)),
        ("gating_batch_size", s.gating.batch_size.unwrap_or(1)),
    ] {
        if v == 0 {
            return Err(CoreError::Config(format!("{name} must be positive")));
        }
    }
    let phases = [("expert", &s.expert), ("gating", &s.gating)];
    for (name, phase) in phases {
        let opt = phase.optimizer;
        let ok = [opt.lr, opt.beta1, opt.beta2, opt.eps, opt.weight_decay]
            .iter()
            .all(|x| x.is_finite() && *x >= 0.0);
        if !ok || opt.beta1 >= 1.0 || opt.beta2 >= 1.0 {
            return Err(CoreError::Config(format!("invalid {name} optimiser settings {opt:?}")));
        }
    }
    for (_, phase) in phases {
        phase.schedule.validate().map_err(|e| CoreError::Config(e.to_string()))?;
    }
    if let Some(m) = s.max_grad_norm {
        if !(m.is_finite() && m > 0.0) {
            return Err(CoreError::Config("max_grad_norm must be positive".into()));
        }
    }
    Ok(())
}

/// Minibatch buffers: the drawn row indices and the gathered states and actions.
#[derive(Debug, Clone)]
pub(crate) struct Minibatch {
    /// Row indices into the data.
    pub(crate) idx: Vec<usize>,
    /// The rows' states.
    pub(crate) states: Mat<f32>,
    /// The rows' actions.
    pub(crate) actions: Mat<f32>,
}

impl Default for Minibatch {
    fn default() -> Self {
        Self { idx: Vec::new(), states: Mat::zeros(0, 0), actions: Mat::zeros(0, 0) }
    }
}

impl Minibatch {
    /// Replaces the batch with `size` rows of `data` drawn by `sampler` from `rng` and gathers
    /// their states and actions.
    pub(crate) fn draw(
        &mut self,
        data: &Dataset,
        sampler: &RowSampler,
        rng: &mut Rng,
        size: usize,
    ) {
        sampler.draw(rng, size, &mut self.idx);
        gather_rows(data.states(), &self.idx, &mut self.states);
        gather_rows(data.actions(), &self.idx, &mut self.actions);
    }
}

/// A row of a step's batch, as the callbacks of [`MixtureFit::expert_steps`] and
/// [`MixtureFit::gating_steps`] see it.
#[derive(Debug, Clone, Copy)]
pub(crate) struct BatchRow {
    /// The data row it holds.
    pub o: usize,
    /// The batch is the whole dataset (rows in order), not a drawn minibatch.
    pub full: bool,
    /// Rows in the batch.
    pub len: usize,
}

/// What EM and IMC carry from iteration to iteration: the mixture, the data, both optimisers,
/// the iteration counter, the random streams and the reused buffers of the steps. Each method
/// adds its own E-step (responsibilities; curricula) and says, through the callbacks of
/// [`MixtureFit::expert_steps`] and [`MixtureFit::gating_steps`], how a batch row is weighted.
pub(crate) struct MixtureFit<E: Expert> {
    /// The mixture being trained.
    pub(crate) student: Moe<E>,
    /// The data being fitted.
    pub(crate) data: Dataset,
    /// Iterations done so far.
    pub(crate) iteration: usize,
    expert_optimizer: Adam,
    gating_optimizer: Adam,
    seeds: Seeds,
    uniform: RowSampler,
    batch: Minibatch,
    weights: Vec<f32>,
    row_weights: Vec<f32>,
    grad_logits: Mat<f32>,
    buf: FitBuffers,
    eval: ParallelEval<E>,
    /// Expert steps score the experts as `N(μ_z, I)` ([`weighted_unit_nll_gradients`]).
    pub(crate) unit_variance: bool,
}

impl<E: Expert> MixtureFit<E> {
    /// Checks that `data` fit the mixture's dimensions and sets up the optimisers of
    /// `settings` and the random streams of `seed`.
    pub(crate) fn new(
        settings: &LoopSettings<'_>,
        seed: u64,
        student: Moe<E>,
        data: Dataset,
    ) -> Result<Self, MixtureError> {
        let mc = student.config();
        data.check_dims(mc.state_dim, mc.action_dim)?;
        Ok(Self {
            expert_optimizer: Adam::new(*settings.expert.optimizer),
            gating_optimizer: Adam::new(*settings.gating.optimizer),
            iteration: 0,
            seeds: Seeds::new(seed),
            uniform: RowSampler::uniform(data.len())?,
            batch: Minibatch::default(),
            weights: Vec::new(),
            row_weights: Vec::new(),
            grad_logits: Mat::zeros(0, 0),
            buf: FitBuffers::default(),
            eval: ParallelEval::new(Workers::default()),
            unit_variance: false,
            student,
            data,
        })
    }

    /// [`evaluate_dataset`] of the mixture on the data, on the process-wide pool's threads
    /// (the same bits as in one thread).
    pub(crate) fn evaluate(
        &mut self,
        expert_log_lik: Option<&mut [f32]>,
        responsibilities: Option<&mut [f32]>,
    ) -> Result<f64, MixtureError> {
        let (ll, resp) = (expert_log_lik, responsibilities);
        self.eval.evaluate(Scoring::Gaussian, &mut self.student, &self.data, ll, resp)
    }

    /// The authors' IMC's E-step: `ℓ_z(o) = −½‖a_o − μ_z(s_o)‖²` of every pair into `out_ll`
    /// (`N·Z`); returns the mixture's mean log-likelihood with experts `N(μ_z, I)`.
    pub(crate) fn evaluate_unit(&mut self, out_ll: &mut [f32]) -> Result<f64, MixtureError> {
        let scoring = Scoring::UnitVariance;
        self.eval.evaluate(scoring, &mut self.student, &self.data, Some(out_ll), None)
    }

    /// `k` distinct rows of the data, drawn from stream `stream` of the current iteration,
    /// in increasing order (a subsampled E-step's or curriculum update's rows).
    pub(crate) fn draw_rows(&self, stream: &str, k: usize) -> Vec<usize> {
        let mut rng = self.seeds.stream_indexed(stream, self.iteration as u64);
        let mut rows = rand::seq::index::sample(&mut rng, self.data.len(), k).into_vec();
        rows.sort_unstable();
        rows
    }

    /// The pairs `rows` of the data, as a dataset of their own.
    pub(crate) fn rows_of(&self, rows: &[usize]) -> Result<Dataset, MixtureError> {
        let (mut states, mut actions) = (Mat::zeros(0, 0), Mat::zeros(0, 0));
        gather_rows(self.data.states(), rows, &mut states);
        gather_rows(self.data.actions(), rows, &mut actions);
        Ok(Dataset::new(states, actions)?)
    }

    /// As [`MixtureFit::evaluate_unit`] on other data (a subset of the rows).
    pub(crate) fn evaluate_unit_on(
        &mut self,
        data: &Dataset,
        out_ll: &mut [f32],
    ) -> Result<f64, MixtureError> {
        self.eval.evaluate(Scoring::UnitVariance, &mut self.student, data, Some(out_ll), None)
    }

    /// As [`MixtureFit::evaluate`] on other data (a subset of the rows).
    pub(crate) fn evaluate_on(
        &mut self,
        data: &Dataset,
        responsibilities: &mut [f32],
    ) -> Result<f64, MixtureError> {
        self.eval.evaluate(Scoring::Gaussian, &mut self.student, data, None, Some(responsibilities))
    }

    /// The expert steps of the current iteration: `steps_per_iter` [`expert_step`]s, each on a
    /// minibatch drawn by `sampler` (uniformly when `None`) from the `"expert-batch"` stream of
    /// the step, or on the whole dataset; `weights(row, w)` writes the `Z` weights of a batch
    /// row into `w`. Returns the loss and the learning rate of the last step.
    pub(crate) fn expert_steps(
        &mut self,
        settings: &LoopSettings<'_>,
        sampler: Option<&RowSampler>,
        mut weights: impl FnMut(BatchRow, &mut [f32]),
    ) -> Result<(f64, f32), MixtureError> {
        let (phase, z_n) = (&settings.expert, self.student.num_experts());
        let (mut loss, mut lr) = (0.0, 0.0);
        for k in 0..phase.steps_per_iter {
            let full = self.draw(phase, k, "expert-batch", sampler);
            let len = self.batch.idx.len();
            self.weights.resize(len * z_n, 0.0);
            for (b, &o) in self.batch.idx.iter().enumerate() {
                weights(BatchRow { o, full, len }, &mut self.weights[b * z_n..(b + 1) * z_n]);
            }
            let total = (settings.iterations * phase.steps_per_iter) as u64;
            let factor = phase.schedule.factor(self.expert_optimizer.steps(), total);
            lr = phase.optimizer.lr * factor;
            let (states, actions) = rows(&self.batch, &self.data, full);
            let step = StepArgs {
                lr_factor: factor,
                max_grad_norm: settings.max_grad_norm,
                iteration: self.iteration,
                unit_variance: self.unit_variance,
            };
            loss = expert_step_with(
                &mut self.student,
                states,
                actions,
                &self.weights,
                &mut self.expert_optimizer,
                step,
                &mut self.buf,
            )?;
        }
        Ok((loss, lr))
    }

    /// The gating steps of the current iteration: `steps_per_iter` [`gating_step`]s, batches
    /// drawn as by [`MixtureFit::expert_steps`] from the `"gating-batch"` stream;
    /// `targets(row, t)` writes the `Z` soft targets of a batch row into `t` and returns the
    /// row's weight. Returns the loss and the learning rate of the last step.
    pub(crate) fn gating_steps(
        &mut self,
        settings: &LoopSettings<'_>,
        sampler: Option<&RowSampler>,
        mut targets: impl FnMut(BatchRow, &mut [f32]) -> f32,
    ) -> Result<(Option<f64>, f32), MixtureError> {
        let (phase, z_n) = (&settings.gating, self.student.num_experts());
        let (mut loss, mut lr) = (None, 0.0);
        for k in 0..phase.steps_per_iter {
            let full = self.draw(phase, k, "gating-batch", sampler);
            let len = self.batch.idx.len();
            self.weights.resize(len * z_n, 0.0);
            self.row_weights.resize(len, 0.0);
            for (b, &o) in self.batch.idx.iter().enumerate() {
                let t = &mut self.weights[b * z_n..(b + 1) * z_n];
                self.row_weights[b] = targets(BatchRow { o, full, len }, t);
            }
            let total = (settings.iterations * phase.steps_per_iter) as u64;
            let factor = phase.schedule.factor(self.gating_optimizer.steps(), total);
            lr = phase.optimizer.lr * factor;
            loss = gating_step(
                &mut self.student,
                rows(&self.batch, &self.data, full).0,
                &self.weights,
                &self.row_weights,
                &mut self.gating_optimizer,
                factor,
                settings.max_grad_norm,
                self.iteration,
                &mut self.grad_logits,
            )?;
        }
        Ok((loss, lr))
    }

    /// Fills the batch for step `k` of `phase` in the current iteration: a minibatch drawn by
    /// `sampler` (uniform when `None`) from the `purpose` stream indexed by the step, or the
    /// whole dataset (`idx = 0..N`, nothing gathered), in which case it returns `true`.
    fn draw(
        &mut self,
        phase: &PhaseSettings<'_>,
        k: usize,
        purpose: &str,
        sampler: Option<&RowSampler>,
    ) -> bool {
        let n = self.data.len();
        match phase.batch_size {
            Some(b) if b < n => {
                let stream = (self.iteration * phase.steps_per_iter + k) as u64;
                let mut rng = self.seeds.stream_indexed(purpose, stream);
                self.batch.draw(&self.data, sampler.unwrap_or(&self.uniform), &mut rng, b);
                false
            }
            _ => {
                self.batch.idx.clear();
                self.batch.idx.extend(0..n);
                true
            }
        }
    }
}

/// The states and actions of a step's batch: the whole dataset's when `full`, else the
/// gathered minibatch's.
fn rows<'a>(
    batch: &'a Minibatch,
    data: &'a Dataset,
    full: bool,
) -> (MatRef<'a, f32>, MatRef<'a, f32>) {
    if full {
        (data.states(), data.actions())
    } else {
        (batch.states.as_ref(), batch.actions.as_ref())
    }
}

#[cfg(test)]
mod tests;
