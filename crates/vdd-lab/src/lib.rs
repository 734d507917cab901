//! The experiment layer: what turns teacher × method × task into a row of results.
//!
//! * [`method`]: the [`method::Method`] trait (an algorithm), the [`method::Job`] it trains
//!   from and the [`method::Trained`] policy it returns; [`methods`]: the methods, one file
//!   each. [`teachers`]: the [`teachers::TeacherSource`] trait and the sources, one file each.
//!   [`row`]: the rows of the results tables, a method run from a teacher, named in data
//!   (`recipes/defaults/runs.toml`, a recipe's `[runs.<name>]`).
//! * [`task`]: the [`task::Task`] trait (a recipe's `task`); [`tasks`]: the tasks, one file
//!   each; [`driver`]: the stages every task shares: the plan (methods × variants), datasets,
//!   the training phases with the teacher store and the student cache, writing
//!   `metrics.json`.
//! * [`Registry`]: the methods, teacher sources, rows and tasks a run can name, the
//!   workspace's ([`Registry::builtin`]) and a program's own.
//! * [`experiment`]: running a recipe ([`experiment::Request`]), what `cargo xtask
//!   experiment` calls.
//! * [`teachers`] (again), [`policy`], [`plots`], [`tuning`], [`acceptance`]: the learned
//!   teachers' cache, every method's trained policy as one type, the tasks' figures, the tuning protocol
//!   and log, the acceptance lines.
//! * [`bench`](mod@bench): the benchmarks of `cargo xtask bench` that are experiments (the
//!   robustness benchmark of VDD's defaults, the toy teachers' acceptance checks and sampling
//!   latency).
//!
//! The layer never prints: progress and result lines go to the [`progress`] sink the program
//! installs.
//!
//! ```no_run
//! // What `cargo xtask experiment avoiding --quick` does.
//! let request = vdd_lab::experiment::Request {
//!     recipe: "avoiding".into(),
//!     overrides: vdd_lab::recipe::Overrides { quick: true, ..Default::default() },
//!     command: "example".into(),
//!     ..Default::default()
//! };
//! vdd_lab::experiment::run(&request)?;
//! # Ok::<(), vdd_lab::LabError>(())
//! ```

pub mod acceptance;
pub mod bench;
pub mod capability;
pub mod context;
pub mod driver;
mod error;
pub mod experiment;
pub mod finished;
pub mod method;
pub mod methods;
pub mod plots;
pub mod policy;
pub mod progress;
pub mod recipe;
pub mod registry;
pub mod report;
pub mod row;
pub mod sample_fit;
pub mod task;
pub mod tasks;
pub mod teachers;
pub mod tuning;

pub use error::{LabError, Result};
pub use registry::Registry;

impl Registry {
    /// The workspace's methods ([`methods::BUILTIN`]), teacher sources
    /// ([`teachers::BUILTIN`]), rows ([`row::BUILTIN_ROWS`], in table order) and tasks
    /// ([`tasks::BUILTIN`]).
    pub fn builtin() -> Self {
        let registry = Registry::new(
            methods::BUILTIN.to_vec(),
            teachers::BUILTIN.to_vec(),
            tasks::BUILTIN.to_vec(),
        );
        // The embedded rows are part of the code; `methods::tests` checks that they build.
        row::builtin_runs()
            .and_then(|runs| registry.with_rows(&runs))
            .unwrap_or_else(|e| panic!("recipes/defaults/runs.toml: {e}"))
    }
}

impl Default for Registry {
    fn default() -> Self {
        Self::builtin()
    }
}
