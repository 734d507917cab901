//! # vdd-moe
//!
//! A mixture of Gaussian experts with a gating distribution,
//! `q(a|s) = Σ_z q(z|s) N(a; μ_z(s), Σ_z(s))`: the student that VDD distils a diffusion
//! policy into. It acts with one network evaluation ([`Moe`] implements
//! [`vdd_core::Policy`]), has an exact log-likelihood, and exposes the per-state means,
//! scales, gating and responsibilities that trainers need.
//!
//! Expert families: [`DiagonalExpert`], [`FullExpert`] (full Cholesky), or [`ExpertFamily`] to
//! choose either by one config value ([`ExpertKind`]); any [`vdd_core::Expert`] works.
//!
//! Deployment: [`Moe::save`] writes one `safetensors` file with the weights, the normalisers,
//! the act mode and the deployment spec ([`vdd_data::DeploySpec`]: observation feature map,
//! window, chunk, executed steps); [`load_policy`] loads it as a [`DeployedPolicy`] that acts on
//! raw environment observations.
//!
//! [`step`] holds the optimiser steps every trainer of a mixture shares (the gating step, the
//! checked gradient clipping).
#![warn(missing_docs)]

pub mod cache;
mod error;
mod experts;
mod moe;
pub mod step;

pub use error::MoeError;
pub use experts::{DiagonalExpert, ExpertFamily, ExpertKind, FullExpert};
pub use moe::{
    ActMode, Components, DeployedPolicy, ExpertNetworks, GatingKind, MAX_ACTION_DIM, MAX_EXPERTS,
    MAX_SCALE_ENTRIES, MAX_STD, Moe, MoeConfig, MoeOutput, NetworkConfig, deployed_components,
    deployed_log_likelihood, load_policy, mixture_observations,
};
