//! Tuning runs, kept apart from the reported ones, and the committed tuning log: the protocol
//! and the log are [`vdd_recipe::tuning`]'s (re-exported here); this module adds where the
//! repository keeps the logs and what a method's configuration is.
//!
//! `cargo xtask experiment <recipe> --tuning` sets the tuning seeds (100–104 unless `--seeds`
//! names others) and the tuning data; its results go to `results/tuning/<recipe>/<run>/`
//! (outside the runs `cargo xtask table` collects). The rollouts' root is derived from the run
//! seed, the demonstrations' from `data.seed`, and the training of every method from the run
//! seed. Every tuning run appends one entry per method to `docs/<task>-tuning-log.toml`
//! (committed); `tuning_configs` in a reported run's `metrics.json` is the number of distinct
//! configurations of the method in that log.

use std::path::PathBuf;

pub use vdd_recipe::tuning::*;

use crate::method::{Method, MethodRecipe};

/// The tuning log of `task`: `docs/<task>-tuning-log.toml`.
pub fn log_path(root: &std::path::Path, task: &str) -> PathBuf {
    root.join("docs").join(format!("{task}-tuning-log.toml"))
}

/// [`vdd_recipe::tuning::method_config_hash`] of `method`: `data`, its teachers (when it has
/// one), the student mixture and the values of its recipe keys.
pub fn method_config_hash<D: serde::Serialize>(
    method: &dyn Method,
    recipe: &MethodRecipe<'_>,
    data: &D,
) -> crate::Result<String> {
    let info = method.info();
    let mut keys = serde_json::Map::new();
    for k in info.keys {
        let v: Option<toml::Value> = recipe.get_opt(k)?;
        keys.insert((*k).to_owned(), serde_json::to_value(v)?);
    }
    let teachers = info.teacher.map(|_| recipe.teachers);
    Ok(vdd_recipe::tuning::method_config_hash(info.name, data, teachers, recipe.student, keys)?)
}
