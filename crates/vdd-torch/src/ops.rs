//! Row-major forward kernels shared by the imported networks (the transformers' token-column
//! kernels are in `cols`).

use faer::{Accum, MatMut, MatRef};
use vdd_nn::matmul;

use vdd_nn::{Linear, Module as _};

/// `out = x Wᵀ + b` for `rows` row-major rows of `x` (`rows x in`); `out` is resized to
/// `rows x out` (row-major) and reuses its allocation.
pub(crate) fn affine_rows(lin: &Linear, x: &[f32], rows: usize, out: &mut Vec<f32>) {
    let (k, m) = (lin.in_dim(), lin.out_dim());
    debug_assert_eq!(x.len(), rows * k);
    out.resize(rows * m, 0.0);
    for row in out.chunks_exact_mut(m) {
        row.copy_from_slice(&lin.bias.value);
    }
    if rows == 0 || m == 0 || k == 0 {
        return;
    }
    let xv = MatRef::from_row_major_slice(x, rows, k);
    let yv = MatMut::from_row_major_slice_mut(out.as_mut_slice(), rows, m);
    matmul(yv, Accum::Add, xv, lin.weight_t(), 1.0);
}

/// PyTorch's exact (erf) GELU, `x Φ(x)`, branch-free in `f32`: erf by Abramowitz–Stegun
/// 7.1.26 (absolute error below 1.5e-7) with [`vdd_core::gaussian::exp_fast`].
#[inline(always)]
pub(crate) fn gelu(x: f32) -> f32 {
    const P: f32 = 0.327_591_1;
    const A: [f32; 5] = [0.254_829_6, -0.284_496_74, 1.421_413_7, -1.453_152_1, 1.061_405_4];
    let z = (x * std::f32::consts::FRAC_1_SQRT_2).abs();
    let t = 1.0 / (1.0 + P * z);
    let poly = t * (A[0] + t * (A[1] + t * (A[2] + t * (A[3] + t * A[4]))));
    let erf_abs = 1.0 - poly * vdd_core::gaussian::exp_fast(-z * z);
    0.5 * x * (1.0 + erf_abs.copysign(x))
}
