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
//! [`soft_cross_entropy`] is `−Σ_b c_b Σ_z t_{bz} log q(z|s_b)` for per-row weights `c_b` and
//! targets `t_b` (responsibilities or curriculum posteriors); its gradient with respect to the
//! gating logits is `c_b (q(z|s_b) Σ_k t_{bk} − t_{bz})`.

use faer::{Mat, MatMut, MatRef};
use rand::Rng as _;
use vdd_core::gaussian::{self, solve_lower_in_place, solve_upper_t_in_place};
use vdd_core::{CoreError, Expert, Rng, Seeds, check_finite_slice, check_len, check_shape};
use vdd_moe::{Moe, MoeOutput};
use vdd_nn::{Adam, AdamConfig, LrSchedule, Parameters};

use crate::dataset::Dataset;
use crate::error::BaselineError;

/// Rows per forward pass when a whole dataset is evaluated.
pub const EVAL_CHUNK: usize = 2048;

/// `−log N(a; μ, L Lᵀ)` and its gradients: `d_mean = ∂/∂μ` (`d`) and `d_scale_tril = ∂/∂L`
/// (`d·d`, row-major, zero above the diagonal). `work` is scratch of length `d`.
///
/// ```
/// use vdd_baselines::fit::gaussian_nll_and_grad;
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

/// Soft cross-entropy `−Σ_b c_b Σ_z t_{bz} log q(z|s_b)` of the gating towards `targets`, and
/// its gradient with respect to the gating logits, `c_b (q(z|s_b) Σ_k t_{bk} − t_{bz})`,
/// written into `grad_logits` (`n x Z`).
///
/// `log_gating` and `targets` are `n·Z` row-major, `row_weights` (`c_b`) has length `n`.
///
/// ```
/// use vdd_baselines::fit::soft_cross_entropy;
/// let log_q = [0.5f32.ln(), 0.5f32.ln()];
/// let mut g = faer::Mat::<f32>::zeros(1, 2);
/// let loss = soft_cross_entropy(&log_q, &[1.0, 0.0], &[1.0], g.as_mut()).unwrap();
/// assert!((loss - 2.0f64.ln()).abs() < 1e-6);
/// assert!((g[(0, 0)] + 0.5).abs() < 1e-6 && (g[(0, 1)] - 0.5).abs() < 1e-6);
/// ```
pub fn soft_cross_entropy(
    log_gating: &[f32],
    targets: &[f32],
    row_weights: &[f32],
    mut grad_logits: MatMut<'_, f32>,
) -> Result<f64, CoreError> {
    let (n, z_n) = (row_weights.len(), grad_logits.ncols());
    check_shape("gating gradient", grad_logits.as_ref(), n, z_n)?;
    check_len("log gating", log_gating.len(), n * z_n)?;
    check_len("gating targets", targets.len(), n * z_n)?;
    check_finite_slice("gating targets", targets)?;
    check_finite_slice("gating row weights", row_weights)?;
    let mut loss = 0.0f64;
    for b in 0..n {
        let c = row_weights[b];
        let t = &targets[b * z_n..(b + 1) * z_n];
        let lg = &log_gating[b * z_n..(b + 1) * z_n];
        let t_sum: f32 = t.iter().sum();
        for k in 0..z_n {
            if t[k] != 0.0 {
                loss -= f64::from(c * t[k]) * f64::from(lg[k]);
            }
            grad_logits[(b, k)] = c * (lg[k].exp() * t_sum - t[k]);
        }
    }
    Ok(loss)
}

/// Evaluates the mixture on every pair of `data` (in chunks of [`EVAL_CHUNK`] rows) and returns
/// the mean log-likelihood `(1/n) Σ_o log q(a_o|s_o)`.
///
/// Optionally writes the experts' log-likelihoods `log N(a_o; μ_z(s_o), Σ_z(s_o))` into
/// `expert_log_lik` and the responsibilities `q(z|a_o, s_o)` into `responsibilities` (both
/// `n·Z`, row-major).
pub fn evaluate_dataset<E: Expert>(
    student: &mut Moe<E>,
    data: &Dataset,
    mut expert_log_lik: Option<&mut [f32]>,
    mut responsibilities: Option<&mut [f32]>,
) -> Result<f64, BaselineError> {
    let (n, z_n, d) = (data.len(), student.num_experts(), student.config().action_dim);
    data.check_dims(student.config().state_dim, d)?;
    if let Some(e) = expert_log_lik.as_deref() {
        check_len("expert log-likelihood output", e.len(), n * z_n)?;
    }
    if let Some(r) = responsibilities.as_deref() {
        check_len("responsibilities output", r.len(), n * z_n)?;
    }
    let (mut a, mut work, mut row) = (vec![0.0f32; d], vec![0.0f32; d], vec![0.0f32; z_n]);
    let actions = data.actions();
    let mut sum = 0.0f64;
    let mut start = 0;
    while start < n {
        let len = EVAL_CHUNK.min(n - start);
        student.forward(data.states().subrows(start, len))?;
        let out = student.output();
        for b in 0..len {
            let o = start + b;
            for j in 0..d {
                a[j] = actions[(o, j)];
            }
            let lg = out.log_gating_row(b);
            for k in 0..z_n {
                let ll = gaussian::log_density(&a, out.mean(b, k), out.scale(b, k), &mut work);
                if let Some(e) = expert_log_lik.as_deref_mut() {
                    e[o * z_n + k] = ll;
                }
                row[k] = lg[k] + ll;
            }
            sum += f64::from(gaussian::softmax_in_place(&mut row));
            if let Some(r) = responsibilities.as_deref_mut() {
                r[o * z_n..(o + 1) * z_n].copy_from_slice(&row);
            }
        }
        start += len;
    }
    Ok(sum / n as f64)
}

/// Draws dataset row indices for minibatches: uniformly, or in proportion to weights.
///
/// ```
/// use vdd_baselines::fit::RowSampler;
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

/// Global gradient norm of `params`: an error when it is NaN or infinite, clipped to
/// `max_norm` when one is given.
pub fn clip_or_fail(
    params: &mut dyn Parameters,
    max_norm: Option<f32>,
    iteration: usize,
    quantity: &'static str,
) -> Result<(), BaselineError> {
    let mut sq = 0.0f64;
    params.visit_params("", &mut |_, p| {
        sq += p.grad.iter().map(|g| f64::from(*g) * f64::from(*g)).sum::<f64>();
    });
    if !sq.is_finite() {
        return Err(BaselineError::NonFinite { iteration, quantity });
    }
    if let Some(max) = max_norm {
        vdd_nn::clip_grad_norm(params, max);
    }
    Ok(())
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
) -> Result<f64, BaselineError> {
    student.forward_experts(states)?;
    let loss = weighted_nll_gradients(student.expert(), student.output(), actions, weights, buf)?;
    if !loss.is_finite() {
        return Err(BaselineError::NonFinite { iteration, quantity: "expert loss" });
    }
    student.expert_networks_mut().zero_grad();
    let grad_raw = std::mem::take(&mut buf.grad_raw);
    let r = student.backward_experts(&grad_raw);
    buf.grad_raw = grad_raw;
    r?;
    let nets = student.expert_networks_mut();
    clip_or_fail(nets, max_grad_norm, iteration, "expert gradient")?;
    optimizer.step(nets, lr_factor);
    Ok(loss)
}

/// One optimiser step of the gating on the soft cross-entropy towards `targets` (`n·Z`) with
/// per-row weights `row_weights` (`n`). Returns the loss before the step, or `None` (and does
/// nothing) when the mixture's gating is not learned. `grad_logits` is a reusable buffer.
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
) -> Result<Option<f64>, BaselineError> {
    if !student.has_learned_gating() {
        return Ok(None);
    }
    let (n, z_n) = (states.nrows(), student.num_experts());
    if grad_logits.nrows() != n || grad_logits.ncols() != z_n {
        *grad_logits = Mat::zeros(n, z_n);
    }
    // Both passes, so that the output's batch size is the one `backward_gating` checks against.
    student.forward(states)?;
    let loss = soft_cross_entropy(
        &student.output().log_gating,
        targets,
        row_weights,
        grad_logits.as_mut(),
    )?;
    if !loss.is_finite() {
        return Err(BaselineError::NonFinite { iteration, quantity: "gating loss" });
    }
    if let Some(net) = student.gating_network_mut() {
        net.zero_grad();
    }
    student.backward_gating(grad_logits.as_ref())?;
    let net = student.gating_network_mut().expect("learned gating has a network");
    clip_or_fail(net, max_grad_norm, iteration, "gating gradient")?;
    optimizer.step(net, lr_factor);
    Ok(Some(loss))
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

/// Checks the ranges of the shared loop settings.
pub(crate) fn validate_loop(s: &LoopSettings<'_>) -> Result<(), CoreError> {
    for (name, v) in [
        ("iterations", s.iterations),
        ("expert_steps_per_iter", s.expert.steps_per_iter),
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
}

impl<E: Expert> MixtureFit<E> {
    /// Checks that `data` fit the mixture's dimensions and sets up the optimisers of
    /// `settings` and the random streams of `seed`.
    pub(crate) fn new(
        settings: &LoopSettings<'_>,
        seed: u64,
        student: Moe<E>,
        data: Dataset,
    ) -> Result<Self, BaselineError> {
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
            student,
            data,
        })
    }

    /// [`evaluate_dataset`] of the mixture on the data.
    pub(crate) fn evaluate(
        &mut self,
        expert_log_lik: Option<&mut [f32]>,
        responsibilities: Option<&mut [f32]>,
    ) -> Result<f64, BaselineError> {
        evaluate_dataset(&mut self.student, &self.data, expert_log_lik, responsibilities)
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
    ) -> Result<(f64, f32), BaselineError> {
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
            loss = expert_step(
                &mut self.student,
                states,
                actions,
                &self.weights,
                &mut self.expert_optimizer,
                factor,
                settings.max_grad_norm,
                self.iteration,
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
    ) -> Result<(Option<f64>, f32), BaselineError> {
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
mod tests {
    use super::*;
    use approx::assert_relative_eq;
    use vdd_core::Seeds;
    use vdd_moe::{DiagonalExpert, ExpertKind, FullExpert, GatingKind, MoeConfig};

    /// An output for `n` rows and `Z` experts decoded from given raw rows.
    fn output<E: Expert>(expert: &E, raw: &[f32], n: usize, z_n: usize) -> MoeOutput {
        let (d, r) = (expert.action_dim(), expert.raw_dim());
        let mut out = MoeOutput {
            n,
            num_experts: z_n,
            action_dim: d,
            raw: raw.to_vec(),
            means: vec![0.0; n * z_n * d],
            scales: vec![0.0; n * z_n * d * d],
            log_gating: vec![-(z_n as f32).ln(); n * z_n],
        };
        for k in 0..n * z_n {
            expert.decode(
                &raw[k * r..(k + 1) * r],
                &mut out.means[k * d..(k + 1) * d],
                &mut out.scales[k * d * d..(k + 1) * d * d],
            );
        }
        out
    }

    fn weighted_nll(
        expert: &impl Expert,
        raw: &[f32],
        n: usize,
        z_n: usize,
        a: &Mat<f32>,
        w: &[f32],
    ) -> f64 {
        let out = output(expert, raw, n, z_n);
        let d = expert.action_dim();
        let mut work = vec![0.0; d];
        let mut s = 0.0f64;
        for b in 0..n {
            let row: Vec<f32> = (0..d).map(|j| a[(b, j)]).collect();
            for k in 0..z_n {
                let lp = gaussian::log_density(&row, out.mean(b, k), out.scale(b, k), &mut work);
                s -= f64::from(w[b * z_n + k]) * f64::from(lp);
            }
        }
        s
    }

    fn check_raw_gradient<E: Expert>(expert: E) {
        let (n, z_n, d, r) = (3, 2, expert.action_dim(), expert.raw_dim());
        let raw: Vec<f32> =
            (0..n * z_n * r).map(|i| ((i * 37 % 13) as f32 / 13.0 - 0.5) * 0.8).collect();
        let a = Mat::from_fn(n, d, |i, j| ((i * 3 + j * 5) % 7) as f32 * 0.4 - 1.1);
        let w = [0.7f32, 0.3, 0.0, 1.0, 0.25, 0.5];
        let out = output(&expert, &raw, n, z_n);
        let mut buf = FitBuffers::default();
        let loss = weighted_nll_gradients(&expert, &out, a.as_ref(), &w, &mut buf).unwrap();
        assert_relative_eq!(loss, weighted_nll(&expert, &raw, n, z_n, &a, &w), epsilon = 1e-4);
        for i in 0..raw.len() {
            let h = 1e-3f32;
            let mut p = raw.clone();
            p[i] += h;
            let mut m = raw.clone();
            m[i] -= h;
            let fd = (weighted_nll(&expert, &p, n, z_n, &a, &w)
                - weighted_nll(&expert, &m, n, z_n, &a, &w))
                / (2.0 * f64::from(h));
            assert_relative_eq!(
                f64::from(buf.grad_raw[i]),
                fd,
                epsilon = 3e-3,
                max_relative = 3e-3
            );
        }
    }

    #[test]
    fn weighted_nll_gradient_matches_finite_differences_diagonal() {
        check_raw_gradient(DiagonalExpert::new(3, 0.8, 1e-3).unwrap());
    }

    #[test]
    fn weighted_nll_gradient_matches_finite_differences_full() {
        check_raw_gradient(FullExpert::new(3, 0.8, 1e-3).unwrap());
    }

    /// The same loss through the networks: parameter gradients from `backward_experts` against
    /// central differences of the parameters.
    fn check_network_gradient(kind: ExpertKind, shared_trunk: bool) {
        let mut mc = MoeConfig::toy(2, 2, 2);
        mc.expert_kind = kind;
        mc.shared_trunk = shared_trunk;
        mc.experts_network.hidden_dim = 8;
        mc.init_std = 0.7;
        let mut moe = Moe::from_config(mc, 4).unwrap();
        let n = 5;
        let states = Mat::from_fn(n, 2, |i, j| (i as f32 - 2.0) * 0.3 + j as f32 * 0.2);
        let actions = Mat::from_fn(n, 2, |i, j| ((i * 2 + j) % 5) as f32 * 0.3 - 0.6);
        let w: Vec<f32> = (0..n * 2).map(|i| 0.1 + (i % 3) as f32 * 0.2).collect();
        let mut buf = FitBuffers::default();
        let loss_at = |moe: &mut Moe, buf: &mut FitBuffers| {
            moe.forward_experts(states.as_ref()).unwrap();
            weighted_nll_gradients(moe.expert(), moe.output(), actions.as_ref(), &w, buf).unwrap()
        };
        loss_at(&mut moe, &mut buf);
        moe.expert_networks_mut().zero_grad();
        let g = buf.grad_raw.clone();
        moe.backward_experts(&g).unwrap();
        let mut analytic = Vec::new();
        moe.expert_networks_mut().visit_params("", &mut |_, p| analytic.push(p.grad.clone()));
        let mut worst = 0.0f64;
        for (pi, grads) in analytic.iter().enumerate() {
            for e in (0..grads.len()).step_by(3) {
                let h = 2e-3f32;
                let mut value = 0.0;
                set(&mut moe, pi, e, |v| {
                    value = *v;
                    *v += h;
                });
                let lp = loss_at(&mut moe, &mut buf);
                set(&mut moe, pi, e, |v| *v = value - h);
                let lm = loss_at(&mut moe, &mut buf);
                set(&mut moe, pi, e, |v| *v = value);
                let fd = (lp - lm) / (2.0 * f64::from(h));
                let err = (f64::from(grads[e]) - fd).abs() / fd.abs().max(1e-2);
                worst = worst.max(err);
            }
        }
        assert!(worst < 2e-2, "{kind:?} shared={shared_trunk}: worst relative error {worst}");
    }

    fn set(moe: &mut Moe, index: usize, entry: usize, f: impl FnOnce(&mut f32)) {
        let mut k = 0;
        let mut f = Some(f);
        moe.expert_networks_mut().visit_params_mut("", &mut |_, p| {
            if k == index {
                (f.take().expect("visited once"))(&mut p.value[entry]);
            }
            k += 1;
        });
    }

    #[test]
    fn network_gradients_of_the_weighted_nll_match_finite_differences() {
        check_network_gradient(ExpertKind::Diagonal, true);
        check_network_gradient(ExpertKind::Full, false);
    }

    #[test]
    fn soft_cross_entropy_gradient_matches_finite_differences() {
        let (n, z_n) = (3, 4);
        let logits: Vec<f32> = (0..n * z_n).map(|i| ((i * 7 % 5) as f32 - 2.0) * 0.6).collect();
        let log_softmax = |l: &[f32]| {
            let mut out = l.to_vec();
            for b in 0..n {
                let row = &mut out[b * z_n..(b + 1) * z_n];
                let lse = gaussian::log_sum_exp(row);
                row.iter_mut().for_each(|x| *x -= lse);
            }
            out
        };
        // Targets need not be normalised (row 2 sums to 0.5).
        let t = [0.1f32, 0.2, 0.3, 0.4, 1.0, 0.0, 0.0, 0.0, 0.25, 0.0, 0.25, 0.0];
        let c = [0.5f32, 0.2, 0.3];
        let mut g = Mat::zeros(n, z_n);
        soft_cross_entropy(&log_softmax(&logits), &t, &c, g.as_mut()).unwrap();
        let mut scratch = Mat::zeros(n, z_n);
        for i in 0..n * z_n {
            let h = 1e-2f32;
            let mut p = logits.clone();
            p[i] += h;
            let mut m = logits.clone();
            m[i] -= h;
            let lp = soft_cross_entropy(&log_softmax(&p), &t, &c, scratch.as_mut()).unwrap();
            let lm = soft_cross_entropy(&log_softmax(&m), &t, &c, scratch.as_mut()).unwrap();
            let fd = (lp - lm) / (2.0 * f64::from(h));
            assert_relative_eq!(f64::from(g[(i / z_n, i % z_n)]), fd, epsilon = 1e-4);
        }
    }

    #[test]
    fn weighted_sampler_follows_its_weights() {
        let w = [1.0, 0.0, 3.0, 6.0];
        let s = RowSampler::weighted(&w).unwrap();
        let mut idx = Vec::new();
        s.draw(&mut Seeds::new(1).stream("t"), 20_000, &mut idx);
        let mut counts = [0usize; 4];
        idx.iter().for_each(|&i| counts[i] += 1);
        assert_eq!(counts[1], 0);
        for (c, w) in counts.iter().zip(w) {
            assert!((*c as f64 / 20_000.0 - w / 10.0).abs() < 0.01, "{counts:?}");
        }
        assert!(RowSampler::weighted(&[0.0, 0.0]).is_err());
        assert!(RowSampler::weighted(&[1.0, -1.0]).is_err());
        assert!(RowSampler::uniform(0).is_err());
    }

    #[test]
    fn dataset_evaluation_matches_the_policy_likelihood() {
        use vdd_core::Policy;
        let mut mc = MoeConfig::toy(1, 2, 3);
        mc.gating = GatingKind::Learned;
        mc.experts_network.hidden_dim = 8;
        mc.gating_network.hidden_dim = 8;
        let mut moe = Moe::from_config(mc, 2).unwrap();
        let n = EVAL_CHUNK + 5; // two chunks
        let states = Mat::from_fn(n, 1, |i, _| (i % 17) as f32 * 0.1);
        let actions = Mat::from_fn(n, 2, |i, j| ((i * 3 + j) % 11) as f32 * 0.2 - 1.0);
        let data = Dataset::new(states.clone(), actions.clone()).unwrap();
        let mut resp = vec![0.0; n * 3];
        let mut ell = vec![0.0; n * 3];
        let mean = evaluate_dataset(&mut moe, &data, Some(&mut ell), Some(&mut resp)).unwrap();
        let mut ll = vec![0.0; n];
        moe.log_likelihood(states.as_ref(), actions.as_ref(), &mut ll).unwrap();
        let expect = ll.iter().map(|&x| f64::from(x)).sum::<f64>() / n as f64;
        assert_relative_eq!(mean, expect, epsilon = 1e-4);
        for o in [0, n - 1] {
            assert_relative_eq!(resp[o * 3..o * 3 + 3].iter().sum::<f32>(), 1.0, epsilon = 1e-5);
            // log q = logsumexp_z (log q(z|s) + log N_z): rebuild it from the experts' values.
            moe.forward(states.as_ref().subrows(o, 1)).unwrap();
            let lg = moe.output().log_gating_row(0).to_vec();
            let joint: Vec<f32> = (0..3).map(|z| lg[z] + ell[o * 3 + z]).collect();
            assert_relative_eq!(gaussian::log_sum_exp(&joint), ll[o], epsilon = 1e-4);
        }
    }
}
