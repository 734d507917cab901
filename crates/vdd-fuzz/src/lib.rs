//! The engine of the workspace's mutation fuzzer (`cargo xtask fuzz`) and its runner
//! ([`runner`]: each case in a child process with memory and time limits).
//!
//! A [`Target`] is one family of files a loader reads (`npy`, `npz`, `safetensors`, `moe`,
//! `teacher`, `checkpoint`, `recipe`, and the importers `lerobot`, `diffusion-policy`, `beso`),
//! or the checkpoint lock (`lock`: two processes opening one directory at the same instant). For each the crate writes valid seed inputs
//! ([`write_seeds`]), derives a mutated case from them with a stream of the campaign's seed
//! indexed by the case number ([`prepare_case`]: bit flips, interesting bytes and floats,
//! truncation, extension, header and JSON/TOML field edits with huge, negative, non-finite and
//! `1e39` values, shape and dtype edits; YAML values, alias bombs and JSON/YAML nested 100,000
//! deep; a checkpoint's `LATEST` and `LOCK`; an input replaced by a FIFO or a symlink to
//! `/dev/zero` or a directory), and runs a case: load the input, use it (act, score, forward, a
//! training step) and check every output is finite ([`run_case`]). The child's exit code gives
//! the case's [`Outcome`] (a file a writer committed that its loader refuses is
//! [`Outcome::Unreadable`]; a lock race with two holders, [`Outcome::LockHolders`]);
//! [`Report`] holds the counts and writes `fuzz.json`.
//! The crate never prints.
//!
//! ```
//! use vdd_fuzz::{Loaded, Outcome, Target};
//! # fn main() -> Result<(), vdd_fuzz::Error> {
//! let dir = std::env::temp_dir().join(format!("vdd-fuzz-doc-{}", std::process::id()));
//! let seeds = vdd_fuzz::write_seeds(Target::Npy, &dir.join("seeds"))?;
//! // The unmutated seed loads, and every output is finite.
//! let ok = vdd_fuzz::run_case(Target::Npy, &seeds[0], |_| Ok(()))?;
//! assert!(matches!(ok, Loaded::Finite));
//! // Case 7 of the campaign with seed 1: the same files on every run.
//! let case = dir.join("case");
//! vdd_fuzz::prepare_case(Target::Npy, &seeds, 1, 7, &case)?;
//! let outcome = match vdd_fuzz::run_case(Target::Npy, &case, |_| Ok(())) {
//!     Ok(loaded) => Outcome::from_exit_code(Some(loaded.exit_code())),
//!     Err(_) => Outcome::Err,
//! };
//! assert!(!outcome.is_failure());
//! # std::fs::remove_dir_all(&dir).ok();
//! # Ok(())
//! # }
//! ```
#![warn(missing_docs)]

mod mutate;
mod report;
pub mod runner;
mod targets;

use std::path::{Path, PathBuf};

pub use report::{Counts, Outcome, Report, TargetReport};
pub use targets::Loaded;

/// What a target's case code returns before it is attributed to a target.
pub type BoxError = Box<dyn std::error::Error>;

/// Errors of the fuzzer's engine.
#[derive(Debug, thiserror::Error)]
pub enum Error {
    /// A target name that is none of [`Target::ALL`].
    #[error(
        "unknown fuzz target `{0}` (npy, npz, safetensors, moe, teacher, checkpoint, recipe, \
         lerobot, diffusion-policy, beso, lock)"
    )]
    UnknownTarget(String),
    /// Writing seeds, mutating or running a case of `target` failed (for a case: the loader
    /// refused the input, the expected outcome of most mutations).
    #[error("fuzz target {target}")]
    Target {
        /// The target.
        target: Target,
        /// What failed.
        #[source]
        source: BoxError,
    },
    /// The runner could not write a case, start, wait for or keep a child.
    #[error("fuzz runner: {}: {source}", .path.display())]
    Io {
        /// The file, directory or program.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// Settings the runner cannot use.
    #[error("invalid fuzz settings: {0}")]
    Settings(&'static str),
}

/// A family of files the fuzzer mutates, and the loader that reads them.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Target {
    /// An episode directory of `.npy` files (`Episodes::load_npy_dir`).
    Npy,
    /// An episode `.npz` archive (`Episodes::load_npz`).
    Npz,
    /// A residual MLP in a `safetensors` file with its config in the metadata.
    Safetensors,
    /// A mixture-of-experts policy file (`Moe::load`, `load_policy`).
    Moe,
    /// A diffusion teacher file (`DiffusionTeacher::load`).
    Teacher,
    /// A VDD trainer checkpoint: a flat directory (`Vdd::resume`, then a step), or a directory
    /// of generations with its `LATEST` and `LOCK` edited (taken, resumed, stepped, committed,
    /// and the commit resumed again).
    Checkpoint,
    /// A toy-gmm recipe (`recipe.toml`); its check is the caller's (see [`run_case`]).
    Recipe,
    /// A LeRobot diffusion policy directory (`vdd_import::import_lerobot`), then the round
    /// trip of the importer's output: `save_unet_teacher`, `load_teacher`, a score.
    Lerobot,
    /// A converted diffusion_policy checkpoint directory (`config.json`, `model.safetensors`;
    /// `vdd_import::import_diffusion_policy`), then the round trip of the importer's output as
    /// for [`Target::Lerobot`].
    DiffusionPolicy,
    /// A BESO/D3IL run directory (hydra `config.yaml`, the converted state dict, and
    /// `scaler.json` in some seeds; `vdd_import::import_beso_run`), then the round trip:
    /// `BesoTeacher::save`, `BesoTeacher::load`, a score and a sample.
    Beso,
    /// The checkpoint lock: two processes opening one checkpoint directory at the same instant
    /// (`vdd_nn::checkpoint::race_open`), on a fresh directory, over a stale or edited `LOCK`,
    /// or while a third writer holds it. Two holders, a live writer's lock taken, or no holder
    /// of a free lock is [`Outcome::LockHolders`].
    Lock,
}

impl Target {
    /// Every target, in the order `all` runs them.
    pub const ALL: [Target; 11] = [
        Target::Npy,
        Target::Npz,
        Target::Safetensors,
        Target::Moe,
        Target::Teacher,
        Target::Checkpoint,
        Target::Recipe,
        Target::Lerobot,
        Target::DiffusionPolicy,
        Target::Beso,
        Target::Lock,
    ];

    /// The target's name on the command line and in `fuzz.json`.
    pub fn name(self) -> &'static str {
        match self {
            Target::Npy => "npy",
            Target::Npz => "npz",
            Target::Safetensors => "safetensors",
            Target::Moe => "moe",
            Target::Teacher => "teacher",
            Target::Checkpoint => "checkpoint",
            Target::Recipe => "recipe",
            Target::Lerobot => "lerobot",
            Target::DiffusionPolicy => "diffusion-policy",
            Target::Beso => "beso",
            Target::Lock => "lock",
        }
    }
}

impl std::fmt::Display for Target {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.pad(self.name())
    }
}

impl std::str::FromStr for Target {
    type Err = Error;
    fn from_str(s: &str) -> Result<Self, Error> {
        Target::ALL
            .into_iter()
            .find(|t| t.name() == s)
            .ok_or_else(|| Error::UnknownTarget(s.into()))
    }
}

fn at<T>(target: Target, r: Result<T, BoxError>) -> Result<T, Error> {
    r.map_err(|source| Error::Target { target, source })
}

/// Writes the valid seed inputs of `target` under `dir`, one directory each, and returns them.
pub fn write_seeds(target: Target, dir: &Path) -> Result<Vec<PathBuf>, Error> {
    at(target, targets::write_seeds(target, dir))
}

/// Writes case `case` of a campaign with seed `seed` into `dir`: a copy of one of `seeds` (as
/// returned by [`write_seeds`]) with one file mutated. The same arguments give the same files.
pub fn prepare_case(
    target: Target,
    seeds: &[PathBuf],
    seed: u64,
    case: usize,
    dir: &Path,
) -> Result<(), Error> {
    at(target, targets::prepare_case(target, seeds, seed, case, dir))
}

/// Runs one case: loads the input in `dir`, uses it and checks the outputs. A refused input
/// is an `Err`. For [`Target::Recipe`], `check_recipe` is called with the recipe file: a
/// recipe's meaning is the tool's that runs it, not the loaders'.
pub fn run_case(
    target: Target,
    dir: &Path,
    check_recipe: impl FnOnce(&Path) -> Result<(), BoxError>,
) -> Result<Loaded, Error> {
    at(target, targets::run_case(target, dir, check_recipe))
}

/// Copies the regular files and directories of `from` into `to`, creating it (symlinks,
/// FIFOs and other special files are left out).
pub fn copy_case(from: &Path, to: &Path) -> std::io::Result<()> {
    std::fs::create_dir_all(to)?;
    for e in std::fs::read_dir(from)? {
        let e = e?;
        let kind = e.file_type()?;
        if kind.is_file() {
            std::fs::copy(e.path(), to.join(e.file_name()))?;
        } else if kind.is_dir() {
            copy_case(&e.path(), &to.join(e.file_name()))?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests;
