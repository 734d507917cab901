//! Gaussian helpers on a mean `μ` and a lower-triangular scale `L` (`Σ = L Lᵀ`).
//!
//! `L` is stored row-major as `d * d` floats with zeros above the diagonal; a diagonal scale
//! is the special case with zeros below it too. These are the per-sample kernels used by the
//! experts, the MoE likelihood and the VDD expert step; they never allocate.

/// `ln(2π)`.
pub const LN_2PI: f32 = 1.837_877_1;

/// Solves `L y = x` in place (forward substitution).
#[inline]
pub fn solve_lower_in_place(l: &[f32], x: &mut [f32]) {
    let d = x.len();
    for i in 0..d {
        let row = &l[i * d..i * d + i];
        let mut s = x[i];
        for (k, lik) in row.iter().enumerate() {
            s -= lik * x[k];
        }
        x[i] = s / l[i * d + i];
    }
}

/// Solves `Lᵀ y = x` in place (back substitution).
#[inline]
pub fn solve_upper_t_in_place(l: &[f32], x: &mut [f32]) {
    let d = x.len();
    for i in (0..d).rev() {
        let mut s = x[i];
        for k in i + 1..d {
            s -= l[k * d + i] * x[k];
        }
        x[i] = s / l[i * d + i];
    }
}

/// `Σ log L_ii`, i.e. `½ log det Σ`.
#[inline]
pub fn half_log_det(l: &[f32], d: usize) -> f32 {
    (0..d).map(|i| l[i * d + i].ln()).sum()
}

/// `log N(a; μ, L Lᵀ)`. `work` is scratch of length `d`.
///
/// ```
/// use vdd_core::gaussian::{log_density, LN_2PI};
/// let l = [2.0f32, 0.0, 0.0, 1.0];
/// let mut work = [0.0; 2];
/// let lp = log_density(&[0.0, 0.0], &[0.0, 0.0], &l, &mut work);
/// assert!((lp - (-LN_2PI - 2.0f32.ln())).abs() < 1e-6);
/// ```
#[inline]
pub fn log_density(a: &[f32], mean: &[f32], l: &[f32], work: &mut [f32]) -> f32 {
    let d = a.len();
    for i in 0..d {
        work[i] = a[i] - mean[i];
    }
    solve_lower_in_place(l, work);
    let maha: f32 = work.iter().map(|y| y * y).sum();
    -0.5 * maha - half_log_det(l, d) - 0.5 * d as f32 * LN_2PI
}

/// `log N(a; μ, L Lᵀ)` and its gradient `∇_a = −Σ⁻¹ (a − μ)` written into `grad`.
#[inline]
pub fn log_density_and_grad(a: &[f32], mean: &[f32], l: &[f32], grad: &mut [f32]) -> f32 {
    let d = a.len();
    for i in 0..d {
        grad[i] = a[i] - mean[i];
    }
    solve_lower_in_place(l, grad);
    let maha: f32 = grad.iter().map(|y| y * y).sum();
    solve_upper_t_in_place(l, grad);
    for g in grad.iter_mut() {
        *g = -*g;
    }
    -0.5 * maha - half_log_det(l, d) - 0.5 * d as f32 * LN_2PI
}

/// Cholesky factorisation in place: on success `a` (row-major `d x d`, symmetric) holds the
/// lower-triangular `L` with `L Lᵀ = A` and zeros above the diagonal. Returns `false` (and leaves
/// `a` partly overwritten) when `A` is not positive definite or not finite.
///
/// ```
/// let mut a = [4.0f32, 2.0, 2.0, 5.0];
/// assert!(vdd_core::gaussian::cholesky_in_place(&mut a, 2));
/// assert_eq!(a, [2.0, 0.0, 1.0, 2.0]);
/// ```
pub fn cholesky_in_place(a: &mut [f32], d: usize) -> bool {
    if a.len() != d * d {
        return false;
    }
    for j in 0..d {
        let mut diag = a[j * d + j] as f64;
        for k in 0..j {
            diag -= (a[j * d + k] as f64).powi(2);
        }
        if !(diag > 0.0 && diag.is_finite()) {
            return false;
        }
        let ljj = diag.sqrt();
        a[j * d + j] = ljj as f32;
        for i in j + 1..d {
            let mut s = a[i * d + j] as f64;
            for k in 0..j {
                s -= a[i * d + k] as f64 * a[j * d + k] as f64;
            }
            a[i * d + j] = (s / ljj) as f32;
        }
        for k in j + 1..d {
            a[j * d + k] = 0.0;
        }
    }
    true
}

/// Writes `L⁻¹` (lower-triangular, row-major `d x d`) into `out`.
///
/// ```
/// let (l, mut inv) = ([2.0f32, 0.0, 1.0, 4.0], [0.0f32; 4]);
/// vdd_core::gaussian::invert_lower(&l, 2, &mut inv);
/// assert_eq!(inv, [0.5, 0.0, -0.125, 0.25]);
/// ```
#[inline]
pub fn invert_lower(l: &[f32], d: usize, out: &mut [f32]) {
    for r in 0..d {
        for c in 0..d {
            out[r * d + c] = if c > r {
                0.0
            } else if c == r {
                1.0 / l[r * d + r]
            } else {
                let s: f32 = (c..r).map(|k| l[r * d + k] * out[k * d + c]).sum();
                -s / l[r * d + r]
            };
        }
    }
}

/// Reparameterised sample `a = μ + L ε`.
#[inline]
pub fn sample_into(mean: &[f32], l: &[f32], eps: &[f32], a: &mut [f32]) {
    let d = mean.len();
    for i in 0..d {
        let row = &l[i * d..i * d + i + 1];
        let mut s = mean[i];
        for (k, lik) in row.iter().enumerate() {
            s += lik * eps[k];
        }
        a[i] = s;
    }
}

/// Differential entropy of `N(μ, L Lᵀ)`: `Σ log L_ii + d/2 (1 + log 2π)`.
#[inline]
pub fn entropy(l: &[f32], d: usize) -> f32 {
    half_log_det(l, d) + 0.5 * d as f32 * (1.0 + LN_2PI)
}

/// Numerically stable `log Σ exp(x_i)`.
#[inline]
pub fn log_sum_exp(xs: &[f32]) -> f32 {
    let m = xs.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    if !m.is_finite() {
        return m;
    }
    m + xs.iter().map(|x| (x - m).exp()).sum::<f32>().ln()
}

/// `eˣ` in `f32`, branch-free so loops over it vectorise (Cephes' `expf`: range reduction to
/// `[−ln2/2, ln2/2]` and a degree-6 polynomial). Relative error below `3e-7` on `[−87, 88]`;
/// the argument is clamped to that range, `NaN` propagates.
#[inline(always)]
pub fn exp_fast(x: f32) -> f32 {
    const MAGIC: f32 = 12_582_912.0; // 1.5 · 2²³: adding it rounds to an integer
    const LN2_HI: f32 = 0.693_359_4;
    const LN2_LO: f32 = -2.121_944_4e-4;
    let x = x.clamp(-87.3, 88.3);
    let t = x * std::f32::consts::LOG2_E + MAGIC;
    let n = t - MAGIC;
    let r = (x - n * LN2_HI) - n * LN2_LO;
    let mut p = 1.987_569_1e-4;
    p = p * r + 1.398_199_9e-3;
    p = p * r + 8.333_452e-3;
    p = p * r + 4.166_579_6e-2;
    p = p * r + 1.666_666_5e-1;
    p = p * r + 0.5;
    let er = p * r * r + r + 1.0;
    // 2ⁿ from the integer n sitting in the low mantissa bits of t.
    let k = (t.to_bits() as i32).wrapping_sub(0x4B40_0000);
    er * f32::from_bits((k.wrapping_add(127) << 23) as u32)
}

/// Like [`softmax_in_place`] without the log-sum-exp (one `ln` fewer per call).
#[inline]
pub fn softmax_probs_in_place(xs: &mut [f32]) {
    let m = xs.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let mut sum = 0.0f32;
    for x in xs.iter_mut() {
        *x = (*x - m).exp();
        sum += *x;
    }
    let inv = 1.0 / sum;
    for x in xs.iter_mut() {
        *x *= inv;
    }
}

/// Turns log-weights into a normalised probability vector in place; returns their log-sum-exp.
#[inline]
pub fn softmax_in_place(xs: &mut [f32]) -> f32 {
    let m = xs.iter().copied().fold(f32::NEG_INFINITY, f32::max);
    let mut sum = 0.0f32;
    for x in xs.iter_mut() {
        *x = (*x - m).exp();
        sum += *x;
    }
    let inv = 1.0 / sum;
    for x in xs.iter_mut() {
        *x *= inv;
    }
    m + sum.ln()
}

#[cfg(test)]
mod tests {
    use super::*;
    use approx::assert_relative_eq;

    fn full_l() -> [f32; 9] {
        [1.2, 0.0, 0.0, 0.3, 0.8, 0.0, -0.5, 0.2, 1.5]
    }

    #[test]
    fn solves_invert_the_triangle() {
        let l = full_l();
        let mut x = [0.3f32, -1.0, 2.0];
        let orig = x;
        solve_lower_in_place(&l, &mut x);
        let mut back = [0.0f32; 3];
        sample_into(&[0.0; 3], &l, &x, &mut back);
        for i in 0..3 {
            assert_relative_eq!(back[i], orig[i], epsilon = 1e-5);
        }
    }

    #[test]
    fn gradient_matches_finite_differences() {
        let l = full_l();
        let mean = [0.1f32, -0.2, 0.4];
        let a = [0.7f32, 0.1, -0.9];
        let mut g = [0.0f32; 3];
        let mut w = [0.0f32; 3];
        let lp = log_density_and_grad(&a, &mean, &l, &mut g);
        assert_relative_eq!(lp, log_density(&a, &mean, &l, &mut w), epsilon = 1e-6);
        for i in 0..3 {
            let h = 1e-3f32;
            let mut ap = a;
            ap[i] += h;
            let mut am = a;
            am[i] -= h;
            let fd = (log_density(&ap, &mean, &l, &mut w) - log_density(&am, &mean, &l, &mut w))
                / (2.0 * h);
            assert_relative_eq!(g[i], fd, epsilon = 2e-3);
        }
    }

    #[test]
    fn log_density_matches_closed_form_in_1d() {
        let l = [0.5f32];
        let mut w = [0.0f32];
        let lp = log_density(&[1.0], &[0.0], &l, &mut w);
        let expect = -0.5 * (1.0f32 / 0.25) - 0.5f32.ln() - 0.5 * LN_2PI;
        assert_relative_eq!(lp, expect, epsilon = 1e-6);
        assert_relative_eq!(entropy(&l, 1), 0.5 * (1.0 + LN_2PI) + 0.5f32.ln(), epsilon = 1e-6);
    }

    #[test]
    fn exp_fast_is_accurate_over_the_whole_range() {
        let mut worst = 0.0f64;
        let mut x = -87.0f32;
        while x < 88.0 {
            let exact = f64::from(x).exp();
            worst = worst.max((f64::from(exp_fast(x)) - exact).abs() / exact);
            x += 0.001_3;
        }
        assert!(worst < 3e-7, "max relative error {worst}");
        assert_eq!(exp_fast(0.0), 1.0);
        assert!(exp_fast(f32::NAN).is_nan());
        assert!(exp_fast(-1000.0) < 1e-37 && exp_fast(1000.0) > 1e38);
    }

    #[test]
    fn softmax_normalises() {
        let mut x = [1000.0f32, 1001.0, 999.0];
        let lse = softmax_in_place(&mut x);
        assert_relative_eq!(x.iter().sum::<f32>(), 1.0, epsilon = 1e-6);
        assert!(lse > 1001.0 && lse < 1002.0);
    }
}
