//! The student cache: trained mixtures stored by the hash of a caller-built key (everything
//! that determines the trained weights), with their training seconds and learning curves.
//!
//! A cached student is `<dir>/<method>-<hash>.safetensors` with a `.json` sidecar (key,
//! training seconds, learning curves). [`STUDENT_CACHE_VERSION`] belongs in every key.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};
use std::sync::{Condvar, Mutex, MutexGuard};

use serde::{Deserialize, Serialize};

use crate::{Moe, MoeError};

/// The version of the student cache's key and files, part of every key (the key's
/// `"version"`): raise it when the training code or the file format changes what a cached
/// student would be (every student is then retrained once). Version 2: acting on one
/// observation rounds differently since the fused row kernel, so a student distilled on the
/// states it visits is another student.
pub const STUDENT_CACHE_VERSION: u32 = 2;

/// Largest sidecar read (its training curves included; a real one has a few hundred KB).
pub const MAX_SIDECAR_BYTES: u64 = 1 << 30;

/// Named learning curves, `(x, y)` points each.
pub type Curves = BTreeMap<String, Vec<(f64, f64)>>;

/// Errors of the student cache.
#[derive(Debug, thiserror::Error)]
pub enum StudentCacheError {
    /// A cache file or directory cannot be read or written.
    #[error("student cache: {path}: {source}")]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The underlying error.
        source: std::io::Error,
    },
    /// A sidecar cannot be serialised as JSON.
    #[error("student cache: {path}: {source}")]
    Json {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        source: serde_json::Error,
    },
    /// Saving or loading the mixture (safetensors) failed.
    #[error(transparent)]
    Moe(#[from] MoeError),
}

/// Where students are cached and whether to ignore what is there.
#[derive(Debug, Clone, Copy)]
pub struct StudentCache<'a> {
    /// The cache directory.
    pub dir: &'a Path,
    /// Retrain and overwrite: [`StudentCache::load`] misses every student that this process
    /// did not store itself, so each is trained once per run.
    pub fresh: bool,
}

/// A student loaded from the cache or about to be stored in it.
#[derive(Debug, Clone)]
pub struct CachedStudent {
    /// The trained mixture (normalisers and act mode are set by the caller).
    pub student: Moe,
    /// Wall-clock training time of the original training.
    pub train_seconds: f64,
    /// Learning curves of the original training.
    pub curves: Curves,
}

#[derive(Serialize, Deserialize)]
struct Sidecar {
    key: String,
    train_seconds: f64,
    curves: Curves,
}

/// The students being trained in this process, by weights path, and the signal that one ended.
static IN_FLIGHT: (Mutex<BTreeSet<PathBuf>>, Condvar) =
    (Mutex::new(BTreeSet::new()), Condvar::new());

/// The students this process stored, by weights path: what a `fresh` cache still loads.
static STORED_HERE: Mutex<BTreeSet<PathBuf>> = Mutex::new(BTreeSet::new());

fn stored_here() -> MutexGuard<'static, BTreeSet<PathBuf>> {
    STORED_HERE.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

fn in_flight() -> MutexGuard<'static, BTreeSet<PathBuf>> {
    // The set stays consistent even if a holder panicked: it only inserts and removes.
    IN_FLIGHT.0.lock().unwrap_or_else(|poisoned| poisoned.into_inner())
}

/// A claim on one student of the cache, held while it is looked up, trained and stored; see
/// [`StudentCache::claim`]. Dropping it lets the next claimant of the same student go on.
#[derive(Debug)]
#[must_use = "the claim ends when it is dropped"]
pub struct Claim {
    weights: PathBuf,
}

impl Drop for Claim {
    fn drop(&mut self) {
        in_flight().remove(&self.weights);
        IN_FLIGHT.1.notify_all();
    }
}

impl StudentCache<'_> {
    /// Claims `method`'s student with key `hash` for this thread, waiting while another
    /// thread of the process holds it. Hold the claim across [`StudentCache::load`], the
    /// training and [`StudentCache::store`]: two jobs of one run that would train the same
    /// student then train it once, and the second loads what the first stored. Claims are
    /// per process; a thread must not claim a second student while it holds one.
    ///
    /// ```
    /// use std::path::Path;
    /// use vdd_moe::cache::StudentCache;
    /// let cache = StudentCache { dir: Path::new("c"), fresh: false };
    /// let claim = cache.claim("vdd-beso", "ab");
    /// drop(claim);
    /// let _again = cache.claim("vdd-beso", "ab"); // free again once dropped
    /// ```
    pub fn claim(&self, method: &str, hash: &str) -> Claim {
        let weights = self.paths(method, hash).0;
        let mut held = in_flight();
        while held.contains(&weights) {
            held = IN_FLIGHT.1.wait(held).unwrap_or_else(|poisoned| poisoned.into_inner());
        }
        held.insert(weights.clone());
        Claim { weights }
    }

    /// The weights and sidecar files of `method`'s student with key `hash`.
    ///
    /// ```
    /// use std::path::Path;
    /// use vdd_moe::cache::StudentCache;
    /// let cache = StudentCache { dir: Path::new("c"), fresh: false };
    /// assert_eq!(cache.paths("vdd-beso", "ab").0, Path::new("c/vdd-beso-ab.safetensors"));
    /// ```
    pub fn paths(&self, method: &str, hash: &str) -> (PathBuf, PathBuf) {
        let stem = format!("{method}-{hash}");
        (self.dir.join(format!("{stem}.safetensors")), self.dir.join(format!("{stem}.json")))
    }

    /// The student of `method` with key `hash`, if cached (under `fresh`, only if this process
    /// stored it). An unreadable sidecar (say, a curve with a non-finite value) is a miss.
    ///
    /// ```
    /// use vdd_moe::cache::StudentCache;
    /// let dir = std::env::temp_dir().join("vdd-moe-doc-empty-cache");
    /// let cache = StudentCache { dir: &dir, fresh: false };
    /// assert!(cache.load("vdd-beso", "0123").unwrap().is_none());
    /// ```
    pub fn load(
        &self,
        method: &str,
        hash: &str,
    ) -> Result<Option<CachedStudent>, StudentCacheError> {
        let (weights, sidecar) = self.paths(method, hash);
        let stale = self.fresh && !stored_here().contains(&weights);
        if stale || !weights.is_file() || !sidecar.is_file() {
            return Ok(None);
        }
        let text = vdd_core::files::read_bounded_string(&sidecar, MAX_SIDECAR_BYTES)
            .map_err(|source| StudentCacheError::Io { path: sidecar.clone(), source })?;
        let side: Sidecar = match serde_json::from_str(&text) {
            Ok(side) => side,
            Err(_) => return Ok(None),
        };
        if side.key != hash {
            return Ok(None);
        }
        let student = Moe::load(&weights)?;
        Ok(Some(CachedStudent { student, train_seconds: side.train_seconds, curves: side.curves }))
    }

    /// Stores a freshly trained student under `hash`; returns the weights' path.
    ///
    /// ```
    /// use vdd_moe::cache::{CachedStudent, StudentCache};
    /// use vdd_moe::{Moe, MoeConfig};
    /// let dir = std::env::temp_dir().join(format!("vdd-moe-doc-cache-{}", std::process::id()));
    /// let cache = StudentCache { dir: &dir, fresh: false };
    /// let student = Moe::from_config(MoeConfig::toy(1, 2, 2), 0).unwrap();
    /// let c = CachedStudent { student, train_seconds: 1.0, curves: Default::default() };
    /// cache.store("vdd-beso", "ab", &c).unwrap();
    /// assert!(cache.load("vdd-beso", "ab").unwrap().is_some());
    /// # std::fs::remove_dir_all(&dir).unwrap();
    /// ```
    pub fn store(
        &self,
        method: &str,
        hash: &str,
        trained: &CachedStudent,
    ) -> Result<PathBuf, StudentCacheError> {
        let (weights, sidecar) = self.paths(method, hash);
        std::fs::create_dir_all(self.dir)
            .map_err(|source| StudentCacheError::Io { path: self.dir.to_path_buf(), source })?;
        trained.student.save(&weights)?;
        let side = Sidecar {
            key: hash.to_owned(),
            train_seconds: trained.train_seconds,
            curves: trained.curves.clone(),
        };
        let json = serde_json::to_string(&side)
            .map_err(|source| StudentCacheError::Json { path: sidecar.clone(), source })?;
        vdd_nn::io::write_atomic(&sidecar, json.as_bytes()).map_err(MoeError::from)?;
        stored_here().insert(weights.clone());
        Ok(weights)
    }
}

#[cfg(test)]
mod tests;
