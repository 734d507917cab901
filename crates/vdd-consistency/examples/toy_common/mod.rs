//! The paper's 2-D toy of the consistency examples: 8 modes on a circle of radius 2,
//! isotropic std 0.5, equal weights, 5000 samples, one constant state `s = 0` (1-D) — its
//! exact density, samples, and the exact-density metrics of samplers without a density.

use faer::{Mat, MatRef};
use rand::Rng as _;
use vdd_core::Rng;
use vdd_core::gaussian::{self, LN_2PI};

pub const MODES: usize = 8;
pub const RADIUS: f32 = 2.0;
pub const STD: f32 = 0.5;
pub const DATA_POINTS: usize = 5000;

pub fn mode(k: usize) -> [f32; 2] {
    let t = 2.0 * std::f32::consts::PI * k as f32 / MODES as f32;
    [RADIUS * t.cos(), RADIUS * t.sin()]
}

/// `log p(a) = log Σ_k (1/8) N(a; μ_k, 0.5² I)`, written out directly.
pub fn log_p(a: &[f32]) -> f32 {
    let var = STD * STD;
    let terms: Vec<f32> = (0..MODES)
        .map(|k| {
            let m = mode(k);
            let d2 = (a[0] - m[0]).powi(2) + (a[1] - m[1]).powi(2);
            -(MODES as f32).ln() - 0.5 * d2 / var - var.ln() - LN_2PI
        })
        .collect();
    gaussian::log_sum_exp(&terms)
}

pub fn sample_target(n: usize, rng: &mut Rng) -> Mat<f32> {
    let mut out = Mat::zeros(n, 2);
    for i in 0..n {
        let m = mode(rng.random_range(0..MODES));
        for j in 0..2 {
            out[(i, j)] = m[j] + STD * vdd_core::standard_normal(rng);
        }
    }
    out
}

pub fn arg<T: std::str::FromStr>(args: &[String], name: &str, default: T) -> T {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .map(|v| v.parse().unwrap_or_else(|_| panic!("bad value for {name}")))
        .unwrap_or(default)
}

/// The neighbour rank of the k-nearest-neighbour estimators.
pub const KNN_K: usize = 5;

/// `ψ(n)` for a positive integer: `−γ + Σ_{j<n} 1/j`.
fn digamma(n: usize) -> f64 {
    -0.577_215_664_901_532_9 + (1..n).map(|j| 1.0 / j as f64).sum::<f64>()
}

/// Mean over the rows of `query` of `ln` of the distance to the `KNN_K`-th nearest row of
/// `reference` (skipping the row itself when `same` is set: `query` is `reference`).
fn mean_log_knn_distance(query: MatRef<'_, f32>, reference: MatRef<'_, f32>, same: bool) -> f64 {
    let (q, r) = (query.nrows(), reference.nrows());
    let rx: Vec<f32> = (0..r).map(|i| reference[(i, 0)]).collect();
    let ry: Vec<f32> = (0..r).map(|i| reference[(i, 1)]).collect();
    let mut total = 0.0f64;
    for i in 0..q {
        let (x, y) = (query[(i, 0)], query[(i, 1)]);
        // The KNN_K smallest squared distances, ascending.
        let mut best = [f32::INFINITY; KNN_K];
        for l in 0..r {
            if same && l == i {
                continue;
            }
            let d2 = (rx[l] - x).powi(2) + (ry[l] - y).powi(2);
            if d2 < best[KNN_K - 1] {
                let mut p = KNN_K - 1;
                while p > 0 && best[p - 1] > d2 {
                    best[p] = best[p - 1];
                    p -= 1;
                }
                best[p] = d2;
            }
        }
        total += 0.5 * f64::from(best[KNN_K - 1].max(1e-30)).ln();
    }
    total / q as f64
}

/// Kozachenko–Leonenko entropy `H(q) ≈ ψ(N) − ψ(k) + ln V_2 + (2/N) Σ ln ε_k(i)` of 2-D
/// samples (`V_2 = π`, `ε_k(i)` the distance to the k-th nearest other sample).
pub fn knn_entropy(samples: MatRef<'_, f32>) -> f64 {
    let n = samples.nrows();
    digamma(n) - digamma(KNN_K)
        + std::f64::consts::PI.ln()
        + 2.0 * mean_log_knn_distance(samples, samples, true)
}

/// The cross-entropy `−E_p[ln q] ≈ ψ(M) − ψ(k) + ln V_2 + (2/N) Σ ln ν_k(i)` from `N` samples
/// of `p` and `M` of `q` (`ν_k(i)` the distance from `p`-sample `i` to its k-th nearest
/// `q`-sample; Leonenko, Pronzato & Savani 2008).
pub fn knn_cross_entropy(p_samples: MatRef<'_, f32>, q_samples: MatRef<'_, f32>) -> f64 {
    digamma(q_samples.nrows()) - digamma(KNN_K)
        + std::f64::consts::PI.ln()
        + 2.0 * mean_log_knn_distance(p_samples, q_samples, false)
}

/// The mean of the exact `ln p` over the rows.
pub fn mean_log_p(samples: MatRef<'_, f32>) -> f64 {
    (0..samples.nrows()).map(|i| f64::from(log_p(&[samples[(i, 0)], samples[(i, 1)]]))).sum::<f64>()
        / samples.nrows() as f64
}

/// Reverse and forward KL of a sampler without a density against the exact toy density:
/// `KL(q‖p) = −H(q) − E_q[ln p]` and `KL(p‖q) = E_p[ln p] − E_p[ln q]`, with the exact `ln p`
/// and k-nearest-neighbour estimates of `H(q)` and `−E_p[ln q]` from `samples` of `q` and
/// `truth` of `p`.
pub fn knn_kl(samples: MatRef<'_, f32>, truth: MatRef<'_, f32>) -> (f64, f64) {
    let reverse = -knn_entropy(samples) - mean_log_p(samples);
    let forward = mean_log_p(truth) + knn_cross_entropy(truth, samples);
    (reverse, forward)
}

/// The fraction of samples nearest to each mode.
pub fn mode_histogram(samples: MatRef<'_, f32>) -> Vec<f64> {
    let n = samples.nrows();
    let mut counts = [0usize; MODES];
    for i in 0..n {
        let (mut best, mut arg) = (f32::INFINITY, 0);
        for k in 0..MODES {
            let m = mode(k);
            let d2 = (samples[(i, 0)] - m[0]).powi(2) + (samples[(i, 1)] - m[1]).powi(2);
            if d2 < best {
                (best, arg) = (d2, k);
            }
        }
        counts[arg] += 1;
    }
    counts.iter().map(|&c| c as f64 / n as f64).collect()
}

/// Mean distance of the samples to their nearest mode (true samples: about 0.63).
pub fn mean_nearest_mode_distance(samples: MatRef<'_, f32>) -> f64 {
    let n = samples.nrows();
    (0..n)
        .map(|i| {
            (0..MODES)
                .map(|k| {
                    let m = mode(k);
                    let d2 = (samples[(i, 0)] - m[0]).powi(2) + (samples[(i, 1)] - m[1]).powi(2);
                    f64::from(d2.sqrt())
                })
                .fold(f64::INFINITY, f64::min)
        })
        .sum::<f64>()
        / n as f64
}
