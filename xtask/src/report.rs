//! Results: `cargo xtask table` and `cargo xtask compare`, on top of `vdd-report` (which holds
//! the `metrics.json` layout, the mean ± std summaries and the tables; see
//! [`vdd_report::metrics`]). This module keeps the command lines and the printing.

use std::path::PathBuf;

use vdd_report::compare::compare_runs;
use vdd_report::table::{Table, budget_columns, table_of_runs, tables_of_all_runs};

/// The command line of `table`.
#[derive(Debug, Clone, clap::Args)]
pub struct TableArgs {
    /// Run directories (or their metrics.json), all of one task; none: every run under results/.
    #[arg(value_name = "RUN_DIR")]
    pub runs: Vec<PathBuf>,
    /// Also write the tables to FILE.
    #[arg(long, value_name = "FILE")]
    pub out: Option<PathBuf>,
    /// Add the budget columns: training steps, batch, steps × batch and configurations tried
    /// on the tuning seeds (beside the training seconds).
    #[arg(long)]
    pub budgets: bool,
}

/// `cargo xtask table [--out FILE] [RUN_DIR | metrics.json]...`: one mean ± std table over
/// every seed found in the given runs (which must be of one task). Without paths, one table
/// per recipe over every run under `results/` (the teacher cache excluded).
pub fn run_table(args: &TableArgs) -> crate::XResult {
    let (paths, out) = (&args.runs, &args.out);
    let extra = if args.budgets { budget_columns() } else { Vec::new() };
    let registry = vdd_lab::Registry::builtin();
    let columns = &|task: &str| registry.columns_of(task);
    let Table { text, notes } = if paths.is_empty() {
        tables_of_all_runs(&crate::recipe::repo_root().join("results"), columns, &extra)?
    } else {
        table_of_runs(paths, columns, &extra)?
    };
    if text.is_empty() {
        return Err("no results/<recipe>/<run>/metrics.json found; run `cargo xtask \
                    experiment <recipe>` first or pass run directories"
            .into());
    }
    notes.iter().for_each(|n| eprintln!("note: {n}"));
    print!("{text}");
    if let Some(out) = out {
        std::fs::write(out, &text).map_err(|e| format!("writing {}: {e}", out.display()))?;
        eprintln!("wrote {}", out.display());
    }
    Ok(())
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
    let c = compare_runs(&args.run_a, &args.run_b)?;
    if !c.identical() {
        return Err(c.to_string().into());
    }
    println!("{c}");
    Ok(())
}
