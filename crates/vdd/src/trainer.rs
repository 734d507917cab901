//! The EM loop: E-step snapshot, expert step, gating step; checkpoints and resume.

use std::path::{Path, PathBuf};

use faer::{Mat, MatRef};
use rand::Rng as _;
use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Expert, ScoreModel, Seeds, check_finite, check_len};
use vdd_moe::step::clip_or_fail;
use vdd_moe::{ExpertFamily, Moe, MoeOutput};
use vdd_nn::{Adam, Ema, Parameters};

use crate::config::{ExpertWeighting, VddConfig};
use crate::error::VddError;
use crate::expert_step::{
    ExpertStepBuffers, ExpertStepStats, corrected_score_moments, raw_gradients,
};

/// The states to distil on, and optionally the dataset's actions for the gating step.
#[derive(Debug, Clone)]
pub struct DistillData {
    states: Mat<f32>,
    actions: Option<Mat<f32>>,
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
        Ok(Self { states, actions })
    }

    /// The states.
    pub fn states(&self) -> MatRef<'_, f32> {
        self.states.as_ref()
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
}

#[derive(Serialize, Deserialize)]
struct TrainerState {
    config: VddConfig,
    iteration: usize,
    expert_optimizer: Adam,
    gating_optimizer: Adam,
    #[serde(default)]
    student_ema: Option<Ema>,
}

/// Variational Diffusion Distillation of a teacher `S` into a mixture of experts of family `E`.
///
/// The teacher is anything that implements [`ScoreModel`]; the trainer never needs more than
/// its score. Here a user-defined teacher, the score of `N((1, 1), 0.5² I)`, is distilled into
/// two experts; switching to full-covariance experts is the one config value `expert_kind`.
///
/// ```
/// use faer::{Mat, MatMut, MatRef};
/// use vdd::{DistillData, Vdd, VddConfig};
/// use vdd_core::{check_score_args, CoreError, ScoreModel};
/// use vdd_moe::{ExpertKind, Moe, MoeConfig};
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
///     let student = Moe::from_config(MoeConfig { expert_kind: kind, ..MoeConfig::toy(1, 2, 2) }, 0)?;
///     let data = DistillData::from_states(Mat::zeros(16, 1))?;
///     let config = VddConfig { iterations: 300, ..VddConfig::toy() };
///     let mut vdd = Vdd::new(config, MyTeacher, student, data)?;
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
    batch: Mat<f32>,
    snapshot: MoeOutput,
    weights: Vec<f32>,
    gating_states: Mat<f32>,
    gating_actions: Mat<f32>,
    grad_logits: Mat<f32>,
    resp: Vec<f32>,
    action: Vec<f32>,
    work: Vec<f32>,
}

impl<S: ScoreModel, E: Expert> Vdd<S, E> {
    /// Sets up a run. Checks that teacher, student and data agree on dimensions, and that the
    /// gating step has actions to learn from (dataset actions or a teacher that samples).
    pub fn new(
        config: VddConfig,
        mut teacher: S,
        student: Moe<E>,
        data: DistillData,
    ) -> Result<Self, VddError> {
        config.validate()?;
        let mc = student.config();
        check_len("teacher action_dim vs student", teacher.action_dim(), mc.action_dim)?;
        check_len("teacher state_dim vs student", teacher.state_dim(), mc.state_dim)?;
        check_len("data state columns", data.states.ncols(), mc.state_dim)?;
        if let Some(a) = &data.actions {
            check_len("data action columns", a.ncols(), mc.action_dim)?;
        }
        if student.has_learned_gating() && data.actions.is_none() {
            let mut probe = Mat::zeros(1, mc.action_dim);
            let mut rng = Seeds::new(config.seed).stream("probe");
            teacher
                .sample_actions(data.states.as_ref().subrows(0, 1), &mut rng, probe.as_mut())
                .map_err(|e| {
                    CoreError::Config(format!(
                        "a learned gating needs dataset actions or a teacher that samples: {e}"
                    ))
                })?;
        }
        let (z, d) = (mc.num_experts, mc.action_dim);
        let student_ema = config.student_ema.map(|decay| Ema::new(&student, decay)).transpose()?;
        Ok(Self {
            expert_optimizer: Adam::new(config.expert_optimizer),
            gating_optimizer: Adam::new(config.gating_optimizer),
            student_ema,
            iteration: 0,
            seeds: Seeds::new(config.seed),
            buf: ExpertStepBuffers::default(),
            batch: Mat::zeros(config.batch_size, mc.state_dim),
            snapshot: MoeOutput::default(),
            weights: vec![0.0; config.batch_size * z],
            gating_states: Mat::zeros(config.gating_batch_size, mc.state_dim),
            gating_actions: Mat::zeros(config.gating_batch_size, d),
            grad_logits: Mat::zeros(config.gating_batch_size, z),
            resp: vec![0.0; z],
            action: vec![0.0; d],
            work: vec![0.0; d],
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

    /// The teacher.
    pub fn teacher_mut(&mut self) -> &mut S {
        &mut self.teacher
    }

    /// Ends training and returns the student: the moving average of its parameters when
    /// [`VddConfig::student_ema`] is set, else the last iterate.
    pub fn into_student(mut self) -> Moe<E> {
        if let Some(ema) = &self.student_ema {
            ema.copy_to(&mut self.student).expect("the average was made from this student");
        }
        self.student
    }

    /// Runs the remaining iterations, calling `callback` after each.
    pub fn train(&mut self, mut callback: impl FnMut(&IterationMetrics)) -> Result<(), VddError> {
        while self.iteration < self.config.iterations {
            let m = self.step()?;
            callback(&m);
        }
        Ok(())
    }

    /// One EM iteration: E-step snapshot, `expert_steps_per_iter` expert steps, then
    /// `gating_steps_per_iter` gating steps. On error nothing of this iteration is applied
    /// beyond the steps that already completed, and the iteration counter does not advance.
    pub fn step(&mut self) -> Result<IterationMetrics, VddError> {
        let it = self.iteration;
        let progress = it as f32 / self.config.iterations.max(1) as f32;

        // State minibatch.
        let mut rng = self.seeds.stream_indexed("state-batch", it as u64);
        let n_data = self.data.states.nrows();
        for b in 0..self.config.batch_size {
            let idx = rng.random_range(0..n_data);
            for j in 0..self.data.states.ncols() {
                self.batch[(b, j)] = self.data.states[(idx, j)];
            }
        }

        // E-step: freeze a copy of the student on this batch.
        self.student.forward(self.batch.as_ref())?;
        self.snapshot.clone_from(self.student.output());
        let z_n = self.student.num_experts();
        for (w, lg) in self.weights.iter_mut().zip(&self.snapshot.log_gating) {
            *w = match self.config.expert_weighting {
                ExpertWeighting::Gating => lg.exp(),
                ExpertWeighting::Uniform => 1.0 / z_n as f32,
            };
        }
        let gating_entropy = -self.snapshot.log_gating.iter().map(|l| l.exp() * l).sum::<f32>()
            / self.config.batch_size as f32;

        // Expert steps.
        let mut stats = ExpertStepStats::default();
        let mut expert_lr = 0.0;
        for k in 0..self.config.expert_steps_per_iter {
            let stream = (it * self.config.expert_steps_per_iter + k) as u64;
            let mut rng = self.seeds.stream_indexed("vi-noise", stream);
            if k > 0 {
                self.student.forward_experts(self.batch.as_ref())?;
            }
            stats = corrected_score_moments(
                &mut self.teacher,
                self.student.output(),
                &self.snapshot,
                self.batch.as_ref(),
                &self.config.noise,
                progress,
                self.config.vi_samples,
                &mut rng,
                &mut self.buf,
            )
            .map_err(|e| match e {
                CoreError::NonFinite { what } => {
                    VddError::NonFinite { iteration: it, quantity: what }
                }
                other => other.into(),
            })?;
            raw_gradients(
                self.student.expert(),
                self.student.output(),
                &self.weights,
                &mut self.buf,
            );
            let nets = self.student.expert_networks_mut();
            nets.zero_grad();
            let grad_raw = std::mem::take(&mut self.buf.grad_raw);
            let r = self.student.backward_experts(&grad_raw);
            self.buf.grad_raw = grad_raw;
            r?;
            let nets = self.student.expert_networks_mut();
            clip_or_fail(nets, self.config.max_grad_norm, it, "expert gradient")?;
            expert_lr = self.config.expert_optimizer.lr
                * self.config.expert_lr_schedule.factor(self.expert_optimizer.steps());
            let factor = self.config.expert_lr_schedule.factor(self.expert_optimizer.steps());
            self.expert_optimizer.step(nets, factor);
        }

        // Gating steps.
        let mut gating_loss = None;
        let mut gating_lr = 0.0;
        let frozen = self.config.freeze_gating_after.is_some_and(|n| it >= n);
        if self.student.has_learned_gating() && !frozen {
            for k in 0..self.config.gating_steps_per_iter {
                let stream = (it * self.config.gating_steps_per_iter + k) as u64;
                let factor = self.config.gating_lr_schedule.factor(self.gating_optimizer.steps());
                gating_lr = self.config.gating_optimizer.lr * factor;
                gating_loss = self.gating_step(it, stream, factor)?;
            }
        }

        if let Some(ema) = &mut self.student_ema {
            ema.update(&self.student)?;
        }
        self.iteration += 1;
        Ok(IterationMetrics {
            iteration: it,
            expert: stats,
            gating_loss,
            gating_entropy,
            expert_lr,
            gating_lr,
        })
    }

    /// One gating step ([`vdd_moe::step::gating_step`] with learning-rate factor `factor`) on
    /// the soft cross-entropy `−mean Σ_z q̃(z|a,s) log q(z|s)` towards the current student's
    /// responsibilities of dataset actions (or teacher samples); returns the loss.
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
        let mut idx = Vec::with_capacity(n);
        for b in 0..n {
            let i = rng.random_range(0..n_data);
            idx.push(i);
            for j in 0..ds {
                self.gating_states[(b, j)] = self.data.states[(i, j)];
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
                self.teacher.sample_actions(
                    self.gating_states.as_ref(),
                    &mut rng,
                    self.gating_actions.as_mut(),
                )?;
                check_finite("teacher samples", self.gating_actions.as_ref()).map_err(|_| {
                    VddError::NonFinite { iteration: it, quantity: "teacher samples" }
                })?;
            }
        }
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

    /// Writes a checkpoint directory (`student.safetensors` + `trainer.json`) atomically: the
    /// files go to a temporary sibling directory that replaces `dir` only when complete.
    pub fn save_checkpoint(&self, dir: &Path) -> Result<(), VddError> {
        let err = |reason: String| VddError::Checkpoint { path: dir.to_owned(), reason };
        let tmp = sibling(dir, "tmp");
        if tmp.exists() {
            std::fs::remove_dir_all(&tmp).map_err(|e| err(e.to_string()))?;
        }
        std::fs::create_dir_all(&tmp).map_err(|e| err(e.to_string()))?;
        self.student.save(&tmp.join("student.safetensors"))?;
        let state = TrainerState {
            config: self.config.clone(),
            iteration: self.iteration,
            expert_optimizer: self.expert_optimizer.clone(),
            gating_optimizer: self.gating_optimizer.clone(),
            student_ema: self.student_ema.clone(),
        };
        let json = serde_json::to_vec(&state).map_err(|e| err(e.to_string()))?;
        vdd_nn::io::write_atomic(&tmp.join("trainer.json"), &json)?;
        let old = sibling(dir, "old");
        if dir.exists() {
            if old.exists() {
                std::fs::remove_dir_all(&old).map_err(|e| err(e.to_string()))?;
            }
            std::fs::rename(dir, &old).map_err(|e| err(e.to_string()))?;
        }
        std::fs::rename(&tmp, dir).map_err(|e| err(e.to_string()))?;
        if old.exists() {
            std::fs::remove_dir_all(&old).map_err(|e| err(e.to_string()))?;
        }
        Ok(())
    }

    /// Resumes a run from [`Vdd::save_checkpoint`] with a custom expert family; continuing
    /// gives exactly the numbers of an uninterrupted run.
    pub fn resume_with_family(
        dir: &Path,
        teacher: S,
        expert: E,
        data: DistillData,
    ) -> Result<Self, VddError> {
        let student = Moe::load_with_family(&dir.join("student.safetensors"), expert)?;
        Self::resume_inner(dir, teacher, student, data)
    }

    fn resume_inner(
        dir: &Path,
        teacher: S,
        student: Moe<E>,
        data: DistillData,
    ) -> Result<Self, VddError> {
        let path = dir.join("trainer.json");
        let bytes = std::fs::read(&path)
            .map_err(|e| VddError::Checkpoint { path: path.clone(), reason: e.to_string() })?;
        let state: TrainerState = serde_json::from_slice(&bytes)
            .map_err(|e| VddError::Checkpoint { path, reason: e.to_string() })?;
        let mut vdd = Self::new(state.config, teacher, student, data)?;
        vdd.iteration = state.iteration;
        vdd.expert_optimizer = state.expert_optimizer;
        vdd.gating_optimizer = state.gating_optimizer;
        // A checkpoint written without an average starts one at the resumed student.
        vdd.student_ema = state.student_ema.or(vdd.student_ema);
        Ok(vdd)
    }
}

impl<S: ScoreModel> Vdd<S, ExpertFamily> {
    /// Resumes a run from [`Vdd::save_checkpoint`] (built-in expert families).
    pub fn resume(dir: &Path, teacher: S, data: DistillData) -> Result<Self, VddError> {
        let student = Moe::load(&dir.join("student.safetensors"))?;
        Self::resume_inner(dir, teacher, student, data)
    }
}

fn sibling(dir: &Path, tag: &str) -> PathBuf {
    let name = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
    dir.with_file_name(format!(".{name}.{tag}"))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::eval::{modes_covered, reverse_kl};
    use crate::test_support::IsoGmm;
    use faer::MatMut;
    use vdd_core::NoiseSchedule;
    use vdd_moe::{GatingKind, MoeConfig};

    fn small_run(iterations: usize) -> (VddConfig, IsoGmm, Moe, DistillData) {
        let teacher = IsoGmm::circle(4, 2.0, 0.5);
        let mut mc = MoeConfig::toy(1, 2, 4);
        mc.experts_network.hidden_dim = 16;
        mc.gating = GatingKind::Learned;
        mc.gating_network.hidden_dim = 16;
        let student = Moe::from_config(mc, 3).unwrap();
        let config = VddConfig {
            iterations,
            batch_size: 8,
            vi_samples: 16,
            gating_batch_size: 32,
            expert_optimizer: vdd_nn::AdamConfig { lr: 1e-2, ..Default::default() },
            ..VddConfig::toy()
        };
        let data = DistillData::from_states(Mat::zeros(8, 1)).unwrap();
        (config, teacher, student, data)
    }

    #[test]
    fn distils_a_four_mode_mixture() {
        let (config, teacher, student, data) = small_run(300);
        let mut vdd = Vdd::new(config, teacher.clone(), student, data).unwrap();
        vdd.train(|_| {}).unwrap();
        let mut student = vdd.into_student();
        let modes = teacher.means.clone();
        assert_eq!(modes_covered(&mut student, &[0.0], &modes, 0.3, 0.05).unwrap(), 4);
        let mut rng = Seeds::new(9).stream("eval");
        let kl =
            reverse_kl(&mut student, &[0.0], |a| teacher.log_density(a, 0.0), 20_000, &mut rng)
                .unwrap();
        assert!(kl < 0.05, "reverse KL {kl}");
    }

    #[test]
    fn resuming_from_a_checkpoint_reproduces_an_uninterrupted_run() {
        let dir = std::env::temp_dir().join(format!("vdd-resume-{}", std::process::id()));
        let (mut config, teacher, student, data) = small_run(12);
        config.student_ema = Some(0.9);
        let mut straight =
            Vdd::new(config.clone(), teacher.clone(), student.clone(), data.clone()).unwrap();
        straight.train(|_| {}).unwrap();

        let mut first = Vdd::new(config, teacher.clone(), student, data.clone()).unwrap();
        for _ in 0..5 {
            first.step().unwrap();
        }
        first.save_checkpoint(&dir).unwrap();
        drop(first);
        let mut resumed = Vdd::resume(&dir, teacher, data).unwrap();
        assert_eq!(resumed.iteration(), 5);
        resumed.train(|_| {}).unwrap();
        assert_eq!(params(straight.student()), params(resumed.student()));
        // The moving average is part of the checkpoint too.
        assert_eq!(params(&straight.into_student()), params(&resumed.into_student()));
        std::fs::remove_dir_all(&dir).ok();
    }

    fn params(student: &Moe) -> Vec<(String, Vec<f32>)> {
        let mut out = Vec::new();
        student.visit_params("", &mut |n, p| out.push((n.to_owned(), p.value.clone())));
        out
    }

    #[test]
    fn the_returned_student_is_the_moving_average_of_the_iterates() {
        let (mut config, teacher, student, data) = small_run(6);
        let decay = 0.7;
        config.student_ema = Some(decay);
        let mut average = params(&student);
        let mut vdd = Vdd::new(config, teacher, student, data).unwrap();
        let mut trainable = Vec::new();
        vdd.student().visit_params("", &mut |_, p| trainable.push(p.trainable));
        for _ in 0..6 {
            vdd.step().unwrap();
            for ((avg, (_, now)), &t) in
                average.iter_mut().zip(params(vdd.student())).zip(&trainable)
            {
                for (a, v) in avg.1.iter_mut().zip(now) {
                    *a = if t { *a + (1.0 - decay) * (v - *a) } else { v };
                }
            }
        }
        let last = params(vdd.student());
        let averaged = params(&vdd.into_student());
        assert_ne!(averaged, last);
        for ((name, got), (_, want)) in averaged.iter().zip(&average) {
            for (g, w) in got.iter().zip(want) {
                assert!((g - w).abs() < 1e-6, "{name}: {g} vs {w}");
            }
        }
    }

    #[test]
    fn an_ema_decay_outside_zero_to_one_is_rejected() {
        let (mut config, teacher, student, data) = small_run(2);
        config.student_ema = Some(1.0);
        assert!(Vdd::new(config, teacher, student, data).is_err());
    }

    struct NanAfter(IsoGmm, usize);
    impl ScoreModel for NanAfter {
        fn action_dim(&self) -> usize {
            2
        }
        fn state_dim(&self) -> usize {
            1
        }
        fn score(
            &mut self,
            a: MatRef<'_, f32>,
            s: MatRef<'_, f32>,
            l: &[f32],
            mut out: MatMut<'_, f32>,
        ) -> Result<(), CoreError> {
            self.0.score(a, s, l, out.as_mut())?;
            if self.1 == 0 {
                out[(0, 0)] = f32::NAN;
            } else {
                self.1 -= 1;
            }
            Ok(())
        }
        fn sample_actions(
            &mut self,
            s: MatRef<'_, f32>,
            rng: &mut dyn rand::RngCore,
            out: MatMut<'_, f32>,
        ) -> Result<(), CoreError> {
            self.0.sample_actions(s, rng, out)
        }
    }

    #[test]
    fn a_non_finite_score_stops_training_with_the_iteration() {
        let (config, teacher, student, data) = small_run(10);
        let before = student.clone();
        let mut vdd = Vdd::new(config, NanAfter(teacher, 3), student, data).unwrap();
        let err = vdd.train(|_| {}).unwrap_err();
        match err {
            VddError::NonFinite { iteration, quantity } => {
                assert_eq!(iteration, 3);
                assert_eq!(quantity, "teacher score");
            }
            other => panic!("unexpected error {other}"),
        }
        assert_eq!(vdd.iteration(), 3);
        let mut changed = false;
        let mut old = Vec::new();
        before.visit_params("", &mut |_, p| old.push(p.value.clone()));
        let mut k = 0;
        vdd.student().visit_params("", &mut |_, p| {
            changed |= p.value != old[k];
            k += 1;
        });
        assert!(changed, "three iterations should have trained");
        assert!(vdd.student().clone().act(&[0.0]).unwrap().iter().all(|x| x.is_finite()));
    }

    /// Gating weights of the student at state 0.
    fn gating_at_zero(student: &mut Moe) -> Vec<f32> {
        student.forward(Mat::<f32>::zeros(1, 1).as_ref()).unwrap();
        student.output().log_gating_row(0).iter().map(|l| l.exp()).collect()
    }

    /// With a dataset, the gating step learns the responsibilities of the dataset's actions:
    /// a teacher with equal modes but data that visits one mode 3x as often gives a gating
    /// that follows the data, not the teacher.
    #[test]
    fn the_gating_follows_the_responsibilities_of_dataset_actions() {
        let teacher =
            IsoGmm { means: vec![vec![2.0, 0.0], vec![-2.0, 0.0]], std: 0.3, state_dim: 1 };
        let mut mc = MoeConfig::toy(1, 2, 2);
        mc.experts_network.hidden_dim = 16;
        mc.gating = GatingKind::Learned;
        mc.gating_network.hidden_dim = 16;
        let student = Moe::from_config(mc, 1).unwrap();
        let n = 400;
        let actions = Mat::from_fn(n, 2, |i, j| match (i % 4, j) {
            (3, 0) => -2.0,
            (_, 0) => 2.0,
            _ => 0.0,
        });
        let data = DistillData::new(Mat::zeros(n, 1), Some(actions)).unwrap();
        let config = VddConfig {
            iterations: 300,
            batch_size: 4,
            vi_samples: 16,
            gating_batch_size: 64,
            expert_optimizer: vdd_nn::AdamConfig { lr: 1e-2, ..Default::default() },
            gating_optimizer: vdd_nn::AdamConfig { lr: 1e-2, ..Default::default() },
            ..VddConfig::toy()
        };
        let mut vdd = Vdd::new(config, teacher, student, data).unwrap();
        vdd.train(|_| {}).unwrap();
        let mut student = vdd.into_student();
        let w = gating_at_zero(&mut student);
        let out = student.output();
        // The expert at +2 carries 3/4 of the weight.
        let right = if out.mean(0, 0)[0] > out.mean(0, 1)[0] { 0 } else { 1 };
        assert!((out.mean(0, right)[0] - 2.0).abs() < 0.2, "means {:?}", out.means);
        assert!((w[right] - 0.75).abs() < 0.05, "gating {w:?}");
    }

    /// `freeze_gating_after: Some(n)` stops gating updates from iteration n on.
    #[test]
    fn a_frozen_gating_stops_changing() {
        let (mut config, teacher, student, data) = small_run(8);
        config.freeze_gating_after = Some(4);
        config.gating_optimizer.lr = 1e-2;
        let mut vdd = Vdd::new(config, teacher, student, data).unwrap();
        let mut gating = Vec::new();
        let mut losses = Vec::new();
        for _ in 0..8 {
            losses.push(vdd.step().unwrap().gating_loss);
            let mut student = vdd.student().clone();
            gating.push(gating_at_zero(&mut student));
        }
        assert!(losses[..4].iter().all(Option::is_some));
        assert!(losses[4..].iter().all(Option::is_none));
        assert_ne!(gating[2], gating[3], "the gating trains before the freeze");
        assert!(gating[3..].windows(2).all(|w| w[0] == w[1]), "{gating:?}");
    }

    /// The expert step queries the teacher at the configured noise levels: fixed, uniform in a
    /// range, or annealed from start to end over the run.
    #[test]
    fn noise_levels_follow_the_configured_schedule() {
        let levels = |noise: NoiseSchedule| {
            let (mut config, teacher, student, data) = small_run(10);
            config.noise = noise;
            let mut vdd = Vdd::new(config, teacher, student, data).unwrap();
            let mut out = Vec::new();
            vdd.train(|m| out.push(m.expert.noise_level)).unwrap();
            out
        };
        let fixed = levels(NoiseSchedule::Fixed { level: 0.3 });
        assert!(fixed.iter().all(|&l| (l - 0.3).abs() < 1e-6), "{fixed:?}");
        let uniform = levels(NoiseSchedule::Uniform { min: 0.2, max: 0.6 });
        // Means over 8·4·16 draws: close to 0.4, never at the ends.
        assert!(uniform.iter().all(|&l| (l - 0.4).abs() < 0.03), "{uniform:?}");
        let annealed = levels(NoiseSchedule::Annealed { start: 1.0, end: 0.1 });
        assert!((annealed[0] - 1.0).abs() < 1e-6, "{annealed:?}");
        assert!(annealed.windows(2).all(|w| w[1] < w[0]), "{annealed:?}");
        assert!(annealed[9] < 0.2 && annealed[9] > 0.1, "{annealed:?}");
    }

    #[test]
    fn mismatched_dimensions_are_rejected() {
        let (config, teacher, _, data) = small_run(1);
        let student = Moe::from_config(MoeConfig::toy(1, 3, 2), 0).unwrap();
        assert!(Vdd::new(config, teacher, student, data).is_err());
    }

    use vdd_core::Policy;
}
