//! # vdd-import
//!
//! Diffusion policies trained in PyTorch, imported as [`vdd_core::ScoreModel`]s (to distil)
//! and [`vdd_core::Policy`]s (to roll out with their own samplers):
//! - LeRobot's and diffusion_policy's 1-D conditional U-Net and diffusion_policy's transformer,
//!   with diffusers' DDPM/DDIM scheduler conventions;
//! - BESO/D3IL's GPT and ResNet-MLP score networks with Karras (EDM) preconditioning.
//!
//! The networks themselves (forward only) live in [`vdd_nn::torch`]; this crate reads the
//! packages' files (safetensors, JSON, YAML), checks them, and wires network, noise process and
//! normalisers into one teacher.
#![warn(missing_docs)]
