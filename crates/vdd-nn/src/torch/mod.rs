//! Forward-only networks matching PyTorch packages' teacher architectures to f32 precision
//! (LeRobot / diffusion_policy 1-D conditional U-Net and transformer, BESO/D3IL GPT and
//! ResNet-MLP), for teachers imported by `vdd-import`. VDD needs their scores only, so they have
//! no backward pass; batch throughput is what matters.

mod cols;
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
mod norm;
mod unet1d;

pub use conv::{Conv1d, ConvTranspose1d};
pub use norm::{GROUP_NORM_EPS, GroupNorm, mish, mish_inplace, mish_mat, sinusoidal_embedding};
pub use unet1d::{ConditionalUnet1d, Unet1dConfig, UnetLayout};
