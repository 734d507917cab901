//! What a method is to the recipes: the [`Method`] trait (an algorithm, run by the rows of
//! [`crate::row`] from a teacher), the task-agnostic [`Job`] it trains from, and the
//! [`Trained`] policy it returns. The methods themselves, one file each, and their list are in
//! [`crate::methods`].
//!
//! A method reads its own settings from the recipe by key path ([`MethodRecipe::get`]), so its
//! defaults live in `recipes/defaults/<task>.toml` under the keys it declares
//! ([`Method::keys`]); the recipe types hold those tables without knowing their contents.

use serde::Serialize;
use serde::de::DeserializeOwned;
use toml::{Table, Value};
use vdd_moe::MoeConfig;

pub use crate::capability::Capability;
use crate::plots::Curves;
use crate::policy::TrainedPolicy;
use crate::recipe;
use crate::teachers::{LoadedTeacher, TeacherSource, TeachersConfig, TrainedTeacher};
pub use vdd_data::TrainingData;
use vdd_moe::cache::StudentCache;
pub use vdd_report::budget::{Budget, BudgetRole};

/// Whether a method is distilled from (or is) a teacher, and which: what a row of it must
/// name ([`crate::row::Row`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum TeacherUse {
    /// It takes none (a row naming one is refused).
    Never,
    /// Any teacher source: a learned one or the task's exact mixture.
    Any,
    /// A learned teacher (trained, or loaded from the cache, before the method).
    Learned,
    /// A teacher that acts: a learned one or one loaded from a file
    /// ([`crate::teachers::TeacherSource::load`]).
    Acting,
}

/// What a method is: its name, what it takes and needs.
#[derive(Debug, Clone, Copy)]
pub struct Info {
    /// The lower-case hyphenated algorithm name (`vdd`), as in a row's `method`.
    pub name: &'static str,
    /// The teacher a row of it names.
    pub teacher: TeacherUse,
    /// What it needs of a task (its teacher source adds its own): a row runs on every task
    /// that offers all of it ([`crate::task::Task::offers`]).
    pub needs: &'static [Capability],
    /// The keys of a row's `with` table it reads ([`crate::row::Row::settings`]).
    pub row_keys: &'static [&'static str],
}

/// One method of the comparison: an algorithm that a row of the results table runs from a
/// teacher ([`crate::row`]). Its own settings are recipe keys ([`Method::keys`]) and the row's
/// `with` table.
pub trait Method: Sync {
    /// Name, teacher, needs and row keys.
    fn info(&self) -> &Info;
    /// The recipe keys (dotted paths below a task's method sections) `row` reads, e.g.
    /// `vdd.beso` for VDD from the BESO teacher.
    fn keys(&self, row: &Row) -> Vec<String>;
    /// Reads its settings from `recipe` (and `recipe.row`), failing as training would on a
    /// missing or bad one.
    fn check(&self, recipe: &MethodRecipe<'_>) -> crate::Result;
    /// Trains on `job`.
    fn train(&self, job: &Job<'_>) -> crate::Result<Trained>;
    /// The shared recipe keys `row` does not read, as `(shared key, the key it reads
    /// instead)`; `None` when the method fixes the value itself. A `--set` of such a shared key
    /// is refused for the row while its own key is set ([`crate::driver::plan`]): it would
    /// not take effect. (The keys a row sets itself, [`crate::row::Row::set`], are refused
    /// alike.)
    fn shadowed_keys(&self, _row: &Row) -> Vec<(String, Option<String>)> {
        Vec::new()
    }
    /// Checks a row of a teacher loaded from a file against that teacher, before anything
    /// trains (by default: any loaded teacher).
    fn check_loaded(&self, _row: &Row, _teacher: &LoadedTeacher) -> crate::Result {
        Ok(())
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
    /// The whole resolved recipe, with the row's own settings ([`Row::set`]) merged in.
    pub tree: &'a Table,
    /// The row being run.
    pub row: &'a Row,
}

impl MethodRecipe<'_> {
    /// The value at `path` (`baselines.em`); unknown keys inside it are errors.
    pub fn get<T: Serialize + DeserializeOwned>(&self, path: &str) -> crate::Result<T> {
        self.get_opt(path)?.ok_or_else(|| format!("the recipe has no `{path}`").into())
    }

    /// The value at `path`, `None` when the key is absent ([`recipe::get_path`]).
    pub fn get_opt<T: Serialize + DeserializeOwned>(&self, path: &str) -> crate::Result<Option<T>> {
        Ok(recipe::get_path(self.tree, path)?)
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
    /// The trained teacher of the row's learned teacher source.
    pub teacher: Option<&'a TrainedTeacher>,
    /// The teacher of the row's file source ([`crate::teachers::TeacherSource::load`]); the
    /// job's `data` are then cut in its windows and chunks, in its normalised space.
    pub loaded: Option<&'a LoadedTeacher>,
    /// The recipe.
    pub recipe: MethodRecipe<'a>,
    /// Where students are cached, for tasks that cache them.
    pub students: Option<StudentCache<'a>>,
    /// The run's checkpoint directory, and whether to resume from it (`--resume`).
    pub checkpoints: (&'a std::path::Path, bool),
    /// Curves over training, when the task takes them ([`CurveProbe`]).
    pub curves: Option<&'a dyn CurveEval>,
    /// Rollouts of a policy in the task, when the task has them ([`StateVisits`]).
    pub visits: Option<&'a dyn StateVisits>,
}

/// The states a policy reaches in a task's episodes: what a method fits beyond the
/// demonstrations (a distilled student's gating on the states the student itself visits).
pub trait StateVisits: Sync {
    /// The states `policy` (acting on the data's raw states) acts on in `episodes` episodes
    /// drawn from root seed `seed` (a stream of the task's own, apart from its evaluation and
    /// curve episodes), in the data's state space and in episode order.
    fn visit(
        &self,
        policy: &TrainedPolicy,
        seed: u64,
        episodes: usize,
    ) -> Result<faer::Mat<f32>, vdd_tasks::TaskError>;
}

/// What a task evaluates at checkpoints of a training (the held-out curves of
/// `eval.curve_points`; the evaluation itself is the task crate's, e.g.
/// `vdd_tasks::avoiding::CurveProtocol`), on policies acting on the data's raw states.
pub trait CurveEval:
    vdd_core::curves::CurveEval<TrainedPolicy, Error = vdd_tasks::TaskError>
{
    /// What the curves depend on, for the keys of cached students.
    fn key(&self) -> serde_json::Value;
    /// The series each checkpoint gives (what checkpoint selection may choose by).
    fn series(&self) -> Vec<String>;
}

/// A training's curve points ([`vdd_core::curves::CurveProbe`] of [`Job::curves`]).
pub type CurveProbe<'a> = vdd_core::curves::CurveProbe<'a, TrainedPolicy, dyn CurveEval + 'a>;

impl<'a> Job<'a> {
    /// The probe of the training's curves over training.
    pub fn probe(&self) -> CurveProbe<'a> {
        CurveProbe::new(self.curves, self.seed)
    }

    /// The trained teacher, or an error for a method that declared none.
    pub fn teacher(&self) -> crate::Result<&TrainedTeacher> {
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
    /// How the policy acts on raw observations (features, window, chunk) when it is not the
    /// task's own (a policy of a file teacher's windows and chunks); `None`: the task's.
    pub deploy: Option<vdd_data::DeploySpec>,
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
            deploy: None,
        }
    }
}

/// A row of the results tables, resolved against the registry's methods and teacher sources
/// (written as a [`crate::row::RowSpec`]; [`crate::row`]).
#[derive(Clone)]
pub struct Row {
    /// The lower-case hyphenated name (`vdd-beso`): `--methods`, tables, `metrics.json`.
    pub name: String,
    /// The method.
    pub method: &'static dyn Method,
    /// The teacher source.
    pub teacher: Option<&'static dyn TeacherSource>,
    /// The method's row settings ([`crate::row::RowSpec::with`]).
    pub with: Table,
    /// The recipe keys set for this row ([`crate::row::RowSpec::set`], dotted keys expanded).
    pub set: Table,
    /// [`crate::row::RowSpec::needs`].
    pub needs: Vec<Capability>,
    /// [`crate::row::RowSpec::only_on`].
    pub only_on: Vec<String>,
}

impl std::fmt::Debug for Row {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Row")
            .field("name", &self.name)
            .field("method", &self.method.name())
            .field("teacher", &self.teacher_name())
            .field("with", &self.with)
            .field("set", &self.set)
            .finish()
    }
}

impl Row {
    /// The family of the row's learned teacher; `None` without a teacher or for the task's
    /// exact mixture.
    pub fn teacher_kind(&self) -> Option<crate::teachers::TeacherKind> {
        self.teacher.and_then(|t| t.kind())
    }

    /// The teacher source's name.
    pub fn teacher_name(&self) -> Option<&'static str> {
        self.teacher.map(|t| t.name())
    }

    /// The teacher's name as a recipe key segment (`beso-d3il` → `beso_d3il`), for methods
    /// whose settings are per teacher (`vdd.<teacher>`); an error for a row without one.
    pub fn teacher_key(&self) -> crate::Result<String> {
        let t = self.teacher.ok_or_else(|| format!("row `{}` has no teacher", self.name))?;
        Ok(t.name().replace('-', "_"))
    }

    /// The method's row settings, typed (`T` should deny unknown fields).
    pub fn settings<T: DeserializeOwned>(&self) -> crate::Result<T> {
        Value::Table(self.with.clone())
            .try_into()
            .map_err(|e| format!("row `{}`: `with`: {e}", self.name).into())
    }

    /// The recipe keys the row reads: its teacher source's, then its method's.
    pub fn keys(&self) -> Vec<String> {
        let mut keys: Vec<String> = self
            .teacher
            .map(|t| t.keys().iter().map(|k| (*k).to_owned()).collect())
            .unwrap_or_default();
        keys.extend(self.method.keys(self));
        keys
    }

    /// Everything the row needs of a task: its method's, its teacher's and its own.
    pub fn needs(&self) -> Vec<Capability> {
        let mut needs = self.method.info().needs.to_vec();
        needs.extend(self.teacher.iter().flat_map(|t| t.needs().iter().copied()));
        needs.extend(self.needs.iter().copied());
        needs
    }

    /// The dotted paths of [`Row::set`].
    pub fn set_paths(&self) -> Vec<String> {
        fn walk(prefix: &str, t: &Table, out: &mut Vec<String>) {
            for (k, v) in t {
                let path = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
                match v {
                    Value::Table(inner) if !inner.is_empty() => walk(&path, inner, out),
                    _ => out.push(path),
                }
            }
        }
        let mut out = Vec::new();
        walk("", &self.set, &mut out);
        out
    }

    /// `tree` with the row's [`Row::set`] merged in.
    pub fn apply_set(&self, tree: &Table) -> Table {
        let mut tree = tree.clone();
        crate::recipe::merge(&mut tree, &self.set);
        tree
    }
}
