//! An analytic teacher for the consistency tests: the exact denoiser of a 2-D mixture of four
//! isotropic Gaussians, and a measure of how many samples land on its modes.

use faer::{MatMut, MatRef};
use vdd_core::{Affine, CoreError};

use crate::consistency::DenoiserFn;

/// The four modes (unit circle, 90° apart).
pub const FOUR_MODES: [[f32; 2]; 4] = [[1.0, 0.0], [0.0, 1.0], [-1.0, 0.0], [0.0, -1.0]];

/// Standard deviation of each mode.
pub const MODE_STD: f32 = 0.1;

/// The exact denoiser `D(x; σ) = E[a | a + σ z = x]` of `Σ_k ¼ N(μ_k, s² I)`:
/// with `v = s² + σ²` and responsibilities `w_k ∝ exp(−|x − μ_k|² / 2v)`,
/// `D = (s²/v) x + (σ²/v) Σ_k w_k μ_k`.
pub fn gmm_denoise(
    x: MatRef<'_, f32>,
    sigma: &[f32],
    _states: MatRef<'_, f32>,
    mut out: MatMut<'_, f32>,
) -> Result<(), CoreError> {
    let s2 = MODE_STD * MODE_STD;
    for i in 0..x.nrows() {
        let v = s2 + sigma[i] * sigma[i];
        let (x0, x1) = (x[(i, 0)], x[(i, 1)]);
        let mut logits = [0.0f32; 4];
        for (k, m) in FOUR_MODES.iter().enumerate() {
            logits[k] = -((x0 - m[0]).powi(2) + (x1 - m[1]).powi(2)) / (2.0 * v);
        }
        let max = logits.iter().copied().fold(f32::NEG_INFINITY, f32::max);
        let (mut total, mut m0, mut m1) = (0.0f32, 0.0f32, 0.0f32);
        for (k, m) in FOUR_MODES.iter().enumerate() {
            let w = (logits[k] - max).exp();
            total += w;
            m0 += w * m[0];
            m1 += w * m[1];
        }
        let (a, b) = (s2 / v, sigma[i] * sigma[i] / v);
        out[(i, 0)] = a * x0 + b * m0 / total;
        out[(i, 1)] = a * x1 + b * m1 / total;
    }
    Ok(())
}

/// The type of [`four_mode_teacher`].
pub type FnTeacher = DenoiserFn<
    fn(MatRef<'_, f32>, &[f32], MatRef<'_, f32>, MatMut<'_, f32>) -> Result<(), CoreError>,
>;

/// The exact four-mode teacher with identity normalisers (1-D state, ignored).
pub fn four_mode_teacher() -> FnTeacher {
    DenoiserFn::new(Affine::identity(1), Affine::identity(2), gmm_denoise as _)
}

/// The fraction of rows within `radius` of some mode, and the fraction of rows nearest to
/// each mode.
pub fn near_mode_fraction(samples: MatRef<'_, f32>, radius: f32) -> (f32, [f32; 4]) {
    let n = samples.nrows();
    let (mut near, mut counts) = (0usize, [0usize; 4]);
    for i in 0..n {
        let (mut best, mut arg) = (f32::INFINITY, 0);
        for (k, m) in FOUR_MODES.iter().enumerate() {
            let d = ((samples[(i, 0)] - m[0]).powi(2) + (samples[(i, 1)] - m[1]).powi(2)).sqrt();
            if d < best {
                (best, arg) = (d, k);
            }
        }
        counts[arg] += 1;
        near += usize::from(best <= radius);
    }
    (near as f32 / n as f32, counts.map(|c| c as f32 / n as f32))
}
