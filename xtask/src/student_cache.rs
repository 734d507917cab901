//! Trained VDD students, cached like the teachers ([`crate::teachers`]): keyed by a hash of
//! everything that determines the trained weights ([`STUDENT_CACHE_VERSION`], the teacher's
//! configuration and cache hash, which covers the data, the student's architecture, VDD's
//! configuration with the run seed, and the score clipping), but not the act mode or the
//! evaluation, so that changing how a student acts (`vdd.greedy_gating`, `vdd.sample_action`)
//! or is evaluated re-uses it. The key is built by the VDD method (`methods/vdd.rs`).
//!
//! A cached student is `results/cache/students/<method>-<hash>.safetensors` with a `.json`
//! sidecar (key, training seconds, learning curves); `--fresh` retrains and overwrites.

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};
use vdd_moe::Moe;

use crate::plots::Curves;

/// The version of the student cache's key and files, part of every key (the key's
/// `"version"`): raise it when the training code or the file format changes what a cached
/// student would be (every student is then retrained once).
pub const STUDENT_CACHE_VERSION: u32 = 1;

/// Where students are cached and whether to ignore what is there.
#[derive(Debug, Clone, Copy)]
pub struct StudentCache<'a> {
    /// The cache directory.
    pub dir: &'a Path,
    /// `--fresh`: retrain and overwrite.
    pub fresh: bool,
}

/// A student loaded from the cache or about to be stored in it.
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

impl StudentCache<'_> {
    fn paths(&self, method: &str, hash: &str) -> (PathBuf, PathBuf) {
        let stem = format!("{method}-{hash}");
        (self.dir.join(format!("{stem}.safetensors")), self.dir.join(format!("{stem}.json")))
    }

    /// The student of `method` with key `hash`, if cached (and not `fresh`).
    pub fn load(&self, method: &str, hash: &str) -> crate::XResult<Option<CachedStudent>> {
        let (weights, sidecar) = self.paths(method, hash);
        if self.fresh || !weights.is_file() || !sidecar.is_file() {
            return Ok(None);
        }
        // An unreadable sidecar (say, a curve with a non-finite value) is a miss: retrain.
        let side: Sidecar = match serde_json::from_str(&std::fs::read_to_string(&sidecar)?) {
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
    pub fn store(
        &self,
        method: &str,
        hash: &str,
        trained: &CachedStudent,
    ) -> crate::XResult<PathBuf> {
        let (weights, sidecar) = self.paths(method, hash);
        std::fs::create_dir_all(self.dir)?;
        trained.student.save(&weights)?;
        let side = Sidecar {
            key: hash.to_owned(),
            train_seconds: trained.train_seconds,
            curves: trained.curves.clone(),
        };
        vdd_nn::io::write_atomic(&sidecar, serde_json::to_string(&side)?.as_bytes())?;
        Ok(weights)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use vdd_core::Policy;
    use vdd_moe::{GatingKind, MoeConfig};

    #[test]
    fn a_stored_student_loads_identically_under_its_key_only() {
        let dir = std::env::temp_dir().join(format!("xtask-student-cache-{}", std::process::id()));
        let cache = StudentCache { dir: &dir, fresh: false };
        let config = MoeConfig { gating: GatingKind::Learned, ..MoeConfig::toy(3, 2, 4) };
        let mut student = Moe::from_config(config, 5).unwrap();
        let mut curves = Curves::default();
        curves.insert("gating loss".into(), vec![(0.0, 1.5), (10.0, 0.5)]);
        let stored = CachedStudent { student: student.clone(), train_seconds: 12.5, curves };
        assert!(cache.load("vdd-beso", "abc").unwrap().is_none(), "empty cache");
        cache.store("vdd-beso", "abc", &stored).unwrap();

        let mut loaded = cache.load("vdd-beso", "abc").unwrap().expect("a hit");
        assert_eq!(loaded.train_seconds, 12.5);
        assert_eq!(loaded.curves, stored.curves);
        let obs = [0.3f32, -0.2, 0.9];
        student.seed(1);
        loaded.student.seed(1);
        assert_eq!(student.act(&obs).unwrap(), loaded.student.act(&obs).unwrap());

        assert!(cache.load("vdd-beso", "abd").unwrap().is_none(), "another key");
        assert!(cache.load("vdd-ddpm", "abc").unwrap().is_none(), "another method");
        let fresh = StudentCache { dir: &dir, fresh: true };
        assert!(fresh.load("vdd-beso", "abc").unwrap().is_none(), "--fresh retrains");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
