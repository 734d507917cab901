//! The mean ± std table of one or more runs, and whether the first two agree apart from
//! timings.
//!
//! ```sh
//! cargo run -p vdd-report --example table -- results/toy-gmm/RUN_A results/toy-gmm/RUN_B \
//!     --columns reverse_kl,forward_kl
//! ```
//!
//! The columns are the per-seed keys after `--columns` (this crate knows no task; `cargo xtask
//! table` takes each task's own columns).

use std::path::PathBuf;

use vdd_report::compare::compare_runs;
use vdd_report::table::{Column, table_of_runs};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let keys: Vec<&'static str> = match args.iter().position(|a| a == "--columns") {
        Some(i) if i + 1 < args.len() => {
            let list = args.remove(i + 1);
            args.remove(i);
            list.split(',').map(|k| &*Box::leak(k.to_owned().into_boxed_str())).collect()
        }
        _ => vec!["success_rate", "task_entropy"],
    };
    let runs: Vec<PathBuf> = args.into_iter().map(PathBuf::from).collect();
    if runs.is_empty() {
        return Err("usage: table RUN_DIR [RUN_DIR...] [--columns key,key] (run directories \
                    or their metrics.json)"
            .into());
    }
    let columns: Vec<Column> = keys.iter().map(|k| Column::new(k, k, 3)).collect();
    let table = table_of_runs(&runs, &|_| columns.clone(), &[])?;
    print!("{}", table.text);
    for note in &table.notes {
        eprintln!("note: {note}");
    }
    if let [a, b, ..] = runs.as_slice() {
        let c = compare_runs(a, b)?;
        if c.identical() {
            println!("\n{} and {} agree apart from timings", a.display(), b.display());
        } else {
            println!("\n{} and {} differ in {} place(s):", a.display(), b.display(), c.diffs.len());
            for d in c.diffs.iter().take(20) {
                println!("  {d}");
            }
        }
    }
    Ok(())
}
