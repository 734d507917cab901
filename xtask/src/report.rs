//! Results: `metrics.json` aggregation over seeds, markdown tables, `cargo xtask table` and
//! `cargo xtask compare`.
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
//! `train_seconds`, `teacher_seconds`, `ms_per_iter`, and their `_std`) are wall-clock
//! measurements; everything else is a deterministic function of the resolved recipe and the
//! seed, so two runs of the same recipe and seeds give `metrics.json` files that are identical
//! apart from the timing values (`cargo xtask compare A B` checks exactly that).

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use serde_json::{Map, Value};

/// One method's values at one seed.
pub type Row = Map<String, Value>;

/// Keys holding wall-clock measurements (excluded from the reproducibility guarantee).
pub const TIMING_KEYS: [&str; 4] =
    ["us_per_action", "train_seconds", "teacher_seconds", "ms_per_iter"];

/// Whether `key` (or its `_std`) is a timing value.
pub fn is_timing_key(key: &str) -> bool {
    let base = key.strip_suffix("_std").unwrap_or(key);
    TIMING_KEYS.contains(&base)
}

/// Mean and population standard deviation.
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
pub fn json_f64(x: f64) -> Value {
    serde_json::Number::from_f64(x).map(Value::Number).unwrap_or(Value::Null)
}

/// A column of a results table.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Column {
    /// Key in the per-seed rows.
    pub key: &'static str,
    /// Header text.
    pub header: &'static str,
    /// Decimal digits.
    pub digits: usize,
}

const fn col(key: &'static str, header: &'static str, digits: usize) -> Column {
    Column { key, header, digits }
}

/// The paper's columns for `task`.
pub fn columns_for(task: &str) -> Vec<Column> {
    match task {
        "toy-gmm" => vec![
            col("reverse_kl", "reverse KL (nats)", 4),
            col("forward_kl", "forward KL (nats)", 4),
            col("modes_covered", "modes covered", 2),
            col("ms_per_iter", "ms / iter", 3),
            col("train_seconds", "train s", 1),
        ],
        "toy-conditional" => vec![
            col("states_fully_covered", "states fully covered", 2),
            col("mean_reverse_kl", "reverse KL (nats)", 4),
            col("mean_forward_kl", "forward KL (nats)", 4),
            col("ms_per_iter", "ms / iter", 3),
            col("train_seconds", "train s", 1),
        ],
        _ => vec![
            col("success_rate", "success rate", 3),
            col("task_entropy", "task entropy", 3),
            col("us_per_action", "µs / action", 1),
            col("train_seconds", "train s", 1),
        ],
    }
}

/// `mean ± std` (just the mean for one seed, `–` when missing).
pub fn fmt_cell(xs: &[f64], digits: usize) -> String {
    match xs.len() {
        0 => "–".into(),
        1 => format!("{:.*}", digits, xs[0]),
        _ => {
            let (m, s) = mean_std(xs);
            format!("{m:.digits$} ± {s:.digits$}")
        }
    }
}

/// A markdown table with one row per method (in the given order) and `columns`.
pub fn markdown_table(rows: &[(String, Vec<Row>)], columns: &[Column]) -> String {
    let mut s = String::from("| method | seeds |");
    for c in columns {
        s.push_str(&format!(" {} |", c.header));
    }
    s.push_str("\n|---|---|");
    for _ in columns {
        s.push_str("---|");
    }
    s.push('\n');
    for (name, per_seed) in rows {
        s.push_str(&format!("| {name} | {} |", per_seed.len()));
        for c in columns {
            let xs: Vec<f64> = per_seed.iter().filter_map(|r| r.get(c.key)?.as_f64()).collect();
            s.push_str(&format!(" {} |", fmt_cell(&xs, c.digits)));
        }
        s.push('\n');
    }
    s
}

/// Builds `metrics.json`'s common part from `(label, per-seed rows)` in order.
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

/// Reads `dir/metrics.json` (or a `metrics.json` path).
fn read_metrics(path: &Path) -> Result<(PathBuf, Value), String> {
    let file = if path.is_dir() { path.join("metrics.json") } else { path.to_path_buf() };
    let text =
        std::fs::read_to_string(&file).map_err(|e| format!("reading {}: {e}", file.display()))?;
    let v: Value =
        serde_json::from_str(&text).map_err(|e| format!("parsing {}: {e}", file.display()))?;
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

/// The command line of `table`.
#[derive(Debug, Clone, clap::Args)]
pub struct TableArgs {
    /// Run directories (or their metrics.json), all of one task; none: every run under results/.
    #[arg(value_name = "RUN_DIR")]
    pub runs: Vec<PathBuf>,
    /// Also write the tables to FILE.
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,
}

/// `cargo xtask table [--out FILE] [RUN_DIR | metrics.json]...`: one mean ± std table over
/// every seed found in the given runs (which must be of one task). Without paths, one table
/// per recipe over every run under `results/` (the teacher cache excluded).
pub fn run_table(args: &TableArgs) -> crate::XResult {
    let (paths, out) = (&args.runs, &args.out);
    let text = if paths.is_empty() {
        let groups = find_runs(&crate::recipe::repo_root().join("results"));
        if groups.is_empty() {
            return Err("no results/<recipe>/<run>/metrics.json found; run `cargo xtask \
                        experiment <recipe>` first or pass run directories"
                .into());
        }
        let mut text = String::new();
        for (_, runs) in groups {
            text.push_str(&table_text(&runs)?);
            text.push('\n');
        }
        text
    } else {
        table_text(paths)?
    };
    print!("{text}");
    if let Some(out) = out {
        std::fs::write(out, &text).map_err(|e| format!("writing {}: {e}", out.display()))?;
        eprintln!("wrote {}", out.display());
    }
    Ok(())
}

/// Run directories under `results` holding a `metrics.json`, grouped by recipe directory
/// (sorted), skipping `cache`.
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

/// The mean ± std table of the runs at `paths` (one task).
fn table_text(paths: &[PathBuf]) -> Result<String, String> {
    let mut values = Vec::new();
    let mut tasks: Vec<String> = Vec::new();
    let mut recipes: Vec<String> = Vec::new();
    for p in paths {
        let (file, v) = read_metrics(p)?;
        if v.get("methods").and_then(Value::as_object).is_none() {
            return Err(format!("{} has no `methods` object", file.display()));
        }
        for (key, list) in [("task", &mut tasks), ("recipe", &mut recipes)] {
            if let Some(t) = v.get(key).and_then(Value::as_str) {
                if !list.iter().any(|x| x == t) {
                    list.push(t.to_owned());
                }
            }
        }
        values.push(v);
    }
    if tasks.len() > 1 {
        return Err(format!(
            "the runs are of different tasks ({}); tabulate them separately",
            tasks.join(", ")
        ));
    }
    let task = tasks.first().cloned().unwrap_or_else(|| "avoiding".into());
    let mut notes = Vec::new();
    let rows = collect_rows(&values, &mut notes);
    let mut text = format!("## {} ({task})\n\n", recipes.join(" + "));
    text.push_str(&markdown_table(&rows, &columns_for(&task)));
    text.push_str(&format!(
        "\nmean ± std over seeds (population std); from {}\n",
        paths.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", ")
    ));
    for n in &notes {
        eprintln!("note: {n}");
    }
    Ok(text)
}

/// Removes timing values (see [`TIMING_KEYS`]) from a JSON value, recursively.
pub fn strip_timings(v: &mut Value) {
    match v {
        Value::Object(m) => {
            m.retain(|k, _| !is_timing_key(k));
            m.values_mut().for_each(strip_timings);
        }
        Value::Array(a) => a.iter_mut().for_each(strip_timings),
        _ => {}
    }
}

/// The command line of `compare`.
#[derive(Debug, Clone, clap::Args)]
pub struct CompareArgs {
    /// The first run directory (or its metrics.json).
    pub run_a: PathBuf,
    /// The second run directory (or its metrics.json).
    pub run_b: PathBuf,
}

/// `cargo xtask compare A B`: whether two runs' `metrics.json` agree apart from timings.
pub fn run_compare(args: &CompareArgs) -> crate::XResult {
    let (a, b) = (&args.run_a, &args.run_b);
    let (fa, mut va) = read_metrics(a)?;
    let (fb, mut vb) = read_metrics(b)?;
    strip_timings(&mut va);
    strip_timings(&mut vb);
    if va == vb {
        println!("{} and {} are identical apart from timings", fa.display(), fb.display());
        Ok(())
    } else {
        let mut diffs = Vec::new();
        diff_paths(&va, &vb, "", &mut diffs);
        for d in diffs.iter().take(20) {
            println!("  differs: {d}");
        }
        Err(format!("{} and {} differ in {} place(s)", fa.display(), fb.display(), diffs.len())
            .into())
    }
}

fn diff_paths(a: &Value, b: &Value, path: &str, out: &mut Vec<String>) {
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            let mut keys: Vec<&String> = x.keys().chain(y.keys()).collect();
            keys.sort();
            keys.dedup();
            for k in keys {
                let p = format!("{path}.{k}");
                match (x.get(k), y.get(k)) {
                    (Some(u), Some(v)) => diff_paths(u, v, &p, out),
                    _ => out.push(p),
                }
            }
        }
        (Value::Array(x), Value::Array(y)) if x.len() == y.len() => {
            for (i, (u, v)) in x.iter().zip(y).enumerate() {
                diff_paths(u, v, &format!("{path}[{i}]"), out);
            }
        }
        _ if a != b => out.push(format!("{path}: {a} vs {b}")),
        _ => {}
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    fn row(v: Value) -> Row {
        v.as_object().unwrap().clone()
    }

    #[test]
    fn summaries_give_mean_and_population_std() {
        let rows = vec![
            row(json!({"seed": 0, "success_rate": 0.9, "train_seconds": 10.0, "name": "x"})),
            row(json!({"seed": 1, "success_rate": 1.0, "train_seconds": 14.0})),
        ];
        let s = summarise(&rows);
        assert!((s["success_rate"].as_f64().unwrap() - 0.95).abs() < 1e-12);
        assert!((s["success_rate_std"].as_f64().unwrap() - 0.05).abs() < 1e-12);
        assert!((s["train_seconds"].as_f64().unwrap() - 12.0).abs() < 1e-12);
        assert_eq!(s["seeds"], json!(2));
        assert!(!s.contains_key("seed") && !s.contains_key("name"));
        assert_eq!(s["per_seed"].as_array().unwrap().len(), 2);
    }

    #[test]
    fn tables_aggregate_seeds_across_runs() {
        let run = |seed: u64, sr: f64| {
            Value::Object(metrics_json(
                "avoiding",
                "avoiding",
                &[seed],
                &[
                    (
                        "beso".into(),
                        vec![row(json!({"seed": seed, "success_rate": sr, "task_entropy": 0.8}))],
                    ),
                    ("vdd-beso".into(), vec![row(json!({"seed": seed, "success_rate": 0.5}))]),
                ],
            ))
        };
        let mut notes = Vec::new();
        let rows = collect_rows(&[run(0, 0.9), run(1, 0.7)], &mut notes);
        assert_eq!(rows.len(), 2);
        assert_eq!(rows[0].0, "beso", "method order is kept");
        assert_eq!(rows[0].1.len(), 2);
        let table = markdown_table(&rows, &columns_for("avoiding"));
        assert!(table.contains("| beso | 2 | 0.800 ± 0.100 | 0.800 ± 0.000 | – | – |"), "{table}");
        assert!(table.contains("| vdd-beso | 2 | 0.500 ± 0.000 |"), "{table}");
        assert!(notes.is_empty());
        // The same seed twice: the later run wins, with a note.
        let rows = collect_rows(&[run(0, 0.9), run(0, 0.1)], &mut notes);
        assert_eq!(rows[0].1.len(), 1);
        assert_eq!(rows[0].1[0]["success_rate"], json!(0.1));
        assert_eq!(notes.len(), 2);
    }

    #[test]
    fn timings_are_stripped_for_comparison() {
        let mut a = json!({"methods": {"beso": {"success_rate": 0.9, "us_per_action": 12.0,
            "us_per_action_std": 1.0, "per_seed": [{"train_seconds": 3.0, "task_entropy": 0.5}]}}});
        strip_timings(&mut a);
        assert_eq!(
            a,
            json!({"methods": {"beso": {"success_rate": 0.9, "per_seed": [{"task_entropy": 0.5}]}}})
        );
        let mut d = Vec::new();
        diff_paths(&json!({"a": 1, "b": [1, 2]}), &json!({"a": 1, "b": [1, 3]}), "", &mut d);
        assert_eq!(d, vec![".b[1]: 2 vs 3"]);
    }

    #[test]
    fn tables_come_from_run_directories() {
        let root = std::env::temp_dir().join(format!("xtask-table-{}", std::process::id()));
        let write = |dir: &str, seed: u64, sr: f64| {
            let d = root.join(dir);
            std::fs::create_dir_all(&d).unwrap();
            let m = metrics_json(
                "avoiding",
                "avoiding",
                &[seed],
                &[("beso".into(), vec![row(json!({"seed": seed, "success_rate": sr}))])],
            );
            std::fs::write(d.join("metrics.json"), Value::Object(m).to_string()).unwrap();
        };
        write("avoiding/seed0", 0, 0.5);
        write("avoiding/seed1", 1, 0.7);
        std::fs::create_dir_all(root.join("cache/teachers")).unwrap();
        let groups = find_runs(&root);
        assert_eq!(groups.len(), 1, "the cache is skipped");
        assert_eq!(groups[0].1.len(), 2);
        let text = table_text(&groups[0].1).unwrap();
        assert!(text.contains("| beso | 2 | 0.600 ± 0.100 |"), "{text}");
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn cells_format_mean_and_std() {
        assert_eq!(fmt_cell(&[], 2), "–");
        assert_eq!(fmt_cell(&[0.5], 2), "0.50");
        assert_eq!(fmt_cell(&[1.0, 3.0], 1), "2.0 ± 1.0");
    }
}
