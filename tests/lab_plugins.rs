//! A method, its row, a teacher source and a task added to the experiment layer from outside
//! `vdd-lab` (issue 32): the method `bc` (behaviour cloning, EM with one expert: the worked
//! example of docs/recipes.md) and the task `line` (a 1-D regression, actions `a = 2s` plus
//! noise), registered with [`Registry::with_method`], [`Registry::with_rows`] and
//! [`Registry::with_task`] and run through the driver by [`vdd_lab::experiment::run_with`], as
//! a program using the layer would; a recipe adding a row of its own; and a teacher source
//! ([`Registry::with_teacher`]) that rows name.
//!
//! This file is the working example docs/recipes.md ("Adding a method", "Adding a task")
//! points at: everything it uses is public API of `vdd-lab`.

use std::path::{Path, PathBuf};

use faer::Mat;
use rand::Rng;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use toml::Table;
use vdd_core::{Policy, Seeds};
use vdd_lab::Registry;
use vdd_lab::context::{RunContext, StageTimes};
use vdd_lab::driver::{self, Datasets, Task, TaskRecipe};
use vdd_lab::experiment::{Request, run_with};
use vdd_lab::method::{
    Info, Job, Method, MethodRecipe, Row as LabRow, TeacherUse, Trained, TrainingData,
};
use vdd_lab::recipe::{self, Header};
use vdd_lab::report::{self, Column, Row};
use vdd_lab::teachers::TeachersConfig;
use vdd_mixture::EmConfig;
use vdd_moe::MoeConfig;

// ---------------------------------------------------------------------------------------------
// The method `bc`.

/// `bc`: behaviour cloning, one Gaussian expert fitted to the demonstrations by EM. Keys:
/// `baselines.bc` (an [`EmConfig`]; its `seed` is replaced by the run seed).
struct Bc;

static BC: Bc = Bc;

/// `bc` takes no teacher and needs nothing of a task.
const BC_INFO: Info = Info { name: "bc", teacher: TeacherUse::Never, needs: &[], row_keys: &[] };

/// The row `bc` runs only on `line` (its settings are `line`'s).
const BC_ROW: &str = "[bc]\nmethod = \"bc\"\nonly_on = [\"line\"]";

impl Method for Bc {
    fn info(&self) -> &Info {
        &BC_INFO
    }
    fn keys(&self, _: &LabRow) -> Vec<String> {
        vec!["baselines.bc".into()]
    }
    fn check(&self, recipe: &MethodRecipe<'_>) -> vdd_lab::Result {
        recipe.get::<EmConfig>("baselines.bc").map(drop)
    }
    fn train(&self, job: &Job<'_>) -> vdd_lab::Result<Trained> {
        let config = EmConfig { seed: job.seed, ..job.recipe.get("baselines.bc")? };
        let one = MoeConfig { num_experts: 1, ..job.recipe.student.clone() };
        let job = Job { recipe: MethodRecipe { student: &one, ..job.recipe }, ..*job };
        vdd_lab::methods::em::fit(&job, config.iterations, |student, data, bar, _curves, _probe| {
            let mut em = vdd_mixture::Em::from_config(config, student, data)?;
            em.train(|_| bar.inc(1))?;
            Ok(em.into_student())
        })
    }
}

// ---------------------------------------------------------------------------------------------
// The task `line`.

/// The `line` recipe: the common header, the data, the evaluation, the (unused) learned
/// teachers and the student every recipe type has, and the method tables.
#[derive(Debug, Clone, Serialize, Deserialize)]
struct LineRecipe {
    #[serde(flatten)]
    header: Header,
    data: LineData,
    eval: LineEval,
    teachers: TeachersConfig,
    student: MoeConfig,
    /// Read by the methods by key path (`baselines.bc`).
    baselines: Table,
}

/// States `s ~ U[-1, 1]`, actions `2s + noise · U[-1, 1]`, drawn from the run seed.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct LineData {
    points: usize,
    noise: f32,
}

/// Held-out states: a grid of `states` points over `[-1, 1]`.
#[derive(Debug, Clone, Copy, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct LineEval {
    states: usize,
}

/// Every key of [`LineRecipe`]; a recipe file states only what differs. The `teachers` table
/// is required by [`TaskRecipe`] although no method of `line` uses a learned teacher.
const DEFAULTS: &str = r#"
name = "line"
description = "behaviour cloning on a line: a = 2s"
task = "line"
seeds = [0]
methods = ["bc"]

[data]
points = 256
noise = 0.05

[eval]
states = 200

[teachers.beso.config]
sigma_data = 0.5
sigma_min = 0.002
sigma_max = 80.0
rho = 7.0
sampler = "heun"
sampling_steps = 24
state_normalizer = "standard"
action_normalizer = "standard"
net = { hidden_dim = 64, num_blocks = 2, activation = "mish", embed_dim = 16, max_frequency = 16.0 }
training_sigma = { kind = "log_normal", mean = -1.6, std = 1.2 }

[teachers.beso.train]
steps = 4000
batch_size = 1024
warmup_steps = 200
final_lr_factor = 0.02
ema_decay = 0.995
grad_clip = 1.0
log_every = 100
chunks = 1
adam = { lr = 0.01, beta1 = 0.9, beta2 = 0.999, eps = 1e-8, weight_decay = 0.0, decoupled = false }

[teachers.ddpm.config]
num_steps = 16
sampler = "ancestral_large"
sampling_steps = 16
clip_denoised = 5.0
state_normalizer = "standard"
action_normalizer = "standard"
net = { hidden_dim = 64, num_blocks = 2, activation = "mish", embed_dim = 16, max_frequency = 16.0 }
beta_schedule = { kind = "cosine", s = 0.008 }
time_sampling = { kind = "log_normal", mean = -1.6, std = 1.2 }

[teachers.ddpm.train]
steps = 4000
batch_size = 1024
warmup_steps = 200
final_lr_factor = 0.02
ema_decay = 0.995
grad_clip = 1.0
log_every = 100
chunks = 1
adam = { lr = 0.01, beta1 = 0.9, beta2 = 0.999, eps = 1e-8, weight_decay = 0.0, decoupled = false }

[student]
state_dim = 1
action_dim = 1
num_experts = 1
expert_kind = "diagonal"
init_std = 1.0
min_std = 0.0001
shared_trunk = true
gating = "uniform"
mean_bias_init = 0.0
experts_network = { hidden_dim = 16, num_blocks = 1, activation = "mish" }
gating_network = { hidden_dim = 16, num_blocks = 1, activation = "mish" }

[baselines.bc]
iterations = 20
expert_steps_per_iter = 20
gating_steps_per_iter = 0
batch_size = 128
gating_batch_size = 128
seed = 0
expert_optimizer = { lr = 0.01, beta1 = 0.9, beta2 = 0.999, eps = 1e-8, weight_decay = 0.0, decoupled = false }
expert_lr_schedule = "constant"
gating_optimizer = { lr = 0.01, beta1 = 0.9, beta2 = 0.999, eps = 1e-8, weight_decay = 0.0, decoupled = false }
gating_lr_schedule = "constant"
"#;

impl TaskRecipe for LineRecipe {
    const METHOD_SECTIONS: &'static [&'static str] = &["baselines"];
    fn header(&self) -> &Header {
        &self.header
    }
    fn teachers(&self) -> &TeachersConfig {
        &self.teachers
    }
    fn student(&self) -> &MoeConfig {
        &self.student
    }
}

/// The task `line`.
struct Line;

static LINE: Line = Line;

impl Task for Line {
    fn name(&self) -> &'static str {
        "line"
    }
    /// Neither rollouts nor learned teachers: `line` scores policies by their error on
    /// held-out states, so no built-in method runs on it.
    fn offers(&self) -> &'static [vdd_lab::method::Capability] {
        &[]
    }

    fn columns(&self) -> Vec<Column> {
        vec![Column::new("mse", "MSE", 4), Column::new("train_seconds", "train s", 2)]
    }

    fn run(&self, ctx: &RunContext) -> vdd_lab::Result {
        let defaults: LineRecipe = recipe::defaults_from_toml(&[("line defaults", DEFAULTS)])?;
        let resolved = recipe::resolve(&defaults, &ctx.file, &ctx.overrides)?;
        let plan = driver::plan(&ctx.registry, &resolved, self.name(), &ctx.overrides.sets)?;
        let seeds = &resolved.base.header.seeds;
        let dir = ctx.run_dir(seeds);
        ctx.write_resolved(&dir, &resolved.to_toml()?)?;
        let mut stages = StageTimes::default();
        let key = |si: usize, pi: usize| -> vdd_lab::Result<String> {
            Ok(format!("{}-{}", recipe::config_hash(&plan[pi].cfg.data)?, seeds[si]))
        };
        let data = Datasets::build(seeds.len(), plan.len(), key, |si, pi| {
            Ok(line_data(&plan[pi].cfg.data, seeds[si]))
        })?;
        // No student cache, no curves over training, one job at a time.
        let mut trainings = driver::train_all(
            ctx,
            &plan,
            seeds,
            &data,
            1,
            (None, &|_| driver::Probes::default()),
            &mut stages,
        )?;
        let mut rows = driver::empty_rows(&plan);
        for (si, &seed) in seeds.iter().enumerate() {
            for (pi, e) in plan.iter().enumerate() {
                let mut trained =
                    trainings.trained.remove(&(si, pi)).ok_or("internal: not trained")?;
                let mse = line_mse(&mut trained.policy, e.cfg.eval.states, seed)?;
                let mut row = Row::new();
                row.insert("seed".into(), json!(seed));
                row.insert("mse".into(), report::json_f64(mse));
                row.insert("train_seconds".into(), report::json_f64(trained.train_seconds));
                rows[pi].1.push(row);
            }
        }
        let metrics = report::metrics_json(&ctx.name, self.name(), seeds, &rows);
        let table = report::markdown_table(&rows, &self.columns());
        driver::write_results(ctx, &dir, &metrics, &table, json!({ "stages": stages.to_json() }))
    }
}

/// The run seed's `points` pairs of the line.
fn line_data(d: &LineData, seed: u64) -> TrainingData {
    let mut rng = Seeds::new(seed).stream("line-data");
    let mut states = Mat::zeros(d.points, 1);
    let mut actions = Mat::zeros(d.points, 1);
    for i in 0..d.points {
        let s: f32 = rng.random_range(-1.0..1.0);
        states[(i, 0)] = s;
        actions[(i, 0)] = 2.0 * s + d.noise * rng.random_range(-1.0..1.0);
    }
    TrainingData::raw(states, actions, None)
}

/// The mean squared error of `policy`'s actions against `2s` on `n` held-out states.
fn line_mse(policy: &mut dyn Policy, n: usize, seed: u64) -> vdd_core::Result<f64> {
    policy.seed(seed);
    let states = Mat::from_fn(n, 1, |i, _| -1.0 + 2.0 * (i as f32 + 0.5) / n as f32);
    let mut actions = Mat::zeros(n, 1);
    policy.act_batch(states.as_ref(), actions.as_mut())?;
    let err = |i: usize| f64::from(actions[(i, 0)] - 2.0 * states[(i, 0)]).powi(2);
    Ok((0..n).map(err).sum::<f64>() / n as f64)
}

// ---------------------------------------------------------------------------------------------
// The tests.

/// The workspace's methods, rows and tasks with `bc` (method and row) and `line`.
fn registry() -> Registry {
    let rows: Table = BC_ROW.parse().unwrap();
    let with = |r: Registry| r.with_method(&BC)?.with_rows(&rows)?.with_task(&LINE);
    with(Registry::builtin()).unwrap_or_else(|e| panic!("{e}"))
}

/// A fresh directory under the system's temporary directory.
fn temp_dir(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("vdd-lab-plugins-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// Writes a recipe (`body` after `task = "line"`) into `dir` and runs it into `dir/run`.
fn run(registry: &Registry, dir: &Path, body: &str) -> vdd_lab::Result<PathBuf> {
    let file = dir.join("line-test.toml");
    std::fs::write(&file, format!("task = \"line\"\nseeds = [0, 1]\n{body}")).unwrap();
    let out = dir.join("run");
    let request = Request {
        recipe: file.to_str().unwrap().to_owned(),
        out: Some(out.clone()),
        command: "tests/lab_plugins.rs".into(),
        // The project root of the run: caches and logs go below it, not into the repository.
        root: Some(dir.to_path_buf()),
        ..Default::default()
    };
    run_with(registry, &request).map(|()| out)
}

/// The zero policy: what `line_mse` must call wrong.
struct Zero;

impl Policy for Zero {
    fn obs_dim(&self) -> usize {
        1
    }
    fn action_dim(&self) -> usize {
        1
    }
    fn act_into(&mut self, _: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
        action.fill(0.0);
        Ok(())
    }
}

/// One test for every run: a failed run removes the run directory it created through a
/// process-wide record ([`vdd_lab::context::remove_created_run_dir`]), so runs in parallel
/// tests of one binary could remove each other's.
#[test]
fn an_outside_method_and_task_run_through_the_driver() {
    let dir = temp_dir("run");
    let registry = registry();
    let t0 = std::time::Instant::now();
    let out = run(&registry, &dir, "methods = [\"bc\"]\n").unwrap_or_else(|e| panic!("{e}"));
    let seconds = t0.elapsed().as_secs_f64();
    let metrics: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(metrics["task"], json!("line"));
    assert_eq!(metrics["method_order"], json!(["bc"]));
    let bc = &metrics["methods"]["bc"];
    let mse = bc["mse"].as_f64().unwrap_or_else(|| panic!("no mse in {bc}"));
    assert!(mse.is_finite() && mse < 0.01, "bc fits the line badly: mse {mse} ({bc})");
    assert!(bc["train_seconds"].as_f64().is_some(), "{bc}");
    assert!(seconds < 30.0, "the run took {seconds:.1} s");
    for f in ["resolved.toml", "table.md", "run.json"] {
        assert!(out.join(f).is_file(), "no {f}");
    }
    let resolved = std::fs::read_to_string(out.join("resolved.toml")).unwrap();
    assert!(resolved.contains("[baselines.bc]"), "{resolved}");

    // Every finished training is kept; `--resume` loads it instead of training again (a
    // sentinel written into the kept seconds comes back), with the same evaluation.
    let sidecar = out.join("trained").join("bc-s0.json");
    let text = std::fs::read_to_string(&sidecar).unwrap_or_else(|e| panic!("{e}"));
    let mut kept: Value = serde_json::from_str(&text).unwrap();
    kept["train_seconds"] = json!(12345.0);
    std::fs::write(&sidecar, kept.to_string()).unwrap();
    let again = |resume: bool| {
        let recipe = dir.join("line-test.toml");
        let request = Request {
            recipe: recipe.to_str().unwrap().to_owned(),
            out: Some(out.clone()),
            root: Some(dir.clone()),
            resume,
            ..Default::default()
        };
        run_with(&registry, &request).unwrap_or_else(|e| panic!("{e}"));
        let m = std::fs::read_to_string(out.join("metrics.json")).unwrap();
        serde_json::from_str::<Value>(&m).unwrap()["methods"]["bc"].clone()
    };
    let resumed = again(true);
    assert_eq!(resumed["per_seed"][0]["train_seconds"], json!(12345.0), "{resumed}");
    assert_ne!(resumed["per_seed"][1]["train_seconds"], json!(12345.0), "{resumed}");
    assert_eq!(resumed["mse"], bc["mse"], "{resumed}");
    // Without `--resume` every training runs again.
    let fresh = again(false);
    assert_ne!(fresh["per_seed"][0]["train_seconds"], json!(12345.0), "{fresh}");
    assert_eq!(fresh["mse"], bc["mse"], "{fresh}");

    // The evaluation tells a wrong policy from the fitted one: E[(2s)²] = 4/3.
    let zero = line_mse(&mut Zero, 200, 0).unwrap();
    assert!(zero > 1.0 && zero > 20.0 * mse, "zero policy {zero}, bc {mse}");

    // Names the registry does not hold are errors naming them, and leave no run directory.
    let err = run(&registry, &dir, "methods = [\"nope\"]\n").unwrap_err().to_string();
    assert!(err.contains("unknown method `nope`") && err.contains("bc"), "{err}");
    let err = run(&Registry::builtin(), &dir, "methods = [\"bc\"]\n").unwrap_err().to_string();
    assert!(err.contains("unknown task `line`"), "{err}");
    // `em` is registered but does not run on `line`.
    let err = run(&registry, &dir, "methods = [\"em\"]\n").unwrap_err().to_string();
    assert!(err.contains("not available on task `line`"), "{err}");
    // A key of a method table no method reads.
    let err = run(&registry, &dir, "[baselines.bd]\niterations = 1\n").unwrap_err().to_string();
    assert!(err.contains("baselines.bd"), "{err}");

    // A recipe's own row: `bc` with settings of its own, beside `bc`; it changes `bc-short`
    // alone, so the two fit differently.
    let body = "methods = [\"bc\", \"bc-short\"]\n[runs.bc-short]\nmethod = \"bc\"\n\
                set = { \"baselines.bc.iterations\" = 1, \"baselines.bc.expert_steps_per_iter\" = 1 }\n";
    let out = run(&registry, &dir, body).unwrap_or_else(|e| panic!("{e}"));
    let metrics: Value =
        serde_json::from_str(&std::fs::read_to_string(out.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(metrics["method_order"], json!(["bc", "bc-short"]));
    let short = metrics["methods"]["bc-short"]["mse"].as_f64().unwrap();
    assert!(short > 2.0 * metrics["methods"]["bc"]["mse"].as_f64().unwrap(), "{metrics}");
    let resolved = std::fs::read_to_string(out.join("resolved.toml")).unwrap();
    assert!(resolved.contains("[runs.bc-short]"), "{resolved}");
    // A `--set` of a key the row sets itself would not reach it, and is refused.
    let recipe = dir.join("line-test.toml");
    let request = Request {
        recipe: recipe.to_str().unwrap().to_owned(),
        overrides: vdd_lab::recipe::Overrides {
            sets: vec![("baselines.bc.iterations".into(), "3".into())],
            ..Default::default()
        },
        out: Some(dir.join("run-set")),
        root: Some(dir.clone()),
        ..Default::default()
    };
    let err = run_with(&registry, &request).unwrap_err().to_string();
    assert!(err.contains("does not reach bc-short"), "{err}");
    // A row setting a key its method does not read.
    let body = "methods = [\"bc-x\"]\n[runs.bc-x]\nmethod = \"bc\"\nset = { \"baselines.em.iterations\" = 1 }\n";
    let err = run(&registry, &dir, body).unwrap_err().to_string();
    assert!(err.contains("row `bc-x`") && err.contains("does not read"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_name_is_registered_once() {
    let registry = registry();
    assert_eq!(registry.method("bc").unwrap().name(), "bc");
    assert_eq!(
        registry.rows_of("line").iter().map(|r| r.name.as_str()).collect::<Vec<_>>(),
        ["bc"]
    );
    assert_eq!(registry.columns_of("line")[0].key, "mse");
    let err = registry.clone().with_method(&BC).unwrap_err().to_string();
    assert!(err.contains("a method `bc` is registered already"), "{err}");
    let err = registry.with_task(&LINE).unwrap_err().to_string();
    assert!(err.contains("a task `line` is registered already"), "{err}");
    let err = Registry::builtin().with_task(vdd_lab::tasks::BUILTIN[0]).unwrap_err();
    assert!(err.to_string().contains("avoiding"), "{err}");
}

/// A teacher source of one's own: a wider BESO teacher read from a recipe key of its own, and
/// a row distilling it with VDD (`vdd.beso_wide` holds that row's VDD settings).
static BESO_WIDE: vdd_lab::teachers::Learned = vdd_lab::teachers::Learned {
    name: "beso-wide",
    kind: vdd_lab::teachers::TeacherKind::Beso,
    key: &["baselines.beso_wide"],
};

#[test]
fn an_outside_teacher_source_is_named_by_rows() {
    let rows: Table = "[vdd-beso-wide]\nmethod = \"vdd\"\nteacher = \"beso-wide\"".parse().unwrap();
    let err = Registry::builtin().with_rows(&rows).unwrap_err().to_string();
    assert!(err.contains("unknown teacher `beso-wide`"), "{err}");
    let registry = Registry::builtin().with_teacher(&BESO_WIDE).unwrap().with_rows(&rows).unwrap();
    let row = registry.row("vdd-beso-wide").unwrap();
    assert_eq!(row.keys()[..2], ["baselines.beso_wide", "vdd.beso_wide"]);
    let err = registry.with_teacher(&BESO_WIDE).unwrap_err().to_string();
    assert!(err.contains("registered already"), "{err}");
}
