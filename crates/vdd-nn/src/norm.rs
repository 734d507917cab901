//! Layer normalisation (Ba et al. 2016), PyTorch's `nn.LayerNorm(dim)`.

use faer::{Mat, MatRef};

use crate::error::NnError;
use crate::module::{Module, col_slice, contiguous, ensure_shape};
use crate::param::{Param, Parameters, join_name};

/// PyTorch's default `nn.LayerNorm` epsilon.
pub const LAYER_NORM_EPS: f32 = 1e-5;

/// `y = (x − mean(x)) / √(var(x) + ε) · weight + bias` over the features of each sample
/// (biased variance, as PyTorch). Parameters `weight` (ones) and `bias` (zeros), both `[dim]`.
///
/// ```
/// use vdd_nn::{LayerNorm, Module};
/// let mut ln = LayerNorm::new(3);
/// let y = ln.forward(faer::mat![[1.0f32, 2.0, 3.0]].as_ref()).to_owned();
/// assert!((y[(0, 0)] + 1.224_74).abs() < 1e-4 && y[(0, 1)].abs() < 1e-6);
/// ```
#[derive(Debug, Clone)]
pub struct LayerNorm {
    /// Per-feature scale, `[dim]`.
    pub weight: Param,
    /// Per-feature shift, `[dim]`.
    pub bias: Param,
    dim: usize,
    eps: f32,
    scratch: Mat<f32>,
    /// Normalised input `x̂`, kept for the backward pass.
    xhat: Mat<f32>,
    /// Per-sample `1 / √(var + ε)`.
    rstd: Vec<f32>,
    /// Per-sample accumulators (means in the forward pass, projections in the backward).
    acc1: Vec<f32>,
    acc2: Vec<f32>,
    output: Mat<f32>,
    grad_input: Mat<f32>,
}

impl LayerNorm {
    /// A layer norm over `dim` features with `ε = 1e-5`, weight ones and bias zeros.
    pub fn new(dim: usize) -> Self {
        Self {
            weight: Param::new(&[dim], vec![1.0; dim]),
            bias: Param::zeros(&[dim]),
            dim,
            eps: LAYER_NORM_EPS,
            scratch: Mat::zeros(0, 0),
            xhat: Mat::zeros(0, 0),
            rstd: Vec::new(),
            acc1: Vec::new(),
            acc2: Vec::new(),
            output: Mat::zeros(0, 0),
            grad_input: Mat::zeros(0, 0),
        }
    }

    /// The same layer with another `ε` (BESO's residual blocks use `1e-6`); it must be finite
    /// and positive.
    pub fn with_eps(mut self, eps: f32) -> Result<Self, NnError> {
        self.set_eps(eps)?;
        Ok(self)
    }

    /// Sets `ε` (finite and positive).
    pub fn set_eps(&mut self, eps: f32) -> Result<(), NnError> {
        if !(eps.is_finite() && eps > 0.0) {
            return Err(NnError::Config(format!(
                "layer norm eps must be finite and > 0, got {eps}"
            )));
        }
        self.eps = eps;
        Ok(())
    }

    /// The `ε` added to the variance.
    pub fn eps(&self) -> f32 {
        self.eps
    }
}

impl Parameters for LayerNorm {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        f(&join_name(prefix, "weight"), &self.weight);
        f(&join_name(prefix, "bias"), &self.bias);
    }
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        f(&join_name(prefix, "weight"), &mut self.weight);
        f(&join_name(prefix, "bias"), &mut self.bias);
    }
}

fn resize(v: &mut Vec<f32>, n: usize) {
    v.clear();
    v.resize(n, 0.0);
}

impl Module for LayerNorm {
    fn in_dim(&self) -> usize {
        self.dim
    }
    fn out_dim(&self) -> usize {
        self.dim
    }

    fn forward(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32> {
        assert_eq!(x.ncols(), self.dim, "LayerNorm: input width");
        let (n, d) = (x.nrows(), self.dim);
        let x = contiguous(x, &mut self.scratch);
        ensure_shape(&mut self.xhat, n, d);
        ensure_shape(&mut self.output, n, d);
        // Rows are samples and the matrix is column-major, so the per-sample statistics are
        // accumulated column by column (a vectorised pass over the batch per feature).
        let (mean, var) = (&mut self.acc1, &mut self.acc2);
        resize(mean, n);
        resize(var, n);
        for j in 0..d {
            let xc = col_slice(x, j);
            for i in 0..n {
                mean[i] += xc[i];
            }
        }
        let inv_d = 1.0 / d as f32;
        mean.iter_mut().for_each(|m| *m *= inv_d);
        for j in 0..d {
            let xc = col_slice(x, j);
            for i in 0..n {
                let c = xc[i] - mean[i];
                var[i] += c * c;
            }
        }
        resize(&mut self.rstd, n);
        for i in 0..n {
            self.rstd[i] = 1.0 / (var[i] * inv_d + self.eps).sqrt();
        }
        for j in 0..d {
            let (w, b) = (self.weight.value[j], self.bias.value[j]);
            let xc = col_slice(x, j);
            let xh = self.xhat.col_as_slice_mut(j);
            for i in 0..n {
                xh[i] = (xc[i] - mean[i]) * self.rstd[i];
            }
            let y = self.output.col_as_slice_mut(j);
            for i in 0..n {
                y[i] = xh[i] * w + b;
            }
        }
        self.output.as_ref()
    }

    fn backward(&mut self, grad_out: MatRef<'_, f32>) -> MatRef<'_, f32> {
        let (n, d) = (self.xhat.nrows(), self.dim);
        assert_eq!((grad_out.nrows(), grad_out.ncols()), (n, d), "LayerNorm: grad shape");
        if self.weight.grad.len() != d || self.bias.grad.len() != d {
            self.weight.zero_grad();
            self.bias.zero_grad();
        }
        let g = contiguous(grad_out, &mut self.scratch);
        // With ĝ = g ⊙ weight: dx = rstd · (ĝ − mean(ĝ) − x̂ · mean(ĝ ⊙ x̂)) per sample.
        let (m1, m2) = (&mut self.acc1, &mut self.acc2);
        resize(m1, n);
        resize(m2, n);
        for j in 0..d {
            let (gc, xh) = (col_slice(g, j), self.xhat.col_as_slice(j));
            let w = self.weight.value[j];
            let (mut dw, mut db) = (0.0f32, 0.0f32);
            for i in 0..n {
                dw += gc[i] * xh[i];
                db += gc[i];
                let gh = gc[i] * w;
                m1[i] += gh;
                m2[i] += gh * xh[i];
            }
            self.weight.grad[j] += dw;
            self.bias.grad[j] += db;
        }
        let inv_d = 1.0 / d as f32;
        ensure_shape(&mut self.grad_input, n, d);
        for j in 0..d {
            let (gc, xh) = (col_slice(g, j), self.xhat.col_as_slice(j));
            let w = self.weight.value[j];
            let dx = self.grad_input.col_as_slice_mut(j);
            for i in 0..n {
                dx[i] = self.rstd[i] * (gc[i] * w - (m1[i] + xh[i] * m2[i]) * inv_d);
            }
        }
        self.grad_input.as_ref()
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gradcheck::check_module;

    fn input(n: usize, d: usize) -> Mat<f32> {
        Mat::from_fn(n, d, |i, j| ((i * 7 + j * 3) % 11) as f32 / 5.5 - 1.0 + 0.1 * i as f32)
    }

    fn random_affine(ln: &mut LayerNorm, rng: &mut vdd_core::Rng) {
        use rand::Rng as _;
        ln.weight.value.iter_mut().for_each(|w| *w = rng.random_range(0.5..1.5));
        ln.bias.value.iter_mut().for_each(|b| *b = rng.random_range(-0.5..0.5));
    }

    #[test]
    fn normalises_each_sample() {
        let mut ln = LayerNorm::new(5);
        let x = input(4, 5);
        let y = ln.forward(x.as_ref()).to_owned();
        for i in 0..4 {
            let row: Vec<f64> = (0..5).map(|j| f64::from(y[(i, j)])).collect();
            let mean = row.iter().sum::<f64>() / 5.0;
            let var = row.iter().map(|v| (v - mean).powi(2)).sum::<f64>() / 5.0;
            assert!(mean.abs() < 1e-6, "{mean}");
            // var(x̂) = var / (var + eps) < 1 by the epsilon.
            let xr: Vec<f64> = (0..5).map(|j| f64::from(x[(i, j)])).collect();
            let xm = xr.iter().sum::<f64>() / 5.0;
            let xv = xr.iter().map(|v| (v - xm).powi(2)).sum::<f64>() / 5.0;
            assert!((var - xv / (xv + 1e-5)).abs() < 1e-5, "{var}");
        }
    }

    #[test]
    fn gradients_match_finite_differences() {
        let mut rng = vdd_core::Seeds::new(4).stream("t");
        let mut ln = LayerNorm::new(6);
        random_affine(&mut ln, &mut rng);
        let r = check_module(&mut ln, input(5, 6).as_ref(), 1e-2, 1e-2, &mut rng);
        assert!(r.input_error < 2e-3 && r.param_error < 2e-3, "{r:?}");
        // A strided (row-major) input takes the copying path and gives the same result.
        let x = input(5, 6);
        let xt = x.transpose().to_owned();
        let a = ln.forward(x.as_ref()).to_owned();
        let b = ln.forward(xt.transpose()).to_owned();
        assert_eq!(a, b);
    }

    /// The classic LayerNorm bug: treating mean and variance as constants in the backward
    /// pass (`dx = rstd · g ⊙ weight`). Parameter gradients stay right.
    struct NaiveBackward {
        ln: LayerNorm,
        x: Mat<f32>,
        dx: Mat<f32>,
    }
    impl Parameters for NaiveBackward {
        fn visit_params(&self, p: &str, f: &mut dyn FnMut(&str, &Param)) {
            self.ln.visit_params(p, f)
        }
        fn visit_params_mut(&mut self, p: &str, f: &mut dyn FnMut(&str, &mut Param)) {
            self.ln.visit_params_mut(p, f)
        }
    }
    impl Module for NaiveBackward {
        fn in_dim(&self) -> usize {
            self.ln.in_dim()
        }
        fn out_dim(&self) -> usize {
            self.ln.out_dim()
        }
        fn forward(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32> {
            self.x = x.to_owned();
            self.ln.forward(x)
        }
        fn backward(&mut self, g: MatRef<'_, f32>) -> MatRef<'_, f32> {
            self.ln.backward(g);
            let (n, d) = (self.x.nrows(), self.x.ncols());
            self.dx = Mat::from_fn(n, d, |i, j| {
                let row: Vec<f32> = (0..d).map(|k| self.x[(i, k)]).collect();
                let mean = row.iter().sum::<f32>() / d as f32;
                let var = row.iter().map(|v| (v - mean).powi(2)).sum::<f32>() / d as f32;
                g[(i, j)] * self.ln.weight.value[j] / (var + self.ln.eps()).sqrt()
            });
            self.dx.as_ref()
        }
    }

    #[test]
    fn a_wrong_layer_norm_backward_is_caught() {
        let mut rng = vdd_core::Seeds::new(5).stream("t");
        let mut ln = LayerNorm::new(6);
        random_affine(&mut ln, &mut rng);
        let mut broken = NaiveBackward { ln, x: Mat::zeros(0, 0), dx: Mat::zeros(0, 0) };
        let r = check_module(&mut broken, input(5, 6).as_ref(), 1e-2, 1e-2, &mut rng);
        assert!(r.param_error < 2e-3, "{r:?}");
        assert!(r.input_error > 0.1, "{r:?}");
    }

    #[test]
    fn bad_eps_is_an_error() {
        assert!(LayerNorm::new(3).with_eps(0.0).is_err());
        assert!(LayerNorm::new(3).with_eps(f32::NAN).is_err());
        assert_eq!(LayerNorm::new(3).with_eps(1e-6).unwrap().eps(), 1e-6);
    }
}
