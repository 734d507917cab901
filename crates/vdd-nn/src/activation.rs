//! Element-wise activations: ReLU, Tanh, Mish, GELU, SiLU, Softplus (and identity).

use faer::{Mat, MatRef};
use serde::{Deserialize, Serialize};
use vdd_core::{sigmoid, softplus};

use crate::module::{Module, col_slice, contiguous, ensure_shape, gather_row};
use crate::param::{Param, Parameters};

/// An element-wise nonlinearity. Names match PyTorch's modules (`nn.Mish`, `nn.GELU`, ...).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Activation {
    /// `x`.
    Identity,
    /// `max(x, 0)`.
    Relu,
    /// `tanh(x)`.
    Tanh,
    /// `x · tanh(softplus(x))`.
    Mish,
    /// `x · Φ(x)` with the exact Gaussian CDF (PyTorch's default `nn.GELU`).
    Gelu,
    /// `x · sigmoid(x)`.
    Silu,
    /// `log(1 + eˣ)`.
    Softplus,
}

const FRAC_1_SQRT_2: f32 = std::f32::consts::FRAC_1_SQRT_2;
const FRAC_1_SQRT_2PI: f32 = 0.398_942_3;

pub use vdd_core::gaussian::exp_fast;

/// Mish and its derivative with one exponential: with `e = eˣ`, `n = e(e + 2)`,
/// `tanh(softplus(x)) = n / (n + 2)` and `mish'(x) = t + 4x·e(e + 1) / (n + 2)²`.
#[inline(always)]
fn mish_with_derivative(x: f32) -> (f32, f32) {
    let e = exp_fast(x.clamp(-88.0, 20.0));
    let n = e * (e + 2.0);
    let q = 1.0 / (n + 2.0);
    let t = n * q;
    (x * t, t + 4.0 * x * e * (e + 1.0) * q * q)
}

/// SiLU and its derivative with one exponential.
#[inline(always)]
fn silu_with_derivative(x: f32) -> (f32, f32) {
    let s = 1.0 / (1.0 + exp_fast(-x));
    (x * s, s * (1.0 + x * (1.0 - s)))
}

impl Activation {
    /// `f(x)`.
    #[inline]
    pub fn apply(self, x: f32) -> f32 {
        match self {
            Activation::Identity => x,
            Activation::Relu => x.max(0.0),
            Activation::Tanh => x.tanh(),
            Activation::Mish => mish_with_derivative(x).0,
            Activation::Gelu => 0.5 * x * (1.0 + erf(x * FRAC_1_SQRT_2)),
            Activation::Silu => silu_with_derivative(x).0,
            Activation::Softplus => softplus(x),
        }
    }

    /// `f'(x)`.
    #[inline]
    pub fn derivative(self, x: f32) -> f32 {
        self.apply_with_derivative(x).1
    }

    /// `(f(x), f'(x))`, sharing the work between the two.
    #[inline]
    pub fn apply_with_derivative(self, x: f32) -> (f32, f32) {
        match self {
            Activation::Identity => (x, 1.0),
            Activation::Relu => {
                if x > 0.0 {
                    (x, 1.0)
                } else {
                    (0.0, 0.0)
                }
            }
            Activation::Tanh => {
                let t = x.tanh();
                (t, 1.0 - t * t)
            }
            Activation::Mish => mish_with_derivative(x),
            Activation::Gelu => {
                let cdf = 0.5 * (1.0 + erf(x * FRAC_1_SQRT_2));
                (x * cdf, cdf + x * FRAC_1_SQRT_2PI * (-0.5 * x * x).exp())
            }
            Activation::Silu => silu_with_derivative(x),
            Activation::Softplus => (softplus(x), sigmoid(x)),
        }
    }

    /// `y = f(x)` and `d = f'(x)` element-wise over slices of equal length (a tight loop that
    /// the compiler vectorises for ReLU, Mish and SiLU, with AVX2 where the CPU has it: the
    /// same bits either way, as nothing is fused or reordered).
    pub fn apply_slices(self, x: &[f32], y: &mut [f32], d: &mut [f32]) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2, checked just above.
            unsafe { self.apply_slices_avx2(x, y, d) };
            return;
        }
        self.apply_slices_portable(x, y, d)
    }

    /// [`Activation::apply_slices_portable`] compiled for AVX2.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn apply_slices_avx2(self, x: &[f32], y: &mut [f32], d: &mut [f32]) {
        self.apply_slices_portable(x, y, d)
    }

    /// `y = f(x)` element-wise over slices of equal length, without the derivative: the same
    /// bits as [`Activation::apply_slices`]'s `y` (inference, where nothing is differentiated).
    pub fn apply_values(self, x: &[f32], y: &mut [f32]) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2, checked just above.
            unsafe { self.apply_values_avx2(x, y) };
            return;
        }
        self.apply_values_portable(x, y)
    }

    /// [`Activation::apply_values_portable`] compiled for AVX2.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn apply_values_avx2(self, x: &[f32], y: &mut [f32]) {
        self.apply_values_portable(x, y)
    }

    /// The value half of [`Activation::apply_slices_portable`]: the same expressions, the
    /// derivative's left out.
    #[inline(always)]
    fn apply_values_portable(self, x: &[f32], y: &mut [f32]) {
        let y = &mut y[..x.len()];
        match self {
            Activation::Identity => y.copy_from_slice(x),
            Activation::Relu => {
                y.iter_mut().zip(x).for_each(|(y, &x)| *y = if x > 0.0 { x } else { 0.0 })
            }
            Activation::Mish => {
                y.iter_mut().zip(x).for_each(|(y, &x)| *y = mish_with_derivative(x).0)
            }
            Activation::Silu => {
                y.iter_mut().zip(x).for_each(|(y, &x)| *y = silu_with_derivative(x).0)
            }
            other => y.iter_mut().zip(x).for_each(|(y, &x)| *y = other.apply_with_derivative(x).0),
        }
    }

    #[inline(always)]
    fn apply_slices_portable(self, x: &[f32], y: &mut [f32], d: &mut [f32]) {
        let n = x.len();
        let (y, d) = (&mut y[..n], &mut d[..n]);
        match self {
            Activation::Identity => {
                y.copy_from_slice(x);
                d.fill(1.0);
            }
            Activation::Relu => {
                for i in 0..n {
                    let pos = x[i] > 0.0;
                    y[i] = if pos { x[i] } else { 0.0 };
                    d[i] = if pos { 1.0 } else { 0.0 };
                }
            }
            Activation::Mish => {
                for i in 0..n {
                    (y[i], d[i]) = mish_with_derivative(x[i]);
                }
            }
            Activation::Silu => {
                for i in 0..n {
                    (y[i], d[i]) = silu_with_derivative(x[i]);
                }
            }
            other => {
                for i in 0..n {
                    (y[i], d[i]) = other.apply_with_derivative(x[i]);
                }
            }
        }
    }
}

/// The error function, |error| < 1.2e-7 (Numerical Recipes' `erfc` Chebyshev fit).
pub fn erf(x: f32) -> f32 {
    let z = f64::from(x).abs();
    let t = 1.0 / (1.0 + 0.5 * z);
    let poly = -z * z - 1.265_512_23
        + t * (1.000_023_68
            + t * (0.374_091_96
                + t * (0.096_784_18
                    + t * (-0.186_288_06
                        + t * (0.278_868_07
                            + t * (-1.135_203_98
                                + t * (1.488_515_87 + t * (-0.822_152_23 + t * 0.170_872_77))))))));
    let erfc = t * poly.exp();
    let r = 1.0 - erfc;
    (if x >= 0.0 { r } else { -r }) as f32
}

/// An activation as a [`Module`] (no parameters). The forward pass stores `f'(x)` beside
/// `f(x)`, so the backward pass is one multiplication.
///
/// ```
/// use vdd_nn::{Activation, ActivationLayer, Module};
/// let mut relu = ActivationLayer::new(Activation::Relu, 2);
/// let x = faer::mat![[-1.0f32, 2.0]];
/// assert_eq!(relu.forward(x.as_ref())[(0, 1)], 2.0);
/// let g = relu.backward(faer::mat![[1.0f32, 1.0]].as_ref());
/// assert_eq!((g[(0, 0)], g[(0, 1)]), (0.0, 1.0));
/// ```
#[derive(Debug, Clone)]
pub struct ActivationLayer {
    activation: Activation,
    dim: usize,
    scratch: Mat<f32>,
    output: Mat<f32>,
    derivative: Mat<f32>,
    grad_input: Mat<f32>,
    /// One observation at a time (a policy acting in a control loop): the row gathered into
    /// contiguous memory, its outputs and derivatives, so the element-wise loop vectorises
    /// instead of running once per column.
    row: Vec<f32>,
    /// Whether the last forward took that path (its derivatives are in `row`).
    single_row: bool,
    /// Whether the last forward kept its derivatives (not [`Module::forward_inference`]).
    kept: bool,
}

impl ActivationLayer {
    /// An activation layer on `dim` features.
    pub fn new(activation: Activation, dim: usize) -> Self {
        Self {
            activation,
            dim,
            scratch: Mat::zeros(0, 0),
            output: Mat::zeros(0, 0),
            derivative: Mat::zeros(0, 0),
            grad_input: Mat::zeros(0, 0),
            row: Vec::new(),
            single_row: false,
            kept: false,
        }
    }

    /// Which nonlinearity this layer applies.
    pub fn activation(&self) -> Activation {
        self.activation
    }
}

impl Parameters for ActivationLayer {
    fn visit_params(&self, _prefix: &str, _f: &mut dyn FnMut(&str, &Param)) {}
    fn visit_params_mut(&mut self, _prefix: &str, _f: &mut dyn FnMut(&str, &mut Param)) {}
}

impl Module for ActivationLayer {
    fn in_dim(&self) -> usize {
        self.dim
    }
    fn out_dim(&self) -> usize {
        self.dim
    }

    fn forward(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32> {
        assert_eq!(x.ncols(), self.dim, "activation: input width");
        let (n, d) = (x.nrows(), self.dim);
        self.single_row = n == 1;
        self.kept = true;
        if n == 1 {
            // The same element-wise function, so the same bits as the column loop below; the
            // output is a contiguous row.
            self.row.resize(3 * d, 0.0);
            let (xs, rest) = self.row.split_at_mut(d);
            let (ys, ds) = rest.split_at_mut(d);
            gather_row(x, xs);
            self.activation.apply_slices(xs, ys, ds);
            return MatRef::from_row_major_slice(ys, 1, d);
        }
        let x = contiguous(x, &mut self.scratch);
        ensure_shape(&mut self.output, n, d);
        ensure_shape(&mut self.derivative, n, d);
        for j in 0..d {
            self.activation.apply_slices(
                col_slice(x, j),
                self.output.col_as_slice_mut(j),
                self.derivative.col_as_slice_mut(j),
            );
        }
        self.output.as_ref()
    }

    fn forward_inference(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32> {
        assert_eq!(x.ncols(), self.dim, "activation: input width");
        let (n, d) = (x.nrows(), self.dim);
        self.kept = false;
        if n == 1 {
            self.row.resize(2 * d, 0.0);
            let (xs, ys) = self.row.split_at_mut(d);
            gather_row(x, xs);
            self.activation.apply_values(xs, ys);
            return MatRef::from_row_major_slice(ys, 1, d);
        }
        let x = contiguous(x, &mut self.scratch);
        ensure_shape(&mut self.output, n, d);
        for j in 0..d {
            self.activation.apply_values(col_slice(x, j), self.output.col_as_slice_mut(j));
        }
        self.output.as_ref()
    }

    fn backward(&mut self, grad_out: MatRef<'_, f32>) -> MatRef<'_, f32> {
        assert!(self.kept, "activation: backward without a forward that kept its derivatives");
        let d = self.dim;
        if self.single_row {
            assert_eq!((grad_out.nrows(), grad_out.ncols()), (1, d), "activation: grad shape");
            ensure_shape(&mut self.grad_input, 1, d);
            for (j, dv) in self.row[2 * d..3 * d].iter().enumerate() {
                self.grad_input[(0, j)] = grad_out[(0, j)] * dv;
            }
            return self.grad_input.as_ref();
        }
        let n = self.derivative.nrows();
        assert_eq!((grad_out.nrows(), grad_out.ncols()), (n, d), "activation: grad shape");
        let g = contiguous(grad_out, &mut self.scratch);
        ensure_shape(&mut self.grad_input, n, d);
        for j in 0..d {
            let (g, dv) = (col_slice(g, j), self.derivative.col_as_slice(j));
            let dst = self.grad_input.col_as_slice_mut(j);
            for i in 0..n {
                dst[i] = g[i] * dv[i];
            }
        }
        self.grad_input.as_ref()
    }
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;
    use crate::gradcheck::check_module;

    /// Every activation.
    pub(crate) const ALL: [Activation; 7] = [
        Activation::Identity,
        Activation::Relu,
        Activation::Tanh,
        Activation::Mish,
        Activation::Gelu,
        Activation::Silu,
        Activation::Softplus,
    ];

    /// Reference `f(x)` in f64 from the textbook definitions.
    fn reference(act: Activation, x: f64) -> f64 {
        let softplus = |x: f64| if x > 30.0 { x } else { x.exp().ln_1p() };
        let sigmoid = |x: f64| 1.0 / (1.0 + (-x).exp());
        match act {
            Activation::Identity => x,
            Activation::Relu => x.max(0.0),
            Activation::Tanh => x.tanh(),
            Activation::Mish => x * softplus(x).tanh(),
            // Φ via the erf series is overkill; a high-order Simpson rule of the density is
            // accurate to 1e-12 here.
            Activation::Gelu => x * normal_cdf(x),
            Activation::Silu => x * sigmoid(x),
            Activation::Softplus => softplus(x),
        }
    }

    fn normal_cdf(x: f64) -> f64 {
        let (a, n) = (-12.0f64, 4000);
        let h = (x - a) / n as f64;
        let pdf = |t: f64| (-0.5 * t * t).exp() / (2.0 * std::f64::consts::PI).sqrt();
        let mut s = pdf(a) + pdf(x);
        for k in 1..n {
            s += pdf(a + k as f64 * h) * if k % 2 == 1 { 4.0 } else { 2.0 };
        }
        s * h / 3.0
    }

    #[test]
    fn values_and_derivatives_match_references() {
        for act in ALL {
            for k in 0..=400 {
                let x = -10.0 + 0.05 * k as f64 + 0.0123; // avoids ReLU's kink at 0
                let (y, d) = act.apply_with_derivative(x as f32);
                let x = f64::from(x as f32);
                let ry = reference(act, x);
                let h = 1e-5;
                let rd = (reference(act, x + h) - reference(act, x - h)) / (2.0 * h);
                assert!(
                    (f64::from(y) - ry).abs() <= 1e-6 * (1.0 + ry.abs()),
                    "{act:?}({x}) = {y}, want {ry}"
                );
                assert!(
                    (f64::from(d) - rd).abs() <= 2e-6 * (1.0 + rd.abs()),
                    "{act:?}'({x}) = {d}, want {rd}"
                );
                assert_eq!(y, act.apply(x as f32));
                assert_eq!(d, act.derivative(x as f32));
            }
            // Far tails stay finite.
            for x in [-1e4f32, -90.0, 25.0, 90.0, 1e4] {
                let (y, d) = act.apply_with_derivative(x);
                assert!(y.is_finite() && d.is_finite(), "{act:?} at {x}: {y} {d}");
            }
        }
    }

    #[test]
    fn slice_kernels_match_the_scalar_functions() {
        let x: Vec<f32> = (0..257).map(|i| (i as f32 - 128.0) * 0.37).collect();
        let (mut y, mut d) = (vec![0.0; x.len()], vec![0.0; x.len()]);
        // The dispatched (AVX2 here) and the portable loops: the scalar function's bits.
        for act in ALL {
            act.apply_slices(&x, &mut y, &mut d);
            for i in 0..x.len() {
                assert_eq!((y[i], d[i]), act.apply_with_derivative(x[i]), "{act:?} at {}", x[i]);
            }
            act.apply_slices_portable(&x, &mut y, &mut d);
            for i in 0..x.len() {
                assert_eq!((y[i], d[i]), act.apply_with_derivative(x[i]), "{act:?} at {}", x[i]);
            }
        }
    }

    #[test]
    fn layer_gradients_match_finite_differences() {
        let mut rng = vdd_core::Seeds::new(7).stream("t");
        // Entries k/4.4 − 1.1 + 0.05: at least 0.05 away from ReLU's kink, |x| ≤ 1.2.
        let x = Mat::from_fn(6, 5, |i, j| ((i * 7 + j * 3) % 11) as f32 / 4.4 - 1.1 + 0.05);
        for act in ALL {
            let mut layer = ActivationLayer::new(act, 5);
            let r = check_module(&mut layer, x.as_ref(), 1e-2, 1e-2, &mut rng);
            assert!(r.input_error < 1e-3, "{act:?}: {r:?}");
        }
    }

    #[test]
    fn one_row_at_a_time_gives_the_batch_rows_and_gradients() {
        let x = Mat::from_fn(4, 37, |i, j| (i * 37 + j) as f32 * 0.11 - 8.0);
        let g = Mat::from_fn(4, 37, |i, j| ((i + 2 * j) % 5) as f32 - 2.0);
        for act in ALL {
            let mut batch = ActivationLayer::new(act, 37);
            let y = batch.forward(x.as_ref()).to_owned();
            let gx = batch.backward(g.as_ref()).to_owned();
            let mut single = ActivationLayer::new(act, 37);
            for i in 0..4 {
                let yi = single.forward(x.subrows(i, 1)).to_owned();
                let gi = single.backward(g.subrows(i, 1)).to_owned();
                for j in 0..37 {
                    assert_eq!(yi[(0, j)], y[(i, j)], "{act:?} output ({i}, {j})");
                    assert_eq!(gi[(0, j)], gx[(i, j)], "{act:?} gradient ({i}, {j})");
                }
            }
        }
    }
}
