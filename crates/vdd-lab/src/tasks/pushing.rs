//! The D3IL Pushing pipeline: scripted demonstrations → dataset
//! ([`vdd_tasks::pushing::dataset`]) → teachers (cached) → every method → rollouts
//! ([`vdd_tasks::pushing::EvalProtocol`]: test contexts × rollouts per context; success, p1,
//! D3IL's mean distance, task entropy per context over the four modes) and µs per action →
//! `metrics.json`, `table.md`, `curves.json`, the mode histograms (the demonstrations' and each
//! method's), trajectory figures coloured by mode (the demonstrations' and each method's, first
//! seed) and learning curves.
//!
//! The stages are Avoiding's ([`super::rollouts`]): the demonstrations come from `data.seed`
//! (one dataset for every run seed), the run seed drives the teachers, the students and the
//! rollouts (the same episodes for every method of a seed), and `--tuning` runs the tuning
//! seeds 100–104 on their own demonstrations, appending to `docs/pushing-tuning-log.toml`
//! ([`crate::tuning`]). No curves over training are taken on this task.

use std::time::Instant;

use serde::{Deserialize, Serialize};
use serde_json::Value;
use toml::Table;
use vdd_data::Windowed;
use vdd_moe::MoeConfig;
use vdd_tasks::pushing::EvalProtocol;
use vdd_tasks::pushing::dataset::DatasetConfig;
use vdd_tasks::pushing::oracle::generate_demonstrations;
use vdd_tasks::timing::Timing;

use super::rollouts::{self, Prepared, RolloutRecipe, Visits};
use crate::context::{RunContext, StageTimes};
use crate::driver::{self, Entry, Probes, Task, TaskRecipe};
use crate::method::Trained;
use crate::plots::{self, Curves};
use crate::policy::TrainedPolicy;
use crate::recipe::{self, Overrides};
use crate::report::{self, Row};
use crate::teachers::TeachersConfig;
use crate::tuning;
use vdd_tasks::pushing::rollout::Metrics;
use vdd_tasks::pushing::{EnvConfig, PushingEnv};

/// A recipe of the Pushing task (see `recipes/pushing.toml`); the values not given there
/// come from `recipes/defaults/pushing.toml` ([`Self::defaults`]). Unknown keys are errors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PushingRecipe {
    /// Name, description, task (`pushing`), seeds and methods.
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
    /// The baselines' settings, read by their methods.
    pub baselines: Table,
    /// Rollouts and timing.
    pub eval: PushingEval,
    /// Figures.
    pub plots: PushingPlots,
}

/// `recipes/defaults/pushing.toml`, embedded so that the binary is self-contained.
const DEFAULTS: &str = include_str!("../../../../recipes/defaults/pushing.toml");

impl PushingRecipe {
    /// The task's defaults, `recipes/defaults/pushing.toml`, which a recipe file overrides.
    pub fn defaults() -> recipe::RecipeResult<Self> {
        recipe::defaults_from_toml(&[("recipes/defaults/pushing.toml", DEFAULTS)])
    }
}

/// The `[eval]` table: the rollouts ([`Self::protocol`]) and the timing ([`Self::timing`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PushingEval {
    /// Test contexts (start states) per method and seed.
    pub contexts: usize,
    /// Rollouts per context.
    pub rollouts_per_context: usize,
    /// Environments stepped together with one batched `act_batch` (0: one episode at a time).
    pub lockstep_batch: usize,
    /// Evaluation threads (0: all cores).
    pub threads: usize,
    /// Timed single-observation `Policy::act` calls for µs per action (single thread).
    pub timing_calls: usize,
    /// Untimed calls before timing.
    pub timing_warmup: usize,
    /// The shortest timing round in milliseconds.
    pub timing_min_round_ms: f64,
}

impl PushingEval {
    /// The rollouts' protocol (the seed comes from the run seed).
    pub fn protocol(&self) -> EvalProtocol {
        EvalProtocol::new(self.contexts, self.rollouts_per_context, self.lockstep_batch)
    }

    /// The settings of `us_per_action`.
    pub fn timing(&self) -> Timing {
        Timing {
            calls: self.timing_calls,
            warmup: self.timing_warmup,
            min_round_ms: self.timing_min_round_ms,
        }
    }

    /// The threads the rollouts run on: `threads`, or every core when it is 0.
    pub fn eval_threads(&self) -> usize {
        match self.threads {
            0 => std::thread::available_parallelism().map_or(1, |p| p.get()),
            n => n,
        }
    }
}

/// The `[plots]` table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PushingPlots {
    /// Write the mode histograms, trajectory figures and learning curves.
    pub enabled: bool,
    /// Also write PNGs (SVG always).
    pub png: bool,
    /// Paths per panel of the trajectory figures: rollouts of each method spread over the
    /// contexts (first seed), and as many demonstrations (0: no trajectory figures).
    pub trajectories: usize,
}

impl TaskRecipe for PushingRecipe {
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

impl RolloutRecipe for PushingRecipe {
    type Data = DatasetConfig;
    const TASK: &'static str = "pushing";
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
        self.eval.protocol().check().map_err(|e| format!("eval: {e}"))?;
        self.eval.timing().check().map_err(|e| format!("eval: {e}"))?;
        self.data.deploy_spec().validate().map_err(|e| format!("data: {e}"))?;
        self.data.oracle.validate().map_err(|e| format!("data.oracle: {e}"))?;
        Ok(())
    }
    fn prepare(&self) -> crate::Result<Prepared> {
        let t0 = Instant::now();
        let d = self.data.build()?;
        let counts = d.mode_counts.clone();
        let mut p = Prepared::new(d, self.data.demonstrations, vdd_tasks::pushing::N_MODES, t0);
        p.summary["dataset_mode_counts"] = serde_json::json!(counts);
        Ok(p)
    }
}

/// The D3IL Pushing task.
pub struct Pushing;

/// The columns of Pushing's tables.
pub const COLUMNS: [report::Column; 7] = [
    report::Column::new("success_rate", "success", 3),
    report::Column::new("p1_rate", "p1", 3),
    report::Column::new("mean_distance", "mean distance", 4),
    report::Column::new("task_entropy", "task entropy", 3),
    report::Column::new("mode_entropy", "mode entropy", 3),
    report::Column::new("us_per_action", "µs / action", 1),
    report::Column::new("train_seconds", "train s", 1),
];

impl Task for Pushing {
    fn name(&self) -> &'static str {
        "pushing"
    }

    fn columns(&self) -> Vec<report::Column> {
        COLUMNS.to_vec()
    }

    /// `--tuning`: the tuning seeds (unless given) and the tuning demonstrations.
    fn apply_shorthands(
        &self,
        given: &[(String, String)],
        o: &mut Overrides,
    ) -> Result<(), String> {
        given.iter().try_for_each(|(k, _)| rollouts::tuning_shorthand(self.name(), k, o))
    }

    fn run(&self, ctx: &RunContext) -> crate::Result {
        let resolved = recipe::resolve(&PushingRecipe::defaults()?, &ctx.file, &ctx.overrides)?;
        let base = &resolved.base;
        let plan = driver::plan(&ctx.registry, &resolved, "pushing", &ctx.overrides.sets)?;
        let threads = base.eval.eval_threads();
        let probes = |cfg: &PushingRecipe| Probes {
            curves: None,
            visits: Some(Box::new(Visits::<PushingEnv, Metrics>::new(
                &EnvConfig::default(),
                cfg.data.deploy_spec(),
                "pushing-visits",
            ))),
        };
        rollouts::run_logged(ctx, &resolved, &plan, |dir, log, tuning_log| {
            let eval = |e: &Entry<'_, PushingRecipe>,
                        trained,
                        seed,
                        first: bool,
                        kept: &mut _,
                        st: &mut _| {
                evaluate(e, trained, seed, threads, dir, st, first.then_some(kept))
            };
            let write = |out, kept, st: &mut _| write_outputs(ctx, dir, base, out, kept, st);
            rollouts::run_plan(ctx, base, &plan, dir, log, tuning_log, &probes, eval, write)
        })
    }
}

/// What the first seed's evaluations keep for the figures: learning curves and trajectory
/// panels, per method.
#[derive(Default)]
struct FirstSeed {
    curves: Vec<(String, Curves)>,
    panels: Vec<vdd_report::plots::TrajectoryPanel>,
}

/// Rolls out one trained method on raw observations through the recipe's window and chunk,
/// saves a mixture with its deployment spec, keeps its learning curves and the paths of its
/// first rollouts (`first`, first seed); returns its row and the deployed policy for timing.
fn evaluate(
    e: &Entry<'_, PushingRecipe>,
    mut trained: Trained,
    seed: u64,
    threads: usize,
    dir: &std::path::Path,
    stages: &mut StageTimes,
    first: Option<&mut FirstSeed>,
) -> crate::Result<(Row, Windowed<TrainedPolicy>)> {
    let (label, cfg) = (&e.label, e.cfg);
    let protocol = cfg.eval.protocol();
    let record = first.is_some() && cfg.plots.enabled && cfg.plots.trajectories > 0;
    let (spec, n) = (cfg.data.deploy_spec(), protocol.rollouts());
    let (wrapped, ev, eval_seconds) =
        rollouts::roll_out(&mut trained, spec, label, seed, n, dir, stages, |w| {
            Ok(protocol.evaluate(w, seed, threads, record)?)
        })?;
    let tag = format!("{label} s{seed}");
    let m = &ev.metrics;
    crate::progress::log(format!(
        "[{tag}] success {:.3}, p1 {:.3}, mean distance {:.4}, task entropy {:.3}, mode entropy {:.3} (modes {:?}), trained in {:.1} s{}, evaluated in {:.1} s",
        m.success_rate,
        m.p1_rate.unwrap_or_default(),
        m.mean_distance,
        m.task_entropy,
        m.mode_entropy,
        m.mode_counts,
        trained.train_seconds,
        rollouts::teacher_note(&trained),
        eval_seconds
    ));
    let row = rollouts::trained_row(m.row_fields(), &trained, seed);
    if let Some(first) = first {
        if record {
            // Spread the drawn rollouts over the contexts: every `k`-th episode.
            let n = cfg.plots.trajectories;
            let step = (ev.rollouts.len() / n.max(1)).max(1);
            let paths: Vec<_> = ev
                .rollouts
                .iter()
                .step_by(step)
                .take(n)
                .filter_map(|r| {
                    let t = r.trajectory.as_ref()?;
                    let mode = r.success().then_some(r.info.mode).flatten().map(|m| m.index());
                    Some((&t.observations, Some(t.final_observation.as_slice()), mode))
                })
                .collect();
            first.panels.push(plots::pushing_panel(label, &paths, m.success_rate, m.task_entropy));
        }
        first.curves.push((label.clone(), trained.curves));
    }
    Ok((row, wrapped))
}

/// The demonstrations' panel: the first `n` demonstrations of the recipe's data settings,
/// coloured by mode, titled with the demonstrator's success rate and the entropy of their
/// modes.
fn demonstrations_panel(
    base: &PushingRecipe,
    n: usize,
) -> crate::Result<vdd_report::plots::TrajectoryPanel> {
    let d = &base.data;
    let demos = generate_demonstrations(n, d.seed, &d.oracle)?;
    let paths: Vec<_> = demos
        .observations
        .iter()
        .zip(&demos.modes)
        .map(|(o, m)| (o, None, Some(m.index())))
        .collect();
    let entropy = f64::from(vdd_tasks::normalized_entropy(&demos.mode_counts()));
    Ok(plots::pushing_panel("demonstrations", &paths, demos.success_rate(), entropy))
}

/// `metrics.json`, `curves.json`, `table.md`, the figures and `run.json`; returns the
/// tuning-log entries.
fn write_outputs(
    ctx: &RunContext,
    dir: &std::path::Path,
    base: &PushingRecipe,
    out: rollouts::Outcome,
    first: FirstSeed,
    stages: &mut StageTimes,
) -> crate::Result<Vec<tuning::LogEntry>> {
    let metrics = rollouts::metrics(ctx, base, &out);
    let json: serde_json::Map<String, Value> = first
        .curves
        .iter()
        .map(|(l, c)| Ok((l.clone(), serde_json::to_value(c)?)))
        .collect::<crate::Result<_>>()?;
    vdd_nn::io::write_atomic(&dir.join("curves.json"), serde_json::to_string(&json)?.as_bytes())?;
    let p = base.eval.protocol();
    let table = format!(
        "## {} (Pushing)\n\n{}\n\n{}\nmean ± std over seeds {:?}; {} contexts × {} rollouts per method and seed; success: both boxes in distinct targets; p1: a box reached a target; mean distance: D3IL's ½ (min d_r + min d_g) at the last step; task entropy: D3IL's, per context over the 4 modes of the successes (log base 4), averaged over contexts; mode entropy: over all successes pooled; µs per action: single-threaded `Policy::act` on one observation.\n",
        ctx.name,
        base.header.description,
        report::markdown_table(&out.rows, &COLUMNS),
        base.header.seeds,
        p.contexts,
        p.rollouts_per_context
    );
    let mut figures = Vec::new();
    if base.plots.enabled {
        let t0 = Instant::now();
        let png = base.plots.png;
        figures.extend(plots::learning_curves(&dir.join("curves"), &first.curves, png)?);
        let mut shares = Vec::new();
        if let Some(counts) = out.data_summary["dataset_mode_counts"].as_array() {
            let counts: Vec<f64> = counts.iter().map(|c| c.as_f64().unwrap_or(0.0)).collect();
            let total: f64 = counts.iter().sum();
            if total > 0.0 {
                shares.push((
                    "demonstrations".to_owned(),
                    counts.iter().map(|c| c / total).collect(),
                ));
            }
        }
        shares.extend(report::mode_shares(&out.rows));
        figures.extend(plots::mode_histograms(&dir.join("modes"), &shares, png)?);
        if base.plots.trajectories > 0 {
            let mut panels = vec![demonstrations_panel(base, base.plots.trajectories)?];
            panels.extend(first.panels);
            figures.extend(plots::pushing_trajectories(&dir.join("trajectories"), &panels, png)?);
        }
        stages.add("plots", t0.elapsed().as_secs_f64());
    }
    rollouts::finish(ctx, dir, &metrics, &table, out, figures, Vec::new(), stages)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Registry;

    #[test]
    fn the_defaults_file_is_complete_and_valid() {
        recipe::check_complete_defaults::<PushingRecipe>(&[(
            "recipes/defaults/pushing.toml",
            DEFAULTS,
        )])
        .unwrap_or_else(|e| panic!("{e}"));
    }

    #[test]
    fn the_recipe_resolves_and_plans_every_method() {
        let path = recipe::recipe_path("pushing").unwrap();
        let file = recipe::read_recipe(&path).unwrap();
        for quick in [false, true] {
            for methods in [None, Some(vec!["all".to_owned()])] {
                let o = recipe::Overrides { quick, methods, ..Default::default() };
                let r = recipe::resolve(&PushingRecipe::defaults().unwrap(), &file, &o)
                    .unwrap_or_else(|e| panic!("{e}"));
                r.base.check_before_training().unwrap();
                let plan = driver::plan(&Registry::builtin(), &r, "pushing", &[])
                    .unwrap_or_else(|e| panic!("{e}"));
                assert!(!plan.is_empty());
            }
        }
    }

    #[test]
    fn tuning_sets_the_tuning_seeds_and_data() {
        let mut o = recipe::Overrides::default();
        Pushing.apply_shorthands(&[("tuning".into(), "true".into())], &mut o).unwrap();
        assert_eq!(o.seeds, Some(tuning::TUNING_SEEDS.collect()));
        assert_eq!(o.sets[0], ("data.seed".into(), tuning::TUNING_DATA_SEED.to_string()));
        let e = Pushing.apply_shorthands(&[("teacher".into(), "x".into())], &mut o);
        assert!(e.unwrap_err().contains("pushing"));
    }
}
