//! The D3IL recipes (Pushing, Aligning) end to end on a tiny budget (a few demonstrations, a few
//! dozen training steps, 2 contexts × 2 rollouts): data, the BESO teacher, VDD-BESO and EM, the
//! rollouts of `vdd_tasks::d3il::EvalProtocol`, the timing, `metrics.json`, `table.md`, the mode
//! histograms and the mode-coloured trajectory figure, a saved student reproducing its row, and
//! a tuning run appending to its log.

use std::path::Path;

use vdd_lab::Registry;
use vdd_lab::experiment::{Request, run_with};
use vdd_tasks::aligning::AligningEnv;
use vdd_tasks::d3il::{ContextEnv, EvalProtocol};
use vdd_tasks::pushing::PushingEnv;

mod common;

/// The tiny recipe of task `task`.
fn tiny(task: &str) -> String {
    format!(
        r#"
name = "tiny"
task = "{task}"
description = "{task} on a tiny budget"
seeds = [0]
methods = ["beso", "vdd-beso", "em"]

[data]
demonstrations = 3
validation_fraction = 0.0

[teachers.beso.train]
steps = 30
batch_size = 32
log_every = 10

[vdd.beso]
iterations = 30
batch_size = 8

[baselines.em]
iterations = 2
expert_steps_per_iter = 3
gating_steps_per_iter = 3

[eval]
contexts = 2
rollouts_per_context = 2
lockstep_batch = 4
timing_calls = 20
timing_warmup = 2
timing_min_round_ms = 0.1

[plots]
png = false
trajectories = 2
"#
    )
}

/// The `--tuning` run of recipe `tiny` of `root` (tuning seed 100) into `out`.
fn tuning_run(root: &Path, out: &Path) -> vdd_lab::Result {
    let request = Request {
        recipe: "tiny".into(),
        overrides: vdd_lab::recipe::Overrides { seeds: Some(vec![100]), ..Default::default() },
        shorthands: vec![("tuning".into(), "true".into())],
        out: Some(out.to_owned()),
        command: "tests/d3il_runs.rs".into(),
        root: Some(root.to_owned()),
        ..Default::default()
    };
    run_with(&Registry::builtin(), &request)
}

/// A tiny run of the task of `E` writes its metrics (with p1 when `p1`), table and figures, its
/// saved student gives its row bit for bit, and a tuning run appends to the task's log.
fn a_tiny_run<E: ContextEnv>(p1: bool) {
    let task = E::NAME;
    let root = common::root(&format!("{task}-run"), &tiny(task));
    let out = root.join("results/tiny");
    common::run(&root, "tests/d3il_runs.rs", |_| {}).unwrap();
    let metrics: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(metrics["task"], task);
    let text = metrics.to_string();
    for method in ["beso", "vdd-beso", "em"] {
        assert!(text.contains(&format!("\"{method}\"")), "{method} missing: {text}");
    }
    for key in [
        "success_rate",
        "mean_distance",
        "task_entropy",
        "mode_entropy",
        "us_per_action",
        "mode_counts",
        "dataset_mode_counts",
    ] {
        assert!(text.contains(key), "{key} missing: {text}");
    }
    assert_eq!(text.contains("p1_rate"), p1, "{text}");
    let table = std::fs::read_to_string(out.join("table.md")).unwrap();
    assert!(table.contains("| vdd-beso | 1 |") && table.contains("task entropy"), "{table}");
    assert_eq!(table.contains("| p1 |"), p1, "{table}");
    // The saved student acts on raw observations and gives the run's figures bit for bit
    // (what `rollout_saved --task <task> --contexts 2 --rollouts 2 --lockstep-batch 4` prints).
    let saved = vdd_moe::load_policy(&out.join("models/vdd-beso-s0.safetensors")).unwrap();
    let m = EvalProtocol::<E>::new(2, 2, 4).evaluate(&saved, 0, 2, false).unwrap().metrics;
    let row = &metrics["methods"]["vdd-beso"]["per_seed"][0];
    assert_eq!(row["success_rate"], serde_json::json!(m.success_rate), "{row}");
    assert_eq!(row.get("p1_rate"), m.p1_rate.map(|p1| serde_json::json!(p1)).as_ref(), "{row}");
    assert_eq!(row["task_entropy"], serde_json::json!(m.task_entropy), "{row}");
    assert_eq!(row["mean_distance"], serde_json::json!(m.mean_distance), "{row}");
    let modes = std::fs::read_to_string(out.join("modes.svg")).unwrap();
    assert!(modes.contains("demonstrations"), "the demonstrations' histogram is missing");
    let traj = std::fs::read_to_string(out.join("trajectories.svg")).unwrap();
    for panel in ["demonstrations", "beso", "vdd-beso", "em"] {
        assert!(traj.contains(&format!("{panel}: success")), "panel {panel} missing");
    }

    let tuning_out = root.join("results/tuning-tiny");
    tuning_run(&root, &tuning_out).unwrap();
    let log_path = root.join(format!("docs/{task}-tuning-log.toml"));
    let log = vdd_lab::tuning::read_log(&log_path).unwrap();
    assert_eq!(log.len(), 3);
    assert!(log.iter().all(|e| e.seeds == [100] && e.success_rate.len() == 1));
    std::fs::remove_dir_all(&root).unwrap();
}

#[test]
fn a_tiny_pushing_run_writes_its_metrics_and_a_tuning_run_its_log() {
    a_tiny_run::<PushingEnv>(true);
}

#[test]
fn a_tiny_aligning_run_writes_its_metrics_and_a_tuning_run_its_log() {
    a_tiny_run::<AligningEnv>(false);
}
