//! Noise-level embeddings (a column of noise levels `n x 1` → `n x dim` features) and column
//! concatenation of several inputs, with the gradient split back to the parts.
//!
//! A denoiser or a noise-conditioned network typically embeds its noise level and concatenates
//! it with the state and action:
//!
//! ```
//! use faer::Mat;
//! use vdd_nn::{concat_cols_into, split_cols, Module, SinusoidalEmbedding};
//! let mut emb = SinusoidalEmbedding::new(8).unwrap();
//! let sigma = Mat::from_fn(4, 1, |i, _| 0.1 * (i + 1) as f32);
//! let action = Mat::<f32>::zeros(4, 2);
//! let mut input = Mat::zeros(0, 0);
//! concat_cols_into(&mut input, &[action.as_ref(), emb.forward(sigma.as_ref())]).unwrap();
//! assert_eq!(input.ncols(), 10);
//! // ... network forward/backward gives `g`, the gradient for `input` (n x 10):
//! let g = Mat::<f32>::ones(4, 10);
//! let parts = split_cols(g.as_ref(), &[2, 8]).unwrap();
//! let d_sigma = emb.backward(parts[1]);
//! assert_eq!(d_sigma.ncols(), 1);
//! ```

use std::f32::consts::PI;

use faer::{Mat, MatRef};

use crate::error::NnError;
use crate::module::{Module, ensure_shape};
use crate::param::{Param, Parameters};

fn check_embedding_dim(what: &str, dim: usize) -> Result<(), NnError> {
    if dim == 0 || dim % 2 != 0 {
        return Err(NnError::Config(format!("{what}: dim must be even and positive, got {dim}")));
    }
    Ok(())
}

/// `[sin(t·f₀) … sin(t·f_{h−1}), cos(t·f₀) … cos(t·f_{h−1})]` with `h = dim / 2` frequencies
/// `f_k = 10000^(−k/(h−1))` (geometric from 1 to 1/10000): the DDPM / transformer
/// positional embedding, as BESO's `SinusoidalPosEmb`. No parameters; `dim = 2` uses the
/// single frequency 1.
///
/// ```
/// use vdd_nn::{Module, SinusoidalEmbedding};
/// let mut emb = SinusoidalEmbedding::new(4).unwrap();
/// let y = emb.forward(faer::mat![[0.5f32]].as_ref()).to_owned();
/// assert!((y[(0, 0)] - 0.5f32.sin()).abs() < 1e-7 && (y[(0, 2)] - 0.5f32.cos()).abs() < 1e-7);
/// ```
#[derive(Debug, Clone)]
pub struct SinusoidalEmbedding {
    dim: usize,
    freqs: Vec<f32>,
    output: Mat<f32>,
    grad_input: Mat<f32>,
}

impl SinusoidalEmbedding {
    /// An embedding of width `dim` (even, positive).
    pub fn new(dim: usize) -> Result<Self, NnError> {
        check_embedding_dim("SinusoidalEmbedding", dim)?;
        let half = dim / 2;
        let step = if half > 1 { 10000f64.ln() / (half - 1) as f64 } else { 0.0 };
        let freqs = (0..half).map(|k| (-(k as f64) * step).exp() as f32).collect();
        Ok(Self { dim, freqs, output: Mat::zeros(0, 0), grad_input: Mat::zeros(0, 0) })
    }

    /// The frequencies `f_k`.
    pub fn frequencies(&self) -> &[f32] {
        &self.freqs
    }
}

/// `[sin(2π t·W), cos(2π t·W)]` with fixed random frequencies `W ~ N(0, scale²)` of size
/// `dim / 2`: the Gaussian Fourier projection of score-based models (Song et al. 2021), BESO's
/// and EDM's noise-level embedding. `W` is stored as a non-trainable tensor named `W` (as in
/// BESO's `GaussianFourierProjection`), so it is saved and loaded with the network but never
/// updated by optimisers.
///
/// ```
/// use vdd_nn::{FourierFeatures, Module, Parameters};
/// let mut rng = vdd_core::Seeds::new(0).stream("init");
/// let mut emb = FourierFeatures::new(16, 30.0, &mut rng).unwrap();
/// assert_eq!(emb.forward(faer::Mat::<f32>::zeros(3, 1).as_ref()).ncols(), 16);
/// emb.visit_params("", &mut |name, p| assert!(name == "W" && !p.trainable));
/// ```
#[derive(Debug, Clone)]
pub struct FourierFeatures {
    /// The frequencies `W` (`[dim / 2]`, not trainable).
    pub w: Param,
    dim: usize,
    output: Mat<f32>,
    grad_input: Mat<f32>,
}

impl FourierFeatures {
    /// An embedding of width `dim` (even, positive) with frequencies drawn from
    /// `N(0, scale²)` (`scale` finite and positive; BESO uses 30, EDM 16).
    pub fn new(dim: usize, scale: f32, rng: &mut vdd_core::Rng) -> Result<Self, NnError> {
        check_embedding_dim("FourierFeatures", dim)?;
        if !(scale.is_finite() && scale > 0.0) {
            return Err(NnError::Config(format!(
                "FourierFeatures: scale must be finite and > 0, got {scale}"
            )));
        }
        let w = (0..dim / 2).map(|_| vdd_core::standard_normal(rng) * scale).collect();
        Ok(Self::from_frequencies(Param::buffer(&[dim / 2], w)))
    }

    fn from_frequencies(w: Param) -> Self {
        let dim = 2 * w.len();
        Self { w, dim, output: Mat::zeros(0, 0), grad_input: Mat::zeros(0, 0) }
    }
}

/// Shared forward of both embeddings: `out[:, k] = sin(t·ω_k)`, `out[:, h + k] = cos(t·ω_k)`.
fn embed_forward(out: &mut Mat<f32>, x: MatRef<'_, f32>, omega: impl Fn(usize) -> f32, h: usize) {
    assert_eq!(x.ncols(), 1, "embedding: input must be one column of noise levels");
    let n = x.nrows();
    ensure_shape(out, n, 2 * h);
    for k in 0..h {
        let w = omega(k);
        for i in 0..n {
            let (s, c) = (x[(i, 0)] * w).sin_cos();
            out[(i, k)] = s;
            out[(i, h + k)] = c;
        }
    }
}

/// Shared backward: `dt = Σ_k ω_k (g[:, k] cos − g[:, h + k] sin)`.
fn embed_backward(
    grad_input: &mut Mat<f32>,
    out: &Mat<f32>,
    g: MatRef<'_, f32>,
    omega: impl Fn(usize) -> f32,
    h: usize,
) {
    let n = out.nrows();
    assert_eq!((g.nrows(), g.ncols()), (n, 2 * h), "embedding: grad shape");
    ensure_shape(grad_input, n, 1);
    let dt = grad_input.col_as_slice_mut(0);
    dt.fill(0.0);
    for k in 0..h {
        let w = omega(k);
        let (sin, cos) = (out.col_as_slice(k), out.col_as_slice(h + k));
        for i in 0..n {
            dt[i] += w * (g[(i, k)] * cos[i] - g[(i, h + k)] * sin[i]);
        }
    }
}

impl Parameters for SinusoidalEmbedding {
    fn visit_params(&self, _prefix: &str, _f: &mut dyn FnMut(&str, &Param)) {}
    fn visit_params_mut(&mut self, _prefix: &str, _f: &mut dyn FnMut(&str, &mut Param)) {}
}

impl Module for SinusoidalEmbedding {
    fn in_dim(&self) -> usize {
        1
    }
    fn out_dim(&self) -> usize {
        self.dim
    }
    fn forward(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32> {
        let freqs = &self.freqs;
        embed_forward(&mut self.output, x, |k| freqs[k], freqs.len());
        self.output.as_ref()
    }
    fn backward(&mut self, grad_out: MatRef<'_, f32>) -> MatRef<'_, f32> {
        let freqs = &self.freqs;
        embed_backward(&mut self.grad_input, &self.output, grad_out, |k| freqs[k], freqs.len());
        self.grad_input.as_ref()
    }
}

impl Parameters for FourierFeatures {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        f(&crate::join_name(prefix, "W"), &self.w);
    }
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        f(&crate::join_name(prefix, "W"), &mut self.w);
    }
}

impl Module for FourierFeatures {
    fn in_dim(&self) -> usize {
        1
    }
    fn out_dim(&self) -> usize {
        self.dim
    }
    fn forward(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32> {
        let w = &self.w.value;
        embed_forward(&mut self.output, x, |k| 2.0 * PI * w[k], w.len());
        self.output.as_ref()
    }
    fn backward(&mut self, grad_out: MatRef<'_, f32>) -> MatRef<'_, f32> {
        let w = &self.w.value;
        embed_backward(&mut self.grad_input, &self.output, grad_out, |k| 2.0 * PI * w[k], w.len());
        self.grad_input.as_ref()
    }
}

/// Writes the column concatenation `[parts₀ | parts₁ | …]` into `dst`, resizing it only when
/// its shape changes (so a loop reusing `dst` does not allocate). All parts must have the same
/// number of rows.
pub fn concat_cols_into(dst: &mut Mat<f32>, parts: &[MatRef<'_, f32>]) -> Result<(), NnError> {
    let n = parts.first().map_or(0, |p| p.nrows());
    if let Some((i, p)) = parts.iter().enumerate().find(|(_, p)| p.nrows() != n) {
        return Err(NnError::Config(format!(
            "concat_cols: part {i} has {} rows, part 0 has {n}",
            p.nrows()
        )));
    }
    let cols = parts.iter().map(|p| p.ncols()).sum();
    ensure_shape(dst, n, cols);
    let mut j0 = 0;
    for p in parts {
        dst.as_mut().subcols_mut(j0, p.ncols()).copy_from(p);
        j0 += p.ncols();
    }
    Ok(())
}

/// The column concatenation `[parts₀ | parts₁ | …]` in a new matrix (see
/// [`concat_cols_into`] for the allocation-free form).
pub fn concat_cols(parts: &[MatRef<'_, f32>]) -> Result<Mat<f32>, NnError> {
    let mut dst = Mat::zeros(0, 0);
    concat_cols_into(&mut dst, parts)?;
    Ok(dst)
}

/// Splits `m` into consecutive column blocks of the given widths (views, no copy): the
/// backward of [`concat_cols`], handing each part its share of the gradient. The widths must
/// add up to `m.ncols()`.
pub fn split_cols<'a>(
    m: MatRef<'a, f32>,
    widths: &[usize],
) -> Result<Vec<MatRef<'a, f32>>, NnError> {
    let total: usize = widths.iter().sum();
    if total != m.ncols() {
        return Err(NnError::Config(format!(
            "split_cols: widths {widths:?} add up to {total}, the matrix has {} columns",
            m.ncols()
        )));
    }
    let mut j0 = 0;
    Ok(widths
        .iter()
        .map(|&w| {
            let v = m.subcols(j0, w);
            j0 += w;
            v
        })
        .collect())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gradcheck::check_module;
    use rand::Rng as _;

    fn levels(n: usize, rng: &mut vdd_core::Rng) -> Mat<f32> {
        Mat::from_fn(n, 1, |_, _| rng.random_range(-1.0f32..1.0))
    }

    #[test]
    fn sinusoidal_matches_the_ddpm_formula() {
        let mut emb = SinusoidalEmbedding::new(8).unwrap();
        let t = 3.7f64;
        let y = emb.forward(faer::mat![[t as f32]].as_ref()).to_owned();
        for k in 0..4 {
            let f = (-(10000f64.ln()) * k as f64 / 3.0).exp();
            assert!((f64::from(y[(0, k)]) - (t * f).sin()).abs() < 2e-6);
            assert!((f64::from(y[(0, 4 + k)]) - (t * f).cos()).abs() < 2e-6);
        }
        assert!((emb.frequencies()[3] - 1e-4).abs() < 1e-9);
        assert_eq!(SinusoidalEmbedding::new(2).unwrap().frequencies(), [1.0]);
        assert!(SinusoidalEmbedding::new(7).is_err() && SinusoidalEmbedding::new(0).is_err());
    }

    #[test]
    fn embedding_gradients_match_finite_differences() {
        let mut rng = vdd_core::Seeds::new(6).stream("t");
        let mut emb = SinusoidalEmbedding::new(6).unwrap();
        let x = levels(7, &mut rng);
        let r = check_module(&mut emb, x.as_ref(), 1e-3, 1e-2, &mut rng);
        assert!(r.input_error < 2e-3, "{r:?}");
        // Small scale so that finite differences resolve the oscillation.
        let mut ff = FourierFeatures::new(6, 0.3, &mut rng).unwrap();
        let r = check_module(&mut ff, x.as_ref(), 1e-3, 1e-2, &mut rng);
        assert!(r.input_error < 2e-3, "{r:?}");
        assert_eq!(r.param_error, 0.0, "the frequencies are not trainable");
    }

    #[test]
    fn fourier_features_are_seeded_gaussian() {
        let mut a =
            FourierFeatures::new(4000, 30.0, &mut vdd_core::Seeds::new(1).stream("f")).unwrap();
        let b = FourierFeatures::new(4000, 30.0, &mut vdd_core::Seeds::new(1).stream("f")).unwrap();
        assert_eq!(a.w, b.w);
        let w = a.w.value.clone();
        let mean = w.iter().map(|&v| f64::from(v)).sum::<f64>() / w.len() as f64;
        let var = w.iter().map(|&v| (f64::from(v) - mean).powi(2)).sum::<f64>() / w.len() as f64;
        // 2000 draws: sd of the sample sd ≈ 30 / √4000 ≈ 0.5.
        assert!(mean.abs() < 2.5 && (var.sqrt() - 30.0).abs() < 2.0, "{mean} {var}");
        let y = a.forward(faer::mat![[0.25f32]].as_ref()).to_owned();
        let arg = 2.0 * std::f64::consts::PI * 0.25 * f64::from(w[3]);
        assert!((f64::from(y[(0, 3)]) - arg.sin()).abs() < 1e-4);
        assert!((f64::from(y[(0, 2003)]) - arg.cos()).abs() < 1e-4);
        assert!(
            FourierFeatures::new(4, f32::NAN, &mut vdd_core::Seeds::new(1).stream("f")).is_err()
        );
    }

    #[test]
    fn concat_and_split_are_inverse() {
        let a = Mat::from_fn(3, 2, |i, j| (i * 2 + j) as f32);
        let b = Mat::from_fn(3, 1, |i, _| -(i as f32));
        let mut dst = Mat::zeros(0, 0);
        concat_cols_into(&mut dst, &[a.as_ref(), b.as_ref()]).unwrap();
        assert_eq!(dst, concat_cols(&[a.as_ref(), b.as_ref()]).unwrap());
        assert_eq!(dst[(2, 1)], 5.0);
        assert_eq!(dst[(2, 2)], -2.0);
        let parts = split_cols(dst.as_ref(), &[2, 1]).unwrap();
        assert_eq!(parts[0], a.as_ref());
        assert_eq!(parts[1], b.as_ref());
        assert!(split_cols(dst.as_ref(), &[2, 2]).is_err());
        let short = Mat::<f32>::zeros(2, 1);
        assert!(concat_cols_into(&mut dst, &[a.as_ref(), short.as_ref()]).is_err());
    }
}
