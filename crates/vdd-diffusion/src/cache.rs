//! The teacher cache: train a [`DiffusionTeacher`] or load it from a directory, keyed by a hash
//! of everything that determines the trained weights.
//!
//! The key ([`TeacherCacheKey`]) is [`TEACHER_CACHE_VERSION`], the teacher kind, its model
//! configuration without the sampling settings (sampler and default steps are applied after
//! loading, so changing them reuses the cached weights), its training configuration, the
//! training seed and a hash of the training data's bits ([`data_hash`]). The caller hashes the
//! key (the recipes use a 16-hex-digit FNV-1a hash of its JSON form) and passes the hash to
//! [`TeacherCache::train_or_load`]. A cached teacher is `<dir>/<kind>-<hash>.safetensors` with a
//! `.json` sidecar (key, training seconds, loss curve). Loading a cached teacher gives
//! bit-identical scores and samples to the freshly trained one (the weights are stored as `f32`).

use std::path::{Path, PathBuf};
use std::time::Instant;

use faer::MatRef;
use serde::{Deserialize, Serialize};

use crate::{
    Beso, BesoConfig, Ddpm, DdpmConfig, DiffusionError, DiffusionTeacher, TeacherKind, TrainConfig,
    TrainProgress,
};

/// The version of the teacher cache's key and files, part of every key: raise it when the
/// training code or the file format changes what a cached teacher would be (every teacher is
/// then retrained once). Version 2 is the format since the sidecar files.
pub const TEACHER_CACHE_VERSION: u32 = 2;

/// Largest sidecar read (its loss curve included; a real one has a few hundred KB).
pub const MAX_SIDECAR_BYTES: u64 = 1 << 30;

/// Errors of the teacher cache.
#[derive(Debug, thiserror::Error)]
pub enum CacheError {
    /// A cache file or directory cannot be read or written.
    #[error("teacher cache: {path}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// A sidecar or the key cannot be (de)serialised as JSON.
    #[error("teacher cache: {path}: {source}")]
    Json {
        /// The file (empty for the key).
        path: PathBuf,
        /// The underlying error.
        source: serde_json::Error,
    },
    /// Training, configuring, saving or loading (safetensors) the teacher failed.
    #[error(transparent)]
    Teacher(#[from] DiffusionError),
}

/// A BESO teacher's model and training configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct BesoTeacherConfig {
    /// The model (network, noise distribution, sampler and default sampling steps).
    pub config: BesoConfig,
    /// Denoising-score-matching training.
    pub train: TrainConfig,
}

/// A DDPM teacher's model and training configuration.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct DdpmTeacherConfig {
    /// The model (network, schedule, sampler and default sampling steps).
    pub config: DdpmConfig,
    /// Denoising-score-matching training.
    pub train: TrainConfig,
}

/// Both learned teachers of a recipe.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct TeachersConfig {
    /// The BESO teacher.
    pub beso: BesoTeacherConfig,
    /// The DDPM teacher.
    pub ddpm: DdpmTeacherConfig,
}

/// A trained (or cache-loaded) teacher.
#[derive(Debug, Clone)]
pub struct CachedTeacher {
    /// The teacher, with the configured sampler and default steps.
    pub teacher: DiffusionTeacher,
    /// Wall-clock training time (from the cache sidecar when loaded).
    pub train_seconds: f64,
    /// Whether it came from the cache.
    pub cached: bool,
    /// `(step, loss)` reports of training.
    pub losses: Vec<(u64, f32)>,
    /// The cache key hash.
    pub hash: String,
    /// The weights file.
    pub path: PathBuf,
}

impl CachedTeacher {
    /// A record of where the teacher of `kind` and `seed` came from (for a run's `run.json`):
    /// `{"teacher", "seed", "hash", "cached", "train_seconds"}`.
    pub fn log_entry(&self, kind: TeacherKind, seed: u64) -> serde_json::Value {
        serde_json::json!({
            "teacher": kind_name(kind),
            "seed": seed,
            "hash": self.hash,
            "cached": self.cached,
            "train_seconds": self.train_seconds,
        })
    }
}

/// What determines a cached teacher's weights; serialise it (fields in declaration order) and
/// hash the JSON to get the cache key hash.
#[derive(Debug, Clone, Serialize)]
pub struct TeacherCacheKey {
    /// [`TEACHER_CACHE_VERSION`].
    pub version: u32,
    /// The teacher kind.
    pub kind: TeacherKind,
    /// The model configuration without its sampling settings (`sampler`, `sampling_steps`).
    pub config: serde_json::Value,
    /// The training configuration.
    pub train: TrainConfig,
    /// The training seed.
    pub seed: u64,
    /// Training rows.
    pub rows: usize,
    /// State dimension.
    pub state_dim: usize,
    /// Action dimension.
    pub action_dim: usize,
    /// [`data_hash`] of the training data.
    pub data: String,
}

impl TeacherCacheKey {
    /// The key of the `kind` teacher of `config` trained on `states` / `actions` with `seed`.
    ///
    /// ```
    /// use faer::Mat;
    /// use vdd_diffusion::cache::{BesoTeacherConfig, DdpmTeacherConfig, TeacherCacheKey, TeachersConfig};
    /// use vdd_diffusion::TeacherKind;
    /// let config = TeachersConfig {
    ///     beso: BesoTeacherConfig { config: Default::default(), train: Default::default() },
    ///     ddpm: DdpmTeacherConfig { config: Default::default(), train: Default::default() },
    /// };
    /// let (s, a) = (Mat::<f32>::zeros(4, 1), Mat::<f32>::zeros(4, 2));
    /// let key = TeacherCacheKey::new(TeacherKind::Beso, &config, s.as_ref(), a.as_ref(), 0).unwrap();
    /// assert_eq!((key.rows, key.state_dim, key.action_dim), (4, 1, 2));
    /// ```
    pub fn new(
        kind: TeacherKind,
        config: &TeachersConfig,
        states: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
        seed: u64,
    ) -> Result<Self, CacheError> {
        let (model, train) = match kind {
            TeacherKind::Beso => (training_part(&config.beso.config)?, &config.beso.train),
            TeacherKind::Ddpm => (training_part(&config.ddpm.config)?, &config.ddpm.train),
        };
        Ok(Self {
            version: TEACHER_CACHE_VERSION,
            kind,
            config: model,
            train: train.clone(),
            seed,
            rows: states.nrows(),
            state_dim: states.ncols(),
            action_dim: actions.ncols(),
            data: data_hash(states, actions),
        })
    }
}

#[derive(Serialize, Deserialize)]
struct Sidecar {
    key: String,
    kind: TeacherKind,
    train_seconds: f64,
    losses: Vec<(u64, f32)>,
}

pub use vdd_core::hash::data_hash;

/// `ddpm` / `beso`: the file-name prefix of a cached teacher.
///
/// ```
/// assert_eq!(vdd_diffusion::cache::kind_name(vdd_diffusion::TeacherKind::Beso), "beso");
/// ```
pub fn kind_name(kind: TeacherKind) -> &'static str {
    match kind {
        TeacherKind::Ddpm => "ddpm",
        TeacherKind::Beso => "beso",
    }
}

/// Where teachers are cached and whether to ignore what is there.
#[derive(Debug, Clone, Copy)]
pub struct TeacherCache<'a> {
    /// The cache directory.
    pub dir: &'a Path,
    /// Retrain and overwrite instead of loading.
    pub fresh: bool,
}

impl TeacherCache<'_> {
    /// The weights and sidecar files of the `kind` teacher with key `hash`.
    ///
    /// ```
    /// use std::path::Path;
    /// use vdd_diffusion::cache::TeacherCache;
    /// let cache = TeacherCache { dir: Path::new("c"), fresh: false };
    /// let (w, _) = cache.paths(vdd_diffusion::TeacherKind::Ddpm, "ab");
    /// assert_eq!(w, Path::new("c/ddpm-ab.safetensors"));
    /// ```
    pub fn paths(&self, kind: TeacherKind, hash: &str) -> (PathBuf, PathBuf) {
        let name = kind_name(kind);
        (
            self.dir.join(format!("{name}-{hash}.safetensors")),
            self.dir.join(format!("{name}-{hash}.json")),
        )
    }

    /// Trains the `kind` teacher of `config` on raw `states` / `actions` with `seed`, or loads
    /// it when a teacher with key `hash` (the caller's hash of [`TeacherCacheKey::new`]) is
    /// cached and the cache is not `fresh`. `progress` sees every training report.
    ///
    /// ```no_run
    /// # use faer::Mat;
    /// # use vdd_diffusion::cache::*;
    /// # use vdd_diffusion::TeacherKind;
    /// # let config: TeachersConfig = unimplemented!();
    /// let (s, a) = (Mat::<f32>::zeros(16, 1), Mat::<f32>::zeros(16, 2));
    /// let cache = TeacherCache { dir: std::path::Path::new("cache"), fresh: false };
    /// let t = cache
    ///     .train_or_load(TeacherKind::Beso, &config, s.as_ref(), a.as_ref(), 0, "0123abcd", &mut |_| {})
    ///     .unwrap();
    /// println!("cached: {}", t.cached);
    /// ```
    #[allow(clippy::too_many_arguments)]
    pub fn train_or_load(
        &self,
        kind: TeacherKind,
        config: &TeachersConfig,
        states: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
        seed: u64,
        hash: &str,
        progress: &mut dyn FnMut(TrainProgress),
    ) -> Result<CachedTeacher, CacheError> {
        let (weights, sidecar) = self.paths(kind, hash);
        if !self.fresh && weights.is_file() && sidecar.is_file() {
            let text = vdd_core::files::read_bounded_string(&sidecar, MAX_SIDECAR_BYTES)
                .map_err(|source| CacheError::Io { path: sidecar.clone(), source })?;
            let side: Sidecar = serde_json::from_str(&text)
                .map_err(|source| CacheError::Json { path: sidecar.clone(), source })?;
            let mut teacher = DiffusionTeacher::load(&weights, seed)?;
            if teacher.kind() == kind && side.key == hash {
                apply_sampling(&mut teacher, config)?;
                return Ok(CachedTeacher {
                    teacher,
                    train_seconds: side.train_seconds,
                    cached: true,
                    losses: side.losses,
                    hash: hash.to_owned(),
                    path: weights,
                });
            }
        }
        let mut losses = Vec::new();
        let mut report = |p: TrainProgress| {
            losses.push((p.step, p.loss));
            progress(p);
        };
        let t0 = Instant::now();
        let mut teacher: DiffusionTeacher = match kind {
            TeacherKind::Beso => {
                let c = &config.beso;
                Beso::train(&c.config, &c.train, states, actions, seed, &mut report)?.into()
            }
            TeacherKind::Ddpm => {
                let c = &config.ddpm;
                Ddpm::train(&c.config, &c.train, states, actions, seed, &mut report)?.into()
            }
        };
        let train_seconds = t0.elapsed().as_secs_f64();
        apply_sampling(&mut teacher, config)?;
        std::fs::create_dir_all(self.dir)
            .map_err(|source| CacheError::Io { path: self.dir.to_path_buf(), source })?;
        teacher.save(&weights)?;
        let side = Sidecar { key: hash.to_owned(), kind, train_seconds, losses: losses.clone() };
        let json = serde_json::to_string(&side)
            .map_err(|source| CacheError::Json { path: sidecar.clone(), source })?;
        vdd_nn::io::write_atomic(&sidecar, json.as_bytes()).map_err(DiffusionError::from)?;
        Ok(CachedTeacher {
            teacher,
            train_seconds,
            cached: false,
            losses,
            hash: hash.to_owned(),
            path: weights,
        })
    }
}

/// `config` as JSON without the keys that only affect sampling.
fn training_part<C: Serialize>(config: &C) -> Result<serde_json::Value, CacheError> {
    let mut v = serde_json::to_value(config)
        .map_err(|source| CacheError::Json { path: PathBuf::new(), source })?;
    if let Some(m) = v.as_object_mut() {
        m.remove("sampler");
        m.remove("sampling_steps");
    }
    Ok(v)
}

/// Sets the teacher's sampler and default steps from `config` (a cached teacher carries the
/// ones it was saved with).
fn apply_sampling(
    teacher: &mut DiffusionTeacher,
    config: &TeachersConfig,
) -> Result<(), DiffusionError> {
    match teacher {
        DiffusionTeacher::Beso(b) => {
            let c = &config.beso.config;
            b.set_sampler(c.sampler, c.sampling_steps)
        }
        DiffusionTeacher::Ddpm(d) => {
            let c = &config.ddpm.config;
            d.set_sampler(c.sampler, c.sampling_steps)
        }
    }
}

#[cfg(test)]
mod tests;
