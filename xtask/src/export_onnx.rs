//! `cargo xtask export-onnx MODEL --out policy.onnx`: a saved policy as an ONNX graph
//! (`vdd_onnx`: input `obs`, outputs `log_gating`, `means`, `scale_tril`).

use std::path::PathBuf;

/// The command line of `export-onnx`.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// The saved policy (a `.safetensors` file written by `Moe::save`).
    pub model: PathBuf,
    /// Where to write the ONNX model.
    #[arg(long, default_value = "policy.onnx")]
    pub out: PathBuf,
}

/// Writes the graph and says where.
pub fn run(args: &Args) -> crate::XResult {
    vdd_onnx::export_file(&args.model, &args.out)?;
    println!(
        "wrote {} (input `obs`; outputs `log_gating`, `means`, `scale_tril`; see vdd_onnx's docs)",
        args.out.display()
    );
    Ok(())
}
