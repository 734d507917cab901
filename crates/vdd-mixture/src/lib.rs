//! # vdd-mixture
//!
//! The mixture-of-experts baselines of the VDD paper, fitted by maximum likelihood of the
//! demonstrations into the same [`vdd_moe::Moe`] that VDD distils into, and returned as
//! [`vdd_core::Policy`]s with exact likelihoods. Only `vdd-moe`, `vdd-nn` and `vdd-core` are
//! needed: a user who wants EM does not compile the diffusion stack.
//!
//! * [`em`]: **EM** — E-step responsibilities, M-step weighted Gaussian NLL per expert and
//!   soft cross-entropy for the gating, by gradient steps;
//! * [`imc`]: **IMC**, Information Maximizing Curriculum (Blessing et al., NeurIPS 2023) — per-
//!   expert curricula over the data points with closed-form updates and a joint-entropy term,
//!   experts fitted to their curricula by weighted maximum likelihood, gating fitted to the
//!   curricula's posterior over experts;
//! * [`fit`]: the pieces both share — the weighted Gaussian NLL with closed-form gradients for
//!   diagonal and full (Cholesky) experts, dataset evaluation, minibatch sampling and one
//!   optimiser step of experts or gating (and, inside the crate, the iteration loop around them
//!   that both run). The gating step and the checked gradient clipping are the ones VDD uses
//!   ([`vdd_moe::step`]);
//! * [`gating`]: a gating fitted to a teacher policy's samples with the experts frozen (EM with
//!   `expert_steps_per_iter = 0`), for a student whose experts came from elsewhere (VDD).
//!
//! Both trainers implement [`vdd_core::Trainer`] (one report per iteration, the fitted
//! [`vdd_moe::Moe`] as output) and take plain matrices in a [`Dataset`] (states `n x d_s`,
//! actions `n x d_a`, already normalised). Every random draw comes from
//! `vdd_core::Seeds::new(seed)` of the config.
//!
//! ```
//! use faer::Mat;
//! use vdd_core::Trainer;
//! use vdd_mixture::{Dataset, Em, EmConfig};
//! use vdd_moe::{GatingKind, MoeConfig};
//!
//! // Two clusters of 1-D actions at ±2 (the state is constant).
//! let actions = Mat::from_fn(64, 1, |i, _| if i % 2 == 0 { 2.0 } else { -2.0 });
//! let data = Dataset::new(Mat::zeros(64, 1), actions)?;
//! let mut mc = MoeConfig::toy(1, 1, 2);
//! mc.gating = GatingKind::Learned;
//! let config = EmConfig { iterations: 5, ..EmConfig::toy() };
//! // One seed (`config.seed`) initialises the mixture and drives the fit.
//! let mut em = Em::from_config(config, mc, data)?;
//! em.run(|metrics| assert!(metrics.log_likelihood.is_finite()))?;
//! let mut student = em.finish()?; // a vdd_core::Policy
//! # use vdd_core::Policy;
//! assert_eq!(student.act(&[0.0])?.len(), 1);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
#![warn(missing_docs)]

mod dataset;
pub mod em;
mod error;
pub mod fit;
pub mod gating;
pub mod imc;

#[cfg(test)]
mod test_support;

pub use dataset::Dataset;
pub use em::{Em, EmConfig, EmMetrics};
pub use error::MixtureError;
pub use imc::{Curricula, GatingData, Imc, ImcConfig, ImcMetrics, ImcVariant};
