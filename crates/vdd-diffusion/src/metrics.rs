//! Small sample-quality measures used to accept a teacher on toy tasks: kernel MMD, mode
//! assignment and score agreement.

use faer::MatRef;

/// The (biased, V-statistic) squared maximum mean discrepancy between the rows of `x` and `y`
/// under the RBF kernel `k(a, b) = exp(−|a − b|² / (2 h²))` with bandwidth `h`:
/// `mean k(x, x') + mean k(y, y') − 2 mean k(x, y)` over all pairs (diagonals included), so
/// it is never negative and two independent samples of one distribution give a small
/// positive baseline of order `1/n`.
///
/// ```
/// let x = faer::mat![[0.0f32, 0.0], [1.0, 0.0]];
/// assert!(vdd_diffusion::metrics::mmd2_rbf(x.as_ref(), x.as_ref(), 1.0).abs() < 1e-9);
/// ```
pub fn mmd2_rbf(x: MatRef<'_, f32>, y: MatRef<'_, f32>, bandwidth: f32) -> f64 {
    let g = 1.0 / (2.0 * f64::from(bandwidth) * f64::from(bandwidth));
    let mean_k = |a: MatRef<'_, f32>, b: MatRef<'_, f32>| {
        let mut s = 0.0f64;
        for i in 0..a.nrows() {
            for k in 0..b.nrows() {
                let mut d2 = 0.0f64;
                for j in 0..a.ncols() {
                    let d = f64::from(a[(i, j)] - b[(k, j)]);
                    d2 += d * d;
                }
                s += (-g * d2).exp();
            }
        }
        s / (a.nrows() * b.nrows()).max(1) as f64
    };
    mean_k(x, x) + mean_k(y, y) - 2.0 * mean_k(x, y)
}

/// How many rows of `samples` lie nearest (Euclidean) to each of `modes`.
pub fn nearest_mode_counts(samples: MatRef<'_, f32>, modes: &[Vec<f32>]) -> Vec<usize> {
    let mut counts = vec![0usize; modes.len()];
    for i in 0..samples.nrows() {
        let mut best = (f32::INFINITY, 0usize);
        for (k, m) in modes.iter().enumerate() {
            let d: f32 = m.iter().enumerate().map(|(j, mj)| (samples[(i, j)] - mj).powi(2)).sum();
            if d < best.0 {
                best = (d, k);
            }
        }
        if !modes.is_empty() {
            counts[best.1] += 1;
        }
    }
    counts
}

/// The share of the rows of `samples` nearest to each of `modes` (in order), and the smallest
/// share.
///
/// ```
/// let x = faer::mat![[0.1f32, 0.0], [0.9, 0.0], [1.1, 0.0], [1.0, 0.1]];
/// let (min, shares) = vdd_diffusion::metrics::mode_shares(x.as_ref(), &[vec![0.0, 0.0], vec![1.0, 0.0]]);
/// assert_eq!(shares, [0.25, 0.75]);
/// assert_eq!(min, 0.25);
/// ```
pub fn mode_shares(samples: MatRef<'_, f32>, modes: &[Vec<f32>]) -> (f32, Vec<f32>) {
    let counts = nearest_mode_counts(samples, modes);
    let n = samples.nrows() as f32;
    let shares: Vec<f32> = counts.iter().map(|&c| c as f32 / n).collect();
    (shares.iter().copied().fold(f32::INFINITY, f32::min), shares)
}

/// Mean over rows of the cosine similarity between the rows of `a` and `b` (rows where either
/// vector is zero count as 0).
pub fn mean_cosine_similarity(a: MatRef<'_, f32>, b: MatRef<'_, f32>) -> f32 {
    let n = a.nrows();
    let mut total = 0.0f64;
    for i in 0..n {
        let (mut ab, mut aa, mut bb) = (0.0f64, 0.0f64, 0.0f64);
        for j in 0..a.ncols() {
            let (x, y) = (f64::from(a[(i, j)]), f64::from(b[(i, j)]));
            ab += x * y;
            aa += x * x;
            bb += y * y;
        }
        if aa > 0.0 && bb > 0.0 {
            total += ab / (aa.sqrt() * bb.sqrt());
        }
    }
    (total / n.max(1) as f64) as f32
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::Mat;

    #[test]
    fn mmd_separates_shifted_samples() {
        let x = Mat::from_fn(50, 1, |i, _| i as f32 / 50.0);
        let y = Mat::from_fn(50, 1, |i, _| i as f32 / 50.0 + 2.0);
        let near = mmd2_rbf(x.as_ref(), x.as_ref(), 1.0);
        let far = mmd2_rbf(x.as_ref(), y.as_ref(), 1.0);
        assert!(near.abs() < 1e-12 && far > 0.5, "{near} {far}");
        // Two point masses at distance r: 2 − 2 exp(−r²/2).
        let a = faer::mat![[0.0f32]];
        let b = faer::mat![[1.0f32]];
        assert!(
            (mmd2_rbf(a.as_ref(), b.as_ref(), 1.0) - (2.0 - 2.0 * (-0.5f64).exp())).abs() < 1e-9
        );
    }

    #[test]
    fn modes_and_cosines() {
        let s = faer::mat![[0.9f32, 0.1], [-1.0, 0.2], [1.2, -0.1]];
        let modes = vec![vec![1.0, 0.0], vec![-1.0, 0.0]];
        assert_eq!(nearest_mode_counts(s.as_ref(), &modes), vec![2, 1]);
        let a = faer::mat![[1.0f32, 0.0], [0.0, 2.0]];
        let b = faer::mat![[2.0f32, 0.0], [0.0, -1.0]];
        assert!((mean_cosine_similarity(a.as_ref(), b.as_ref()) - 0.0).abs() < 1e-6);
        assert!((mean_cosine_similarity(a.as_ref(), a.as_ref()) - 1.0).abs() < 1e-6);
    }
}
