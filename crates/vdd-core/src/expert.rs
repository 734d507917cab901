//! A Gaussian expert family: the map from raw network outputs to a mean and a scale, and back.

use serde::{Deserialize, Serialize};

use crate::error::{CoreError, Result};

/// The positive scale activation `softplus(x + shift) + min_std`, with `shift` chosen so that a
/// raw output of `0` gives `init_std`.
///
/// ```
/// use vdd_core::ScaleActivation;
/// let act = ScaleActivation::new(1.0, 1e-4).unwrap();
/// assert!((act.apply(0.0) - 1.0).abs() < 1e-6);
/// assert!(act.apply(-50.0) >= 1e-4);
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ScaleActivation {
    shift: f32,
    min_std: f32,
}

impl ScaleActivation {
    /// Builds the activation for a given initial and minimal standard deviation.
    pub fn new(init_std: f32, min_std: f32) -> Result<Self> {
        if !(min_std.is_finite() && init_std.is_finite() && min_std >= 0.0 && init_std > min_std) {
            return Err(CoreError::Config(format!(
                "need 0 <= min_std < init_std, got min_std {min_std}, init_std {init_std}"
            )));
        }
        let target = (init_std - min_std) as f64;
        // softplus⁻¹(y) = log(exp(y) − 1), written stably for large y.
        let shift = target + (-(-target).exp_m1()).ln();
        Ok(Self { shift: shift as f32, min_std })
    }

    /// The shift inside the softplus (`softplus⁻¹(init_std − min_std)`): for exporters that
    /// rebuild the activation elsewhere (ONNX).
    pub fn shift(&self) -> f32 {
        self.shift
    }

    /// The smallest standard deviation this activation can produce.
    pub fn min_std(&self) -> f32 {
        self.min_std
    }

    /// `softplus(x + shift) + min_std`.
    #[inline]
    pub fn apply(&self, x: f32) -> f32 {
        softplus(x + self.shift) + self.min_std
    }

    /// The raw value that [`ScaleActivation::apply`] maps to `std` (clamped just above
    /// `min_std`, where the activation has no inverse).
    pub fn inverse(&self, std: f32) -> f32 {
        let y = f64::from(std - self.min_std).max(1e-12);
        // softplus⁻¹(y) = y + log(1 − exp(−y)).
        (y + (-(-y).exp_m1()).ln()) as f32 - self.shift
    }

    /// The derivative `sigmoid(x + shift)`.
    #[inline]
    pub fn derivative(&self, x: f32) -> f32 {
        sigmoid(x + self.shift)
    }
}

/// `log(1 + exp(x))`, stable for large `|x|`.
#[inline]
pub fn softplus(x: f32) -> f32 {
    if x > 20.0 {
        x
    } else if x < -20.0 {
        x.exp()
    } else {
        x.exp().ln_1p()
    }
}

/// `1 / (1 + exp(−x))`.
#[inline]
pub fn sigmoid(x: f32) -> f32 {
    if x >= 0.0 {
        1.0 / (1.0 + (-x).exp())
    } else {
        let e = x.exp();
        e / (1.0 + e)
    }
}

/// A family of Gaussian experts parameterised by raw network outputs.
///
/// A network emits `raw_dim()` numbers per (state, expert). The family decodes them into a
/// mean `μ` (`action_dim()` numbers) and a lower-triangular scale `L` (`d * d` row-major, zeros
/// above the diagonal; a diagonal family leaves the strict lower part zero too), and maps
/// gradients with respect to `μ` and `L` back to gradients of the raw outputs, through the
/// positive scale activation. Per-sample math on `(μ, L)` lives in [`crate::gaussian`].
///
/// VDD's expert step only ever calls [`Expert::expert_step_grad`], so a new family (say, a
/// low-rank-plus-diagonal one) plugs into the trainer by implementing this trait.
pub trait Expert: Clone + std::fmt::Debug + Send + Sync {
    /// Action dimension `d`.
    fn action_dim(&self) -> usize;

    /// Raw outputs per expert (e.g. `2d` for diagonal, `d + d(d+1)/2` for full Cholesky).
    fn raw_dim(&self) -> usize;

    /// Whether `L` is always diagonal.
    fn is_diagonal(&self) -> bool;

    /// Decodes one raw row into `mean` (`d`) and `scale_tril` (`d * d`, row-major).
    fn decode(&self, raw: &[f32], mean: &mut [f32], scale_tril: &mut [f32]);

    /// Maps gradients of a scalar objective with respect to `μ` (`d_mean`) and `L`
    /// (`d_scale_tril`, `d * d`, only the entries the family uses are read) to the gradient with
    /// respect to the raw outputs, written into `grad_raw`.
    fn backward(&self, raw: &[f32], d_mean: &[f32], d_scale_tril: &[f32], grad_raw: &mut [f32]);

    /// The VDD expert-step gradient of `J_z = E[log π + log q̃] + H` with respect to the raw
    /// outputs (an ascent direction), given the Monte-Carlo means `mean_g = E_ε[g]` (`d`) and
    /// `mean_g_eps = E_ε[g εᵀ]` (`d * d`, row-major) of the corrected score `g`:
    ///
    /// * `∂J/∂μ = E[g]`,
    /// * `∂J/∂L = tril(E[g εᵀ]) + diag(1 / L_ii)` (a diagonal family keeps the diagonal only).
    ///
    /// `scale_tril` is the decoded `L` of this raw row.
    fn expert_step_grad(
        &self,
        raw: &[f32],
        scale_tril: &[f32],
        mean_g: &[f32],
        mean_g_eps: &[f32],
        grad_raw: &mut [f32],
    ) {
        let d = self.action_dim();
        let mut small = [0.0f32; 64];
        let mut large = Vec::new();
        let d_l: &mut [f32] = if d * d <= small.len() {
            &mut small[..d * d]
        } else {
            large.resize(d * d, 0.0);
            &mut large
        };
        for i in 0..d {
            let lo = if self.is_diagonal() { i } else { 0 };
            for j in lo..=i {
                d_l[i * d + j] = mean_g_eps[i * d + j];
            }
            d_l[i * d + i] += 1.0 / scale_tril[i * d + i];
        }
        self.backward(raw, mean_g, d_l, grad_raw);
    }

    /// `log N(a; μ, L Lᵀ)` of one decoded expert (`work`: scratch of length `d`).
    fn log_density(&self, mean: &[f32], scale_tril: &[f32], a: &[f32], work: &mut [f32]) -> f32 {
        crate::gaussian::log_density(a, mean, scale_tril, work)
    }

    /// Reparameterised sample `a = μ + L ε`: draws `ε ~ N(0, I)` into `eps` and writes `a`.
    fn sample(
        &self,
        mean: &[f32],
        scale_tril: &[f32],
        rng: &mut dyn rand::RngCore,
        eps: &mut [f32],
        a: &mut [f32],
    ) {
        crate::seed::fill_standard_normal(rng, eps);
        crate::gaussian::sample_into(mean, scale_tril, eps, a);
    }

    /// Differential entropy `H[N(μ, L Lᵀ)]` in nats.
    fn entropy(&self, scale_tril: &[f32]) -> f32 {
        crate::gaussian::entropy(scale_tril, self.action_dim())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    #[test]
    fn activation_hits_init_std_and_has_right_derivative() {
        for init in [0.05f32, 1.0, 30.0] {
            let a = ScaleActivation::new(init, 1e-4).unwrap();
            assert_relative_eq!(a.apply(0.0), init, max_relative = 1e-5);
            let h = 1e-3;
            let fd = (a.apply(0.3 + h) - a.apply(0.3 - h)) / (2.0 * h);
            assert_relative_eq!(a.derivative(0.3), fd, max_relative = 1e-2);
        }
        assert!(ScaleActivation::new(0.1, 0.2).is_err());
    }
}
