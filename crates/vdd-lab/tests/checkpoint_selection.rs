//! `vdd-beso-selected` end to end on a tiny Avoiding budget: the row is the snapshot with the
//! highest held-out task entropy among the curves' checkpoints, its curves say which, rounds on
//! visited states become iterations on the demonstrations' states (the same budget), a
//! training without selection keeps the selected snapshot for the selecting row of the same
//! training, and a task without curves over training refuses the row, before any training,
//! with the reason (and `all` leaves it out there).

use std::path::{Path, PathBuf};

mod common;

use common::TINY_AVOIDING as TINY;

fn run(root: &Path) -> vdd_lab::Result {
    common::run(root, "tests/checkpoint_selection.rs", |_| {})
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
    assert!(e.contains("needs \"training_curves\", which the task does not offer"), "{e}");
    // Refused before any training: no teacher was trained.
    assert!(!root.join("results/cache").exists(), "{e}");
    std::fs::remove_dir_all(&root).unwrap();
    let all = vdd_lab::Registry::builtin();
    let rows = all.parse_rows(&["all".to_owned()], "block-push").unwrap();
    assert!(rows.iter().all(|r| r.name != "vdd-beso-selected"));
    let rows = all.parse_rows(&["all".to_owned()], "avoiding").unwrap();
    assert!(rows.iter().any(|r| r.name == "vdd-beso-selected"));
}

/// The files of the student cache under `root`.
fn cached_students(root: &Path) -> Vec<String> {
    let dir = root.join("results/cache/students");
    let mut names: Vec<String> = std::fs::read_dir(&dir)
        .unwrap_or_else(|e| panic!("{}: {e}", dir.display()))
        .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
        .collect();
    names.sort();
    names
}

#[test]
fn a_training_without_selection_spares_the_selecting_row_its_training() {
    // Without rounds on visited states both rows train the same student.
    let plain = TINY
        .replace(r#"methods = ["vdd-beso-selected"]"#, r#"methods = ["vdd-beso"]"#)
        .replace("{ episodes = 2, rounds = 2, iterations = 10 }", "false");
    let root = root("spared", &plain);
    run(&root).unwrap_or_else(|e| panic!("{e}"));
    let after_plain = cached_students(&root);
    assert!(after_plain.iter().any(|n| n.starts_with("vdd-beso-selected-")), "{after_plain:?}");
    let selecting =
        plain.replace(r#"methods = ["vdd-beso"]"#, r#"methods = ["vdd-beso-selected"]"#);
    std::fs::write(root.join("recipes/tiny.toml"), selecting).unwrap();
    run(&root).unwrap_or_else(|e| panic!("{e}"));
    assert_eq!(cached_students(&root), after_plain, "the selecting row trained again");
    let curves = std::fs::read_to_string(root.join("results/tiny/curves.json")).unwrap();
    assert!(curves.contains("selected checkpoint"), "{curves}");
    std::fs::remove_dir_all(&root).unwrap();
}
