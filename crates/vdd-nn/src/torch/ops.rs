//! Row-major forward kernels shared by the imported networks: token matrices are kept
//! row-major (`rows x features`, one token per row) so attention reads each token's features
//! contiguously, and every dense layer runs as one `faer` matrix product over all tokens.

use faer::linalg::matmul::matmul;
use faer::{Accum, MatMut, MatRef, Par};

use vdd_core::gaussian::exp_fast;

use crate::{LayerNorm, Linear, Module as _};

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
    matmul(yv, Accum::Add, xv, lin.weight_t(), 1.0, Par::Seq);
}

/// PyTorch's `LayerNorm` over each row of `x` (`rows x dim`, row-major) into `out`, with the
/// layer's `ε` (biased variance, two passes in `f32` as PyTorch's CPU kernel).
pub(crate) fn layer_norm_rows(ln: &LayerNorm, x: &[f32], out: &mut Vec<f32>) {
    let d = ln.weight.value.len();
    out.resize(x.len(), 0.0);
    if d == 0 {
        return;
    }
    let (w, b, eps) = (&ln.weight.value[..], &ln.bias.value[..], ln.eps());
    let inv_d = 1.0 / d as f32;
    for (xr, yr) in x.chunks_exact(d).zip(out.chunks_exact_mut(d)) {
        let mean = lane_sum(xr) * inv_d;
        for (y, &v) in yr.iter_mut().zip(xr) {
            *y = v - mean;
        }
        let var = lane_sum_sq(yr) * inv_d;
        let rstd = 1.0 / (var + eps).sqrt();
        for ((y, &wj), &bj) in yr.iter_mut().zip(w).zip(b) {
            *y = *y * rstd * wj + bj;
        }
    }
}

/// `Σ x` in eight interleaved partial sums (vectorises).
#[inline]
fn lane_sum(x: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let chunks = x.chunks_exact(8);
    let rest: f32 = chunks.remainder().iter().sum();
    for c in chunks {
        for l in 0..8 {
            acc[l] += c[l];
        }
    }
    acc.iter().sum::<f32>() + rest
}

/// `Σ x²` in eight interleaved partial sums.
#[inline]
fn lane_sum_sq(x: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let chunks = x.chunks_exact(8);
    let rest: f32 = chunks.remainder().iter().map(|v| v * v).sum();
    for c in chunks {
        for l in 0..8 {
            acc[l] += c[l] * c[l];
        }
    }
    acc.iter().sum::<f32>() + rest
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

/// Copies a (possibly strided) matrix into a row-major buffer.
pub(crate) fn gather_rows(m: MatRef<'_, f32>, out: &mut Vec<f32>) {
    let (n, k) = (m.nrows(), m.ncols());
    out.resize(n * k, 0.0);
    for i in 0..n {
        for j in 0..k {
            out[i * k + j] = m[(i, j)];
        }
    }
}

/// Multi-head scaled dot-product attention of one sequence: query row `i` of `q` (row stride
/// `qs`, features at `0..d`) attends to the rows `j < limits[i]` of `k` and `v` (row strides
/// `ks` and `vs`); every mask of the imported networks (causal, diffusion_policy's memory mask,
/// none) keeps such a prefix, as `masked_fill(-inf)` before the softmax would. `heads` divides
/// `d`; `y` (`limits.len() x d`, row-major) receives the heads side by side; `p` is scratch of
/// at least `max(limits)` floats. A row with `limits[i] == 0` (which PyTorch would turn into
/// NaN) stays zero; no imported network builds one.
#[allow(clippy::too_many_arguments)]
pub(crate) fn attention(
    (q, qs): (&[f32], usize),
    (k, ks): (&[f32], usize),
    (v, vs): (&[f32], usize),
    limits: &[usize],
    d: usize,
    heads: usize,
    p: &mut [f32],
    y: &mut [f32],
) {
    let hs = d / heads;
    let scale = 1.0 / (hs as f32).sqrt();
    for (i, &lim) in limits.iter().enumerate() {
        let yrow = &mut y[i * d..(i + 1) * d];
        yrow.fill(0.0);
        if lim == 0 {
            continue;
        }
        let p = &mut p[..lim];
        for h in 0..heads {
            let c = h * hs;
            let qi = &q[i * qs + c..i * qs + c + hs];
            let mut max = f32::NEG_INFINITY;
            for (j, pj) in p.iter_mut().enumerate() {
                let kj = &k[j * ks + c..j * ks + c + hs];
                let s = qi.iter().zip(kj).map(|(a, b)| a * b).sum::<f32>() * scale;
                *pj = s;
                max = max.max(s);
            }
            let mut sum = 0.0f32;
            for pj in p.iter_mut() {
                *pj = exp_fast(*pj - max);
                sum += *pj;
            }
            let inv = 1.0 / sum;
            let yi = &mut yrow[c..c + hs];
            for (j, &pj) in p.iter().enumerate() {
                let w = pj * inv;
                let vj = &v[j * vs + c..j * vs + c + hs];
                for (o, &x) in yi.iter_mut().zip(vj) {
                    *o += w * x;
                }
            }
        }
    }
}

/// Row limits of a causal mask (`j ≤ i`) over `len` rows, into `out`.
pub(crate) fn causal_limits(len: usize, out: &mut Vec<usize>) {
    out.clear();
    out.extend(1..=len);
}

/// `x += y` element-wise.
pub(crate) fn add_assign(x: &mut [f32], y: &[f32]) {
    for (a, b) in x.iter_mut().zip(y) {
        *a += b;
    }
}
