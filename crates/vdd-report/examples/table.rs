//! The mean ± std table of one or more runs, and whether the first two agree apart from
//! timings.
//!
//! ```sh
//! cargo run -p vdd-report --example table -- results/toy-gmm/RUN_A results/toy-gmm/RUN_B
//! ```

use std::path::PathBuf;

use vdd_report::compare::compare_runs;
use vdd_report::table::table_of_runs;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let runs: Vec<PathBuf> = std::env::args_os().skip(1).map(PathBuf::from).collect();
    if runs.is_empty() {
        return Err(
            "usage: table RUN_DIR [RUN_DIR...] (run directories or their metrics.json)".into()
        );
    }
    let table = table_of_runs(&runs)?;
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
