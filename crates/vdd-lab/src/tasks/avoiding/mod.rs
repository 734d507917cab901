//! The Avoiding pipeline: scripted demonstrations → dataset
//! ([`vdd_tasks::avoiding::dataset`]) → teachers (cached) → every method → rollouts (success
//! rate, task entropy) and µs per action → `metrics.json`, `table.md`, `curves.json`, plots.
//!
//! Seeds: the demonstrations come from `data.seed` (one fixed dataset for every run seed);
//! the run seed drives teacher training, student initialisation and training, and the
//! evaluation rollouts (`vdd_tasks::avoiding::EvalProtocol`: the same episode seeds for every
//! method of a seed, so methods are compared on the same episodes). Every `seed` field inside the
//! component configurations is replaced by the run seed. Tuning runs (seeds 100–104,
//! `--tuning`) use their own demonstrations and are logged: [`crate::tuning`].

use std::time::Instant;

use faer::Mat;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use toml::Table;
use vdd_data::Windowed;
use vdd_moe::MoeConfig;

use vdd_tasks::avoiding::dataset::DatasetConfig;
use vdd_tasks::avoiding::{AvoidingEval, DeployedCurves, EvalProtocol, PlotSettings};
use vdd_tasks::timing::us_per_action;

mod imported;

use crate::context::{RunContext, StageTimes};
use crate::driver::{self, Datasets, Entry, Task, TaskRecipe};
use crate::method::{CurveEval, Trained, TrainingData};
use crate::plots::{self, Curves, TrajectoryPanel};
use crate::policy::TrainedPolicy;
use crate::recipe::{self, Overrides};
use crate::report::{self, Row};
use crate::teachers::{self, TeachersConfig};
use crate::tuning;
use imported::ImportedSettings;
use vdd_moe::cache::StudentCache;

/// A recipe of the Avoiding task (see `recipes/avoiding.toml`): the schema of the recipe files;
/// the values not given there come from `recipes/defaults/avoiding.toml` ([`Self::defaults`]).
/// Unknown keys are errors ([`recipe::from_tree`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AvoidingRecipe {
    /// Name, description, task (`avoiding`), seeds and methods (`beso`, `vdd-beso`, ...; `all`).
    #[serde(flatten)]
    pub header: recipe::Header,
    /// Trainings run concurrently, each on one thread (0: one per core). Results do not
    /// depend on it.
    pub jobs: usize,
    /// Demonstrations and windowing.
    pub data: DatasetConfig,
    /// The learned teachers.
    pub teachers: TeachersConfig,
    /// The mixture of experts of VDD, EM and IMC (`state_dim` / `action_dim` come from the data).
    pub student: MoeConfig,
    /// VDD's settings, read by the VDD methods ([`crate::methods`]).
    pub vdd: Table,
    /// The baselines' settings, read by their methods (`em.rs`, `imc.rs`, `cd.rs`, `ctm.rs`).
    pub baselines: Table,
    /// Rollouts and timing.
    pub eval: AvoidingEval,
    /// Figures.
    pub plots: PlotSettings,
    /// A teacher imported from PyTorch (`--teacher FILE`; the `imported` module).
    pub imported: ImportedSettings,
}

/// `recipes/defaults/avoiding.toml`, embedded so that the binary is self-contained.
const DEFAULTS: &str = include_str!("../../../../../recipes/defaults/avoiding.toml");

impl AvoidingRecipe {
    /// The task's defaults, `recipes/defaults/avoiding.toml`, which a recipe file overrides.
    pub fn defaults() -> recipe::RecipeResult<Self> {
        recipe::defaults_from_toml(&[("recipes/defaults/avoiding.toml", DEFAULTS)])
    }
}

impl TaskRecipe for AvoidingRecipe {
    const METHOD_SECTIONS: &'static [&'static str] = &["vdd", "baselines"];
    fn header(&self) -> &recipe::Header {
        &self.header
    }
    fn teachers(&self) -> &TeachersConfig {
        &self.teachers
    }
    fn student(&self) -> &MoeConfig {
        &self.student
    }
}

/// The Avoiding task.
pub struct Avoiding;

/// The dataset of a run.
struct Prepared {
    training: TrainingData,
    /// Raw observations of the training episodes (µs-per-action timing).
    episodes_obs: Vec<Mat<f32>>,
    summary: Value,
}

impl AsRef<TrainingData> for Prepared {
    fn as_ref(&self) -> &TrainingData {
        &self.training
    }
}

fn prepare(data: &DatasetConfig) -> crate::Result<Prepared> {
    let t0 = Instant::now();
    let d = data.build()?;
    let summary = d.summary(data.demonstrations);
    crate::progress::log(format!(
        "data: {} demonstrations ({} train episodes, {} samples, {} of 24 modes, entropy {:.3}) in {:.2} s",
        data.demonstrations,
        d.train_episodes,
        d.training.states.nrows(),
        summary["dataset_modes"],
        summary["dataset_entropy"].as_f64().unwrap_or(0.0),
        t0.elapsed().as_secs_f64()
    ));
    Ok(Prepared { training: d.training, episodes_obs: d.episode_observations, summary })
}

/// Curves over training on Avoiding, through the recipe's features and windows; `None` when
/// `eval.curve_points` is 0.
fn curves_of(cfg: &AvoidingRecipe) -> Option<Box<dyn CurveEval>> {
    let curves = DeployedCurves { protocol: cfg.eval.curves(), spec: cfg.data.deploy_spec() };
    curves.protocol.enabled().then(|| Box::new(curves) as Box<dyn CurveEval>)
}

impl CurveEval for DeployedCurves {
    fn key(&self) -> Value {
        json!({ "protocol": self.protocol, "spec": self.spec })
    }
}

/// What the evaluation collects for the outputs.
#[derive(Default)]
struct Collected {
    rows: Vec<(String, Vec<Row>)>,
    curves: serde_json::Map<String, Value>,
    panels: Vec<TrajectoryPanel>,
    curve_panels: Vec<(String, Curves)>,
}

/// The columns of Avoiding's tables.
pub const COLUMNS: [report::Column; 4] = [
    report::Column::new("success_rate", "success rate", 3),
    report::Column::new("task_entropy", "task entropy", 3),
    report::Column::new("us_per_action", "µs / action", 1),
    report::Column::new("train_seconds", "train s", 1),
];

impl Task for Avoiding {
    fn name(&self) -> &'static str {
        "avoiding"
    }

    fn columns(&self) -> Vec<report::Column> {
        COLUMNS.to_vec()
    }

    /// `--tuning`: the tuning seeds (unless given) and the tuning demonstrations; `--teacher
    /// FILE`: an imported teacher and its VDD student (methods `teacher,vdd` unless given).
    fn apply_shorthands(
        &self,
        given: &[(String, String)],
        o: &mut Overrides,
    ) -> Result<(), String> {
        for (k, v) in given {
            if k == "teacher" {
                o.sets.insert(0, ("imported.teacher".into(), format!("{v:?}")));
                o.methods.get_or_insert_with(|| vec!["teacher".into(), "vdd".into()]);
                continue;
            }
            if k != "tuning" {
                return Err(format!("option --{k} does not apply to task `avoiding`"));
            }
            o.seeds.get_or_insert_with(|| tuning::TUNING_SEEDS.collect());
            o.sets.insert(0, ("data.seed".into(), tuning::TUNING_DATA_SEED.to_string()));
        }
        Ok(())
    }

    fn run(&self, ctx: &RunContext) -> crate::Result {
        let resolved = recipe::resolve(&AvoidingRecipe::defaults()?, &ctx.file, &ctx.overrides)?;
        let base = &resolved.base;
        if !base.imported.teacher.is_empty() {
            return imported::run(ctx, &resolved);
        }
        let plan = driver::plan(&ctx.registry, &resolved, "avoiding", &ctx.overrides.sets)?;
        for (_, cfg) in resolved.configs() {
            // Before any training: a bad setting would otherwise fail after it.
            cfg.eval.check().map_err(|e| format!("eval: {e}"))?;
            cfg.data.deploy_spec().validate().map_err(|e| format!("data: {e}"))?;
        }
        let runs = resolved.configs().into_iter().map(|(_, c)| (&c.header.seeds[..], c.data.seed));
        let is_tuning = tuning::is_tuning_plan(runs)?;
        let dir = match (&ctx.out, is_tuning) {
            (None, true) => ctx
                .root
                .join("results/tuning")
                .join(&ctx.name)
                .join(crate::context::run_name(&base.header.seeds, &ctx.overrides)),
            _ => ctx.run_dir(&base.header.seeds),
        };
        let log_path = tuning::log_path(&ctx.root, "avoiding");
        let log = tuning::read_log(&log_path)?;
        ctx.write_resolved(&dir, &resolved.to_toml()?)?;
        crate::progress::log(format!(
            "recipe `{}`: {} method run(s) x {} seed(s) -> {}",
            ctx.name,
            plan.len(),
            base.header.seeds.len(),
            teachers::rel(&dir)
        ));
        let result =
            run_plan(ctx, base, &plan, &dir, &log, is_tuning.then_some(log_path.as_path()));
        if let (Err(e), true) = (&result, is_tuning) {
            // A configuration that failed was still tried: the log says so, with the error.
            let mut rows = driver::empty_rows(&plan);
            let mut entries = tuning_entries(ctx, &plan, &log, &dir, &mut rows)?;
            for entry in &mut entries {
                entry.seeds.clone_from(&base.header.seeds);
                entry.failure = Some(format!("the run failed: {e}"));
            }
            let n = entries.len();
            tuning::append_log(&log_path, entries)?;
            crate::progress::log(format!(
                "tuning log: {n} entries with the run's error appended to {}",
                teachers::rel(&log_path)
            ));
        }
        result
    }
}

/// Trains, evaluates and reports `plan` into `dir`, with `tuning_configs` from the tuning `log`;
/// a tuning run (`tuning_log`: the log's path) appends one entry per method to it.
fn run_plan(
    ctx: &RunContext,
    base: &AvoidingRecipe,
    plan: &[Entry<'_, AvoidingRecipe>],
    dir: &std::path::Path,
    log: &[tuning::LogEntry],
    tuning_log: Option<&std::path::Path>,
) -> crate::Result {
    let mut stages = StageTimes::default();
    let cores = std::thread::available_parallelism().map_or(1, |p| p.get());
    let threads = base.eval.eval_threads();
    let jobs = if base.jobs == 0 { cores } else { base.jobs };

    // One dataset per distinct `data` table (usually one), whatever the seed.
    let key = |_, pi: usize| -> crate::Result<_> { Ok(recipe::config_hash(&plan[pi].cfg.data)?) };
    let prepare = |_, pi: usize| stages.time("data", || prepare(&plan[pi].cfg.data));
    let data = Datasets::build(base.header.seeds.len(), plan.len(), key, prepare)?;
    let students = StudentCache { dir: &ctx.student_cache_dir, fresh: ctx.fresh };
    let mut trainings = driver::train_all(
        ctx,
        plan,
        &base.header.seeds,
        &data,
        jobs,
        (Some(students), &curves_of),
        &mut stages,
    )?;

    // Evaluation, one method at a time (rollouts on every core), then the seed's
    // single-threaded timing with nothing else running.
    let mut out = Collected { rows: driver::empty_rows(plan), ..Default::default() };
    for (si, &seed) in base.header.seeds.iter().enumerate() {
        let mut timed = Vec::with_capacity(plan.len());
        for (pi, e) in plan.iter().enumerate() {
            let trained = trainings.trained.remove(&(si, pi)).ok_or("internal: not trained")?;
            let first = si == 0;
            let (row, policy) =
                evaluate(e, trained, seed, first, threads, dir, &mut out, &mut stages)?;
            out.rows[pi].1.push(row);
            timed.push((pi, policy));
        }
        let t0 = Instant::now();
        time_seed(plan, &data, si, seed, timed, &mut out.rows)?;
        stages.add("timing", t0.elapsed().as_secs_f64());
    }
    let entries = tuning_entries(ctx, plan, log, dir, &mut out.rows)?;
    let summary = data.get(0, 0).summary.clone();
    write_outputs(ctx, dir, base, out, summary, trainings.teachers.log, jobs, &mut stages)?;
    if let Some(path) = tuning_log {
        let n = entries.len();
        tuning::append_log(path, entries)?;
        crate::progress::print(format!(
            "tuning log: {n} entries appended to {}",
            teachers::rel(path)
        ));
    }
    Ok(())
}

/// Adds `tuning_configs` (the method's configurations in the tuning `log`) to every row and
/// returns the run's tuning-log entries, one per method.
fn tuning_entries(
    ctx: &RunContext,
    plan: &[Entry<'_, AvoidingRecipe>],
    log: &[tuning::LogEntry],
    dir: &std::path::Path,
    rows: &mut [(String, Vec<Row>)],
) -> crate::Result<Vec<tuning::LogEntry>> {
    let revision = ctx.revision_label();
    let mut entries = Vec::with_capacity(plan.len());
    for (e, (_, rows)) in plan.iter().zip(rows.iter_mut()) {
        let n = tuning::configs_tried(log, &e.label);
        rows.iter_mut().for_each(|r| drop(r.insert("tuning_configs".into(), json!(n))));
        let id = tuning::RunId {
            method: e.label.clone(),
            config: tuning::method_config_hash(e.method, &e.recipe(), &e.cfg.data)?,
            recipe: ctx.name.clone(),
            command: ctx.command.clone(),
            revision: revision.clone(),
            run: teachers::rel(dir),
        };
        entries.push(tuning::LogEntry::from_rows(id, rows));
    }
    Ok(entries)
}

/// Rolls out one trained method on raw observations through the recipe's features and windows,
/// saves a mixture with its deployment spec (`vdd_moe::load_policy` gives a policy on raw
/// observations), records its curves and (first seed) plot panels; returns its row and the
/// deployed policy for timing.
#[allow(clippy::too_many_arguments)]
fn evaluate(
    e: &Entry<'_, AvoidingRecipe>,
    mut trained: Trained,
    seed: u64,
    first_seed: bool,
    threads: usize,
    dir: &std::path::Path,
    out: &mut Collected,
    stages: &mut StageTimes,
) -> crate::Result<(Row, Windowed<TrainedPolicy>)> {
    let (label, cfg) = (&e.label, e.cfg);
    let tag = format!("{label} s{seed}");
    let spec = cfg.data.deploy_spec();
    if let TrainedPolicy::Moe(moe) = &mut trained.policy {
        moe.set_deploy_spec(spec.clone())?;
    }
    let wrapped = Windowed::new(trained.policy.clone(), spec)?;
    let protocol = cfg.eval.protocol();
    let record = first_seed && cfg.plots.enabled;
    let spin = crate::progress::spinner(&tag, &format!("{} rollouts", cfg.eval.rollouts));
    let t0 = Instant::now();
    let ev = protocol.evaluate(&wrapped, seed, threads, record)?;
    let eval_seconds = t0.elapsed().as_secs_f64();
    stages.add("rollouts", eval_seconds);
    spin.finish_and_clear();
    if let TrainedPolicy::Moe(moe) = &trained.policy {
        let models = dir.join("models");
        std::fs::create_dir_all(&models)?;
        moe.save(&models.join(format!("{label}-s{seed}.safetensors")))?;
    }

    let m = &ev.metrics;
    crate::progress::log(format!(
        "[{tag}] success {:.3}, entropy {:.3} ({} modes), trained in {:.1} s{}, evaluated in {:.1} s",
        m.success_rate,
        m.task_entropy,
        m.modes_reached,
        trained.train_seconds,
        trained.teacher_seconds.map_or(String::new(), |t| format!(" (+ teacher {t:.1} s)")),
        eval_seconds
    ));
    let mut row = m.row_fields();
    row.insert("seed".into(), json!(seed));
    row.insert("train_seconds".into(), report::json_f64(trained.train_seconds));
    if let Some(t) = trained.teacher_seconds {
        row.insert("teacher_seconds".into(), report::json_f64(t));
    }
    if let Some(s) = trained.sampling_steps {
        row.insert("sampling_steps".into(), json!(s));
    }
    if let Some(b) = trained.budget {
        row.extend(b.fields());
    }
    if trained.curve_seconds > 0.0 {
        row.insert("curve_seconds".into(), report::json_f64(trained.curve_seconds));
    }
    out.curves.insert(format!("{label}/seed{seed}"), serde_json::to_value(&trained.curves)?);

    if record {
        let t0 = Instant::now();
        let n = cfg.plots.trajectories;
        let experts = match &trained.policy {
            TrainedPolicy::Moe(moe) if cfg.data.obs_window == 1 && cfg.data.action_chunk == 1 => {
                Some((protocol.replay_experts(&wrapped, seed, &ev, n)?, moe.num_experts()))
            }
            _ => None,
        };
        let (sr, te) = (m.success_rate, m.task_entropy);
        out.panels.push(TrajectoryPanel::from_rollouts(label, &ev.rollouts, n, experts, sr, te));
        out.curve_panels.push((label.clone(), trained.curves));
        stages.add("plots", t0.elapsed().as_secs_f64());
    }
    Ok((row, wrapped))
}

/// Inference time, single-threaded, one observation per call, with nothing else running: the
/// seed's methods take their timing rounds in turn (see `us_per_action`), in groups that share
/// the observations and the timing settings (one group unless variants change them).
fn time_seed(
    plan: &[Entry<'_, AvoidingRecipe>],
    data: &Datasets<Prepared>,
    si: usize,
    seed: u64,
    mut timed: Vec<(usize, Windowed<TrainedPolicy>)>,
    rows: &mut [(String, Vec<Row>)],
) -> crate::Result {
    let eval_seed = EvalProtocol::seed(seed);
    while let Some((first, _)) = timed.first() {
        let (timing, id) = (plan[*first].cfg.eval.timing(), data.id(si, *first));
        let same = |pi: usize| data.id(si, pi) == id && plan[pi].cfg.eval.timing() == timing;
        let (group, rest): (Vec<_>, Vec<_>) = timed.drain(..).partition(|(pi, _)| same(*pi));
        timed = rest;
        let (pis, mut policies): (Vec<usize>, Vec<_>) = group.into_iter().unzip();
        let episodes = &data.get(si, pis[0]).episodes_obs;
        let us = us_per_action(&mut policies, episodes, timing, eval_seed)?;
        let mut line = Vec::with_capacity(pis.len());
        for (pi, us) in pis.into_iter().zip(us) {
            rows[pi].1[si].insert("us_per_action".into(), report::json_f64(us));
            line.push(format!("{} {us:.1}", plan[pi].label));
        }
        crate::progress::log(format!("[s{seed}] µs per action: {}", line.join(", ")));
    }
    Ok(())
}

/// `metrics.json`, `curves.json`, `table.md`, the figures and `run.json`.
#[allow(clippy::too_many_arguments)]
fn write_outputs(
    ctx: &RunContext,
    dir: &std::path::Path,
    base: &AvoidingRecipe,
    out: Collected,
    data_summary: Value,
    teacher_log: Vec<Value>,
    jobs: usize,
    stages: &mut StageTimes,
) -> crate::Result {
    let mut metrics = report::metrics_json(&ctx.name, "avoiding", &base.header.seeds, &out.rows);
    metrics.insert("data".into(), data_summary.clone());
    if let Some(w) = report::unequal_budgets(&out.rows) {
        crate::progress::log(format!("\nWARNING: unequal budgets: {w}\n"));
        metrics.insert("budget_warning".into(), json!(w));
    }
    let curves = serde_json::to_string(&out.curves)?;
    vdd_nn::io::write_atomic(&dir.join("curves.json"), curves.as_bytes())?;
    let table = format!(
        "## {} (Avoiding)\n\n{}\n\n{}\nmean ± std over seeds {:?}; {} rollouts per method and seed; µs per action: single-threaded `Policy::act` on one observation.\n",
        ctx.name,
        base.header.description,
        report::markdown_table(&out.rows, &COLUMNS),
        base.header.seeds,
        base.eval.rollouts
    );
    let mut figures = Vec::new();
    if base.plots.enabled && !out.panels.is_empty() {
        let t0 = Instant::now();
        let png = base.plots.png;
        figures.extend(plots::avoiding_trajectories(&dir.join("trajectories"), &out.panels, png)?);
        figures.extend(plots::learning_curves(&dir.join("curves"), &out.curve_panels, png)?);
        figures.extend(plots::mode_histograms(
            &dir.join("modes"),
            &report::mode_shares(&out.rows),
            png,
        )?);
        stages.add("plots", t0.elapsed().as_secs_f64());
    }
    let details = json!({
        "figures": figures,
        "data": data_summary,
        "teachers": teacher_log,
        "jobs": jobs,
        "stage_seconds": stages.to_json(),
    });
    driver::write_results(ctx, dir, &metrics, &table, details)?;
    crate::acceptance::avoiding_acceptance(&out.rows).iter().for_each(crate::progress::print);
    crate::progress::print(format!("stages: {}", stages.summary()));
    let cpu = crate::context::cpu_seconds().map_or(String::new(), |c| format!(", {c:.0} s CPU"));
    let wall = ctx.started.elapsed().as_secs_f64();
    crate::progress::print(format!("results in {} ({wall:.1} s wall{cpu})", teachers::rel(dir)));
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Registry;

    #[test]
    fn the_defaults_file_is_complete_and_valid() {
        recipe::check_complete_defaults::<AvoidingRecipe>(&[(
            "recipes/defaults/avoiding.toml",
            DEFAULTS,
        )])
        .unwrap_or_else(|e| panic!("{e}"));
    }

    #[test]
    fn recipes_in_the_repository_resolve() {
        for name in [
            "avoiding",
            "avoiding-ablation-experts",
            "avoiding-ablation-gating",
            "avoiding-ablation-noise",
            "avoiding-deviations",
        ] {
            let path = recipe::recipe_path(name).unwrap();
            let file = recipe::read_recipe(&path).unwrap();
            for quick in [false, true] {
                let o = recipe::Overrides { quick, ..Default::default() };
                let r = recipe::resolve(&AvoidingRecipe::defaults().unwrap(), &file, &o)
                    .unwrap_or_else(|e| panic!("{name}: {e}"));
                driver::plan(&Registry::builtin(), &r, "avoiding", &[])
                    .unwrap_or_else(|e| panic!("{name}: {e}"));
            }
        }
    }

    #[test]
    fn a_set_that_a_row_would_not_read_is_refused_naming_both_keys() {
        let file = recipe::read_recipe(&recipe::recipe_path("avoiding").unwrap()).unwrap();
        let defaults = AvoidingRecipe::defaults().unwrap();
        let plan_with = |methods: &str, sets: &[&str]| {
            let sets: Vec<(String, String)> = sets
                .iter()
                .map(|s| s.split_once('=').map(|(k, v)| (k.into(), v.into())).unwrap())
                .collect();
            let methods = Some(methods.split(',').map(String::from).collect());
            let o = recipe::Overrides { quick: true, methods, sets: sets.clone(), seeds: None };
            let r = recipe::resolve(&defaults, &file, &o).unwrap();
            driver::plan(&Registry::builtin(), &r, "avoiding", &sets)
                .map(|p| p.len())
                .map_err(|e| e.to_string())
        };
        // `cargo xtask experiment avoiding --quick --methods vdd-beso --set student.num_experts=4`
        let e = plan_with("vdd-beso", &["student.num_experts=4"]).unwrap_err();
        assert!(e.contains("student.num_experts") && e.contains("vdd.beso_experts"), "{e}");
        let e = plan_with("em,vdd-ddpm", &["student.num_experts=4"]).unwrap_err();
        assert!(e.contains("vdd-ddpm") && e.contains("vdd.ddpm_experts"), "{e}");
        let e = plan_with("vdd-beso-learned", &["vdd.beso_gating=uniform"]).unwrap_err();
        assert!(e.contains("vdd-beso-learned") && e.contains("fixes"), "{e}");
        // Rows that read the shared key take it; a row's own key set beside it takes effect.
        assert_eq!(plan_with("em,imc", &["student.num_experts=4"]), Ok(2));
        assert_eq!(plan_with("vdd-ddpm", &["student.gating=uniform"]), Ok(1));
        let both = ["student.num_experts=4", "vdd.beso_experts=4"];
        assert_eq!(plan_with("em,vdd-beso", &both), Ok(2));
    }

    #[test]
    fn method_keys_are_checked() {
        let file = recipe::read_recipe(&recipe::recipe_path("avoiding").unwrap()).unwrap();
        let defaults = AvoidingRecipe::defaults().unwrap();
        for (set, what) in [
            ("baselines.emm.iterations=3", "baselines.emm"),
            ("baselines.em.iteratons=3", "iteratons"),
            ("vdd.beso_gating=sometimes", "vdd-beso"),
            // A schedule written in another unit than its teacher's levels.
            (
                "vdd.ddpm.noise_unit=\"sigma\"",
                "vdd.ddpm: invalid configuration: noise_unit is sigma",
            ),
            ("vdd.beso.noise_unit=\"time\"", "vdd.beso: invalid configuration: noise_unit is time"),
        ] {
            let (k, v) = set.split_once('=').unwrap();
            let o = recipe::Overrides { sets: vec![(k.into(), v.into())], ..Default::default() };
            let e = match recipe::resolve(&defaults, &file, &o) {
                Ok(r) => driver::plan(&Registry::builtin(), &r, "avoiding", &o.sets)
                    .err()
                    .unwrap()
                    .to_string(),
                Err(e) => e.to_string(),
            };
            assert!(e.contains(what), "{set}: {e}");
        }
    }
}
