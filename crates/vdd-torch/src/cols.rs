//! Token-column forward kernels of the imported transformers: a batch of `n` sequences of `len`
//! tokens is a `(len · n) × features` column-major [`Mat`] whose row `t · n + b` holds token `t`
//! of sample `b`, so token `t` of every sample is the row block `t·n .. (t+1)·n`.
//!
//! Every feature is a contiguous column, so layer norms, activations and the attention's
//! scores, softmax and weighted sums are element-wise loops across the batch (compiled for AVX2
//! where the CPU has it, the same bits either way: nothing is fused or reordered), and each
//! dense layer is one `faer` product in faer's preferred layout.

use std::ops::Range;

use faer::{Accum, Mat, MatMut, MatRef};
use vdd_core::gaussian::exp_fast;
use vdd_nn::matmul;

use super::conv::ensure;
use super::dispatch::avx2_dispatch;
use super::norm::mish;
use super::ops::gelu;
use vdd_nn::{LayerNorm, Linear};

/// Rows a layer norm or an attention head processes at a time (their scratch stays in L1).
const BLOCK: usize = 64;

/// `out = x Wᵀ + b` into a view, for `wt = Wᵀ` (`in × out`, e.g. a column range of
/// [`Linear::weight_t`]) and `bias` (`out`).
pub(crate) fn affine_into(
    wt: MatRef<'_, f32>,
    bias: &[f32],
    x: MatRef<'_, f32>,
    mut out: MatMut<'_, f32>,
) {
    debug_assert_eq!((x.ncols(), bias.len()), (wt.nrows(), wt.ncols()));
    for (j, &b) in bias.iter().enumerate() {
        out.as_mut().col_mut(j).fill(b);
    }
    if x.nrows() > 0 && x.ncols() > 0 {
        matmul(out, Accum::Add, x, wt, 1.0);
    }
}

/// `out = x Wᵀ + b` with `out` resized to `x.nrows() × wt.ncols()`.
pub(crate) fn affine(wt: MatRef<'_, f32>, bias: &[f32], x: MatRef<'_, f32>, out: &mut Mat<f32>) {
    ensure(out, x.nrows(), wt.ncols());
    affine_into(wt, bias, x, out.as_mut());
}

/// `out = lin(x)`, `out` resized.
pub(crate) fn linear(lin: &Linear, x: MatRef<'_, f32>, out: &mut Mat<f32>) {
    affine(lin.weight_t(), &lin.bias.value, x, out);
}

/// `x += lin(h)` (a residual branch's output layer added in place).
pub(crate) fn linear_add(lin: &Linear, h: MatRef<'_, f32>, x: &mut Mat<f32>) {
    debug_assert_eq!((h.nrows(), lin.bias.value.len()), (x.nrows(), x.ncols()));
    for (j, &b) in lin.bias.value.iter().enumerate() {
        x.col_as_slice_mut(j).iter_mut().for_each(|v| *v += b);
    }
    if h.nrows() > 0 && h.ncols() > 0 {
        matmul(x.as_mut(), Accum::Add, h, lin.weight_t(), 1.0);
    }
}

/// Writes `pos` (one token's position embedding, `features` wide) added to each row of the
/// `n`-row block of `x` starting at row `r0`.
pub(crate) fn add_row(x: &mut Mat<f32>, r0: usize, n: usize, pos: &[f32]) {
    for (c, &p) in pos.iter().enumerate() {
        x.col_as_slice_mut(c)[r0..r0 + n].iter_mut().for_each(|v| *v += p);
    }
}

/// The columns `first..first + width` of a token-column matrix.
#[derive(Clone, Copy)]
pub(crate) struct Cols<'a> {
    m: &'a Mat<f32>,
    first: usize,
}

impl<'a> Cols<'a> {
    /// Columns from `first` on.
    pub(crate) fn new(m: &'a Mat<f32>, first: usize) -> Self {
        Self { m, first }
    }

    #[inline(always)]
    fn col(&self, c: usize) -> &'a [f32] {
        self.m.col_as_slice(self.first + c)
    }
}

/// PyTorch's `LayerNorm` of the rows `rows` of `x` (biased variance, two passes in `f32`) into
/// `out`, resized to `rows.len() × features`.
pub(crate) fn layer_norm(ln: &LayerNorm, x: &Mat<f32>, rows: Range<usize>, out: &mut Mat<f32>) {
    ensure(out, rows.len(), x.ncols());
    layer_norm_dispatch(ln, x, rows, out);
}

avx2_dispatch! {
    /// [`layer_norm`]'s kernel.
    fn layer_norm_dispatch(ln: &LayerNorm, x: &Mat<f32>, rows: Range<usize>, out: &mut Mat<f32>)
        => layer_norm_body
}

#[inline(always)]
fn layer_norm_body(ln: &LayerNorm, x: &Mat<f32>, rows: Range<usize>, out: &mut Mat<f32>) {
    let (w, b, eps) = (&ln.weight.value, &ln.bias.value, ln.eps());
    let d = x.ncols();
    if d == 0 {
        return;
    }
    let inv_d = 1.0 / d as f32;
    let (mut mean, mut rstd) = ([0.0f32; BLOCK], [0.0f32; BLOCK]);
    for o0 in (0..rows.len()).step_by(BLOCK) {
        let len = BLOCK.min(rows.len() - o0);
        let r0 = rows.start + o0;
        let (mean, rstd) = (&mut mean[..len], &mut rstd[..len]);
        mean.fill(0.0);
        for c in 0..d {
            let xs = &x.col_as_slice(c)[r0..r0 + len];
            mean.iter_mut().zip(xs).for_each(|(m, &v)| *m += v);
        }
        mean.iter_mut().for_each(|m| *m *= inv_d);
        rstd.fill(0.0);
        for c in 0..d {
            let xs = &x.col_as_slice(c)[r0..r0 + len];
            for ((s, &m), &v) in rstd.iter_mut().zip(mean.iter()).zip(xs) {
                let e = v - m;
                *s += e * e;
            }
        }
        rstd.iter_mut().for_each(|s| *s = 1.0 / (*s * inv_d + eps).sqrt());
        for c in 0..d {
            let (wc, bc) = (w[c], b[c]);
            let xs = &x.col_as_slice(c)[r0..r0 + len];
            let ys = &mut out.col_as_slice_mut(c)[o0..o0 + len];
            for (((y, &v), &m), &s) in ys.iter_mut().zip(xs).zip(mean.iter()).zip(rstd.iter()) {
                *y = (v - m) * s * wc + bc;
            }
        }
    }
}

/// The element-wise activations of the imported transformers.
#[derive(Clone, Copy, PartialEq)]
pub(crate) enum Act {
    /// PyTorch's exact GELU ([`gelu`]).
    Gelu,
    /// Mish ([`mish`]).
    Mish,
    /// SiLU, `x σ(x)`.
    Silu,
    /// ReLU.
    Relu,
    /// The logistic sigmoid.
    Sigmoid,
    /// PReLU with this slope.
    Prelu(f32),
}

avx2_dispatch! {
    /// Applies `act` to every element of `m` in place.
    fn activate(act: Act, m: &mut Mat<f32>) => activate_body
}

#[inline(always)]
fn activate_body(act: Act, m: &mut Mat<f32>) {
    for c in 0..m.ncols() {
        let col = m.col_as_slice_mut(c);
        match act {
            Act::Gelu => col.iter_mut().for_each(|v| *v = gelu(*v)),
            Act::Mish => col.iter_mut().for_each(|v| *v = mish(*v)),
            Act::Silu => col.iter_mut().for_each(|v| *v = *v / (1.0 + exp_fast(-*v))),
            Act::Relu => col.iter_mut().for_each(|v| *v = v.max(0.0)),
            Act::Sigmoid => col.iter_mut().for_each(|v| *v = 1.0 / (1.0 + exp_fast(-*v))),
            Act::Prelu(a) => col.iter_mut().for_each(|v| *v = if *v >= 0.0 { *v } else { a * *v }),
        }
    }
}

/// Multi-head scaled dot-product attention of `n` sequences: query token `i` (rows
/// `i·n .. (i+1)·n` of `q`) attends to the key tokens `j < limits[i]` of `k` and `v`; every mask
/// of the imported networks (causal, diffusion_policy's memory mask, none) keeps such a prefix,
/// as `masked_fill(-inf)` before the softmax would. `heads` divides `d` (the width of `q`, `k`,
/// `v`); `y` is resized to `(limits.len() · n) × d` and receives the heads side by side; `p` is
/// scratch. A query with `limits[i] == 0` (which PyTorch would turn into NaN) gives zeros; no
/// imported network builds one.
#[allow(clippy::too_many_arguments)]
pub(crate) fn attention(
    (q, k, v): (Cols<'_>, Cols<'_>, Cols<'_>),
    n: usize,
    limits: &[usize],
    d: usize,
    heads: usize,
    y: &mut Mat<f32>,
    p: &mut Vec<f32>,
) {
    ensure(y, limits.len() * n, d);
    let most = limits.iter().copied().max().unwrap_or(0);
    p.resize(most * BLOCK, 0.0);
    attention_dispatch((q, k, v), n, limits, heads, y, p);
}

avx2_dispatch! {
    /// [`attention`]'s kernel.
    fn attention_dispatch(
        qkv: (Cols<'_>, Cols<'_>, Cols<'_>),
        n: usize,
        limits: &[usize],
        heads: usize,
        y: &mut Mat<f32>,
        p: &mut [f32],
    ) => attention_body
}

#[inline(always)]
fn attention_body(
    (q, k, v): (Cols<'_>, Cols<'_>, Cols<'_>),
    n: usize,
    limits: &[usize],
    heads: usize,
    y: &mut Mat<f32>,
    p: &mut [f32],
) {
    let d = y.ncols();
    let hs = d / heads.max(1);
    let scale = 1.0 / (hs as f32).sqrt();
    for (i, &lim) in limits.iter().enumerate() {
        for b0 in (0..n).step_by(BLOCK) {
            let bl = BLOCK.min(n - b0);
            let qr = i * n + b0;
            for h in 0..heads {
                let cs = h * hs..(h + 1) * hs;
                if lim == 0 {
                    cs.for_each(|c| y.col_as_slice_mut(c)[qr..qr + bl].fill(0.0));
                    continue;
                }
                // Scores s_j = (q · k_j) scale, one lane per sequence.
                for j in 0..lim {
                    let s = &mut p[j * BLOCK..j * BLOCK + bl];
                    s.fill(0.0);
                    let kr = j * n + b0;
                    for c in cs.clone() {
                        let (qc, kc) = (&q.col(c)[qr..qr + bl], &k.col(c)[kr..kr + bl]);
                        s.iter_mut().zip(qc).zip(kc).for_each(|((s, &a), &b)| *s += a * b);
                    }
                    s.iter_mut().for_each(|s| *s *= scale);
                }
                // Softmax over j.
                let mut max = [f32::NEG_INFINITY; BLOCK];
                for j in 0..lim {
                    let s = &p[j * BLOCK..j * BLOCK + bl];
                    max[..bl].iter_mut().zip(s).for_each(|(m, &s)| *m = m.max(s));
                }
                let mut sum = [0.0f32; BLOCK];
                for j in 0..lim {
                    let s = &mut p[j * BLOCK..j * BLOCK + bl];
                    for ((s, &m), t) in s.iter_mut().zip(&max[..bl]).zip(&mut sum[..bl]) {
                        *s = exp_fast(*s - m);
                        *t += *s;
                    }
                }
                sum[..bl].iter_mut().for_each(|t| *t = 1.0 / *t);
                for j in 0..lim {
                    let s = &mut p[j * BLOCK..j * BLOCK + bl];
                    s.iter_mut().zip(&sum[..bl]).for_each(|(s, &inv)| *s *= inv);
                }
                // y = Σ_j p_j v_j.
                for c in cs {
                    let yc = &mut y.col_as_slice_mut(c)[qr..qr + bl];
                    yc.fill(0.0);
                    for j in 0..lim {
                        let (s, vc) = (&p[j * BLOCK..j * BLOCK + bl], &v.col(c)[j * n + b0..]);
                        yc.iter_mut().zip(s).zip(vc).for_each(|((o, &w), &x)| *o += w * x);
                    }
                }
            }
        }
    }
}

/// Row limits of a causal mask (`j ≤ i`) over `len` tokens, into `out`.
pub(crate) fn causal_limits(len: usize, out: &mut Vec<usize>) {
    out.clear();
    out.extend(1..=len);
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The definition, one sequence and one head at a time, on the same layout.
    fn naive(q: &Mat<f32>, kv: &Mat<f32>, n: usize, limits: &[usize], heads: usize) -> Mat<f32> {
        let d = q.ncols();
        let hs = d / heads;
        let mut y = Mat::zeros(limits.len() * n, d);
        for b in 0..n {
            for (i, &lim) in limits.iter().enumerate() {
                for h in 0..heads {
                    let cs = h * hs..(h + 1) * hs;
                    let s: Vec<f32> = (0..lim)
                        .map(|j| {
                            cs.clone().map(|c| q[(i * n + b, c)] * kv[(j * n + b, c)]).sum::<f32>()
                                / (hs as f32).sqrt()
                        })
                        .collect();
                    let m = s.iter().copied().fold(f32::NEG_INFINITY, f32::max);
                    let e: Vec<f32> = s.iter().map(|v| (v - m).exp()).collect();
                    let z: f32 = e.iter().sum();
                    for c in cs.clone() {
                        y[(i * n + b, c)] =
                            (0..lim).map(|j| e[j] / z * kv[(j * n + b, d + c)]).sum();
                    }
                }
            }
        }
        y
    }

    #[test]
    fn attention_matches_the_definition_across_blocks_and_masks() {
        // 70 sequences: one full block of lanes and a partial one.
        let (n, d, heads) = (70, 6, 3);
        let val = |r: usize, c: usize| ((r * 7 + c * 13) % 23) as f32 / 7.0 - 1.5;
        for limits in [vec![1, 2, 3, 4], vec![4, 4, 4], vec![2, 3, 3, 3, 3]] {
            let keys = *limits.iter().max().unwrap();
            let q = Mat::from_fn(limits.len() * n, d, val);
            let kv = Mat::from_fn(keys * n, 2 * d, |r, c| val(r + 5, c + 1));
            let (mut y, mut p) = (Mat::new(), Vec::new());
            let cols = (Cols::new(&q, 0), Cols::new(&kv, 0), Cols::new(&kv, d));
            attention(cols, n, &limits, d, heads, &mut y, &mut p);
            let want = naive(&q, &kv, n, &limits, heads);
            for r in 0..want.nrows() {
                for c in 0..d {
                    assert!((y[(r, c)] - want[(r, c)]).abs() < 1e-5, "{limits:?} ({r}, {c})");
                }
            }
        }
    }

    #[test]
    fn layer_norm_of_a_row_range_matches_the_definition() {
        let mut ln = LayerNorm::new(5);
        ln.weight.value = vec![1.0, 0.5, -1.0, 2.0, 0.25];
        ln.bias.value = vec![0.0, 0.1, 0.2, -0.3, 0.4];
        let x = Mat::from_fn(150, 5, |r, c| ((r * 3 + c * 11) % 17) as f32 * 0.3 - 2.0);
        let mut out = Mat::new();
        layer_norm(&ln, &x, 10..140, &mut out);
        assert_eq!((out.nrows(), out.ncols()), (130, 5));
        for r in 0..130 {
            let row: Vec<f32> = (0..5).map(|c| x[(r + 10, c)]).collect();
            let m = row.iter().sum::<f32>() / 5.0;
            let v = row.iter().map(|a| (a - m) * (a - m)).sum::<f32>() / 5.0;
            for c in 0..5 {
                let want =
                    (row[c] - m) / (v + ln.eps()).sqrt() * ln.weight.value[c] + ln.bias.value[c];
                assert!((out[(r, c)] - want).abs() < 1e-5, "({r}, {c})");
            }
        }
    }
}
