//! Element-wise kernels over *lanes*: equally long `f32` slices holding one quantity for many
//! samples (structure-of-arrays layout, sample index innermost).
//!
//! Batched kernels over small mixtures (the VDD expert step, exact mixture scores) keep one lane
//! per component and loop over components outside, samples inside: every operation is then
//! element-wise over samples and the compiler vectorises it, where a per-sample loop over a
//! handful of components would need horizontal reductions. Slices of equal length are expected
//! (`zip` stops at the shorter one); lengths should be run-time values, since LLVM fully unrolls
//! loops of a small constant length before its loop vectoriser sees them.
//!
//! ```
//! use vdd_core::lanes::{exp_shifted, max_into};
//! // Softmax over two components for three samples, lane per component.
//! let mut joint = [vec![0.0f32, 1.0, -2.0], vec![1.0f32, 1.0, 0.0]];
//! let mut max = vec![f32::NEG_INFINITY; 3];
//! for lane in &joint {
//!     max_into(&mut max, lane);
//! }
//! let mut total = vec![0.0; 3];
//! for lane in &mut joint {
//!     exp_shifted(lane, &max, &mut total);
//! }
//! let p0: Vec<f32> = joint[0].iter().zip(&total).map(|(p, t)| p / t).collect();
//! assert!((p0[1] - 0.5).abs() < 1e-6);
//! assert!((p0[0] - 1.0 / (1.0 + 1f32.exp())).abs() < 1e-6);
//! ```

/// `Σ a b` (eight partial sums, so the reduction vectorises).
#[inline(always)]
pub fn dot(a: &[f32], b: &[f32]) -> f32 {
    let mut acc = [0.0f32; 8];
    let (ac, bc) = (a.chunks_exact(8), b.chunks_exact(8));
    let tail: f32 = ac.remainder().iter().zip(bc.remainder()).map(|(a, b)| a * b).sum();
    for (a, b) in ac.zip(bc) {
        for i in 0..8 {
            acc[i] += a[i] * b[i];
        }
    }
    acc.iter().sum::<f32>() + tail
}

/// `y += l (a − m)`.
#[inline(always)]
pub fn add_scaled_diff(y: &mut [f32], l: f32, a: &[f32], m: f32) {
    for (y, a) in y.iter_mut().zip(a) {
        *y += l * (a - m);
    }
}

/// `joint −= ½ y²`.
#[inline(always)]
pub fn sub_half_square(joint: &mut [f32], y: &[f32]) {
    for (j, y) in joint.iter_mut().zip(y) {
        *j -= 0.5 * y * y;
    }
}

/// `x += s y`.
#[inline(always)]
pub fn add_scaled(x: &mut [f32], s: f32, y: &[f32]) {
    for (x, y) in x.iter_mut().zip(y) {
        *x += s * y;
    }
}

/// `x += a b`.
#[inline(always)]
pub fn add_product(x: &mut [f32], a: &[f32], b: &[f32]) {
    for ((x, a), b) in x.iter_mut().zip(a).zip(b) {
        *x += a * b;
    }
}

/// `max = max(max, x)`.
#[inline(always)]
pub fn max_into(max: &mut [f32], x: &[f32]) {
    for (m, x) in max.iter_mut().zip(x) {
        *m = m.max(*x);
    }
}

/// `x = exp(x − max)`, `total += x`.
#[inline(always)]
pub fn exp_shifted(x: &mut [f32], max: &[f32], total: &mut [f32]) {
    for ((x, m), t) in x.iter_mut().zip(max).zip(total.iter_mut()) {
        *x = crate::gaussian::exp_fast(*x - m);
        *t += *x;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn kernels_match_scalar_formulas() {
        let a: Vec<f32> = (0..19).map(|i| i as f32 * 0.3 - 2.0).collect();
        let b: Vec<f32> = (0..19).map(|i| (i as f32 * 0.7).sin()).collect();
        let mut y = b.clone();
        add_scaled_diff(&mut y, 0.5, &a, 1.0);
        let mut x = b.clone();
        add_scaled(&mut x, -2.0, &a);
        let mut p = b.clone();
        add_product(&mut p, &a, &b);
        let mut h = b.clone();
        sub_half_square(&mut h, &a);
        let mut m = b.clone();
        max_into(&mut m, &a);
        let (mut e, mut t) = (a.clone(), vec![1.0; 19]);
        exp_shifted(&mut e, &b, &mut t);
        for i in 0..19 {
            assert_eq!(y[i], b[i] + 0.5 * (a[i] - 1.0));
            assert_eq!(x[i], b[i] - 2.0 * a[i]);
            assert_eq!(p[i], b[i] + a[i] * b[i]);
            assert_eq!(h[i], b[i] - 0.5 * a[i] * a[i]);
            assert_eq!(m[i], a[i].max(b[i]));
            assert!((e[i] - (a[i] - b[i]).exp()).abs() <= 1e-6 * e[i]);
            assert_eq!(t[i], 1.0 + e[i]);
        }
        let exact: f64 = a.iter().zip(&b).map(|(a, b)| f64::from(a * b)).sum();
        assert!((f64::from(dot(&a, &b)) - exact).abs() < 1e-5);
    }
}
