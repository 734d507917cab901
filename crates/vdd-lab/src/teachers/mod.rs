//! The teachers of the rows: the [`TeacherSource`] trait (what a row's `teacher` names), the
//! built-in sources, one file each, and their list [`BUILTIN`]; and, for recipes and
//! benchmarks, the learned diffusion teachers' training: the progress bar and log lines around
//! the teacher cache of [`vdd_diffusion::cache`] (keyed by the hash of
//! [`vdd_diffusion::cache::TeacherCacheKey`]); the recipes' cache directory is
//! `results/cache/teachers`, `cargo xtask bench teachers` uses its own, and `--fresh`
//! (`--retrain`) retrains and overwrites.
//!
//! Adding a teacher source: a new file here implementing [`TeacherSource`] and one line in
//! [`BUILTIN`] (or [`crate::Registry::with_teacher`] from outside the crate).

use std::path::{Path, PathBuf};

use faer::MatRef;
use vdd_core::NoiseConvention;
pub use vdd_diffusion::TeacherKind;

use crate::capability::Capability;

mod exact;
mod imported;
mod learned;

pub use exact::EXACT;
pub use imported::{IMPORTED, Imported, LoadedTeacher};
pub use learned::{BESO, BESO_D3IL, DDPM, Learned};

/// Every built-in teacher source.
pub static BUILTIN: &[&dyn TeacherSource] = &[&BESO, &DDPM, &BESO_D3IL, &EXACT, &IMPORTED];

/// Where a row's teacher comes from (a row's `teacher` names it): a learned diffusion teacher
/// trained on the task's demonstrations (and cached), the task's exact mixture, or a file
/// (a teacher imported from PyTorch, [`TeacherSource::load`]).
pub trait TeacherSource: Sync {
    /// The lower-case hyphenated name (`beso`), as in a row's `teacher`.
    fn name(&self) -> &'static str;
    /// The diffusion family it trains, which keys its training in the run and the cache;
    /// `None`: the task's exact mixture ([`Capability::ExactMixture`]), nothing to train.
    fn kind(&self) -> Option<TeacherKind>;
    /// What it needs of a task.
    fn needs(&self) -> &'static [Capability];
    /// The recipe keys it reads beside the shared `teachers` table.
    fn keys(&self) -> &'static [&'static str] {
        &[]
    }
    /// The learned teachers' configuration of rows from this source, given the recipe's
    /// `shared` teachers and its whole `tree`: `shared`, or with this source's own settings in
    /// its family's place. Checked: an error names the key.
    fn teachers(
        &self,
        shared: &TeachersConfig,
        _tree: &toml::Table,
    ) -> crate::Result<TeachersConfig> {
        Ok(shared.clone())
    }
    /// The unit of its noise levels (a VDD schedule's `noise_unit` must match it).
    fn noise_unit(&self) -> NoiseConvention {
        match self.kind() {
            Some(TeacherKind::Ddpm) => NoiseConvention::Time,
            Some(TeacherKind::Beso) | None => NoiseConvention::Sigma,
        }
    }
    /// Whether its teacher is a file named in the recipe ([`TeacherSource::file`]): its rows
    /// run only when asked for by name (`all` leaves them out).
    fn loads_file(&self) -> bool {
        false
    }
    /// The teacher file the resolved recipe `tree` names, for a source that
    /// [`loads_file`](TeacherSource::loads_file) (an error names the key when it is missing);
    /// `None` for sources that train or are the task's.
    fn file(&self, _tree: &toml::Table) -> crate::Result<Option<String>> {
        Ok(None)
    }
    /// Loads the teacher `file` (once per run, when a row of it is planned). An error names
    /// the file.
    fn load(&self, file: &str) -> crate::Result<LoadedTeacher> {
        Err(format!("teacher source `{}` loads no file (asked for {file})", self.name()).into())
    }
}
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
