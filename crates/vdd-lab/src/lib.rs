//! The experiment layer: what turns teacher × method × task into a row of results.
//!
//! * [`method`]: the [`method::Method`] trait (a row of the results table), the [`method::Job`]
//!   it trains from and the [`method::Trained`] policy it returns; [`methods`]: the methods,
//!   one file each, and their registry.
//! * [`task`]: the [`task::Task`] trait (a recipe's `task`); [`tasks`]: the tasks, one file
//!   each; [`driver`]: the stages every task shares: the plan (methods × variants), datasets,
//!   the training phases with the teacher store and the student cache, writing
//!   `metrics.json`.
//! * [`Registry`]: the methods and tasks a run can name, the workspace's
//!   ([`Registry::builtin`]) and a program's own.
//! * [`experiment`]: running a recipe ([`experiment::Request`]), what `cargo xtask
//!   experiment` calls.
//! * [`teachers`], [`policy`], [`plots`], [`tuning`], [`acceptance`]: the learned teachers'
//!   cache, every method's trained policy as one type, the tasks' figures, the tuning protocol
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
pub mod context;
pub mod driver;
mod error;
pub mod experiment;
pub mod method;
pub mod methods;
pub mod plots;
pub mod policy;
pub mod progress;
pub mod recipe;
pub mod registry;
pub mod report;
pub mod sample_fit;
pub mod task;
pub mod tasks;
pub mod teachers;
pub mod tuning;

pub use error::{LabError, Result};
pub use registry::Registry;

impl Registry {
    /// The workspace's methods ([`methods::BUILTIN`], in table order) and tasks
    /// ([`tasks::BUILTIN`]).
    pub fn builtin() -> Self {
        Registry::new(methods::BUILTIN.to_vec(), tasks::BUILTIN.to_vec())
    }
}

impl Default for Registry {
    fn default() -> Self {
        Self::builtin()
    }
}
