//! The Aligning training data, built the way Avoiding's is ([`crate::avoiding::dataset`]):
//! scripted demonstrations → episodes (a train/validation split) → observation windows and
//! action chunks → standard normalisation, returned as Avoiding's [`Dataset`] (plain matrices
//! with their normalisers). The models see the raw 14-D observation (identity features).
//!
//! ```
//! use vdd_tasks::aligning::dataset::DatasetConfig;
//!
//! let config = DatasetConfig { demonstrations: 2, validation_fraction: 0.0, ..Default::default() };
//! let data = config.build().unwrap();
//! let t = &data.training;
//! assert_eq!((t.states.ncols(), t.actions.ncols()), (14, 3));
//! assert_eq!(data.mode_counts.iter().sum::<usize>(), 2);
//! assert_eq!(data.summary(2)["train_episodes"], 2);
//! ```

use super::AligningMode;
use super::oracle::{Demonstrations, OracleConfig, generate_demonstrations};
pub use crate::demo_data::{Dataset, DatasetError};
use crate::demo_data::{DemoDataConfig, Demonstrator};

/// How demonstrations become training data ([`DemoDataConfig`] with this task's oracle).
pub type DatasetConfig = DemoDataConfig<OracleConfig>;

impl Default for DatasetConfig {
    /// 1000 demonstrations (D3IL's count, 500 per mode there) of seed 0, 10 % held out (D3IL
    /// holds out 50 per mode), window and chunk 1.
    fn default() -> Self {
        Self::with_demonstrations(1000)
    }
}

impl Demonstrator for OracleConfig {
    type Mode = AligningMode;
    fn demonstrations(&self, n: usize, seed: u64) -> crate::Result<Demonstrations> {
        generate_demonstrations(n, seed, self)
    }
}
