//! The record `cargo xtask bench import` writes per fixture architecture (shared by every
//! importer's fixtures).

use serde::{Deserialize, Serialize};

/// One fixture architecture's agreement with PyTorch and throughput.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ImportBenchRecord {
    /// The fixture (its directory name under `tests/fixtures/import`).
    pub fixture: String,
    /// The architecture (`lerobot_unet1d`, `diffusion_policy_unet1d`, ...).
    pub architecture: String,
    /// Largest absolute difference of our network's outputs from PyTorch's on the fixture.
    pub max_abs_diff: f32,
    /// Rows (samples) per second of our forward pass at batch [`BENCH_BATCH`], one thread.
    pub rows_per_s: f64,
    /// The same for PyTorch, as the fixture script recorded it (`torch.set_num_threads(1)`).
    pub torch_rows_per_s: f64,
}

/// The batch the throughput is measured at.
pub const BENCH_BATCH: usize = 1024;
