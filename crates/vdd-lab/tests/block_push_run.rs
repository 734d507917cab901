//! The Block-Push recipe end to end on a tiny budget (a few demonstrations, a few dozen
//! training steps, a few rollouts): data, the BESO teacher, VDD-BESO and EM, the rollouts of
//! `vdd_tasks::block_push::EvalProtocol`, the timing, `metrics.json` and `table.md`, and a
//! tuning run appending to its log. Figures are checked only for their ranges.

use std::path::{Path, PathBuf};

use vdd_lab::Registry;
use vdd_lab::experiment::{Request, run_with};

/// A fresh project root with the recipe `tiny.toml` in `recipes/`.
fn root(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("vdd-lab-bp-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(dir.join("recipes")).unwrap();
    std::fs::create_dir_all(dir.join("docs")).unwrap();
    std::fs::write(dir.join("recipes/tiny.toml"), TINY).unwrap();
    dir
}

const TINY: &str = r#"
name = "tiny"
task = "block-push"
description = "Block-Push on a tiny budget"
seeds = [0]
methods = ["beso", "vdd-beso", "em", "cd"]

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

[baselines.cd.train]
steps = 20
batch_size = 16
log_every = 10

[baselines.em]
iterations = 2
expert_steps_per_iter = 3
gating_steps_per_iter = 3

[eval]
rollouts = 4
lockstep_batch = 2
timing_calls = 20
timing_warmup = 2
timing_min_round_ms = 0.1

[plots]
enabled = true
png = false
trajectories = 2
"#;

fn run(root: &Path, out: &Path, tuning: bool) -> vdd_lab::Result {
    let shorthands = if tuning { vec![("tuning".into(), "true".into())] } else { Vec::new() };
    let overrides =
        vdd_lab::recipe::Overrides { seeds: tuning.then(|| vec![100]), ..Default::default() };
    let request = Request {
        recipe: "tiny".into(),
        overrides,
        shorthands,
        out: Some(out.to_owned()),
        command: "tests/block_push_run.rs".into(),
        root: Some(root.to_owned()),
        ..Default::default()
    };
    run_with(&Registry::builtin(), &request)
}

#[test]
fn a_tiny_block_push_run_writes_its_metrics_and_a_tuning_run_its_log() {
    let root = root("run");
    let out = root.join("results/tiny");
    run(&root, &out, false).unwrap();
    let metrics: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("metrics.json")).unwrap()).unwrap();
    assert_eq!(metrics["task"], "block-push");
    let text = metrics.to_string();
    for method in ["beso", "vdd-beso", "em"] {
        assert!(text.contains(&format!("\"{method}\"")), "{method} missing: {text}");
    }
    for key in ["success_rate", "p1_rate", "task_entropy", "us_per_action", "mode_counts"] {
        assert!(text.contains(key), "{key} missing: {text}");
    }
    let table = std::fs::read_to_string(out.join("table.md")).unwrap();
    assert!(table.contains("| vdd-beso | 1 |") && table.contains("p1"), "{table}");
    let modes = std::fs::read_to_string(out.join("modes.svg")).unwrap();
    assert!(modes.contains("demonstrations"), "the demonstrations' histogram is missing");
    assert_eq!(metrics["data"]["dataset_mode_counts"].as_array().map(Vec::len), Some(4));
    // The trajectory figure: the demonstrations' panel and one per method.
    let svg = std::fs::read_to_string(out.join("trajectories.svg")).unwrap();
    for panel in ["demonstrations (target 0 left)", "beso: success", "vdd-beso: success"] {
        assert!(svg.contains(panel), "{panel} missing from trajectories.svg");
    }
    // Every saved policy (student, teacher, consistency model) acts on raw observations and
    // gives the run's figures bit for bit (what `rollout_saved --task block-push` prints).
    let protocol = vdd_tasks::block_push::EvalProtocol { rollouts: 4, lockstep_batch: 2 };
    let figures = |m: vdd_tasks::block_push::rollout::Metrics| {
        serde_json::json!([m.success_rate, m.p1_rate, m.task_entropy])
    };
    let same_figures = |method: &str, got: serde_json::Value| {
        let row = &metrics["methods"][method]["per_seed"][0];
        let want = serde_json::json!([row["success_rate"], row["p1_rate"], row["task_entropy"]]);
        assert_eq!(got, want, "{method}: {row}");
    };
    let model = |name: &str| out.join(format!("models/{name}-s0.safetensors"));
    let saved = vdd_moe::load_policy(&model("vdd-beso")).unwrap();
    same_figures("vdd-beso", figures(protocol.evaluate(&saved, 0, 2, false).unwrap().metrics));
    let saved = vdd_diffusion::DiffusionTeacher::load_policy(&model("beso"), 0).unwrap();
    same_figures("beso", figures(protocol.evaluate(&saved, 0, 2, false).unwrap().metrics));
    let saved = vdd_consistency::ConsistencyModel::load_policy(&model("cd"), 0).unwrap();
    same_figures("cd", figures(protocol.evaluate(&saved, 0, 2, false).unwrap().metrics));

    let tuning_out = root.join("results/tuning-tiny");
    run(&root, &tuning_out, true).unwrap();
    let log = vdd_lab::tuning::read_log(&root.join("docs/block-push-tuning-log.toml")).unwrap();
    assert_eq!(log.len(), 4);
    assert!(log.iter().all(|e| e.seeds == [100] && e.success_rate.len() == 1));
    std::fs::remove_dir_all(&root).unwrap();
}

/// `vdd.beso_gating_visits`: the student's gating is fitted to teacher samples at the
/// demonstration states and at the states the student visits, over two rounds.
#[test]
fn a_gating_fitted_on_visited_states_runs_end_to_end() {
    let root = root("visits");
    let tiny = TINY
        .replace(r#"methods = ["beso", "vdd-beso", "em", "cd"]"#, r#"methods = ["vdd-beso"]"#)
        + r#"
[vdd]
beso_gating_fit = { samples_per_state = 1, iterations = 2, steps_per_iter = 2, batch_size = 16 }
beso_gating_visits = { episodes = 2, rounds = 2 }
"#;
    std::fs::write(root.join("recipes/tiny.toml"), tiny).unwrap();
    let out = root.join("results/tiny");
    run(&root, &out, false).unwrap();
    let model = out.join("models/vdd-beso-s0.safetensors");
    let policy = vdd_moe::load_policy(&model).unwrap();
    assert!(policy.inner().has_learned_gating(), "the fit replaced the uniform gating");
    std::fs::remove_dir_all(&root).unwrap();
}
