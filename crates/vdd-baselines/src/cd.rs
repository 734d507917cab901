//! **Consistency Distillation** (CD; Song, Dhariwal, Chen & Sutskever, "Consistency Models",
//! ICML 2023) of a variance-exploding (BESO / EDM) teacher.
//!
//! The student is a consistency function `f_θ(x, σ, s)` that maps any point of a teacher
//! probability-flow ODE trajectory at level `σ` to the trajectory's end at `σ_min`:
//!
//! `f_θ(x, σ, s) = c_skip(σ) x + c_out(σ) F_θ(c_in(σ) x, s, c_noise(σ))`
//!
//! with the boundary preconditioning of [`BoundaryPreconditioning`] (`c_skip(σ_min) = 1`,
//! `c_out(σ_min) = 0`, so `f_θ(x, σ_min, s) = x` exactly).
//!
//! **Training** (Song et al., Algorithm 2). On the Karras grid `σ_max = σ_0 > … > σ_{N−1} =
//! σ_min` ([`CdConfig::num_scales`] `= N`), per minibatch row: draw a data pair `(s, a)`, an
//! index `n` uniform in `0..N−1` and `z ~ N(0, I)`; `x = a + σ_n z`; one Heun step of the
//! teacher's probability-flow ODE from `σ_n` to `σ_{n+1}` gives `x̂`; the loss is
//!
//! `L(θ) = 1/(B d) Σ_rows ‖ f_θ(x, σ_n, s) − f_{θ⁻}(x̂, σ_{n+1}, s) ‖²`
//!
//! (squared L2 — the paper's `d` for low-dimensional actions — and uniform weighting
//! `λ(σ) = 1`). The target parameters `θ⁻` are an exponential moving average of `θ`
//! ([`ConsistencyTrainConfig::target_ema_decay`], `θ⁻ ← μ θ⁻ + (1 − μ) θ` after every Adam
//! step); the gradient flows only through the online network (explicit backward of
//! `F_θ`, scaled by `c_out(σ_n)`). The student starts from the teacher's weights when
//! [`CdConfig::init_from_teacher`] is set (the paper's choice; the architectures must match),
//! otherwise from a fresh network.
//!
//! **Sampling** (Song et al., Algorithm 1). One step: `a = f(σ_max ε, σ_max, s)`. `k` steps:
//! then for each intermediate level `τ` (the inner points of a `(k+1)`-level Karras grid),
//! `x = a + sqrt(τ² − σ_min²) z`, `a = f(x, τ, s)`.

use std::time::Instant;

use faer::reborrow::{Reborrow, ReborrowMut};
use faer::{Mat, MatMut, MatRef};
use rand::{Rng as _, RngCore};
use serde::{Deserialize, Serialize};
use vdd_core::{Affine, CoreError, Policy, Seeds, check_act_args};
use vdd_diffusion::{BesoConfig, NetConfig, SamplerBuffers};
use vdd_nn::Parameters;

use crate::consistency::{
    self, BoundaryPreconditioning, Coefficients, ConditionedNet, ConsistencyProgress,
    ConsistencyTeacher, ConsistencyTrainConfig, LossMeter, Minibatch, Optimisation, PolicyIo,
    check_model_batch, check_policy_batch, ensure, fill_normal,
};
use crate::dataset::Dataset;
use crate::error::BaselineError;
use crate::fit::RowSampler;

const POLICY_STREAM: &str = "cd-policy";

/// Configuration of [`CdTrainer`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CdConfig {
    /// The student network `F_θ` (the teacher's architecture to start from its weights).
    pub net: NetConfig,
    /// Start the student from the teacher's network (it must have one of the same
    /// architecture); otherwise from fresh weights of the seed's `"init"` stream.
    pub init_from_teacher: bool,
    /// `σ_data` of the preconditioning (normalised action space).
    pub sigma_data: f32,
    /// The boundary level `σ_min` (`f(x, σ_min) = x`), the end of the grid.
    pub sigma_min: f32,
    /// The largest level `σ_max`, where sampling starts.
    pub sigma_max: f32,
    /// The Karras grid's `ρ`.
    pub rho: f32,
    /// Number of grid levels `N` (Song et al. use 18 for their EDM teacher).
    pub num_scales: usize,
    /// Sampling steps of the returned policy (1: one-step consistency sampling).
    pub sampling_steps: usize,
    /// Optimisation.
    pub train: ConsistencyTrainConfig,
}

impl Default for CdConfig {
    /// BESO's default levels (`σ_data = 0.5`, `σ ∈ [0.002, 80]`, `ρ = 7`), `N = 18`, a fresh
    /// student of the default [`NetConfig`], one-step sampling.
    fn default() -> Self {
        Self {
            net: NetConfig::default(),
            init_from_teacher: false,
            sigma_data: 0.5,
            sigma_min: 0.002,
            sigma_max: 80.0,
            rho: 7.0,
            num_scales: 18,
            sampling_steps: 1,
            train: ConsistencyTrainConfig::default(),
        }
    }
}

impl CdConfig {
    /// The configuration for distilling a BESO teacher built with `beso`: its network
    /// architecture (started from its weights), `σ_data`, `σ_min`, `σ_max` and `ρ`.
    pub fn for_beso(beso: &BesoConfig) -> Self {
        Self {
            net: beso.net.clone(),
            init_from_teacher: true,
            sigma_data: beso.sigma_data,
            sigma_min: beso.sigma_min,
            sigma_max: beso.sigma_max,
            rho: beso.rho,
            ..Self::default()
        }
    }

    /// Checks the numbers.
    pub fn validate(&self) -> Result<(), CoreError> {
        self.net.validate().map_err(CoreError::from)?;
        consistency::validate_levels(
            self.sigma_data,
            self.sigma_min,
            self.sigma_max,
            self.rho,
            self.num_scales,
        )?;
        if self.sampling_steps == 0 {
            return Err(CoreError::Config("sampling_steps must be >= 1".into()));
        }
        self.train.validate()
    }
}

/// Fills `coef` for the consistency function at levels `sigma`.
fn boundary_coefficients(coef: &mut Coefficients, pre: &BoundaryPreconditioning, sigma: &[f32]) {
    coef.clear();
    for &s in sigma {
        coef.c_in.push(pre.c_in(s));
        coef.noise.push(pre.c_noise(s));
        coef.skip.push(pre.c_skip(s));
        coef.out.push(pre.c_out(s));
    }
}

/// Reused buffers of one CD step.
#[derive(Debug, Clone)]
struct CdBuffers {
    batch: Minibatch,
    sigma_hi: Vec<f32>,
    sigma_lo: Vec<f32>,
    noise: Mat<f32>,
    x_hi: Mat<f32>,
    x_lo: Mat<f32>,
    target_out: Mat<f32>,
    online_out: Mat<f32>,
    grad: Mat<f32>,
    coef: Coefficients,
    heun: SamplerBuffers,
}

impl Default for CdBuffers {
    fn default() -> Self {
        let z = || Mat::zeros(0, 0);
        Self {
            batch: Minibatch::default(),
            sigma_hi: Vec::new(),
            sigma_lo: Vec::new(),
            noise: z(),
            x_hi: z(),
            x_lo: z(),
            target_out: z(),
            online_out: z(),
            grad: z(),
            coef: Coefficients::default(),
            heun: SamplerBuffers::default(),
        }
    }
}

/// Consistency Distillation of a [`ConsistencyTeacher`] (see the [module docs](self)).
///
/// ```
/// use faer::{Mat, MatMut, MatRef};
/// use vdd_baselines::cd::{CdConfig, CdTrainer};
/// use vdd_baselines::consistency::DenoiserFn;
/// use vdd_core::{Affine, CoreError, Policy};
/// use vdd_diffusion::NetConfig;
///
/// // Teacher: the exact denoiser of N(0, 0.5²) actions, D(x; σ) = 0.25 / (0.25 + σ²) x.
/// let teacher = DenoiserFn::new(
///     Affine::identity(1),
///     Affine::identity(1),
///     |x: MatRef<'_, f32>, s: &[f32], _: MatRef<'_, f32>, mut out: MatMut<'_, f32>| {
///         for i in 0..x.nrows() {
///             out[(i, 0)] = 0.25 / (0.25 + s[i] * s[i]) * x[(i, 0)];
///         }
///         Ok::<(), CoreError>(())
///     },
/// );
/// let states = Mat::<f32>::zeros(64, 1);
/// let actions = Mat::from_fn(64, 1, |i, _| 0.5 * ((i as f32) / 32.0 - 1.0));
/// let mut config = CdConfig::default();
/// config.net = NetConfig { hidden_dim: 16, num_blocks: 1, ..Default::default() };
/// config.train.steps = 20;
/// config.train.batch_size = 16;
/// let mut trainer = CdTrainer::new(config, teacher, states.as_ref(), actions.as_ref()).unwrap();
/// let mut policy = trainer.train(&mut |_| {}).unwrap();
/// assert!(policy.act(&[0.0]).unwrap()[0].is_finite());
/// ```
pub struct CdTrainer<T: ConsistencyTeacher> {
    config: CdConfig,
    teacher: T,
    data: Dataset,
    sampler: RowSampler,
    pre: BoundaryPreconditioning,
    grid: Vec<f32>,
    online: ConditionedNet,
    target: ConditionedNet,
    opt: Optimisation,
    batch_rng: vdd_core::Rng,
    noise_rng: vdd_core::Rng,
    steps_done: u64,
    buf: CdBuffers,
}

impl<T: ConsistencyTeacher> std::fmt::Debug for CdTrainer<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CdTrainer")
            .field("config", &self.config)
            .field("steps_done", &self.steps_done)
            .field("data_len", &self.data.len())
            .finish_non_exhaustive()
    }
}

impl<T: ConsistencyTeacher> CdTrainer<T> {
    /// Sets up distillation of `teacher` on raw `states` (`n x d_s`) and `actions`
    /// (`n x d_a`), which are normalised with the teacher's normalisers.
    pub fn new(
        config: CdConfig,
        teacher: T,
        states: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
    ) -> Result<Self, BaselineError> {
        config.validate()?;
        let data = consistency::normalised_data(&teacher, states, actions)?;
        let online = consistency::initial_network(
            &teacher,
            &config.net,
            config.init_from_teacher,
            1,
            config.train.seed,
        )?;
        let seeds = Seeds::new(config.train.seed);
        Ok(Self {
            pre: BoundaryPreconditioning::new(config.sigma_data, config.sigma_min)?,
            grid: consistency::karras_levels(
                config.num_scales,
                config.sigma_min,
                config.sigma_max,
                config.rho,
            )?,
            sampler: RowSampler::uniform(data.len())?,
            opt: Optimisation::new(&config.train, &online)?,
            target: online.clone(),
            online,
            data,
            teacher,
            batch_rng: seeds.stream("minibatch"),
            noise_rng: seeds.stream("cd-noise"),
            steps_done: 0,
            buf: CdBuffers::default(),
            config,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &CdConfig {
        &self.config
    }

    /// Optimisation steps taken so far.
    pub fn steps_done(&self) -> u64 {
        self.steps_done
    }

    /// The teacher.
    pub fn teacher(&self) -> &T {
        &self.teacher
    }

    /// The normalised training data.
    pub fn data(&self) -> &Dataset {
        &self.data
    }

    /// The Karras grid `σ_0 = σ_max > … > σ_{N−1} = σ_min`.
    pub fn grid(&self) -> &[f32] {
        &self.grid
    }

    /// The online network `F_θ`.
    pub fn online(&self) -> &ConditionedNet {
        &self.online
    }

    /// Draws a minibatch, grid indices and noise, takes the teacher's Heun step and evaluates
    /// the target `f_{θ⁻}(x̂, σ_{n+1})`: everything of the loss that does not depend on `θ`.
    fn draw(&mut self) -> Result<(), BaselineError> {
        let n = self.config.train.batch_size;
        let d = self.data.action_dim();
        let b = &mut self.buf;
        b.batch.draw(&self.data, &self.sampler, n, &mut self.batch_rng);
        b.sigma_hi.clear();
        b.sigma_lo.clear();
        let last = self.grid.len() - 1;
        for _ in 0..n {
            let k = self.noise_rng.random_range(0..last);
            b.sigma_hi.push(self.grid[k]);
            b.sigma_lo.push(self.grid[k + 1]);
        }
        ensure(&mut b.noise, n, d);
        ensure(&mut b.x_hi, n, d);
        ensure(&mut b.x_lo, n, d);
        ensure(&mut b.target_out, n, d);
        ensure(&mut b.online_out, n, d);
        ensure(&mut b.grad, n, d);
        fill_normal(&mut b.noise, &mut self.noise_rng);
        for j in 0..d {
            let (a, z) = (b.batch.actions.col_as_slice(j), b.noise.col_as_slice(j));
            let x = b.x_hi.col_as_slice_mut(j);
            for i in 0..n {
                x[i] = a[i] + b.sigma_hi[i] * z[i];
            }
        }
        consistency::teacher_heun_step(
            &mut self.teacher,
            b.x_hi.as_ref(),
            &b.sigma_hi,
            &b.sigma_lo,
            b.batch.states.as_ref(),
            b.x_lo.as_mut(),
            &mut b.heun,
        )?;
        boundary_coefficients(&mut b.coef, &self.pre, &b.sigma_lo);
        self.target.forward_preconditioned(
            b.x_lo.as_ref(),
            b.batch.states.as_ref(),
            &b.coef,
            b.target_out.as_mut(),
        );
        Ok(())
    }

    /// The loss `1/(B d) Σ ‖f_θ(x, σ_n) − target‖²` of the drawn batch and, with `backward`,
    /// its gradient accumulated into the online network's parameters.
    fn online_loss(&mut self, backward: bool) -> f32 {
        let b = &mut self.buf;
        let (n, d) = (b.x_hi.nrows(), b.x_hi.ncols());
        boundary_coefficients(&mut b.coef, &self.pre, &b.sigma_hi);
        self.online.forward_preconditioned(
            b.x_hi.as_ref(),
            b.batch.states.as_ref(),
            &b.coef,
            b.online_out.as_mut(),
        );
        let scale = 1.0 / (n * d) as f32;
        let mut total = 0.0f64;
        for j in 0..d {
            let (f, t) = (b.online_out.col_as_slice(j), b.target_out.col_as_slice(j));
            let g = b.grad.col_as_slice_mut(j);
            for i in 0..n {
                let r = f[i] - t[i];
                total += f64::from(r * r);
                // ∂L/∂F = ∂L/∂f · c_out(σ_n).
                g[i] = 2.0 * r * scale * b.coef.out[i];
            }
        }
        if backward {
            self.online.backward(b.grad.as_ref());
        }
        (total * f64::from(scale)) as f32
    }

    /// One optimisation step; returns the loss before the update. Nothing is updated when
    /// the loss or a gradient is not finite.
    pub fn step(&mut self) -> Result<f32, BaselineError> {
        self.step_with_lr().map(|(loss, _)| loss)
    }

    fn step_with_lr(&mut self) -> Result<(f32, f32), BaselineError> {
        self.draw()?;
        self.online.zero_grad();
        let loss = self.online_loss(true);
        if !loss.is_finite() {
            return Err(BaselineError::NonFinite {
                iteration: self.steps_done as usize,
                quantity: "consistency distillation loss",
            });
        }
        let lr = self.opt.apply(&mut self.online, &mut self.target, self.steps_done)?;
        self.steps_done += 1;
        Ok((loss, lr))
    }

    /// Runs the remaining configured steps, calling `progress` every `log_every` steps and after
    /// the last, and returns the distilled policy (evaluation-averaged weights).
    pub fn train(
        &mut self,
        progress: &mut dyn FnMut(&ConsistencyProgress),
    ) -> Result<ConsistencyModel, BaselineError> {
        let start = Instant::now();
        let total = self.config.train.steps;
        let mut meter = LossMeter::default();
        while self.steps_done < total {
            let (loss, lr) = self.step_with_lr()?;
            meter.add(loss, 0.0, loss);
            let done = self.steps_done;
            if done % self.config.train.log_every == 0 || done == total {
                progress(&meter.report(done, total, lr, start.elapsed().as_secs_f64()));
            }
        }
        self.model()
    }

    /// The current student as a policy (evaluation-averaged weights, the configured sampling
    /// steps, the teacher's normalisers, policy stream seeded with the training seed).
    pub fn model(&self) -> Result<ConsistencyModel, BaselineError> {
        let (sn, an) = self.teacher.normalizers();
        ConsistencyModel::new(
            self.opt.averaged(&self.online)?,
            self.pre,
            self.config.sigma_max,
            self.config.rho,
            self.config.sampling_steps,
            sn.clone(),
            an.clone(),
            self.config.train.seed,
        )
    }
}

/// A distilled consistency model: the consistency function `f(x, σ, s)` in the teacher's
/// normalised space, and a [`Policy`] (raw observations in, raw actions out) that samples
/// with one or more consistency steps.
#[derive(Debug, Clone)]
pub struct ConsistencyModel {
    net: ConditionedNet,
    pre: BoundaryPreconditioning,
    sigma_max: f32,
    rho: f32,
    /// `σ_max` followed by the intermediate levels of multistep sampling.
    levels: Vec<f32>,
    state_norm: Affine,
    action_norm: Affine,
    rng: vdd_core::Rng,
    io: PolicyIo,
    scratch: SampleScratch,
}

#[derive(Debug, Clone)]
struct SampleScratch {
    x: Mat<f32>,
    sigma: Vec<f32>,
    coef: Coefficients,
}

impl Default for SampleScratch {
    fn default() -> Self {
        Self { x: Mat::zeros(0, 0), sigma: Vec::new(), coef: Coefficients::default() }
    }
}

impl ConsistencyModel {
    /// Assembles a model from a one-level network and its settings.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        net: ConditionedNet,
        pre: BoundaryPreconditioning,
        sigma_max: f32,
        rho: f32,
        sampling_steps: usize,
        state_norm: Affine,
        action_norm: Affine,
        seed: u64,
    ) -> Result<Self, BaselineError> {
        if net.levels() != 1 {
            return Err(
                CoreError::Config("a consistency model takes one noise level".into()).into()
            );
        }
        vdd_core::check_len("state normaliser", state_norm.dim(), net.state_dim())?;
        vdd_core::check_len("action normaliser", action_norm.dim(), net.action_dim())?;
        consistency::validate_levels(pre.sigma_data, pre.sigma_min, sigma_max, rho, 2)?;
        let mut model = Self {
            net,
            pre,
            sigma_max,
            rho,
            levels: Vec::new(),
            state_norm,
            action_norm,
            rng: Seeds::new(seed).stream(POLICY_STREAM),
            io: PolicyIo::default(),
            scratch: SampleScratch::default(),
        };
        model.set_sampling_steps(sampling_steps)?;
        Ok(model)
    }

    /// The network `F`.
    pub fn net(&self) -> &ConditionedNet {
        &self.net
    }

    /// The preconditioning.
    pub fn preconditioning(&self) -> BoundaryPreconditioning {
        self.pre
    }

    /// The `(state, action)` normalisers (the teacher's).
    pub fn normalizers(&self) -> (&Affine, &Affine) {
        (&self.state_norm, &self.action_norm)
    }

    /// Number of sampling steps (network evaluations per action).
    pub fn sampling_steps(&self) -> usize {
        self.levels.len()
    }

    /// The levels sampling evaluates `f` at: `σ_max`, then the intermediate levels.
    pub fn sampling_levels(&self) -> &[f32] {
        &self.levels
    }

    /// Sets the number of sampling steps `k ≥ 1`: `σ_max`, then the `k − 1` inner levels of a
    /// `(k + 1)`-level Karras grid from `σ_max` to `σ_min`.
    pub fn set_sampling_steps(&mut self, steps: usize) -> Result<(), BaselineError> {
        if steps == 0 {
            return Err(CoreError::Config("sampling steps must be >= 1".into()).into());
        }
        let grid =
            consistency::karras_levels(steps + 1, self.pre.sigma_min, self.sigma_max, self.rho)?;
        self.levels = grid[..steps].to_vec();
        Ok(())
    }

    /// Sets explicit sampling levels: `σ_max` first, then strictly decreasing levels above
    /// `σ_min` (multistep consistency sampling adds fresh noise of `sqrt(τ² − σ_min²)` before
    /// each further evaluation).
    pub fn set_sampling_levels(&mut self, levels: &[f32]) -> Result<(), BaselineError> {
        let ok = !levels.is_empty()
            && levels.iter().all(|s| s.is_finite() && *s > self.pre.sigma_min)
            && levels.windows(2).all(|w| w[1] < w[0]);
        if !ok {
            return Err(CoreError::Config(format!(
                "sampling levels must be finite, above sigma_min and decreasing, got {levels:?}"
            ))
            .into());
        }
        self.levels = levels.to_vec();
        Ok(())
    }

    /// The consistency function `f(x, σ, s)` for a batch in the normalised space: `x` is
    /// `n x d_a`, `sigma` has `n` positive levels, `states` is `n x d_s`, `out` `n x d_a`.
    pub fn consistency_fn(
        &mut self,
        x: MatRef<'_, f32>,
        sigma: &[f32],
        states: MatRef<'_, f32>,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let (da, ds) = (self.net.action_dim(), self.net.state_dim());
        check_model_batch(x, states, &[sigma], out.rb(), da, ds)?;
        boundary_coefficients(&mut self.scratch.coef, &self.pre, sigma);
        self.net.forward_preconditioned(x, states, &self.scratch.coef, out.as_mut());
        Ok(())
    }

    /// Samples one action per row of normalised `states` into `out` (normalised space) with
    /// the configured steps, drawing noise from `rng`.
    pub fn sample(
        &mut self,
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let n = states.nrows();
        vdd_core::check_shape("states", states, n, self.net.state_dim())?;
        vdd_core::check_finite("states", states)?;
        vdd_core::check_shape("sampled actions", out.rb(), n, self.net.action_dim())?;
        let Self { net, pre, levels, scratch, .. } = self;
        sample_into(net, pre, levels, scratch, states, rng, out.as_mut());
        Ok(())
    }
}

/// Multistep consistency sampling (Song et al., Algorithm 1) without argument checks.
fn sample_into(
    net: &mut ConditionedNet,
    pre: &BoundaryPreconditioning,
    levels: &[f32],
    scratch: &mut SampleScratch,
    states: MatRef<'_, f32>,
    rng: &mut dyn RngCore,
    mut out: MatMut<'_, f32>,
) {
    let (n, d) = (out.nrows(), out.ncols());
    ensure(&mut scratch.x, n, d);
    for (step, &level) in levels.iter().enumerate() {
        // Noise of the level: the full σ_max at the start, sqrt(τ² − σ_min²) afterwards.
        let std = if step == 0 {
            level
        } else {
            (level * level - pre.sigma_min * pre.sigma_min).max(0.0).sqrt()
        };
        for j in 0..d {
            let x = scratch.x.col_as_slice_mut(j);
            for i in 0..n {
                let base = if step == 0 { 0.0 } else { out[(i, j)] };
                x[i] = base + std * vdd_core::standard_normal(rng);
            }
        }
        scratch.sigma.clear();
        scratch.sigma.resize(n, level);
        boundary_coefficients(&mut scratch.coef, pre, &scratch.sigma);
        net.forward_preconditioned(scratch.x.as_ref(), states, &scratch.coef, out.rb_mut());
    }
}

impl Policy for ConsistencyModel {
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
        let (ds, da) = (self.obs_dim(), self.action_dim());
        self.act_batch(
            MatRef::from_row_major_slice(obs, 1, ds),
            MatMut::from_row_major_slice_mut(action, 1, da),
        )
    }

    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        actions: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let (ds, da) = (self.obs_dim(), self.action_dim());
        check_policy_batch(obs, actions.rb(), ds, da)?;
        self.io.load(obs, &self.state_norm, da);
        let Self { net, pre, levels, scratch, io, rng, .. } = self;
        sample_into(net, pre, levels, scratch, io.obs.as_ref(), rng, io.act.as_mut());
        self.io.store(&self.action_norm, actions);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_consistency::{FOUR_MODES, four_mode_teacher, near_mode_fraction};
    use vdd_diffusion::Beso;

    fn tiny_config() -> CdConfig {
        let mut c = CdConfig {
            net: NetConfig { hidden_dim: 6, num_blocks: 1, embed_dim: 4, ..Default::default() },
            num_scales: 6,
            sigma_max: 10.0,
            ..Default::default()
        };
        c.train.batch_size = 5;
        c
    }

    fn toy_data(n: usize, seed: u64) -> (Mat<f32>, Mat<f32>) {
        let mut rng = Seeds::new(seed).stream("data");
        let actions = Mat::from_fn(n, 2, |_, _| rng.random_range(-1.5f32..1.5));
        (Mat::zeros(n, 1), actions)
    }

    #[test]
    fn consistency_function_is_the_identity_at_sigma_min() {
        let (s, a) = toy_data(16, 0);
        let mut t =
            CdTrainer::new(tiny_config(), four_mode_teacher(), s.as_ref(), a.as_ref()).unwrap();
        for _ in 0..3 {
            t.step().unwrap();
        }
        let mut model = t.model().unwrap();
        let x = Mat::from_fn(7, 2, |i, j| 3.0 * (i as f32 - 3.0) + 0.37 * j as f32);
        let states = Mat::from_fn(7, 1, |i, _| i as f32);
        let mut out = Mat::zeros(7, 2);
        model.consistency_fn(x.as_ref(), &[0.002; 7], states.as_ref(), out.as_mut()).unwrap();
        assert_eq!(out, x, "f(x, σ_min) must be exactly x");
        // Away from the boundary it is not the identity.
        model.consistency_fn(x.as_ref(), &[1.0; 7], states.as_ref(), out.as_mut()).unwrap();
        assert_ne!(out, x);
        // Bad inputs are errors.
        assert!(
            model.consistency_fn(x.as_ref(), &[0.0; 7], states.as_ref(), out.as_mut()).is_err()
        );
        assert!(
            model.consistency_fn(x.as_ref(), &[1.0; 6], states.as_ref(), out.as_mut()).is_err()
        );
    }

    /// The analytic gradient of the CD loss w.r.t. every parameter matches central finite
    /// differences of the loss (teacher step and target fixed, as the method prescribes).
    #[test]
    fn cd_loss_gradient_matches_finite_differences() {
        let (s, a) = toy_data(16, 1);
        let mut t =
            CdTrainer::new(tiny_config(), four_mode_teacher(), s.as_ref(), a.as_ref()).unwrap();
        // Move the online network away from the target so the loss is not ~0.
        for _ in 0..5 {
            t.step().unwrap();
        }
        t.draw().unwrap();
        t.online.zero_grad();
        let loss0 = t.online_loss(true);
        assert!(loss0 > 1e-4, "loss {loss0}");
        let mut analytic = Vec::new();
        t.online.visit_params("", &mut |_, p| analytic.push(p.grad.clone()));
        let h = 3e-3f32;
        let mut worst = 0.0f64;
        let mut checked = 0;
        for (pi, grads) in analytic.iter().enumerate() {
            for (e, &g) in grads.iter().enumerate() {
                let set = |t: &mut CdTrainer<_>, delta: f32| {
                    let mut k = 0;
                    t.online.visit_params_mut("", &mut |_, p| {
                        if k == pi {
                            p.value[e] += delta;
                        }
                        k += 1;
                    });
                };
                set(&mut t, h);
                let up = f64::from(t.online_loss(false));
                set(&mut t, -2.0 * h);
                let down = f64::from(t.online_loss(false));
                set(&mut t, h);
                let fd = (up - down) / (2.0 * f64::from(h));
                let err = (fd - f64::from(g)).abs() / fd.abs().max(1e-2);
                worst = worst.max(err);
                checked += 1;
            }
        }
        assert!(checked > 50);
        assert!(worst < 2e-2, "worst relative gradient error {worst}");
    }

    /// A CD student of the exact denoiser of a 4-mode mixture puts its one-step samples on the
    /// modes, all four of them.
    #[test]
    fn cd_student_of_an_exact_gmm_teacher_samples_near_the_modes() {
        let mut rng = Seeds::new(5).stream("data");
        let n = 2000;
        let labels: Vec<usize> = (0..n).map(|_| rng.random_range(0..4)).collect();
        let actions = Mat::from_fn(n, 2, |i, j| {
            FOUR_MODES[labels[i]][j] + 0.1 * vdd_core::standard_normal(&mut rng)
        });
        let states = Mat::<f32>::zeros(n, 1);
        let mut config = CdConfig {
            net: NetConfig { hidden_dim: 32, num_blocks: 1, ..Default::default() },
            num_scales: 10,
            sigma_max: 20.0,
            ..Default::default()
        };
        config.train.steps = 1000;
        config.train.batch_size = 128;
        config.train.adam.lr = 1e-2;
        config.train.lr_schedule =
            vdd_nn::LrSchedule::Cosine { total_steps: 1000, final_factor: 0.05 };
        config.train.target_ema_decay = 0.9;
        config.train.ema_decay = 0.9;
        config.train.seed = 2;
        let mut t =
            CdTrainer::new(config, four_mode_teacher(), states.as_ref(), actions.as_ref()).unwrap();
        let obs = Mat::<f32>::zeros(1000, 1);
        let mut out = Mat::zeros(1000, 2);
        // Untrained, the one-step samples are spread out: the test discriminates.
        t.model().unwrap().act_batch(obs.as_ref(), out.as_mut()).unwrap();
        let (near_untrained, _) = near_mode_fraction(out.as_ref(), 0.3);
        assert!(near_untrained < 0.3, "untrained: {near_untrained}");
        let mut model = t.train(&mut |_| {}).unwrap();
        model.act_batch(obs.as_ref(), out.as_mut()).unwrap();
        let (near, per_mode) = near_mode_fraction(out.as_ref(), 0.3);
        assert!(near > 0.5, "only {near} of the samples within 0.3 of a mode");
        assert!(per_mode.iter().all(|&f| f > 0.15), "mode fractions {per_mode:?}");
    }

    #[test]
    fn training_is_deterministic_for_a_seed() {
        let (s, a) = toy_data(32, 2);
        let run = |seed: u64| {
            let mut c = tiny_config();
            c.train.steps = 5;
            c.train.seed = seed;
            let mut t = CdTrainer::new(c, four_mode_teacher(), s.as_ref(), a.as_ref()).unwrap();
            let mut reports = Vec::new();
            let mut m = t.train(&mut |p| reports.push(p.loss)).unwrap();
            let out = m.act(&[0.0]).unwrap();
            (reports, out)
        };
        assert_eq!(run(7), run(7));
        assert_ne!(run(7).1, run(8).1);
    }

    #[test]
    fn bad_configs_and_data_are_errors() {
        let (s, a) = toy_data(8, 0);
        let teacher = four_mode_teacher;
        for c in [
            CdConfig { num_scales: 1, ..tiny_config() },
            CdConfig { sigma_min: 0.0, ..tiny_config() },
            CdConfig { sigma_max: 0.001, ..tiny_config() },
            CdConfig { sampling_steps: 0, ..tiny_config() },
        ] {
            assert!(CdTrainer::new(c, teacher(), s.as_ref(), a.as_ref()).is_err());
        }
        let mut c = tiny_config();
        c.train.target_ema_decay = 1.0;
        assert!(CdTrainer::new(c, teacher(), s.as_ref(), a.as_ref()).is_err());
        // The closure teacher has no network to start from.
        let c = CdConfig { init_from_teacher: true, ..tiny_config() };
        assert!(CdTrainer::new(c, teacher(), s.as_ref(), a.as_ref()).is_err());
        // Wrong data shapes and values.
        let bad = Mat::<f32>::zeros(8, 3);
        assert!(CdTrainer::new(tiny_config(), teacher(), s.as_ref(), bad.as_ref()).is_err());
        let mut nan = a.clone();
        nan[(0, 0)] = f32::NAN;
        assert!(CdTrainer::new(tiny_config(), teacher(), s.as_ref(), nan.as_ref()).is_err());
        // The policy checks its inputs.
        let mut m = CdTrainer::new(tiny_config(), teacher(), s.as_ref(), a.as_ref())
            .unwrap()
            .model()
            .unwrap();
        assert!(m.act(&[0.0, 1.0]).is_err());
        assert!(m.act(&[f32::NAN]).is_err());
        assert!(m.set_sampling_steps(0).is_err());
        assert!(m.set_sampling_levels(&[1.0, 2.0]).is_err());
    }

    #[test]
    fn student_starts_from_a_beso_teacher_and_multistep_sampling_runs() {
        let net = NetConfig { hidden_dim: 8, num_blocks: 1, ..Default::default() };
        let bc = BesoConfig { net, ..Default::default() };
        let mut beso = Beso::new(&bc, Affine::identity(1), Affine::identity(2), 0).unwrap();
        let (s, a) = toy_data(16, 3);
        let mut c = CdConfig::for_beso(&bc);
        c.train.batch_size = 4;
        let t = CdTrainer::new(c.clone(), &mut beso, s.as_ref(), a.as_ref()).unwrap();
        // Before training f(x, σ) differs from the teacher's D(x; σ) only through the
        // boundary-shifted c_skip and c_out.
        let mut model = t.model().unwrap();
        let x = Mat::from_fn(3, 2, |i, j| i as f32 - j as f32);
        let st = Mat::<f32>::zeros(3, 1);
        let (mut f, mut dn) = (Mat::zeros(3, 2), Mat::zeros(3, 2));
        model.consistency_fn(x.as_ref(), &[5.0; 3], st.as_ref(), f.as_mut()).unwrap();
        drop(t);
        beso.denoise(x.as_ref(), &[5.0; 3], st.as_ref(), dn.as_mut()).unwrap();
        for i in 0..3 {
            for j in 0..2 {
                assert!((f[(i, j)] - dn[(i, j)]).abs() < 1e-2, "{f:?} vs {dn:?}");
            }
        }
        model.set_sampling_steps(3).unwrap();
        assert_eq!(model.sampling_levels().len(), 3);
        assert_eq!(model.sampling_levels()[0], 80.0);
        assert!(model.act(&[0.0]).unwrap().iter().all(|v| v.is_finite()));
        // A different architecture cannot start from the teacher.
        let mut other = c;
        other.net.hidden_dim = 16;
        assert!(CdTrainer::new(other, &mut beso, s.as_ref(), a.as_ref()).is_err());
    }
}
