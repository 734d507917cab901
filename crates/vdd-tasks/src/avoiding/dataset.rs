//! The Avoiding training data as the recipes build it: scripted demonstrations → episodes (a
//! train/validation split) → observation features → observation windows and action chunks →
//! standard normalisation, returned as plain matrices with their normalisers.
//!
//! ```
//! use vdd_tasks::avoiding::dataset::DatasetConfig;
//!
//! let config = DatasetConfig { demonstrations: 4, validation_fraction: 0.0, ..Default::default() };
//! let data = config.build().unwrap();
//! let t = &data.training;
//! assert_eq!(t.states.ncols(), 4); // one window of 4 features
//! assert_eq!(t.actions.ncols(), 2); // one chunk of 2 action components
//! assert_eq!(t.states.nrows(), t.states_normalized.nrows());
//! assert_eq!(data.train_episodes, 4);
//! assert_eq!(data.mode_counts.iter().sum::<usize>(), 4);
//! let summary = data.summary(4);
//! assert_eq!(summary["train_samples"], t.states.nrows());
//! assert!(summary["dataset_modes"].as_u64().is_some_and(|m| (1..=4).contains(&m)));
//! ```

use faer::Mat;
use serde::{Deserialize, Serialize};
use vdd_core::Affine;
use vdd_data::{
    DataError, DeploySpec, Episodes, Normalization, NormalizationKind, SequenceDataset,
    TrainingData, WindowConfig,
};

use super::ObsFeatures;
use super::demonstrator::{DemonstratorConfig, generate_demonstrations};
use crate::TaskError;

/// How demonstrations become training data (the `[data]` table of the Avoiding recipes).
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
    /// What the models see of each observation (a registered feature map, saved with the
    /// models in their deployment spec).
    pub features: ObsFeatures,
    /// The scripted demonstrator.
    pub demonstrator: DemonstratorConfig,
}

impl Default for DatasetConfig {
    /// 200 demonstrations of seed 0, 10 % held out, window and chunk 1, `position_and_lag`.
    fn default() -> Self {
        Self {
            demonstrations: 200,
            seed: 0,
            validation_fraction: 0.1,
            obs_window: 1,
            action_chunk: 1,
            execute_steps: 1,
            pad_start: true,
            features: ObsFeatures::PositionAndLag,
            demonstrator: DemonstratorConfig::default(),
        }
    }
}

/// Training matrices of the Avoiding task, one row per window of the training episodes.
#[derive(Debug, Clone)]
pub struct Dataset {
    /// Observation windows (features of `W` steps, concatenated) and action chunks (`C`
    /// steps), raw and under the standard normalisation fitted per step on the training
    /// episodes (repeated over the window or chunk); no exact teacher.
    pub training: TrainingData,
    /// Raw observations (before the features) of each training episode.
    pub episode_observations: Vec<Mat<f32>>,
    /// Training episodes.
    pub train_episodes: usize,
    /// Demonstrations per behaviour mode (all demonstrations, indexed by
    /// [`super::AvoidingMode::index`]).
    pub mode_counts: Vec<usize>,
}

/// Errors of building the dataset.
#[derive(Debug, thiserror::Error)]
pub enum DatasetError {
    /// Generating the demonstrations failed.
    #[error(transparent)]
    Task(#[from] TaskError),
    /// Splitting, windowing or normalising failed.
    #[error(transparent)]
    Data(#[from] DataError),
}

impl DatasetConfig {
    /// How models trained on this data act on raw observations: the features, the window,
    /// the chunk and the executed steps.
    pub fn deploy_spec(&self) -> DeploySpec {
        DeploySpec {
            obs_window: self.obs_window,
            action_chunk: self.action_chunk,
            execute_steps: self.execute_steps,
            ..DeploySpec::identity()
        }
        .with_features(self.features.feature_map())
    }

    /// The training episodes (the demonstrations less the held-out share) with their
    /// observations through [`Self::features`], and their raw observations: what the recipes
    /// train on, and what `cargo xtask demos avoiding --export` writes for models trained
    /// elsewhere.
    ///
    /// ```
    /// use vdd_tasks::avoiding::dataset::DatasetConfig;
    ///
    /// let config = DatasetConfig { demonstrations: 4, validation_fraction: 0.25, ..Default::default() };
    /// let (train, raw) = config.train_episodes().unwrap();
    /// assert_eq!((train.num_episodes(), raw.len()), (3, 3));
    /// let (o, r) = (train.observations(0), &raw[0]);
    /// assert_eq!(o[(5, 0)], r[(5, 2)]); // position_and_lag: (c, d − c)
    /// assert_eq!(o[(5, 2)], r[(5, 0)] - r[(5, 2)]);
    /// ```
    pub fn train_episodes(&self) -> Result<(Episodes, Vec<Mat<f32>>), DatasetError> {
        let demos = generate_demonstrations(self.demonstrations, self.seed, &self.demonstrator)?;
        self.featured_train(demos.observations, demos.actions)
    }

    fn featured_train(
        &self,
        observations: Vec<Mat<f32>>,
        actions: Vec<Mat<f32>>,
    ) -> Result<(Episodes, Vec<Mat<f32>>), DatasetError> {
        let episodes = Episodes::from_episodes(observations, actions)?;
        let train = if self.validation_fraction > 0.0 {
            episodes.split(self.validation_fraction, self.seed)?.train
        } else {
            episodes
        };
        let (episode_observations, episode_actions) = train.to_episode_matrices();
        let features = self.features.feature_map();
        let train = if features.is_identity() {
            train
        } else {
            let obs: Result<Vec<_>, _> =
                episode_observations.iter().map(|o| features.apply_rows(o.as_ref())).collect();
            Episodes::from_episodes(obs?, episode_actions)?
        };
        Ok((train, episode_observations))
    }

    /// Generates the demonstrations and builds the training matrices.
    pub fn build(&self) -> Result<Dataset, DatasetError> {
        let demos = generate_demonstrations(self.demonstrations, self.seed, &self.demonstrator)?;
        let mode_counts = demos.mode_counts();
        // The models train on the features; the raw observations are kept for timing, which
        // feeds them through the deployed policy (that applies the features itself).
        let (train, episode_observations) =
            self.featured_train(demos.observations, demos.actions)?;
        let window =
            WindowConfig::new(self.obs_window, self.action_chunk).with_pad_start(self.pad_start);
        Dataset::from_train(&train, window, episode_observations, mode_counts)
    }
}

impl Dataset {
    /// The training matrices of `train`'s episodes cut into `window`s, raw and under the
    /// standard normalisation fitted per step on `train` (repeated over the window or chunk);
    /// `episode_observations` and `mode_counts` are kept as given. Every task's dataset is
    /// built by it (Avoiding's, Block-Push's).
    pub fn from_train(
        train: &Episodes,
        window: WindowConfig,
        episode_observations: Vec<Mat<f32>>,
        mode_counts: Vec<usize>,
    ) -> Result<Self, DatasetError> {
        let (states, actions) = SequenceDataset::new(train.clone(), window)?.to_matrices();
        let norm = Normalization::fit(train, NormalizationKind::standard())?;
        let (states_normalized, actions_normalized) =
            SequenceDataset::new(train.normalized(&norm)?, window)?.to_matrices();
        let training = TrainingData {
            states,
            actions,
            state_normalizer: tile(&norm.observations, window.obs_window),
            action_normalizer: tile(&norm.actions, window.action_chunk),
            states_normalized,
            actions_normalized,
            exact: None,
        };
        Ok(Dataset {
            training,
            episode_observations,
            train_episodes: train.num_episodes(),
            mode_counts,
        })
    }

    /// What a run records of its data: `demonstrations` (given), `train_episodes`,
    /// `train_samples`, `state_dim`, `action_dim`, `dataset_modes` (modes with a
    /// demonstration) and `dataset_entropy` ([`crate::normalized_entropy`] of the modes).
    pub fn summary(&self, demonstrations: usize) -> serde_json::Value {
        serde_json::json!({
            "demonstrations": demonstrations,
            "train_episodes": self.train_episodes,
            "train_samples": self.training.states.nrows(),
            "state_dim": self.training.states.ncols(),
            "action_dim": self.training.actions.ncols(),
            "dataset_modes": self.mode_counts.iter().filter(|&&c| c > 0).count(),
            "dataset_mode_counts": self.mode_counts,
            "dataset_entropy": crate::normalized_entropy(&self.mode_counts),
        })
    }
}

/// Repeats a per-step normaliser over a window of `k` steps.
fn tile(a: &Affine, k: usize) -> Affine {
    Affine { offset: a.offset.repeat(k), scale: a.scale.repeat(k) }
}
