//! The Block-Push pipeline: oracle demonstrations → dataset
//! ([`vdd_tasks::block_push::dataset`]) → teachers (cached) → every method → rollouts
//! ([`vdd_tasks::block_push::EvalProtocol`]: success p2 as `success_rate`, p1, task entropy over
//! the four modes) and µs per action → `metrics.json`, `table.md`, `curves.json`, mode
//! histograms, learning curves and a trajectory figure coloured by mode (the demonstrations'
//! and each method's first-seed rollouts, those with target 0 on the left, so that one scene
//! holds them).
//!
//! The stages are Avoiding's ([`super::rollouts`]): the demonstrations come from `data.seed`
//! (one dataset for every run seed), the run seed drives the teachers, the students and the
//! rollouts (the same episodes for every method of a seed), and `--tuning` runs the tuning
//! seeds 100–104 on their own demonstrations, appending to `docs/block-push-tuning-log.toml`
//! ([`crate::tuning`]). No curves over training are taken on this task.

use std::time::Instant;

use serde::{Deserialize, Serialize};
use serde_json::Value;
use toml::Table;
use vdd_data::Windowed;
use vdd_moe::MoeConfig;
use vdd_report::plots::TrajectoryPanel;
use vdd_tasks::block_push::EvalProtocol;
use vdd_tasks::block_push::dataset::DatasetConfig;
use vdd_tasks::demo_data::Demonstrator as _;
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
use vdd_tasks::block_push::rollout::Metrics;
use vdd_tasks::block_push::{BlockPushEnv, EnvConfig};

/// A recipe of the Block-Push task (see `recipes/block-push.toml`); the values not given there
/// come from `recipes/defaults/block-push.toml` ([`Self::defaults`]). Unknown keys are errors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BlockPushRecipe {
    /// Name, description, task (`block-push`), seeds and methods.
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
    pub eval: BlockPushEval,
    /// Figures.
    pub plots: BlockPushPlots,
}

/// `recipes/defaults/block-push.toml`, embedded so that the binary is self-contained.
const DEFAULTS: &str = include_str!("../../../../recipes/defaults/block-push.toml");

impl BlockPushRecipe {
    /// The task's defaults, `recipes/defaults/block-push.toml`, which a recipe file overrides.
    pub fn defaults() -> recipe::RecipeResult<Self> {
        recipe::defaults_from_toml(&[("recipes/defaults/block-push.toml", DEFAULTS)])
    }
}

/// The `[eval]` table: the rollouts ([`Self::protocol`]) and the timing ([`Self::timing`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BlockPushEval {
    /// Rollouts per method and seed.
    pub rollouts: usize,
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

impl BlockPushEval {
    /// The rollouts' protocol (the seed comes from the run seed).
    pub fn protocol(&self) -> EvalProtocol {
        EvalProtocol { rollouts: self.rollouts, lockstep_batch: self.lockstep_batch }
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
pub struct BlockPushPlots {
    /// Write the mode histograms, learning curves and the trajectory figure.
    pub enabled: bool,
    /// Also write PNGs (SVG always).
    pub png: bool,
    /// Paths a panel of the trajectory figure: as many demonstrations, and first-seed rollouts
    /// of each method spread over the evaluation, all with target 0 on the left (0: no figure).
    pub trajectories: usize,
}

/// What the first seed's evaluations keep for the figures: learning curves and trajectory
/// panels, per method.
#[derive(Default)]
struct FirstSeed {
    curves: Vec<(String, Curves)>,
    panels: Vec<TrajectoryPanel>,
}

/// Whether the observation whose column `c` is `o(c)` has target 0 left of target 1: the
/// layout the trajectory figure draws (the targets' sides are a coin flip per episode).
fn target_0_left(o: impl Fn(usize) -> f32) -> bool {
    o(12) < o(14)
}

impl TaskRecipe for BlockPushRecipe {
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

impl RolloutRecipe for BlockPushRecipe {
    type Data = DatasetConfig;
    const TASK: &'static str = "block-push";
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
        Ok(Prepared::new(d, self.data.demonstrations, vdd_tasks::block_push::N_MODES, t0))
    }
}

/// The Block-Push task.
pub struct BlockPush;

/// The columns of Block-Push's tables.
pub const COLUMNS: [report::Column; 5] = [
    report::Column::new("success_rate", "success (p2)", 3),
    report::Column::new("p1_rate", "p1", 3),
    report::Column::new("task_entropy", "task entropy", 3),
    report::Column::new("us_per_action", "µs / action", 1),
    report::Column::new("train_seconds", "train s", 1),
];

impl Task for BlockPush {
    fn name(&self) -> &'static str {
        "block-push"
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
        let resolved = recipe::resolve(&BlockPushRecipe::defaults()?, &ctx.file, &ctx.overrides)?;
        let base = &resolved.base;
        let plan = driver::plan(&ctx.registry, &resolved, "block-push", &ctx.overrides.sets)?;
        let threads = base.eval.eval_threads();
        let probes = |cfg: &BlockPushRecipe| Probes {
            curves: None,
            visits: Some(Box::new(Visits::<BlockPushEnv, Metrics>::new(
                &EnvConfig::default(),
                cfg.data.deploy_spec(),
                "block-push-visits",
            ))),
        };
        rollouts::run_logged(ctx, &resolved, &plan, |dir, log, tuning_log| {
            let eval = |e: &Entry<'_, BlockPushRecipe>,
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

/// Rolls out one trained method on raw observations through the recipe's window and chunk,
/// saves a mixture with its deployment spec, keeps its learning curves and the paths of its
/// rollouts (`first`, first seed); returns its row and the deployed policy for timing.
fn evaluate(
    e: &Entry<'_, BlockPushRecipe>,
    mut trained: Trained,
    seed: u64,
    threads: usize,
    dir: &std::path::Path,
    stages: &mut StageTimes,
    first: Option<&mut FirstSeed>,
) -> crate::Result<(Row, Windowed<TrainedPolicy>)> {
    let (label, cfg) = (&e.label, e.cfg);
    let (spec, n) = (cfg.data.deploy_spec(), cfg.eval.rollouts);
    let record = first.is_some() && cfg.plots.enabled && cfg.plots.trajectories > 0;
    let (wrapped, ev, eval_seconds) =
        rollouts::roll_out(&mut trained, spec, label, seed, n, dir, stages, |w| {
            Ok(cfg.eval.protocol().evaluate(w, seed, threads, record)?)
        })?;
    let tag = format!("{label} s{seed}");
    let m = &ev.metrics;
    crate::progress::log(format!(
        "[{tag}] success {:.3}, p1 {:.3}, entropy {:.3} (modes {:?}), trained in {:.1} s{}, evaluated in {:.1} s",
        m.success_rate,
        m.p1_rate,
        m.task_entropy,
        m.mode_counts,
        trained.train_seconds,
        rollouts::teacher_note(&trained),
        eval_seconds
    ));
    let row = rollouts::trained_row(m.row_fields(), &trained, seed);
    if let Some(first) = first {
        if record {
            let left =
                |t: &vdd_tasks::episodes::Trajectory| target_0_left(|c| t.final_observation[c]);
            let mode = |r: &vdd_tasks::block_push::rollout::Rollout| {
                r.success().then_some(r.info.mode).flatten().map(|m| m.index())
            };
            let paths = rollouts::drawn_paths(&ev.rollouts, cfg.plots.trajectories, left, mode);
            first.panels.push(plots::block_push_panel(
                label,
                &paths,
                m.success_rate,
                m.task_entropy,
            ));
        }
        first.curves.push((label.clone(), trained.curves));
    }
    Ok((row, wrapped))
}

/// `metrics.json`, `curves.json`, `table.md`, the figures and `run.json`; returns the
/// tuning-log entries.
fn write_outputs(
    ctx: &RunContext,
    dir: &std::path::Path,
    base: &BlockPushRecipe,
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
    let table = format!(
        "## {} (Block-Push)\n\n{}\n\n{}\nmean ± std over seeds {:?}; {} rollouts per method and seed; success (p2): both blocks in distinct targets; p1: a block reached a target; task entropy over the 4 modes of the successes; µs per action: single-threaded `Policy::act` on one observation.\n",
        ctx.name,
        base.header.description,
        report::markdown_table(&out.rows, &COLUMNS),
        base.header.seeds,
        base.eval.rollouts
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
            let (demos, targets) = demonstrations_panel(base, base.plots.trajectories)?;
            let mut panels = vec![demos];
            panels.extend(first.panels);
            let stem = dir.join("trajectories");
            figures.extend(plots::block_push_trajectories(&stem, targets, &panels, png)?);
        }
        stages.add("plots", t0.elapsed().as_secs_f64());
    }
    rollouts::finish(ctx, dir, &metrics, &table, out, figures, Vec::new(), stages)
}

/// The demonstrations' panel and the targets of its scene: the first `n` demonstrations of the
/// recipe's data settings with target 0 on the left (of the first `4n` drawn), coloured by
/// mode, titled with the demonstrator's success rate and the entropy of their modes; the
/// targets are the first drawn episode's.
fn demonstrations_panel(
    base: &BlockPushRecipe,
    n: usize,
) -> crate::Result<(TrajectoryPanel, [[f32; 2]; 2])> {
    let d = &base.data;
    let demos = d.oracle.demonstrations(4 * n, d.seed)?;
    let paths: Vec<_> = demos
        .observations
        .iter()
        .zip(&demos.modes)
        .filter(|(o, _)| o.nrows() > 0 && target_0_left(|c| o[(0, c)]))
        .take(n)
        .map(|(o, m)| (o, None, Some(m.index())))
        .collect();
    let targets = paths.first().map_or([[0.28, 0.2], [0.52, 0.2]], |(o, _, _)| {
        [[o[(0, 12)], o[(0, 13)]], [o[(0, 14)], o[(0, 15)]]]
    });
    let mut counts = [0usize; vdd_tasks::block_push::N_MODES];
    paths.iter().filter_map(|p| p.2).for_each(|m| counts[m] += 1);
    let entropy = f64::from(vdd_tasks::normalized_entropy(&counts));
    let label = "demonstrations (target 0 left)";
    Ok((plots::block_push_panel(label, &paths, demos.success_rate(), entropy), targets))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Registry;

    #[test]
    fn the_defaults_file_is_complete_and_valid() {
        recipe::check_complete_defaults::<BlockPushRecipe>(&[(
            "recipes/defaults/block-push.toml",
            DEFAULTS,
        )])
        .unwrap_or_else(|e| panic!("{e}"));
    }

    #[test]
    fn the_recipe_resolves_and_plans_every_method() {
        let path = recipe::recipe_path("block-push").unwrap();
        let file = recipe::read_recipe(&path).unwrap();
        for quick in [false, true] {
            for methods in [None, Some(vec!["all".to_owned()])] {
                let o = recipe::Overrides { quick, methods, ..Default::default() };
                let r = recipe::resolve(&BlockPushRecipe::defaults().unwrap(), &file, &o)
                    .unwrap_or_else(|e| panic!("{e}"));
                r.base.check_before_training().unwrap();
                let plan = driver::plan(&Registry::builtin(), &r, "block-push", &[])
                    .unwrap_or_else(|e| panic!("{e}"));
                assert!(!plan.is_empty());
            }
        }
    }

    #[test]
    fn the_demonstrations_panel_draws_one_target_layout() {
        let mut base = BlockPushRecipe::defaults().unwrap();
        base.data.seed = 5;
        let (panel, targets) = demonstrations_panel(&base, 3).unwrap();
        assert!((1..=3).contains(&panel.paths.len()), "{}", panel.paths.len());
        assert!(targets[0][0] < targets[1][0], "{targets:?}");
        assert!(panel.success.iter().all(|&s| s));
        // Every path starts at the effector's start.
        let start = vdd_tasks::block_push::EFFECTOR_START;
        for p in &panel.paths {
            assert!((p[0].0 - start[0]).abs() < 1e-3 && (p[0].1 - start[1]).abs() < 1e-3);
        }
        assert!(target_0_left(|c| c as f32) && !target_0_left(|c| -(c as f32)));
    }

    #[test]
    fn tuning_sets_the_tuning_seeds_and_data() {
        let mut o = recipe::Overrides::default();
        BlockPush.apply_shorthands(&[("tuning".into(), "true".into())], &mut o).unwrap();
        assert_eq!(o.seeds, Some(tuning::TUNING_SEEDS.collect()));
        assert_eq!(o.sets[0], ("data.seed".into(), tuning::TUNING_DATA_SEED.to_string()));
        let e = BlockPush.apply_shorthands(&[("teacher".into(), "x".into())], &mut o);
        assert!(e.unwrap_err().contains("block-push"));
    }
}
