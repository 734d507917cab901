//! The Pushing training data, built the way Avoiding's is ([`crate::avoiding::dataset`]):
//! scripted demonstrations → episodes (a train/validation split) → observation windows and
//! action chunks → standard normalisation, returned as Avoiding's [`Dataset`] (plain matrices
//! with their normalisers). The models see the raw 12-D observation (identity features).
//!
//! ```
//! use vdd_tasks::pushing::dataset::DatasetConfig;
//!
//! let config = DatasetConfig { demonstrations: 2, validation_fraction: 0.0, ..Default::default() };
//! let data = config.build().unwrap();
//! let t = &data.training;
//! assert_eq!((t.states.ncols(), t.actions.ncols()), (12, 2));
//! assert_eq!(data.mode_counts.iter().sum::<usize>(), 2);
//! assert_eq!(data.summary(2)["train_episodes"], 2);
//! ```

use serde::{Deserialize, Serialize};
use vdd_data::{DeploySpec, Episodes, WindowConfig};

use super::oracle::{OracleConfig, generate_demonstrations};
pub use crate::avoiding::dataset::{Dataset, DatasetError};

/// How demonstrations become training data.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DatasetConfig {
    /// Number of successful scripted demonstrations.
    pub demonstrations: usize,
    /// Seed of the demonstrations and of the train/validation split.
    pub seed: u64,
    /// Share of episodes held out (0: train on all); the normalisation is fitted on the rest.
    pub validation_fraction: f64,
    /// Observation window `W` (steps).
    pub obs_window: usize,
    /// Action chunk `C` (steps).
    pub action_chunk: usize,
    /// Actions of each predicted chunk executed before predicting again (`1..=C`).
    pub execute_steps: usize,
    /// Also train on the first `W − 1` steps with the window padded by the first observation.
    pub pad_start: bool,
    /// The scripted demonstrator.
    pub oracle: OracleConfig,
}

impl Default for DatasetConfig {
    /// 2000 demonstrations (D3IL's count, 500 per mode there) of seed 0, 10 % held out (D3IL
    /// holds out 50 per mode), window and chunk 1.
    fn default() -> Self {
        Self {
            demonstrations: 2000,
            seed: 0,
            validation_fraction: 0.1,
            obs_window: 1,
            action_chunk: 1,
            execute_steps: 1,
            pad_start: true,
            oracle: OracleConfig::default(),
        }
    }
}

impl DatasetConfig {
    /// How models trained on this data act on raw observations: the window, the chunk and the
    /// executed steps (identity features).
    pub fn deploy_spec(&self) -> DeploySpec {
        DeploySpec {
            obs_window: self.obs_window,
            action_chunk: self.action_chunk,
            execute_steps: self.execute_steps,
            ..DeploySpec::identity()
        }
    }

    /// The training episodes (the demonstrations less the held-out share), and the modes of
    /// all demonstrations.
    pub fn train_episodes(&self) -> Result<(Episodes, Vec<usize>), DatasetError> {
        let demos = generate_demonstrations(self.demonstrations, self.seed, &self.oracle)?;
        let mode_counts = demos.mode_counts();
        let episodes = Episodes::from_episodes(demos.observations, demos.actions)?;
        let train = if self.validation_fraction > 0.0 {
            episodes.split(self.validation_fraction, self.seed)?.train
        } else {
            episodes
        };
        Ok((train, mode_counts))
    }

    /// Generates the demonstrations and builds the training matrices.
    pub fn build(&self) -> Result<Dataset, DatasetError> {
        let (train, mode_counts) = self.train_episodes()?;
        let (episode_observations, _) = train.to_episode_matrices();
        let window =
            WindowConfig::new(self.obs_window, self.action_chunk).with_pad_start(self.pad_start);
        Dataset::from_train(&train, window, episode_observations, mode_counts)
    }
}
