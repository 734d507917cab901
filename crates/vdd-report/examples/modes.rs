//! The mode histograms of a run: the share of each method's successful rollouts in each
//! behaviour mode, summed over the run's seeds, as `OUT.svg` (and `OUT.png` with `--png`),
//! for the methods named (all by default).
//!
//! ```sh
//! cargo run -p vdd-report --example modes -- results/avoiding/RUN OUT [--png] [beso vdd-beso ...]
//! ```

use std::path::PathBuf;

use vdd_report::metrics::{collect_rows, mode_shares, read_metrics};
use vdd_report::plots::mode_histograms;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut args: Vec<String> = std::env::args().skip(1).collect();
    let png = args.iter().any(|a| a == "--png");
    args.retain(|a| a != "--png");
    let [run, out, methods @ ..] = args.as_slice() else {
        return Err("usage: modes RUN_DIR OUT_STEM [--png] [METHOD...]".into());
    };
    let (_, metrics) = read_metrics(&PathBuf::from(run))?;
    let mut rows = collect_rows(&[metrics], &mut Vec::new());
    if !methods.is_empty() {
        rows.retain(|(m, _)| methods.contains(m));
        rows.sort_by_key(|(m, _)| methods.iter().position(|x| x == m));
    }
    for f in mode_histograms(&PathBuf::from(out), &mode_shares(&rows), png)? {
        println!("wrote {f}");
    }
    Ok(())
}
