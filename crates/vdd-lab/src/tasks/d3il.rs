//! The D3IL contact tasks' pipeline (Pushing, Aligning; [`vdd_tasks::d3il`]), one body for
//! both: scripted demonstrations → dataset ([`vdd_tasks::demo_data`]) → teachers (cached) →
//! every method → rollouts ([`vdd_tasks::d3il::EvalProtocol`]: test contexts × rollouts per
//! context; success, p1 where the task counts it, D3IL's mean distance, task entropy per
//! context over the task's modes) and µs per action → `metrics.json`, `table.md`,
//! `curves.json`, the mode histograms (the demonstrations' and each method's), trajectory
//! figures coloured by mode (the demonstrations' and each method's, first seed) and learning
//! curves.
//!
//! A task is a [`D3ilTask`]: its environment, its demonstrator's settings, its title,
//! defaults, table columns and figures (`tasks/pushing.rs`, `tasks/aligning.rs`); its recipe
//! is [`D3ilRecipe`] and the driver runs it as [`D3il`].
//!
//! The stages are Avoiding's ([`super::rollouts`]): the demonstrations come from `data.seed`
//! (one dataset for every run seed), the run seed drives the teachers, the students and the
//! rollouts (the same episodes for every method of a seed), and `--tuning` runs the tuning
//! seeds 100–104 on their own demonstrations, appending to `docs/<task>-tuning-log.toml`
//! ([`crate::tuning`]). No curves over training are taken on these tasks.

use std::marker::PhantomData;
use std::path::Path;
use std::time::Instant;

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use serde_json::Value;
use toml::Table;
use vdd_data::Windowed;
use vdd_moe::MoeConfig;
use vdd_report::plots::TrajectoryPanel;
use vdd_tasks::d3il::rollout::Metrics;
use vdd_tasks::d3il::{ContextEnv, ContextOutcome, EnvConfig, EvalProtocol};
use vdd_tasks::demo_data::{DemoDataConfig, Demonstrator};
use vdd_tasks::scripted::Mode as _;
use vdd_tasks::timing::Timing;

use super::rollouts::{self, Prepared, RolloutRecipe, Visits};
use crate::context::{RunContext, StageTimes};
use crate::driver::{self, Entry, Probes, Task, TaskRecipe};
use crate::method::Trained;
use crate::plots::{self, Curves, PushingPath};
use crate::policy::TrainedPolicy;
use crate::recipe::{self, Overrides};
use crate::report::{self, Row};
use crate::teachers::TeachersConfig;
use crate::tuning;

/// A D3IL contact task as the experiment layer runs it: what differs between Pushing and
/// Aligning (`tasks/pushing.rs`, `tasks/aligning.rs`).
pub trait D3ilTask: Sync + 'static {
    /// The environment; its [`ContextEnv::NAME`] is the task's name (a recipe's `task`).
    type Env: ContextEnv;
    /// The scripted demonstrator's settings (the `data.oracle` table).
    type Oracle: Demonstrator<Mode = <<Self::Env as ContextEnv>::Outcome as ContextOutcome>::Mode>
        + Serialize
        + DeserializeOwned
        + Clone
        + std::fmt::Debug
        + PartialEq
        + Sync;
    /// The name in titles (`Pushing`).
    const TITLE: &'static str;
    /// The defaults file and its text (`recipes/defaults/<task>.toml`, embedded).
    const DEFAULTS: (&'static str, &'static str);
    /// The columns of the task's tables.
    const COLUMNS: &'static [report::Column];
    /// The seed stream of the episodes whose states a policy visits ([`Probes::visits`]).
    const VISITS_STREAM: &'static str;
    /// What the table's figures mean, from `success:` to the task entropy (`table.md`).
    const TABLE_NOTE: &'static str;

    /// Checks the demonstrator's settings.
    const CHECK_ORACLE: fn(&Self::Oracle) -> Result<(), vdd_tasks::TaskError>;
    /// One panel of the trajectory figure, the paths coloured by mode.
    const PANEL: PanelFn;
    /// Writes the trajectory figure.
    const TRAJECTORIES: FigureFn;
}

/// A task's trajectory panel: `(label, paths, success rate, task entropy)` → the panel, each
/// path coloured by its mode (e.g. [`plots::pushing_panel`]).
pub type PanelFn = fn(&str, &[PushingPath<'_>], f64, f64) -> TrajectoryPanel;

/// A task's trajectory figure: `(stem, panels, png)` → writes `stem.svg` (and `stem.png` when
/// `png`) and returns the files written (e.g. [`plots::pushing_trajectories`]).
pub type FigureFn = fn(&Path, &[TrajectoryPanel], bool) -> vdd_report::Result<Vec<String>>;

/// A recipe of a D3IL task `T` (see `recipes/<task>.toml`); the values not given there come
/// from `recipes/defaults/<task>.toml` ([`Self::defaults`]). Unknown keys are errors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(bound = "")]
pub struct D3ilRecipe<T: D3ilTask> {
    /// Name, description, task (`pushing`, `aligning`), seeds and methods.
    #[serde(flatten)]
    pub header: recipe::Header,
    /// Trainings run concurrently, each on one thread (0: one per core). Results do not
    /// depend on it.
    pub jobs: usize,
    /// Demonstrations and windowing.
    pub data: DemoDataConfig<T::Oracle>,
    /// The learned teachers.
    pub teachers: TeachersConfig,
    /// The mixture of experts of VDD, EM and IMC (`state_dim` / `action_dim` come from the data).
    pub student: MoeConfig,
    /// VDD's settings, read by the VDD methods ([`crate::methods`]).
    pub vdd: Table,
    /// The baselines' settings, read by their methods.
    pub baselines: Table,
    /// Rollouts and timing.
    pub eval: D3ilEval,
    /// Figures.
    pub plots: D3ilPlots,
}

impl<T: D3ilTask> D3ilRecipe<T> {
    /// The task's defaults, `recipes/defaults/<task>.toml`, which a recipe file overrides.
    pub fn defaults() -> recipe::RecipeResult<Self> {
        recipe::defaults_from_toml(&[T::DEFAULTS])
    }
}

/// The `[eval]` table of a D3IL task: the rollouts ([`Self::protocol`]) and the timing
/// ([`Self::timing`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct D3ilEval {
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

impl D3ilEval {
    /// The rollouts' protocol on the task of `E` (the seed comes from the run seed).
    pub fn protocol<E: ContextEnv>(&self) -> EvalProtocol<E> {
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

/// The `[plots]` table of a D3IL task.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct D3ilPlots {
    /// Write the mode histograms, trajectory figures and learning curves.
    pub enabled: bool,
    /// Also write PNGs (SVG always).
    pub png: bool,
    /// Paths per panel of the trajectory figures: rollouts of each method spread over the
    /// contexts (first seed), and as many demonstrations (0: no trajectory figures).
    pub trajectories: usize,
}

impl<T: D3ilTask> TaskRecipe for D3ilRecipe<T> {
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

impl<T: D3ilTask> RolloutRecipe for D3ilRecipe<T> {
    type Data = DemoDataConfig<T::Oracle>;
    const TASK: &'static str = <T::Env as ContextEnv>::NAME;
    fn data(&self) -> &Self::Data {
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
        EvalProtocol::<T::Env>::seed(run_seed)
    }
    fn check_before_training(&self) -> crate::Result {
        self.eval.protocol::<T::Env>().check().map_err(|e| format!("eval: {e}"))?;
        self.eval.timing().check().map_err(|e| format!("eval: {e}"))?;
        self.data.deploy_spec().validate().map_err(|e| format!("data: {e}"))?;
        (T::CHECK_ORACLE)(&self.data.oracle).map_err(|e| format!("data.oracle: {e}"))?;
        Ok(())
    }
    fn prepare(&self) -> crate::Result<Prepared> {
        let t0 = Instant::now();
        let d = self.data.build()?;
        let modes = <T::Env as ContextEnv>::N_MODES;
        Ok(Prepared::new(d, self.data.demonstrations, modes, t0))
    }
}

/// The driver's [`Task`] of the D3IL task `T`: what [`super::BUILTIN`] lists for Pushing and
/// Aligning, and what [`crate::Registry::with_task`] takes for another D3IL task.
pub struct D3il<T>(PhantomData<fn() -> T>);

impl<T> D3il<T> {
    /// The task.
    pub const TASK: Self = D3il(PhantomData);
}

impl<T: D3ilTask> Task for D3il<T> {
    fn name(&self) -> &'static str {
        <T::Env as ContextEnv>::NAME
    }

    fn columns(&self) -> Vec<report::Column> {
        T::COLUMNS.to_vec()
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
        let resolved = recipe::resolve(&D3ilRecipe::<T>::defaults()?, &ctx.file, &ctx.overrides)?;
        let base = &resolved.base;
        let plan = driver::plan(&ctx.registry, &resolved, self.name(), &ctx.overrides.sets)?;
        let threads = base.eval.eval_threads();
        let probes = |cfg: &D3ilRecipe<T>| Probes {
            curves: None,
            visits: Some(Box::new(Visits::<T::Env, Metrics>::new(
                &EnvConfig::default(),
                cfg.data.deploy_spec(),
                T::VISITS_STREAM,
            ))),
        };
        rollouts::run_logged(ctx, &resolved, &plan, |dir, log, tuning_log| {
            let eval = |e: &Entry<'_, D3ilRecipe<T>>,
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
    panels: Vec<TrajectoryPanel>,
}

/// Rolls out one trained method on raw observations through the recipe's window and chunk,
/// saves a mixture with its deployment spec, keeps its learning curves and the paths of its
/// first rollouts (`first`, first seed); returns its row and the deployed policy for timing.
fn evaluate<T: D3ilTask>(
    e: &Entry<'_, D3ilRecipe<T>>,
    mut trained: Trained,
    seed: u64,
    threads: usize,
    dir: &Path,
    stages: &mut StageTimes,
    first: Option<&mut FirstSeed>,
) -> crate::Result<(Row, Windowed<TrainedPolicy>)> {
    let (label, cfg) = (&e.label, e.cfg);
    let protocol = cfg.eval.protocol::<T::Env>();
    let record = first.is_some() && cfg.plots.enabled && cfg.plots.trajectories > 0;
    let (spec, n) = (cfg.data.deploy_spec(), protocol.rollouts());
    let (wrapped, ev, eval_seconds) =
        rollouts::roll_out(&mut trained, spec, label, seed, n, dir, stages, |w| {
            Ok(protocol.evaluate(w, seed, threads, record)?)
        })?;
    let tag = format!("{label} s{seed}");
    let m = &ev.metrics;
    let p1 = m.p1_rate.map_or(String::new(), |p1| format!(", p1 {p1:.3}"));
    crate::progress::log(format!(
        "[{tag}] success {:.3}{p1}, mean distance {:.4}, task entropy {:.3}, mode entropy {:.3} (modes {:?}), trained in {:.1} s{}, evaluated in {:.1} s",
        m.success_rate,
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
            // Spread the drawn rollouts over the contexts.
            let mode = |r: &vdd_tasks::episodes::Rollout<T::Env>| {
                r.success().then(|| r.info.reached_mode()).flatten().map(|m| m.index())
            };
            let paths = rollouts::drawn_paths(&ev.rollouts, cfg.plots.trajectories, |_| true, mode);
            first.panels.push((T::PANEL)(label, &paths, m.success_rate, m.task_entropy));
        }
        first.curves.push((label.clone(), trained.curves));
    }
    Ok((row, wrapped))
}

/// The demonstrations' panel: the first `n` demonstrations of the recipe's data settings,
/// coloured by mode, titled with the demonstrator's success rate and the entropy of their
/// modes.
fn demonstrations_panel<T: D3ilTask>(
    base: &D3ilRecipe<T>,
    n: usize,
) -> crate::Result<TrajectoryPanel> {
    let d = &base.data;
    let demos = d.oracle.demonstrations(n, d.seed)?;
    let paths: Vec<_> = demos
        .observations
        .iter()
        .zip(&demos.modes)
        .map(|(o, m)| (o, None, Some(m.index())))
        .collect();
    let entropy = f64::from(vdd_tasks::normalized_entropy(&demos.mode_counts()));
    Ok((T::PANEL)("demonstrations", &paths, demos.success_rate(), entropy))
}

/// `metrics.json`, `curves.json`, `table.md`, the figures and `run.json`; returns the
/// tuning-log entries.
fn write_outputs<T: D3ilTask>(
    ctx: &RunContext,
    dir: &Path,
    base: &D3ilRecipe<T>,
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
    let p = &base.eval;
    let table = format!(
        "## {} ({})\n\n{}\n\n{}\nmean ± std over seeds {:?}; {} contexts × {} rollouts per method and seed; {}; mode entropy: over all successes pooled; µs per action: single-threaded `Policy::act` on one observation.\n",
        ctx.name,
        T::TITLE,
        base.header.description,
        report::markdown_table(&out.rows, T::COLUMNS),
        base.header.seeds,
        p.contexts,
        p.rollouts_per_context,
        T::TABLE_NOTE
    );
    let mut figures = Vec::new();
    if base.plots.enabled {
        let t0 = Instant::now();
        let png = base.plots.png;
        figures.extend(plots::learning_curves(&dir.join("curves"), &first.curves, png)?);
        let mut shares: Vec<_> =
            rollouts::demonstration_shares(&out.data_summary).into_iter().collect();
        shares.extend(report::mode_shares(&out.rows));
        figures.extend(plots::mode_histograms(&dir.join("modes"), &shares, png)?);
        if base.plots.trajectories > 0 {
            let mut panels = vec![demonstrations_panel(base, base.plots.trajectories)?];
            panels.extend(first.panels);
            figures.extend((T::TRAJECTORIES)(&dir.join("trajectories"), &panels, png)?);
        }
        stages.add("plots", t0.elapsed().as_secs_f64());
    }
    rollouts::finish(ctx, dir, &metrics, &table, out, figures, Vec::new(), stages)
}

/// The checks of a D3IL task's recipe, run by each task's tests (`tasks/pushing.rs`,
/// `tasks/aligning.rs`): its defaults file is complete and valid, its recipe resolves and plans
/// every method (default and `--quick`), and `--tuning` sets the tuning seeds and data.
#[cfg(test)]
pub(crate) fn check_recipe<T: D3ilTask>() {
    use crate::Registry;
    recipe::check_complete_defaults::<D3ilRecipe<T>>(&[T::DEFAULTS])
        .unwrap_or_else(|e| panic!("{e}"));
    let name = <T::Env as ContextEnv>::NAME;
    let path = recipe::recipe_path(name).unwrap();
    let file = recipe::read_recipe(&path).unwrap();
    for quick in [false, true] {
        for methods in [None, Some(vec!["all".to_owned()])] {
            let o = recipe::Overrides { quick, methods, ..Default::default() };
            let r = recipe::resolve(&D3ilRecipe::<T>::defaults().unwrap(), &file, &o)
                .unwrap_or_else(|e| panic!("{e}"));
            r.base.check_before_training().unwrap();
            let plan =
                driver::plan(&Registry::builtin(), &r, name, &[]).unwrap_or_else(|e| panic!("{e}"));
            assert!(!plan.is_empty());
        }
    }
    let task = D3il::<T>::TASK;
    let mut o = recipe::Overrides::default();
    task.apply_shorthands(&[("tuning".into(), "true".into())], &mut o).unwrap();
    assert_eq!(o.seeds, Some(tuning::TUNING_SEEDS.collect()));
    assert_eq!(o.sets[0], ("data.seed".into(), tuning::TUNING_DATA_SEED.to_string()));
    let e = task.apply_shorthands(&[("teacher".into(), "x".into())], &mut o);
    assert!(e.unwrap_err().contains(name));
}
