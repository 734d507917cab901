//! Learned diffusion teachers for recipes and benchmarks: configuration, training with a
//! progress bar, and the one teacher cache ([`train_or_load`]), keyed by a hash of everything
//! that determines the trained weights.
//!
//! The cache key is [`TEACHER_CACHE_VERSION`], the teacher kind, its model configuration without
//! the sampling settings (sampler and default steps are applied after loading, so changing them
//! reuses the cached weights), its training configuration, the training seed and a hash of the
//! training data's bits (so a change in the demonstrator or the windowing gives a new key). A
//! cached teacher is `<cache dir>/<kind>-<hash>.safetensors` with a `.json` sidecar (key,
//! training seconds, loss curve); the recipes' cache directory is `results/cache/teachers`,
//! `cargo xtask bench teachers` uses its own. `--fresh` (`--retrain`) retrains and overwrites.
//! Loading a cached teacher gives bit-identical scores and samples to the freshly trained one
//! (the weights are stored as `f32`).

use std::path::{Path, PathBuf};
use std::time::Instant;

use faer::MatRef;
use serde::{Deserialize, Serialize};
use vdd_diffusion::{
    Beso, BesoConfig, Ddpm, DdpmConfig, DiffusionTeacher, TeacherKind, TrainConfig,
};

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
    /// The BESO teacher (methods `beso`, `beso-1`, `vdd-beso`).
    pub beso: BesoTeacherConfig,
    /// The DDPM teacher (methods `ddpm`, `ddpm-1`, `vdd-ddpm`).
    pub ddpm: DdpmTeacherConfig,
}

/// A trained (or cache-loaded) teacher.
#[derive(Debug, Clone)]
pub struct TrainedTeacher {
    /// The teacher.
    pub teacher: DiffusionTeacher,
    /// Wall-clock training time (from the cache sidecar when loaded).
    pub train_seconds: f64,
    /// Whether it came from the cache.
    pub cached: bool,
    /// `(step, loss)` reports of training.
    pub losses: Vec<(u64, f32)>,
    /// The cache key hash.
    pub hash: String,
}

/// The version of the teacher cache's key and files, part of every key: raise it when the
/// training code or the file format changes what a cached teacher would be (every teacher is
/// then retrained once). Version 2 is the format since the sidecar files.
pub const TEACHER_CACHE_VERSION: u32 = 2;

#[derive(Serialize)]
struct CacheKey<'a> {
    /// [`TEACHER_CACHE_VERSION`].
    version: u32,
    kind: TeacherKind,
    /// The model configuration without its sampling settings (`sampler`, `sampling_steps`):
    /// they do not change the trained weights and are applied after loading.
    config: serde_json::Value,
    train: &'a TrainConfig,
    seed: u64,
    rows: usize,
    state_dim: usize,
    action_dim: usize,
    data: String,
}

#[derive(Serialize, Deserialize)]
struct Sidecar {
    key: String,
    kind: TeacherKind,
    train_seconds: f64,
    losses: Vec<(u64, f32)>,
}

/// A hash of a matrix's shape and bits.
pub fn data_hash(states: MatRef<'_, f32>, actions: MatRef<'_, f32>) -> String {
    let mut bytes =
        Vec::with_capacity(4 * (states.nrows() * (states.ncols() + actions.ncols())) + 32);
    for m in [states, actions] {
        bytes.extend_from_slice(&(m.nrows() as u64).to_le_bytes());
        bytes.extend_from_slice(&(m.ncols() as u64).to_le_bytes());
        for j in 0..m.ncols() {
            for i in 0..m.nrows() {
                bytes.extend_from_slice(&m[(i, j)].to_bits().to_le_bytes());
            }
        }
    }
    format!("{:016x}", crate::recipe::fnv1a(&bytes))
}

/// Trains the teacher of `kind` on raw `states` / `actions` with `seed`, or loads it from
/// `cache_dir` when a teacher with the same key exists (and `fresh` is false).
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
) -> crate::XResult<TrainedTeacher> {
    let data = data_hash(states, actions);
    let (rows, state_dim, action_dim) = (states.nrows(), states.ncols(), actions.ncols());
    let (model, train) = match kind {
        TeacherKind::Beso => (training_part(&config.beso.config)?, &config.beso.train),
        TeacherKind::Ddpm => (training_part(&config.ddpm.config)?, &config.ddpm.train),
    };
    let key = CacheKey {
        version: TEACHER_CACHE_VERSION,
        kind,
        config: model,
        train,
        seed,
        rows,
        state_dim,
        action_dim,
        data,
    };
    let hash = crate::recipe::config_hash(&key)?;
    let train = train.clone();
    let name = kind_name(kind);
    let weights = cache_dir.join(format!("{name}-{hash}.safetensors"));
    let sidecar = cache_dir.join(format!("{name}-{hash}.json"));
    if !fresh && weights.is_file() && sidecar.is_file() {
        let side: Sidecar = serde_json::from_str(&std::fs::read_to_string(&sidecar)?)
            .map_err(|e| format!("reading {}: {e}", sidecar.display()))?;
        let mut teacher = DiffusionTeacher::load(&weights, seed)?;
        if teacher.kind() == kind && side.key == hash {
            apply_sampling(&mut teacher, config)?;
            crate::progress::log(format!("[{label}] teacher loaded from {}", rel(&weights)));
            return Ok(TrainedTeacher {
                teacher,
                train_seconds: side.train_seconds,
                cached: true,
                losses: side.losses,
                hash,
            });
        }
    }
    let bar = crate::progress::bar(train.steps, label);
    let mut losses = Vec::new();
    let mut progress = |p: vdd_diffusion::TrainProgress| {
        bar.set_position(p.step);
        bar.set_message(format!("loss {:.4}", p.loss));
        losses.push((p.step, p.loss));
    };
    let t0 = Instant::now();
    let mut teacher: DiffusionTeacher = match kind {
        TeacherKind::Beso => {
            Beso::train(&config.beso.config, &train, states, actions, seed, &mut progress)?.into()
        }
        TeacherKind::Ddpm => {
            Ddpm::train(&config.ddpm.config, &train, states, actions, seed, &mut progress)?.into()
        }
    };
    let train_seconds = t0.elapsed().as_secs_f64();
    bar.finish_and_clear();
    apply_sampling(&mut teacher, config)?;
    std::fs::create_dir_all(cache_dir)?;
    teacher.save(&weights)?;
    let side = Sidecar { key: hash.clone(), kind, train_seconds, losses: losses.clone() };
    vdd_nn::io::write_atomic(&sidecar, serde_json::to_string(&side)?.as_bytes())?;
    let last = losses.last().map_or(f32::NAN, |l| l.1);
    crate::progress::log(format!(
        "[{label}] teacher trained in {train_seconds:.1} s ({} steps, final loss {last:.4}); cached as {}",
        train.steps,
        rel(&weights)
    ));
    Ok(TrainedTeacher { teacher, train_seconds, cached: false, losses, hash })
}

/// `config` as JSON without the keys that only affect sampling.
fn training_part<C: Serialize>(config: &C) -> crate::XResult<serde_json::Value> {
    let mut v = serde_json::to_value(config)?;
    if let Some(m) = v.as_object_mut() {
        m.remove("sampler");
        m.remove("sampling_steps");
    }
    Ok(v)
}

/// Sets the teacher's sampler and default steps from the recipe (a cached teacher carries the
/// ones it was saved with).
fn apply_sampling(teacher: &mut DiffusionTeacher, config: &TeachersConfig) -> crate::XResult {
    match teacher {
        DiffusionTeacher::Beso(b) => {
            let c = &config.beso.config;
            b.set_sampler(c.sampler, c.sampling_steps)?;
        }
        DiffusionTeacher::Ddpm(d) => {
            let c = &config.ddpm.config;
            d.set_sampler(c.sampler, c.sampling_steps)?;
        }
    }
    Ok(())
}

/// A `run.json` entry for a teacher: kind, seed, cache hash, whether it came from the cache
/// and its training seconds.
pub fn cache_entry(kind: TeacherKind, seed: u64, t: &TrainedTeacher) -> serde_json::Value {
    serde_json::json!({
        "teacher": kind_name(kind),
        "seed": seed,
        "hash": t.hash,
        "cached": t.cached,
        "train_seconds": t.train_seconds,
    })
}

/// `ddpm` / `beso`.
pub fn kind_name(kind: TeacherKind) -> &'static str {
    match kind {
        TeacherKind::Ddpm => "ddpm",
        TeacherKind::Beso => "beso",
    }
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

#[cfg(test)]
mod tests {
    use super::*;
    use faer::Mat;
    use vdd_core::ScoreModel;
    use vdd_diffusion::NetConfig;

    fn tiny_net() -> NetConfig {
        NetConfig { hidden_dim: 8, num_blocks: 1, ..Default::default() }
    }

    #[test]
    fn the_cache_stores_then_loads_the_same_teacher_under_one_key() {
        let dir = std::env::temp_dir().join(format!("xtask-teacher-cache-{}", std::process::id()));
        let train = TrainConfig { steps: 3, batch_size: 8, log_every: 1, ..Default::default() };
        let config = TeachersConfig {
            beso: BesoTeacherConfig {
                config: BesoConfig { net: tiny_net(), ..Default::default() },
                train: train.clone(),
            },
            ddpm: DdpmTeacherConfig {
                config: DdpmConfig { net: tiny_net(), ..Default::default() },
                train,
            },
        };
        let states = Mat::from_fn(16, 1, |i, _| i as f32 / 16.0);
        let actions = Mat::from_fn(16, 2, |i, j| (i * (j + 1)) as f32 / 8.0);
        let go = |fresh| {
            let (s, a) = (states.as_ref(), actions.as_ref());
            train_or_load(TeacherKind::Beso, &config, s, a, 4, &dir, fresh, "t").unwrap()
        };
        let first = go(false);
        let loaded = go(false);
        assert!(!first.cached && loaded.cached);
        assert_eq!(first.hash, loaded.hash);
        assert_eq!(loaded.losses, first.losses);
        let (a, s) = (actions.as_ref(), states.as_ref());
        let levels = vec![0.3f32; 16];
        let mut x = Mat::<f32>::zeros(16, 2);
        let mut y = Mat::<f32>::zeros(16, 2);
        first.teacher.clone().score(a, s, &levels, x.as_mut()).unwrap();
        loaded.teacher.clone().score(a, s, &levels, y.as_mut()).unwrap();
        assert_eq!(x, y, "a cached teacher scores bit-identically");
        assert!(!go(true).cached, "--fresh retrains");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
