//! Weight and bias initialisers from a seeded RNG, with PyTorch's formulas
//! (`torch.nn.init`): orthogonal, Xavier (Glorot), Kaiming (He), uniform, and PyTorch's
//! default `nn.Linear` initialisation.
//!
//! A weight of shape `[out, in]` has `fan_in = in` and `fan_out = out`.
//!
//! ```
//! use vdd_nn::init::{BiasInit, Init};
//! use vdd_nn::{Activation, ResidualMlp, ResidualMlpConfig};
//! let cfg = ResidualMlpConfig { in_dim: 3, hidden_dim: 16, num_blocks: 1, out_dim: 2,
//!                               activation: Activation::Mish, layer_norm: false };
//! let mut rng = vdd_core::Seeds::new(0).stream("init");
//! let mut net = ResidualMlp::new(&cfg, &mut rng).unwrap();
//! net.init_weights(Init::Orthogonal { gain: 1.0 }, &mut rng).unwrap();
//! net.init_biases(BiasInit::Zero, &mut rng).unwrap();
//! net.output_layer_mut().init_bias(BiasInit::Uniform { low: -0.5, high: 0.5 }, &mut rng).unwrap();
//! ```

use faer::Mat;
use rand::Rng as _;
use serde::{Deserialize, Serialize};

use crate::activation::Activation;
use crate::error::NnError;

/// How to initialise a weight matrix `[out, in]`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Init {
    /// PyTorch's `nn.Linear` default, `kaiming_uniform_(a=√5)`: `U(−1/√fan_in, 1/√fan_in)`.
    #[default]
    Default,
    /// A (semi-)orthogonal matrix times `gain`, from the QR decomposition of a Gaussian matrix
    /// with the signs of `R`'s diagonal folded into `Q` (`torch.nn.init.orthogonal_`): rows
    /// orthonormal when `out ≤ in`, columns orthonormal otherwise.
    Orthogonal {
        /// Scale of the matrix.
        gain: f32,
    },
    /// `U(−b, b)` with `b = gain·√(6 / (fan_in + fan_out))` (`xavier_uniform_`).
    XavierUniform {
        /// Scale.
        gain: f32,
    },
    /// `N(0, s²)` with `s = gain·√(2 / (fan_in + fan_out))` (`xavier_normal_`).
    XavierNormal {
        /// Scale.
        gain: f32,
    },
    /// `U(−b, b)` with `b = √2·√(3 / fan_in)` (`kaiming_uniform_` with its defaults: fan-in,
    /// ReLU gain).
    KaimingUniform,
    /// `N(0, 2 / fan_in)` (`kaiming_normal_` with its defaults).
    KaimingNormal,
    /// `U(low, high)`.
    Uniform {
        /// Lower bound.
        low: f32,
        /// Upper bound (`≥ low`).
        high: f32,
    },
}

/// How to initialise a bias vector `[out]`.
#[derive(Debug, Clone, Copy, Default, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum BiasInit {
    /// PyTorch's `nn.Linear` default: `U(−1/√fan_in, 1/√fan_in)`.
    #[default]
    Default,
    /// Zeros.
    Zero,
    /// `U(low, high)` (e.g. VDD's expert-mean bias `U(−0.5, 0.5)`).
    Uniform {
        /// Lower bound.
        low: f32,
        /// Upper bound (`≥ low`).
        high: f32,
    },
}

fn check_gain(gain: f32) -> Result<(), NnError> {
    if gain.is_finite() {
        Ok(())
    } else {
        Err(NnError::Config(format!("init gain must be finite, got {gain}")))
    }
}

fn check_range(low: f32, high: f32) -> Result<(), NnError> {
    if low.is_finite() && high.is_finite() && low <= high {
        Ok(())
    } else {
        Err(NnError::Config(format!("uniform init needs finite low <= high, got [{low}, {high}]")))
    }
}

fn uniform(n: usize, low: f32, high: f32, rng: &mut vdd_core::Rng) -> Vec<f32> {
    (0..n).map(|_| rng.random_range(low..=high)).collect()
}

fn normal(n: usize, std: f32, rng: &mut vdd_core::Rng) -> Vec<f32> {
    (0..n).map(|_| std * vdd_core::standard_normal(rng)).collect()
}

/// PyTorch's recommended gain for a nonlinearity (`torch.nn.init.calculate_gain`): √2 for
/// ReLU, 5/3 for tanh, 1 otherwise (PyTorch has no entry for Mish, GELU, SiLU, softplus).
pub fn gain(activation: Activation) -> f32 {
    match activation {
        Activation::Relu => std::f32::consts::SQRT_2,
        Activation::Tanh => 5.0 / 3.0,
        _ => 1.0,
    }
}

impl Init {
    /// Checks the numbers (finite gain, finite `low ≤ high`).
    pub fn validate(&self) -> Result<(), NnError> {
        match *self {
            Init::Default | Init::KaimingUniform | Init::KaimingNormal => Ok(()),
            Init::Orthogonal { gain }
            | Init::XavierUniform { gain }
            | Init::XavierNormal { gain } => check_gain(gain),
            Init::Uniform { low, high } => check_range(low, high),
        }
    }

    /// Draws a `rows x cols` weight (`[out, in]`, row-major as PyTorch stores it).
    pub fn sample(
        &self,
        rows: usize,
        cols: usize,
        rng: &mut vdd_core::Rng,
    ) -> Result<Vec<f32>, NnError> {
        self.validate()?;
        let n = rows * cols;
        let (fan_in, fan_out) = (cols.max(1) as f32, rows.max(1) as f32);
        Ok(match *self {
            Init::Default => {
                let b = 1.0 / fan_in.sqrt();
                uniform(n, -b, b, rng)
            }
            Init::Orthogonal { gain } => orthogonal(rows, cols, gain, rng),
            Init::XavierUniform { gain } => {
                let b = gain * (6.0 / (fan_in + fan_out)).sqrt();
                uniform(n, -b, b, rng)
            }
            Init::XavierNormal { gain } => normal(n, gain * (2.0 / (fan_in + fan_out)).sqrt(), rng),
            Init::KaimingUniform => {
                let b = std::f32::consts::SQRT_2 * (3.0 / fan_in).sqrt();
                uniform(n, -b, b, rng)
            }
            Init::KaimingNormal => normal(n, (2.0 / fan_in).sqrt(), rng),
            Init::Uniform { low, high } => uniform(n, low, high, rng),
        })
    }
}

impl BiasInit {
    /// Checks the numbers (finite `low ≤ high`).
    pub fn validate(&self) -> Result<(), NnError> {
        match *self {
            BiasInit::Default | BiasInit::Zero => Ok(()),
            BiasInit::Uniform { low, high } => check_range(low, high),
        }
    }

    /// Draws a bias of length `out` for a layer with `fan_in` inputs.
    pub fn sample(
        &self,
        out: usize,
        fan_in: usize,
        rng: &mut vdd_core::Rng,
    ) -> Result<Vec<f32>, NnError> {
        self.validate()?;
        Ok(match *self {
            BiasInit::Default => {
                let b = 1.0 / (fan_in.max(1) as f32).sqrt();
                uniform(out, -b, b, rng)
            }
            BiasInit::Zero => vec![0.0; out],
            BiasInit::Uniform { low, high } => uniform(out, low, high, rng),
        })
    }
}

/// `torch.nn.init.orthogonal_` for a `rows x cols` matrix: QR of a tall Gaussian matrix
/// (transposed when `rows < cols`), `Q`'s columns multiplied by the signs of `diag(R)` so the
/// result is uniformly (Haar) distributed, then scaled by `gain`.
fn orthogonal(rows: usize, cols: usize, gain: f32, rng: &mut vdd_core::Rng) -> Vec<f32> {
    if rows == 0 || cols == 0 {
        return Vec::new();
    }
    let wide = rows < cols;
    let (m, n) = if wide { (cols, rows) } else { (rows, cols) };
    let mut a = Mat::<f64>::zeros(m, n);
    for i in 0..m {
        for j in 0..n {
            a[(i, j)] = f64::from(vdd_core::standard_normal(rng));
        }
    }
    let qr = a.qr();
    let mut q = qr.compute_thin_Q();
    let r = qr.thin_R();
    for j in 0..n {
        if r[(j, j)] < 0.0 {
            q.col_mut(j).iter_mut().for_each(|v| *v = -*v);
        }
    }
    let g = f64::from(gain);
    let mut w = vec![0.0f32; rows * cols];
    for i in 0..rows {
        for k in 0..cols {
            let v = if wide { q[(k, i)] } else { q[(i, k)] };
            w[i * cols + k] = (g * v) as f32;
        }
    }
    w
}

#[cfg(test)]
mod tests {
    use super::*;

    fn rng(seed: u64) -> vdd_core::Rng {
        vdd_core::Seeds::new(seed).stream("init-test")
    }

    /// `W Wᵀ` (rows x rows) in f64.
    fn gram_rows(w: &[f32], rows: usize, cols: usize) -> Vec<f64> {
        let mut g = vec![0.0; rows * rows];
        for a in 0..rows {
            for b in 0..rows {
                g[a * rows + b] = (0..cols)
                    .map(|k| f64::from(w[a * cols + k]) * f64::from(w[b * cols + k]))
                    .sum();
            }
        }
        g
    }

    fn max_dev_from_scaled_identity(g: &[f64], n: usize, s: f64) -> f64 {
        let mut worst = 0.0f64;
        for a in 0..n {
            for b in 0..n {
                let target = if a == b { s } else { 0.0 };
                worst = worst.max((g[a * n + b] - target).abs());
            }
        }
        worst
    }

    #[test]
    fn orthogonal_rows_or_columns_are_orthonormal() {
        // Wide and square: W Wᵀ = gain² I.
        for (rows, cols) in [(8, 20), (16, 16)] {
            let w = Init::Orthogonal { gain: 1.5 }.sample(rows, cols, &mut rng(1)).unwrap();
            let g = gram_rows(&w, rows, cols);
            assert!(max_dev_from_scaled_identity(&g, rows, 2.25) < 1e-5, "{rows}x{cols}");
        }
        // Tall: Wᵀ W = I (the rows of Wᵀ are orthonormal).
        let (rows, cols) = (20, 8);
        let w = Init::Orthogonal { gain: 1.0 }.sample(rows, cols, &mut rng(2)).unwrap();
        let wt: Vec<f32> = (0..cols)
            .flat_map(|k| (0..rows).map(move |i| (i, k)))
            .map(|(i, k)| w[i * cols + k])
            .collect();
        let g = gram_rows(&wt, cols, rows);
        assert!(max_dev_from_scaled_identity(&g, cols, 1.0) < 1e-5);
        // Seeded: the same stream gives the same matrix, another gives another.
        let a = Init::Orthogonal { gain: 1.0 }.sample(4, 6, &mut rng(3)).unwrap();
        assert_eq!(a, Init::Orthogonal { gain: 1.0 }.sample(4, 6, &mut rng(3)).unwrap());
        assert_ne!(a, Init::Orthogonal { gain: 1.0 }.sample(4, 6, &mut rng(4)).unwrap());
    }

    #[test]
    fn orthogonal_entries_are_not_sign_biased() {
        // Without the sign correction Q's diagonal is biased; with it, the mean diagonal entry
        // of a square orthogonal matrix is ~0 (sd 1/√n per entry, 200 draws of 8 entries).
        let mut r = rng(5);
        let n = 8;
        let mut sum = 0.0f64;
        for _ in 0..200 {
            let w = Init::Orthogonal { gain: 1.0 }.sample(n, n, &mut r).unwrap();
            sum += (0..n).map(|i| f64::from(w[i * n + i])).sum::<f64>();
        }
        let mean = sum / (200 * n) as f64;
        // sd of the mean ≈ (1/√8)/√1600 ≈ 0.009.
        assert!(mean.abs() < 0.04, "{mean}");
    }

    fn moments(w: &[f32]) -> (f64, f64, f64) {
        let n = w.len() as f64;
        let mean = w.iter().map(|&v| f64::from(v)).sum::<f64>() / n;
        let var = w.iter().map(|&v| (f64::from(v) - mean).powi(2)).sum::<f64>() / n;
        let max = w.iter().map(|v| f64::from(v.abs())).fold(0.0, f64::max);
        (mean, var, max)
    }

    #[test]
    fn variance_statistics_match_pytorch_formulas() {
        let (rows, cols) = (200, 300); // fan_out 200, fan_in 300, 60 000 draws
        let cases: [(Init, f64, Option<f64>); 6] = [
            (
                Init::XavierUniform { gain: 2.0 },
                4.0 * 2.0 / 500.0,
                Some(2.0 * (6.0f64 / 500.0).sqrt()),
            ),
            (Init::XavierNormal { gain: 2.0 }, 4.0 * 2.0 / 500.0, None),
            (Init::KaimingUniform, 2.0 / 300.0, Some((6.0f64 / 300.0).sqrt())),
            (Init::KaimingNormal, 2.0 / 300.0, None),
            (Init::Default, 1.0 / 900.0, Some(1.0 / 300f64.sqrt())),
            (Init::Uniform { low: -0.5, high: 0.5 }, 1.0 / 12.0, Some(0.5)),
        ];
        for (k, (init, var_expected, bound)) in cases.into_iter().enumerate() {
            let w = init.sample(rows, cols, &mut rng(10 + k as u64)).unwrap();
            let (mean, var, max) = moments(&w);
            // The sample variance of 60 000 draws is within ~1% (uniform) / ~0.6% (normal)
            // sd of the truth; 3% is > 3 sd, and every wrong fan or gain is off by > 20%.
            assert!((var / var_expected - 1.0).abs() < 0.03, "{init:?}: {var} vs {var_expected}");
            assert!(mean.abs() < 4.0 * (var_expected / 60_000.0).sqrt(), "{init:?}: mean {mean}");
            match bound {
                Some(b) => assert!(max <= b * (1.0 + 1e-6) && max > 0.99 * b, "{init:?}: {max}"),
                // Gaussian: 60 000 draws reach beyond 3.5 sd.
                None => assert!(max > 3.5 * var_expected.sqrt(), "{init:?}: {max}"),
            }
        }
    }

    #[test]
    fn bias_inits_and_bad_arguments() {
        let z = BiasInit::Zero.sample(5, 3, &mut rng(0)).unwrap();
        assert_eq!(z, vec![0.0; 5]);
        let u = BiasInit::Uniform { low: 0.25, high: 0.5 }.sample(1000, 3, &mut rng(0)).unwrap();
        assert!(u.iter().all(|&b| (0.25..=0.5).contains(&b)));
        let (mean, _, _) = moments(&u);
        assert!((mean - 0.375).abs() < 0.01);
        let d = BiasInit::Default.sample(1000, 4, &mut rng(0)).unwrap();
        assert!(d.iter().all(|&b| b.abs() <= 0.5) && d.iter().any(|&b| b.abs() > 0.45));
        assert!(BiasInit::Uniform { low: 1.0, high: 0.0 }.sample(2, 2, &mut rng(0)).is_err());
        assert!(Init::Orthogonal { gain: f32::INFINITY }.sample(2, 2, &mut rng(0)).is_err());
        assert!(Init::Uniform { low: f32::NAN, high: 0.0 }.sample(2, 2, &mut rng(0)).is_err());
        assert_eq!(gain(Activation::Relu), std::f32::consts::SQRT_2);
    }

    #[test]
    fn inits_round_trip_through_serde() {
        for init in [Init::Default, Init::Orthogonal { gain: 1.4 }, Init::KaimingNormal] {
            let s = serde_json::to_string(&init).unwrap();
            assert_eq!(serde_json::from_str::<Init>(&s).unwrap(), init);
        }
        let b: BiasInit = serde_json::from_str(r#"{"uniform":{"low":-0.5,"high":0.5}}"#).unwrap();
        assert_eq!(b, BiasInit::Uniform { low: -0.5, high: 0.5 });
    }
}
