//! # vdd-baselines
//!
//! Baselines: EM and IMC mixtures, consistency distillation, consistency trajectory models.
#![warn(missing_docs)]
