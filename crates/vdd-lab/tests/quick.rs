//! `--quick` on a recipe without a `[quick]` table (a tuning or table recipe) takes the task's
//! own recipe's table instead of running the full budget, and says so when there is none.

use std::path::Path;

mod common;

fn run_quick(root: &Path) -> vdd_lab::Result {
    common::run(root, "tests/quick.rs", |r| r.overrides.quick = true)
}

#[test]
fn a_recipe_without_quick_takes_the_tasks_quick_table() {
    let tiny = format!("{}\n[vdd]\nbeso_expert_visits = false\n", common::tiny_vdd_beso());
    let root = common::root("quick-none", &tiny);
    let e = run_quick(&root).unwrap_err().to_string();
    assert!(e.contains("tiny.toml has no [quick] table") && e.contains("avoiding.toml"), "{e}");
    assert!(!root.join("results").exists(), "{e}");

    let task = "name = \"avoiding\"\ntask = \"avoiding\"\n[quick]\n\"vdd.beso.iterations\" = 7\n";
    std::fs::write(root.join("recipes/avoiding.toml"), task).unwrap();
    run_quick(&root).unwrap_or_else(|e| panic!("{e}"));
    let metrics = std::fs::read_to_string(root.join("results/tiny/metrics.json")).unwrap();
    let m: serde_json::Value = serde_json::from_str(&metrics).unwrap();
    let steps = &m["methods"]["vdd-beso"]["per_seed"][0]["train_steps"];
    assert_eq!(steps.as_u64(), Some(7), "{metrics}");
    std::fs::remove_dir_all(&root).unwrap();
}
