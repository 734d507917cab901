//! `vdd-beso-selected` end to end on a tiny Avoiding budget: the row is the snapshot with the
//! highest held-out task entropy among the curves' checkpoints, its curves say which, rounds on
//! visited states become iterations on the demonstrations' states (the same budget), and on
//! a task without curves over training the row is refused with the reason.

use std::path::{Path, PathBuf};

mod common;

const TINY: &str = r#"
name = "tiny"
task = "avoiding"
description = "Avoiding on a tiny budget"
seeds = [0]
methods = ["vdd-beso-selected"]

[data]
demonstrations = 4
validation_fraction = 0.0

[teachers.beso.train]
steps = 30
batch_size = 32
log_every = 10

[vdd]
beso_expert_visits = { episodes = 2, rounds = 2, iterations = 10 }

[vdd.beso]
iterations = 30
batch_size = 8

[eval]
rollouts = 4
lockstep_batch = 2
timing_calls = 20
timing_warmup = 2
timing_min_round_ms = 0.1
curve_points = 3
curve_rollouts = 4

[plots]
enabled = false
"#;

fn run(root: &Path) -> vdd_lab::Result {
    common::run(root, "tests/checkpoint_selection.rs")
}

fn root(tag: &str, recipe: &str) -> PathBuf {
    common::root(&format!("select-{tag}"), recipe)
}

#[test]
fn the_selected_row_is_the_checkpoint_with_the_highest_held_out_entropy() {
    let root = root("avoiding", TINY);
    run(&root).unwrap_or_else(|e| panic!("{e}"));
    let out = root.join("results/tiny");
    let metrics = std::fs::read_to_string(out.join("metrics.json")).unwrap();
    assert!(metrics.contains("\"vdd-beso-selected\""), "{metrics}");
    // The rounds on visited states take no checkpoints: their iterations run on the
    // demonstrations' states, the same budget.
    let m: serde_json::Value = serde_json::from_str(&metrics).unwrap();
    let steps = &m["methods"]["vdd-beso-selected"]["per_seed"][0]["train_steps"];
    assert_eq!(steps.as_u64(), Some(30 + 2 * 10), "{metrics}");
    let curves: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("curves.json")).unwrap()).unwrap();
    let text = curves.to_string();
    // The held-out entropy at the three checkpoints, and the one chosen.
    let find = |series: &str| -> Vec<(f64, f64)> {
        fn walk(v: &serde_json::Value, series: &str, out: &mut Vec<(f64, f64)>) {
            match v {
                serde_json::Value::Object(m) => {
                    for (k, v) in m {
                        if k == series {
                            *out = serde_json::from_value(v.clone()).unwrap();
                            return;
                        }
                        walk(v, series, out);
                    }
                }
                serde_json::Value::Array(a) => a.iter().for_each(|v| walk(v, series, out)),
                _ => {}
            }
        }
        let mut out = Vec::new();
        walk(&curves, series, &mut out);
        out
    };
    let entropy = find("held-out task entropy");
    assert_eq!(entropy.len(), 3, "{text}");
    let chosen = find("selected checkpoint");
    assert_eq!(chosen.len(), 1, "{text}");
    let best = entropy.iter().copied().fold(entropy[0], |a, p| if p.1 > a.1 { p } else { a });
    assert_eq!(chosen[0], best, "{text}");
    std::fs::remove_dir_all(&root).unwrap();
}

#[test]
fn a_task_without_curves_refuses_the_selected_row_with_the_reason() {
    let recipe = TINY
        .replace(r#"task = "avoiding""#, r#"task = "block-push""#)
        .replace("curve_points = 3\ncurve_rollouts = 4\n", "");
    let root = root("block-push", &recipe);
    let e = run(&root).unwrap_err().to_string();
    assert!(e.contains("checkpoint selection needs curves over training"), "{e}");
    std::fs::remove_dir_all(&root).unwrap();
}
