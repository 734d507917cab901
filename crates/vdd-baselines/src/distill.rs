//! The machinery Consistency Distillation ([`crate::cd`]) and the Consistency Trajectory Model
//! ([`crate::ctm`]) share:
//!
//! * [`ConsistencyTrainer`]: a training run — the shared state ([`Distillation`]: teacher,
//!   normalised data, Karras grid, online and target networks, optimiser, random streams) and
//!   the loop; each method supplies an [`Objective`] (what to draw, the loss and its gradient);
//! * [`DistilledPolicy`]: a distilled network as a [`vdd_core::Policy`] — raw observations in,
//!   the method's sampler ([`Sampling`]) in the normalised space, raw actions out;
//! * [`Coefficients`]: per-row preconditioning of `skip · x + out · F(c_in · x, …)`.
//!
//! The module is private: the two public generic types are re-exported from
//! [`crate::consistency`] and used through the aliases `CdTrainer`, `CtmTrainer`,
//! `ConsistencyModel` and `TrajectoryModel`; the traits are sealed by being unreachable.

use std::time::Instant;

use faer::reborrow::{Reborrow, ReborrowMut};
use faer::{Mat, MatMut, MatRef};
use rand::RngCore;
use vdd_core::{
    Affine, CoreError, Policy, Seeds, check_act_args, check_finite, check_len, check_shape,
};
use vdd_diffusion::SamplerBuffers;
use vdd_nn::{Adam, Ema, Parameters};

use crate::consistency::{
    ConditionedNet, ConsistencyConfig, ConsistencyProgress, ConsistencyTeacher,
    ConsistencyTrainConfig,
};
use crate::dataset::Dataset;
use crate::error::BaselineError;
use crate::fit::{Minibatch, RowSampler};

/// Per-row coefficients of a preconditioned evaluation
/// `out_i = skip_i x_i + out_i F(c_in_i x_i, s_i, noise_i[, noise_to_i])`.
#[derive(Debug, Clone, Default)]
pub struct Coefficients {
    pub(crate) c_in: Vec<f32>,
    pub(crate) noise: Vec<f32>,
    pub(crate) noise_to: Vec<f32>,
    pub(crate) skip: Vec<f32>,
    pub(crate) out: Vec<f32>,
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

/// The loss terms of one evaluation (`total = consistency + λ_DSM · dsm`).
#[derive(Debug, Clone, Copy, PartialEq, Default)]
pub struct LossTerms {
    pub(crate) consistency: f32,
    pub(crate) dsm: f32,
    pub(crate) total: f32,
}

/// What a distillation method adds to the shared training loop.
pub trait Objective<T>: Sized {
    /// The method's configuration.
    type Config: std::fmt::Debug;
    /// The preconditioning the distilled policy samples with.
    type Sampler: Sampling;
    /// Names the loss in [`BaselineError::NonFinite`].
    const QUANTITY: &'static str;
    /// Name of the random stream of the returned policy.
    const POLICY_STREAM: &'static str;
    /// Name of the random stream of the training draws (levels and noise).
    const NOISE_STREAM: &'static str;

    /// Checks `config` and sets up the method's part of a run (its buffers start empty).
    fn new(config: Self::Config) -> Result<Self, BaselineError>;

    /// The configuration.
    fn config(&self) -> &Self::Config;

    /// The settings shared with every consistency method.
    fn base(&self) -> &ConsistencyConfig;

    /// The sampler of the returned policy.
    fn sampler(&self) -> Self::Sampler;

    /// Draws a minibatch and everything of the loss that does not depend on `θ` (teacher
    /// steps, target-network outputs).
    fn draw(&mut self, core: &mut Distillation<T>) -> Result<(), BaselineError>;

    /// The loss of the drawn batch; with `backward`, its gradient accumulated into
    /// `core.online`'s parameters.
    fn loss(&mut self, core: &mut Distillation<T>, backward: bool) -> LossTerms;
}

/// A consistency-distillation run of a [`ConsistencyTeacher`]: used as
/// [`crate::cd::CdTrainer`] (Consistency Distillation) and [`crate::ctm::CtmTrainer`]
/// (Consistency Trajectory Model), whose docs have examples.
pub struct ConsistencyTrainer<T, O> {
    pub(crate) core: Distillation<T>,
    pub(crate) objective: O,
}

impl<T: ConsistencyTeacher, O: Objective<T>> std::fmt::Debug for ConsistencyTrainer<T, O> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ConsistencyTrainer")
            .field("config", self.objective.config())
            .field("steps_done", &self.core.steps_done)
            .field("data_len", &self.core.data.len())
            .finish_non_exhaustive()
    }
}

impl<T: ConsistencyTeacher, O: Objective<T>> ConsistencyTrainer<T, O> {
    /// Sets up distillation of `teacher` on raw `states` (`n x d_s`) and `actions`
    /// (`n x d_a`, action chunks flattened) — the data the teacher was trained on, normalised
    /// here with the teacher's normalisers. Errors on bad settings, a teacher that cannot be
    /// distilled, or data that do not match it.
    pub fn new(
        config: O::Config,
        teacher: T,
        states: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
    ) -> Result<Self, BaselineError> {
        let objective = O::new(config)?;
        let core = Distillation::new(
            objective.base(),
            O::Sampler::LEVELS,
            teacher,
            states,
            actions,
            O::NOISE_STREAM,
        )?;
        Ok(Self { core, objective })
    }

    /// The configuration.
    pub fn config(&self) -> &O::Config {
        self.objective.config()
    }

    /// Optimisation steps taken so far.
    pub fn steps_done(&self) -> u64 {
        self.core.steps_done
    }

    /// The training data, normalised with the teacher's normalisers.
    pub fn data(&self) -> &Dataset {
        &self.core.data
    }

    /// The teacher.
    pub fn teacher(&self) -> &T {
        &self.core.teacher
    }

    /// One optimisation step; returns the (total) loss before the update. Nothing is updated
    /// when the loss or a gradient is not finite.
    pub fn step(&mut self) -> Result<f32, BaselineError> {
        Ok(self.core.step(&mut self.objective)?.0.total)
    }

    /// Runs the remaining configured steps, calling `progress` every `log_every` steps and
    /// after the last, and returns the distilled policy ([`ConsistencyTrainer::model`]).
    pub fn train(
        &mut self,
        progress: &mut dyn FnMut(&ConsistencyProgress),
    ) -> Result<DistilledPolicy<O::Sampler>, BaselineError> {
        self.core.run(&mut self.objective, progress)?;
        self.model()
    }

    /// The current student as a policy: evaluation-averaged weights, the configured sampling
    /// steps, the teacher's normalisers, its random stream seeded with the training seed.
    pub fn model(&self) -> Result<DistilledPolicy<O::Sampler>, BaselineError> {
        let (sn, an) = self.core.teacher.normalizers();
        let base = self.objective.base();
        DistilledPolicy::new(
            self.core.averaged()?,
            self.objective.sampler(),
            base,
            (sn.clone(), an.clone()),
            base.train.seed,
            O::POLICY_STREAM,
        )
    }
}

/// The state of a consistency-distillation run.
pub struct Distillation<T> {
    pub(crate) teacher: T,
    pub(crate) data: Dataset,
    sampler: RowSampler,
    /// The Karras grid `σ_0 = σ_max > … > σ_{N−1} = σ_min`.
    pub(crate) grid: Vec<f32>,
    pub(crate) online: ConditionedNet,
    pub(crate) target: ConditionedNet,
    pub(crate) noise_rng: vdd_core::Rng,
    batch_rng: vdd_core::Rng,
    pub(crate) steps_done: u64,
    /// The current minibatch (normalised).
    pub(crate) batch: Minibatch,
    heun: SamplerBuffers,
    opt: Optimisation,
    train: ConsistencyTrainConfig,
}

impl<T: ConsistencyTeacher> Distillation<T> {
    /// Validates the teacher and the data, normalises the data with the teacher's normalisers
    /// and builds the student (`levels` noise conditions) and its optimiser.
    pub(crate) fn new(
        config: &ConsistencyConfig,
        levels: usize,
        teacher: T,
        states: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
        noise_stream: &str,
    ) -> Result<Self, BaselineError> {
        config.validate()?;
        teacher.validate()?;
        let data = normalised_data(&teacher, states, actions)?;
        let online = initial_network(&teacher, config, levels)?;
        let seeds = Seeds::new(config.train.seed);
        Ok(Self {
            grid: karras_levels(config.num_scales, config.sigma_min, config.sigma_max, config.rho)?,
            sampler: RowSampler::uniform(data.len())?,
            opt: Optimisation::new(&config.train, &online)?,
            target: online.clone(),
            online,
            data,
            teacher,
            noise_rng: seeds.stream(noise_stream),
            batch_rng: seeds.stream("minibatch"),
            steps_done: 0,
            batch: Minibatch::default(),
            heun: SamplerBuffers::default(),
            train: config.train.clone(),
        })
    }

    /// Draws the next minibatch of `batch_size` rows (uniform, with replacement).
    pub(crate) fn draw_batch(&mut self) {
        self.batch.draw(&self.data, &self.sampler, &mut self.batch_rng, self.train.batch_size);
    }

    /// `out = a + σ_i z` per row, with the batch's actions `a`, levels `sigma` and fresh
    /// standard normal `z` (drawn into `noise`).
    pub(crate) fn perturb(&mut self, sigma: &[f32], noise: &mut Mat<f32>, out: &mut Mat<f32>) {
        let (n, d) = (self.batch.actions.nrows(), self.batch.actions.ncols());
        ensure(noise, n, d);
        ensure(out, n, d);
        fill_normal(noise, &mut self.noise_rng);
        for j in 0..d {
            let (a, z) = (self.batch.actions.col_as_slice(j), noise.col_as_slice(j));
            let x = out.col_as_slice_mut(j);
            for i in 0..n {
                x[i] = a[i] + sigma[i] * z[i];
            }
        }
    }

    /// One Heun step of the teacher's probability-flow ODE `dx/dσ = (x − D(x; σ, s))/σ` from
    /// `sigma_from[i]` to `sigma_to[i]` per row, at the batch's states, written into `out`.
    pub(crate) fn teacher_heun(
        &mut self,
        x: MatRef<'_, f32>,
        sigma_from: &[f32],
        sigma_to: &[f32],
        out: MatMut<'_, f32>,
    ) -> Result<(), BaselineError> {
        let Self { teacher, batch, heun, .. } = self;
        let states = batch.states.as_ref();
        let mut denoise = |x: MatRef<'_, f32>, s: &[f32], o: MatMut<'_, f32>| {
            teacher.denoise(x, s, states, o).map_err(vdd_diffusion::DiffusionError::from)
        };
        vdd_diffusion::heun_step(&mut denoise, x, sigma_from, sigma_to, out, heun)
            .map_err(|e| BaselineError::Core(CoreError::from(e)))
    }

    /// One optimisation step of `objective`; returns the loss terms before the update and the
    /// learning rate. Nothing is updated when the loss or a gradient is not finite.
    pub(crate) fn step<O: Objective<T>>(
        &mut self,
        objective: &mut O,
    ) -> Result<(LossTerms, f32), BaselineError> {
        objective.draw(self)?;
        self.online.zero_grad();
        let loss = objective.loss(self, true);
        let iteration = self.steps_done as usize;
        if !loss.total.is_finite() {
            return Err(BaselineError::NonFinite { iteration, quantity: O::QUANTITY });
        }
        vdd_nn::clip_grad_norm_checked(&mut self.online, self.train.grad_clip)
            .map_err(|_| BaselineError::NonFinite { iteration, quantity: O::QUANTITY })?;
        let lr = self.opt.apply(&mut self.online, &mut self.target, self.steps_done)?;
        self.steps_done += 1;
        Ok((loss, lr))
    }

    /// Runs the remaining configured steps, calling `progress` every `log_every` steps and
    /// after the last.
    pub(crate) fn run<O: Objective<T>>(
        &mut self,
        objective: &mut O,
        progress: &mut dyn FnMut(&ConsistencyProgress),
    ) -> Result<(), BaselineError> {
        let start = Instant::now();
        let total = self.train.steps;
        let mut meter = LossMeter::default();
        while self.steps_done < total {
            let (loss, lr) = self.step(objective)?;
            meter.add(loss);
            let done = self.steps_done;
            if done % self.train.log_every == 0 || done == total {
                progress(&meter.report(done, total, lr, start.elapsed().as_secs_f64()));
            }
        }
        Ok(())
    }

    /// A copy of the online network carrying the evaluation average of its weights.
    pub(crate) fn averaged(&self) -> Result<ConditionedNet, BaselineError> {
        let mut net = self.online.clone();
        self.opt.eval_ema.copy_to(&mut net)?;
        Ok(net)
    }
}

/// Adam, the learning-rate schedule, the target network's and the evaluation average.
#[derive(Debug, Clone)]
struct Optimisation {
    adam: Adam,
    target_ema: Ema,
    eval_ema: Ema,
    base_lr: f32,
    final_lr_factor: f32,
    steps: u64,
}

impl Optimisation {
    fn new(
        config: &ConsistencyTrainConfig,
        online: &ConditionedNet,
    ) -> Result<Self, BaselineError> {
        Ok(Self {
            adam: Adam::new(config.adam),
            target_ema: Ema::new(online, config.target_ema_decay)?,
            eval_ema: Ema::new(online, config.ema_decay)?,
            base_lr: config.adam.lr,
            final_lr_factor: config.final_lr_factor,
            steps: config.steps,
        })
    }

    /// One Adam step on `online` with the cosine-decayed learning rate, then the target
    /// network and the evaluation average follow. Returns the learning rate used.
    fn apply(
        &mut self,
        online: &mut ConditionedNet,
        target: &mut ConditionedNet,
        step: u64,
    ) -> Result<f32, BaselineError> {
        let progress = (step as f32 / self.steps.max(1) as f32).min(1.0);
        let cosine = 0.5 * (1.0 + (std::f32::consts::PI * progress).cos());
        let factor = self.final_lr_factor + (1.0 - self.final_lr_factor) * cosine;
        self.adam.step(online, factor);
        self.target_ema.update(online)?;
        self.target_ema.copy_to(target)?;
        self.eval_ema.update(online)?;
        Ok(self.base_lr * factor)
    }
}

/// Accumulates the loss terms between progress reports.
#[derive(Debug, Clone, Default)]
struct LossMeter {
    total: f64,
    consistency: f64,
    dsm: f64,
    count: u64,
}

impl LossMeter {
    fn add(&mut self, loss: LossTerms) {
        self.total += f64::from(loss.total);
        self.consistency += f64::from(loss.consistency);
        self.dsm += f64::from(loss.dsm);
        self.count += 1;
    }

    /// The report for `step` of `total_steps`, resetting the averages.
    fn report(
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

/// Validates raw `states`/`actions` against the teacher and normalises them with its
/// normalisers.
fn normalised_data<T: ConsistencyTeacher + ?Sized>(
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
    Dataset::new(normalize(states, sn), normalize(actions, an))
}

/// `(m − offset) / scale` per column.
fn normalize(m: MatRef<'_, f32>, a: &Affine) -> Mat<f32> {
    Mat::from_fn(m.nrows(), m.ncols(), |i, j| (m[(i, j)] - a.offset[j]) / a.scale[j])
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
fn initial_network<T: ConsistencyTeacher + ?Sized>(
    teacher: &T,
    config: &ConsistencyConfig,
    levels: usize,
) -> Result<ConditionedNet, BaselineError> {
    if !config.init_from_teacher {
        return ConditionedNet::new(
            &config.net,
            teacher.action_dim(),
            teacher.state_dim(),
            levels,
            &mut Seeds::new(config.train.seed).stream("init"),
        );
    }
    let Some(net) = teacher.network() else {
        return Err(CoreError::Config(
            "init_from_teacher is set but the teacher exposes no network".into(),
        )
        .into());
    };
    if *net.config() != config.net
        || net.action_dim() != teacher.action_dim()
        || net.state_dim() != teacher.state_dim()
    {
        return Err(CoreError::Config(format!(
            "init_from_teacher is set but the student architecture {:?} differs from the \
             teacher's {:?}",
            config.net,
            net.config()
        ))
        .into());
    }
    ConditionedNet::from_teacher(net, levels)
}

/// Resizes `m` to `r x c` when its shape differs.
pub(crate) fn ensure(m: &mut Mat<f32>, r: usize, c: usize) {
    if m.nrows() != r || m.ncols() != c {
        *m = Mat::zeros(r, c);
    }
}

/// Fills `m` with standard normal draws.
pub(crate) fn fill_normal(m: &mut Mat<f32>, rng: &mut dyn RngCore) {
    for j in 0..m.ncols() {
        vdd_core::fill_standard_normal(rng, m.col_as_slice_mut(j));
    }
}

/// How a distilled network samples: from noise `x = σ_max z` at `levels[0] = σ_max` down to
/// `levels[k] = σ_min` with `k` network evaluations, in the normalised space; step `i`
/// evaluates the network on `x` from `levels[i]` towards `levels[i + 1]` (`sample_along`).
pub trait Sampling: Copy {
    /// Number of noise conditions of the network.
    const LEVELS: usize;

    /// Writes into `coef` (cleared first) the coefficients of the evaluation taking each row
    /// from its level `t` towards its level `u`.
    fn coefficients(&self, coef: &mut Coefficients, t: &[f32], u: &[f32]);

    /// Every step but the first starts from the previous step's output plus fresh noise of
    /// this standard deviation at the step's `level`, or (`None`) from the output itself,
    /// without drawing.
    fn fresh_noise_std(&self, level: f32) -> Option<f32>;
}

/// Writes one sample per row of `states` into `out` along `levels` with `pre`'s steps.
fn sample_along<P: Sampling>(
    pre: &P,
    net: &mut ConditionedNet,
    levels: &[f32],
    scratch: &mut SampleScratch,
    states: MatRef<'_, f32>,
    rng: &mut dyn RngCore,
    mut out: MatMut<'_, f32>,
) {
    let (n, d) = (out.nrows(), out.ncols());
    scratch.start(n, d, levels[0], rng);
    for (k, w) in levels.windows(2).enumerate() {
        if k > 0 {
            match pre.fresh_noise_std(w[0]) {
                Some(std) => {
                    scratch.start(n, d, std, rng);
                    for j in 0..d {
                        let x = scratch.x.col_as_slice_mut(j);
                        for i in 0..n {
                            x[i] += out[(i, j)];
                        }
                    }
                }
                None => scratch.x.copy_from(out.rb()),
            }
        }
        scratch.set_levels(n, w[0], w[1]);
        pre.coefficients(&mut scratch.coef, &scratch.t, &scratch.u);
        net.forward_preconditioned(scratch.x.as_ref(), states, &scratch.coef, out.rb_mut());
    }
}

/// Reused buffers of sampling.
#[derive(Debug, Clone)]
pub struct SampleScratch {
    pub(crate) x: Mat<f32>,
    pub(crate) t: Vec<f32>,
    pub(crate) u: Vec<f32>,
    pub(crate) coef: Coefficients,
}

impl Default for SampleScratch {
    fn default() -> Self {
        Self { x: Mat::zeros(0, 0), t: Vec::new(), u: Vec::new(), coef: Coefficients::default() }
    }
}

impl SampleScratch {
    /// `x = σ z` for an `n x d` batch.
    pub(crate) fn start(&mut self, n: usize, d: usize, sigma: f32, rng: &mut dyn RngCore) {
        ensure(&mut self.x, n, d);
        fill_normal(&mut self.x, rng);
        for j in 0..d {
            for v in self.x.col_as_slice_mut(j) {
                *v *= sigma;
            }
        }
    }

    /// Sets the per-row levels `t` and `u` to constants for `n` rows.
    pub(crate) fn set_levels(&mut self, n: usize, t: f32, u: f32) {
        self.t.clear();
        self.t.resize(n, t);
        self.u.clear();
        self.u.resize(n, u);
    }
}

/// A distilled network as a [`Policy`]: the teacher's normalisers around the method's
/// sampler — raw observations in, raw actions out, one network evaluation per sampling step.
/// Used as [`crate::cd::ConsistencyModel`] and [`crate::ctm::TrajectoryModel`], which add the
/// method's own functions (the consistency function; the jump and the denoiser); see
/// [`crate::cd::CdTrainer`] for an example.
#[derive(Debug, Clone)]
pub struct DistilledPolicy<P> {
    pub(crate) net: ConditionedNet,
    pub(crate) pre: P,
    sigma_min: f32,
    sigma_max: f32,
    rho: f32,
    /// `σ_max = l_0 > … > l_k = σ_min`.
    levels: Vec<f32>,
    state_norm: Affine,
    action_norm: Affine,
    rng: vdd_core::Rng,
    stream: &'static str,
    obs: Mat<f32>,
    act: Mat<f32>,
    pub(crate) scratch: SampleScratch,
}

impl<P: Sampling> DistilledPolicy<P> {
    /// Assembles a policy; `config` gives the levels and the sampling steps.
    fn new(
        net: ConditionedNet,
        pre: P,
        config: &ConsistencyConfig,
        (state_norm, action_norm): (Affine, Affine),
        seed: u64,
        stream: &'static str,
    ) -> Result<Self, BaselineError> {
        check_len("network noise conditions", net.levels(), P::LEVELS)?;
        check_len("state normaliser", state_norm.dim(), net.state_dim())?;
        check_len("action normaliser", action_norm.dim(), net.action_dim())?;
        let mut policy = Self {
            net,
            pre,
            sigma_min: config.sigma_min,
            sigma_max: config.sigma_max,
            rho: config.rho,
            levels: Vec::new(),
            state_norm,
            action_norm,
            rng: Seeds::new(seed).stream(stream),
            stream,
            obs: Mat::zeros(0, 0),
            act: Mat::zeros(0, 0),
            scratch: SampleScratch::default(),
        };
        policy.set_sampling_steps(config.sampling_steps)?;
        Ok(policy)
    }

    /// The network `F`.
    pub fn net(&self) -> &ConditionedNet {
        &self.net
    }

    /// The preconditioning.
    pub fn preconditioning(&self) -> P {
        self.pre
    }

    /// The `(state, action)` normalisers (the teacher's).
    pub fn normalizers(&self) -> (&Affine, &Affine) {
        (&self.state_norm, &self.action_norm)
    }

    /// The sampling levels `σ_max = l_0 > … > l_k = σ_min` (`k` network evaluations per
    /// action).
    pub fn sampling_levels(&self) -> &[f32] {
        &self.levels
    }

    /// Sets `k ≥ 1` sampling steps along a `(k + 1)`-level Karras grid from `σ_max` to
    /// `σ_min`.
    pub fn set_sampling_steps(&mut self, steps: usize) -> Result<(), BaselineError> {
        if steps == 0 {
            return Err(CoreError::Config("sampling steps must be >= 1".into()).into());
        }
        self.levels = karras_levels(steps + 1, self.sigma_min, self.sigma_max, self.rho)?;
        Ok(())
    }

    /// Sets explicit sampling levels: strictly decreasing, all above `σ_min` (which is
    /// appended as the last level).
    pub fn set_sampling_levels(&mut self, levels: &[f32]) -> Result<(), BaselineError> {
        let ok = !levels.is_empty()
            && levels.iter().all(|s| s.is_finite() && *s > self.sigma_min)
            && levels.windows(2).all(|w| w[1] < w[0]);
        if !ok {
            return Err(CoreError::Config(format!(
                "sampling levels must be finite, above sigma_min = {} and strictly decreasing, \
                 got {levels:?}",
                self.sigma_min
            ))
            .into());
        }
        self.levels.clear();
        self.levels.extend_from_slice(levels);
        self.levels.push(self.sigma_min);
        Ok(())
    }

    /// Checks normalised model inputs: `x` `n x d_a` and `states` `n x d_s` finite, `out`
    /// `n x d_a`, and positive finite levels of length `n`.
    pub(crate) fn check_model_batch(
        &self,
        x: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        levels: &[&[f32]],
        out: MatRef<'_, f32>,
    ) -> Result<(), CoreError> {
        let n = x.nrows();
        check_shape("x", x, n, self.net.action_dim())?;
        check_shape("states", states, n, self.net.state_dim())?;
        check_shape("output", out, n, self.net.action_dim())?;
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

    /// Samples one action per row of normalised `states` into `out` (normalised space) with
    /// the configured steps, drawing noise from `rng`.
    pub fn sample(
        &mut self,
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let n = states.nrows();
        check_shape("states", states, n, self.net.state_dim())?;
        check_finite("states", states)?;
        check_shape("sampled actions", out.rb(), n, self.net.action_dim())?;
        let Self { net, pre, levels, scratch, .. } = self;
        sample_along(pre, net, levels, scratch, states, rng, out.rb_mut());
        Ok(())
    }

    /// `out = skip · x + out · F(c_in · x, states, …)` with the coefficients that
    /// `coefficients(pre, coef)` writes, for inputs that [`DistilledPolicy::check_model_batch`]
    /// accepted.
    pub(crate) fn forward_with(
        &mut self,
        x: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
        coefficients: impl FnOnce(&P, &mut Coefficients),
    ) {
        let Self { net, pre, scratch, .. } = self;
        coefficients(pre, &mut scratch.coef);
        net.forward_preconditioned(x, states, &scratch.coef, out);
    }
}

impl<P: Sampling> Policy for DistilledPolicy<P> {
    fn obs_dim(&self) -> usize {
        self.state_norm.dim()
    }

    fn action_dim(&self) -> usize {
        self.action_norm.dim()
    }

    fn seed(&mut self, seed: u64) {
        self.rng = Seeds::new(seed).stream(self.stream);
    }

    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> Result<(), CoreError> {
        check_act_args(self, obs, action)?;
        let (ds, da) = (self.obs_dim(), self.action_dim());
        self.act_batch(
            MatRef::from_row_major_slice(obs, 1, ds),
            MatMut::from_row_major_slice_mut(action, 1, da),
        )
    }

    /// Normalises the observations, samples, denormalises the actions.
    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        mut actions: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let (n, ds, da) = (obs.nrows(), self.obs_dim(), self.action_dim());
        check_shape("observations", obs, n, ds)?;
        check_finite("observations", obs)?;
        check_shape("actions", actions.rb(), n, da)?;
        ensure(&mut self.obs, n, ds);
        ensure(&mut self.act, n, da);
        for j in 0..ds {
            let (o, s) = (self.state_norm.offset[j], self.state_norm.scale[j]);
            let dst = self.obs.col_as_slice_mut(j);
            for i in 0..n {
                dst[i] = (obs[(i, j)] - o) / s;
            }
        }
        let Self { net, pre, levels, scratch, rng, obs, act, .. } = self;
        sample_along(pre, net, levels, scratch, obs.as_ref(), rng, act.as_mut());
        for j in 0..da {
            let (o, s) = (self.action_norm.offset[j], self.action_norm.scale[j]);
            let src = self.act.col_as_slice(j);
            for i in 0..n {
                actions[(i, j)] = src[i] * s + o;
            }
        }
        Ok(())
    }
}
