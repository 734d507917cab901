//! What the rollout tasks (Avoiding, Block-Push, Pushing) share beyond [`crate::driver`]: the
//! run's directory and tuning log ([`run_logged`]), the dataset of a run ([`Prepared`]),
//! training and evaluating every method of the plan with the single-threaded timing
//! ([`train_and_evaluate`]), a trained method's deployment and its results row ([`deploy`],
//! [`trained_row`]), and the closing outputs ([`metrics`], [`finish`]). Each task keeps its
//! evaluation (protocol, figures) and its tables.
//!
//! Seeds: the demonstrations come from `data.seed` (one fixed dataset for every run seed);
//! the run seed drives teacher training, student initialisation and training, and the
//! evaluation rollouts. Tuning runs (seeds 100–104, `--tuning`) use their own demonstrations
//! and are logged in `docs/<task>-tuning-log.toml` ([`crate::tuning`]).

use std::path::Path;
use std::time::Instant;

use faer::Mat;
use serde::Serialize;
use serde_json::{Value, json};
use vdd_data::{DeploySpec, Windowed};
use vdd_moe::cache::StudentCache;
use vdd_tasks::avoiding::dataset::Dataset;
use vdd_tasks::episodes::{Env, EvalConfig, TaskMetrics};
use vdd_tasks::timing::{Timing, us_per_action};

use crate::context::{RunContext, StageTimes};
use crate::driver::{self, Datasets, Entry, ProbesFor, TaskRecipe};
use crate::method::{StateVisits, Trained, TrainingData};
use crate::policy::TrainedPolicy;
use crate::recipe::{self, Overrides, Resolved};
use crate::report::{self, Row};
use crate::teachers;
use crate::tuning::{self, LogEntry};

/// What the shared stages need of a rollout task's recipe.
pub(crate) trait RolloutRecipe: TaskRecipe {
    /// The `data` table.
    type Data: Serialize;
    /// The task's name (`avoiding`, `block-push`, `pushing`).
    const TASK: &'static str;
    /// The `data` table (its hash keys the datasets and the tuning log's configurations).
    fn data(&self) -> &Self::Data;
    /// `data.seed`: the demonstrations' seed.
    fn data_seed(&self) -> u64;
    /// Concurrent trainings (0: one per core).
    fn jobs(&self) -> usize;
    /// The settings of µs per action.
    fn timing(&self) -> Timing;
    /// The root seed of the evaluation of a run seed (the timing's seed derives from it).
    fn eval_seed(run_seed: u64) -> u64;
    /// Checks what would fail only after training (evaluation settings, deployment spec).
    fn check_before_training(&self) -> crate::Result;
    /// Builds the dataset of this configuration.
    fn prepare(&self) -> crate::Result<Prepared>;
    /// The training episodes' raw observations and actions, one matrix per episode (what a
    /// teacher loaded from a file cuts into its own windows: [`Capability::RawEpisodes`]).
    ///
    /// [`Capability::RawEpisodes`]: crate::capability::Capability::RawEpisodes
    fn raw_train_episodes(&self) -> crate::Result<RawEpisodes> {
        Err(format!("task `{}` gives no raw episodes to a teacher file", Self::TASK).into())
    }
}

/// The training episodes' raw observations and their actions, one matrix per episode each.
pub(crate) type RawEpisodes = (Vec<Mat<f32>>, Vec<Mat<f32>>);

/// The dataset of `e`: its configuration's, or for a row of a teacher file the same
/// episodes cut into the teacher's windows and chunks ([`teachers::LoadedTeacher`]).
fn prepare_entry<R: RolloutRecipe>(e: &Entry<'_, R>) -> crate::Result<Prepared> {
    let mut prepared = e.cfg.prepare()?;
    if let Some(t) = &e.loaded {
        let (raw_obs, actions) = e.cfg.raw_train_episodes()?;
        prepared.training = t.training_data(&raw_obs, actions)?;
        crate::progress::log(format!(
            "data: {} windows and chunks of the {} teacher {}",
            prepared.training.states.nrows(),
            t.source(),
            t.file
        ));
    }
    Ok(prepared)
}

/// `--tuning`: the tuning seeds (unless given) and the tuning demonstrations.
pub(crate) fn apply_tuning(o: &mut Overrides) {
    o.seeds.get_or_insert_with(|| tuning::TUNING_SEEDS.collect());
    o.sets.insert(0, ("data.seed".into(), tuning::TUNING_DATA_SEED.to_string()));
}

/// The shorthand `--<key>` of a rollout task `task` whose only shorthand is `--tuning`
/// ([`apply_tuning`]); any other is an error naming it and the task.
pub(crate) fn tuning_shorthand(task: &str, key: &str, o: &mut Overrides) -> Result<(), String> {
    if key != "tuning" {
        return Err(format!("option --{key} does not apply to task `{task}`"));
    }
    apply_tuning(o);
    Ok(())
}

/// The dataset of a run.
pub(crate) struct Prepared {
    pub training: TrainingData,
    /// Raw observations of the training episodes (µs-per-action timing).
    pub episodes_obs: Vec<Mat<f32>>,
    pub summary: Value,
}

impl AsRef<TrainingData> for Prepared {
    fn as_ref(&self) -> &TrainingData {
        &self.training
    }
}

impl Prepared {
    /// The dataset `d` of `demonstrations` demonstrations of a task with `modes` behaviour
    /// modes, built since `t0`, with a log line.
    pub fn new(d: Dataset, demonstrations: usize, modes: usize, t0: Instant) -> Self {
        let summary = d.summary(demonstrations);
        crate::progress::log(format!(
            "data: {demonstrations} demonstrations ({} train episodes, {} samples, {} of {modes} modes, entropy {:.3}) in {:.2} s",
            d.train_episodes,
            d.training.states.nrows(),
            summary["dataset_modes"],
            summary["dataset_entropy"].as_f64().unwrap_or(0.0),
            t0.elapsed().as_secs_f64()
        ));
        Prepared { training: d.training, episodes_obs: d.episode_observations, summary }
    }
}

/// Runs `body(dir, log, tuning_log)` for the `plan` of `resolved`, after checking every
/// configuration and writing `resolved.toml` into the run directory `dir`; `log` is the task's
/// tuning log, `tuning_log` its path when this is a tuning run (then `dir` is under
/// `results/tuning/` unless `--out` says otherwise). A tuning run that fails is logged with its
/// error (a configuration that failed was still tried).
pub(crate) fn run_logged<R: RolloutRecipe>(
    ctx: &RunContext,
    resolved: &Resolved<R>,
    plan: &[Entry<'_, R>],
    body: impl FnOnce(&Path, &[LogEntry], Option<&Path>) -> crate::Result,
) -> crate::Result {
    let base = &resolved.base;
    for (_, cfg) in resolved.configs() {
        // Before any training: a bad setting would otherwise fail after it.
        cfg.check_before_training()?;
    }
    let runs = resolved.configs().into_iter().map(|(_, c)| (&c.header().seeds[..], c.data_seed()));
    let is_tuning = tuning::is_tuning_plan(runs)?;
    let seeds = &base.header().seeds;
    let dir = match (&ctx.out, is_tuning) {
        (None, true) => ctx
            .root
            .join("results/tuning")
            .join(&ctx.name)
            .join(crate::context::run_name(seeds, &ctx.overrides)),
        _ => ctx.run_dir(seeds),
    };
    let log_path = tuning::log_path(&ctx.root, R::TASK);
    let log = tuning::read_log(&log_path)?;
    ctx.write_resolved(&dir, &resolved.to_toml()?)?;
    crate::progress::log(format!(
        "recipe `{}`: {} method run(s) x {} seed(s) -> {}",
        ctx.name,
        plan.len(),
        seeds.len(),
        teachers::rel(&dir)
    ));
    let result = body(&dir, &log, is_tuning.then_some(log_path.as_path()));
    if let (Err(e), true) = (&result, is_tuning) {
        let mut rows = driver::empty_rows(plan);
        let mut entries = tuning_entries(ctx, plan, &log, &dir, &mut rows)?;
        for entry in &mut entries {
            entry.seeds.clone_from(seeds);
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

/// Adds `tuning_configs` (the method's configurations in the tuning `log`) to every row and
/// returns the run's tuning-log entries, one per method.
pub(crate) fn tuning_entries<R: RolloutRecipe>(
    ctx: &RunContext,
    plan: &[Entry<'_, R>],
    log: &[LogEntry],
    dir: &Path,
    rows: &mut [(String, Vec<Row>)],
) -> crate::Result<Vec<LogEntry>> {
    let revision = ctx.revision_label();
    let mut entries = Vec::with_capacity(plan.len());
    for (e, (_, rows)) in plan.iter().zip(rows.iter_mut()) {
        let n = tuning::configs_tried(log, &e.label);
        rows.iter_mut().for_each(|r| drop(r.insert("tuning_configs".into(), json!(n))));
        let id = tuning::RunId {
            method: e.label.clone(),
            config: tuning::method_config_hash(&e.recipe(), e.cfg.data())?,
            recipe: ctx.name.clone(),
            command: ctx.command.clone(),
            revision: revision.clone(),
            run: teachers::rel(dir),
        };
        entries.push(LogEntry::from_rows(id, rows));
    }
    Ok(entries)
}

/// Appends a tuning run's `entries` to its log at `path`.
pub(crate) fn append_tuning(path: &Path, entries: Vec<LogEntry>) -> crate::Result {
    let n = entries.len();
    tuning::append_log(path, entries)?;
    crate::progress::print(format!("tuning log: {n} entries appended to {}", teachers::rel(path)));
    Ok(())
}

/// The body of [`run_logged`] for a task: trains `plan` and evaluates each trained method with
/// `evaluate` (`(entry, trained, run seed, first seed?, kept, stages)`; `kept` collects what the
/// figures need), then `write_outputs(outcome, kept, stages)` writes the run's outputs and returns
/// its tuning-log entries, which a tuning run (`tuning_log`: the log's path) appends to the log.
#[allow(clippy::too_many_arguments)]
pub(crate) fn run_plan<R: RolloutRecipe, K: Default>(
    ctx: &RunContext,
    base: &R,
    plan: &[Entry<'_, R>],
    dir: &Path,
    log: &[LogEntry],
    tuning_log: Option<&Path>,
    probes: ProbesFor<'_, R>,
    mut evaluate: impl FnMut(
        &Entry<'_, R>,
        Trained,
        u64,
        bool,
        &mut K,
        &mut StageTimes,
    ) -> crate::Result<(Row, Windowed<TrainedPolicy>)>,
    write_outputs: impl FnOnce(Outcome, K, &mut StageTimes) -> crate::Result<Vec<LogEntry>>,
) -> crate::Result {
    let mut stages = StageTimes::default();
    let mut kept = K::default();
    let mut eval = |e: &Entry<'_, R>, trained, seed, first, st: &mut StageTimes| {
        evaluate(e, trained, seed, first, &mut kept, st)
    };
    let out = train_and_evaluate(ctx, base, plan, dir, log, probes, &mut eval, &mut stages)?;
    let entries = write_outputs(out, kept, &mut stages)?;
    if let Some(path) = tuning_log {
        append_tuning(path, entries)?;
    }
    Ok(())
}

/// The demonstrations' bar of the mode histogram: their modes' shares from a run's data summary
/// (`dataset_mode_counts`, [`Dataset::summary`]), if it has any.
pub(crate) fn demonstration_shares(summary: &Value) -> Option<(String, Vec<f64>)> {
    let counts: Vec<f64> = summary["dataset_mode_counts"]
        .as_array()?
        .iter()
        .map(|c| c.as_f64().unwrap_or(0.0))
        .collect();
    let total: f64 = counts.iter().sum();
    (total > 0.0).then(|| ("demonstrations".to_owned(), counts.iter().map(|c| c / total).collect()))
}

/// The paths a trajectory panel draws of an evaluation: up to `n` of the recorded rollouts
/// that `keep` accepts, spread over them (every `k`-th), each as its observations, its final
/// observation and `mode` of it (`None`: a failure, drawn in the failure colour).
pub(crate) fn drawn_paths<'a, E: Env>(
    rollouts: &'a [vdd_tasks::episodes::Rollout<E>],
    n: usize,
    keep: impl Fn(&vdd_tasks::episodes::Trajectory) -> bool,
    mode: impl Fn(&vdd_tasks::episodes::Rollout<E>) -> Option<usize>,
) -> Vec<crate::plots::PushingPath<'a>> {
    let recorded: Vec<_> = rollouts
        .iter()
        .filter_map(|r| r.trajectory.as_ref().filter(|t| keep(t)).map(|t| (r, t)))
        .collect();
    let step = (recorded.len() / n.max(1)).max(1);
    recorded
        .into_iter()
        .step_by(step)
        .take(n)
        .map(|(r, t)| (&t.observations, Some(t.final_observation.as_slice()), mode(r)))
        .collect()
}

/// Deploys `trained` through `spec` ([`deploy`]), runs `rollouts` on the deployed policy (`n`
/// rollouts, for the spinner `label s<seed>`) as the stage `rollouts`, and saves a mixture
/// ([`save_model`]); returns the deployed policy, what `rollouts` returned and its seconds.
#[allow(clippy::too_many_arguments)]
pub(crate) fn roll_out<T>(
    trained: &mut Trained,
    spec: DeploySpec,
    label: &str,
    seed: u64,
    n: usize,
    dir: &Path,
    stages: &mut StageTimes,
    rollouts: impl FnOnce(&Windowed<TrainedPolicy>) -> crate::Result<T>,
) -> crate::Result<(Windowed<TrainedPolicy>, T, f64)> {
    let tag = format!("{label} s{seed}");
    let wrapped = deploy(trained, spec)?;
    let spin = crate::progress::spinner(&tag, &format!("{n} rollouts"));
    let t0 = Instant::now();
    let ev = rollouts(&wrapped)?;
    let eval_seconds = t0.elapsed().as_secs_f64();
    stages.add("rollouts", eval_seconds);
    spin.finish_and_clear();
    save_model(trained, dir, label, seed)?;
    Ok((wrapped, ev, eval_seconds))
}

/// What [`train_and_evaluate`] gives the task's outputs.
pub(crate) struct Outcome {
    /// One list of per-seed rows per plan entry.
    pub rows: Vec<(String, Vec<Row>)>,
    /// The tuning-log entries of the run, one per method.
    pub entries: Vec<LogEntry>,
    /// The first dataset's summary.
    pub data_summary: Value,
    /// `run.json` entries of the teachers.
    pub teacher_log: Vec<Value>,
    /// Concurrent trainings.
    pub jobs: usize,
}

/// How a task evaluates one trained method: `(entry, trained, run seed, first seed?, stages)`
/// → its results row and the deployed policy (for the timing).
pub(crate) type Evaluate<'a, R> = dyn FnMut(
        &Entry<'_, R>,
        Trained,
        u64,
        bool,
        &mut StageTimes,
    ) -> crate::Result<(Row, Windowed<TrainedPolicy>)>
    + 'a;

/// Trains every method of `plan` for every seed (one dataset per distinct `data` table,
/// the student cache, the task's `probes`: curves over training and visited states), evaluates each with `evaluate`, one method at a
/// time, and times the seed's methods single-threaded with nothing else running.
#[allow(clippy::too_many_arguments)]
pub(crate) fn train_and_evaluate<R: RolloutRecipe>(
    ctx: &RunContext,
    base: &R,
    plan: &[Entry<'_, R>],
    dir: &Path,
    log: &[LogEntry],
    probes: ProbesFor<'_, R>,
    evaluate: &mut Evaluate<'_, R>,
    stages: &mut StageTimes,
) -> crate::Result<Outcome> {
    let cores = std::thread::available_parallelism().map_or(1, |p| p.get());
    let jobs = if base.jobs() == 0 { cores } else { base.jobs() };
    let seeds = &base.header().seeds;

    // One dataset per distinct `data` table and teacher file (usually one), whatever the seed.
    let key = |_, pi: usize| -> crate::Result<_> {
        let file = plan[pi].loaded.as_ref().map(|t| t.hash.clone());
        Ok(recipe::config_hash(&(plan[pi].cfg.data(), file))?)
    };
    let prepare = |_, pi: usize| stages.time("data", || prepare_entry(&plan[pi]));
    let data = Datasets::build(seeds.len(), plan.len(), key, prepare)?;
    let students = StudentCache { dir: &ctx.student_cache_dir, fresh: ctx.fresh };
    let mut trainings =
        driver::train_all(ctx, plan, seeds, &data, jobs, (Some(students), probes), stages)?;

    let mut rows = driver::empty_rows(plan);
    for (si, &seed) in seeds.iter().enumerate() {
        let mut timed = Vec::with_capacity(plan.len());
        for (pi, e) in plan.iter().enumerate() {
            let trained = trainings.trained.remove(&(si, pi)).ok_or("internal: not trained")?;
            let (row, policy) = evaluate(e, trained, seed, si == 0, stages)?;
            rows[pi].1.push(row);
            timed.push((pi, policy));
        }
        let t0 = Instant::now();
        time_seed(plan, &data, si, seed, timed, &mut rows)?;
        stages.add("timing", t0.elapsed().as_secs_f64());
    }
    let entries = tuning_entries(ctx, plan, log, dir, &mut rows)?;
    let data_summary = data.get(0, 0).summary.clone();
    Ok(Outcome { rows, entries, data_summary, teacher_log: trainings.teachers.log, jobs })
}

/// Inference time, single-threaded, one observation per call, with nothing else running: the
/// seed's methods take their timing rounds in turn (see `us_per_action`), in groups that share
/// the observations and the timing settings (one group unless variants change them).
fn time_seed<R: RolloutRecipe>(
    plan: &[Entry<'_, R>],
    data: &Datasets<Prepared>,
    si: usize,
    seed: u64,
    mut timed: Vec<(usize, Windowed<TrainedPolicy>)>,
    rows: &mut [(String, Vec<Row>)],
) -> crate::Result {
    let eval_seed = R::eval_seed(seed);
    while let Some((first, _)) = timed.first() {
        let (timing, id) = (plan[*first].cfg.timing(), data.id(si, *first));
        let same = |pi: usize| data.id(si, pi) == id && plan[pi].cfg.timing() == timing;
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

/// The policy of `trained` acting on raw observations through `spec` (a mixture, a diffusion
/// teacher or a consistency model also keeps the spec, so that its saved file loads as a
/// deployed policy).
pub(crate) fn deploy(
    trained: &mut Trained,
    spec: DeploySpec,
) -> crate::Result<Windowed<TrainedPolicy>> {
    match &mut trained.policy {
        TrainedPolicy::Moe(moe) => moe.set_deploy_spec(spec.clone())?,
        TrainedPolicy::Teacher(t) => t.set_deploy_spec(spec.clone())?,
        TrainedPolicy::Consistency(m) => m.set_deploy_spec(spec.clone())?,
        TrainedPolicy::Trajectory(m) => m.set_deploy_spec(spec.clone())?,
        TrainedPolicy::Other(_) => {}
    }
    Ok(Windowed::new(trained.policy.clone(), spec)?)
}

/// Saves the policy of a mixture, a diffusion teacher or a consistency model (CD, CTM) as
/// `<dir>/models/<label>-s<seed>.safetensors` with its deployment (`vdd_moe::load_policy`,
/// `vdd_diffusion::DiffusionTeacher::load_policy`, `vdd_consistency::ConsistencyModel::load_policy`
/// give a policy on raw observations); a policy of another type ([`TrainedPolicy::Other`]) is
/// not saved.
pub(crate) fn save_model(trained: &Trained, dir: &Path, label: &str, seed: u64) -> crate::Result {
    if matches!(trained.policy, TrainedPolicy::Other(_)) {
        return Ok(());
    }
    let models = dir.join("models");
    std::fs::create_dir_all(&models)?;
    trained.policy.save(&models.join(format!("{label}-s{seed}.safetensors")))?;
    Ok(())
}

/// `row` (the evaluation's figures) with the seed and what the training reports: its seconds
/// (and the teacher's), sampling steps, budget and the curves' seconds.
pub(crate) fn trained_row(mut row: Row, trained: &Trained, seed: u64) -> Row {
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
    row
}

/// `trained in N s` for a log line, or `trained elsewhere` for a policy loaded from a file
/// (no training time).
pub(crate) fn trained_note(trained: &Trained) -> String {
    match trained.train_seconds {
        s if s.is_finite() => format!("trained in {s:.1} s"),
        _ => "trained elsewhere".to_owned(),
    }
}

/// The training time of `trained` for a log line: ` (+ teacher N s)` when it has a teacher.
pub(crate) fn teacher_note(trained: &Trained) -> String {
    trained.teacher_seconds.map_or(String::new(), |t| format!(" (+ teacher {t:.1} s)"))
}

/// `metrics.json` of a run: the rows, the data summary, and a warning when the students'
/// budgets differ.
pub(crate) fn metrics<R: RolloutRecipe>(ctx: &RunContext, base: &R, out: &Outcome) -> Row {
    let mut metrics = report::metrics_json(&ctx.name, R::TASK, &base.header().seeds, &out.rows);
    metrics.insert("data".into(), out.data_summary.clone());
    if let Some(w) = report::unequal_budgets(&out.rows) {
        crate::progress::log(format!("\nWARNING: unequal budgets: {w}\n"));
        metrics.insert("budget_warning".into(), json!(w));
    }
    metrics
}

/// Writes `metrics.json`, `table.md` and `run.json` (`figures`, data, teachers, jobs and the
/// stages' seconds), prints the table, the task's `lines` (acceptance), the stages and the wall
/// time.
#[allow(clippy::too_many_arguments)]
pub(crate) fn finish(
    ctx: &RunContext,
    dir: &Path,
    metrics: &Row,
    table: &str,
    out: Outcome,
    figures: Vec<String>,
    lines: Vec<String>,
    stages: &StageTimes,
) -> crate::Result<Vec<LogEntry>> {
    let details = json!({
        "figures": figures,
        "data": out.data_summary,
        "teachers": out.teacher_log,
        "jobs": out.jobs,
        "stage_seconds": stages.to_json(),
    });
    driver::write_results(ctx, dir, metrics, table, details)?;
    lines.iter().for_each(crate::progress::print);
    crate::progress::print(format!("stages: {}", stages.summary()));
    let cpu = crate::context::cpu_seconds().map_or(String::new(), |c| format!(", {c:.0} s CPU"));
    let wall = ctx.started.elapsed().as_secs_f64();
    crate::progress::print(format!("results in {} ({wall:.1} s wall{cpu})", teachers::rel(dir)));
    Ok(out.entries)
}

/// The states a policy visits in task `E`'s episodes (metrics `M`) through a deployment spec:
/// the [`StateVisits`] of a rollout task, episodes from the seed stream `stream`.
pub(crate) struct Visits<E: Env, M> {
    env: E::Config,
    spec: DeploySpec,
    stream: &'static str,
    metrics: std::marker::PhantomData<fn() -> M>,
}

impl<E: Env, M> Visits<E, M> {
    /// Visits in environments with `env`'s settings, through `spec`, on the stream `stream`.
    pub(crate) fn new(env: &E::Config, spec: DeploySpec, stream: &'static str) -> Self {
        Self { env: env.clone(), spec, stream, metrics: std::marker::PhantomData }
    }
}

/// Most states one [`Visits`] call returns.
const MAX_VISITED: usize = 1 << 20;

impl<E: Env, M: TaskMetrics<E>> StateVisits for Visits<E, M>
where
    E::Config: Sync,
{
    fn visit(
        &self,
        policy: &TrainedPolicy,
        seed: u64,
        episodes: usize,
    ) -> Result<Mat<f32>, vdd_tasks::TaskError> {
        let root = vdd_core::Seeds::new(seed).child(self.stream).root();
        let cfg = EvalConfig::protocol(episodes, 0, root, false);
        vdd_tasks::visits::visited_states::<E, M, _>(
            &self.env,
            policy,
            &self.spec,
            &cfg,
            MAX_VISITED,
        )
    }
}
