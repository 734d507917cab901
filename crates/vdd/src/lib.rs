//! # vdd
//!
//! Variational Diffusion Distillation trainer: distils any ScoreModel into a mixture of experts.
#![warn(missing_docs)]
