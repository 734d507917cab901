//! # vdd-diffusion
//!
//! Diffusion teachers (DDPM, BESO/EDM) and an exact Gaussian-mixture teacher, as
//! [`vdd_core::ScoreModel`]s — what Variational Diffusion Distillation distils — and as
//! [`vdd_core::Policy`]s (the paper's DDPM, DDPM-1, BESO and BESO-1 baselines).
//!
//! * [`Ddpm`]: variance-preserving, `ε`-prediction, cosine or linear `β`, `N` steps
//!   (default 16); DDPM ancestral (variance `β_t` or `β̃_t`) and DDIM samplers with any
//!   `k ≤ N` steps (`k = 1`: DDPM-1).
//!   Score `−ε̂(a, t, s)/sqrt(1 − ᾱ_t)` at continuous `t ∈ (0, N]` (noise convention `t`).
//! * [`Beso`]: variance-exploding with Karras (EDM) preconditioning, log-normal or
//!   log-logistic training `σ`, the Karras `σ` schedule and Euler / Heun / Euler-ancestral /
//!   DDIM samplers with any number of steps (1: BESO-1). Score `(D(a; σ, s) − a)/σ²` (noise
//!   convention `σ`).
//! * [`GmmTeacher`]: an exact Gaussian mixture, state-conditioned or not (defined in
//!   [`vdd_core::gmm`], re-exported here with the other teachers).
//!
//! Both learned teachers are [`LearnedTeacher`]s — one type holds what they share (normalisers,
//! network and EMA weights, training, save / load, the `ScoreModel` and `Policy`
//! implementations) and is parameterised by the diffusion process (`Ddpm =
//! LearnedTeacher<DdpmProcess>`, `Beso = LearnedTeacher<BesoProcess>`). Learned teachers
//! store the data normalisers fitted on their training data: their
//! `ScoreModel` works in the normalised space, their `Policy` maps raw observations to raw
//! actions. Both are trained from plain matrices by seeded minibatch denoising score matching
//! ([`TrainConfig`]), sample with EMA weights, and save to `safetensors` with their config and
//! normalisers as metadata. The samplers ([`sample_karras`], [`sample_vp`], [`heun_step`])
//! take the denoiser as a closure, so distillation baselines can reuse them;
//! [`Beso::denoise`], [`Beso::heun_step`], [`Ddpm::predict_noise`] and [`Ddpm::ddim_step`]
//! expose the trained networks batched in the normalised space.
//!
//! ```
//! use faer::Mat;
//! use vdd_core::{Policy, ScoreModel};
//! use vdd_diffusion::{Beso, BesoConfig, KarrasSampler, NetConfig, TrainConfig};
//!
//! // Demonstrations: a 1-D state and a 2-D action that is ±(1, 1) (two modes).
//! let states = Mat::from_fn(500, 1, |i, _| (i % 10) as f32);
//! let actions = Mat::from_fn(500, 2, |i, _| if i % 2 == 0 { 1.0 } else { -1.0 });
//! let config = BesoConfig { net: NetConfig { hidden_dim: 32, ..Default::default() }, ..Default::default() };
//! let train = TrainConfig { steps: 100, ..Default::default() };
//! let mut teacher =
//!     Beso::train(&config, &train, states.as_ref(), actions.as_ref(), 0, &mut |_| {}).unwrap();
//!
//! // VDD's view: the score in the normalised space at σ = 0.1.
//! let (sn, an) = teacher.normalizers();
//! let mut s = [3.0f32];
//! sn.normalize(&mut s);
//! let mut a = [1.0f32, 1.0];
//! an.normalize(&mut a);
//! let mut score = Mat::zeros(1, 2);
//! teacher
//!     .score(Mat::from_fn(1, 2, |_, j| a[j]).as_ref(), Mat::from_fn(1, 1, |_, _| s[0]).as_ref(), &[0.1], score.as_mut())
//!     .unwrap();
//!
//! // The policy's view: raw observation in, raw action out; BESO-1 is a setting.
//! teacher.set_sampler(KarrasSampler::Euler, 1).unwrap();
//! let action = teacher.act(&[3.0]).unwrap();
//! assert_eq!(action.len(), 2);
//! ```
#![warn(missing_docs)]

mod beso;
pub mod cache;
mod common;
mod ddpm;
mod error;
mod learned;
pub mod metrics;
mod net;
mod normalize;
pub mod sampling;
mod schedule;
mod teacher;
#[cfg(test)]
mod tests;
mod train;

pub use beso::{Beso, BesoConfig, SigmaDistribution};
pub use ddpm::{Ddpm, DdpmConfig, MIN_TIME, TimeSampling};
pub use error::{DiffusionError, Result};
pub use learned::{LearnedTeacher, TeacherTrainer};
pub use net::{DenoiserNet, NetConfig, NoiseEmbedding, RowCoefficients};
pub use normalize::{NormalizerKind, fit_normalizer};
pub use sampling::{KarrasSampler, SamplerBuffers, VpSampler, heun_step, sample_karras, sample_vp};
pub use schedule::{
    BetaSchedule, MAX_DIFFUSION_STEPS, MAX_SAMPLING_STEPS, MAX_SIGMA, MIN_SIGMA, Preconditioning,
    VpSchedule, check_sigma_range, karras_sigmas, karras_sigmas_into,
};
pub use teacher::{DiffusionTeacher, TeacherKind};
pub use train::{TrainConfig, TrainProgress};
pub use vdd_core::gmm::{self, Gmm, GmmTeacher};
