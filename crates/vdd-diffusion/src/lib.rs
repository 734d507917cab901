//! # vdd-diffusion
//!
//! Diffusion teachers (DDPM, BESO/EDM) and an exact Gaussian-mixture teacher, as ScoreModels.
#![warn(missing_docs)]

pub mod gmm;
pub use gmm::{Gmm, GmmTeacher};
