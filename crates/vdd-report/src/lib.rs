//! Results of experiment runs, from plain data to files and strings.
//!
//! * [`metrics`]: one method's per-seed values ([`Row`](metrics::Row)) summarised into mean and
//!   population std over seeds, and the `metrics.json` layout the recipes write;
//! * [`budget`]: training budgets (`train_steps` × `train_batch`) and the equal-budget check;
//! * [`table`]: markdown tables of those summaries, for one run or several run directories;
//! * [`compare`]: whether two runs' `metrics.json` agree apart from wall-clock timings;
//! * [`plots`]: figures (SVG and optionally PNG): trajectories coloured by the acting expert,
//!   learning curves, and a 2-D density with its score field and experts' ellipses;
//! * [`timing`]: wall-clock seconds per pipeline stage and the process's CPU seconds.
//!
//! The crate knows no teacher, student, trainer or task: it takes numbers, rows and points,
//! and returns strings or writes files. It never prints; the caller decides what to show.
//!
//! ```
//! use serde_json::json;
//! use vdd_report::metrics::{Row, metrics_json};
//! use vdd_report::table::{Column, markdown_table};
//!
//! let row = |seed: u64, sr: f64| -> Row {
//!     json!({"seed": seed, "success_rate": sr}).as_object().unwrap().clone()
//! };
//! let rows = vec![("vdd".to_string(), vec![row(0, 0.9), row(1, 0.7)])];
//! let metrics = metrics_json("my-recipe", "my-task", &[0, 1], &rows);
//! assert_eq!(metrics["methods"]["vdd"]["seeds"], json!(2));
//! let table = markdown_table(&rows, &[Column::new("success_rate", "success rate", 3)]);
//! assert!(table.contains("| vdd | 2 | 0.800 ± 0.100 |"));
//! ```

#![warn(missing_docs)]

pub mod budget;
pub mod compare;
mod error;
pub mod metrics;
pub mod plots;
pub mod table;
pub mod timing;

pub use error::{Error, Result};
