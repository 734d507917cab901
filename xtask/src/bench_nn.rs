//! `cargo xtask bench nn`: forward+backward throughput of a residual MLP against one bare faer
//! matmul of the same total FLOPs.
//!
//! The measurement (and what counts as FLOPs) is [`vdd_nn::bench::mlp_vs_matmul`]'s.
//!
//! ```text
//! cargo xtask bench nn [--batch 1024] [--width 256] [--blocks 2] [--reps 20]
//!                      [--activation mish] [--layer-norm]
//! ```

use vdd_nn::bench::mlp_vs_matmul;
use vdd_nn::{Activation, ResidualMlpConfig};

/// The command line of `bench nn`.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// Rows per forward/backward pass.
    #[arg(long, default_value_t = 1024)]
    pub batch: usize,
    /// Input, hidden and output width.
    #[arg(long, default_value_t = 256)]
    pub width: usize,
    /// Residual blocks.
    #[arg(long, default_value_t = 2)]
    pub blocks: usize,
    /// Timed repetitions.
    #[arg(long, default_value_t = 20)]
    pub reps: usize,
    /// Activation (as in a network configuration: mish, relu, ...).
    #[arg(long, default_value = "mish")]
    pub activation: String,
    /// With layer normalisation.
    #[arg(long)]
    pub layer_norm: bool,
}

/// Runs the benchmark and prints both rates and their ratio.
pub fn run(args: &Args) -> crate::XResult {
    let (batch, width, blocks, reps) = (args.batch, args.width, args.blocks, args.reps);
    let activation: Activation =
        serde_json::from_value(serde_json::Value::String(args.activation.clone()))
            .map_err(|e| format!("--activation: {e}"))?;
    if batch == 0 || width == 0 || reps == 0 {
        return Err("--batch, --width and --reps must be positive".into());
    }
    let (in_dim, hidden_dim, out_dim, layer_norm) = (width, width, width, args.layer_norm);
    let cfg = ResidualMlpConfig {
        in_dim,
        hidden_dim,
        num_blocks: blocks,
        out_dim,
        activation,
        layer_norm,
    };
    println!("{}", mlp_vs_matmul(&cfg, batch, reps)?.report(&cfg, batch));
    Ok(())
}
