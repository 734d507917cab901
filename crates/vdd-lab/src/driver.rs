//! The stages every task pipeline shares (a [`crate::task::Task`] runs them): the run's
//! plan (rows × variants, [`plan`]), its datasets ([`Datasets`]), the training phases with
//! the teacher store and the student cache ([`train_all`]), and writing the results
//! ([`write_results`]). The tasks themselves are in [`crate::tasks`].
//!
//! Training runs in two parallel phases of single-threaded jobs (`jobs` at a time): the
//! teachers with the methods that need none, then the methods that need a teacher. Every job is
//! seeded on its own, so the results do not depend on the number of jobs.

use std::collections::HashMap;
use std::sync::Arc;
use std::time::Instant;

use serde_json::Value;
use toml::Table;
use vdd_diffusion::TeacherKind;

use crate::context::{RunContext, StageTimes};
use crate::method::{CurveEval, Job, MethodRecipe, StateVisits, Trained, TrainingData};
use crate::recipe::{self, Resolved};
use crate::report::Row;
use crate::row::Row as PlanRow;
pub use crate::task::{Task, TaskRecipe};
use crate::teachers::{self, LoadedTeacher, TeacherSource, TeachersConfig, TrainedTeacher};
use crate::{Registry, Result as XResult};
use vdd_moe::cache::StudentCache;

/// One row of one variant of the recipe.
pub struct Entry<'r, R> {
    /// `vdd-beso`, `vdd-beso-z4`.
    pub label: String,
    /// The row: its method and teacher.
    pub row: PlanRow,
    /// The variant's configuration.
    pub cfg: &'r R,
    /// `cfg` as a TOML tree with the row's own settings, for the method's keys.
    tree: Table,
    /// The learned teachers of the row ([`crate::teachers::TeacherSource::teachers`]).
    teachers: TeachersConfig,
    /// The teacher of a file source, loaded once per run ([`TeacherSource::load`]).
    pub loaded: Option<Arc<LoadedTeacher>>,
}

impl<R: TaskRecipe> Entry<'_, R> {
    /// The method's view of the configuration.
    pub fn recipe(&self) -> MethodRecipe<'_> {
        let (teachers, student, tree) = (&self.teachers, self.cfg.student(), &self.tree);
        MethodRecipe { teachers, student, tree, row: &self.row }
    }

    /// The family of the row's learned teacher, if it has one ([`PlanRow::teacher_kind`]).
    pub fn teacher_kind(&self) -> Option<TeacherKind> {
        self.row.teacher_kind()
    }
}

/// The rows of every variant of `resolved` (the registry's and the recipe's own `runs`), in
/// order, after checking the task, the seeds, the method sections (every key claimed by a
/// row; every row of the task reads its settings), the rows' own `set` keys and that every
/// `--set` of `sets` reaches the rows it names ([`crate::method::Method::shadowed_keys`]).
pub fn plan<'r, R: TaskRecipe>(
    registry: &Registry,
    resolved: &'r Resolved<R>,
    task: &str,
    sets: &[(String, String)],
) -> XResult<Vec<Entry<'r, R>>> {
    let header = resolved.base.header();
    if header.task != task {
        return Err(format!("recipe task `{}` is not `{task}`", header.task).into());
    }
    if header.seeds.is_empty() {
        return Err("the recipe lists no seeds".into());
    }
    let mut out = Vec::new();
    let mut files: HashMap<String, Arc<LoadedTeacher>> = HashMap::new();
    for (variant, cfg) in resolved.configs() {
        let registry = registry.clone().with_rows(&cfg.header().runs)?;
        let tree = recipe::to_tree(cfg)?;
        cfg.student().check(1).map_err(|e| format!("student: {e}"))?;
        check_method_sections::<R>(&registry, task, &tree, cfg)?;
        for row in registry.parse_rows(&cfg.header().methods, task)? {
            let label = crate::row::label(&row.name, variant.map(|v| v.name.as_str()));
            let (tree, teachers) = row_view(row, &tree, cfg)?;
            let view =
                MethodRecipe { teachers: &teachers, student: cfg.student(), tree: &tree, row };
            check_sets_reach(row, &label, &view, sets)?;
            let loaded = match row.teacher {
                Some(t) => load_once(t, &tree, &mut files).map_err(|e| format!("{label}: {e}"))?,
                None => None,
            };
            let mut label = label;
            if let Some(t) = &loaded {
                row.method.check_loaded(row, t).map_err(|e| format!("{label}: {e}"))?;
                // The file's own source names its rows: `imported` → `lerobot`.
                label = label.replacen("imported", t.source(), 1);
            }
            out.push(Entry { label, row: row.clone(), cfg, tree, teachers, loaded });
        }
    }
    Ok(out)
}

/// The teacher `source` loads from the file `tree` names, loaded once per file (`files`).
fn load_once(
    source: &dyn TeacherSource,
    tree: &Table,
    files: &mut HashMap<String, Arc<LoadedTeacher>>,
) -> XResult<Option<Arc<LoadedTeacher>>> {
    let Some(file) = source.file(tree)? else { return Ok(None) };
    if let Some(t) = files.get(&file) {
        return Ok(Some(t.clone()));
    }
    let t = Arc::new(source.load(&file)?);
    files.insert(file, t.clone());
    Ok(Some(t))
}

/// The tree (`tree` with the row's `set`) and the learned teachers of `row`, after checking
/// that the row sets only keys of the methods' tables that it reads.
fn row_view<R: TaskRecipe>(
    row: &PlanRow,
    tree: &Table,
    cfg: &R,
) -> XResult<(Table, TeachersConfig)> {
    let fail = |e: String| -> crate::LabError { format!("row `{}`: {e}", row.name).into() };
    let keys = row.keys();
    for p in row.set_paths() {
        let top = p.split('.').next().unwrap_or_default();
        if !R::METHOD_SECTIONS.contains(&top) {
            let sections = R::METHOD_SECTIONS.join(", ");
            return Err(fail(format!(
                "`set` may change the methods' tables ({sections}), not `{p}`"
            )));
        }
        if !keys.iter().any(|k| p == *k || p.starts_with(&format!("{k}."))) {
            return Err(fail(format!("`set` names `{p}`, which the row does not read")));
        }
    }
    let tree = row.apply_set(tree);
    let teachers = match row.teacher {
        Some(t) => t.teachers(cfg.teachers(), &tree).map_err(|e| fail(e.to_string()))?,
        None => cfg.teachers().clone(),
    };
    Ok((tree, teachers))
}

/// Refuses a `--set` of a shared key that `row` would not read (see
/// [`crate::method::Method::shadowed_keys`]) or that the row sets itself, naming both keys.
fn check_sets_reach(
    row: &PlanRow,
    label: &str,
    view: &MethodRecipe<'_>,
    sets: &[(String, String)],
) -> XResult {
    // The `--set` that sets `path` (the key itself or a table holding it), if any.
    let set_of =
        |path: &str| sets.iter().find(|(k, _)| path == k || path.starts_with(&format!("{k}.")));
    let mut shadowed = row.method.shadowed_keys(row);
    shadowed.extend(row.set_paths().into_iter().map(|p| (p, None)));
    for (shared, own) in shadowed {
        let Some((k, _)) = set_of(&shared) else { continue };
        let message = match own {
            None => format!("`--set {k}` does not reach {label}, which fixes `{shared}` itself"),
            // Set too: the method takes its own key's value.
            Some(own) if set_of(&own).is_some() => continue,
            Some(own) => match view.get_opt::<toml::Value>(&own)? {
                None => continue,
                Some(v) => format!(
                    "`--set {k}` does not reach {label}, which reads `{own}` (= {v}) instead of \
                     `{shared}`; set `{own}`"
                ),
            },
        };
        return Err(message.into());
    }
    Ok(())
}

fn check_method_sections<R: TaskRecipe>(
    registry: &Registry,
    task: &str,
    tree: &Table,
    cfg: &R,
) -> XResult {
    let claimed = |key: &str| registry.rows().iter().any(|r| r.keys().iter().any(|k| k == key));
    for section in R::METHOD_SECTIONS {
        let keys = tree.get(*section).and_then(|v| v.as_table()).into_iter().flatten();
        for (k, _) in keys {
            let key = format!("{section}.{k}");
            if !claimed(&key) {
                return Err(format!("unknown recipe key `{key}` (no method reads it)").into());
            }
        }
    }
    for row in registry.rows_of(task) {
        let (tree, teachers) = row_view(row, tree, cfg)?;
        let view = MethodRecipe { teachers: &teachers, student: cfg.student(), tree: &tree, row };
        row.method.check(&view).map_err(|e| format!("{}: {e}", row.name))?;
    }
    Ok(())
}

/// The prepared datasets of a run, one per distinct data key, and which one each (seed, plan
/// entry) trains on.
pub use vdd_recipe::run::Shared as Datasets;

/// The teachers of a run, keyed by kind, configuration, seed and data (`teacher_key`): trained
/// once per run and shared by every method and variant that needs them.
#[derive(Default)]
pub struct TeacherStore {
    teachers: HashMap<String, TrainedTeacher>,
    /// `run.json` entries of the teachers, in training order.
    pub log: Vec<Value>,
}

/// The key of the teacher of `kind` for a configuration, data and seed.
fn teacher_key(
    kind: TeacherKind,
    cfg: &TeachersConfig,
    data: &TrainingData,
    seed: u64,
) -> XResult<String> {
    let sub = match kind {
        TeacherKind::Beso => recipe::config_hash(&cfg.beso)?,
        TeacherKind::Ddpm => recipe::config_hash(&cfg.ddpm)?,
    };
    Ok(format!("{}-{sub}-{seed}-{}", teachers::kind_name(kind), data.hash()))
}

impl TeacherStore {
    /// The teacher of `kind` for `cfg`, `data` and `seed`.
    pub fn get(
        &self,
        kind: TeacherKind,
        cfg: &TeachersConfig,
        data: &TrainingData,
        seed: u64,
    ) -> XResult<&TrainedTeacher> {
        let key = teacher_key(kind, cfg, data, seed)?;
        self.teachers.get(&key).ok_or_else(|| {
            let kind = teachers::kind_name(kind);
            format!("internal: the {kind} teacher of seed {seed} was not trained").into()
        })
    }
}

/// The trained methods of a run, by (seed index, entry index), and their teachers.
pub struct Trainings {
    /// The trained methods.
    pub trained: HashMap<(usize, usize), Trained>,
    /// The teachers.
    pub teachers: TeacherStore,
}

/// What a task's episodes give a training of a configuration: curves over training
/// ([`Job::curves`]) and the states a policy visits ([`Job::visits`]); `None`: not offered.
#[derive(Default)]
pub struct Probes {
    /// Curves over training.
    pub curves: Option<Box<dyn CurveEval>>,
    /// Rollouts that return the states a policy visits.
    pub visits: Option<Box<dyn StateVisits>>,
}

/// How a task builds the [`Probes`] of a configuration.
pub type ProbesFor<'a, R> = &'a (dyn Fn(&R) -> Probes + Sync);

/// Trains every entry of `plan` for every seed (see the module docs for the phases; the stages
/// `teachers` and `students`). `students`: the student cache, for tasks that use it; `probes`:
/// what the task's episodes give a configuration's trainings.
pub fn train_all<R: TaskRecipe, P: AsRef<TrainingData> + Sync>(
    ctx: &RunContext,
    plan: &[Entry<'_, R>],
    seeds: &[u64],
    data: &Datasets<P>,
    jobs: usize,
    (students, probes): (Option<StudentCache<'_>>, ProbesFor<'_, R>),
    stages: &mut StageTimes,
) -> XResult<Trainings> {
    let mut teacher_jobs: Vec<(String, TeacherKind, usize, usize)> = Vec::new();
    for (si, &seed) in seeds.iter().enumerate() {
        for (pi, e) in plan.iter().enumerate() {
            if let Some(kind) = e.teacher_kind() {
                let key = teacher_key(kind, &e.teachers, data.get(si, pi).as_ref(), seed)?;
                if !teacher_jobs.iter().any(|j| j.0 == key) {
                    teacher_jobs.push((key, kind, si, pi));
                }
            }
        }
    }
    let (free, dependent): (Vec<_>, Vec<_>) = (0..seeds.len())
        .flat_map(|si| (0..plan.len()).map(move |pi| (si, pi)))
        .partition(|&(_, pi)| plan[pi].teacher_kind().is_none());
    enum Work {
        Teacher(usize),
        Method(usize, usize),
    }
    enum Done {
        Teacher(usize, Box<TrainedTeacher>),
        Method((usize, usize), Box<Trained>),
    }
    let run_dir = ctx.run_dir(seeds);
    let (ck, finished) = (run_dir.join("checkpoints"), crate::finished::dir(&run_dir));
    let run_job = |w: &Work, store: &TeacherStore| -> Result<Done, String> {
        let (si, pi) = match *w {
            Work::Teacher(i) => (teacher_jobs[i].2, teacher_jobs[i].3),
            Work::Method(si, pi) => (si, pi),
        };
        let (e, seed, d) = (&plan[pi], seeds[si], data.get(si, pi).as_ref());
        let cfg = &e.teachers;
        if let Work::Teacher(i) = *w {
            let kind = teacher_jobs[i].1;
            let label = format!("{} s{seed}", teachers::kind_name(kind));
            let (s, a, cache) = (d.states.as_ref(), d.actions.as_ref(), &ctx.cache_dir);
            let t = teachers::train_or_load(kind, cfg, s, a, seed, cache, ctx.fresh, &label);
            return Ok(Done::Teacher(i, Box::new(t.map_err(|e| e.to_string())?)));
        }
        let label = format!("{} s{seed}", e.label);
        let config = toml::to_string(&e.tree).map_err(|err| format!("{label}: {err}"))?;
        let file_hash = e.loaded.as_deref().map(|l| l.hash.as_str());
        let key = crate::finished::TrainingKey::new(&config, &e.label, seed, file_hash);
        if ctx.resume {
            let kept = crate::finished::load(&finished, &e.label, seed, &key);
            if let Some(t) = kept.map_err(|err| format!("{label}: {err}"))? {
                crate::progress::print(format!("{label}: finished before, loaded (--resume)"));
                return Ok(Done::Method((si, pi), Box::new(t)));
            }
        }
        let teacher = e.teacher_kind().map(|kind| store.get(kind, cfg, d, seed));
        let teacher = teacher.transpose().map_err(|e| e.to_string())?;
        let checkpoints = (ck.as_path(), ctx.resume);
        let (data, recipe) = (d, e.recipe());
        // The task's curves and visits act through its own windows, not a file teacher's.
        let probe = if e.loaded.is_some() { Probes::default() } else { probes(e.cfg) };
        let (curves, visits) = (probe.curves.as_deref(), probe.visits.as_deref());
        let job = Job {
            seed,
            label: &label,
            data,
            teacher,
            loaded: e.loaded.as_deref(),
            recipe,
            students,
            checkpoints,
            curves,
            visits,
        };
        let t = e.row.method.train(&job).map_err(|e| format!("{label}: {e}"))?;
        let keep = crate::finished::store(&finished, &e.label, seed, &key, &t);
        keep.map_err(|err| format!("{label}: keeping the training: {err}"))?;
        Ok(Done::Method((si, pi), Box::new(t)))
    };
    let mut out = Trainings { trained: HashMap::new(), teachers: TeacherStore::default() };
    let first = (0..teacher_jobs.len()).map(Work::Teacher);
    let phases = [
        ("teachers", first.chain(free.iter().map(|&(s, p)| Work::Method(s, p))).collect()),
        ("students", dependent.iter().map(|&(s, p)| Work::Method(s, p)).collect::<Vec<_>>()),
    ];
    for (stage, work) in phases {
        let t0 = Instant::now();
        for done in crate::context::parallel_map(&work, jobs, |w| run_job(w, &out.teachers))? {
            match done {
                Done::Teacher(i, t) => {
                    let (key, kind, si, _) = &teacher_jobs[i];
                    out.teachers.log.push(t.log_entry(*kind, seeds[*si]));
                    out.teachers.teachers.insert(key.clone(), *t);
                }
                Done::Method(k, t) => {
                    out.trained.insert(k, *t);
                }
            }
        }
        stages.add(stage, t0.elapsed().as_secs_f64());
    }
    Ok(out)
}

/// The rows of the results table, one list (a row per seed) per plan entry.
pub fn empty_rows<R>(plan: &[Entry<'_, R>]) -> Vec<(String, Vec<Row>)> {
    plan.iter().map(|e| (e.label.clone(), Vec::new())).collect()
}

/// Writes `metrics.json`, `table.md` and `run.json` (with `details`) into `dir` and prints the
/// table.
pub fn write_results(
    ctx: &RunContext,
    dir: &std::path::Path,
    metrics: &Row,
    table: &str,
    details: Value,
) -> XResult {
    let write = |name: &str, text: &str| vdd_nn::io::write_atomic(&dir.join(name), text.as_bytes());
    write("metrics.json", &serde_json::to_string_pretty(metrics)?)?;
    write("table.md", table)?;
    ctx.write_run_info(dir, details)?;
    crate::progress::print(format!("\n{table}"));
    Ok(())
}
