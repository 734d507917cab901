//! # vdd-nn
//!
//! Neural-network building blocks on faer with explicit forward and backward passes.
#![warn(missing_docs)]
