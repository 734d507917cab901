//! Fully connected layer `y = x Wᵀ + b`.

use faer::linalg::matmul::matmul;
use faer::{Accum, Mat, MatRef, Par};
use rand::Rng as _;

use crate::error::NnError;
use crate::init::{BiasInit, Init};
use crate::module::{Module, ensure_shape};
use crate::param::{Param, Parameters, join_name};

/// A fully connected layer with PyTorch's layout: `weight` is `[out, in]`, `bias` is `[out]`.
///
/// ```
/// use vdd_nn::{Linear, Module};
/// let mut rng = vdd_core::Seeds::new(0).stream("init");
/// let mut layer = Linear::new(3, 2, &mut rng);
/// let x = faer::Mat::<f32>::zeros(4, 3);
/// let y = layer.forward(x.as_ref());
/// assert_eq!((y.nrows(), y.ncols()), (4, 2));
/// ```
#[derive(Debug, Clone)]
pub struct Linear {
    /// `[out, in]`, row-major (PyTorch layout).
    pub weight: Param,
    /// `[out]`.
    pub bias: Param,
    in_dim: usize,
    out_dim: usize,
    input: Mat<f32>,
    output: Mat<f32>,
    grad_input: Mat<f32>,
}

impl Linear {
    /// A layer with PyTorch's default initialisation: weight and bias `U(−1/√in, 1/√in)`.
    pub fn new(in_dim: usize, out_dim: usize, rng: &mut vdd_core::Rng) -> Self {
        let bound = 1.0 / (in_dim.max(1) as f32).sqrt();
        let weight = (0..in_dim * out_dim).map(|_| rng.random_range(-bound..=bound)).collect();
        let bias = (0..out_dim).map(|_| rng.random_range(-bound..=bound)).collect();
        Self::from_params(
            in_dim,
            out_dim,
            Param::new(&[out_dim, in_dim], weight),
            Param::new(&[out_dim], bias),
        )
    }

    /// A layer from explicit parameters (`weight` row-major `[out, in]`).
    pub fn from_params(in_dim: usize, out_dim: usize, weight: Param, bias: Param) -> Self {
        assert_eq!(weight.shape, [out_dim, in_dim]);
        assert_eq!(bias.shape, [out_dim]);
        Self {
            weight,
            bias,
            in_dim,
            out_dim,
            input: Mat::zeros(0, 0),
            output: Mat::zeros(0, 0),
            grad_input: Mat::zeros(0, 0),
        }
    }

    /// Re-initialises the weight with `init` (see [`Init`]); on error the layer is unchanged.
    pub fn init_weight(&mut self, init: Init, rng: &mut vdd_core::Rng) -> Result<(), NnError> {
        self.weight.value = init.sample(self.out_dim, self.in_dim, rng)?;
        Ok(())
    }

    /// Re-initialises the bias with `init` (see [`BiasInit`]); on error the layer is unchanged.
    pub fn init_bias(&mut self, init: BiasInit, rng: &mut vdd_core::Rng) -> Result<(), NnError> {
        self.bias.value = init.sample(self.out_dim, self.in_dim, rng)?;
        Ok(())
    }

    /// `Wᵀ` as an `in x out` view (the row-major `[out, in]` buffer read column-major).
    pub fn weight_t(&self) -> MatRef<'_, f32> {
        MatRef::from_column_major_slice(&self.weight.value, self.in_dim, self.out_dim)
    }
}

impl Parameters for Linear {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        f(&join_name(prefix, "weight"), &self.weight);
        f(&join_name(prefix, "bias"), &self.bias);
    }
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        f(&join_name(prefix, "weight"), &mut self.weight);
        f(&join_name(prefix, "bias"), &mut self.bias);
    }
}

impl Module for Linear {
    fn in_dim(&self) -> usize {
        self.in_dim
    }
    fn out_dim(&self) -> usize {
        self.out_dim
    }

    fn forward(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32> {
        assert_eq!(x.ncols(), self.in_dim, "Linear: input width");
        let n = x.nrows();
        ensure_shape(&mut self.input, n, self.in_dim);
        self.input.copy_from(x);
        ensure_shape(&mut self.output, n, self.out_dim);
        // y = b (broadcast), then y += x Wᵀ: one pass over the output for the bias.
        for (j, &b) in self.bias.value.iter().enumerate() {
            self.output.col_as_slice_mut(j).fill(b);
        }
        let wt = MatRef::from_column_major_slice(&self.weight.value, self.in_dim, self.out_dim);
        matmul(self.output.as_mut(), Accum::Add, x, wt, 1.0, Par::Seq);
        self.output.as_ref()
    }

    fn backward(&mut self, grad_out: MatRef<'_, f32>) -> MatRef<'_, f32> {
        let n = self.input.nrows();
        assert_eq!((grad_out.nrows(), grad_out.ncols()), (n, self.out_dim), "Linear: grad shape");
        if self.weight.grad.len() != self.weight.len() || self.bias.grad.len() != self.bias.len() {
            self.weight.zero_grad();
            self.bias.zero_grad();
        }
        // dWᵀ (in x out) += xᵀ · gy
        let dwt = faer::MatMut::from_column_major_slice_mut(
            &mut self.weight.grad,
            self.in_dim,
            self.out_dim,
        );
        matmul(dwt, Accum::Add, self.input.transpose(), grad_out, 1.0, Par::Seq);
        for (j, db) in self.bias.grad.iter_mut().enumerate() {
            let col = grad_out.col(j);
            *db += match col.try_as_col_major() {
                Some(c) => c.as_slice().iter().sum::<f32>(),
                None => col.iter().sum::<f32>(),
            };
        }
        ensure_shape(&mut self.grad_input, n, self.in_dim);
        let wt = MatRef::from_column_major_slice(&self.weight.value, self.in_dim, self.out_dim);
        matmul(self.grad_input.as_mut(), Accum::Replace, grad_out, wt.transpose(), 1.0, Par::Seq);
        self.grad_input.as_ref()
    }
}
