//! `torch.nn.GroupNorm`, `torch.nn.Mish` and the sinusoidal diffusion-step embedding of
//! diffusion_policy / LeRobot, forward only.

use faer::reborrow::ReborrowMut as _;
use faer::{Mat, MatMut};

use crate::error::NnError;
use crate::param::{Param, Parameters, join_name};

/// PyTorch's default `GroupNorm` epsilon.
pub const GROUP_NORM_EPS: f32 = 1e-5;

/// `mish(x) = x · tanh(softplus(x))`, computed with one exponential:
/// `tanh(log(1 + eˣ)) = n / (n + 2)` with `n = eˣ (eˣ + 2)`.
///
/// ```
/// let m = vdd_nn::torch::mish(1.0);
/// assert!((m - 0.865_098_4).abs() < 1e-5, "{m}");
/// assert!((vdd_nn::torch::mish(30.0) - 30.0).abs() < 1e-5);
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
/// vdd_nn::torch::sinusoidal_embedding(&[0.0], out.as_mut()).unwrap();
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
/// channels` (see [`crate::torch::Conv1d`]): each sample's channels are split into `groups`
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
        let cpg = ch / self.groups;
        let count = (cpg * len) as f64;
        for b in 0..batch {
            let rows = b * len..(b + 1) * len;
            for g in 0..self.groups {
                let chans = g * cpg..(g + 1) * cpg;
                // Per-channel runs summed in f32 (short), accumulated in f64.
                let mut sum = 0.0f64;
                for c in chans.clone() {
                    sum += f64::from(x.col_as_slice(c)[rows.clone()].iter().sum::<f32>());
                }
                let mean = sum / count;
                let m32 = mean as f32;
                let mut ss = 0.0f64;
                for c in chans.clone() {
                    let seg = &x.col_as_slice(c)[rows.clone()];
                    ss += f64::from(seg.iter().map(|&v| (v - m32) * (v - m32)).sum::<f32>());
                }
                // Σ(x − m32)² = Σ(x − mean)² + n (mean − m32)², the rounding of the mean.
                let dm = mean - f64::from(m32);
                let var = (ss / count - dm * dm).max(0.0);
                let inv = 1.0 / (var + f64::from(self.eps)).sqrt();
                for c in chans {
                    let w = f64::from(self.weight.value[c]);
                    let a = (inv * w) as f32;
                    let s = (f64::from(self.bias.value[c]) - mean * inv * w) as f32;
                    let seg = &mut x.col_as_slice_mut(c)[rows.clone()];
                    if then_mish {
                        seg.iter_mut().for_each(|v| *v = mish(*v * a + s));
                    } else {
                        seg.iter_mut().for_each(|v| *v = *v * a + s);
                    }
                }
            }
        }
        Ok(())
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
