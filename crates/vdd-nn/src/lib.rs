//! # vdd-nn
//!
//! Neural-network building blocks on `faer`, with explicit forward and backward passes (no
//! autodiff framework): [`Linear`], activations, [`Mlp`], the pre-activation [`ResidualMlp`]
//! used by VDD and BESO, optimisers and PyTorch-compatible `safetensors` checkpoints.
//!
//! Every network implements [`Module`] (batched `forward`/`backward` on `n x features`
//! matrices, parameter gradients accumulated) and [`Parameters`] (named tensors in PyTorch's
//! layout). Every backward pass is checked against finite differences in the tests.
#![warn(missing_docs)]

mod activation;
mod error;
pub mod gradcheck;
pub mod io;
mod linear;
mod mlp;
mod module;
mod optim;
mod param;
mod schedule;

pub use activation::{erf, Activation, ActivationLayer};
pub use error::NnError;
pub use linear::Linear;
pub use mlp::{Mlp, MlpConfig, ResidualBlock, ResidualMlp, ResidualMlpConfig};
pub use module::Module;
pub use optim::{clip_grad_norm, Adam, AdamConfig};
pub use param::{join_name, Param, Parameters};
pub use schedule::LrSchedule;
