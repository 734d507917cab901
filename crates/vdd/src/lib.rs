//! # vdd
//!
//! **Variational Diffusion Distillation** (Zhou et al., NeurIPS 2024): distils a diffusion
//! policy, seen only through its score ([`vdd_core::ScoreModel`]), into a mixture of Gaussian
//! experts ([`vdd_moe::Moe`]) by minimising an upper bound of the reverse KL that splits into
//! one problem per expert.
//!
//! Where things live:
//! * [`expert_step`]: the expert step — corrected score `g = score + ∇ log q̃` and the
//!   closed-form gradients for means and scales;
//! * [`trainer`]: the EM loop ([`Vdd`]): E-step snapshot, expert step, gating step
//!   (soft cross-entropy to responsibilities), checkpoints and resume;
//! * [`spaces`]: the raw, student's and teacher's spaces, and [`TeacherSpace`];
//! * [`config`]: [`VddConfig`] with the paper's toy defaults;
//! * [`eval`]: Monte-Carlo reverse/forward KL and mode coverage for toy problems.
#![warn(missing_docs)]

pub mod config;
mod error;
pub mod eval;
pub mod expert_step;
pub mod spaces;
pub mod trainer;

#[cfg(test)]
mod test_support;

pub use config::{ExpertWeighting, VddConfig};
pub use error::VddError;
pub use spaces::TeacherSpace;
pub use trainer::{DistillData, IterationMetrics, Vdd};
