//! # vdd-baselines
//!
//! The baselines the VDD paper compares against, trained through the same data plumbing and
//! returned as [`vdd_core::Policy`]s:
//!
//! * [`em`]: **EM** for the same mixture of experts ([`vdd_moe::Moe`]) that VDD distils into —
//!   maximum likelihood of the demonstrations (E-step responsibilities, M-step weighted
//!   Gaussian NLL per expert and cross-entropy for the gating, by gradient steps);
//! * [`imc`]: **IMC**, Information Maximizing Curriculum (Blessing et al., NeurIPS 2023) — per-
//!   expert curricula over the data points with closed-form updates and a joint-entropy term,
//!   experts fitted to their curricula by weighted maximum likelihood, gating fitted to the
//!   curricula's posterior over experts;
//! * [`fit`]: the pieces both share — the weighted Gaussian NLL with closed-form gradients for
//!   diagonal and full (Cholesky) experts, the gating's soft cross-entropy, dataset evaluation,
//!   minibatch sampling and one optimiser step of experts or gating.
//!
//! Data come as plain matrices in a [`Dataset`] (states `n x d_s`, actions `n x d_a`, already
//! normalised). Every random draw comes from `vdd_core::Seeds::new(config.seed)`.
#![warn(missing_docs)]

mod dataset;
pub mod em;
mod error;
pub mod fit;
pub mod imc;

#[cfg(test)]
mod test_support;

pub use dataset::Dataset;
pub use em::{Em, EmConfig, EmMetrics};
pub use error::BaselineError;
pub use imc::{Curricula, GatingData, Imc, ImcConfig, ImcMetrics};
