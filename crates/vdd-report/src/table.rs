//! Markdown tables of per-seed rows: one line per method, `mean ± std` over seeds per column.

use std::path::{Path, PathBuf};

use serde_json::Value;

use crate::metrics::{Row, collect_rows, find_runs, mean_std, read_metrics};
use crate::{Error, Result};

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

impl Column {
    /// The column of `key`, headed `header`, with `digits` decimals.
    pub const fn new(key: &'static str, header: &'static str, digits: usize) -> Self {
        Column { key, header, digits }
    }
}

const fn col(key: &'static str, header: &'static str, digits: usize) -> Column {
    Column::new(key, header, digits)
}

/// The columns of a task's table, by the task's name in `metrics.json` (the experiment layer
/// knows its tasks; this crate knows none).
pub type ColumnsOf<'a> = &'a dyn Fn(&str) -> Vec<Column>;

/// The budget columns (`--budgets` of `cargo xtask table`): optimiser steps, batch and their
/// product ([`crate::budget::samples`]) of a method's own training, and the configurations
/// tried on the tuning seeds (the wall clock is the task's `train s` column). Their cells show
/// the value when every seed agrees, else the range ([`budget_cell`]).
///
/// ```
/// let keys: Vec<_> = vdd_report::table::budget_columns().iter().map(|c| c.key).collect();
/// assert_eq!(keys, ["train_steps", "train_batch", "train_samples", "tuning_configs"]);
/// ```
pub fn budget_columns() -> Vec<Column> {
    BUDGET_KEYS
        .iter()
        .zip(["train steps", "batch", "steps × batch", "configs tried"])
        .map(|(&k, h)| col(k, h, 0))
        .collect()
}

/// The keys of [`budget_columns`].
pub const BUDGET_KEYS: [&str; 4] =
    ["train_steps", "train_batch", "train_samples", "tuning_configs"];

/// A budget cell: the value when all agree, `min–max` otherwise, `–` when missing.
///
/// ```
/// use vdd_report::table::budget_cell;
/// assert_eq!(budget_cell(&[96000.0, 96000.0]), "96000");
/// assert_eq!(budget_cell(&[1.0, 3.0]), "1–3");
/// assert_eq!(budget_cell(&[]), "–");
/// ```
pub fn budget_cell(xs: &[f64]) -> String {
    let lo = xs.iter().copied().fold(f64::INFINITY, f64::min);
    let hi = xs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    match xs.len() {
        0 => "–".into(),
        _ if lo == hi => format!("{lo:.0}"),
        _ => format!("{lo:.0}–{hi:.0}"),
    }
}

/// `mean ± std` (just the mean for one seed, `–` when missing).
///
/// ```
/// use vdd_report::table::fmt_cell;
/// assert_eq!(fmt_cell(&[1.0, 3.0], 1), "2.0 ± 1.0");
/// assert_eq!(fmt_cell(&[0.5], 2), "0.50");
/// ```
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
///
/// ```
/// use serde_json::json;
/// use vdd_report::table::{Column, markdown_table};
/// let row = json!({"seed": 0, "success_rate": 0.9}).as_object().unwrap().clone();
/// let table = markdown_table(&[("em".into(), vec![row])], &[Column::new("success_rate", "success rate", 3)]);
/// assert!(table.starts_with("| method | seeds | success rate |"));
/// assert!(table.contains("| em | 1 | 0.900 |"));
/// ```
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
            let xs: Vec<f64> = per_seed
                .iter()
                .filter_map(|r| match c.key {
                    "train_samples" => crate::budget::samples(r),
                    k => r.get(k)?.as_f64(),
                })
                .collect();
            let cell = if BUDGET_KEYS.contains(&c.key) {
                budget_cell(&xs)
            } else {
                fmt_cell(&xs, c.digits)
            };
            s.push_str(&format!(" {cell} |"));
        }
        s.push('\n');
    }
    s
}

/// A table over several runs: the markdown text and notes about how the runs were merged.
#[derive(Debug, Clone, PartialEq)]
pub struct Table {
    /// A `## recipe (task)` heading, the table, and a line naming the runs.
    pub text: String,
    /// Notes such as a `(method, seed)` found in two runs (the later one is used).
    pub notes: Vec<String>,
}

/// The mean ± std table over every seed found in the runs at `paths` (run directories or
/// their `metrics.json`), which must be of one task: the task's `columns`, then `extra` ones
/// (e.g. [`budget_columns`]).
///
/// ```no_run
/// use vdd_report::table::{Column, budget_columns, table_of_runs};
/// let columns = |_task: &str| vec![Column::new("success_rate", "success rate", 3)];
/// let table = table_of_runs(&["results/avoiding/run1".into()], &columns, &budget_columns())?;
/// print!("{}", table.text);
/// # Ok::<(), vdd_report::Error>(())
/// ```
pub fn table_of_runs(paths: &[PathBuf], columns: ColumnsOf<'_>, extra: &[Column]) -> Result<Table> {
    let mut values = Vec::new();
    let mut tasks: Vec<String> = Vec::new();
    let mut recipes: Vec<String> = Vec::new();
    for p in paths {
        let (file, v) = read_metrics(p)?;
        if v.get("methods").and_then(Value::as_object).is_none() {
            return Err(Error::NoMethods { path: file });
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
        return Err(Error::MixedTasks { tasks });
    }
    let task = tasks.first().cloned().unwrap_or_default();
    let mut notes = Vec::new();
    let rows = collect_rows(&values, &mut notes);
    let mut text = format!("## {} ({task})\n\n", recipes.join(" + "));
    let mut columns = columns(&task);
    columns.extend_from_slice(extra);
    text.push_str(&markdown_table(&rows, &columns));
    text.push_str(&format!(
        "\nmean ± std over seeds (population std); from {}\n",
        paths.iter().map(|p| p.display().to_string()).collect::<Vec<_>>().join(", ")
    ));
    Ok(Table { text, notes })
}

/// One [`table_of_runs`] per recipe over every run under `results`
/// (`results/<recipe>/<run>/metrics.json`, [`find_runs`]), each followed by an empty line;
/// empty text when there is none.
pub fn tables_of_all_runs(
    results: &Path,
    columns: ColumnsOf<'_>,
    extra: &[Column],
) -> Result<Table> {
    let mut all = Table { text: String::new(), notes: Vec::new() };
    for (_, runs) in find_runs(results) {
        let Table { text, notes } = table_of_runs(&runs, columns, extra)?;
        all.text.push_str(&text);
        all.text.push('\n');
        all.notes.extend(notes);
    }
    Ok(all)
}

#[cfg(test)]
mod tests;
