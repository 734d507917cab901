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

/// A learned teacher whose score is formed from a denoised estimate clamped to a box: the
/// posterior mean `E[a | x]` of clean actions lies in the data's bounding box, so clamping the
/// teacher's estimate there can only move it closer. Far from the data, where a network trained
/// at small noise levels extrapolates (its score there can point away from the data and make a
/// distilled expert's variance run away), the clamped score points back into the box. Inside
/// the box it is the teacher's score unchanged. (DDPM's samplers clip their `x̂₀` the same way.)
///
/// With the VE convention (BESO) the denoised estimate is `D = a + σ² s`; with the VP
/// convention (DDPM, `a` fed as `x_t`) it is `x̂₀ = (a + (1 − ᾱ) s) / √ᾱ`. The clamped score is
/// `(D_c − a)/σ²`, respectively `(√ᾱ x̂₀_c − a)/(1 − ᾱ)`.
#[derive(Debug, Clone)]
pub struct ClippedTeacher {
    teacher: DiffusionTeacher,
    /// Per-dimension lower and upper bounds of the denoised estimate (normalised units).
    bounds: Option<(Vec<f32>, Vec<f32>)>,
}

impl ClippedTeacher {
    /// Wraps `teacher`; `bounds` `(lo, hi)` per action dimension, `None` for the plain score.
    pub fn new(
        teacher: DiffusionTeacher,
        bounds: Option<(Vec<f32>, Vec<f32>)>,
    ) -> Result<Self, String> {
        if let Some((lo, hi)) = &bounds {
            let d = teacher.action_dim();
            if lo.len() != d
                || hi.len() != d
                || lo.iter().zip(hi).any(|(l, h)| l.partial_cmp(h).is_none_or(|o| o.is_gt()))
            {
                return Err(format!("clip bounds must be {d} ordered pairs"));
            }
        }
        Ok(Self { teacher, bounds })
    }

    /// The bounding box of the rows of `actions` widened by `margin` on each side.
    pub fn data_box(actions: MatRef<'_, f32>, margin: f32) -> (Vec<f32>, Vec<f32>) {
        (0..actions.ncols())
            .map(|j| {
                let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
                for i in 0..actions.nrows() {
                    lo = lo.min(actions[(i, j)]);
                    hi = hi.max(actions[(i, j)]);
                }
                (lo - margin, hi + margin)
            })
            .unzip()
    }

    /// `(k, v)` with `D = (a + v s) / k` for a noise level (see the type's docs).
    fn scale_and_variance(&self, level: f32) -> (f32, f32) {
        match &self.teacher {
            DiffusionTeacher::Beso(_) => (1.0, level * level),
            DiffusionTeacher::Ddpm(d) => {
                let ab = d.schedule().alpha_bar(level);
                (ab.sqrt(), 1.0 - ab)
            }
        }
    }
}

impl vdd_core::ScoreModel for ClippedTeacher {
    fn action_dim(&self) -> usize {
        vdd_core::ScoreModel::action_dim(&self.teacher)
    }
    fn state_dim(&self) -> usize {
        vdd_core::ScoreModel::state_dim(&self.teacher)
    }
    fn noise_convention(&self) -> vdd_core::NoiseConvention {
        self.teacher.noise_convention()
    }
    fn score(
        &mut self,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        noise_levels: &[f32],
        mut out: faer::MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        use faer::reborrow::ReborrowMut;
        self.teacher.score(actions, states, noise_levels, out.rb_mut())?;
        let Some((lo, hi)) = &self.bounds else { return Ok(()) };
        for (i, &level) in noise_levels.iter().enumerate() {
            let (k, v) = self.scale_and_variance(level);
            if !(v > 0.0 && k > 0.0) {
                continue;
            }
            for j in 0..actions.ncols() {
                let a = actions[(i, j)];
                let d = (a + v * out[(i, j)]) / k;
                let dc = d.clamp(lo[j], hi[j]);
                if dc != d {
                    out[(i, j)] = (k * dc - a) / v;
                }
            }
        }
        Ok(())
    }
    fn sample_actions(
        &mut self,
        states: MatRef<'_, f32>,
        rng: &mut dyn rand::RngCore,
        out: faer::MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        self.teacher.sample_actions(states, rng, out)
    }
    fn draw_noise_levels(
        &self,
        schedule: &vdd_core::NoiseSchedule,
        progress: f32,
        rng: &mut dyn rand::RngCore,
        out: &mut [f32],
    ) {
        self.teacher.draw_noise_levels(schedule, progress, rng, out)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::Mat;
    use vdd_core::{Affine, ScoreModel};
    use vdd_diffusion::{Beso, Ddpm, NetConfig};

    fn tiny_net() -> NetConfig {
        NetConfig { hidden_dim: 8, num_blocks: 1, ..Default::default() }
    }

    fn teachers() -> Vec<DiffusionTeacher> {
        let (sn, an) = (Affine::identity(1), Affine::identity(2));
        let b = BesoConfig { net: tiny_net(), ..Default::default() };
        let d = DdpmConfig { net: tiny_net(), ..Default::default() };
        vec![
            Beso::new(&b, sn.clone(), an.clone(), 3).unwrap().into(),
            Ddpm::new(&d, sn, an, 3).unwrap().into(),
        ]
    }

    /// The denoised estimate `D` behind a score (see `ClippedTeacher`).
    fn denoised(t: &ClippedTeacher, a: f32, s: f32, level: f32) -> f32 {
        let (k, v) = t.scale_and_variance(level);
        (a + v * s) / k
    }

    #[test]
    fn clipped_scores_equal_the_teachers_inside_the_box_and_point_back_outside() {
        for teacher in teachers() {
            let level = if teacher.kind() == TeacherKind::Beso { 0.3 } else { 2.0 };
            let actions = faer::mat![[0.1f32, -0.2], [30.0, -40.0], [0.0, 0.0]];
            let states = Mat::<f32>::zeros(3, 1);
            let levels = [level; 3];
            let mut raw = Mat::<f32>::zeros(3, 2);
            let mut plain = ClippedTeacher::new(teacher.clone(), None).unwrap();
            plain.score(actions.as_ref(), states.as_ref(), &levels, raw.as_mut()).unwrap();
            // A box wide enough never clips: the score is the teacher's, bit for bit.
            let wide = (vec![-1e6; 2], vec![1e6; 2]);
            let mut clipped = ClippedTeacher::new(teacher.clone(), Some(wide)).unwrap();
            let mut out = Mat::<f32>::zeros(3, 2);
            clipped.score(actions.as_ref(), states.as_ref(), &levels, out.as_mut()).unwrap();
            assert_eq!(out, raw);
            // A unit box: every denoised estimate lands in it, and far points are pulled back.
            let unit = (vec![-1.0; 2], vec![1.0; 2]);
            let mut clipped = ClippedTeacher::new(teacher, Some(unit)).unwrap();
            clipped.score(actions.as_ref(), states.as_ref(), &levels, out.as_mut()).unwrap();
            for i in 0..3 {
                for j in 0..2 {
                    let d = denoised(&clipped, actions[(i, j)], out[(i, j)], level);
                    assert!((-1.0 - 1e-3..=1.0 + 1e-3).contains(&d), "row {i}: D = {d}");
                    let rd = denoised(&clipped, actions[(i, j)], raw[(i, j)], level);
                    if (-1.0..=1.0).contains(&rd) {
                        assert_eq!(out[(i, j)], raw[(i, j)], "unclipped entries are unchanged");
                    }
                }
            }
            assert!(out[(1, 0)] < 0.0 && out[(1, 1)] > 0.0, "far points are pulled back: {out:?}");
        }
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

    #[test]
    fn clip_boxes_come_from_the_data() {
        let a = faer::mat![[0.0f32, 5.0], [2.0, -1.0], [1.0, 0.0]];
        let (lo, hi) = ClippedTeacher::data_box(a.as_ref(), 0.5);
        assert_eq!((lo, hi), (vec![-0.5, -1.5], vec![2.5, 5.5]));
        let t = teachers().remove(0);
        assert!(ClippedTeacher::new(t.clone(), Some((vec![1.0, 0.0], vec![0.0, 1.0]))).is_err());
        assert!(ClippedTeacher::new(t, Some((vec![0.0], vec![1.0]))).is_err());
    }
}
