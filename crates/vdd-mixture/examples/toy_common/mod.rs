//! The paper's 2-D toy of the mixture examples: 8 modes on a circle of radius 2, isotropic
//! std 0.5, equal weights, 5000 samples, one constant state `s = 0` (1-D) — its exact density
//! and samples. (The consistency crate's examples carry the same toy, with the k-NN metrics of
//! samplers without a density.)

use faer::Mat;
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
