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

use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use toml::Table;
use vdd_data::Windowed;
use vdd_moe::MoeConfig;

use vdd_tasks::avoiding::dataset::DatasetConfig;
use vdd_tasks::avoiding::{
    AvoidingEval, CURVE_ENTROPY, CURVE_SUCCESS, DeployedCurves, EvalProtocol, PlotSettings,
};
use vdd_tasks::timing::Timing;
use vdd_tasks::{AvoidingEnv, Metrics};

use super::rollouts::{self, Prepared, RolloutRecipe, Visits};
use crate::context::{RunContext, StageTimes};
use crate::driver::{self, Entry, Probes, Task, TaskRecipe};
use crate::method::{CurveEval, Trained};
use crate::plots::{self, Curves, TrajectoryPanel};
use crate::policy::TrainedPolicy;
use crate::recipe::{self, Overrides};
use crate::report::{self, Row};
use crate::task::Capability;
use crate::teachers::TeachersConfig;
use crate::tuning;

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
    /// A teacher imported from PyTorch (`--teacher FILE`): the file of the rows `imported`
    /// and `vdd-imported` ([`crate::teachers::Imported`]).
    pub imported: ImportedSettings,
}

/// The `[imported]` table of the Avoiding recipes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImportedSettings {
    /// The teacher file (a `cargo xtask import` file; `--teacher FILE`); empty: none.
    pub teacher: String,
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

impl RolloutRecipe for AvoidingRecipe {
    type Data = DatasetConfig;
    const TASK: &'static str = "avoiding";
    fn data(&self) -> &DatasetConfig {
        &self.data
    }
    fn data_seed(&self) -> u64 {
        self.data.seed
    }
    fn jobs(&self) -> usize {
        self.jobs
    }
    fn timing(&self) -> Timing {
        self.eval.timing()
    }
    fn eval_seed(run_seed: u64) -> u64 {
        EvalProtocol::seed(run_seed)
    }
    fn check_before_training(&self) -> crate::Result {
        self.eval.check().map_err(|e| format!("eval: {e}"))?;
        self.data.deploy_spec().validate().map_err(|e| format!("data: {e}"))?;
        Ok(())
    }
    fn prepare(&self) -> crate::Result<Prepared> {
        let t0 = Instant::now();
        let d = self.data.build()?;
        Ok(Prepared::new(d, self.data.demonstrations, 24, t0))
    }
    fn raw_train_episodes(&self) -> crate::Result<rollouts::RawEpisodes> {
        let (train, raw_obs) = self.data.train_episodes()?;
        Ok((raw_obs, train.to_episode_matrices().1))
    }
}

/// What Avoiding's episodes give a training, through the recipe's features and windows: curves
/// over training (none when `eval.curve_points` is 0) and visited states.
fn probes_of(cfg: &AvoidingRecipe) -> Probes {
    let spec = cfg.data.deploy_spec();
    let curves = DeployedCurves { protocol: cfg.eval.curves(), spec: spec.clone() };
    Probes {
        curves: curves.protocol.enabled().then(|| Box::new(curves) as Box<dyn CurveEval>),
        visits: Some(Box::new(Visits::<AvoidingEnv, Metrics>::new(&(), spec, "avoiding-visits"))),
    }
}

impl CurveEval for DeployedCurves {
    fn key(&self) -> Value {
        json!({ "protocol": self.protocol, "spec": self.spec })
    }
    fn series(&self) -> Vec<String> {
        [CURVE_SUCCESS, CURVE_ENTROPY].map(String::from).to_vec()
    }
}

/// What the evaluation collects for the figures.
#[derive(Default)]
struct Collected {
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

    fn offers(&self) -> &'static [Capability] {
        &[
            Capability::Rollouts,
            Capability::LearnedTeachers,
            Capability::RawEpisodes,
            Capability::TrainingCurves,
        ]
    }

    /// `--tuning`: the tuning seeds (unless given) and the tuning demonstrations; `--teacher
    /// FILE`: an imported teacher and its VDD student (rows `imported,vdd-imported` unless
    /// `--methods` names others; `teacher` and `vdd` there stand for those two).
    fn apply_shorthands(
        &self,
        given: &[(String, String)],
        o: &mut Overrides,
    ) -> Result<(), String> {
        for (k, v) in given {
            if k == "teacher" {
                o.sets.insert(0, ("imported.teacher".into(), format!("{v:?}")));
                let methods = o.methods.get_or_insert_with(|| vec!["teacher".into(), "vdd".into()]);
                for m in methods.iter_mut() {
                    match m.as_str() {
                        "teacher" => *m = "imported".into(),
                        "vdd" => *m = "vdd-imported".into(),
                        _ => {}
                    }
                }
                continue;
            }
            rollouts::tuning_shorthand(self.name(), k, o)?;
        }
        Ok(())
    }

    fn run(&self, ctx: &RunContext) -> crate::Result {
        let resolved = recipe::resolve(&AvoidingRecipe::defaults()?, &ctx.file, &ctx.overrides)?;
        let base = &resolved.base;
        let plan = driver::plan(&ctx.registry, &resolved, "avoiding", &ctx.overrides.sets)?;
        rollouts::run_logged(ctx, &resolved, &plan, |dir, log, tuning_log| {
            run_plan(ctx, base, &plan, dir, log, tuning_log)
        })
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
    let threads = base.eval.eval_threads();
    let eval = |e: &Entry<'_, AvoidingRecipe>, trained, seed, first, kept: &mut _, st: &mut _| {
        evaluate(e, trained, seed, first, threads, dir, kept, st)
    };
    let write = |out, kept, st: &mut _| write_outputs(ctx, dir, base, out, kept, st);
    rollouts::run_plan(ctx, base, plan, dir, log, tuning_log, &probes_of, eval, write)
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
    let protocol = cfg.eval.protocol();
    let record = first_seed && cfg.plots.enabled;
    // The task's features and windows, or those of a policy of a file teacher's windows.
    let spec = trained.deploy.clone().unwrap_or_else(|| cfg.data.deploy_spec());
    let n = cfg.eval.rollouts;
    let (wrapped, ev, eval_seconds) =
        rollouts::roll_out(&mut trained, spec, label, seed, n, dir, stages, |w| {
            Ok(protocol.evaluate(w, seed, threads, record)?)
        })?;
    let tag = format!("{label} s{seed}");

    let m = &ev.metrics;
    crate::progress::log(format!(
        "[{tag}] success {:.3}, entropy {:.3} ({} modes), {}{}, evaluated in {:.1} s",
        m.success_rate,
        m.task_entropy,
        m.modes_reached,
        rollouts::trained_note(&trained),
        rollouts::teacher_note(&trained),
        eval_seconds
    ));
    let row = rollouts::trained_row(m.row_fields(), &trained, seed);
    out.curves.insert(format!("{label}/seed{seed}"), serde_json::to_value(&trained.curves)?);

    if record {
        let t0 = Instant::now();
        let n = cfg.plots.trajectories;
        let experts = match &trained.policy {
            TrainedPolicy::Moe(moe) if spec_is_single_step(&trained, cfg) => {
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

/// Whether `trained` acts on one observation per action (no window, no chunk): the expert
/// replay of the figures needs it.
fn spec_is_single_step(trained: &Trained, cfg: &AvoidingRecipe) -> bool {
    match &trained.deploy {
        Some(s) => s.obs_window == 1 && s.action_chunk == 1,
        None => cfg.data.obs_window == 1 && cfg.data.action_chunk == 1,
    }
}

/// `metrics.json`, `curves.json`, `table.md`, the figures and `run.json`; returns the tuning-log
/// entries.
fn write_outputs(
    ctx: &RunContext,
    dir: &std::path::Path,
    base: &AvoidingRecipe,
    out: rollouts::Outcome,
    collected: Collected,
    stages: &mut StageTimes,
) -> crate::Result<Vec<tuning::LogEntry>> {
    let metrics = rollouts::metrics(ctx, base, &out);
    let curves = serde_json::to_string(&collected.curves)?;
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
    if base.plots.enabled && !collected.panels.is_empty() {
        let t0 = Instant::now();
        let png = base.plots.png;
        let panels = &collected.panels;
        figures.extend(plots::avoiding_trajectories(&dir.join("trajectories"), panels, png)?);
        let curve_panels = &collected.curve_panels;
        figures.extend(plots::learning_curves(&dir.join("curves"), curve_panels, png)?);
        figures.extend(plots::mode_histograms(
            &dir.join("modes"),
            &report::mode_shares(&out.rows),
            png,
        )?);
        stages.add("plots", t0.elapsed().as_secs_f64());
    }
    let lines = crate::acceptance::avoiding_acceptance(&out.rows);
    rollouts::finish(ctx, dir, &metrics, &table, out, figures, lines, stages)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Registry;

    fn resolved(shorthands: &[(String, String)], mut o: Overrides) -> AvoidingRecipe {
        Avoiding.apply_shorthands(shorthands, &mut o).unwrap();
        let file = recipe::read_recipe(&recipe::recipe_path("avoiding").unwrap()).unwrap();
        recipe::resolve(&AvoidingRecipe::defaults().unwrap(), &file, &o).unwrap().base
    }

    #[test]
    fn the_teacher_option_names_the_file_and_its_rows() {
        let plain = resolved(&[], Overrides::default());
        assert!(plain.imported.teacher.is_empty(), "no teacher file by default");
        let given = [("teacher".to_owned(), r"dir with space/t\1.safetensors".to_owned())];
        let r = resolved(&given, Overrides::default());
        assert_eq!(r.imported.teacher, r"dir with space/t\1.safetensors");
        assert_eq!(r.header.methods, ["imported", "vdd-imported"]);
        // `teacher` and `vdd` stand for the file's rows; other rows stay as named.
        let only =
            Overrides { methods: Some(vec!["vdd".into(), "beso".into()]), ..Default::default() };
        assert_eq!(resolved(&given, only).header.methods, ["vdd-imported", "beso"]);
    }

    #[test]
    fn rows_of_a_teacher_file_need_the_file_and_all_leaves_them_out() {
        let plan = |methods: &[&str]| {
            let methods = Some(methods.iter().map(|m| (*m).to_owned()).collect());
            let r = recipe::resolve(
                &AvoidingRecipe::defaults().unwrap(),
                &recipe::read_recipe(&recipe::recipe_path("avoiding").unwrap()).unwrap(),
                &Overrides { quick: true, methods, ..Default::default() },
            )
            .unwrap();
            driver::plan(&Registry::builtin(), &r, "avoiding", &[])
                .map(|p| p.iter().map(|e| e.label.clone()).collect::<Vec<_>>())
                .map_err(|e| e.to_string())
        };
        let all = plan(&["all"]).unwrap();
        assert!(all.iter().all(|l| !l.contains("imported")), "{all:?}");
        let e = plan(&["vdd-imported"]).unwrap_err();
        assert!(e.contains("--teacher FILE") && e.contains("imported.teacher"), "{e}");
        // A file that is not there is named.
        let e = {
            let file = recipe::read_recipe(&recipe::recipe_path("avoiding").unwrap()).unwrap();
            let o = Overrides {
                methods: Some(vec!["imported".into()]),
                sets: vec![("imported.teacher".into(), "\"/nonexistent/t.safetensors\"".into())],
                ..Default::default()
            };
            let r = recipe::resolve(&AvoidingRecipe::defaults().unwrap(), &file, &o).unwrap();
            driver::plan(&Registry::builtin(), &r, "avoiding", &o.sets).err().unwrap().to_string()
        };
        assert!(e.contains("/nonexistent/t.safetensors"), "{e}");
    }

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
            "avoiding-table",
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
            // Visited states feed a gating fit, which must be asked for; bounded rounds.
            ("vdd.beso_gating_visits={episodes=10,rounds=1}", "needs vdd.beso_gating_fit"),
            ("vdd.beso_gating_visits={episodes=10,rounds=0,extra=1}", "extra"),
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
