//! # vdd-core
//!
//! The vocabulary of Variational Diffusion Distillation (Zhou et al., NeurIPS 2024):
//!
//! * [`ScoreModel`]: a teacher policy seen through its score `∇_a log π_σ(a|s)`;
//! * [`Expert`]: a Gaussian expert family (raw network outputs ↔ mean and scale);
//! * [`Policy`]: anything that acts, from demonstrators to the distilled mixture;
//! * [`gmm`]: the exact Gaussian mixture ([`gmm::GmmTeacher`]), a `ScoreModel` known in closed
//!   form at every noise level: the toys' teacher and the reference the learned teachers and
//!   the trainers are tested against;
//! * [`NoiseProcess`]: what a teacher's noise levels mean, stated once (unit, trained range,
//!   valid levels, denoiser form, `σ` conversion), with the VE form [`VeProcess`] and the
//!   interpolated VP grid [`VpGrid`] shared by in-house and imported DDPM teachers;
//! * [`ClampedDenoiser`]: a teacher whose denoised estimate is clamped to a box (a deviation
//!   from the paper, for learned teachers that extrapolate far from their data);
//! * shared helpers: [`files`] (the one bounded reader of regular files), [`Seeds`] (independent ChaCha streams per purpose), the stable hash
//!   [`hash::fnv1a`] (seed purposes, cache keys, config hashes), Gaussian kernels in
//!   [`gaussian`], element-wise [`lanes`] kernels for batched mixtures, independent jobs on a few threads
//!   ([`parallel::parallel_map`]), shape and finiteness checks, and [`CoreError`].
//!
//! Batches are `faer` matrices with one row per sample (`n x dim`), `f32` throughout.
#![warn(missing_docs)]

pub mod curves;
mod denoiser;
mod error;
mod expert;
pub mod files;
pub mod gaussian;
pub mod gmm;
pub mod hash;
pub mod lanes;
pub mod memory;
mod noise;
mod normalize;
pub mod parallel;
mod policy;
mod score;
mod seed;
pub mod trainer;

pub use denoiser::{ClampedDenoiser, data_box};
pub use error::{CoreError, Result, check_finite, check_finite_slice, check_len, check_shape};
pub use expert::{Expert, ScaleActivation, sigmoid, softplus};
pub use noise::{DenoiserForm, NoiseConvention, NoiseProcess, VeProcess, VpGrid};
pub use normalize::{
    Affine, MAX_ABS_NORMALIZER_OFFSET, MAX_NORMALIZER_SCALE, MIN_NORMALIZER_SCALE,
};
pub use policy::{Policy, check_act_args};
pub use score::{NoiseSchedule, ScoreModel, check_score_args};
pub use seed::{Rng, Seeds, fill_standard_normal, standard_normal};
pub use trainer::{Snapshot, Trainer};

/// Re-export of `faer` so downstream crates and users name the same version.
pub use faer;
