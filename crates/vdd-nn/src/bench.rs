//! Forward+backward throughput of a residual MLP against one bare faer matmul of the same
//! total FLOPs ([`mlp_vs_matmul`]; `cargo xtask bench nn`).
//!
//! FLOPs are those of the matrix products only: `2·n·in·out` per linear layer forward, twice
//! that backward (weight gradient and input gradient). Activations, biases and the residual
//! additions are overhead the ratio exposes.

use std::time::Instant;

use crate::gemm::matmul;
use faer::{Accum, Mat};

use crate::{Module, NnError, Parameters, ResidualMlp, ResidualMlpConfig};

/// The timings of [`mlp_vs_matmul`], in seconds.
#[derive(Debug, Clone, PartialEq)]
pub struct MlpBench {
    /// Matmul FLOPs of one forward+backward step of the MLP.
    pub step_flops: f64,
    /// FLOPs of the bare matmul `[batch x k]·[k x cols]`.
    pub bare_flops: f64,
    /// Inner dimension of the bare matmul (the MLP's width).
    pub k: usize,
    /// Columns of the bare matmul (chosen to match `step_flops`).
    pub cols: usize,
    /// Every timed forward+backward step.
    pub net: Vec<f64>,
    /// Every timed bare matmul.
    pub bare: Vec<f64>,
}

impl MlpBench {
    /// GFLOP/s of the MLP and of the bare matmul at their best runs (the least disturbed).
    pub fn best_gflops(&self) -> (f64, f64) {
        (self.step_flops / min(&self.net) / 1e9, self.bare_flops / min(&self.bare) / 1e9)
    }

    /// The MLP's rate over the bare matmul's at their medians.
    pub fn median_ratio(&self) -> f64 {
        (self.step_flops / median(&self.net)) / (self.bare_flops / median(&self.bare))
    }

    /// The benchmark's text (`cargo xtask bench nn`): the network, both rates at their best
    /// and median runs, and their ratio against the target of 0.5. `cfg` and `batch` are the
    /// measurement's.
    pub fn report(&self, cfg: &ResidualMlpConfig, batch: usize) -> String {
        let (net_gflops, bare_gflops) = self.best_gflops();
        let (k, cols, reps) = (self.k, self.cols, self.net.len());
        let ms = |v: &[f64]| (min(v) * 1e3, median(v) * 1e3);
        let ((net_best, net_median), (bare_best, bare_median)) = (ms(&self.net), ms(&self.bare));
        format!(
            "residual MLP {} wide, {} blocks, batch {batch}, {:?}{}: {:.3} GFLOP per \
             forward+backward\n  forward+backward : best {net_best:8.2} ms  {net_gflops:7.2} \
             GFLOP/s  (median {net_median:.2} ms)\n  bare faer matmul : best {bare_best:8.2} ms  \
             {bare_gflops:7.2} GFLOP/s  (median {bare_median:.2} ms; [{batch}x{k}]·[{k}x{cols}], \
             Par::Seq)\n  ratio            : {:.3} best-of-{reps} (median {:.3}; target >= 0.5)",
            cfg.hidden_dim,
            cfg.num_blocks,
            cfg.activation,
            if cfg.layer_norm { ", layer norm" } else { "" },
            self.step_flops / 1e9,
            net_gflops / bare_gflops,
            self.median_ratio()
        )
    }
}

/// Smallest of a list of timings.
pub fn min(v: &[f64]) -> f64 {
    v.iter().copied().fold(f64::INFINITY, f64::min)
}

/// Median (upper) of a list of timings (NaN when empty).
pub fn median(v: &[f64]) -> f64 {
    let mut v = v.to_vec();
    v.sort_by(f64::total_cmp);
    v.get(v.len() / 2).copied().unwrap_or(f64::NAN)
}

/// Times `reps` forward+backward steps of a residual MLP of `cfg` on `batch` seeded normal
/// rows, alternating with a bare single-threaded matmul of the same FLOPs (so that both see the
/// same machine load), after 3 untimed rounds.
pub fn mlp_vs_matmul(
    cfg: &ResidualMlpConfig,
    batch: usize,
    reps: usize,
) -> Result<MlpBench, NnError> {
    let seeds = vdd_core::Seeds::new(0);
    let mut net = ResidualMlp::new(cfg, &mut seeds.stream("bench-init"))?;
    let mut rng = seeds.stream("bench-data");
    let mut x = Mat::<f32>::zeros(batch, cfg.in_dim);
    for j in 0..cfg.in_dim {
        vdd_core::fill_standard_normal(&mut rng, x.col_as_slice_mut(j));
    }
    let mut g = Mat::<f32>::zeros(batch, cfg.out_dim);
    for j in 0..cfg.out_dim {
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
    let k = cfg.hidden_dim;
    let cols = (step_flops / (2.0 * batch as f64 * k as f64)).round() as usize;
    let bare_flops = 2.0 * batch as f64 * k as f64 * cols as f64;
    let a = Mat::<f32>::from_fn(batch, k, |i, j| ((i * 7 + j * 3) % 13) as f32 * 0.01);
    let b = Mat::<f32>::from_fn(k, cols, |i, j| ((i * 5 + j) % 11) as f32 * 0.01);
    let mut c = Mat::<f32>::zeros(batch, cols);
    let (mut t_net, mut t_bare) = (Vec::with_capacity(reps), Vec::with_capacity(reps));
    for rep in 0..reps + 3 {
        let t = Instant::now();
        net.zero_grad();
        net.forward(x.as_ref());
        net.backward(g.as_ref());
        let dt_net = t.elapsed().as_secs_f64();
        let t = Instant::now();
        matmul(c.as_mut(), Accum::Replace, a.as_ref(), b.as_ref(), 1.0f32);
        let dt_bare = t.elapsed().as_secs_f64();
        if rep >= 3 {
            t_net.push(dt_net);
            t_bare.push(dt_bare);
        }
    }
    Ok(MlpBench { step_flops, bare_flops, k, cols, net: t_net, bare: t_bare })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Activation;

    #[test]
    fn the_bare_matmul_matches_the_mlps_flops() {
        let cfg = ResidualMlpConfig {
            in_dim: 8,
            hidden_dim: 8,
            num_blocks: 2,
            out_dim: 8,
            activation: Activation::Mish,
            layer_norm: false,
        };
        let b = mlp_vs_matmul(&cfg, 16, 4).unwrap();
        // Six 8x8 layers (input, two per block, output): 3 · 6 · 2 · 16 · 64 FLOPs per step.
        assert_eq!(b.step_flops, 3.0 * 6.0 * 2.0 * 16.0 * 64.0);
        assert_eq!((b.k, b.cols, b.bare_flops), (8, 144, b.step_flops));
        assert_eq!((b.net.len(), b.bare.len()), (4, 4));
        assert_eq!(median(&[3.0, 1.0, 2.0]), 2.0);
        assert_eq!(min(&[3.0, 1.0, 2.0]), 1.0);
        let report = b.report(&cfg, 16);
        assert!(report.starts_with(
            "residual MLP 8 wide, 2 blocks, batch 16, Mish: 0.000 GFLOP per forward+backward\n"
        ));
        assert!(report.contains("[16x8]·[8x144], Par::Seq)") && report.lines().count() == 4);
    }
}
