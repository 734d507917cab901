//! Results, from `vdd-report` (the `metrics.json` layout, mean ± std summaries, tables, budgets
//! and run comparison), re-exported for the tasks.

pub use vdd_report::budget::*;
pub use vdd_report::compare::*;
pub use vdd_report::metrics::*;
pub use vdd_report::table::*;
