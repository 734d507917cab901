//! Whether two runs agree: their `metrics.json` compared apart from wall-clock timings.

use std::path::{Path, PathBuf};

use serde_json::Value;

use crate::Result;
use crate::metrics::{is_timing_key, read_metrics};

/// Removes timing values (see [`TIMING_KEYS`](crate::metrics::TIMING_KEYS)) from a JSON
/// value, recursively.
///
/// ```
/// use serde_json::json;
/// let mut v = json!({"loss": 0.5, "train_seconds": 3.0, "per_seed": [{"us_per_action": 9.0}]});
/// vdd_report::compare::strip_timings(&mut v);
/// assert_eq!(v, json!({"loss": 0.5, "per_seed": [{}]}));
/// ```
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

/// The places where two JSON values differ, as `.key[index]` paths (with both values at a
/// leaf, the bare path where a key exists on one side only or arrays differ in length).
///
/// ```
/// use serde_json::json;
/// let d = vdd_report::compare::diff_paths(&json!({"a": 1, "b": [1, 2]}), &json!({"a": 1, "b": [1, 3]}));
/// assert_eq!(d, vec![".b[1]: 2 vs 3"]);
/// ```
pub fn diff_paths(a: &Value, b: &Value) -> Vec<String> {
    let mut out = Vec::new();
    diff_into(a, b, "", &mut out);
    out
}

fn diff_into(a: &Value, b: &Value, path: &str, out: &mut Vec<String>) {
    match (a, b) {
        (Value::Object(x), Value::Object(y)) => {
            let mut keys: Vec<&String> = x.keys().chain(y.keys()).collect();
            keys.sort();
            keys.dedup();
            for k in keys {
                let p = format!("{path}.{k}");
                match (x.get(k), y.get(k)) {
                    (Some(u), Some(v)) => diff_into(u, v, &p, out),
                    _ => out.push(p),
                }
            }
        }
        (Value::Array(x), Value::Array(y)) if x.len() == y.len() => {
            for (i, (u, v)) in x.iter().zip(y).enumerate() {
                diff_into(u, v, &format!("{path}[{i}]"), out);
            }
        }
        _ if a != b => out.push(format!("{path}: {a} vs {b}")),
        _ => {}
    }
}

/// The outcome of [`compare_runs`].
#[derive(Debug, Clone, PartialEq)]
pub struct Comparison {
    /// The first run's `metrics.json`.
    pub file_a: PathBuf,
    /// The second run's `metrics.json`.
    pub file_b: PathBuf,
    /// Where they differ apart from timings (see [`diff_paths`]); empty when identical.
    pub diffs: Vec<String>,
}

impl Comparison {
    /// Whether the runs are identical apart from timings.
    pub fn identical(&self) -> bool {
        self.diffs.is_empty()
    }
}

/// `A and B are identical apart from timings`, or the first 20 differences, one a line,
/// then `A and B differ in N place(s)` (`cargo xtask compare`).
impl std::fmt::Display for Comparison {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let (a, b) = (self.file_a.display(), self.file_b.display());
        if self.identical() {
            return write!(f, "{a} and {b} are identical apart from timings");
        }
        for d in self.diffs.iter().take(20) {
            writeln!(f, "  differs: {d}")?;
        }
        write!(f, "{a} and {b} differ in {} place(s)", self.diffs.len())
    }
}

/// Compares two runs (run directories or their `metrics.json`) apart from timings.
///
/// ```no_run
/// let c = vdd_report::compare::compare_runs("results/a".as_ref(), "results/b".as_ref())?;
/// assert!(c.identical(), "{:?}", c.diffs);
/// # Ok::<(), vdd_report::Error>(())
/// ```
pub fn compare_runs(a: &Path, b: &Path) -> Result<Comparison> {
    let (file_a, mut va) = read_metrics(a)?;
    let (file_b, mut vb) = read_metrics(b)?;
    strip_timings(&mut va);
    strip_timings(&mut vb);
    let diffs = if va == vb { Vec::new() } else { diff_paths(&va, &vb) };
    Ok(Comparison { file_a, file_b, diffs })
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde_json::json;

    #[test]
    fn timings_are_stripped_for_comparison() {
        let mut a = json!({"methods": {"beso": {"success_rate": 0.9, "us_per_action": 12.0,
            "us_per_action_std": 1.0, "per_seed": [{"train_seconds": 3.0, "task_entropy": 0.5}]}}});
        strip_timings(&mut a);
        assert_eq!(
            a,
            json!({"methods": {"beso": {"success_rate": 0.9, "per_seed": [{"task_entropy": 0.5}]}}})
        );
        let d = diff_paths(&json!({"a": 1, "b": [1, 2]}), &json!({"a": 1, "b": [1, 3]}));
        assert_eq!(d, vec![".b[1]: 2 vs 3"]);
    }

    #[test]
    fn runs_compare_from_their_directories() {
        let root = std::env::temp_dir().join(format!("vdd-report-compare-{}", std::process::id()));
        let write = |dir: &str, v: Value| {
            std::fs::create_dir_all(root.join(dir)).unwrap();
            std::fs::write(root.join(dir).join("metrics.json"), v.to_string()).unwrap();
        };
        write("a", json!({"methods": {"em": {"loss": 1.0, "train_seconds": 3.0}}}));
        write("b", json!({"methods": {"em": {"loss": 1.0, "train_seconds": 4.0}}}));
        write("c", json!({"methods": {"em": {"loss": 2.0}}}));
        let same = compare_runs(&root.join("a"), &root.join("b")).unwrap();
        assert!(same.identical());
        assert_eq!(same.file_a, root.join("a/metrics.json"));
        let differ = compare_runs(&root.join("a"), &root.join("c")).unwrap();
        assert_eq!(differ.diffs, vec![".methods.em.loss: 1.0 vs 2.0"]);
        assert!(same.to_string().ends_with("b/metrics.json are identical apart from timings"));
        let text = differ.to_string();
        assert!(text.starts_with("  differs: .methods.em.loss: 1.0 vs 2.0\n"), "{text}");
        assert!(text.ends_with("c/metrics.json differ in 1 place(s)"), "{text}");
        assert!(matches!(
            compare_runs(&root.join("missing"), &root.join("a")),
            Err(crate::Error::Read { .. })
        ));
        std::fs::remove_dir_all(&root).unwrap();
    }
}
