//! # vdd-data
//!
//! Demonstration datasets for behaviour learning and distillation:
//!
//! * [`Episodes`]: `N` episodes of observations and actions with an existence mask, padded to a
//!   common length `T` (`N x T x d_obs`, `N x T x d_act`, `N x T`), built from per-episode
//!   matrices or loaded from `.npz` / `.npy` files in the play-to-policy / BeT layout
//!   ([`io`] describes the format and [`LoadOptions`] the Relay-Kitchen and Block-Push presets);
//!   saved atomically and loaded back bit-identically;
//! * [`Episodes::split`]: a seeded train/validation split by episode;
//! * [`Normalization`]: standard or min-max normalisation fitted on the training split, giving
//!   a [`vdd_core::Affine`] for observations and one for actions, serialisable with serde;
//! * [`SequenceDataset`]: observation windows and action chunks as BESO / D3IL use them (the
//!   convention is documented in [`window`]);
//! * [`features`]: named, versioned observation feature maps (`identity`, `position_and_lag`),
//!   looked up by name and version;
//! * [`DeploySpec`] and [`Windowed`]: how a policy trained on featured windows and chunks acts
//!   on raw observations, one action per step (the spec is saved with models);
//! * [`Batcher`]: a seeded, shuffling minibatch iterator over any [`BatchSource`] that fills
//!   two reusable buffers instead of allocating per batch; [`MatrixDataset`] adapts plain
//!   `(state, action)` matrices.
//!
//! Every bad input (wrong shape or dtype, NaN or Inf, empty data, mismatched lengths, a window
//! longer than every episode, a missing array) is a [`DataError`], and no constructor leaves a
//! partial value behind.
//!
//! ```
//! use faer::Mat;
//! use vdd_data::{Batcher, Episodes, Normalization, NormalizationKind, SequenceDataset, WindowConfig};
//!
//! // Ten ragged episodes of a 2-D observation and a 1-D action.
//! let observations: Vec<Mat<f32>> =
//!     (0..10).map(|i| Mat::from_fn(8 + i, 2, |t, j| (i + t * (j + 1)) as f32)).collect();
//! let actions: Vec<Mat<f32>> =
//!     (0..10).map(|i| Mat::from_fn(8 + i, 1, |t, _| (t as f32).sin())).collect();
//! let episodes = Episodes::from_episodes(observations, actions)?;
//!
//! // Split by episode, fit the normalisation on the training half only.
//! let split = episodes.split(0.2, 0)?;
//! let norm = Normalization::fit(&split.train, NormalizationKind::standard())?;
//! let train = SequenceDataset::new(split.train.normalized(&norm)?, WindowConfig::new(2, 4))?;
//! let validation =
//!     SequenceDataset::new(split.validation.normalized(&norm)?, WindowConfig::new(2, 4))?;
//! assert_eq!((train.state_dim(), train.action_dim()), (4, 4));
//!
//! // Seeded minibatches; the views are reused buffers.
//! let mut batches = Batcher::new(&train, 16, 0)?;
//! for _ in 0..3 * batches.batches_per_epoch() {
//!     let (states, chunks) = batches.next_batch();
//!     assert_eq!(states.nrows(), chunks.nrows());
//! }
//! let (val_states, val_chunks) = validation.to_matrices();
//! assert_eq!(val_states.nrows(), validation.len());
//! # let _ = val_chunks;
//! // `norm.observations` / `norm.actions` are `vdd_core::Affine`s to store with the model.
//! # Ok::<(), vdd_data::DataError>(())
//! ```
#![warn(missing_docs)]

mod batch;
mod episodes;
mod error;
pub mod features;
pub mod io;
mod normalize;
mod npy;
mod training;
pub mod window;

pub use batch::{BatchSource, Batcher, MatrixDataset};
pub use episodes::{Episodes, TrainValSplit};
pub use error::{DataError, Result};
pub use io::{Layout, LoadOptions};
pub use normalize::{Normalization, NormalizationKind};
pub use training::TrainingData;
pub use window::{DeploySpec, SamplePosition, SequenceDataset, WindowConfig, Windowed};
