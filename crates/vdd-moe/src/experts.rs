//! The two Gaussian expert families: diagonal and full Cholesky covariance.

use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Expert, ScaleActivation};

/// `Σ = diag(σ²)`: raw outputs are `d` means followed by `d` pre-activation scales.
///
/// ```
/// use vdd_core::Expert;
/// use vdd_moe::DiagonalExpert;
/// let e = DiagonalExpert::new(2, 1.0, 1e-4).unwrap();
/// let (mut mean, mut l) = ([0.0; 2], [0.0; 4]);
/// e.decode(&[0.5, -0.5, 0.0, 0.0], &mut mean, &mut l);
/// assert_eq!(mean, [0.5, -0.5]);
/// assert!((l[0] - 1.0).abs() < 1e-6 && l[1] == 0.0);
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct DiagonalExpert {
    dim: usize,
    scale: ScaleActivation,
}

impl DiagonalExpert {
    /// A diagonal family in `dim` dimensions whose raw zero maps to std `init_std`.
    pub fn new(dim: usize, init_std: f32, min_std: f32) -> Result<Self, CoreError> {
        if dim == 0 {
            return Err(CoreError::Config("action dimension must be positive".into()));
        }
        Ok(Self { dim, scale: ScaleActivation::new(init_std, min_std)? })
    }
}

impl Expert for DiagonalExpert {
    fn action_dim(&self) -> usize {
        self.dim
    }
    fn raw_dim(&self) -> usize {
        2 * self.dim
    }
    fn is_diagonal(&self) -> bool {
        true
    }
    fn decode(&self, raw: &[f32], mean: &mut [f32], scale_tril: &mut [f32]) {
        let d = self.dim;
        mean.copy_from_slice(&raw[..d]);
        scale_tril.fill(0.0);
        for i in 0..d {
            scale_tril[i * d + i] = self.scale.apply(raw[d + i]);
        }
    }
    fn backward(&self, raw: &[f32], d_mean: &[f32], d_scale_tril: &[f32], grad_raw: &mut [f32]) {
        let d = self.dim;
        grad_raw[..d].copy_from_slice(d_mean);
        for i in 0..d {
            grad_raw[d + i] = d_scale_tril[i * d + i] * self.scale.derivative(raw[d + i]);
        }
    }
}

/// `Σ = L Lᵀ` with a full lower-triangular `L`: raw outputs are `d` means followed by the
/// `d(d+1)/2` entries of `L` row by row; diagonal entries go through the positive scale
/// activation, off-diagonal ones are used as they are.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct FullExpert {
    dim: usize,
    scale: ScaleActivation,
}

impl FullExpert {
    /// A full-covariance family in `dim` dimensions whose raw zero maps to `init_std · I`.
    pub fn new(dim: usize, init_std: f32, min_std: f32) -> Result<Self, CoreError> {
        if dim == 0 {
            return Err(CoreError::Config("action dimension must be positive".into()));
        }
        Ok(Self { dim, scale: ScaleActivation::new(init_std, min_std)? })
    }
}

impl Expert for FullExpert {
    fn action_dim(&self) -> usize {
        self.dim
    }
    fn raw_dim(&self) -> usize {
        self.dim + self.dim * (self.dim + 1) / 2
    }
    fn is_diagonal(&self) -> bool {
        false
    }
    fn decode(&self, raw: &[f32], mean: &mut [f32], scale_tril: &mut [f32]) {
        let d = self.dim;
        mean.copy_from_slice(&raw[..d]);
        scale_tril.fill(0.0);
        let mut k = d;
        for i in 0..d {
            for j in 0..=i {
                scale_tril[i * d + j] = if i == j { self.scale.apply(raw[k]) } else { raw[k] };
                k += 1;
            }
        }
    }
    fn backward(&self, raw: &[f32], d_mean: &[f32], d_scale_tril: &[f32], grad_raw: &mut [f32]) {
        let d = self.dim;
        grad_raw[..d].copy_from_slice(d_mean);
        let mut k = d;
        for i in 0..d {
            for j in 0..=i {
                let g = d_scale_tril[i * d + j];
                grad_raw[k] = if i == j { g * self.scale.derivative(raw[k]) } else { g };
                k += 1;
            }
        }
    }
}

/// Which expert family a [`crate::MoeConfig`] asks for.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum ExpertKind {
    /// [`DiagonalExpert`].
    #[default]
    Diagonal,
    /// [`FullExpert`].
    Full,
}

/// Either built-in family, chosen at run time by one config value ([`ExpertKind`]).
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub enum ExpertFamily {
    /// Diagonal covariance.
    Diagonal(DiagonalExpert),
    /// Full Cholesky covariance.
    Full(FullExpert),
}

impl ExpertFamily {
    /// Builds the family `kind` in `dim` dimensions.
    pub fn new(
        kind: ExpertKind,
        dim: usize,
        init_std: f32,
        min_std: f32,
    ) -> Result<Self, CoreError> {
        Ok(match kind {
            ExpertKind::Diagonal => Self::Diagonal(DiagonalExpert::new(dim, init_std, min_std)?),
            ExpertKind::Full => Self::Full(FullExpert::new(dim, init_std, min_std)?),
        })
    }
}

impl DiagonalExpert {
    /// The raw outputs that [`Expert::decode`] maps to `mean` and the diagonal of `scale_tril`
    /// (stds at or below `min_std` are clamped just above it).
    pub fn encode(&self, mean: &[f32], scale_tril: &[f32], raw: &mut [f32]) {
        let d = self.dim;
        raw[..d].copy_from_slice(mean);
        for i in 0..d {
            raw[d + i] = self.scale.inverse(scale_tril[i * d + i]);
        }
    }
}

impl FullExpert {
    /// The raw outputs that [`Expert::decode`] maps to `mean` and `scale_tril` (diagonal
    /// entries at or below `min_std` are clamped just above it).
    pub fn encode(&self, mean: &[f32], scale_tril: &[f32], raw: &mut [f32]) {
        let d = self.dim;
        raw[..d].copy_from_slice(mean);
        let mut k = d;
        for i in 0..d {
            for j in 0..=i {
                let l = scale_tril[i * d + j];
                raw[k] = if i == j { self.scale.inverse(l) } else { l };
                k += 1;
            }
        }
    }
}

impl ExpertFamily {
    /// The raw outputs that decode to `mean` and `scale_tril` (the diagonal family keeps the
    /// diagonal of `scale_tril`).
    ///
    /// ```
    /// use vdd_core::Expert;
    /// use vdd_moe::{ExpertFamily, ExpertKind};
    /// let e = ExpertFamily::new(ExpertKind::Full, 2, 1.0, 1e-4).unwrap();
    /// let (mean, l) = ([0.5, -1.0], [0.3, 0.0, 0.2, 2.0]);
    /// let mut raw = [0.0; 5];
    /// e.encode(&mean, &l, &mut raw);
    /// let (mut m2, mut l2) = ([0.0; 2], [0.0; 4]);
    /// e.decode(&raw, &mut m2, &mut l2);
    /// assert_eq!(m2, mean);
    /// assert!(l2.iter().zip(&l).all(|(a, b)| (a - b).abs() < 1e-5));
    /// ```
    pub fn encode(&self, mean: &[f32], scale_tril: &[f32], raw: &mut [f32]) {
        match self {
            Self::Diagonal(e) => e.encode(mean, scale_tril, raw),
            Self::Full(e) => e.encode(mean, scale_tril, raw),
        }
    }
}

macro_rules! dispatch {
    ($self:ident, $e:ident => $body:expr) => {
        match $self {
            ExpertFamily::Diagonal($e) => $body,
            ExpertFamily::Full($e) => $body,
        }
    };
}

impl Expert for ExpertFamily {
    fn action_dim(&self) -> usize {
        dispatch!(self, e => e.action_dim())
    }
    fn raw_dim(&self) -> usize {
        dispatch!(self, e => e.raw_dim())
    }
    fn is_diagonal(&self) -> bool {
        dispatch!(self, e => e.is_diagonal())
    }
    fn decode(&self, raw: &[f32], mean: &mut [f32], scale_tril: &mut [f32]) {
        dispatch!(self, e => e.decode(raw, mean, scale_tril))
    }
    fn backward(&self, raw: &[f32], d_mean: &[f32], d_scale_tril: &[f32], grad_raw: &mut [f32]) {
        dispatch!(self, e => e.backward(raw, d_mean, d_scale_tril, grad_raw))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    #[test]
    fn sampling_returns_its_noise_and_densities_match_moments() {
        let e = FullExpert::new(2, 1.0, 1e-4).unwrap();
        let raw = [0.3f32, -0.2, 0.1, 0.4, -0.3];
        let (mut mu, mut l) = ([0.0f32; 2], [0.0f32; 4]);
        e.decode(&raw, &mut mu, &mut l);
        let mut rng = vdd_core::Seeds::new(4).stream("t");
        let (mut eps, mut a, mut work) = ([0.0f32; 2], [0.0f32; 2], [0.0f32; 2]);
        let n = 20_000;
        let (mut mean_lp, mut m0) = (0.0f64, 0.0f64);
        for _ in 0..n {
            e.sample(&mu, &l, &mut rng, &mut eps, &mut a);
            assert_relative_eq!(a[0], mu[0] + l[0] * eps[0], epsilon = 1e-6);
            assert_relative_eq!(a[1], mu[1] + l[2] * eps[0] + l[3] * eps[1], epsilon = 1e-6);
            mean_lp += f64::from(e.log_density(&mu, &l, &a, &mut work)) / n as f64;
            m0 += f64::from(a[0]) / n as f64;
        }
        // E[log N(a)] = −H for samples of the same Gaussian.
        assert!((mean_lp + f64::from(e.entropy(&l))).abs() < 0.03, "{mean_lp}");
        assert!((m0 - f64::from(mu[0])).abs() < 0.03);
    }

    /// f(raw) = Σ c_μ·μ + Σ c_L·L; its raw gradient from `backward` must match differences.
    fn check_backward<E: Expert>(e: &E) {
        let d = e.action_dim();
        let r = e.raw_dim();
        let raw: Vec<f32> = (0..r).map(|i| ((i * 37 % 11) as f32 / 11.0) - 0.4).collect();
        let cm: Vec<f32> = (0..d).map(|i| 0.3 + i as f32).collect();
        let cl: Vec<f32> = (0..d * d).map(|i| 0.7 - 0.2 * i as f32).collect();
        let f = |raw: &[f32]| {
            let (mut m, mut l) = (vec![0.0; d], vec![0.0; d * d]);
            e.decode(raw, &mut m, &mut l);
            let a: f32 = m.iter().zip(&cm).map(|(x, c)| x * c).sum();
            let b: f32 = l.iter().zip(&cl).map(|(x, c)| x * c).sum();
            a + b
        };
        let mut g = vec![0.0; r];
        e.backward(&raw, &cm, &cl, &mut g);
        for k in 0..r {
            let h = 1e-3;
            let mut p = raw.clone();
            p[k] += h;
            let mut m = raw.clone();
            m[k] -= h;
            let fd = (f(&p) - f(&m)) / (2.0 * h);
            assert_relative_eq!(g[k], fd, epsilon = 2e-3);
        }
    }

    #[test]
    fn backward_matches_finite_differences() {
        check_backward(&DiagonalExpert::new(3, 0.7, 1e-4).unwrap());
        check_backward(&FullExpert::new(3, 0.7, 1e-4).unwrap());
        check_backward(&ExpertFamily::new(ExpertKind::Full, 2, 1.0, 1e-3).unwrap());
    }

    #[test]
    fn full_decode_is_lower_triangular_with_positive_diagonal() {
        let e = FullExpert::new(3, 1.0, 1e-4).unwrap();
        let raw = [0.0, 0.0, 0.0, -30.0, 0.5, 2.0, -1.0, 0.3, 0.0];
        let (mut m, mut l) = ([0.0; 3], [9.0; 9]);
        e.decode(&raw, &mut m, &mut l);
        assert_eq!([l[1], l[2], l[5]], [0.0, 0.0, 0.0]);
        assert!(l[0] > 0.0 && l[4] > 0.0 && l[8] > 0.0);
        assert_eq!(l[3], 0.5);
        assert_eq!(e.raw_dim(), 9);
    }
}
