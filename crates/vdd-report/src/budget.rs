//! Training budgets in the per-seed rows: `train_steps` (optimiser steps), `train_batch` (rows
//! per step), `train_samples` (their product, plus `train_prefit_samples` when the student
//! starts from a fit of its own; the budget compared) and `train_role`
//! (`"teacher"`: a teacher's own budget; `"student"`: a method trained from a teacher or the
//! data, whose budget must equal every other student's in a comparison).

use std::collections::BTreeSet;

use serde_json::Value;

use crate::metrics::Row;

/// A training budget: optimiser steps of a given batch size (the rule is in
/// docs/avoiding-tuning.md, "Budgets": every student gets the same `steps · batch`).
///
/// ```
/// use vdd_report::budget::{Budget, BudgetRole};
/// let b = Budget::student(60_000, 128);
/// assert_eq!(b.role, BudgetRole::Student);
/// assert_eq!(b.fields()["train_samples"], serde_json::json!(7_680_000));
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Budget {
    /// Optimiser steps (of the experts' or the network's parameters; a gating's steps, as many
    /// or fewer, are not counted apart).
    pub steps: u64,
    /// Rows (states, or state-action pairs) per step.
    pub batch: usize,
    /// A teacher's budget (its own) or a student's (equal across a comparison's students).
    pub role: BudgetRole,
    /// Rows processed by the optimiser steps of a fit the training starts from (EM on the
    /// teacher's samples before VDD: its expert steps × its batch), counted in
    /// `train_samples`; 0 without one.
    pub prefit_samples: u64,
}

/// Whose budget a [`Budget`] is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum BudgetRole {
    /// A teacher, trained on the data (its rows, e.g. `beso`, `beso-1`).
    Teacher,
    /// A student, trained from a teacher or the data (VDD, CD, CTM, EM, IMC).
    Student,
}

impl Budget {
    /// A student's budget.
    pub fn student(steps: u64, batch: usize) -> Self {
        Self { steps, batch, role: BudgetRole::Student, prefit_samples: 0 }
    }

    /// A teacher's budget.
    pub fn teacher(steps: u64, batch: usize) -> Self {
        Self { steps, batch, role: BudgetRole::Teacher, prefit_samples: 0 }
    }

    /// The budget with `samples` more rows of a fit the training starts from (`train_samples`
    /// counts them; `train_prefit_samples` says how many).
    ///
    /// ```
    /// use vdd_report::budget::Budget;
    /// // 30,000 VDD steps of 128 after 500 EM iterations × 30 expert steps of 256 pairs.
    /// let b = Budget::student(30_000, 128).with_prefit(500 * 30 * 256);
    /// assert_eq!(b.fields()["train_samples"], serde_json::json!(7_680_000));
    /// assert_eq!(b.fields()["train_prefit_samples"], serde_json::json!(3_840_000));
    /// ```
    pub fn with_prefit(self, samples: u64) -> Self {
        Self { prefit_samples: self.prefit_samples.saturating_add(samples), ..self }
    }

    /// Its [`budget_fields`], with `train_prefit_samples` when there is a fit to start from.
    pub fn fields(&self) -> Row {
        let mut r = budget_fields(self.steps, self.batch, self.role == BudgetRole::Student);
        if self.prefit_samples > 0 {
            let own = self.steps.saturating_mul(self.batch as u64);
            r.insert("train_samples".into(), Value::from(own.saturating_add(self.prefit_samples)));
            r.insert("train_prefit_samples".into(), Value::from(self.prefit_samples));
        }
        r
    }
}

/// The budget fields of a row.
///
/// ```
/// let f = vdd_report::budget::budget_fields(60_000, 128, true);
/// assert_eq!(f["train_samples"], serde_json::json!(7_680_000));
/// assert_eq!(f["train_role"], "student");
/// ```
pub fn budget_fields(steps: u64, batch: usize, student: bool) -> Row {
    let mut r = Row::new();
    r.insert("train_steps".into(), Value::from(steps));
    r.insert("train_batch".into(), Value::from(batch));
    r.insert("train_samples".into(), Value::from(steps.saturating_mul(batch as u64)));
    r.insert("train_role".into(), Value::from(if student { "student" } else { "teacher" }));
    r
}

/// A row's `train_samples`, or `train_steps · train_batch` for rows written before it.
///
/// ```
/// use serde_json::json;
/// let old = json!({"train_steps": 4000, "train_batch": 256}).as_object().unwrap().clone();
/// assert_eq!(vdd_report::budget::samples(&old), Some(1_024_000.0));
/// ```
pub fn samples(row: &Row) -> Option<f64> {
    row.get("train_samples")
        .and_then(Value::as_f64)
        .or_else(|| Some(row.get("train_steps")?.as_f64()? * row.get("train_batch")?.as_f64()?))
}

/// `None` when every student row (`train_role = "student"`) of `rows` has the same
/// `train_samples`; else a message naming each student's `steps × batch`.
///
/// ```
/// use serde_json::json;
/// use vdd_report::budget::{budget_fields, unequal_budgets};
/// let rows = |cd_steps| vec![
///     ("beso".to_string(), vec![budget_fields(96_000, 256, false)]),
///     ("cd".to_string(), vec![budget_fields(cd_steps, 256, true)]),
///     ("vdd-beso".to_string(), vec![budget_fields(60_000, 128, true)]),
/// ];
/// assert_eq!(unequal_budgets(&rows(30_000)), None);
/// let w = unequal_budgets(&rows(4_000)).unwrap();
/// assert!(w.contains("cd 4000 × 256 = 1024000") && w.contains("vdd-beso"), "{w}");
/// ```
pub fn unequal_budgets(rows: &[(String, Vec<Row>)]) -> Option<String> {
    let mut seen = BTreeSet::new();
    let mut parts = Vec::new();
    for (label, per_seed) in rows {
        let students = per_seed.iter().filter(|r| r.get("train_role") == Some(&"student".into()));
        let mut mine = BTreeSet::new();
        for r in students {
            let Some(s) = samples(r) else { continue };
            if mine.insert(s as u64) {
                let n = |k: &str| r.get(k).and_then(Value::as_u64).unwrap_or(0);
                let (steps, batch) = (n("train_steps"), n("train_batch"));
                let prefit = match n("train_prefit_samples") {
                    0 => String::new(),
                    p => format!(" + {p} (fit)"),
                };
                parts.push(format!("{label} {steps} × {batch}{prefit} = {}", s as u64));
            }
        }
        seen.extend(mine);
    }
    (seen.len() > 1)
        .then(|| format!("the students' optimiser steps × batch differ: {}", parts.join(", ")))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn teachers_and_rows_without_budgets_do_not_count() {
        let mut no_role = budget_fields(1, 1, true);
        no_role.remove("train_role");
        let rows = vec![
            ("beso".to_string(), vec![budget_fields(96_000, 256, false)]),
            ("old".to_string(), vec![no_role, Row::new()]),
            ("em".to_string(), vec![budget_fields(30_000, 256, true)]),
            ("vdd".to_string(), vec![budget_fields(60_000, 128, true); 3]),
        ];
        assert_eq!(unequal_budgets(&rows), None);
        let mut uneven = rows.clone();
        uneven[3].1[2] = budget_fields(60_000, 64, true);
        let w = unequal_budgets(&uneven).unwrap();
        assert!(w.contains("vdd 60000 × 64 = 3840000"), "{w}");
        assert!(!w.contains("beso"), "{w}");
    }

    #[test]
    fn a_fit_to_start_from_counts_in_the_budget() {
        let half = Budget::student(30_000, 128);
        let rows = |b: Budget| {
            vec![
                ("cd".to_string(), vec![budget_fields(30_000, 256, true)]),
                ("vdd".to_string(), vec![b.fields()]),
            ]
        };
        let w = unequal_budgets(&rows(half)).unwrap();
        assert!(w.contains("vdd 30000 × 128 = 3840000"), "{w}");
        assert_eq!(unequal_budgets(&rows(half.with_prefit(3_840_000))), None);
        let w = unequal_budgets(&rows(half.with_prefit(1_000))).unwrap();
        assert!(w.contains("vdd 30000 × 128 + 1000 (fit) = 3841000"), "{w}");
        assert!(!half.fields().contains_key("train_prefit_samples"));
    }
}
