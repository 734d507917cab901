//! # vdd-nn
//!
//! Neural-network building blocks on `faer`, with explicit forward and backward passes (no
//! autodiff framework): [`Linear`], activations, [`LayerNorm`], [`Mlp`], the pre-activation
//! [`ResidualMlp`] used by VDD and BESO, noise-level embeddings ([`SinusoidalEmbedding`],
//! [`FourierFeatures`]) and column concatenation, initialisers ([`init`]), Adam/AdamW with
//! LR schedules, parameter [`Ema`], and PyTorch-compatible `safetensors` checkpoints ([`io`]).
//!
//! Every network implements [`Module`] (batched `forward`/`backward` on `n x features`
//! matrices, parameter gradients accumulated) and [`Parameters`] (named tensors in PyTorch's
//! layout). Every backward pass is checked against finite differences in the tests.
#![warn(missing_docs)]

mod activation;
pub mod bench;
pub mod checkpoint;
mod ema;
mod embedding;
mod error;
mod gemm;
pub mod gradcheck;
pub mod init;
pub mod io;
pub mod limits;
mod linear;
mod mlp;
mod module;
mod norm;
mod optim;
pub mod parallel;
mod param;
mod schedule;

pub use activation::{Activation, ActivationLayer, erf, exp_fast};
pub use ema::Ema;
pub use embedding::{
    FourierFeatures, SinusoidalEmbedding, concat_cols, concat_cols_into, split_cols,
};
pub use error::NnError;
pub use gemm::matmul;
pub use linear::Linear;
pub use mlp::{Mlp, MlpConfig, ResidualBlock, ResidualMlp, ResidualMlpConfig};
pub use module::{Module, forward_as};
pub use norm::{LAYER_NORM_EPS, LayerNorm};
pub use optim::{Adam, AdamConfig, NonFiniteGradient, clip_grad_norm, clip_grad_norm_checked};
pub use param::{Param, Parameters, join_name};
pub use schedule::LrSchedule;
