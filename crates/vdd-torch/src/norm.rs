//! `torch.nn.GroupNorm`, `torch.nn.Mish` and the sinusoidal diffusion-step embedding of
//! diffusion_policy / LeRobot, forward only.

use faer::reborrow::ReborrowMut as _;
use faer::{Mat, MatMut};

use super::dispatch::avx2_dispatch;
use super::flush::flush_subnormal;
use vdd_nn::{NnError, Param, Parameters, join_name};

/// PyTorch's default `GroupNorm` epsilon.
pub const GROUP_NORM_EPS: f32 = 1e-5;

/// `mish(x) = x · tanh(softplus(x))`, computed with one exponential:
/// `tanh(log(1 + eˣ)) = n / (n + 2)` with `n = eˣ (eˣ + 2)`.
///
/// ```
/// let m = vdd_torch::mish(1.0);
/// assert!((m - 0.865_098_4).abs() < 1e-5, "{m}");
/// assert!((vdd_torch::mish(30.0) - 30.0).abs() < 1e-5);
/// ```
#[inline(always)]
pub fn mish(x: f32) -> f32 {
    // Branch-free so loops vectorise; beyond 20, n/(n + 2) rounds to 1 in f32.
    let e = vdd_core::gaussian::exp_fast(x.min(20.0));
    let n = e * (e + 2.0);
    x * n / (n + 2.0)
}

/// Applies [`mish`] in place.
pub fn mish_inplace(x: &mut [f32]) {
    for v in x {
        *v = mish(*v);
    }
}

/// Applies [`mish`] in place to every element of `m`.
pub fn mish_mat(mut m: MatMut<'_, f32>) {
    for j in 0..m.ncols() {
        match m.rb_mut().col_mut(j).try_as_col_major_mut() {
            Some(c) => mish_inplace(c.as_slice_mut()),
            None => {
                for i in 0..m.nrows() {
                    m[(i, j)] = mish(m[(i, j)]);
                }
            }
        }
    }
}

/// diffusion_policy's / LeRobot's `SinusoidalPosEmb(dim)` of per-row (possibly fractional)
/// diffusion steps into `out` (`steps.len() × dim`): `[sin(t f_i), cos(t f_i)]` with
/// `f_i = exp(−i · ln(10000)/(dim/2 − 1))`, `i < dim/2`.
///
/// ```
/// let mut out = faer::Mat::<f32>::zeros(1, 4);
/// vdd_torch::sinusoidal_embedding(&[0.0], out.as_mut()).unwrap();
/// assert_eq!([out[(0, 0)], out[(0, 1)], out[(0, 2)], out[(0, 3)]], [0.0, 0.0, 1.0, 1.0]);
/// ```
pub fn sinusoidal_embedding(steps: &[f32], mut out: MatMut<'_, f32>) -> Result<(), NnError> {
    let dim = out.ncols();
    if dim < 4 || dim % 2 != 0 || out.nrows() != steps.len() {
        return Err(NnError::Config(format!(
            "sinusoidal embedding: need an even width >= 4 and one row per step, got {}x{dim} for {} steps",
            out.nrows(),
            steps.len()
        )));
    }
    let half = dim / 2;
    // As PyTorch: the scale is a double turned f32 when multiplied into the f32 arange.
    let scale = -((10000f64).ln() / (half - 1) as f64) as f32;
    for i in 0..half {
        let f = (i as f32 * scale).exp();
        for (r, &t) in steps.iter().enumerate() {
            let a = t * f;
            out[(r, i)] = a.sin();
            out[(r, half + i)] = a.cos();
        }
    }
    Ok(())
}

/// `torch.nn.GroupNorm(groups, channels)` (affine) on sequences stored as `(batch · len) ×
/// channels` (see [`crate::Conv1d`]): each sample's channels are split into `groups`
/// consecutive groups, normalised over the group's channels and time steps, then scaled and
/// shifted per channel. Works in place.
#[derive(Debug, Clone)]
pub struct GroupNorm {
    /// `[channels]` scale.
    pub weight: Param,
    /// `[channels]` shift.
    pub bias: Param,
    groups: usize,
    eps: f32,
}

impl GroupNorm {
    /// A group norm with unit scale and zero shift.
    pub fn new(groups: usize, channels: usize) -> Result<Self, NnError> {
        if groups == 0 || channels % groups != 0 {
            return Err(NnError::Config(format!(
                "GroupNorm: {channels} channels do not split into {groups} groups"
            )));
        }
        Ok(Self {
            weight: Param::buffer(&[channels], vec![1.0; channels]),
            bias: Param::buffer(&[channels], vec![0.0; channels]),
            groups,
            eps: GROUP_NORM_EPS,
        })
    }

    /// Normalises `x` (`(batch · len) × channels`) in place.
    pub fn forward_inplace(&self, x: &mut Mat<f32>, batch: usize) -> Result<(), NnError> {
        self.run(x, batch, false)
    }

    /// Normalises `x` in place and applies [`mish`] (`Conv1dBlock`'s GroupNorm → Mish in one
    /// pass).
    pub fn forward_mish_inplace(&self, x: &mut Mat<f32>, batch: usize) -> Result<(), NnError> {
        self.run(x, batch, true)
    }

    fn run(&self, x: &mut Mat<f32>, batch: usize, then_mish: bool) -> Result<(), NnError> {
        let ch = self.weight.len();
        if batch == 0 || x.nrows() % batch != 0 || x.ncols() != ch {
            return Err(NnError::Config(format!(
                "GroupNorm: input {}x{} is not (batch {batch} · len) x {ch}",
                x.nrows(),
                x.ncols()
            )));
        }
        let len = x.nrows() / batch;
        if len == 0 {
            return Ok(());
        }
        let (w, b, eps) = (&self.weight.value[..], &self.bias.value[..], self.eps);
        // Whole samples at a time, about GROUP_CHUNK rows, so the scratch stays in L1.
        let per_chunk = (GROUP_CHUNK / len.max(1)).clamp(1, batch);
        let mut scratch = vec![0.0f32; 3 * per_chunk * len];
        let shape = (batch, len, per_chunk);
        group_norm_dispatch(w, b, self.groups, eps, x, shape, then_mish, &mut scratch);
        Ok(())
    }
}

/// `Σ a` in `f64`, in four interleaved partial sums (vectorises; a short dependency chain).
#[inline(always)]
fn sum_f64(a: &[f32]) -> f64 {
    let mut p = [0.0f64; 4];
    let chunks = a.chunks_exact(4);
    let rest: f64 = chunks.remainder().iter().map(|&v| f64::from(v)).sum();
    for c in chunks {
        for l in 0..4 {
            p[l] += f64::from(c[l]);
        }
    }
    (p[0] + p[1]) + (p[2] + p[3]) + rest
}

/// Rows of one chunk of [`GroupNorm`]'s pass (whole samples).
const GROUP_CHUNK: usize = 1024;

avx2_dispatch! {
    /// [`GroupNorm`]'s kernel.
    #[allow(clippy::too_many_arguments)]
    fn group_norm_dispatch(
        w: &[f32],
        b: &[f32],
        groups: usize,
        eps: f32,
        x: &mut Mat<f32>,
        shape: (usize, usize, usize),
        then_mish: bool,
        scratch: &mut [f32],
    ) => group_norm_body
}

/// Each sample's group statistics (per-row `f32` sums over the group's channels, accumulated
/// over the sample's rows in `f64`; the variance about the `f32` mean), then every
/// element normalised, scaled, shifted (and passed through [`mish`]; subnormal results flushed
/// to zero) in one pass over its channel's contiguous rows, the sample's mean and inverse deviation spread over its rows.
#[allow(clippy::too_many_arguments)]
#[inline(always)]
fn group_norm_body(
    w: &[f32],
    bias: &[f32],
    groups: usize,
    eps: f32,
    x: &mut Mat<f32>,
    (batch, len, per_chunk): (usize, usize, usize),
    then_mish: bool,
    scratch: &mut [f32],
) {
    let cpg = w.len() / groups;
    let count = (cpg * len) as f64;
    let (acc, rest) = scratch.split_at_mut(per_chunk * len);
    let (mexp, iexp) = rest.split_at_mut(per_chunk * len);
    for b0 in (0..batch).step_by(per_chunk) {
        let nb = per_chunk.min(batch - b0);
        let (r0, rl) = (b0 * len, nb * len);
        let (acc, mexp, iexp) = (&mut acc[..rl], &mut mexp[..rl], &mut iexp[..rl]);
        for g in 0..groups {
            let chans = g * cpg..(g + 1) * cpg;
            acc.fill(0.0);
            for c in chans.clone() {
                let xs = &x.col_as_slice(c)[r0..r0 + rl];
                acc.iter_mut().zip(xs).for_each(|(a, &v)| *a += v);
            }
            for (a, m) in acc.chunks_exact(len).zip(mexp.chunks_exact_mut(len)) {
                m.fill((sum_f64(a) / count) as f32);
            }
            acc.fill(0.0);
            for c in chans.clone() {
                let xs = &x.col_as_slice(c)[r0..r0 + rl];
                for ((a, &v), &m) in acc.iter_mut().zip(xs).zip(mexp.iter()) {
                    let e = v - m;
                    *a += e * e;
                }
            }
            for (a, i) in acc.chunks_exact(len).zip(iexp.chunks_exact_mut(len)) {
                let var = (sum_f64(a) / count).max(0.0);
                i.fill((1.0 / (var + f64::from(eps)).sqrt()) as f32);
            }
            for c in chans {
                let (wc, bc) = (w[c], bias[c]);
                let ys = &mut x.col_as_slice_mut(c)[r0..r0 + rl];
                let it = ys.iter_mut().zip(mexp.iter()).zip(iexp.iter());
                // A channel at its group's mean with zero shift (or a subnormal input) makes a
                // subnormal value here: flushed, so the layers after it never compute on one.
                if then_mish {
                    it.for_each(|((y, &m), &i)| *y = flush_subnormal(mish((*y - m) * i * wc + bc)));
                } else {
                    it.for_each(|((y, &m), &i)| *y = flush_subnormal((*y - m) * i * wc + bc));
                }
            }
        }
    }
}

impl Parameters for GroupNorm {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        f(&join_name(prefix, "weight"), &self.weight);
        f(&join_name(prefix, "bias"), &self.bias);
    }
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        f(&join_name(prefix, "weight"), &mut self.weight);
        f(&join_name(prefix, "bias"), &mut self.bias);
    }
}
