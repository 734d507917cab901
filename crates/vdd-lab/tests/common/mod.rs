//! What the tiny-run integration tests share: a fresh project root holding one recipe, and a
//! run of that recipe.

use std::path::{Path, PathBuf};

use vdd_lab::Registry;
use vdd_lab::experiment::{Request, run_with};

/// A fresh project root `<tmp>/vdd-lab-<tag>-<pid>` with `recipe` as `recipes/tiny.toml`.
pub fn root(tag: &str, recipe: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("vdd-lab-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(dir.join("recipes")).unwrap();
    std::fs::create_dir_all(dir.join("docs")).unwrap();
    std::fs::write(dir.join("recipes/tiny.toml"), recipe).unwrap();
    dir
}

/// Runs recipe `tiny` of `root` into `root/results/tiny`, `command` recorded as its command,
/// with the request changed by `tweak` (`--fresh`, `--quick`, ...).
pub fn run(root: &Path, command: &str, tweak: impl FnOnce(&mut Request)) -> vdd_lab::Result {
    let mut request = Request {
        recipe: "tiny".into(),
        out: Some(root.join("results/tiny")),
        command: command.into(),
        root: Some(root.to_owned()),
        ..Default::default()
    };
    tweak(&mut request);
    run_with(&Registry::builtin(), &request)
}

/// Avoiding with `vdd-beso-selected` on a tiny budget: four demonstrations, a 30-step teacher,
/// 30 VDD iterations and two rounds of 10 on visited states, three curve points.
#[allow(dead_code)] // not every test binary that shares this module uses it
pub const TINY_AVOIDING: &str = r#"
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

/// `vdd-beso` on the tiny Avoiding budget, without curves and without a `[vdd]` table (each
/// test adds its own).
#[allow(dead_code)] // not every test binary that shares this module uses it
pub fn tiny_vdd_beso() -> String {
    TINY_AVOIDING
        .replace(r#"methods = ["vdd-beso-selected"]"#, r#"methods = ["vdd-beso"]"#)
        .replace("[vdd]\nbeso_expert_visits = { episodes = 2, rounds = 2, iterations = 10 }\n", "")
        .replace("curve_points = 3\ncurve_rollouts = 4\n", "curve_points = 0\n")
}
