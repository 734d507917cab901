//! The D3IL Aligning pipeline ([`super::d3il`], the D3IL tasks' one body): scripted
//! demonstrations ([`vdd_tasks::aligning::dataset`]) → teachers → every method → rollouts
//! ([`vdd_tasks::aligning::EvalProtocol`]: success, D3IL's mean distance, task entropy per
//! context over the two modes, inside and outside) and µs per action → `metrics.json`,
//! `table.md`, the figures; `--tuning` appends to `docs/aligning-tuning-log.toml`. This file
//! says what is Aligning's: its environment and demonstrator, defaults, columns and trajectory
//! panels.

use vdd_tasks::aligning::AligningEnv;
use vdd_tasks::aligning::oracle::OracleConfig;

use super::d3il::{D3ilRecipe, D3ilTask, FigureFn, PanelFn};
use crate::plots;
use crate::report;

/// A recipe of the Aligning task (see `recipes/aligning.toml`); the values not given there
/// come from `recipes/defaults/aligning.toml` ([`D3ilRecipe::defaults`]). Unknown keys are
/// errors.
pub type AligningRecipe = D3ilRecipe<Aligning>;

/// The D3IL Aligning task.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Aligning;

/// The columns of Aligning's tables.
pub const COLUMNS: [report::Column; 6] = [
    report::Column::new("success_rate", "success", 3),
    report::Column::new("mean_distance", "mean distance", 4),
    report::Column::new("task_entropy", "task entropy", 3),
    report::Column::new("mode_entropy", "mode entropy", 3),
    report::Column::new("us_per_action", "µs / action", 1),
    report::Column::new("train_seconds", "train s", 1),
];

impl D3ilTask for Aligning {
    type Env = AligningEnv;
    type Oracle = OracleConfig;
    const TITLE: &'static str = "Aligning";
    const DEFAULTS: (&'static str, &'static str) = (
        "recipes/defaults/aligning.toml",
        include_str!("../../../../recipes/defaults/aligning.toml"),
    );
    const COLUMNS: &'static [report::Column] = &COLUMNS;
    const VISITS_STREAM: &'static str = "aligning-visits";
    const TABLE_NOTE: &'static str = "success: the tray within 0.0156 and 0.048π of the target pose; mean distance: D3IL's ½ (position error + rotation error / π) at the last step; task entropy: D3IL's, per context over the 2 modes (inside, outside) of the successes (log base 2), averaged over contexts";
    const CHECK_ORACLE: fn(&OracleConfig) -> Result<(), vdd_tasks::TaskError> =
        OracleConfig::validate;
    const PANEL: PanelFn = plots::aligning_panel;
    const TRAJECTORIES: FigureFn = plots::aligning_trajectories;
}

#[cfg(test)]
mod tests {
    #[test]
    fn the_recipe_and_its_defaults_resolve_and_tuning_sets_the_tuning_seeds() {
        super::super::d3il::check_recipe::<super::Aligning>();
    }
}
