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
/// with `--fresh` if `fresh`.
pub fn run(root: &Path, command: &str, fresh: bool) -> vdd_lab::Result {
    let request = Request {
        recipe: "tiny".into(),
        out: Some(root.join("results/tiny")),
        command: command.into(),
        root: Some(root.to_owned()),
        fresh,
        ..Default::default()
    };
    run_with(&Registry::builtin(), &request)
}
