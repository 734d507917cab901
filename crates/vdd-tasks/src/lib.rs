//! # vdd-tasks
//!
//! Benchmark tasks: toy mixtures and the planar Avoiding task, with scripted demonstrators.
#![warn(missing_docs)]
