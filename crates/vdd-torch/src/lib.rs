//! # vdd-torch
//!
//! PyTorch architectures, forward only, with PyTorch's parameter names: networks matching
//! PyTorch packages' teacher architectures to f32 precision (LeRobot / diffusion_policy 1-D
//! conditional U-Net and transformer, BESO/D3IL GPT and ResNet-MLP), for teachers imported by
//! `vdd-import`. VDD needs their scores only, so they have no backward pass; batch throughput
//! is what matters.
//!
//! Each network implements [`vdd_nn::Parameters`] with the package's `state_dict` names, so a
//! checkpoint's tensors load one to one (`vdd_nn::io::load_safetensors`). This crate knows no
//! files, no importers and no tasks: reading a package's files and wiring a network into a
//! teacher is `vdd-import`'s.
//!
//! ```
//! use vdd_nn::Parameters as _;
//! use vdd_torch::{BlockNorm, MlpActivation, ResMlpScore, ResMlpScoreConfig, SigmaEmbedding};
//!
//! // BESO's ResNet-MLP score network: 3-D observations, 2-D actions.
//! let config = ResMlpScoreConfig {
//!     obs_dim: 3, action_dim: 2, goal_dim: 0, goal_conditional: false, hidden_dim: 16,
//!     num_hidden_layers: 2, output_dim: 2, time_embed_dim: 4,
//!     embedding: SigmaEmbedding::FourierFeatures, activation: MlpActivation::Mish,
//!     norm: BlockNorm::None,
//! };
//! let mut net = ResMlpScore::new(config).unwrap();
//! // Parameters carry PyTorch's names; set every weight the way a checkpoint would.
//! let mut names = Vec::new();
//! net.visit_params_mut("model", &mut |name, p| {
//!     names.push(name.to_owned());
//!     p.value.iter_mut().enumerate().for_each(|(i, v)| *v = 0.01 * (i % 7) as f32);
//! });
//! assert_eq!(names[0], "model.embed.weight"); // BESO's `FourierFeatures` buffer
//! // A batch of two (state, action) rows at noise levels 0.5 and 1.0.
//! let s = faer::Mat::<f32>::from_fn(2, 3, |i, j| (i + j) as f32 * 0.1);
//! let a = faer::Mat::<f32>::zeros(2, 2);
//! let mut out = faer::Mat::<f32>::zeros(2, 2);
//! net.forward(s.as_ref(), a.as_ref(), None, &[0.5, 1.0], out.as_mut()).unwrap();
//! assert!(out.col_iter().flat_map(|c| c.iter().copied()).all(f32::is_finite));
//! ```
#![warn(missing_docs)]

mod cols;
mod dispatch;
mod gpt;
mod ops;
mod resnet_mlp;
mod transformer_dp;

pub use gpt::{DiffusionGpt, DiffusionGptConfig, diffusion_gpt_buffer_suffixes};
pub use resnet_mlp::{BlockNorm, MlpActivation, ResMlpScore, ResMlpScoreConfig, SigmaEmbedding};
pub use transformer_dp::{
    TransformerForDiffusion, TransformerForDiffusionConfig, transformer_for_diffusion_buffer_names,
};

mod conv;
mod flush;
mod norm;
mod unet1d;

pub use conv::{Conv1d, ConvTranspose1d};
pub use flush::{FlushSubnormals, flush_subnormal};
pub use norm::{GROUP_NORM_EPS, GroupNorm, mish, mish_inplace, mish_mat, sinusoidal_embedding};
pub use unet1d::{ConditionalUnet1d, Unet1dConfig, UnetLayout};
