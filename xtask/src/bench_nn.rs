//! `cargo xtask bench nn`: forward+backward throughput of a residual MLP against one bare faer
//! matmul of the same total FLOPs.
//!
//! FLOPs are those of the matrix products only: `2·n·in·out` per linear layer forward, twice
//! that backward (weight gradient and input gradient). Activations, biases and the residual
//! additions are overhead the ratio exposes.
//!
//! ```text
//! cargo xtask bench nn [--batch 1024] [--width 256] [--blocks 2] [--reps 20]
//!                      [--activation mish] [--layer-norm]
//! ```

use std::time::Instant;

use faer::linalg::matmul::matmul;
use faer::{Accum, Mat, Par};
use vdd_nn::{Activation, Module, Parameters, ResidualMlp, ResidualMlpConfig};

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

/// Smallest of a list of timings in seconds.
fn min(v: &[f64]) -> f64 {
    v.iter().copied().fold(f64::INFINITY, f64::min)
}

/// Median of a list of timings in seconds.
fn median(mut v: Vec<f64>) -> f64 {
    v.sort_by(f64::total_cmp);
    v[v.len() / 2]
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

    let cfg = ResidualMlpConfig {
        in_dim: width,
        hidden_dim: width,
        num_blocks: blocks,
        out_dim: width,
        activation,
        layer_norm: args.layer_norm,
    };
    let seeds = vdd_core::Seeds::new(0);
    let mut net = ResidualMlp::new(&cfg, &mut seeds.stream("bench-init"))?;
    let mut rng = seeds.stream("bench-data");
    let mut x = Mat::<f32>::zeros(batch, width);
    for j in 0..width {
        vdd_core::fill_standard_normal(&mut rng, x.col_as_slice_mut(j));
    }
    let mut g = Mat::<f32>::zeros(batch, width);
    for j in 0..width {
        vdd_core::fill_standard_normal(&mut rng, g.col_as_slice_mut(j));
    }

    // Matmul FLOPs of one forward pass: 2·n·in·out per linear layer; backward is twice that.
    let forward_flops: f64 = net
        .linears_mut()
        .iter()
        .map(|l| 2.0 * batch as f64 * l.in_dim() as f64 * l.out_dim() as f64)
        .sum();
    let step_flops = 3.0 * forward_flops;

    // One bare matmul with the same inner dimension and batch, widened to the same FLOPs.
    let k = width;
    let cols = (step_flops / (2.0 * batch as f64 * k as f64)).round() as usize;
    let bare_flops = 2.0 * batch as f64 * k as f64 * cols as f64;
    let a = Mat::<f32>::from_fn(batch, k, |i, j| ((i * 7 + j * 3) % 13) as f32 * 0.01);
    let b = Mat::<f32>::from_fn(k, cols, |i, j| ((i * 5 + j) % 11) as f32 * 0.01);
    let mut c = Mat::<f32>::zeros(batch, cols);

    // The two are timed alternately so that both see the same machine load; the best of
    // `reps` runs is the headline figure (least disturbed), the median is printed beside it.
    let (mut t_net, mut t_bare) = (Vec::with_capacity(reps), Vec::with_capacity(reps));
    for rep in 0..reps + 3 {
        let t = Instant::now();
        net.zero_grad();
        net.forward(x.as_ref());
        net.backward(g.as_ref());
        let dt_net = t.elapsed().as_secs_f64();
        let t = Instant::now();
        matmul(c.as_mut(), Accum::Replace, a.as_ref(), b.as_ref(), 1.0f32, Par::Seq);
        let dt_bare = t.elapsed().as_secs_f64();
        if rep >= 3 {
            t_net.push(dt_net);
            t_bare.push(dt_bare);
        }
    }
    let (best_net, best_bare) = (min(&t_net), min(&t_bare));
    let (med_net, med_bare) = (median(t_net), median(t_bare));
    let net_gflops = step_flops / best_net / 1e9;
    let bare_gflops = bare_flops / best_bare / 1e9;
    let ratio = net_gflops / bare_gflops;
    println!(
        "residual MLP {width} wide, {blocks} blocks, batch {batch}, {activation:?}{}: \
         {:.3} GFLOP per forward+backward",
        if cfg.layer_norm { ", layer norm" } else { "" },
        step_flops / 1e9
    );
    println!(
        "  forward+backward : best {:8.2} ms  {net_gflops:7.2} GFLOP/s  (median {:.2} ms)",
        best_net * 1e3,
        med_net * 1e3
    );
    println!(
        "  bare faer matmul : best {:8.2} ms  {bare_gflops:7.2} GFLOP/s  (median {:.2} ms; \
         [{batch}x{k}]·[{k}x{cols}], Par::Seq)",
        best_bare * 1e3,
        med_bare * 1e3
    );
    println!(
        "  ratio            : {ratio:.3} best-of-{reps} (median {:.3}; target >= 0.5)",
        (step_flops / med_net) / (bare_flops / med_bare)
    );
    Ok(())
}
