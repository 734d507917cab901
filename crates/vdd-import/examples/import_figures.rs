//! The `bench import` figures of the BESO/D3IL and `TransformerForDiffusion` fixtures:
//! `max_abs_diff` against PyTorch, `rows_per_s` of our forward at batch 1024 on this thread,
//! and the `torch_rows_per_s` the fixture scripts recorded.
//!
//! ```text
//! cargo run --release -p vdd-import --example import_figures
//! ```

use std::path::PathBuf;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let dir = PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/import");
    println!(
        "{:<20} {:>13} {:>12} {:>16} {:>6}",
        "fixture", "max_abs_diff", "rows_per_s", "torch_rows_per_s", "ratio"
    );
    let row = |name: &str, diff: f64, ours: f64, torch: f64| {
        println!("{name:<20} {diff:>13.2e} {ours:>12.0} {torch:>16.0} {:>6.2}", ours / torch);
    };
    for name in vdd_import::BESO_FIXTURES {
        let (report, mut teacher) = vdd_import::check_beso_fixture(&dir, name)?;
        let ours = vdd_import::beso_rows_per_s(&mut teacher, 1024, 2.0)?;
        row(name, report.max_abs_diff(), ours, report.torch_rows_per_s);
    }
    for name in vdd_import::DP_TRANSFORMER_FIXTURES {
        let (diff, torch, mut net) = vdd_import::check_dp_transformer_fixture(&dir, name)?;
        let ours = vdd_import::dp_transformer_rows_per_s(&mut net, 1024, 2.0)?;
        row(name, diff, ours, torch);
    }
    Ok(())
}
