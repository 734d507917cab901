//! Tuning runs, kept apart from the reported ones, and the committed tuning log.
//!
//! Settings are chosen on the tuning seeds [`TUNING_SEEDS`] (100–104) with their own
//! demonstrations (`data.seed` = [`TUNING_DATA_SEED`]); the results are reported on other seeds
//! (0–4) with the reporting demonstrations (`data.seed` = 0). A run is a tuning run when its
//! seeds are tuning seeds; it may not mix them with other seeds, must use the tuning data and
//! goes to `results/tuning/<recipe>/<run>/` (outside the runs `cargo xtask table` collects); a
//! run on other seeds may not use the tuning data. `cargo xtask experiment <recipe> --tuning`
//! sets both (seeds 100–104 unless `--seeds` names others).
//!
//! The seeds share no random stream with the reporting seeds: every stream is keyed by its
//! root seed and purpose (`vdd_core::Seeds`), the rollouts' root is derived from the run seed,
//! the demonstrations' from `data.seed`, and the training of every method from the run seed
//! (a test checks the roots and the streams' first draws).
//!
//! Every tuning run appends one entry per method to the task's log, `docs/<task>-tuning-log.toml`
//! (committed): the method, a hash of its configuration (what it trains on and with: data,
//! teachers, student and the method's own keys), the command, the revision, the seeds and the
//! per-seed figures. `tuning_configs` in a reported run's `metrics.json` is the number of
//! distinct configurations of the method in that log.

use std::collections::BTreeSet;
use std::ops::RangeInclusive;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::method::{Method, MethodRecipe};

/// The tuning seeds.
pub const TUNING_SEEDS: RangeInclusive<u64> = 100..=104;

/// The `data.seed` of tuning runs (reported runs use 0).
pub const TUNING_DATA_SEED: u64 = 100;

/// The largest tuning log read (bytes).
const MAX_LOG_BYTES: u64 = 16 << 20;

/// Whether a run on `seeds` with demonstrations of `data_seed` is a tuning run; an error when
/// it mixes tuning and other seeds or uses the other protocol's data.
pub fn is_tuning_run(seeds: &[u64], data_seed: u64) -> Result<bool, String> {
    let tuning = seeds.iter().filter(|s| TUNING_SEEDS.contains(s)).count();
    if tuning > 0 && tuning < seeds.len() {
        return Err(format!(
            "seeds {seeds:?} mix tuning seeds ({}–{}) with reporting seeds",
            TUNING_SEEDS.start(),
            TUNING_SEEDS.end()
        ));
    }
    let is_tuning = tuning > 0;
    if is_tuning && data_seed != TUNING_DATA_SEED {
        return Err(format!(
            "tuning seeds need the tuning demonstrations (data.seed = {TUNING_DATA_SEED}, got \
             {data_seed}); pass --tuning"
        ));
    }
    if !is_tuning && data_seed == TUNING_DATA_SEED {
        return Err(format!(
            "data.seed = {TUNING_DATA_SEED} is the tuning data; use it with the tuning seeds \
             {}–{} only (--tuning)",
            TUNING_SEEDS.start(),
            TUNING_SEEDS.end()
        ));
    }
    Ok(is_tuning)
}

/// The tuning log of `task`: `docs/<task>-tuning-log.toml`.
pub fn log_path(task: &str) -> PathBuf {
    crate::recipe::repo_root().join("docs").join(format!("{task}-tuning-log.toml"))
}

/// One method of one tuning run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct LogEntry {
    /// The method's label (`vdd-beso`, `vdd-beso-z4`).
    pub method: String,
    /// [`method_config_hash`] of the method's configuration.
    pub config: String,
    /// The recipe.
    pub recipe: String,
    /// The command line.
    pub command: String,
    /// `git rev-parse HEAD` (`+dirty` with uncommitted changes).
    pub revision: String,
    /// The tuning seeds.
    pub seeds: Vec<u64>,
    /// Success rate per seed.
    pub success_rate: Vec<f64>,
    /// Task entropy per seed.
    pub task_entropy: Vec<f64>,
    /// Optimiser steps of the method's own training.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub train_steps: Option<u64>,
    /// Rows per step.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub train_batch: Option<u64>,
    /// Training seconds per seed (wall clock, concurrent trainings).
    pub train_seconds: Vec<f64>,
    /// The run directory, relative to the repository.
    pub run: String,
}

#[derive(Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Log {
    #[serde(default)]
    entry: Vec<LogEntry>,
}

/// The entries of the log at `path` (none when the file does not exist).
pub fn read_log(path: &Path) -> crate::XResult<Vec<LogEntry>> {
    let len = match std::fs::metadata(path) {
        Ok(m) => m.len(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(format!("{}: {e}", path.display()).into()),
    };
    if len > MAX_LOG_BYTES {
        return Err(
            format!("{}: {len} bytes, more than a tuning log may hold", path.display()).into()
        );
    }
    let text = std::fs::read_to_string(path).map_err(|e| format!("{}: {e}", path.display()))?;
    let log: Log = toml::from_str(&text).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(log.entry)
}

/// Appends `entries` to the log at `path` (created with a header when missing).
pub fn append_log(path: &Path, entries: Vec<LogEntry>) -> crate::XResult {
    use std::io::Write as _;
    let mut text = String::new();
    if !path.exists() {
        text.push_str(
            "# The tuning log: one entry per method of every tuning run (seeds 100-104, their own\n\
             # data), appended by `cargo xtask experiment <recipe> --tuning`. See\n\
             # docs/avoiding-tuning.md, \"Protocol\".\n",
        );
    }
    text.push('\n');
    text.push_str(&toml::to_string(&Log { entry: entries })?);
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .map_err(|e| format!("{}: {e}", path.display()))?;
    f.write_all(text.as_bytes()).map_err(|e| format!("{}: {e}", path.display()))?;
    Ok(())
}

/// The number of distinct configurations of `method` in `entries`.
pub fn configs_tried(entries: &[LogEntry], method: &str) -> usize {
    entries.iter().filter(|e| e.method == method).map(|e| &e.config).collect::<BTreeSet<_>>().len()
}

/// A hash of what `method` trains on and with: `data`, its teachers (when it has one), the
/// student mixture and the values of its recipe keys.
pub fn method_config_hash<D: Serialize>(
    method: &dyn Method,
    recipe: &MethodRecipe<'_>,
    data: &D,
) -> crate::XResult<String> {
    let info = method.info();
    let mut keys = serde_json::Map::new();
    for k in info.keys {
        let v: Option<toml::Value> = recipe.get_opt(k)?;
        keys.insert((*k).to_owned(), serde_json::to_value(v)?);
    }
    let key = serde_json::json!({
        "method": info.name,
        "data": data,
        "teachers": info.teacher.map(|_| recipe.teachers),
        "student": recipe.student,
        "keys": keys,
    });
    Ok(crate::recipe::config_hash(&key)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng as _;
    use vdd_core::Seeds;

    #[test]
    fn tuning_and_reporting_runs_stay_apart() {
        assert_eq!(is_tuning_run(&[100, 104], TUNING_DATA_SEED), Ok(true));
        assert_eq!(is_tuning_run(&[0, 1, 2], 0), Ok(false));
        assert!(is_tuning_run(&[0, 100], TUNING_DATA_SEED).unwrap_err().contains("mix"));
        assert!(is_tuning_run(&[100], 0).unwrap_err().contains("--tuning"));
        assert!(is_tuning_run(&[3], TUNING_DATA_SEED).unwrap_err().contains("tuning data"));
    }

    #[test]
    fn tuning_seeds_share_no_stream_with_reporting_seeds() {
        let purposes = ["avoiding-eval", "avoiding-episode", "avoiding-demonstrator", "init"];
        let mut firsts = BTreeSet::new();
        let mut roots = BTreeSet::new();
        let seeds = (0..5).chain(TUNING_SEEDS).chain([0, TUNING_DATA_SEED]);
        for s in seeds.collect::<BTreeSet<_>>() {
            let tree = Seeds::new(s);
            assert!(roots.insert(tree.child("avoiding-eval").root()));
            for p in purposes {
                assert!(firsts.insert(tree.stream(p).random::<u64>()), "seed {s}, {p}");
            }
        }
    }

    #[test]
    fn the_log_round_trips_and_counts_configurations() {
        let dir = std::env::temp_dir().join(format!("xtask-tuning-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let path = dir.join("log.toml");
        let _ = std::fs::remove_file(&path);
        assert!(read_log(&path).unwrap().is_empty());
        let e = |m: &str, c: &str| LogEntry {
            method: m.into(),
            config: c.into(),
            recipe: "avoiding".into(),
            command: "cargo xtask experiment avoiding --tuning".into(),
            revision: "abc".into(),
            seeds: vec![100],
            success_rate: vec![0.5],
            task_entropy: vec![0.25],
            train_steps: Some(10),
            train_batch: None,
            train_seconds: vec![1.5],
            run: "results/tuning/avoiding/seed100".into(),
        };
        append_log(&path, vec![e("em", "a"), e("em", "b")]).unwrap();
        append_log(&path, vec![e("em", "a"), e("imc", "a")]).unwrap();
        let log = read_log(&path).unwrap();
        assert_eq!(log.len(), 4);
        assert_eq!(log[0], e("em", "a"));
        assert_eq!((configs_tried(&log, "em"), configs_tried(&log, "imc")), (2, 1));
        assert_eq!(configs_tried(&log, "cd"), 0);
        std::fs::write(&path, "[[entry]]\nmethod = 3\n").unwrap();
        assert!(read_log(&path).unwrap_err().to_string().contains("log.toml"));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
