//! The `[data]` table shared by the tasks whose models see the raw observation (Block-Push,
//! Pushing): scripted demonstrations ([`Demonstrator`]) → episodes (a train/validation split) →
//! observation windows and action chunks → standard normalisation, returned as Avoiding's
//! [`Dataset`] (plain matrices with their normalisers), built the way Avoiding's is
//! ([`crate::avoiding::dataset`]) with identity features.

use serde::{Deserialize, Serialize};
use vdd_data::{DeploySpec, Episodes, WindowConfig};

pub use crate::avoiding::dataset::{Dataset, DatasetError};
use crate::scripted::{Demonstrations, Mode};

/// The settings of a task's scripted demonstrator: they generate its demonstrations.
pub trait Demonstrator {
    /// The task's behaviour modes.
    type Mode: Mode;
    /// `n` successful demonstrations of seed `seed` (deterministic).
    fn demonstrations(&self, n: usize, seed: u64) -> crate::Result<Demonstrations<Self::Mode>>;
}

/// How demonstrations of the demonstrator with settings `O` become training data.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DemoDataConfig<O> {
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
    pub oracle: O,
}

impl<O: Default> DemoDataConfig<O> {
    /// `demonstrations` demonstrations of seed 0, 10 % held out, window and chunk 1, the
    /// demonstrator's defaults.
    pub fn with_demonstrations(demonstrations: usize) -> Self {
        Self {
            demonstrations,
            seed: 0,
            validation_fraction: 0.1,
            obs_window: 1,
            action_chunk: 1,
            execute_steps: 1,
            pad_start: true,
            oracle: O::default(),
        }
    }
}

impl<O: Demonstrator> DemoDataConfig<O> {
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
        let demos = self.oracle.demonstrations(self.demonstrations, self.seed)?;
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
