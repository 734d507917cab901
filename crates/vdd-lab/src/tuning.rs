//! The tuning protocol: tuning runs kept apart from the reported ones, and the committed tuning
//! log.
//!
//! Settings are chosen on the tuning seeds [`TUNING_SEEDS`] (100–104) with their own
//! demonstrations (`data.seed` = [`TUNING_DATA_SEED`]); the results are reported on other seeds
//! (0–4) with the reporting demonstrations (`data.seed` = 0). A run is a tuning run when its
//! seeds are tuning seeds; it may not mix them with other seeds and must use the tuning data
//! ([`is_tuning_run`]); a run on other seeds may not use the tuning data.
//!
//! The seeds share no random stream with the reporting seeds: every stream is keyed by its
//! root seed and purpose (`vdd_core::Seeds`), so the tuning seeds' streams differ from the
//! reporting seeds' (a test checks the roots and the streams' first draws).
//!
//! `cargo xtask experiment <recipe> --tuning` sets the tuning seeds (100–104 unless `--seeds`
//! names others) and the tuning data; its results go to `results/tuning/<recipe>/<run>/`
//! (outside the runs `cargo xtask table` collects). The rollouts' root is derived from the run
//! seed, the demonstrations' from `data.seed`, and the training of every method from the run
//! seed.
//!
//! Every tuning run appends one [`LogEntry`] per method to the task's log
//! `docs/<task>-tuning-log.toml` ([`log_path`], committed; a TOML file with one `[[entry]]`
//! table each, [`append_log`] / [`read_log`]): the method, a hash of its configuration
//! ([`method_config_hash`]), the command, the revision, the seeds and the per-seed figures.
//! [`configs_tried`] counts a method's distinct configurations in a log: `tuning_configs` in a
//! reported run's `metrics.json`.

use std::collections::BTreeSet;
use std::ops::RangeInclusive;
use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use crate::method::MethodRecipe;

/// A run that breaks the tuning protocol, or a tuning log that cannot be read or written.
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum TuningError {
    /// A run breaks the tuning protocol: it mixes tuning and reporting seeds or uses the other
    /// protocol's demonstrations.
    #[error("{0}")]
    Protocol(String),
    /// A tuning log could not be read.
    #[error("reading {}: {source}", .path.display())]
    Read {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// A tuning log could not be written.
    #[error("writing {}: {source}", .path.display())]
    Write {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// A tuning log is not a valid log.
    #[error("parsing {}: {source}", .path.display())]
    Parse {
        /// The file.
        path: PathBuf,
        /// The parser's error.
        #[source]
        source: toml::de::Error,
    },
    /// A tuning log larger than [`MAX_LOG_BYTES`], refused before it is read.
    #[error("{}: {bytes} bytes, more than a tuning log may hold", .path.display())]
    TooLarge {
        /// The file.
        path: PathBuf,
        /// Its size.
        bytes: u64,
    },
    /// Entries could not be serialised as TOML.
    #[error("{0}")]
    Serialize(#[source] toml::ser::Error),
}

/// Result of the tuning protocol and log.
pub type TuningResult<T> = std::result::Result<T, TuningError>;

/// The tuning seeds.
pub const TUNING_SEEDS: RangeInclusive<u64> = 100..=104;

/// The `data.seed` of tuning runs (reported runs use 0).
pub const TUNING_DATA_SEED: u64 = 100;

/// The largest tuning log read (bytes).
pub const MAX_LOG_BYTES: u64 = 16 << 20;

/// Whether a run on `seeds` with demonstrations of `data_seed` is a tuning run; an error
/// ([`TuningError::Protocol`]) when it mixes tuning and other seeds or uses the other protocol's
/// data.
pub fn is_tuning_run(seeds: &[u64], data_seed: u64) -> TuningResult<bool> {
    let (first, last) = (TUNING_SEEDS.start(), TUNING_SEEDS.end());
    let tuning = seeds.iter().filter(|s| TUNING_SEEDS.contains(s)).count();
    if tuning > 0 && tuning < seeds.len() {
        let e = format!("seeds {seeds:?} mix tuning seeds ({first}–{last}) with reporting seeds");
        return Err(TuningError::Protocol(e));
    }
    let is_tuning = tuning > 0;
    if is_tuning && data_seed != TUNING_DATA_SEED {
        return Err(TuningError::Protocol(format!(
            "tuning seeds need the tuning demonstrations (data.seed = {TUNING_DATA_SEED}, got \
             {data_seed}); pass --tuning"
        )));
    }
    if !is_tuning && data_seed == TUNING_DATA_SEED {
        return Err(TuningError::Protocol(format!(
            "data.seed = {TUNING_DATA_SEED} is the tuning data; use it with the tuning seeds \
             {first}–{last} only (--tuning)"
        )));
    }
    Ok(is_tuning)
}

/// Whether the runs of a recipe's variants, each `(seeds, data_seed)`, are tuning runs
/// ([`is_tuning_run`] of each); an error when one is and another is not. No runs: `false`.
///
/// ```
/// use vdd_lab::tuning::is_tuning_plan;
/// assert!(is_tuning_plan([(&[100, 101][..], 100), (&[100, 101][..], 100)])?);
/// assert!(!is_tuning_plan([(&[0][..], 0)])?);
/// assert!(is_tuning_plan([(&[100][..], 100), (&[0][..], 0)]).is_err());
/// # Ok::<(), vdd_lab::tuning::TuningError>(())
/// ```
pub fn is_tuning_plan<'a>(runs: impl IntoIterator<Item = (&'a [u64], u64)>) -> TuningResult<bool> {
    let mut plan = None;
    for (seeds, data_seed) in runs {
        let t = is_tuning_run(seeds, data_seed)?;
        if plan.replace(t).is_some_and(|before| before != t) {
            let e = "variants mix tuning and reporting demonstrations".to_owned();
            return Err(TuningError::Protocol(e));
        }
    }
    Ok(plan.unwrap_or(false))
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
    /// Why the run failed, for a configuration that did not finish. A failed tuning run
    /// writes it with the error and no figures; an entry written by hand may carry the figures
    /// of the seeds that finished. It still counts as tried.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub failure: Option<String>,
}

/// What identifies one method of one tuning run; the figures come from its result rows
/// ([`LogEntry::from_rows`]).
#[derive(Debug, Clone, PartialEq)]
pub struct RunId {
    /// The method's label.
    pub method: String,
    /// [`method_config_hash`] of its configuration.
    pub config: String,
    /// The recipe.
    pub recipe: String,
    /// The command line.
    pub command: String,
    /// The revision (`+dirty` with uncommitted changes).
    pub revision: String,
    /// The run directory, relative to the repository.
    pub run: String,
}

impl LogEntry {
    /// The entry of a method from its per-seed result rows (`seed`, `success_rate`,
    /// `task_entropy`, `train_seconds`, and `train_steps` / `train_batch` of the first row
    /// when present); rows without a value are skipped.
    pub fn from_rows(id: RunId, rows: &[serde_json::Map<String, serde_json::Value>]) -> Self {
        let all = |k: &str| rows.iter().filter_map(|r| r.get(k)?.as_f64()).collect::<Vec<_>>();
        let first = |k: &str| rows.first().and_then(|r| r.get(k)?.as_u64());
        let RunId { method, config, recipe, command, revision, run } = id;
        LogEntry {
            method,
            config,
            recipe,
            command,
            revision,
            seeds: rows.iter().filter_map(|r| r.get("seed")?.as_u64()).collect(),
            success_rate: all("success_rate"),
            task_entropy: all("task_entropy"),
            train_steps: first("train_steps"),
            train_batch: first("train_batch"),
            train_seconds: all("train_seconds"),
            run,
            failure: None,
        }
    }
}

#[derive(Debug, Default, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Log {
    #[serde(default)]
    entry: Vec<LogEntry>,
}

fn io_error(path: &Path) -> impl FnOnce(std::io::Error) -> TuningError + '_ {
    move |source| TuningError::Read { path: path.to_owned(), source }
}

fn write_error(path: &Path) -> impl FnOnce(std::io::Error) -> TuningError + '_ {
    move |source| TuningError::Write { path: path.to_owned(), source }
}

/// The entries of the log at `path` (none when the file does not exist); a file over
/// [`MAX_LOG_BYTES`] is refused before it is read.
pub fn read_log(path: &Path) -> TuningResult<Vec<LogEntry>> {
    let len = match std::fs::metadata(path) {
        Ok(m) => m.len(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(Vec::new()),
        Err(e) => return Err(io_error(path)(e)),
    };
    if len > MAX_LOG_BYTES {
        return Err(TuningError::TooLarge { path: path.to_owned(), bytes: len });
    }
    let text = match vdd_core::files::read_bounded_string(path, MAX_LOG_BYTES) {
        Ok(text) => text,
        // Grown past the bound since its size was checked.
        Err(e) if e.kind() == std::io::ErrorKind::FileTooLarge => {
            return Err(TuningError::TooLarge {
                path: path.to_owned(),
                bytes: len.max(MAX_LOG_BYTES + 1),
            });
        }
        Err(e) => return Err(io_error(path)(e)),
    };
    let log: Log = toml::from_str(&text)
        .map_err(|source| TuningError::Parse { path: path.to_owned(), source })?;
    Ok(log.entry)
}

/// Appends `entries` to the log at `path` (created with a header when missing).
pub fn append_log(path: &Path, entries: Vec<LogEntry>) -> TuningResult<()> {
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
    text.push_str(&toml::to_string(&Log { entry: entries }).map_err(TuningError::Serialize)?);
    let mut f = std::fs::OpenOptions::new()
        .create(true)
        .append(true)
        .open(path)
        .map_err(write_error(path))?;
    f.write_all(text.as_bytes()).map_err(write_error(path))
}

/// The number of distinct configurations of `method` in `entries`.
pub fn configs_tried(entries: &[LogEntry], method: &str) -> usize {
    entries.iter().filter(|e| e.method == method).map(|e| &e.config).collect::<BTreeSet<_>>().len()
}

/// A hash ([`vdd_recipe::config_hash`]) of what a method trains on and with: its `name`, the
/// `data` configuration, its `teachers` (when it has any), the `student` and the values of its
/// own recipe `keys`.
///
/// The committed tuning logs count a method's configurations by it: the JSON built here and
/// its hash must never change (a test pins known values).
pub fn config_hash<D: Serialize + ?Sized, T: Serialize + ?Sized, S: Serialize + ?Sized>(
    name: &str,
    data: &D,
    teachers: Option<&T>,
    student: &S,
    keys: serde_json::Map<String, serde_json::Value>,
) -> vdd_recipe::RecipeResult<String> {
    let key = serde_json::json!({
        "method": name,
        "data": data,
        "teachers": teachers,
        "student": student,
        "keys": keys,
    });
    vdd_recipe::config_hash(&key)
}

/// The tuning log of `task`: `docs/<task>-tuning-log.toml`.
pub fn log_path(root: &std::path::Path, task: &str) -> PathBuf {
    root.join("docs").join(format!("{task}-tuning-log.toml"))
}

/// [`config_hash`] of the row of `recipe`: `data`, its learned teachers (when it has one), the
/// student mixture and the values of its recipe keys.
pub fn method_config_hash<D: serde::Serialize>(
    recipe: &MethodRecipe<'_>,
    data: &D,
) -> crate::Result<String> {
    let row = recipe.row;
    let mut keys = serde_json::Map::new();
    for k in row.keys() {
        let v: Option<toml::Value> = recipe.get_opt(&k)?;
        keys.insert(k, serde_json::to_value(v)?);
    }
    let teachers = row.teacher_kind().map(|_| recipe.teachers);
    Ok(config_hash(&row.name, data, teachers, recipe.student, keys)?)
}

#[cfg(test)]
mod tests {
    use super::*;
    use rand::Rng as _;
    use vdd_core::Seeds;

    #[test]
    fn tuning_and_reporting_runs_stay_apart() {
        let err = |s: &[u64], d| is_tuning_run(s, d).unwrap_err().to_string();
        assert!(is_tuning_run(&[100, 104], TUNING_DATA_SEED).unwrap());
        assert!(!is_tuning_run(&[0, 1, 2], 0).unwrap());
        assert!(err(&[0, 100], TUNING_DATA_SEED).contains("mix"));
        assert!(err(&[100], 0).contains("--tuning"));
        assert!(err(&[3], TUNING_DATA_SEED).contains("tuning data"));
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
        let dir = std::env::temp_dir().join(format!("vdd-lab-tuning-{}", std::process::id()));
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
            failure: (c == "b").then(|| "seed 101 diverged".into()),
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

    #[test]
    fn entries_collect_the_rows_figures() {
        let rows: Vec<serde_json::Map<String, serde_json::Value>> = [
            serde_json::json!({"seed": 100, "success_rate": 0.5, "task_entropy": 0.2,
                "train_seconds": 1.0, "train_steps": 10, "train_batch": 4}),
            serde_json::json!({"seed": 101, "success_rate": 0.7, "train_seconds": 2.0}),
        ]
        .map(|v| v.as_object().unwrap().clone())
        .into();
        let id = RunId {
            method: "em".into(),
            config: "c".into(),
            recipe: "avoiding".into(),
            command: "x".into(),
            revision: "r".into(),
            run: "results/tuning/avoiding/seed100-101".into(),
        };
        let e = LogEntry::from_rows(id, &rows);
        assert_eq!((e.seeds, e.success_rate), (vec![100, 101], vec![0.5, 0.7]));
        assert_eq!((e.task_entropy, e.train_seconds), (vec![0.2], vec![1.0, 2.0]));
        assert_eq!((e.train_steps, e.train_batch, e.method.as_str()), (Some(10), Some(4), "em"));
    }

    #[test]
    fn method_hashes_change_with_what_the_method_trains_on() {
        let keys = |v: i64| {
            let mut m = serde_json::Map::new();
            m.insert("baselines.em".into(), serde_json::json!({ "iterations": v }));
            m
        };
        let h = |name, data: u64, teachers: Option<&str>, k| {
            config_hash(name, &data, teachers, &"moe", keys(k)).unwrap()
        };
        let base = h("em", 0, None, 1);
        assert_eq!(base, h("em", 0, None, 1));
        for other in [h("imc", 0, None, 1), h("em", 1, None, 1), h("em", 0, Some("t"), 1)] {
            assert_ne!(base, other);
        }
        assert_ne!(base, h("em", 0, None, 2));
    }

    /// The committed tuning logs count configurations by these hashes (`tuning_configs` in
    /// `metrics.json`): the values computed before the protocol moved here from vdd-recipe.
    #[test]
    fn known_configurations_keep_their_hashes() {
        let data = serde_json::json!({"seed": 100, "demonstrations": 400, "window": 1});
        let teachers = serde_json::json!({"beso": {"sampling_steps": 3, "noise": 0.5}});
        let student = serde_json::json!({"num_experts": 16, "expert_kind": "diagonal"});
        let mut keys = serde_json::Map::new();
        keys.insert("vdd.beso".into(), serde_json::json!({"iterations": 2000, "lr": 0.001}));
        let with_teachers =
            config_hash("vdd-beso", &data, Some(&teachers), &student, keys.clone()).unwrap();
        assert_eq!(with_teachers, "ef68ed948fb78a36");
        let none = None::<&serde_json::Value>;
        assert_eq!(config_hash("em", &data, none, &student, keys).unwrap(), "d3462ada0b012b59");
    }
}
