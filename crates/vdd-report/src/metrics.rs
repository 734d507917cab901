//! `metrics.json`: per-seed rows, their mean and standard deviation over seeds, and reading
//! runs back.
//!
//! # `metrics.json`
//!
//! ```text
//! { "recipe": "avoiding", "task": "avoiding", "seeds": [0, 1, 2],
//!   "method_order": ["beso", "vdd-beso"],
//!   "methods": { "vdd-beso": { "success_rate": <mean over seeds>, "success_rate_std": <std>,
//!                              ..., "seeds": 3, "per_seed": [ { "seed": 0, ... }, ... ] } } }
//! ```
//!
//! Every numeric per-seed value gets a mean and a standard deviation over seeds (population
//! std, `ddof = 0`, as numpy's default). Timing values (keys in [`TIMING_KEYS`]: `us_per_action`,
//! `train_seconds`, `teacher_seconds`, `ms_per_iter`, `curve_seconds`, and their `_std`) are wall-clock
//! measurements; everything else is a deterministic function of the resolved recipe and the
//! seed, so two runs of the same recipe and seeds give `metrics.json` files that are identical
//! apart from the timing values ([`compare::compare_runs`](crate::compare::compare_runs)
//! checks exactly that).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde_json::{Map, Value};

use crate::{Error, Result};

/// One method's values at one seed.
pub type Row = Map<String, Value>;

/// Keys holding wall-clock measurements (excluded from the reproducibility guarantee).
pub const TIMING_KEYS: [&str; 5] =
    ["us_per_action", "train_seconds", "teacher_seconds", "ms_per_iter", "curve_seconds"];

/// Whether `key` (or its `_std`) is a timing value.
///
/// ```
/// use vdd_report::metrics::is_timing_key;
/// assert!(is_timing_key("train_seconds_std"));
/// assert!(!is_timing_key("success_rate"));
/// ```
pub fn is_timing_key(key: &str) -> bool {
    let base = key.strip_suffix("_std").unwrap_or(key);
    TIMING_KEYS.contains(&base)
}

/// Mean and population standard deviation (`NaN`s for no values).
///
/// ```
/// assert_eq!(vdd_report::metrics::mean_std(&[1.0, 3.0]), (2.0, 1.0));
/// ```
pub fn mean_std(xs: &[f64]) -> (f64, f64) {
    if xs.is_empty() {
        return (f64::NAN, f64::NAN);
    }
    let n = xs.len() as f64;
    let mean = xs.iter().sum::<f64>() / n;
    let var = xs.iter().map(|x| (x - mean) * (x - mean)).sum::<f64>() / n;
    (mean, var.sqrt())
}

/// Summarises per-seed rows: for every numeric key but `seed`, `<key>` = mean and
/// `<key>_std` = std over the rows that have it; `seeds` = number of rows; `per_seed` = rows.
///
/// ```
/// use serde_json::json;
/// let rows = [json!({"seed": 0, "loss": 1.0}), json!({"seed": 1, "loss": 3.0})]
///     .map(|v| v.as_object().unwrap().clone());
/// let s = vdd_report::metrics::summarise(&rows);
/// assert_eq!((s["loss"].clone(), s["loss_std"].clone()), (json!(2.0), json!(1.0)));
/// ```
pub fn summarise(per_seed: &[Row]) -> Row {
    let mut keys: Vec<String> = Vec::new();
    for r in per_seed {
        for (k, v) in r {
            if k != "seed" && v.is_number() && !keys.contains(k) {
                keys.push(k.clone());
            }
        }
    }
    let mut out = Row::new();
    for k in keys {
        let xs: Vec<f64> = per_seed.iter().filter_map(|r| r.get(&k)?.as_f64()).collect();
        let (m, s) = mean_std(&xs);
        out.insert(k.clone(), json_f64(m));
        out.insert(format!("{k}_std"), json_f64(s));
    }
    out.insert("seeds".into(), Value::from(per_seed.len()));
    out.insert(
        "per_seed".into(),
        Value::Array(per_seed.iter().cloned().map(Value::Object).collect()),
    );
    out
}

/// A finite float as JSON, `null` otherwise.
///
/// ```
/// use vdd_report::metrics::json_f64;
/// assert_eq!(json_f64(0.5), serde_json::json!(0.5));
/// assert!(json_f64(f64::NAN).is_null());
/// ```
pub fn json_f64(x: f64) -> Value {
    serde_json::Number::from_f64(x).map(Value::Number).unwrap_or(Value::Null)
}

/// Builds `metrics.json`'s common part from `(label, per-seed rows)` in order.
///
/// ```
/// use serde_json::json;
/// let row = json!({"seed": 0, "success_rate": 0.9}).as_object().unwrap().clone();
/// let m = vdd_report::metrics::metrics_json("avoiding", "avoiding", &[0], &[("em".into(), vec![row])]);
/// assert_eq!(m["method_order"], json!(["em"]));
/// assert_eq!(m["methods"]["em"]["success_rate"], json!(0.9));
/// ```
pub fn metrics_json(recipe: &str, task: &str, seeds: &[u64], rows: &[(String, Vec<Row>)]) -> Row {
    let mut m = Row::new();
    m.insert("recipe".into(), Value::from(recipe));
    m.insert("task".into(), Value::from(task));
    m.insert("seeds".into(), Value::from(seeds.to_vec()));
    m.insert(
        "method_order".into(),
        Value::Array(rows.iter().map(|(n, _)| Value::from(n.as_str())).collect()),
    );
    let mut methods = Row::new();
    for (name, per_seed) in rows {
        methods.insert(name.clone(), Value::Object(summarise(per_seed)));
    }
    m.insert("methods".into(), Value::Object(methods));
    m
}

/// The toy recipes' evaluation fields of a row, from the scores at each evaluation state
/// `(state, reverse KL, forward KL, modes covered)` against a mixture of `modes` modes: for
/// `toy-gmm` (one state, `conditional` false) `reverse_kl`, `forward_kl`, `modes_covered` and
/// `modes_total`; for `toy-conditional` `states_fully_covered` (states with every mode
/// covered), `eval_states`, `mean_reverse_kl`, `mean_forward_kl` (means over the states) and
/// the per-state `states`.
///
/// ```
/// use serde_json::json;
/// let f = vdd_report::metrics::toy_fields(&[(0.0, 0.1, 0.3, 8), (1.0, 0.3, 0.1, 7)], 8, true);
/// assert_eq!((f["states_fully_covered"].clone(), f["eval_states"].clone()), (json!(1), json!(2)));
/// assert!((f["mean_reverse_kl"].as_f64().unwrap() - 0.2).abs() < 1e-12);
/// assert_eq!(f["states"][1]["modes_covered"], json!(7));
/// ```
pub fn toy_fields(scores: &[(f32, f64, f64, usize)], modes: usize, conditional: bool) -> Row {
    let n = scores.len();
    let mean = |f: fn(&(f32, f64, f64, usize)) -> f64| scores.iter().map(f).sum::<f64>() / n as f64;
    let (rev, fwd) = (mean(|g| g.1), mean(|g| g.2));
    let mut row = Row::new();
    let f64_at = |k: &str, v: f64| (k.to_owned(), json_f64(v));
    if conditional {
        let full = scores.iter().filter(|g| g.3 == modes).count();
        row.insert("states_fully_covered".into(), Value::from(full));
        row.insert("eval_states".into(), Value::from(n));
        row.extend([f64_at("mean_reverse_kl", rev), f64_at("mean_forward_kl", fwd)]);
        let per_state = scores.iter().map(|&(state, rev, fwd, cov)| {
            serde_json::json!({"state": state, "modes_covered": cov, "reverse_kl": rev, "forward_kl": fwd})
        });
        row.insert("states".into(), Value::Array(per_state.collect()));
    } else {
        row.extend([f64_at("reverse_kl", rev), f64_at("forward_kl", fwd)]);
        row.insert("modes_covered".into(), Value::from(scores.first().map_or(0, |g| g.3)));
        row.insert("modes_total".into(), Value::from(modes));
    }
    row
}

/// A one-line summary of [`toy_fields`] for `modes` modes: reverse and forward KL and the
/// modes covered, or for the conditional toy the states where all modes are covered and the
/// mean KLs.
///
/// ```
/// let f = vdd_report::metrics::toy_fields(&[(0.0, 0.1, 0.3, 8)], 8, false);
/// assert_eq!(vdd_report::metrics::toy_line(&f, 8), "reverse KL 0.10000 nats, forward KL 0.30000 nats, modes 8/8");
/// ```
pub fn toy_line(fields: &Row, modes: usize) -> String {
    let get = |k: &str| fields.get(k).and_then(Value::as_f64).unwrap_or(f64::NAN);
    match fields.get("eval_states") {
        Some(n) => format!(
            "all {modes} modes covered at {}/{n} states, mean reverse KL {:.4}, mean forward KL \
             {:.4} nats",
            get("states_fully_covered"),
            get("mean_reverse_kl"),
            get("mean_forward_kl")
        ),
        None => format!(
            "reverse KL {:.5} nats, forward KL {:.5} nats, modes {}/{modes}",
            get("reverse_kl"),
            get("forward_kl"),
            get("modes_covered")
        ),
    }
}

/// Adds the toy recipes' top-level keys (those of the original commands) to `metrics`, from the
/// first method of `rows`: `method`, `teacher` (`method` without `vdd-`), `seed` (the first),
/// `ms_per_iter` and `train_seconds` (means over seeds), and for `toy-gmm` (`conditional`
/// false) `reverse_kl`, `forward_kl` (means), `modes_covered` (the minimum) and
/// `modes_total` (`modes`); for `toy-conditional` `modes`, `states_fully_covered` (minimum),
/// `mean_reverse_kl`, `mean_forward_kl` (means) and the first seed's `states`.
///
/// ```
/// use serde_json::json;
/// use vdd_report::metrics::{Row, toy_summary};
/// let row = |kl: f64, cov: u64| json!({"reverse_kl": kl, "modes_covered": cov}).as_object().unwrap().clone();
/// let mut m = Row::new();
/// toy_summary(&mut m, &[("vdd-exact".into(), vec![row(0.1, 8), row(0.3, 7)])], 0, false, 8);
/// assert_eq!((m["teacher"].clone(), m["modes_covered"].clone()), (json!("exact"), json!(7)));
/// assert!((m["reverse_kl"].as_f64().unwrap() - 0.2).abs() < 1e-12);
/// ```
pub fn toy_summary(
    metrics: &mut Row,
    rows: &[(String, Vec<Row>)],
    seed: u64,
    conditional: bool,
    modes: usize,
) {
    let Some((label, first)) = rows.first() else { return };
    let mean = |key: &str| {
        let xs: Vec<f64> = first.iter().filter_map(|r| r.get(key)?.as_f64()).collect();
        json_f64(mean_std(&xs).0)
    };
    let min = |key: &str| first.iter().filter_map(|r| r.get(key)?.as_u64()).min().unwrap_or(0);
    metrics.insert("method".into(), Value::from(label.as_str()));
    metrics.insert("teacher".into(), Value::from(label.trim_start_matches("vdd-")));
    metrics.insert("seed".into(), Value::from(seed));
    if conditional {
        metrics.insert("modes".into(), Value::from(modes));
        metrics.insert("states_fully_covered".into(), Value::from(min("states_fully_covered")));
        metrics.insert("mean_reverse_kl".into(), mean("mean_reverse_kl"));
        metrics.insert("mean_forward_kl".into(), mean("mean_forward_kl"));
        let states = first.first().and_then(|r| r.get("states")).cloned();
        metrics.insert("states".into(), states.unwrap_or(Value::Null));
    } else {
        metrics.insert("reverse_kl".into(), mean("reverse_kl"));
        metrics.insert("forward_kl".into(), mean("forward_kl"));
        metrics.insert("modes_covered".into(), Value::from(min("modes_covered")));
        metrics.insert("modes_total".into(), Value::from(modes));
    }
    metrics.insert("ms_per_iter".into(), mean("ms_per_iter"));
    metrics.insert("train_seconds".into(), mean("train_seconds"));
}

/// Reads `dir/metrics.json` (or a `metrics.json` path); returns the file read and its value.
pub fn read_metrics(path: &Path) -> Result<(PathBuf, Value)> {
    let file = if path.is_dir() { path.join("metrics.json") } else { path.to_path_buf() };
    let text = std::fs::read_to_string(&file)
        .map_err(|source| Error::Read { path: file.clone(), source })?;
    let v: Value = serde_json::from_str(&text)
        .map_err(|source| Error::Parse { path: file.clone(), source })?;
    Ok((file, v))
}

/// Collects `(label, per-seed rows)` from several `metrics.json` values, in first-seen order.
/// A `(method, seed)` pair seen again replaces the earlier row (with a note in `notes`).
pub fn collect_rows(metrics: &[Value], notes: &mut Vec<String>) -> Vec<(String, Vec<Row>)> {
    let mut order: Vec<String> = Vec::new();
    let mut rows: BTreeMap<String, Vec<Row>> = BTreeMap::new();
    for m in metrics {
        let Some(methods) = m.get("methods").and_then(Value::as_object) else { continue };
        let mut names: Vec<String> = m
            .get("method_order")
            .and_then(Value::as_array)
            .map(|a| a.iter().filter_map(|v| v.as_str().map(String::from)).collect())
            .unwrap_or_default();
        for k in methods.keys() {
            if !names.contains(k) {
                names.push(k.clone());
            }
        }
        for name in names {
            let Some(entry) = methods.get(&name) else { continue };
            let per_seed =
                entry.get("per_seed").and_then(Value::as_array).cloned().unwrap_or_default();
            if !order.contains(&name) {
                order.push(name.clone());
            }
            let target = rows.entry(name.clone()).or_default();
            for r in per_seed {
                let Value::Object(r) = r else { continue };
                let seed = r.get("seed").cloned();
                if let Some(i) =
                    target.iter().position(|x| seed.is_some() && x.get("seed") == seed.as_ref())
                {
                    notes.push(format!(
                        "{name}: seed {} appears twice; the later run is used",
                        seed.unwrap_or(Value::Null)
                    ));
                    target[i] = r;
                } else {
                    target.push(r);
                }
            }
        }
    }
    order
        .into_iter()
        .map(|n| {
            let r = rows.remove(&n).unwrap_or_default();
            (n, r)
        })
        .collect()
}

/// The share of each method's successful rollouts in each behaviour mode, summed over its
/// seeds (the rows' `mode_counts`), for [`crate::plots::mode_histograms`]. Methods without
/// `mode_counts` or without a success are left out.
///
/// ```
/// use serde_json::json;
/// let row = |c: Vec<u64>| json!({ "mode_counts": c }).as_object().unwrap().clone();
/// let rows = [("beso".to_owned(), vec![row(vec![1, 3]), row(vec![2, 2])]), ("em".into(), vec![])];
/// assert_eq!(vdd_report::metrics::mode_shares(&rows), [("beso".to_owned(), vec![0.375, 0.625])]);
/// ```
pub fn mode_shares(rows: &[(String, Vec<Row>)]) -> Vec<(String, Vec<f64>)> {
    let mut out = Vec::new();
    for (method, per_seed) in rows {
        let mut counts: Vec<f64> = Vec::new();
        for c in per_seed.iter().filter_map(|r| r.get("mode_counts")?.as_array()) {
            counts.resize(counts.len().max(c.len()), 0.0);
            c.iter().zip(counts.iter_mut()).for_each(|(v, n)| *n += v.as_f64().unwrap_or(0.0));
        }
        let total: f64 = counts.iter().sum();
        if total > 0.0 && total.is_finite() {
            out.push((method.clone(), counts.iter().map(|c| c / total).collect()));
        }
    }
    out
}

/// Run directories under `results` holding a `metrics.json`, grouped by recipe directory
/// (sorted), skipping `cache`. Unreadable directories count as empty.
pub fn find_runs(results: &Path) -> Vec<(String, Vec<PathBuf>)> {
    let sorted_dirs = |p: &Path| -> Vec<PathBuf> {
        let mut v: Vec<PathBuf> = std::fs::read_dir(p)
            .map(|rd| rd.filter_map(|e| e.ok()).map(|e| e.path()).filter(|p| p.is_dir()).collect())
            .unwrap_or_default();
        v.sort();
        v
    };
    let mut groups = Vec::new();
    for recipe in sorted_dirs(results) {
        let Some(name) = recipe.file_name().and_then(|n| n.to_str()).map(String::from) else {
            continue;
        };
        if name == "cache" {
            continue;
        }
        let runs: Vec<PathBuf> =
            sorted_dirs(&recipe).into_iter().filter(|r| r.join("metrics.json").is_file()).collect();
        if !runs.is_empty() {
            groups.push((name, runs));
        }
    }
    groups
}

#[cfg(test)]
mod tests;
