//! `vdd.beso_expert_visits` end to end on a tiny Avoiding budget: the rounds on the states the
//! student visits change the student and count in its budget, and bad settings are refused
//! with the key's name.

use std::path::{Path, PathBuf};

mod common;

const VISITS: &str =
    "\n[vdd]\nbeso_expert_visits = { episodes = 2, rounds = 2, iterations = 10 }\n";

fn run(root: &Path) -> vdd_lab::Result {
    common::run(root, "tests/expert_visits.rs", |_| {})
}

fn root(tag: &str, recipe: &str) -> PathBuf {
    common::root(&format!("visits-{tag}"), recipe)
}

/// The run's student file and its `train_steps`.
fn student_and_steps(root: &Path) -> (Vec<u8>, u64) {
    let out = root.join("results/tiny");
    let model = std::fs::read(out.join("models/vdd-beso-s0.safetensors")).unwrap();
    let metrics: serde_json::Value =
        serde_json::from_slice(&std::fs::read(out.join("metrics.json")).unwrap()).unwrap();
    let steps = metrics["methods"]["vdd-beso"]["per_seed"][0]["train_steps"].as_u64().unwrap();
    (model, steps)
}

#[test]
fn rounds_on_visited_states_change_the_student_and_count_in_its_budget() {
    // Avoiding's defaults continue the distillation on visited states; `false` switches it off.
    let plain =
        root("plain", &format!("{}\n[vdd]\nbeso_expert_visits = false\n", common::tiny_vdd_beso()));
    run(&plain).unwrap_or_else(|e| panic!("{e}"));
    let visits = root("visits", &format!("{}{VISITS}", common::tiny_vdd_beso()));
    run(&visits).unwrap_or_else(|e| panic!("{e}"));
    let (a, steps_a) = student_and_steps(&plain);
    let (b, steps_b) = student_and_steps(&visits);
    assert_eq!(steps_a, 30);
    assert_eq!(steps_b, 30 + 2 * 10, "the budget counts both rounds");
    assert_ne!(a, b, "the rounds on visited states changed nothing");
    // The same settings give the same student (the visits' episodes are seeded).
    let again = root("again", &format!("{}{VISITS}", common::tiny_vdd_beso()));
    run(&again).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(student_and_steps(&again).0, b);
    for r in [plain, visits, again] {
        std::fs::remove_dir_all(&r).unwrap();
    }
}

#[test]
fn bad_expert_visits_are_refused_with_the_key() {
    let bad = VISITS.replace("rounds = 2", "rounds = 0");
    let root = root("bad", &format!("{}{bad}", common::tiny_vdd_beso()));
    let e = run(&root).unwrap_err().to_string();
    assert!(e.contains("vdd.beso_expert_visits") && e.contains("rounds"), "{e}");
    std::fs::remove_dir_all(&root).unwrap();
}
