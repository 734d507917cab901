//! Element-wise activations: ReLU, Tanh, Mish, GELU, SiLU, Softplus (and identity).

use faer::{Mat, MatRef};
use serde::{Deserialize, Serialize};
use vdd_core::{sigmoid, softplus};

use crate::module::{ensure_shape, Module};
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

impl Activation {
    /// `f(x)`.
    #[inline]
    pub fn apply(self, x: f32) -> f32 {
        match self {
            Activation::Identity => x,
            Activation::Relu => x.max(0.0),
            Activation::Tanh => x.tanh(),
            Activation::Mish => x * softplus(x).tanh(),
            Activation::Gelu => 0.5 * x * (1.0 + erf(x * FRAC_1_SQRT_2)),
            Activation::Silu => x * sigmoid(x),
            Activation::Softplus => softplus(x),
        }
    }

    /// `f'(x)`.
    #[inline]
    pub fn derivative(self, x: f32) -> f32 {
        match self {
            Activation::Identity => 1.0,
            Activation::Relu => {
                if x > 0.0 {
                    1.0
                } else {
                    0.0
                }
            }
            Activation::Tanh => {
                let t = x.tanh();
                1.0 - t * t
            }
            Activation::Mish => {
                let t = softplus(x).tanh();
                t + x * (1.0 - t * t) * sigmoid(x)
            }
            Activation::Gelu => {
                0.5 * (1.0 + erf(x * FRAC_1_SQRT_2)) + x * FRAC_1_SQRT_2PI * (-0.5 * x * x).exp()
            }
            Activation::Silu => {
                let s = sigmoid(x);
                s * (1.0 + x * (1.0 - s))
            }
            Activation::Softplus => sigmoid(x),
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

/// An activation as a [`Module`] (no parameters); caches its input for the backward pass.
#[derive(Debug, Clone)]
pub struct ActivationLayer {
    activation: Activation,
    dim: usize,
    input: Mat<f32>,
    output: Mat<f32>,
    grad_input: Mat<f32>,
}

impl ActivationLayer {
    /// An activation layer on `dim` features.
    pub fn new(activation: Activation, dim: usize) -> Self {
        Self {
            activation,
            dim,
            input: Mat::zeros(0, 0),
            output: Mat::zeros(0, 0),
            grad_input: Mat::zeros(0, 0),
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
        ensure_shape(&mut self.input, n, d);
        self.input.copy_from(x);
        ensure_shape(&mut self.output, n, d);
        let act = self.activation;
        for j in 0..d {
            let src = self.input.col_as_slice(j);
            let dst = self.output.col_as_slice_mut(j);
            for (y, &x) in dst.iter_mut().zip(src) {
                *y = act.apply(x);
            }
        }
        self.output.as_ref()
    }

    fn backward(&mut self, grad_out: MatRef<'_, f32>) -> MatRef<'_, f32> {
        let (n, d) = (self.input.nrows(), self.dim);
        assert_eq!((grad_out.nrows(), grad_out.ncols()), (n, d), "activation: grad shape");
        ensure_shape(&mut self.grad_input, n, d);
        let act = self.activation;
        for j in 0..d {
            let src = self.input.col_as_slice(j);
            let g = grad_out.col(j);
            let dst = self.grad_input.col_as_slice_mut(j);
            for i in 0..n {
                dst[i] = g[i] * act.derivative(src[i]);
            }
        }
        self.grad_input.as_ref()
    }
}
