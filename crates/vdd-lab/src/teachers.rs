//! Learned diffusion teachers for recipes and benchmarks: the progress bar and log lines around
//! the teacher cache of [`vdd_diffusion::cache`] (keyed by the hash of
//! [`vdd_diffusion::cache::TeacherCacheKey`]); the recipes' cache directory is
//! `results/cache/teachers`, `cargo xtask bench teachers` uses its own, and `--fresh`
//! (`--retrain`) retrains and overwrites.

use std::path::{Path, PathBuf};

use faer::MatRef;
use vdd_diffusion::TeacherKind;
pub use vdd_diffusion::cache::{CachedTeacher as TrainedTeacher, TeachersConfig, kind_name};
use vdd_diffusion::cache::{TeacherCache, TeacherCacheKey};

/// Trains the teacher of `kind` on raw `states` / `actions` with `seed`, or loads it from
/// `cache_dir` when a teacher with the same key exists (and `fresh` is false), with a
/// progress bar and a log line.
#[allow(clippy::too_many_arguments)]
pub fn train_or_load(
    kind: TeacherKind,
    config: &TeachersConfig,
    states: MatRef<'_, f32>,
    actions: MatRef<'_, f32>,
    seed: u64,
    cache_dir: &Path,
    fresh: bool,
    label: &str,
) -> crate::Result<TrainedTeacher> {
    let key = TeacherCacheKey::new(kind, config, states, actions, seed)?;
    let hash = crate::recipe::config_hash(&key)?;
    let steps = match kind {
        TeacherKind::Beso => config.beso.train.steps,
        TeacherKind::Ddpm => config.ddpm.train.steps,
    };
    let bar = crate::progress::bar(steps, label);
    let mut progress = |p: vdd_diffusion::TrainProgress| {
        bar.set_position(p.step);
        bar.set_message(format!("loss {:.4}", p.loss));
    };
    let cache = TeacherCache { dir: cache_dir, fresh };
    let t = cache.train_or_load(kind, config, states, actions, seed, &hash, &mut progress)?;
    bar.finish_and_clear();
    if t.cached {
        crate::progress::log(format!("[{label}] teacher loaded from {}", rel(&t.path)));
    } else {
        let last = t.losses.last().map_or(f32::NAN, |l| l.1);
        crate::progress::log(format!(
            "[{label}] teacher trained in {:.1} s ({steps} steps, final loss {last:.4}); cached as {}",
            t.train_seconds,
            rel(&t.path)
        ));
    }
    Ok(t)
}

/// `path` relative to the current directory when possible.
pub fn rel(path: &Path) -> String {
    let cwd = std::env::current_dir().unwrap_or_default();
    path.strip_prefix(&cwd)
        .map(PathBuf::from)
        .unwrap_or_else(|_| path.to_path_buf())
        .display()
        .to_string()
}
