//! # vdd-consistency
//!
//! The consistency-model baselines of the VDD paper, distilled from a variance-exploding
//! (BESO / EDM) diffusion teacher of `vdd-diffusion` and returned as [`vdd_core::Policy`]s:
//!
//! * [`cd`]: **Consistency Distillation** (Song et al., ICML 2023) — a consistency function
//!   with the exact boundary condition at `σ_min`, trained against Heun steps of the teacher's
//!   probability-flow ODE with an EMA target network; one-step and multistep sampling;
//! * [`ctm`]: **Consistency Trajectory Model** distillation (Kim et al., ICLR 2024) — a network
//!   `G(x, t, u)` jumping from any level to any lower one, trained with soft consistency
//!   matching against the teacher ODE plus denoising score matching (no GAN term).
//!
//! What both share:
//!
//! * the teacher seen through its denoiser ([`ConsistencyTeacher`], implemented for
//!   [`vdd_diffusion::Beso`], for a [`vdd_diffusion::DiffusionTeacher`] holding one, for any
//!   variance-exploding score model through [`ScoreTeacher`] — e.g. the exact
//!   [`vdd_diffusion::GmmTeacher`] — and for closures through [`DenoiserFn`]);
//! * the students' network and preconditioning, **reused from `vdd-diffusion`**: the
//!   teachers' [`vdd_diffusion::DenoiserNet`] conditioned on one noise level (CD) or two
//!   (CTM's jump), started from the teacher's weights ([`network_from_teacher`]) and evaluated
//!   with per-row coefficients ([`vdd_diffusion::RowCoefficients`]); CTM uses EDM's
//!   [`vdd_diffusion::Preconditioning`] and CD its boundary-shifted form
//!   ([`BoundaryPreconditioning`]);
//! * the settings ([`ConsistencyConfig`], which is [`CdConfig`]), the trainer
//!   ([`ConsistencyTrainer`], used as [`CdTrainer`] / [`CtmTrainer`]; a [`vdd_core::Trainer`]
//!   reporting a [`ConsistencyStep`] per optimisation step) and the distilled policy
//!   ([`DistilledPolicy`], used as [`ConsistencyModel`] / [`TrajectoryModel`]).
//!
//! The trainers take the raw matrices the teacher was trained on (action chunks flattened) and
//! normalise them with the teacher's normalisers; the policies map raw observations to raw
//! actions. Every random draw comes from `vdd_core::Seeds::new(seed)` of the config.
//!
//! The DDPM-1 and BESO-1 baselines are the teachers' own samplers with one step
//! (`DiffusionTeacher::set_steps(1)` in `vdd-diffusion`); nothing here re-implements them.
//!
//! ```
//! use faer::Mat;
//! use vdd_consistency::{CdConfig, CdTrainer, ScoreTeacher};
//! use vdd_core::{Policy, Trainer};
//! use vdd_diffusion::GmmTeacher;
//!
//! // The exact denoiser of a two-mode mixture as the teacher, 1-D states, 2-D actions.
//! let gmm = GmmTeacher::isotropic(&[1.0, 1.0], &[vec![1.0, 1.0], vec![-1.0, -1.0]], 0.1)?;
//! let teacher = ScoreTeacher::identity(gmm)?;
//! let states = Mat::<f32>::zeros(64, 1);
//! let actions = Mat::from_fn(64, 2, |i, _| if i % 2 == 0 { 1.0 } else { -1.0 });
//! let mut config = CdConfig::for_teacher(&teacher).with_seed(3);
//! config.net.hidden_dim = 16;
//! config.train.steps = 10;
//! config.train.batch_size = 16;
//! let mut trainer = CdTrainer::new(config, teacher, states.as_ref(), actions.as_ref())?;
//! trainer.run(|step| assert!(step.loss.is_finite()))?;
//! let mut policy = trainer.finish()?;
//! assert_eq!(policy.act(&[0.0])?.len(), 2);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```
#![warn(missing_docs)]

pub mod cd;
mod config;
pub mod ctm;
mod error;
mod network;
mod policy;
mod teacher;
mod trainer;

#[cfg(test)]
mod test_support;

pub use cd::{CdConfig, CdTrainer, ConsistencyModel};
pub use config::{ConsistencyConfig, ConsistencyProgress, ConsistencyStep, ConsistencyTrainConfig};
pub use ctm::{CtmConfig, CtmMatching, CtmTrainer, DsmWeighting, TrajectoryModel};
pub use error::ConsistencyError;
pub use network::{BoundaryPreconditioning, network_from_teacher};
pub use policy::{DistilledPolicy, SampleScratch, Sampling, SavedKind};
pub use teacher::{ConsistencyTeacher, DenoiserFn, ScoreTeacher};
pub use trainer::{ConsistencyTrainer, LossMeter};
