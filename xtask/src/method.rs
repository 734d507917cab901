//! What a method is to the recipes: the [`Method`] trait, the task-agnostic [`Job`] it trains
//! from, and the [`Trained`] policy it returns. The methods themselves, one file each, and their
//! registry are in `xtask/src/methods/`.
//!
//! A method reads its own settings from the recipe by key path ([`MethodRecipe::get`]), so its
//! defaults live in `recipes/defaults/<task>.toml` under the keys it declares
//! ([`Method::keys`]); the recipe types hold those tables without knowing their contents.

use faer::Mat;
use serde::Serialize;
use serde::de::DeserializeOwned;
use toml::Table;
use vdd_core::Affine;
use vdd_core::gmm::GmmTeacher;
use vdd_diffusion::TeacherKind;
use vdd_moe::MoeConfig;

use vdd_core::{Snapshot, Trainer};

use crate::plots::Curves;
use crate::policy::TrainedPolicy;
use crate::recipe;
use crate::teachers::{TeachersConfig, TrainedTeacher};
use vdd_moe::cache::StudentCache;

/// What a method is: its name, its teacher, where it runs and what it reads.
#[derive(Debug, Clone, Copy)]
pub struct Info {
    /// The lower-case hyphenated name (`vdd-beso`), as in `--methods` and `metrics.json`.
    pub name: &'static str,
    /// The learned teacher the method needs (trained, or loaded from the cache, before it).
    pub teacher: Option<TeacherKind>,
    /// The tasks it runs on (`avoiding`, `toy-gmm`, `toy-conditional`).
    pub tasks: &'static [&'static str],
    /// The recipe keys (dotted paths below a task's method sections) it reads.
    pub keys: &'static [&'static str],
}

/// One method of the comparison (a row of the results table).
pub trait Method: Sync {
    /// Name, teacher, tasks and keys.
    fn info(&self) -> &Info;
    /// Reads its settings from `recipe`, failing as training would on a missing or bad one.
    fn check(&self, recipe: &MethodRecipe<'_>) -> crate::XResult;
    /// Trains on `job`.
    fn train(&self, job: &Job<'_>) -> crate::XResult<Trained>;
    /// The learned teachers it is distilled from or is: the recipe's `teachers` unless the
    /// method brings its own (the D3IL-style BESO rows). Their cache keys follow from it.
    fn teachers(&self, recipe: &MethodRecipe<'_>) -> crate::XResult<TeachersConfig> {
        Ok(recipe.teachers.clone())
    }
    /// [`Info::name`].
    fn name(&self) -> &'static str {
        self.info().name
    }
}

/// A method's view of one resolved recipe: the shared sections typed, anything else by path.
#[derive(Debug, Clone, Copy)]
pub struct MethodRecipe<'a> {
    /// The learned teachers' configuration.
    pub teachers: &'a TeachersConfig,
    /// The mixture of experts of the students (`state_dim` / `action_dim` come from the data).
    pub student: &'a MoeConfig,
    /// The whole resolved recipe.
    pub tree: &'a Table,
}

impl MethodRecipe<'_> {
    /// The value at `path` (`baselines.em`); unknown keys inside it are errors.
    pub fn get<T: Serialize + DeserializeOwned>(&self, path: &str) -> crate::XResult<T> {
        self.get_opt(path)?.ok_or_else(|| format!("the recipe has no `{path}`").into())
    }

    /// The value at `path`, `None` when the key is absent ([`recipe::get_path`]).
    pub fn get_opt<T: Serialize + DeserializeOwned>(
        &self,
        path: &str,
    ) -> crate::XResult<Option<T>> {
        Ok(recipe::get_path(self.tree, path)?)
    }
}

/// Training data of a run, as the task prepared it (row `i` of each matrix belongs together).
#[derive(Debug, Clone)]
pub struct TrainingData {
    /// States, raw.
    pub states: Mat<f32>,
    /// Actions, raw.
    pub actions: Mat<f32>,
    /// The task's normalisation of the states (identity when it has none).
    pub state_normalizer: Affine,
    /// The task's normalisation of the actions.
    pub action_normalizer: Affine,
    /// `states` under `state_normalizer`.
    pub states_normalized: Mat<f32>,
    /// `actions` under `action_normalizer`.
    pub actions_normalized: Mat<f32>,
    /// The exact teacher of the data's distribution, when the task knows it (the toys; it
    /// takes raw states and actions).
    pub exact: Option<GmmTeacher>,
    /// [`crate::teachers::data_hash`] of the raw matrices.
    pub hash: String,
}

impl TrainingData {
    /// Data without a normalisation of the task's own (identity normalisers).
    pub fn raw(states: Mat<f32>, actions: Mat<f32>, exact: Option<GmmTeacher>) -> Self {
        Self {
            state_normalizer: Affine::identity(states.ncols()),
            action_normalizer: Affine::identity(actions.ncols()),
            states_normalized: states.clone(),
            actions_normalized: actions.clone(),
            hash: crate::teachers::data_hash(states.as_ref(), actions.as_ref()),
            states,
            actions,
            exact,
        }
    }
}

impl AsRef<TrainingData> for TrainingData {
    fn as_ref(&self) -> &TrainingData {
        self
    }
}

/// Everything one training of a method gets.
#[derive(Clone, Copy)]
pub struct Job<'a> {
    /// The run seed (every seed inside the method's configurations is replaced by it).
    pub seed: u64,
    /// `vdd-beso s0`, for progress bars and log lines.
    pub label: &'a str,
    /// The training data.
    pub data: &'a TrainingData,
    /// The trained teacher of [`Method::teacher`].
    pub teacher: Option<&'a TrainedTeacher>,
    /// The recipe.
    pub recipe: MethodRecipe<'a>,
    /// Where students are cached, for tasks that cache them.
    pub students: Option<StudentCache<'a>>,
    /// The run's checkpoint directory, and whether to resume from it (`--resume`).
    pub checkpoints: (&'a std::path::Path, bool),
    /// Curves over training, when the task takes them ([`CurveProbe`]).
    pub curves: Option<&'a dyn CurveEval>,
}

/// What a task evaluates at checkpoints of a training (the held-out curves of
/// `eval.curve_points`; the evaluation itself is the task crate's, e.g.
/// `vdd_tasks::avoiding::CurveProtocol`).
pub trait CurveEval: Sync {
    /// The iterations of a run of `iterations` after which to evaluate.
    fn checkpoints(&self, iterations: usize) -> Vec<usize>;
    /// Named figures of `policy` (acting on the data's raw states) for run seed `seed`.
    fn evaluate(&self, policy: &TrainedPolicy, seed: u64) -> crate::XResult<Vec<(String, f64)>>;
    /// What the curves depend on, for the keys of cached students.
    fn key(&self) -> serde_json::Value;
}

/// A training's curve points: evaluates snapshots at the checkpoints of [`Job::curves`] and
/// keeps the time it takes apart from training.
pub struct CurveProbe<'a> {
    eval: Option<&'a dyn CurveEval>,
    seed: u64,
    /// Seconds spent evaluating.
    pub seconds: f64,
    /// The points so far, by series, against iterations.
    pub curves: Curves,
}

impl<'a> CurveProbe<'a> {
    /// The probe of `job`'s training.
    pub fn new(job: &Job<'a>) -> Self {
        Self { eval: job.curves, seed: job.seed, seconds: 0.0, curves: Curves::default() }
    }

    /// The iterations of a run of `iterations` to evaluate after (none without curves).
    pub fn checkpoints(&self, iterations: usize) -> Vec<usize> {
        self.eval.map_or_else(Vec::new, |c| c.checkpoints(iterations))
    }

    /// Evaluates `policy`, the model after `iteration` iterations.
    pub fn record(&mut self, iteration: usize, policy: &TrainedPolicy) -> crate::XResult {
        let Some(eval) = self.eval else { return Ok(()) };
        let t0 = std::time::Instant::now();
        for (series, v) in eval.evaluate(policy, self.seed)? {
            self.curves.entry(series).or_default().push((iteration as f64, v));
        }
        self.seconds += t0.elapsed().as_secs_f64();
        Ok(())
    }

    /// Runs `trainer` to its end through [`Trainer::run_with_checkpoints`] (reports to
    /// `report`), recording the [`Snapshot`] at each checkpoint as `policy` makes it a policy
    /// on raw states.
    pub fn run<T: Trainer + Snapshot>(
        &mut self,
        trainer: &mut T,
        report: impl FnMut(&T::Report),
        policy: impl Fn(T::Output) -> crate::XResult<TrainedPolicy>,
    ) -> crate::XResult {
        let at = self.checkpoints(trainer.iterations());
        trainer.run_with_checkpoints(&at, report, |t| {
            let p = policy(t.snapshot()?)?;
            self.record(t.iteration(), &p)
        })
    }

    /// Moves the points so far to the end of their series in `curves` and returns the
    /// seconds spent evaluating so far.
    pub fn take_into(&mut self, curves: &mut Curves) -> f64 {
        for (series, points) in std::mem::take(&mut self.curves) {
            curves.entry(series).or_default().extend(points);
        }
        self.seconds
    }
}

impl Job<'_> {
    /// The trained teacher, or an error for a method that declared none.
    pub fn teacher(&self) -> crate::XResult<&TrainedTeacher> {
        self.teacher.ok_or_else(|| format!("internal: {} got no teacher", self.label).into())
    }
}

/// A trained method before evaluation.
pub struct Trained {
    /// The policy (normalisers set: it acts on the data's raw states).
    pub policy: TrainedPolicy,
    /// Wall-clock training time (without the teacher's).
    pub train_seconds: f64,
    /// The teacher's training time, for methods distilled from one.
    pub teacher_seconds: Option<f64>,
    /// Sampling steps of a diffusion or consistency policy.
    pub sampling_steps: Option<usize>,
    /// Training iterations of a distilled mixture.
    pub iterations: Option<usize>,
    /// The mean noise level the teacher was queried at during distillation (fresh trainings).
    pub noise_level: Option<f32>,
    /// Learning curves.
    pub curves: Curves,
    /// Optimiser steps and batch of the method's own training (not its teacher's).
    pub budget: Option<Budget>,
    /// Seconds spent on the curves over training (not in `train_seconds`).
    pub curve_seconds: f64,
}

/// A training budget: optimiser steps of a given batch size (the rule is in
/// docs/avoiding-tuning.md, "Budgets": every student gets the same `steps · batch`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Budget {
    /// Optimiser steps (of the experts' or the network's parameters; a gating's steps, as many
    /// or fewer, are not counted apart).
    pub steps: u64,
    /// Rows (states, or state-action pairs) per step.
    pub batch: usize,
    /// A teacher's budget (its own) or a student's (equal across a comparison's students).
    pub role: BudgetRole,
}

/// Whose budget a [`Budget`] is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BudgetRole {
    /// A teacher, trained on the data (its rows, e.g. `beso`, `beso-1`).
    Teacher,
    /// A student, trained from a teacher or the data (VDD, CD, CTM, EM, IMC).
    Student,
}

impl Budget {
    /// A student's budget.
    pub fn student(steps: u64, batch: usize) -> Self {
        Self { steps, batch, role: BudgetRole::Student }
    }
}

impl Trained {
    /// A trained `policy` with nothing but its training time and curves.
    pub fn new(policy: TrainedPolicy, train_seconds: f64, curves: Curves) -> Self {
        Self {
            policy,
            train_seconds,
            teacher_seconds: None,
            sampling_steps: None,
            iterations: None,
            noise_level: None,
            curves,
            budget: None,
            curve_seconds: 0.0,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use vdd_moe::Moe;

    /// Counts iterations; its snapshot is a mixture whose seed is the iteration.
    struct Count(usize);

    impl Trainer for Count {
        type Report = ();
        type Output = usize;
        type Error = std::fmt::Error;
        fn step(&mut self) -> Result<(), Self::Error> {
            self.0 += 1;
            Ok(())
        }
        fn iteration(&self) -> usize {
            self.0
        }
        fn iterations(&self) -> usize {
            9
        }
        fn finish(self) -> Result<usize, Self::Error> {
            Ok(self.0)
        }
    }

    impl Snapshot for Count {
        fn snapshot(&self) -> Result<usize, Self::Error> {
            Ok(self.0)
        }
    }

    /// Reports the number of experts of the policy as its "success".
    struct Experts;

    impl CurveEval for Experts {
        fn checkpoints(&self, iterations: usize) -> Vec<usize> {
            vdd_core::trainer::checkpoints(iterations, 3)
        }
        fn evaluate(&self, p: &TrainedPolicy, seed: u64) -> crate::XResult<Vec<(String, f64)>> {
            let TrainedPolicy::Moe(m) = p else { return Err("not a mixture".into()) };
            Ok(vec![("experts".into(), m.num_experts() as f64), ("seed".into(), seed as f64)])
        }
        fn key(&self) -> serde_json::Value {
            serde_json::json!(3)
        }
    }

    #[test]
    fn the_probe_evaluates_snapshots_at_the_task_checkpoints() {
        let data = TrainingData::raw(Mat::zeros(2, 1), Mat::zeros(2, 2), None);
        use vdd_diffusion::cache::{BesoTeacherConfig, DdpmTeacherConfig};
        let train = vdd_diffusion::TrainConfig::default();
        let teachers = TeachersConfig {
            beso: BesoTeacherConfig { config: Default::default(), train: train.clone() },
            ddpm: DdpmTeacherConfig { config: Default::default(), train },
        };
        let student = vdd_moe::MoeConfig::toy(1, 2, 2);
        let tree = Table::new();
        let recipe = MethodRecipe { teachers: &teachers, student: &student, tree: &tree };
        let job = Job {
            seed: 7,
            label: "t",
            data: &data,
            teacher: None,
            recipe,
            students: None,
            checkpoints: (std::path::Path::new("."), false),
            curves: Some(&Experts),
        };
        let mut probe = CurveProbe::new(&job);
        assert_eq!(probe.checkpoints(9), [3, 6, 9]);
        let mut reports = 0;
        let policy = |it: usize| -> crate::XResult<TrainedPolicy> {
            let config = vdd_moe::MoeConfig::toy(1, 2, it);
            Ok(TrainedPolicy::Moe(Box::new(Moe::from_config(config, 0)?)))
        };
        probe.run(&mut Count(0), |_| reports += 1, policy).unwrap();
        assert_eq!(reports, 9);
        let mut curves = Curves::from([("experts".to_owned(), vec![(0.0, 1.0)])]);
        probe.take_into(&mut curves);
        assert_eq!(curves["experts"], [(0.0, 1.0), (3.0, 3.0), (6.0, 6.0), (9.0, 9.0)]);
        assert_eq!(curves["seed"], [(3.0, 7.0), (6.0, 7.0), (9.0, 7.0)], "the run seed");
        let none = CurveProbe::new(&Job { curves: None, ..job });
        assert!(none.checkpoints(9).is_empty());
    }
}
