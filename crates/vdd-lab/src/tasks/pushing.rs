//! The D3IL Pushing pipeline ([`super::d3il`], the D3IL tasks' one body): scripted
//! demonstrations ([`vdd_tasks::pushing::dataset`]) → teachers → every method → rollouts
//! ([`vdd_tasks::pushing::EvalProtocol`]: success, p1, D3IL's mean distance, task entropy per
//! context over the four modes) and µs per action → `metrics.json`, `table.md`, the figures;
//! `--tuning` appends to `docs/pushing-tuning-log.toml`. This file says what is Pushing's: its
//! environment and demonstrator, defaults, columns (with p1) and trajectory panels.

use vdd_tasks::pushing::PushingEnv;
use vdd_tasks::pushing::oracle::OracleConfig;

use super::d3il::{D3ilRecipe, D3ilTask, FigureFn, PanelFn};
use crate::plots;
use crate::report;

/// A recipe of the Pushing task (see `recipes/pushing.toml`); the values not given there
/// come from `recipes/defaults/pushing.toml` ([`D3ilRecipe::defaults`]). Unknown keys are
/// errors.
pub type PushingRecipe = D3ilRecipe<Pushing>;

/// The D3IL Pushing task.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Pushing;

/// The columns of Pushing's tables.
pub const COLUMNS: [report::Column; 7] = [
    report::Column::new("success_rate", "success", 3),
    report::Column::new("p1_rate", "p1", 3),
    report::Column::new("mean_distance", "mean distance", 4),
    report::Column::new("task_entropy", "task entropy", 3),
    report::Column::new("mode_entropy", "mode entropy", 3),
    report::Column::new("us_per_action", "µs / action", 1),
    report::Column::new("train_seconds", "train s", 1),
];

impl D3ilTask for Pushing {
    type Env = PushingEnv;
    type Oracle = OracleConfig;
    const TITLE: &'static str = "Pushing";
    const DEFAULTS: (&'static str, &'static str) = (
        "recipes/defaults/pushing.toml",
        include_str!("../../../../recipes/defaults/pushing.toml"),
    );
    const COLUMNS: &'static [report::Column] = &COLUMNS;
    const VISITS_STREAM: &'static str = "pushing-visits";
    const TABLE_NOTE: &'static str = "success: both boxes in distinct targets; p1: a box reached a target; mean distance: D3IL's ½ (min d_r + min d_g) at the last step; task entropy: D3IL's, per context over the 4 modes of the successes (log base 4), averaged over contexts";
    const CHECK_ORACLE: fn(&OracleConfig) -> Result<(), vdd_tasks::TaskError> =
        OracleConfig::validate;
    const PANEL: PanelFn = plots::pushing_panel;
    const TRAJECTORIES: FigureFn = plots::pushing_trajectories;
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_recipe_and_its_defaults_resolve_and_tuning_sets_the_tuning_seeds() {
        super::super::d3il::check_recipe::<super::Pushing>();
    }
}
