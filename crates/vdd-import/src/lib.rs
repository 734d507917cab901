//! # vdd-import
//!
//! Diffusion policies trained in PyTorch, imported as [`vdd_core::ScoreModel`]s (to distil)
//! and [`vdd_core::Policy`]s (to roll out with their own samplers):
//! - LeRobot's and diffusion_policy's 1-D conditional U-Net ([`UnetTeacher`], importers
//!   [`import_lerobot`] and [`import_diffusion_policy`]), with diffusers' DDPM/DDIM scheduler
//!   conventions ([`diffusers`]);
//! - BESO/D3IL's GPT and ResNet-MLP score networks with Karras (EDM) preconditioning.
//!
//! The networks themselves (forward only) live in [`vdd_torch`]; this crate reads the
//! packages' files (safetensors, JSON, YAML), checks them, and wires network, noise process and
//! normalisers into one teacher, saved to and loaded from one teacher file ([`load_teacher`]).
//! [`convert`] has one call per package format (package in, teacher file out);
//! [`bench`](mod@bench) checks the fixtures against PyTorch and times them.
#![warn(missing_docs)]

pub mod bench;
pub mod convert;
pub mod diffusers;
mod diffusion_policy;
mod distil_data;
mod error;
mod file;
pub mod fixture;
mod json;
mod lerobot;
pub mod limits;
pub mod normalize;
mod options;
mod teacher;
mod unet_teacher;

pub use diffusion_policy::import_diffusion_policy;
pub use error::ImportError;
pub use file::{KIND_KEY, KIND_UNET1D, SPEC_KEY, load_teacher, save_unet_teacher};
pub use lerobot::{FEATURES_FILE, LerobotOptions, import_lerobot, import_lerobot_with};
pub use options::{ObsMap, Sampler};
pub use teacher::ImportedTeacher;
pub use unet_teacher::{UnetTeacher, UnetTeacherSpec};

mod beso;
mod beso_error;
mod beso_fixture;
mod beso_import;
mod beso_policy;
mod dp_transformer;
pub mod karras;

pub use beso::{BESO_CONFIG_KEY, BesoNetworkConfig, BesoScaler, BesoTeacher, BesoTeacherConfig};
pub use beso_error::BesoError;
pub use beso_fixture::{BESO_FIXTURES, BesoFixtureReport, beso_rows_per_s, check_beso_fixture};
pub use beso_import::{
    BESO_SCALER_FILE, BESO_WEIGHTS_FILE, beso_config_from_yaml, import_beso_run, read_beso_scaler,
};
pub use beso_policy::BesoPolicy;
pub use dp_transformer::{
    DP_TRANSFORMER_FIXTURES, check_dp_transformer_fixture, dp_transformer_config,
    dp_transformer_rows_per_s, load_dp_transformer,
};
pub use karras::SigmaSchedule;
