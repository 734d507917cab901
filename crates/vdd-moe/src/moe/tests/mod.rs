//! Tests of the mixture: fixtures and independent f64 references here, the tests by concern
//! in the submodules.

use std::collections::BTreeMap;

use faer::{Mat, MatRef};
use vdd_core::{Affine, CoreError, Policy};
use vdd_data::DeploySpec;
use vdd_nn::{Activation, Module, Parameters};

use super::*;
use crate::DeployedPolicy;
use crate::error::MoeError;
use crate::experts::{DiagonalExpert, ExpertKind, FullExpert};

// ---------------------------------------------------------------------------------------
// Fixtures and independent f64 references.
// ---------------------------------------------------------------------------------------

const OUT_LAYER: &str = "layers.2"; // input layer, one residual block, output layer

fn small_net() -> NetworkConfig {
    NetworkConfig { hidden_dim: 8, num_blocks: 1, activation: Activation::Mish }
}

fn config(
    state_dim: usize,
    action_dim: usize,
    kind: ExpertKind,
    gating: GatingKind,
    shared: bool,
) -> MoeConfig {
    MoeConfig {
        expert_kind: kind,
        experts_network: small_net(),
        shared_trunk: shared,
        gating,
        gating_network: small_net(),
        ..MoeConfig::toy(state_dim, action_dim, 3)
    }
}

/// Every combination of family, trunk and gating.
fn all_configs(state_dim: usize, action_dim: usize) -> Vec<MoeConfig> {
    let mut v = Vec::new();
    for kind in [ExpertKind::Diagonal, ExpertKind::Full] {
        for shared in [true, false] {
            for gating in [GatingKind::Learned, GatingKind::Uniform] {
                v.push(config(state_dim, action_dim, kind, gating, shared));
            }
        }
    }
    v
}

/// Calls `f(z, c, &mut bias)` for every output bias of the experts' networks, where `z` is
/// the expert and `c` the index into its raw outputs (shared trunk or separate networks).
fn edit_expert_bias(moe: &mut Moe, mut f: impl FnMut(usize, usize, &mut f32)) {
    let r = moe.expert().raw_dim();
    moe.expert_networks_mut().visit_params_mut("", &mut |name, p| {
        if name == format!("{OUT_LAYER}.bias") {
            for (k, b) in p.value.iter_mut().enumerate() {
                f(k / r, k % r, b);
            }
        } else if let Some(z) = name.strip_suffix(&format!(".{OUT_LAYER}.bias")) {
            let z: usize = z.parse().unwrap();
            for (c, b) in p.value.iter_mut().enumerate() {
                f(z, c, b);
            }
        }
    });
}

/// Moves the experts apart, varies their scales and correlations, and makes the gating
/// clearly non-uniform, so that mistakes in weighting or indexing cannot hide.
fn spread(moe: &mut Moe) {
    let d = moe.config().action_dim;
    let zc = moe.num_experts() as f32;
    edit_expert_bias(moe, |z, c, b| {
        if c < d {
            let sign = if c % 2 == 0 { 1.0 } else { -0.6 };
            *b += 1.5 * sign * (z as f32 - 0.5 * (zc - 1.0));
        } else {
            *b += 0.5 * ((z * 3 + c) as f32).sin();
        }
    });
    if let Some(g) = moe.gating_network_mut() {
        g.output_layer_mut().bias.value =
            (0..g.out_dim()).map(|z| [0.9, 0.0, -0.8, 0.3][z % 4]).collect();
    }
}

fn normalizers(state_dim: usize, action_dim: usize) -> (Affine, Affine) {
    let obs = Affine::new(
        (0..state_dim).map(|i| 0.3 * i as f32 - 0.2).collect(),
        (0..state_dim).map(|i| 1.5 + 0.5 * i as f32).collect(),
    )
    .unwrap();
    let act = Affine::new(
        (0..action_dim).map(|i| 1.0 - 1.5 * i as f32).collect(),
        (0..action_dim).map(|i| [3.0, 0.5, 2.0][i % 3]).collect(),
    )
    .unwrap();
    (obs, act)
}

fn built(cfg: MoeConfig, seed: u64) -> Moe {
    let (sd, ad) = (cfg.state_dim, cfg.action_dim);
    let mut moe = Moe::from_config(cfg, seed).unwrap();
    spread(&mut moe);
    let (o, a) = normalizers(sd, ad);
    moe.set_normalizers(Some(o), Some(a)).unwrap();
    moe
}

fn obs_batch(n: usize, state_dim: usize) -> Mat<f32> {
    Mat::from_fn(n, state_dim, |i, j| ((i * 5 + j * 3) % 7) as f32 * 0.4 - 1.1)
}

fn normalized(m: MatRef<'_, f32>, norm: &Affine) -> Mat<f32> {
    Mat::from_fn(m.nrows(), m.ncols(), |i, j| (m[(i, j)] - norm.offset[j]) / norm.scale[j])
}

/// `Σ = L Lᵀ` in f64.
fn covariance(l: &[f32], d: usize) -> Vec<f64> {
    let mut s = vec![0.0; d * d];
    for i in 0..d {
        for j in 0..d {
            s[i * d + j] = (0..d).map(|k| f64::from(l[i * d + k]) * f64::from(l[j * d + k])).sum();
        }
    }
    s
}

/// Inverse and log-determinant by Gauss–Jordan elimination with partial pivoting.
fn inverse_and_log_det(m: &[f64], d: usize) -> (Vec<f64>, f64) {
    let mut a = m.to_vec();
    let mut inv: Vec<f64> = (0..d * d).map(|k| if k / d == k % d { 1.0 } else { 0.0 }).collect();
    let mut log_det = 0.0;
    for c in 0..d {
        let p = (c..d).max_by(|&x, &y| a[x * d + c].abs().total_cmp(&a[y * d + c].abs())).unwrap();
        if p != c {
            for k in 0..d {
                a.swap(p * d + k, c * d + k);
                inv.swap(p * d + k, c * d + k);
            }
        }
        let piv = a[c * d + c];
        assert!(piv != 0.0, "singular covariance");
        log_det += piv.abs().ln();
        for k in 0..d {
            a[c * d + k] /= piv;
            inv[c * d + k] /= piv;
        }
        for r in 0..d {
            if r != c {
                let f = a[r * d + c];
                for k in 0..d {
                    a[r * d + k] -= f * a[c * d + k];
                    inv[r * d + k] -= f * inv[c * d + k];
                }
            }
        }
    }
    (inv, log_det)
}

fn ref_log_normal(x: &[f64], mean: &[f32], l: &[f32]) -> f64 {
    let d = x.len();
    let (inv, log_det) = inverse_and_log_det(&covariance(l, d), d);
    let diff: Vec<f64> = (0..d).map(|i| x[i] - f64::from(mean[i])).collect();
    let mut maha = 0.0;
    for i in 0..d {
        for j in 0..d {
            maha += diff[i] * inv[i * d + j] * diff[j];
        }
    }
    -0.5 * maha - 0.5 * log_det - 0.5 * d as f64 * (2.0 * std::f64::consts::PI).ln()
}

fn ref_log_sum_exp(xs: &[f64]) -> f64 {
    let m = xs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    m + xs.iter().map(|x| (x - m).exp()).sum::<f64>().ln()
}

/// `log q(z|s)` recomputed from the gating network's logits (or `log 1/Z`).
fn ref_log_gating(moe: &mut Moe, states: MatRef<'_, f32>) -> Vec<Vec<f64>> {
    let z = moe.num_experts();
    match moe.gating_network_mut() {
        None => vec![vec![(1.0 / z as f64).ln(); z]; states.nrows()],
        Some(net) => {
            let y = net.forward(states);
            (0..states.nrows())
                .map(|b| {
                    let logits: Vec<f64> = (0..z).map(|k| f64::from(y[(b, k)])).collect();
                    let lse = ref_log_sum_exp(&logits);
                    logits.iter().map(|l| l - lse).collect()
                })
                .collect()
        }
    }
}

fn assert_close(got: f64, want: f64, tol: f64, what: &str) {
    assert!((got - want).abs() <= tol, "{what}: got {got}, want {want} (tol {tol})");
}

mod acting;
mod components;
mod errors;
mod gradients;
mod hostile;
mod io;
mod io_hostile;
mod likelihood;
