//! The training run Consistency Distillation ([`crate::cd`]) and the Consistency Trajectory
//! Model ([`crate::ctm`]) share: [`ConsistencyTrainer`] holds the shared state
//! ([`Distillation`]: teacher, normalised data, Karras grid, online and target networks,
//! optimiser, random streams) and the loop; each method supplies an [`Objective`] (what to
//! draw, the loss and its gradient). The traits and the state are reachable inside the crate
//! only (the public generic trainer is used through the aliases `CdTrainer` and `CtmTrainer`).

use std::time::Instant;

use faer::{Mat, MatMut, MatRef};
use rand::Rng as _;
use vdd_core::{CoreError, Seeds, Snapshot, Trainer, check_finite, check_len};
use vdd_diffusion::{DenoiserNet, DiffusionError, SamplerBuffers};
use vdd_nn::{Adam, Ema, Parameters};

use crate::config::{
    ConsistencyConfig, ConsistencyProgress, ConsistencyStep, ConsistencyTrainConfig,
};
use crate::error::ConsistencyError;
use crate::network::{ensure, fill_normal, network_from_teacher};
use crate::policy::{DistilledPolicy, Sampling, karras_levels};
use crate::teacher::ConsistencyTeacher;

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
    /// Names the loss in [`ConsistencyError::NonFinite`].
    const QUANTITY: &'static str;
    /// Name of the random stream of the returned policy.
    const POLICY_STREAM: &'static str;
    /// Name of the random stream of the training draws (levels and noise).
    const NOISE_STREAM: &'static str;

    /// Checks `config` and sets up the method's part of a run (its buffers start empty).
    fn new(config: Self::Config) -> Result<Self, ConsistencyError>;

    /// The configuration.
    fn config(&self) -> &Self::Config;

    /// The settings shared with every consistency method.
    fn base(&self) -> &ConsistencyConfig;

    /// The sampler of the returned policy.
    fn sampler(&self) -> Self::Sampler;

    /// Draws a minibatch and everything of the loss that does not depend on `θ` (teacher
    /// steps, target-network outputs).
    fn draw(&mut self, core: &mut Distillation<T>) -> Result<(), ConsistencyError>;

    /// The loss of the drawn batch; with `backward`, its gradient accumulated into
    /// `core.online`'s parameters.
    fn loss(&mut self, core: &mut Distillation<T>, backward: bool) -> LossTerms;
}

/// A consistency-distillation run of a [`ConsistencyTeacher`]: used as [`crate::CdTrainer`]
/// (Consistency Distillation) and [`crate::CtmTrainer`] (Consistency Trajectory Model), whose
/// docs have examples. A [`Trainer`] whose report is one [`ConsistencyStep`] per optimisation
/// step and whose output is the distilled policy ([`ConsistencyTrainer::model`]).
pub struct ConsistencyTrainer<T, O> {
    pub(crate) core: Distillation<T>,
    pub(crate) objective: O,
}

impl<T: ConsistencyTeacher, O: Objective<T>> std::fmt::Debug for ConsistencyTrainer<T, O> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("ConsistencyTrainer")
            .field("config", self.objective.config())
            .field("steps_done", &self.core.steps_done)
            .field("data_len", &self.core.data.states.nrows())
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
    ) -> Result<Self, ConsistencyError> {
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

    /// The training data `(states, actions)`, normalised with the teacher's normalisers.
    pub fn data(&self) -> (MatRef<'_, f32>, MatRef<'_, f32>) {
        (self.core.data.states.as_ref(), self.core.data.actions.as_ref())
    }

    /// The teacher.
    pub fn teacher(&self) -> &T {
        &self.core.teacher
    }

    /// Runs the remaining configured steps, calling `progress` every `log_every` steps and
    /// after the last (means over the steps since the previous report, and the wall-clock
    /// time), and returns the distilled policy ([`ConsistencyTrainer::model`]). One step at a
    /// time, with its own report, is [`Trainer::step`].
    pub fn train(
        &mut self,
        progress: &mut dyn FnMut(&ConsistencyProgress),
    ) -> Result<DistilledPolicy<O::Sampler>, ConsistencyError> {
        self.core.run(&mut self.objective, progress)?;
        self.model()
    }

    /// The current student as a policy: evaluation-averaged weights, the configured sampling
    /// steps, the teacher's normalisers, its random stream seeded with the training seed.
    pub fn model(&self) -> Result<DistilledPolicy<O::Sampler>, ConsistencyError> {
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

impl<T: ConsistencyTeacher, O: Objective<T>> Trainer for ConsistencyTrainer<T, O> {
    type Report = ConsistencyStep;
    type Output = DistilledPolicy<O::Sampler>;
    type Error = ConsistencyError;

    /// One optimisation step; reports the loss terms before the update. Nothing is updated
    /// when the loss or a gradient is not finite.
    fn step(&mut self) -> Result<ConsistencyStep, ConsistencyError> {
        self.core.step(&mut self.objective)
    }

    fn iteration(&self) -> usize {
        self.core.steps_done as usize
    }

    fn iterations(&self) -> usize {
        self.core.train.steps as usize
    }

    /// The distilled policy ([`ConsistencyTrainer::model`]).
    fn finish(self) -> Result<Self::Output, ConsistencyError> {
        self.model()
    }
}

/// The current student ([`ConsistencyTrainer::model`]).
impl<T: ConsistencyTeacher, O: Objective<T>> Snapshot for ConsistencyTrainer<T, O> {
    fn snapshot(&self) -> Result<Self::Output, ConsistencyError> {
        self.model()
    }
}

/// The state of a consistency-distillation run.
pub struct Distillation<T> {
    pub(crate) teacher: T,
    pub(crate) data: Pairs,
    /// The Karras grid `σ_0 = σ_max > … > σ_{N−1} = σ_min`.
    pub(crate) grid: Vec<f32>,
    pub(crate) online: DenoiserNet,
    pub(crate) target: DenoiserNet,
    pub(crate) noise_rng: vdd_core::Rng,
    batch_rng: vdd_core::Rng,
    pub(crate) steps_done: u64,
    /// The current minibatch (normalised).
    pub(crate) batch: Batch,
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
    ) -> Result<Self, ConsistencyError> {
        config.validate()?;
        teacher.validate()?;
        let data = normalised_data(&teacher, states, actions)?;
        let online = initial_network(&teacher, config, levels)?;
        let seeds = Seeds::new(config.train.seed);
        Ok(Self {
            grid: karras_levels(config.num_scales, config.sigma_min, config.sigma_max, config.rho)?,
            opt: Optimisation::new(&config.train, &online)?,
            target: online.clone(),
            online,
            data,
            teacher,
            noise_rng: seeds.stream(noise_stream),
            batch_rng: seeds.stream("minibatch"),
            steps_done: 0,
            batch: Batch::default(),
            heun: SamplerBuffers::default(),
            train: config.train.clone(),
        })
    }

    /// Draws the next minibatch of `batch_size` rows (uniform, with replacement).
    pub(crate) fn draw_batch(&mut self) {
        self.batch.draw(&self.data, &mut self.batch_rng, self.train.batch_size);
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
    ) -> Result<(), ConsistencyError> {
        let Self { teacher, batch, heun, .. } = self;
        let states = batch.states.as_ref();
        let mut denoise = |x: MatRef<'_, f32>, s: &[f32], o: MatMut<'_, f32>| {
            teacher.denoise(x, s, states, o).map_err(DiffusionError::from)
        };
        Ok(vdd_diffusion::heun_step(&mut denoise, x, sigma_from, sigma_to, out, heun)?)
    }

    /// One optimisation step of `objective`; reports the loss terms before the update and the
    /// learning rate. Nothing is updated when the loss or a gradient is not finite.
    pub(crate) fn step<O: Objective<T>>(
        &mut self,
        objective: &mut O,
    ) -> Result<ConsistencyStep, ConsistencyError> {
        objective.draw(self)?;
        self.online.zero_grad();
        let loss = objective.loss(self, true);
        let iteration = self.steps_done as usize;
        if !loss.total.is_finite() {
            return Err(ConsistencyError::NonFinite { iteration, quantity: O::QUANTITY });
        }
        vdd_nn::clip_grad_norm_checked(&mut self.online, self.train.grad_clip)
            .map_err(|_| ConsistencyError::NonFinite { iteration, quantity: O::QUANTITY })?;
        let lr = self.opt.apply(&mut self.online, &mut self.target, self.steps_done)?;
        let step = self.steps_done;
        self.steps_done += 1;
        Ok(ConsistencyStep {
            step,
            loss: loss.total,
            consistency_loss: loss.consistency,
            dsm_loss: loss.dsm,
            lr,
        })
    }

    /// Runs the remaining configured steps, calling `progress` every `log_every` steps and
    /// after the last.
    pub(crate) fn run<O: Objective<T>>(
        &mut self,
        objective: &mut O,
        progress: &mut dyn FnMut(&ConsistencyProgress),
    ) -> Result<(), ConsistencyError> {
        let start = Instant::now();
        let total = self.train.steps;
        let mut meter = LossMeter::default();
        while self.steps_done < total {
            let report = self.step(objective)?;
            meter.add(&report);
            let done = self.steps_done;
            if done % self.train.log_every == 0 || done == total {
                progress(&meter.report(done, total, report.lr, start.elapsed().as_secs_f64()));
            }
        }
        Ok(())
    }

    /// A copy of the online network carrying the evaluation average of its weights.
    pub(crate) fn averaged(&self) -> Result<DenoiserNet, ConsistencyError> {
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
        online: &DenoiserNet,
    ) -> Result<Self, ConsistencyError> {
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
        online: &mut DenoiserNet,
        target: &mut DenoiserNet,
        step: u64,
    ) -> Result<f32, ConsistencyError> {
        let progress = (step as f32 / self.steps.max(1) as f32).min(1.0);
        let cosine = 0.5 * (1.0 + (std::f32::consts::PI * progress).cos());
        let factor = self.final_lr_factor + (1.0 - self.final_lr_factor) * cosine;
        self.adam.step(online, factor)?;
        self.target_ema.update(online)?;
        self.target_ema.copy_to(target)?;
        self.eval_ema.update(online)?;
        Ok(self.base_lr * factor)
    }
}

/// Accumulates the loss terms of [`Trainer::step`] reports between progress reports (what
/// [`ConsistencyTrainer::train`] reports, for loops that step the trainer themselves).
///
/// ```
/// use vdd_consistency::{ConsistencyStep, LossMeter};
/// let mut m = LossMeter::default();
/// for loss in [1.0, 3.0] {
///     m.add(&ConsistencyStep { step: 0, loss, consistency_loss: loss, dsm_loss: 0.0, lr: 0.1 });
/// }
/// let p = m.report(2, 10, 0.1, 0.5);
/// assert_eq!((p.loss, p.step, p.total_steps), (2.0, 2, 10));
/// assert_eq!(m.report(2, 10, 0.1, 0.5).loss, 0.0, "reset after a report");
/// ```
#[derive(Debug, Clone, Default)]
pub struct LossMeter {
    total: f64,
    consistency: f64,
    dsm: f64,
    count: u64,
}

impl LossMeter {
    /// Adds one step's loss terms.
    pub fn add(&mut self, step: &ConsistencyStep) {
        self.total += f64::from(step.loss);
        self.consistency += f64::from(step.consistency_loss);
        self.dsm += f64::from(step.dsm_loss);
        self.count += 1;
    }

    /// The report for `step` of `total_steps` (means since the last report), resetting the
    /// averages.
    pub fn report(
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

/// The training pairs, one row each, normalised with the teacher's normalisers.
#[derive(Debug, Clone)]
pub(crate) struct Pairs {
    /// `n x d_s`.
    pub(crate) states: Mat<f32>,
    /// `n x d_a`.
    pub(crate) actions: Mat<f32>,
}

/// A minibatch: the drawn row indices and the gathered states and actions.
#[derive(Debug, Clone)]
pub(crate) struct Batch {
    idx: Vec<usize>,
    /// The rows' states.
    pub(crate) states: Mat<f32>,
    /// The rows' actions.
    pub(crate) actions: Mat<f32>,
}

impl Default for Batch {
    fn default() -> Self {
        Self { idx: Vec::new(), states: Mat::zeros(0, 0), actions: Mat::zeros(0, 0) }
    }
}

impl Batch {
    /// Replaces the batch with `size` rows of `data` drawn uniformly with replacement from
    /// `rng` and gathers their states and actions.
    fn draw(&mut self, data: &Pairs, rng: &mut vdd_core::Rng, size: usize) {
        let n = data.states.nrows();
        self.idx.clear();
        self.idx.extend((0..size).map(|_| rng.random_range(0..n)));
        gather_rows(data.states.as_ref(), &self.idx, &mut self.states);
        gather_rows(data.actions.as_ref(), &self.idx, &mut self.actions);
    }
}

/// Copies rows `idx` of `src` into `dst` (resized to `idx.len() x src.ncols()` if needed).
fn gather_rows(src: MatRef<'_, f32>, idx: &[usize], dst: &mut Mat<f32>) {
    ensure(dst, idx.len(), src.ncols());
    for j in 0..src.ncols() {
        let col = dst.col_as_slice_mut(j);
        for (b, &i) in idx.iter().enumerate() {
            col[b] = src[(i, j)];
        }
    }
}

/// Validates raw `states`/`actions` against the teacher and normalises them with its
/// normalisers.
fn normalised_data<T: ConsistencyTeacher + ?Sized>(
    teacher: &T,
    states: MatRef<'_, f32>,
    actions: MatRef<'_, f32>,
) -> Result<Pairs, CoreError> {
    let (sn, an) = teacher.normalizers();
    check_len("teacher state normaliser", sn.dim(), teacher.state_dim())?;
    check_len("teacher action normaliser", an.dim(), teacher.action_dim())?;
    check_len("data state columns vs teacher state_dim", states.ncols(), teacher.state_dim())?;
    check_len("data action columns vs teacher action_dim", actions.ncols(), teacher.action_dim())?;
    if states.nrows() == 0 {
        return Err(CoreError::Config("distillation needs at least one state-action pair".into()));
    }
    if states.ncols() == 0 || actions.ncols() == 0 {
        return Err(CoreError::Config("state and action dimensions must be positive".into()));
    }
    check_len("action rows vs state rows", actions.nrows(), states.nrows())?;
    check_finite("training states", states)?;
    check_finite("training actions", actions)?;
    let data = Pairs { states: sn.normalize_rows(states)?, actions: an.normalize_rows(actions)? };
    check_finite("normalised training states", data.states.as_ref())?;
    check_finite("normalised training actions", data.actions.as_ref())?;
    Ok(data)
}

/// The student's initial weights: the teacher's network when asked (it must exist and match),
/// or a fresh network from the seed's `"init"` stream.
fn initial_network<T: ConsistencyTeacher + ?Sized>(
    teacher: &T,
    config: &ConsistencyConfig,
    levels: usize,
) -> Result<DenoiserNet, ConsistencyError> {
    if !config.init_from_teacher {
        return Ok(DenoiserNet::with_levels(
            &config.net,
            teacher.action_dim(),
            teacher.state_dim(),
            levels,
            &mut Seeds::new(config.train.seed).stream("init"),
        )?);
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
    network_from_teacher(net, levels)
}
