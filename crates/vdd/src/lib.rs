//! # vdd
//!
//! **Variational Diffusion Distillation** (Zhou et al., NeurIPS 2024): distils a diffusion
//! policy, seen only through its score ([`ScoreModel`]), into a mixture of Gaussian experts
//! ([`Moe`]) by minimising an upper bound of the reverse KL that splits into one problem per
//! expert.
//!
//! This crate is also the front door: it re-exports the core vocabulary ([`Policy`],
//! [`ScoreModel`], [`Expert`], [`Trainer`], [`Seeds`], [`Affine`], [`NoiseSchedule`], ...), the
//! student ([`Moe`], [`MoeConfig`], ...), the optimiser settings ([`AdamConfig`],
//! [`LrSchedule`]) and the versions of [`faer`] and [`rand`] they use, so a library user adds
//! one dependency. A teacher of your own, distilled into two experts:
//!
//! ```
//! use vdd::faer::{Mat, MatMut, MatRef};
//! use vdd::{CoreError, DistillData, MoeConfig, Policy, ScoreModel, Trainer, Vdd, VddConfig};
//!
//! /// Two modes at ±(1, 1), std 0.3 (state ignored), smoothed by N(0, σ²).
//! struct TwoModes;
//! impl ScoreModel for TwoModes {
//!     fn action_dim(&self) -> usize { 2 }
//!     fn state_dim(&self) -> usize { 1 }
//!     fn score(&mut self, a: MatRef<'_, f32>, s: MatRef<'_, f32>, sigma: &[f32],
//!              mut out: MatMut<'_, f32>) -> Result<(), CoreError> {
//!         vdd::check_score_args(self, a, s, sigma, out.as_ref())?;
//!         for i in 0..a.nrows() {
//!             let var = 0.09 + sigma[i] * sigma[i];
//!             let d2 = |m: f32| (a[(i, 0)] - m).powi(2) + (a[(i, 1)] - m).powi(2);
//!             let w = 1.0 / (1.0 + ((d2(1.0) - d2(-1.0)) / (2.0 * var)).exp()); // weight of +1
//!             for j in 0..2 {
//!                 out[(i, j)] = -(a[(i, j)] - (2.0 * w - 1.0)) / var;
//!             }
//!         }
//!         Ok(())
//!     }
//! }
//!
//! let config = VddConfig { iterations: 300, seed: 7, ..VddConfig::toy() };
//! let data = DistillData::from_states(Mat::zeros(16, 1))?;
//! let mut vdd = Vdd::from_config(config, TwoModes, MoeConfig::toy(1, 2, 2), data)?;
//! vdd.run(|_metrics| {})?;
//! let mut student = vdd.finish()?; // a Policy
//! let a = student.act(&[0.0])?;
//! assert!((a[0].abs() - 1.0).abs() < 0.2 && (a[0] - a[1]).abs() < 0.2, "{a:?}");
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
//!
//! These are the paper's toy settings ([`VddConfig::toy`]), for actions of unit scale near the
//! origin. For any other teacher, [`Vdd::auto`] picks the settings from the teacher itself
//! (normalisers, noise schedule, run length, experts started on its modes; see [`auto`]), and
//! [`Vdd::convergence`] says whether the run converged; the README's first example uses it.
//!
//! Where things live:
//! * [`expert_step`]: the expert step — corrected score `g = score + ∇ log q̃` and the
//!   closed-form gradients for means and scales;
//! * [`trainer`]: the EM loop ([`Vdd`]): E-step snapshot, expert step, gating step
//!   (soft cross-entropy to responsibilities), checkpoints and resume;
//! * [`spaces`]: the raw, student's and teacher's spaces, and [`TeacherSpace`];
//! * [`config`]: [`VddConfig`] with the paper's toy defaults;
//! * [`auto`]: defaults picked from the teacher ([`Vdd::auto`], [`VddConfig::for_teacher`]);
//! * [`eval`]: Monte-Carlo reverse/forward KL and mode coverage for toy problems.
//!
//! `examples/distil_own_teacher.rs` distils a user-defined teacher end to end
//! (`cargo run --release -p vdd --example distil_own_teacher`).
#![warn(missing_docs)]

pub mod auto;
pub mod both_sides;
pub mod config;
mod error;
pub mod eval;
pub mod expert_step;
pub mod spaces;
pub mod trainer;

#[cfg(test)]
mod test_support;

pub use auto::{AutoOptions, AutoPlan, InitKind, SampleSource, init_official};
pub use config::{
    ExpertWeighting, MAX_BATCH_SIZE, MAX_ITERATIONS, MAX_SAMPLES_PER_EXPERT, MAX_SAMPLES_PER_STEP,
    MAX_STEPS_PER_ITER, MAX_VI_SAMPLES, ScoreAt, StateNoise, VddConfig,
};
pub use error::VddError;
pub use spaces::TeacherSpace;
pub use trainer::{
    Convergence, DistillData, IterationMetrics, Resumable, ResumableOutcome, Selected, Vdd,
};

// The front door: everything a user of the trainer names, from one dependency.
/// Exact Gaussian-mixture teachers ([`vdd_core::gmm`]), the robustness family among them.
pub use vdd_core::gmm;
pub use vdd_core::{
    Affine, ClampedDenoiser, CoreError, DenoiserForm, Expert, NoiseConvention, NoiseSchedule,
    Policy, Rng, ScaleActivation, ScoreModel, Seeds, Trainer, check_act_args, check_finite,
    check_len, check_score_args, check_shape, data_box, fill_standard_normal, gaussian,
    standard_normal,
};
pub use vdd_moe::{
    ActMode, DiagonalExpert, ExpertFamily, ExpertKind, FullExpert, GatingKind, Moe, MoeConfig,
    MoeError, MoeOutput, NetworkConfig,
};
pub use vdd_nn::{Activation, AdamConfig, LrSchedule, NnError};
pub use {faer, rand};

/// The README's code blocks, compiled and run as doc tests.
#[cfg(doctest)]
#[doc = include_str!("../../../README.md")]
pub struct ReadmeDoctests;
