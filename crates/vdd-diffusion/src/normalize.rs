//! Fitting the data normalisers a teacher stores beside its weights.
//!
//! A teacher learns and answers score queries in the normalised space
//! `x' = (x − offset) / scale` ([`vdd_core::Affine`]); its [`vdd_core::Policy`] maps raw
//! observations in and raw actions out.

use faer::MatRef;
use serde::{Deserialize, Serialize};
use vdd_core::Affine;

/// How to fit a per-dimension [`Affine`] normaliser to data.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NormalizerKind {
    /// No normalisation (`offset = 0`, `scale = 1`).
    Identity,
    /// Per-dimension mean and standard deviation.
    Standard,
    /// Per-dimension mean and one shared standard deviation (the root of the mean variance),
    /// which keeps isotropic geometry isotropic: a mixture of isotropic Gaussians stays one.
    Isotropic,
    /// Per-dimension min-max to `[−1, 1]`.
    MinMax,
}

/// Scales below this are treated as constant dimensions and get scale 1.
const MIN_SCALE: f64 = 1e-6;

/// Fits a normaliser of `kind` to the rows of `data` (`n x dim`, finite, `n ≥ 1`).
///
/// Constant dimensions (zero spread) get scale 1 so they are only shifted.
///
/// ```
/// use vdd_diffusion::{fit_normalizer, NormalizerKind};
/// let data = faer::mat![[0.0f32, 5.0], [2.0, 5.0]];
/// let n = fit_normalizer(data.as_ref(), NormalizerKind::Standard);
/// assert_eq!(n.offset, vec![1.0, 5.0]);
/// assert_eq!(n.scale, vec![1.0, 1.0]);
/// ```
pub fn fit_normalizer(data: MatRef<'_, f32>, kind: NormalizerKind) -> Affine {
    let (n, d) = (data.nrows(), data.ncols());
    if n == 0 || kind == NormalizerKind::Identity {
        return Affine::identity(d);
    }
    let mut offset = vec![0.0f32; d];
    let mut scale = vec![1.0f32; d];
    let mut vars = vec![0.0f64; d];
    for j in 0..d {
        let col = data.col(j);
        let (mut lo, mut hi, mut sum) = (f64::INFINITY, f64::NEG_INFINITY, 0.0f64);
        for i in 0..n {
            let v = f64::from(col[i]);
            lo = lo.min(v);
            hi = hi.max(v);
            sum += v;
        }
        let mean = sum / n as f64;
        let mut ss = 0.0f64;
        for i in 0..n {
            let c = f64::from(col[i]) - mean;
            ss += c * c;
        }
        vars[j] = ss / n as f64;
        match kind {
            NormalizerKind::MinMax => {
                offset[j] = (0.5 * (lo + hi)) as f32;
                let half = 0.5 * (hi - lo);
                scale[j] = if half > MIN_SCALE { half as f32 } else { 1.0 };
            }
            _ => {
                offset[j] = mean as f32;
                let sd = vars[j].sqrt();
                scale[j] = if sd > MIN_SCALE { sd as f32 } else { 1.0 };
            }
        }
    }
    if kind == NormalizerKind::Isotropic && d > 0 {
        let sd = (vars.iter().sum::<f64>() / d as f64).sqrt();
        let s = if sd > MIN_SCALE { sd as f32 } else { 1.0 };
        scale.iter_mut().for_each(|x| *x = s);
    }
    Affine { offset, scale }
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::Mat;

    #[test]
    fn kinds_fit_their_definitions() {
        let data = Mat::from_fn(4, 2, |i, j| if j == 0 { i as f32 } else { 10.0 * i as f32 });
        let st = fit_normalizer(data.as_ref(), NormalizerKind::Standard);
        assert!((st.offset[0] - 1.5).abs() < 1e-6 && (st.offset[1] - 15.0).abs() < 1e-5);
        let sd0 = (1.25f32).sqrt();
        assert!((st.scale[0] - sd0).abs() < 1e-5 && (st.scale[1] - 10.0 * sd0).abs() < 1e-4);
        let iso = fit_normalizer(data.as_ref(), NormalizerKind::Isotropic);
        let shared = ((1.25f32 + 125.0) / 2.0).sqrt();
        assert!(iso.scale.iter().all(|s| (s - shared).abs() < 1e-4), "{iso:?}");
        let mm = fit_normalizer(data.as_ref(), NormalizerKind::MinMax);
        assert_eq!(mm.offset, vec![1.5, 15.0]);
        assert_eq!(mm.scale, vec![1.5, 15.0]);
        let mut x = [3.0f32, 0.0];
        mm.normalize(&mut x);
        assert_eq!(x, [1.0, -1.0]);
        assert_eq!(fit_normalizer(data.as_ref(), NormalizerKind::Identity), Affine::identity(2));
    }

    #[test]
    fn constant_dimensions_get_unit_scale() {
        let data = Mat::from_fn(5, 1, |_, _| 3.0f32);
        for kind in [NormalizerKind::Standard, NormalizerKind::MinMax, NormalizerKind::Isotropic] {
            let n = fit_normalizer(data.as_ref(), kind);
            assert_eq!(n.scale, vec![1.0]);
            assert_eq!(n.offset, vec![3.0]);
        }
    }
}
