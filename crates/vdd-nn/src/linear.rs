//! Fully connected layer `y = x Wᵀ + b`.

use crate::gemm::matmul;
use faer::{Accum, Mat, MatRef};
use rand::Rng as _;

use crate::error::NnError;
use crate::init::{BiasInit, Init};
use crate::module::{Module, ensure_shape, gather_row};
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
    /// One contiguous input row and its output (the single-row path of `forward`).
    row: Vec<f32>,
    /// Whether the last forward took that path (its input is in `row`, not `input`).
    single_row: bool,
    /// Whether the last forward kept its input (not [`Module::forward_inference`]).
    kept: bool,
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
            row: Vec::new(),
            single_row: false,
            kept: false,
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

    /// `y = x W[cols]ᵀ + b[cols]` for one input row `x` (length `in`) and the output columns
    /// `cols` only (`y.len() == cols.len()`), with the kernel `forward` uses on a single row: the
    /// same bits as those columns of `forward` on `x` as a `1 x in` matrix. For acting with one
    /// expert's slice of a shared output layer.
    ///
    /// ```
    /// use vdd_nn::{Linear, Module};
    /// let mut rng = vdd_core::Seeds::new(0).stream("init");
    /// let mut layer = Linear::new(3, 4, &mut rng);
    /// let x = [0.5f32, -1.0, 2.0];
    /// let mut y = [0.0f32; 2];
    /// layer.forward_row_cols(&x, 2..4, &mut y);
    /// let full = layer.forward(faer::MatRef::from_row_major_slice(&x, 1, 3));
    /// assert_eq!((y[0], y[1]), (full[(0, 2)], full[(0, 3)]));
    /// ```
    ///
    /// # Panics
    /// If `x.len() != in`, `cols` reaches past `out`, or `y.len() != cols.len()`.
    pub fn forward_row_cols(&self, x: &[f32], cols: std::ops::Range<usize>, y: &mut [f32]) {
        assert_eq!(x.len(), self.in_dim, "Linear: input width");
        assert!(cols.end <= self.out_dim, "Linear: columns past the output");
        assert_eq!(y.len(), cols.len(), "Linear: output length");
        let k = self.in_dim;
        affine_row(
            &self.weight.value[cols.start * k..cols.end * k],
            &self.bias.value[cols.clone()],
            x,
            y,
        );
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

impl Linear {
    /// `y = x Wᵀ + b`, keeping `x` for `backward` when `keep`.
    fn affine(&mut self, x: MatRef<'_, f32>, keep: bool) -> MatRef<'_, f32> {
        assert_eq!(x.ncols(), self.in_dim, "Linear: input width");
        let n = x.nrows();
        self.single_row = n == 1;
        self.kept = keep;
        if n == 1 {
            // One row (acting on one observation): a general matrix product runs scalar code
            // here, the row kernel runs SIMD (see `affine_row`). The output is a contiguous row.
            let (k, m) = (self.in_dim, self.out_dim);
            self.row.resize(k + m, 0.0);
            let (xs, ys) = self.row.split_at_mut(k);
            gather_row(x, xs);
            affine_row(&self.weight.value, &self.bias.value, xs, ys);
            return MatRef::from_row_major_slice(ys, 1, m);
        }
        if keep {
            ensure_shape(&mut self.input, n, self.in_dim);
            self.input.copy_from(x);
        }
        ensure_shape(&mut self.output, n, self.out_dim);
        // y = b (broadcast), then y += x Wᵀ: one pass over the output for the bias.
        for (j, &b) in self.bias.value.iter().enumerate() {
            self.output.col_as_slice_mut(j).fill(b);
        }
        let wt = MatRef::from_column_major_slice(&self.weight.value, self.in_dim, self.out_dim);
        matmul(self.output.as_mut(), Accum::Add, x, wt, 1.0);
        self.output.as_ref()
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
        self.affine(x, true)
    }

    fn forward_inference(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32> {
        self.affine(x, false)
    }

    fn backward(&mut self, grad_out: MatRef<'_, f32>) -> MatRef<'_, f32> {
        assert!(self.kept, "Linear: backward without a forward that kept its input");
        let k = self.in_dim;
        let input = match self.single_row {
            true => MatRef::from_row_major_slice(&self.row[..k], 1, k),
            false => self.input.as_ref(),
        };
        let n = input.nrows();
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
        matmul(dwt, Accum::Add, input.transpose(), grad_out, 1.0);
        for (j, db) in self.bias.grad.iter_mut().enumerate() {
            let col = grad_out.col(j);
            *db += match col.try_as_col_major() {
                Some(c) => c.as_slice().iter().sum::<f32>(),
                None => col.iter().sum::<f32>(),
            };
        }
        ensure_shape(&mut self.grad_input, n, self.in_dim);
        let wt = MatRef::from_column_major_slice(&self.weight.value, self.in_dim, self.out_dim);
        matmul(self.grad_input.as_mut(), Accum::Replace, grad_out, wt.transpose(), 1.0);
        self.grad_input.as_ref()
    }
}

/// Accumulator lanes of [`affine_row`]: one AVX register.
const LANES: usize = 8;

/// `y[j] = b[j] + Σ_i w[j, i] x[i]` for a row-major `w` of `y.len()` rows of `x.len()`.
///
/// Each dot product runs in [`LANES`] independent partial sums of fused multiply-adds (exact
/// `f32::mul_add`), combined in a fixed order ([`reduce_lanes`]): the AVX2 + FMA and the
/// portable versions compute the same bits.
fn affine_row(w: &[f32], b: &[f32], x: &[f32], y: &mut [f32]) {
    debug_assert_eq!(w.len(), x.len() * y.len());
    debug_assert_eq!(b.len(), y.len());
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx2") && std::arch::is_x86_feature_detected!("fma") {
        // SAFETY: the CPU supports AVX2 and FMA, checked just above.
        unsafe { affine_row_fma(w, b, x, y) };
        return;
    }
    affine_row_portable(w, b, x, y)
}

/// [`affine_row`] in AVX2 registers with FMA: eight rows of `w` at a time (eight independent
/// sums, each input chunk loaded once, the eight folds done together), then the rows past the
/// last group of eight one by one.
///
/// # Safety
/// The CPU must support AVX2 and FMA.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx2,fma")]
unsafe fn affine_row_fma(w: &[f32], b: &[f32], x: &[f32], y: &mut [f32]) {
    use std::arch::x86_64::{
        __m256, _mm_add_ps, _mm_cvtss_f32, _mm256_add_ps, _mm256_castps256_ps128,
        _mm256_extractf128_ps, _mm256_fmadd_ps, _mm256_hadd_ps, _mm256_loadu_ps,
        _mm256_permute2f128_ps, _mm256_setzero_ps, _mm256_storeu_ps,
    };
    let k = x.len();
    // The loads below read through raw pointers: the shapes must hold in release builds too.
    assert!(w.len() == k * y.len() && b.len() == y.len(), "affine_row: shapes");
    if k == 0 {
        y.copy_from_slice(b);
        return;
    }
    let split = k - k % LANES;
    let (xp, rest_x) = (x.as_ptr(), &x[split..]);
    // The lane sums of `acc.len()` rows from row `j`.
    let lane_sums = |j: usize, acc: &mut [__m256]| {
        let mut c = 0;
        while c < split {
            // SAFETY: AVX2 and FMA, as this function's; the loads read 8 floats at `c` with
            // `c + 8 <= split <= k` of `x` and of row `j + r` of `w` (`y.len()` rows of `k`).
            unsafe {
                let xv = _mm256_loadu_ps(xp.add(c));
                for (r, a) in acc.iter_mut().enumerate() {
                    *a = _mm256_fmadd_ps(_mm256_loadu_ps(w.as_ptr().add((j + r) * k + c)), xv, *a);
                }
            }
            c += LANES;
        }
    };
    // The remainder of row `j` on its folded sum, then the bias.
    let finish = |j: usize, s: f32| b[j] + add_rest(s, &w[j * k + split..(j + 1) * k], rest_x);
    let groups = y.len() / 8;
    for g in 0..groups {
        let j = 8 * g;
        let mut acc = [_mm256_setzero_ps(); 8];
        lane_sums(j, &mut acc);
        // `reduce_lanes` for eight rows at once: pairs, then pairs of pairs (both within each
        // 128-bit half), then the two halves.
        let q0 = _mm256_hadd_ps(_mm256_hadd_ps(acc[0], acc[1]), _mm256_hadd_ps(acc[2], acc[3]));
        let q1 = _mm256_hadd_ps(_mm256_hadd_ps(acc[4], acc[5]), _mm256_hadd_ps(acc[6], acc[7]));
        let sums = _mm256_add_ps(
            _mm256_permute2f128_ps::<0x20>(q0, q1),
            _mm256_permute2f128_ps::<0x31>(q0, q1),
        );
        if split == k {
            // SAFETY: `b` and `y` hold 8 floats from `j` (`j + 8 <= y.len() == b.len()`).
            unsafe {
                let v = _mm256_add_ps(_mm256_loadu_ps(b.as_ptr().add(j)), sums);
                _mm256_storeu_ps(y.as_mut_ptr().add(j), v);
            }
        } else {
            let mut s = [0.0f32; 8];
            // SAFETY: `s` holds 8 floats.
            unsafe { _mm256_storeu_ps(s.as_mut_ptr(), sums) };
            for (r, s) in s.into_iter().enumerate() {
                y[j + r] = finish(j + r, s);
            }
        }
    }
    for j in 8 * groups..y.len() {
        let mut acc = [_mm256_setzero_ps()];
        lane_sums(j, &mut acc);
        let p = _mm256_hadd_ps(acc[0], acc[0]);
        let q = _mm256_hadd_ps(p, p);
        let s = _mm_add_ps(_mm256_castps256_ps128(q), _mm256_extractf128_ps::<1>(q));
        y[j] = finish(j, _mm_cvtss_f32(s));
    }
}

/// [`affine_row`] in portable code.
fn affine_row_portable(w: &[f32], b: &[f32], x: &[f32], y: &mut [f32]) {
    let k = x.len();
    if k == 0 {
        y.copy_from_slice(b);
        return;
    }
    let split = k - k % LANES;
    for ((yj, bj), row) in y.iter_mut().zip(b).zip(w.chunks_exact(k)) {
        let acc = lane_sums(&row[..split], &x[..split]);
        *yj = bj + reduce_lanes(acc, &row[split..], &x[split..]);
    }
}

/// `acc[l] = Σ_c r[c·LANES + l] · v[c·LANES + l]` (lengths a multiple of [`LANES`]), each
/// term a fused multiply-add in `c` order.
#[inline(always)]
fn lane_sums(r: &[f32], v: &[f32]) -> [f32; LANES] {
    let mut acc = [0.0f32; LANES];
    for (r, v) in r.chunks_exact(LANES).zip(v.chunks_exact(LANES)) {
        for l in 0..LANES {
            acc[l] = r[l].mul_add(v[l], acc[l]);
        }
    }
    acc
}

/// The lanes' partial sums folded as `((a0 + a1) + (a2 + a3)) + ((a4 + a5) + (a6 + a7))`, then
/// the remainder's products in order (fused): the one summation order both versions share.
#[inline(always)]
fn reduce_lanes(a: [f32; LANES], rest_w: &[f32], rest_x: &[f32]) -> f32 {
    let s = ((a[0] + a[1]) + (a[2] + a[3])) + ((a[4] + a[5]) + (a[6] + a[7]));
    add_rest(s, rest_w, rest_x)
}

/// `s` plus the remainder's products `rest_w[i] · rest_x[i]`, fused, in order: the tail both
/// versions of [`affine_row`] share.
#[inline(always)]
fn add_rest(s: f32, rest_w: &[f32], rest_x: &[f32]) -> f32 {
    rest_w.iter().zip(rest_x).fold(s, |s, (w, x)| w.mul_add(*x, s))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gradcheck::check_module;

    fn layer(k: usize, m: usize) -> Linear {
        Linear::new(k, m, &mut vdd_core::Seeds::new(3).stream("init"))
    }

    fn rows(n: usize, k: usize) -> Mat<f32> {
        Mat::from_fn(n, k, |i, j| ((i * 7 + j * 3) % 11) as f32 * 0.3 - 1.4)
    }

    /// `x Wᵀ + b` in f64.
    fn reference(l: &Linear, x: MatRef<'_, f32>) -> Mat<f64> {
        let (k, m) = (l.in_dim(), l.out_dim());
        Mat::from_fn(x.nrows(), m, |i, j| {
            (0..k).map(|c| l.weight.value[j * k + c] as f64 * x[(i, c)] as f64).sum::<f64>()
                + l.bias.value[j] as f64
        })
    }

    #[test]
    fn one_row_and_a_batch_compute_the_affine_map() {
        // Widths below, at and past the kernel's lanes, with and without a remainder.
        for (k, m) in [(0, 3), (1, 1), (5, 4), (16, 2), (21, 7), (64, 64), (70, 9)] {
            let mut l = layer(k, m);
            let x = rows(4, k);
            let want = reference(&l, x.as_ref());
            let batch = l.forward(x.as_ref()).to_owned();
            for i in 0..4 {
                let one = l.forward(x.subrows(i, 1)).to_owned();
                for j in 0..m {
                    let tol = 1e-5 * (1.0 + want[(i, j)].abs());
                    assert!((one[(0, j)] as f64 - want[(i, j)]).abs() < tol, "k={k} row {i}");
                    assert!((batch[(i, j)] as f64 - want[(i, j)]).abs() < tol, "k={k} batch");
                }
            }
        }
    }

    #[test]
    fn a_single_row_backward_matches_finite_differences() {
        let mut l = layer(21, 5);
        let mut rng = vdd_core::Seeds::new(4).stream("check");
        let r = check_module(&mut l, rows(1, 21).as_ref(), 1e-2, 1e-2, &mut rng);
        assert!(r.input_error < 1e-2 && r.param_error < 1e-2, "{r:?}");
    }

    #[test]
    fn the_simd_and_portable_kernels_give_the_same_bits() {
        // Rows in groups of eight and past them; inputs shorter than, a multiple of and past
        // the lanes.
        for (k, m) in [(70, 9), (64, 64), (64, 5), (4, 64), (16, 3), (33, 12), (48, 8), (7, 17)] {
            let l = layer(k, m);
            let x: Vec<f32> = (0..k)
                .map(|i| (i as f32 * 0.37).sin() * 1e3f32.powf((i % 3) as f32 - 1.0))
                .collect();
            let mut a = vec![0.0; m];
            let mut b = vec![0.0; m];
            affine_row(&l.weight.value, &l.bias.value, &x, &mut a);
            affine_row_portable(&l.weight.value, &l.bias.value, &x, &mut b);
            assert_eq!(
                a.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                b.iter().map(|v| v.to_bits()).collect::<Vec<_>>(),
                "k {k}, m {m}"
            );
        }
    }

    #[test]
    fn selected_columns_are_those_of_the_full_row() {
        let mut l = layer(21, 12);
        let x: Vec<f32> = (0..21).map(|i| i as f32 * 0.1 - 1.0).collect();
        let full = l.forward(MatRef::from_row_major_slice(&x, 1, 21)).to_owned();
        let mut y = vec![0.0; 4];
        l.forward_row_cols(&x, 4..8, &mut y);
        for (c, v) in y.iter().enumerate() {
            assert_eq!(*v, full[(0, 4 + c)]);
        }
    }
}
