//! # vdd-moe
//!
//! Mixture of Gaussian experts with a gating network: a fast Policy with exact likelihood.
#![warn(missing_docs)]
