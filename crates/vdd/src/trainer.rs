//! The EM loop: E-step snapshot, expert step, gating step; checkpoints and resume.

use faer::{Mat, MatRef};
use rand::Rng as _;
use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Expert, ScoreModel, Seeds, Snapshot, Trainer, check_finite, check_len};
use vdd_moe::step::clip_or_fail;
use vdd_moe::{ExpertFamily, Moe, MoeConfig, MoeOutput};
use vdd_nn::parallel::Workers;
use vdd_nn::{Adam, Ema, Parameters};

use crate::both_sides::BothSides;
use crate::config::{ExpertWeighting, ScoreAt, VddConfig};
use crate::error::VddError;
use crate::expert_step::{
    ExpertStepBuffers, ExpertStepStats, draw_sample_noise, moments_from_noise, raw_gradients,
};
pub use convergence::{
    CONVERGED_MISMATCH, Convergence, LATE_SHARE, PROBE_ACTIONS, PROBE_STATES, PROBES, RISE,
    probe_points,
};
pub use resumable::{Resumable, ResumableOutcome, Selected};

use crate::spaces::{ActionMap, TeacherSpace, normalize_rows, same_map, with_map};
use subset::expert_subset;

/// The states to distil on, optionally the dataset's actions for the gating step, both in the
/// raw (environment) space, and the space the teacher works in ([`TeacherSpace`]; see
/// [`crate::spaces`]).
///
/// The trainer maps the data into the student's space with the student's normalisers, and
/// queries the teacher in its own space: a teacher written for raw actions and a student that
/// normalises its actions agree without further ado.
#[derive(Debug, Clone)]
pub struct DistillData {
    pub(crate) states: Mat<f32>,
    pub(crate) actions: Option<Mat<f32>>,
    /// (State, action) pairs of the gating step, when given apart from the states.
    pub(crate) gating: Option<(Mat<f32>, Mat<f32>)>,
    pub(crate) teacher_space: TeacherSpace,
}

impl DistillData {
    /// States only: the gating step then trains on teacher samples
    /// ([`ScoreModel::sample_actions`]).
    pub fn from_states(states: Mat<f32>) -> Result<Self, CoreError> {
        Self::new(states, None)
    }

    /// States with their dataset actions (row `i` of each belongs together).
    pub fn new(states: Mat<f32>, actions: Option<Mat<f32>>) -> Result<Self, CoreError> {
        if states.nrows() == 0 || states.ncols() == 0 {
            return Err(CoreError::Config("distillation needs at least one state".into()));
        }
        check_finite("states", states.as_ref())?;
        if let Some(a) = &actions {
            check_len("dataset actions (rows)", a.nrows(), states.nrows())?;
            check_finite("dataset actions", a.as_ref())?;
        }
        Ok(Self { states, actions, gating: None, teacher_space: TeacherSpace::raw() })
    }

    /// Gives the gating step its own raw (state, action) pairs (row `i` of each belongs
    /// together), used instead of the dataset's actions or the teacher's samples: e.g. many
    /// actions drawn once from a teacher that cannot sample during training, several per state
    /// ([`crate::AutoPlan::gating_pairs`]). The expert step still draws from the data's states.
    ///
    /// ```
    /// use vdd::DistillData;
    /// use vdd::faer::Mat;
    /// let data = DistillData::from_states(Mat::zeros(4, 1))?
    ///     .with_gating_pairs(Mat::zeros(64, 1), Mat::from_fn(64, 2, |i, _| i as f32))?;
    /// assert_eq!(data.gating_pairs().map(|(s, a)| (s.nrows(), a.ncols())), Some((64, 2)));
    /// assert!(DistillData::from_states(Mat::zeros(4, 1))?
    ///     .with_gating_pairs(Mat::zeros(3, 1), Mat::zeros(2, 2))
    ///     .is_err());
    /// # Ok::<(), vdd::CoreError>(())
    /// ```
    pub fn with_gating_pairs(
        mut self,
        states: Mat<f32>,
        actions: Mat<f32>,
    ) -> Result<Self, CoreError> {
        if states.nrows() == 0 {
            return Err(CoreError::Config("gating pairs need at least one pair".into()));
        }
        check_len("gating pair states (columns)", states.ncols(), self.states.ncols())?;
        check_len("gating pair actions (rows)", actions.nrows(), states.nrows())?;
        check_finite("gating pair states", states.as_ref())?;
        check_finite("gating pair actions", actions.as_ref())?;
        self.gating = Some((states, actions));
        Ok(self)
    }

    /// The gating step's own pairs ([`DistillData::with_gating_pairs`]), if given.
    pub fn gating_pairs(&self) -> Option<(MatRef<'_, f32>, MatRef<'_, f32>)> {
        self.gating.as_ref().map(|(s, a)| (s.as_ref(), a.as_ref()))
    }

    /// Declares the space the teacher takes states and actions in (default: the raw space).
    pub fn with_teacher_space(mut self, space: TeacherSpace) -> Self {
        self.teacher_space = space;
        self
    }

    /// The raw states.
    pub fn states(&self) -> MatRef<'_, f32> {
        self.states.as_ref()
    }

    /// The raw dataset actions, if given.
    pub fn actions(&self) -> Option<MatRef<'_, f32>> {
        self.actions.as_ref().map(|a| a.as_ref())
    }

    /// The space the teacher works in.
    pub fn teacher_space(&self) -> &TeacherSpace {
        &self.teacher_space
    }
}

/// What one iteration did; passed to the training callback.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct IterationMetrics {
    /// 0-based iteration index.
    pub iteration: usize,
    /// Statistics of the last expert step.
    pub expert: ExpertStepStats,
    /// Soft cross-entropy of the gating towards the responsibilities (if it was trained).
    pub gating_loss: Option<f32>,
    /// Mean entropy of `q(z|s)` over the state batch, in nats.
    pub gating_entropy: f32,
    /// Experts' learning rate used.
    pub expert_lr: f32,
    /// Gating learning rate used (0 when not trained).
    pub gating_lr: f32,
    /// The student's score mismatch with the teacher after this iteration, at the eighths of
    /// the run where it is measured ([`Convergence`]; `None` elsewhere).
    #[serde(default)]
    pub score_mismatch: Option<f32>,
    /// On the run's last iteration: whether it converged ([`Vdd::convergence`]); `None` on
    /// every other iteration (and when a resumed run lacks the measurement it needs).
    #[serde(default)]
    pub converged: Option<bool>,
}

/// Variational Diffusion Distillation of a teacher `S` into a mixture of experts of family `E`.
///
/// The teacher is anything that implements [`ScoreModel`]; the trainer never needs more than
/// its score. Here a user-defined teacher, the score of `N((1, 1), 0.5² I)`, is distilled into
/// two experts; switching to full-covariance experts is the one config value `expert_kind`.
///
/// ```
/// use vdd::faer::{Mat, MatMut, MatRef};
/// use vdd::{check_score_args, CoreError, DistillData, ExpertKind, MoeConfig, ScoreModel, Vdd, VddConfig};
///
/// struct MyTeacher;
/// impl ScoreModel for MyTeacher {
///     fn action_dim(&self) -> usize { 2 }
///     fn state_dim(&self) -> usize { 1 }
///     fn score(&mut self, a: MatRef<'_, f32>, s: MatRef<'_, f32>, sigma: &[f32],
///              mut out: MatMut<'_, f32>) -> Result<(), CoreError> {
///         check_score_args(self, a, s, sigma, out.as_ref())?;
///         for i in 0..a.nrows() {
///             let var = 0.25 + sigma[i] * sigma[i]; // N(μ, 0.5²) smoothed by N(0, σ²)
///             for j in 0..2 {
///                 out[(i, j)] = -(a[(i, j)] - 1.0) / var;
///             }
///         }
///         Ok(())
///     }
/// }
///
/// for kind in [ExpertKind::Diagonal, ExpertKind::Full] {
///     let student = MoeConfig { expert_kind: kind, ..MoeConfig::toy(1, 2, 2) };
///     let data = DistillData::from_states(Mat::zeros(16, 1))?;
///     let config = VddConfig { iterations: 300, seed: 0, ..VddConfig::toy() };
///     // One seed for the run: the student is initialised from `config.seed` too.
///     let mut vdd = Vdd::from_config(config, MyTeacher, student, data)?;
///     vdd.train(|_metrics| {})?;
///     let student = vdd.into_student();
///     assert!((student.output().mean(0, 0)[0] - 1.0).abs() < 0.3);
/// }
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
pub struct Vdd<S: ScoreModel, E: Expert = ExpertFamily> {
    config: VddConfig,
    teacher: S,
    student: Moe<E>,
    data: DistillData,
    expert_optimizer: Adam,
    gating_optimizer: Adam,
    student_ema: Option<Ema>,
    iteration: usize,
    seeds: Seeds,
    buf: ExpertStepBuffers,
    /// The noising of the expert step's samples with [`crate::ScoreAt::NoisedSample`].
    both: BothSides,
    batch: Mat<f32>,
    snapshot: MoeOutput,
    weights: Vec<f32>,
    /// The experts each state of the current expert step trains
    /// ([`VddConfig::experts_per_state`]; empty when all do).
    subset: Vec<u32>,
    gating_states: Mat<f32>,
    gating_actions: Mat<f32>,
    grad_logits: Mat<f32>,
    resp: Vec<f32>,
    action: Vec<f32>,
    work: Vec<f32>,
    /// The data's states in the teacher's space, when it differs from the student's.
    teacher_states: Option<Mat<f32>>,
    /// The student → teacher action map, when not the identity.
    action_map: Option<ActionMap>,
    /// Per state dimension, the teacher's units per student unit (with `teacher_states`), so
    /// that perturbed states ([`VddConfig::state_noise`]) move alike in both spaces.
    state_ratio: Vec<f32>,
    /// The state batches in the teacher's space (with `teacher_states`).
    teacher_batch: Mat<f32>,
    teacher_gating_states: Mat<f32>,
    map_scratch: Vec<f32>,
    /// The state batch's chunks ([`VddConfig::chunks`]; empty for one chunk) and the threads
    /// they run on.
    chunks: Vec<chunks::Chunk<E>>,
    workers: Workers,
    flat: Vec<f32>,
    /// The convergence probe's measurements: (iterations done, score mismatch).
    probes: Vec<(usize, f32)>,
}

impl<S: ScoreModel> Vdd<S, ExpertFamily> {
    /// Sets up a run with a fresh student of configuration `student`, initialised from the
    /// run's seed ([`VddConfig::seed`]; the student draws from its own `"moe-init"` stream, so
    /// one seed determines the whole run).
    pub fn from_config(
        config: VddConfig,
        teacher: S,
        student: MoeConfig,
        data: DistillData,
    ) -> Result<Self, VddError> {
        let student = Moe::from_config(student, config.seed)?;
        Self::new(config, teacher, student, data)
    }
}

impl<S: ScoreModel, E: Expert> Vdd<S, E> {
    /// As [`Vdd::from_config`] with a custom expert family: the student is
    /// `Moe::new(student, expert, config.seed)`.
    pub fn with_family(
        config: VddConfig,
        teacher: S,
        student: MoeConfig,
        expert: E,
        data: DistillData,
    ) -> Result<Self, VddError> {
        let student = Moe::new(student, expert, config.seed)?;
        Self::new(config, teacher, student, data)
    }

    /// Sets up a run with a student built elsewhere (pretrained, or initialised with a seed of
    /// its own; [`Vdd::from_config`] initialises it from the run's seed). Checks that teacher,
    /// student and data agree on dimensions, and that the gating step has actions to learn
    /// from (gating pairs, dataset actions or a teacher that samples).
    ///
    /// The data are raw; the student's normalisers ([`Moe::normalizers`], as set now) map them
    /// into the student's space, and the data's [`TeacherSpace`] says what the teacher sees.
    pub fn new(
        config: VddConfig,
        mut teacher: S,
        student: Moe<E>,
        mut data: DistillData,
    ) -> Result<Self, VddError> {
        config.validate()?;
        let (unit, range) = (teacher.noise_convention(), teacher.noise_range());
        config.noise.check_teacher(config.noise_unit, unit, range)?;
        let mc = student.config();
        let (ds, d) = (mc.state_dim, mc.action_dim);
        check_len("teacher action_dim vs student", teacher.action_dim(), d)?;
        check_len("teacher state_dim vs student", teacher.state_dim(), ds)?;
        check_len("data state columns", data.states.ncols(), ds)?;
        if let Some(a) = &data.actions {
            check_len("data action columns", a.ncols(), d)?;
        }
        if let Some((_, a)) = &data.gating {
            check_len("gating pair action columns", a.ncols(), d)?;
        }
        // Spaces: the teacher's states from the raw ones, then the data into the student's.
        let space = data.teacher_space.clone();
        if let Some(m) = &space.states {
            check_len("teacher state map", m.dim(), ds)?;
        }
        if let Some(m) = &space.actions {
            check_len("teacher action map", m.dim(), d)?;
        }
        let (obs_norm, act_norm) = student.normalizers();
        let teacher_states = (!same_map(obs_norm, space.states.as_ref(), ds)).then(|| {
            let mut t = data.states.clone();
            if let Some(m) = &space.states {
                normalize_rows(&mut t, m);
            }
            t
        });
        let state_ratio: Vec<f32> = (0..ds)
            .map(|j| {
                let student = obs_norm.map_or(1.0, |m| m.scale[j]);
                student / space.states.as_ref().map_or(1.0, |m| m.scale[j])
            })
            .collect();
        let action_map = ActionMap::between(act_norm, space.actions.as_ref(), d)?;
        if let Some(m) = obs_norm {
            normalize_rows(&mut data.states, m);
            check_finite("states in the student's space", data.states.as_ref())?;
        }
        if let (Some(m), Some(a)) = (act_norm, data.actions.as_mut()) {
            normalize_rows(a, m);
            check_finite("dataset actions in the student's space", a.as_ref())?;
        }
        if let Some((s, a)) = data.gating.as_mut() {
            if let Some(m) = obs_norm {
                normalize_rows(s, m);
            }
            if let Some(m) = act_norm {
                normalize_rows(a, m);
            }
            check_finite("gating pairs in the student's space", s.as_ref())?;
            check_finite("gating pairs in the student's space", a.as_ref())?;
        }
        if let Some(t) = &teacher_states {
            check_finite("states in the teacher's space", t.as_ref())?;
        }
        if student.has_learned_gating() && data.actions.is_none() && data.gating.is_none() {
            let mut probe = Mat::zeros(1, mc.action_dim);
            let mut rng = Seeds::new(config.seed).stream("probe");
            let states = teacher_states.as_ref().unwrap_or(&data.states);
            teacher
                .sample_actions(states.as_ref().subrows(0, 1), &mut rng, probe.as_mut())
                .map_err(|source| VddError::NoGatingActions { source })?;
        }
        let z = mc.num_experts;
        let rows = config.batch_size * config.vi_samples;
        if rows.checked_mul(z).is_none_or(|r| r > crate::config::MAX_SAMPLES_PER_STEP) {
            return Err(CoreError::Config(format!(
                "batch_size · vi_samples · num_experts must be <= {}, got {rows} · {z}",
                crate::config::MAX_SAMPLES_PER_STEP
            ))
            .into());
        }
        let student_ema = config.student_ema.map(|decay| Ema::new(&student, decay)).transpose()?;
        let chunks = match config.chunks.min(config.batch_size) {
            1 => Vec::new(),
            c => (0..c).map(|_| chunks::Chunk::new(&student)).collect(),
        };
        Ok(Self {
            chunks,
            workers: Workers::default(),
            flat: Vec::new(),
            probes: Vec::new(),
            expert_optimizer: Adam::new(config.expert_optimizer),
            gating_optimizer: Adam::new(config.gating_optimizer),
            student_ema,
            iteration: 0,
            seeds: Seeds::new(config.seed),
            buf: ExpertStepBuffers::default(),
            both: BothSides::default(),
            batch: Mat::zeros(config.batch_size, mc.state_dim),
            snapshot: MoeOutput::default(),
            weights: vec![0.0; config.batch_size * z],
            subset: Vec::new(),
            gating_states: Mat::zeros(config.gating_batch_size, mc.state_dim),
            gating_actions: Mat::zeros(config.gating_batch_size, d),
            grad_logits: Mat::zeros(config.gating_batch_size, z),
            resp: vec![0.0; z],
            action: vec![0.0; d],
            work: vec![0.0; d],
            teacher_batch: Mat::zeros(
                if teacher_states.is_some() { config.batch_size } else { 0 },
                ds,
            ),
            teacher_gating_states: Mat::zeros(
                if teacher_states.is_some() { config.gating_batch_size } else { 0 },
                ds,
            ),
            teacher_states,
            state_ratio,
            action_map,
            map_scratch: Vec::new(),
            config,
            teacher,
            student,
            data,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &VddConfig {
        &self.config
    }

    /// Iterations done so far.
    pub fn iteration(&self) -> usize {
        self.iteration
    }

    /// The student being trained (the last iterate, not the average of
    /// [`VddConfig::student_ema`]).
    pub fn student(&self) -> &Moe<E> {
        &self.student
    }

    /// The student, mutably (e.g. to evaluate it between iterations).
    pub fn student_mut(&mut self) -> &mut Moe<E> {
        &mut self.student
    }

    /// The teacher. (The chunks' copies of it, [`VddConfig::chunks`], are made anew at the
    /// next step.)
    pub fn teacher_mut(&mut self) -> &mut S {
        self.chunks.iter_mut().for_each(chunks::Chunk::forget_teacher);
        &mut self.teacher
    }

    /// Runs the chunks of each step ([`VddConfig::chunks`]) on `threads` threads: 1 in the
    /// calling thread, more on a pool of that many threads of its own, 0 (the default) on the
    /// process-wide pool (`RAYON_NUM_THREADS` threads, default one per core), shared with the
    /// other trainings of the process. The student is the same whatever the count.
    pub fn set_threads(&mut self, threads: usize) -> Result<(), VddError> {
        self.workers = Workers::new(threads)?;
        Ok(())
    }

    /// Ends training and returns the student: the moving average of its parameters when
    /// [`VddConfig::student_ema`] is set, else the last iterate.
    pub fn into_student(mut self) -> Moe<E> {
        if let Some(ema) = &self.student_ema {
            ema.copy_to(&mut self.student).expect("the average was made from this student");
        }
        self.student
    }

    /// Runs the remaining iterations, calling `callback` after each ([`Trainer::run`]).
    pub fn train(&mut self, callback: impl FnMut(&IterationMetrics)) -> Result<(), VddError> {
        Trainer::run(self, callback)
    }

    /// One EM iteration: E-step snapshot, `expert_steps_per_iter` expert steps, then
    /// `gating_steps_per_iter` gating steps. On error nothing of this iteration is applied
    /// beyond the steps that already completed, and the iteration counter does not advance.
    pub fn step(&mut self) -> Result<IterationMetrics, VddError> {
        let it = self.iteration;
        let progress = self.config.noise_progress(it as f32 / self.config.iterations.max(1) as f32);

        // State minibatch.
        let mut rng = self.seeds.stream_indexed("state-batch", it as u64);
        let n_data = self.data.states.nrows();
        for b in 0..self.config.batch_size {
            let idx = rng.random_range(0..n_data);
            for j in 0..self.data.states.ncols() {
                self.batch[(b, j)] = self.data.states[(idx, j)];
            }
            if let Some(t) = &self.teacher_states {
                for j in 0..t.ncols() {
                    self.teacher_batch[(b, j)] = t[(idx, j)];
                }
            }
        }
        if let Some(noise) = self.config.state_noise.filter(|n| n.share > 0.0) {
            self.perturb_states(it, noise);
        }

        let (stats, gating_entropy, expert_lr) = match self.chunks.is_empty() {
            true => self.expert_steps(it, progress)?,
            false => self.chunked_expert_steps(it, progress)?,
        };

        // Gating steps.
        let mut gating_loss = None;
        let mut gating_lr = 0.0;
        let frozen = self.config.freeze_gating_after.is_some_and(|n| it >= n);
        if self.student.has_learned_gating() && !frozen {
            for k in 0..self.config.gating_steps_per_iter {
                let stream = (it * self.config.gating_steps_per_iter + k) as u64;
                let total = self.config.gating_steps();
                let factor =
                    self.config.gating_lr_schedule.factor(self.gating_optimizer.steps(), total);
                gating_lr = self.config.gating_optimizer.lr * factor;
                gating_loss = self.gating_step(it, stream, factor)?;
            }
        }

        if let Some(ema) = &mut self.student_ema {
            ema.update(&self.student)?;
        }
        let score_mismatch = self.probe_after(it + 1)?;
        self.iteration += 1;
        let converged = self.convergence().map(|c| c.converged);
        Ok(IterationMetrics {
            iteration: it,
            expert: stats,
            gating_loss,
            gating_entropy,
            expert_lr,
            gating_lr,
            score_mismatch,
            converged,
        })
    }

    /// The E-step snapshot and the expert steps of iteration `it` on the whole batch; returns
    /// the last step's statistics, the mean gating entropy and the last learning rate.
    fn expert_steps(
        &mut self,
        it: usize,
        progress: f32,
    ) -> Result<(ExpertStepStats, f32, f32), VddError> {
        // E-step: freeze a copy of the student on this batch.
        self.student.forward(self.batch.as_ref())?;
        self.snapshot.clone_from(self.student.output());
        let (log_gating, weighting) = (&self.snapshot.log_gating, self.config.expert_weighting);
        let z_n = self.student.num_experts();
        let entropy_sum = e_step_weights(log_gating, weighting, z_n, &mut self.weights);
        let gating_entropy = entropy_sum / self.config.batch_size as f32;

        // Expert steps.
        let mut stats = ExpertStepStats::default();
        let mut expert_lr = 0.0;
        for k in 0..self.config.expert_steps_per_iter {
            let stream = (it * self.config.expert_steps_per_iter + k) as u64;
            let mut rng = self.seeds.stream_indexed("vi-noise", stream);
            if k > 0 {
                self.student.forward_experts(self.batch.as_ref())?;
            }
            self.draw_subset(stream);
            let noised = self.draw_noise(progress, &mut rng).map_err(at_iteration(it))?;
            // The teacher sees the states (and, through the map, the actions) in its space.
            let states = match &self.teacher_states {
                Some(_) => self.teacher_batch.as_ref(),
                None => self.batch.as_ref(),
            };
            let (snapshot, v) = (&self.snapshot, self.config.vi_samples);
            let per_state = self.slots() * v;
            let d = self.student.config().action_dim;
            let both = noised.then(|| self.both.view(0..self.config.batch_size, per_state, d));
            let subset = expert_subset(&self.subset, self.slots());
            let (out, buf) = (self.student.output(), &mut self.buf);
            let map = self.action_map.as_ref();
            let sums = with_map(&mut self.teacher, map, &mut self.map_scratch, |teacher| {
                moments_from_noise(teacher, out, snapshot, states, v, both, subset, buf)
            });
            let pairs = self.config.batch_size * self.student.num_experts();
            stats = sums.map_err(at_iteration(it))?.stats(&self.buf.noise_levels, pairs);
            let (expert, out) = (self.student.expert(), self.student.output());
            raw_gradients(expert, out, &self.weights, subset, &mut self.buf);
            let nets = self.student.expert_networks_mut();
            nets.zero_grad();
            let grad_raw = std::mem::take(&mut self.buf.grad_raw);
            let r = self.student.backward_experts(&grad_raw);
            self.buf.grad_raw = grad_raw;
            r?;
            expert_lr = self.expert_update(it)?;
        }

        Ok((stats, gating_entropy, expert_lr))
    }

    /// Perturbs a share of the state batch ([`VddConfig::state_noise`]), from its own stream,
    /// in the student's space and by the same amount in the teacher's.
    fn perturb_states(&mut self, it: usize, noise: crate::config::StateNoise) {
        let mut rng = self.seeds.stream_indexed("state-noise", it as u64);
        for b in 0..self.config.batch_size {
            if rng.random::<f32>() >= noise.share {
                continue;
            }
            for j in 0..self.batch.ncols() {
                let delta = noise.std * vdd_core::standard_normal(&mut rng);
                self.batch[(b, j)] += delta;
                if self.teacher_states.is_some() {
                    self.teacher_batch[(b, j)] += delta * self.state_ratio[j];
                }
            }
        }
    }

    /// Draws the randomness of one expert step on the whole batch: `ε` and the noise levels
    /// into `self.buf` ([`draw_sample_noise`]), then, with noise on both sides, the noising
    /// into `self.both` ([`BothSides::prepare`]). Returns whether the samples are noised.
    fn draw_noise(
        &mut self,
        progress: f32,
        rng: &mut dyn rand::RngCore,
    ) -> Result<bool, CoreError> {
        let (b_n, k_n, v_n) = (self.config.batch_size, self.slots(), self.config.vi_samples);
        let d = self.student.config().action_dim;
        let noise = &self.config.noise;
        let (eps, levels) = (&mut self.buf.eps, &mut self.buf.noise_levels);
        draw_sample_noise(&self.teacher, noise, progress, rng, b_n * k_n * v_n, d, eps, levels);
        if self.config.score_at == ScoreAt::CleanSample {
            return Ok(false);
        }
        let map = self.action_map.as_ref();
        self.both.prepare(&self.teacher, map, levels, k_n * v_n, d, rng)?;
        Ok(true)
    }

    /// The experts' update after their gradient is in place: the gradient clipped (or the
    /// run stopped on a non-finite one), then one Adam step at the schedule's rate, which is
    /// returned.
    fn expert_update(&mut self, it: usize) -> Result<f32, VddError> {
        let nets = self.student.expert_networks_mut();
        clip_or_fail(nets, self.config.max_grad_norm, it, "expert gradient")?;
        let total = self.config.expert_steps();
        let factor = self.config.expert_lr_schedule.factor(self.expert_optimizer.steps(), total);
        self.expert_optimizer.step(nets, factor)?;
        Ok(self.config.expert_optimizer.lr * factor)
    }

    /// One gating step ([`vdd_moe::step::gating_step`] with learning-rate factor `factor`) on
    /// the soft cross-entropy `−mean Σ_z q̃(z|a,s) log q(z|s)` towards the current student's
    /// responsibilities of the data's gating pairs ([`DistillData::with_gating_pairs`]), else
    /// of dataset actions, else of teacher samples; returns the loss.
    fn gating_step(
        &mut self,
        it: usize,
        stream: u64,
        factor: f32,
    ) -> Result<Option<f32>, VddError> {
        let n = self.config.gating_batch_size;
        let mut rng = self.seeds.stream_indexed("gating-batch", stream);
        let n_data = self.data.states.nrows();
        let (ds, d) = (self.data.states.ncols(), self.student.config().action_dim);
        if let Some((states, actions)) = &self.data.gating {
            for b in 0..n {
                let i = rng.random_range(0..states.nrows());
                for j in 0..ds {
                    self.gating_states[(b, j)] = states[(i, j)];
                }
                for j in 0..d {
                    self.gating_actions[(b, j)] = actions[(i, j)];
                }
            }
            return self.gating_update(it, factor);
        }
        let mut idx = Vec::with_capacity(n);
        for b in 0..n {
            let i = rng.random_range(0..n_data);
            idx.push(i);
            for j in 0..ds {
                self.gating_states[(b, j)] = self.data.states[(i, j)];
            }
            if let Some(t) = &self.teacher_states {
                for j in 0..ds {
                    self.teacher_gating_states[(b, j)] = t[(i, j)];
                }
            }
        }
        match &self.data.actions {
            Some(actions) => {
                for (b, &i) in idx.iter().enumerate() {
                    for j in 0..d {
                        self.gating_actions[(b, j)] = actions[(i, j)];
                    }
                }
            }
            None => {
                let mut rng = self.seeds.stream_indexed("teacher-samples", stream);
                // Sampled in the teacher's space, returned in the student's.
                let states = match &self.teacher_states {
                    Some(_) => self.teacher_gating_states.as_ref(),
                    None => self.gating_states.as_ref(),
                };
                let (out, map) = (self.gating_actions.as_mut(), self.action_map.as_ref());
                with_map(&mut self.teacher, map, &mut self.map_scratch, |teacher| {
                    teacher.sample_actions(states, &mut rng, out)
                })?;
                check_finite("teacher samples", self.gating_actions.as_ref()).map_err(|_| {
                    VddError::NonFinite { iteration: it, quantity: "teacher samples" }
                })?;
            }
        }
        self.gating_update(it, factor)
    }

    /// The gating's update on the batch in `gating_states` and `gating_actions` (student's
    /// space); returns the loss.
    fn gating_update(&mut self, it: usize, factor: f32) -> Result<Option<f32>, VddError> {
        let n = self.config.gating_batch_size;
        let (actions, action, resp, work) =
            (&self.gating_actions, &mut self.action, &mut self.resp, &mut self.work);
        let loss = vdd_moe::step::gating_step(
            &mut self.student,
            self.gating_states.as_ref(),
            &mut self.gating_optimizer,
            factor,
            self.config.max_grad_norm,
            it,
            &mut self.grad_logits,
            |out, mut grad| {
                let mut loss = 0.0f64;
                for b in 0..n {
                    for (j, v) in action.iter_mut().enumerate() {
                        *v = actions[(b, j)];
                    }
                    out.log_density_and_responsibilities(b, action, resp, work);
                    let lg = out.log_gating_row(b);
                    for z in 0..out.num_experts {
                        loss -= f64::from(resp[z] * lg[z]);
                        grad[(b, z)] = (lg[z].exp() - resp[z]) / n as f32;
                    }
                }
                Ok(f64::from((loss / n as f64) as f32))
            },
        )?;
        Ok(loss.map(|l| l as f32))
    }
}

/// VDD as a [`Trainer`]: a step is one EM iteration ([`Vdd::step`]), and
/// [`Trainer::finish`] returns the student ([`Vdd::into_student`]).
impl<S: ScoreModel, E: Expert> Trainer for Vdd<S, E> {
    type Report = IterationMetrics;
    type Output = Moe<E>;
    type Error = VddError;

    fn step(&mut self) -> Result<IterationMetrics, VddError> {
        Vdd::step(self)
    }

    fn iteration(&self) -> usize {
        self.iteration
    }

    fn iterations(&self) -> usize {
        self.config.iterations
    }

    fn finish(mut self) -> Result<Moe<E>, VddError> {
        if let Some(ema) = &self.student_ema {
            ema.copy_to(&mut self.student)?;
        }
        Ok(self.student)
    }
}

/// The student [`Trainer::finish`] would return now (the moving average when
/// [`VddConfig::student_ema`] is set), as a copy.
impl<S: ScoreModel, E: Expert> Snapshot for Vdd<S, E> {
    fn snapshot(&self) -> Result<Moe<E>, VddError> {
        let mut student = self.student.clone();
        if let Some(ema) = &self.student_ema {
            ema.copy_to(&mut student)?;
        }
        Ok(student)
    }
}

/// The E-step's weights of the expert loss, one per (state, expert) of `log_gating` (the
/// snapshot's `log q(z|s)` of `z_n` experts, row-major), written to `weights`: `q(z|s)` for
/// [`ExpertWeighting::Gating`], `1/Z` for [`ExpertWeighting::Uniform`]. Returns the gating
/// entropy summed over the states, `−Σ q log q`.
pub(super) fn e_step_weights(
    log_gating: &[f32],
    weighting: ExpertWeighting,
    z_n: usize,
    weights: &mut Vec<f32>,
) -> f32 {
    weights.clear();
    weights.extend(log_gating.iter().map(|lg| match weighting {
        ExpertWeighting::Gating => lg.exp(),
        ExpertWeighting::Uniform => 1.0 / z_n as f32,
    }));
    -log_gating.iter().map(|l| l.exp() * l).sum::<f32>()
}

/// Names the iteration in a non-finite error of the expert step's moments.
pub(super) fn at_iteration(iteration: usize) -> impl Fn(CoreError) -> VddError {
    move |e| match e {
        CoreError::NonFinite { what } => VddError::NonFinite { iteration, quantity: what },
        other => other.into(),
    }
}

mod checkpoint;
mod chunks;
mod convergence;
mod resumable;
mod subset;
#[cfg(test)]
mod tests;
#[cfg(test)]
mod tests_checkpoint;
#[cfg(test)]
mod tests_chunks;
#[cfg(test)]
mod tests_spaces;
