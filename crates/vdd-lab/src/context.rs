//! What a task pipeline gets from `cargo xtask experiment`: the [`RunContext`] (recipe file,
//! overrides, output and cache directories) and the helpers every pipeline uses (stage timing,
//! parallel jobs, run names, `run.json`). A leaf module: it knows no task.
//!
//! A run directory is `--out DIR`, by default `results/<recipe>/<run>/` with `<run>` built from
//! the seeds (`seed0`, `seed0-1-2`), `-quick` under `--quick`, and a short hash of `--methods` /
//! `--set` overrides when there are any ([`run_name`]).

use std::path::{Path, PathBuf};
use std::time::Instant;

use toml::Table;

use crate::recipe::{Overrides, run};

/// Everything a task pipeline needs to run a recipe.
#[derive(Debug, Clone)]
pub struct RunContext {
    /// The recipe's name (file stem).
    pub name: String,
    /// The recipe file's contents.
    pub file: Table,
    /// CLI overrides.
    pub overrides: Overrides,
    /// `--out`.
    pub out: Option<PathBuf>,
    /// `--fresh`: retrain cached teachers and students.
    pub fresh: bool,
    /// `--resume`: load the run directory's finished trainings ([`crate::finished`]) and
    /// continue the VDD trainings under way from their checkpoints.
    pub resume: bool,
    /// The teacher cache directory.
    pub cache_dir: PathBuf,
    /// The VDD student cache directory ([`vdd_moe::cache`]).
    pub student_cache_dir: PathBuf,
    /// The command line, for `run.json`.
    pub command: String,
    /// When the command started.
    pub started: Instant,
    /// The methods and tasks the recipe may name.
    pub registry: crate::Registry,
    /// The project root: where `results/` (default run directories) and `docs/` (tuning
    /// logs) are, and whose git revision `run.json` records.
    pub root: PathBuf,
    /// The run directory this context created, removed again when the run fails
    /// ([`RunContext::remove_created_run_dir`]).
    pub created: std::sync::Arc<std::sync::Mutex<Option<PathBuf>>>,
}

impl RunContext {
    /// The run directory for the resolved seeds.
    pub fn run_dir(&self, seeds: &[u64]) -> PathBuf {
        match &self.out {
            Some(o) => o.clone(),
            None => {
                self.root.join("results").join(&self.name).join(run_name(seeds, &self.overrides))
            }
        }
    }

    /// Writes `resolved.toml` into `dir` (created; a directory this creates is removed again
    /// when the run fails, [`RunContext::remove_created_run_dir`]).
    pub fn write_resolved(&self, dir: &Path, resolved_toml: &str) -> crate::Result {
        check_run_dir(dir, &self.name)?;
        if !dir.exists() {
            *self.created.lock().unwrap_or_else(|e| e.into_inner()) = Some(dir.to_owned());
        }
        std::fs::create_dir_all(dir).map_err(|e| format!("creating {}: {e}", dir.display()))?;
        let header = run::resolved_header(&self.name, &self.command, dir);
        vdd_nn::io::write_atomic(&dir.join("resolved.toml"), (header + resolved_toml).as_bytes())?;
        Ok(())
    }

    /// Removes the run directory [`RunContext::write_resolved`] created, if any: a failed run
    /// leaves nothing behind (another run's directory, or one that existed, stays). A run that
    /// finished trainings before it failed keeps its directory, so that `--resume` goes on from
    /// them ([`crate::finished`]); the message says so.
    pub fn remove_created_run_dir(&self) {
        if let Some(dir) = self.created.lock().unwrap_or_else(|e| e.into_inner()).take() {
            let kept = std::fs::read_dir(crate::finished::dir(&dir)).map_or(0, |d| d.count());
            if kept > 0 {
                crate::progress::print(format!(
                    "{} kept: it holds finished trainings; `--resume` goes on from them",
                    dir.display()
                ));
                return;
            }
            let _ = std::fs::remove_dir_all(dir);
        }
    }

    /// `(git rev-parse HEAD, working tree dirty)` of the project root
    /// ([`vdd_recipe::run::git_revision`]).
    pub fn git_revision(&self) -> (String, Option<bool>) {
        vdd_recipe::run::git_revision(&self.root)
    }

    /// The revision a tuning-log entry records: `git rev-parse HEAD`, with `+dirty` when the
    /// working tree has uncommitted changes.
    pub fn revision_label(&self) -> String {
        match self.git_revision() {
            (revision, Some(true)) => format!("{revision}+dirty"),
            (revision, _) => revision,
        }
    }

    /// Writes `run.json` ([`vdd_recipe::run::run_info`]) into `dir`.
    pub fn write_run_info(&self, dir: &Path, extra: serde_json::Value) -> crate::Result {
        let times = (self.started.elapsed().as_secs_f64(), cpu_seconds());
        let info = run::run_info(&self.name, &self.command, &self.root, times, extra);
        let text = serde_json::to_string_pretty(&info)?;
        vdd_nn::io::write_atomic(&dir.join("run.json"), text.as_bytes())?;
        Ok(())
    }
}

/// Largest `resolved.toml` read when checking a run directory.
const MAX_RESOLVED_BYTES: u64 = 16 << 20;

/// Checks, before anything is written, that `dir` may receive a run of recipe `recipe`: it
/// must not exist yet, be an empty directory, or be a previous run of the same recipe (a
/// directory whose `resolved.toml` starts with [`run::resolved_header`]'s line for `recipe`).
/// Anything else is refused with an error naming it: a path through a symlink (the directory
/// itself or any component of `dir` as given, whatever it points to; each is checked with
/// [`std::fs::symlink_metadata`], so `LINK/run` with `LINK -> /` is refused as `LINK` is), a
/// file, a special file, a non-empty directory that is not a run of this recipe.
///
/// ```
/// let dir = std::env::temp_dir().join(format!("vdd-lab-run-dir-doc-{}", std::process::id()));
/// assert!(vdd_lab::context::check_run_dir(&dir, "toy-gmm").is_ok()); // new
/// std::fs::create_dir_all(&dir)?;
/// assert!(vdd_lab::context::check_run_dir(&dir, "toy-gmm").is_ok()); // empty
/// std::fs::write(dir.join("notes.txt"), "mine")?;
/// let e = vdd_lab::context::check_run_dir(&dir, "toy-gmm").unwrap_err().to_string();
/// assert!(e.contains(&dir.display().to_string()), "{e}");
/// std::fs::remove_dir_all(&dir)?;
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
pub fn check_run_dir(dir: &Path, recipe: &str) -> crate::Result {
    let refuse = |why: &str| -> crate::Result {
        Err(crate::LabError::Msg(format!(
            "refusing to write a run of `{recipe}` into {}: {why}; give --out a new or empty \
             directory or a previous run of this recipe",
            dir.display()
        )))
    };
    let context = |source: std::io::Error| crate::LabError::Context {
        context: format!("checking the run directory {}", dir.display()),
        source: Box::new(source.into()),
    };
    // Every component of the path as given, from its first: none may be a symbolic link, or
    // the run would land wherever the link points (`LINK/run` with LINK -> /).
    let mut prefix = PathBuf::new();
    for component in dir.components() {
        prefix.push(component);
        match std::fs::symlink_metadata(&prefix) {
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
            Err(e) => return Err(context(e)),
            Ok(m) if m.file_type().is_symlink() && prefix.as_path() == dir => {
                return refuse("it is a symbolic link");
            }
            Ok(m) if m.file_type().is_symlink() => {
                let to = std::fs::read_link(&prefix).map(|t| t.display().to_string());
                return refuse(&format!(
                    "{} on its path is a symbolic link (to {}); give the path without links",
                    prefix.display(),
                    to.unwrap_or_else(|e| e.to_string())
                ));
            }
            Ok(_) => {}
        }
    }
    let meta = match std::fs::symlink_metadata(dir) {
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(()),
        Err(e) => return Err(context(e)),
        Ok(m) => m,
    };
    if !meta.is_dir() {
        return refuse("it is not a directory");
    }
    if std::fs::read_dir(dir).map_err(context)?.next().is_none() {
        return Ok(());
    }
    let resolved = dir.join("resolved.toml");
    let not_a_run = "it is not empty and not a previous run of this recipe";
    match std::fs::symlink_metadata(&resolved) {
        Ok(m) if m.is_file() => {}
        _ => return refuse(not_a_run),
    }
    let text =
        vdd_core::files::read_bounded_string(&resolved, MAX_RESOLVED_BYTES).map_err(context)?;
    let header = run::resolved_header(recipe, "", Path::new(""));
    match (text.lines().next(), header.lines().next()) {
        (Some(have), Some(want)) if have == want => Ok(()),
        _ => refuse(not_a_run),
    }
}

/// Stage timing and CPU seconds ([`vdd_report::timing`]), parallel jobs
/// ([`vdd_core::parallel`]) and run names ([`vdd_recipe::run`]).
pub use vdd_core::parallel::parallel_map;
pub use vdd_recipe::run::run_name;
pub use vdd_report::timing::{StageTimes, cpu_seconds};

#[cfg(test)]
mod tests {
    use super::*;

    fn context(dir: &Path) -> RunContext {
        RunContext {
            name: "toy-gmm".into(),
            file: Table::new(),
            overrides: Overrides::default(),
            out: Some(dir.to_owned()),
            fresh: false,
            resume: false,
            cache_dir: dir.join("cache"),
            student_cache_dir: dir.join("students"),
            command: String::new(),
            started: Instant::now(),
            registry: crate::Registry::builtin(),
            root: dir.to_owned(),
            created: Default::default(),
        }
    }

    #[test]
    fn a_failed_run_removes_its_directory_unless_it_finished_trainings() {
        let dir = std::env::temp_dir().join(format!("vdd-lab-failed-run-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let ctx = context(&dir);
        ctx.write_resolved(&dir, "").unwrap();
        ctx.remove_created_run_dir();
        assert!(!dir.exists(), "nothing finished: removed");

        let ctx = context(&dir);
        ctx.write_resolved(&dir, "").unwrap();
        std::fs::create_dir_all(crate::finished::dir(&dir)).unwrap();
        std::fs::write(crate::finished::dir(&dir).join("em-s0.json"), "{}").unwrap();
        ctx.remove_created_run_dir();
        assert!(dir.join("trained").join("em-s0.json").is_file(), "a finished training: kept");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
