//! Experiment recipes: TOML files in `recipes/` resolved against the task's defaults, the TOML
//! files in `recipes/defaults/` (embedded in the binary).
//!
//! The resolution (defaults, the recipe file, `[quick]`, `--seeds`/`--methods`/`--set`
//! overrides, `[[variants]]`), the checks of unknown keys and the configuration hashes are
//! [`vdd_recipe`]'s, re-exported here; this module adds where the repository keeps its recipes.

use std::path::{Path, PathBuf};

pub use vdd_recipe::*;

/// The workspace this crate belongs to (two levels above `crates/vdd-lab`): where the recipes,
/// the results and the tuning logs live.
pub fn repo_root() -> PathBuf {
    let manifest = Path::new(env!("CARGO_MANIFEST_DIR"));
    let manifest = manifest.parent().unwrap_or(manifest);
    manifest.parent().unwrap_or(manifest).to_path_buf()
}

/// The recipe file for `name`: an existing `.toml` path, or `recipes/<name>.toml`.
pub fn recipe_path(name: &str) -> RecipeResult<PathBuf> {
    run::find_recipe(&repo_root().join("recipes"), name)
}

/// Names of the recipes in `recipes/`.
pub fn available_recipes() -> Vec<String> {
    run::recipes_in(&repo_root().join("recipes"))
}
