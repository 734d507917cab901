//! The numerical pieces of the automatic set-up: a full-covariance Gaussian mixture fitted to
//! samples (k-means++ seeding, Lloyd steps, EM with re-seeding of empty components), least
//! squares, and a small dense Cholesky solver, all in `f64`.

use faer::MatRef;
use rand::Rng as _;
use vdd_core::Rng;

/// A Gaussian mixture fitted to samples: weights, means and lower Cholesky factors
/// (row-major `d x d`).
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Fitted {
    pub weights: Vec<f64>,
    pub means: Vec<Vec<f64>>,
    pub chols: Vec<Vec<f64>>,
}

/// In-place Cholesky of a symmetric `n x n` row-major matrix (lower factor, upper part
/// zeroed); `false` when not positive definite.
pub(crate) fn cholesky(a: &mut [f64], n: usize) -> bool {
    for j in 0..n {
        let mut diag = a[j * n + j];
        for k in 0..j {
            diag -= a[j * n + k] * a[j * n + k];
        }
        if !(diag > 0.0 && diag.is_finite()) {
            return false;
        }
        let l = diag.sqrt();
        a[j * n + j] = l;
        for i in j + 1..n {
            let mut v = a[i * n + j];
            for k in 0..j {
                v -= a[i * n + k] * a[j * n + k];
            }
            a[i * n + j] = v / l;
        }
        for k in j + 1..n {
            a[j * n + k] = 0.0;
        }
    }
    true
}

/// Solves `L Lᵀ x = b` in place for a lower factor `l`.
pub(crate) fn chol_solve(l: &[f64], n: usize, b: &mut [f64]) {
    for i in 0..n {
        let mut v = b[i];
        for k in 0..i {
            v -= l[i * n + k] * b[k];
        }
        b[i] = v / l[i * n + i];
    }
    for i in (0..n).rev() {
        let mut v = b[i];
        for k in i + 1..n {
            v -= l[k * n + i] * b[k];
        }
        b[i] = v / l[i * n + i];
    }
}

/// Ridge least squares: the `p x m` coefficients `β` minimising `|X β − Y|² + λ |β|²` for
/// `X` (`n x p`) and `Y` (`n x m`), both row-major; `None` if the system is singular.
pub(crate) fn least_squares(
    x: &[f64],
    y: &[f64],
    n: usize,
    p: usize,
    m: usize,
    ridge: f64,
) -> Option<Vec<f64>> {
    let mut gram = vec![0.0f64; p * p];
    let mut xty = vec![0.0f64; p * m];
    for r in 0..n {
        let (xr, yr) = (&x[r * p..(r + 1) * p], &y[r * m..(r + 1) * m]);
        for i in 0..p {
            for j in 0..=i {
                gram[i * p + j] += xr[i] * xr[j];
            }
            for c in 0..m {
                xty[i * m + c] += xr[i] * yr[c];
            }
        }
    }
    for i in 0..p {
        for j in 0..i {
            gram[j * p + i] = gram[i * p + j];
        }
        gram[i * p + i] += ridge;
    }
    if !cholesky(&mut gram, p) {
        return None;
    }
    let mut beta = vec![0.0f64; p * m];
    let mut col = vec![0.0f64; p];
    for c in 0..m {
        for i in 0..p {
            col[i] = xty[i * m + c];
        }
        chol_solve(&gram, p, &mut col);
        for i in 0..p {
            beta[i * m + c] = col[i];
        }
    }
    Some(beta)
}

fn dist2(a: &[f64], b: &[f64]) -> f64 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum()
}

/// `log N(x; μ, L Lᵀ)`.
fn log_normal(x: &[f64], mean: &[f64], l: &[f64], work: &mut [f64]) -> f64 {
    let d = mean.len();
    let mut log_det = 0.0;
    for i in 0..d {
        let mut v = x[i] - mean[i];
        for k in 0..i {
            v -= l[i * d + k] * work[k];
        }
        work[i] = v / l[i * d + i];
        log_det += l[i * d + i].ln();
    }
    let maha: f64 = work[..d].iter().map(|w| w * w).sum();
    -0.5 * maha - log_det - 0.5 * d as f64 * (2.0 * std::f64::consts::PI).ln()
}

/// The best (highest mean log-likelihood) of `restarts` fits by [`fit_mixture`].
#[allow(clippy::too_many_arguments)]
pub(crate) fn fit_best(
    x: &[f64],
    n: usize,
    d: usize,
    z: usize,
    em_steps: usize,
    reg: f64,
    restarts: usize,
    rng: &mut Rng,
) -> Fitted {
    let mut best: Option<(f64, Fitted)> = None;
    for _ in 0..restarts.max(1) {
        let f = fit_mixture(x, n, d, z, em_steps, reg, rng);
        let ll = mean_log_likelihood(x, n, d, &f);
        if best.as_ref().is_none_or(|(b, _)| ll > *b) {
            best = Some((ll, f));
        }
    }
    best.expect("at least one fit").1
}

/// Mean log-likelihood of the samples under `f`.
pub(crate) fn mean_log_likelihood(x: &[f64], n: usize, d: usize, f: &Fitted) -> f64 {
    let mut work = vec![0.0f64; d];
    let mut lp = vec![0.0f64; f.weights.len()];
    let mut total = 0.0;
    for i in 0..n {
        for c in 0..lp.len() {
            lp[c] = f.weights[c].max(1e-300).ln()
                + log_normal(&x[i * d..(i + 1) * d], &f.means[c], &f.chols[c], &mut work);
        }
        let max = lp.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        total += max + lp.iter().map(|v| (v - max).exp()).sum::<f64>().ln();
    }
    total / n.max(1) as f64
}

/// The responsibilities (`n x z`, row-major) of the samples `x` (`n x d`) under `f`.
pub(crate) fn responsibilities(x: &[f64], n: usize, d: usize, f: &Fitted) -> Vec<f64> {
    let z = f.weights.len();
    let mut work = vec![0.0f64; d];
    let mut resp = vec![0.0f64; n * z];
    for i in 0..n {
        let r = &mut resp[i * z..(i + 1) * z];
        for c in 0..z {
            r[c] = f.weights[c].max(1e-300).ln()
                + log_normal(&x[i * d..(i + 1) * d], &f.means[c], &f.chols[c], &mut work);
        }
        let max = r.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        let mut total = 0.0;
        for v in r.iter_mut() {
            *v = (*v - max).exp();
            total += *v;
        }
        for v in r.iter_mut() {
            *v /= total;
        }
    }
    resp
}

/// Most samples [`state_dependence`] pairs by nearest states when no two share a state.
const NEAREST_PAIR_SAMPLES: usize = 2048;

/// How much the state decides the component, in `[0, 1]`: the share of the variance of the
/// responsibilities `resp` (`n x z`) that is explained by the state (`states`, `n` rows), the
/// covariance of the responsibilities of two samples at the same state over their variance.
/// Samples at one state share their component's odds, so for a teacher whose components and
/// weights do not depend on the state it is 0 up to noise, and it is 1 when the state decides
/// the component. Pairs are all pairs of samples at equal states; when no two samples share a
/// state (one dataset action per state), each sample is paired with the one at the nearest
/// state among at most [`NEAREST_PAIR_SAMPLES`] evenly spaced samples.
pub(crate) fn state_dependence(resp: &[f64], z: usize, states: MatRef<'_, f32>) -> f64 {
    let n = states.nrows();
    if n < 2 || z < 2 {
        return 0.0;
    }
    let mut mean = vec![0.0f64; z];
    for i in 0..n {
        for c in 0..z {
            mean[c] += resp[i * z + c] / n as f64;
        }
    }
    let centred = |i: usize, c: usize| resp[i * z + c] - mean[c];
    let var: f64 = (0..n).map(|i| (0..z).map(|c| centred(i, c).powi(2)).sum::<f64>()).sum();
    if var <= 1e-12 * n as f64 {
        return 0.0;
    }
    let row = |i: usize| (0..states.ncols()).map(move |t| states[(i, t)]);
    // Groups of samples at equal states.
    let mut order: Vec<usize> = (0..n).collect();
    order.sort_by(|&a, &b| {
        row(a).zip(row(b)).map(|(x, y)| x.total_cmp(&y)).find(|o| o.is_ne()).unwrap_or(a.cmp(&b))
    });
    let (mut cov, mut pairs) = (0.0f64, 0.0f64);
    let mut start = 0;
    while start < n {
        let mut end = start + 1;
        while end < n && row(order[start]).eq(row(order[end])) {
            end += 1;
        }
        let m = end - start;
        if m >= 2 {
            // Σ_{i≠j} ⟨x_i, x_j⟩ = |Σ x_i|² − Σ |x_i|².
            for c in 0..z {
                let (sum, sq) = order[start..end].iter().fold((0.0f64, 0.0f64), |(s, q), &i| {
                    (s + centred(i, c), q + centred(i, c).powi(2))
                });
                cov += sum * sum - sq;
            }
            pairs += (m * (m - 1)) as f64;
        }
        start = end;
    }
    if pairs == 0.0 {
        // Every state distinct: pair each sample with the one at the nearest state.
        let stride = n.div_ceil(NEAREST_PAIR_SAMPLES);
        let rows: Vec<usize> = (0..n).step_by(stride).collect();
        for &i in &rows {
            let mut best = (f64::INFINITY, i);
            for &j in rows.iter().filter(|&&j| j != i) {
                let d2: f64 = row(i).zip(row(j)).map(|(x, y)| f64::from(x - y).powi(2)).sum();
                if d2 < best.0 {
                    best = (d2, j);
                }
            }
            if best.1 != i {
                cov += (0..z).map(|c| centred(i, c) * centred(best.1, c)).sum::<f64>();
                pairs += 1.0;
            }
        }
        if pairs == 0.0 {
            return 0.0;
        }
        let sub_var: f64 =
            rows.iter().map(|&i| (0..z).map(|c| centred(i, c).powi(2)).sum::<f64>()).sum();
        return (cov / pairs / (sub_var / rows.len() as f64)).clamp(0.0, 1.0);
    }
    (cov / pairs / (var / n as f64)).clamp(0.0, 1.0)
}

/// k-means++ seeding, 10 Lloyd steps and `em_steps` EM steps of a `z`-component
/// full-covariance mixture on the `n x d` row-major samples `x`. Covariances get `reg · I`
/// added; a component left with (almost) no samples is re-seeded at the sample the mixture
/// explains worst, so the result always has `z` live components.
pub(crate) fn fit_mixture(
    x: &[f64],
    n: usize,
    d: usize,
    z: usize,
    em_steps: usize,
    reg: f64,
    rng: &mut Rng,
) -> Fitted {
    let row = |i: usize| &x[i * d..(i + 1) * d];
    // k-means++.
    let mut centers: Vec<Vec<f64>> = vec![row(rng.random_range(0..n)).to_vec()];
    let mut nearest: Vec<f64> = (0..n).map(|i| dist2(row(i), &centers[0])).collect();
    while centers.len() < z {
        let total: f64 = nearest.iter().sum();
        let pick = if total > 0.0 {
            let mut u = rng.random::<f64>() * total;
            let mut k = n - 1;
            for (i, w) in nearest.iter().enumerate() {
                if u < *w {
                    k = i;
                    break;
                }
                u -= w;
            }
            k
        } else {
            rng.random_range(0..n)
        };
        centers.push(row(pick).to_vec());
        let c = centers.last().expect("just pushed");
        for i in 0..n {
            nearest[i] = nearest[i].min(dist2(row(i), c));
        }
    }
    // Lloyd.
    let mut assign = vec![0usize; n];
    for _ in 0..10 {
        for i in 0..n {
            assign[i] = (0..z)
                .min_by(|&a, &b| dist2(row(i), &centers[a]).total_cmp(&dist2(row(i), &centers[b])))
                .expect("z >= 1");
        }
        let mut sums = vec![vec![0.0f64; d]; z];
        let mut counts = vec![0usize; z];
        for i in 0..n {
            counts[assign[i]] += 1;
            for j in 0..d {
                sums[assign[i]][j] += row(i)[j];
            }
        }
        for c in 0..z {
            if counts[c] > 0 {
                centers[c] = sums[c].iter().map(|s| s / counts[c] as f64).collect();
            }
        }
    }
    // Responsibilities from the hard assignment, then EM.
    let mut resp = vec![0.0f64; n * z];
    for i in 0..n {
        resp[i * z + assign[i]] = 1.0;
    }
    let mut fitted =
        Fitted { weights: vec![1.0 / z as f64; z], means: centers, chols: vec![identity(d); z] };
    let mut work = vec![0.0f64; d];
    let mut logp = vec![0.0f64; n];
    for step in 0..=em_steps {
        m_step(x, n, d, &resp, reg, &mut fitted);
        if step == em_steps {
            break;
        }
        // E-step.
        for i in 0..n {
            let r = &mut resp[i * z..(i + 1) * z];
            for c in 0..z {
                r[c] = fitted.weights[c].ln()
                    + log_normal(row(i), &fitted.means[c], &fitted.chols[c], &mut work);
            }
            let max = r.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            let mut total = 0.0;
            for v in r.iter_mut() {
                *v = (*v - max).exp();
                total += *v;
            }
            for v in r.iter_mut() {
                *v /= total;
            }
            logp[i] = max + total.ln();
        }
        // Re-seed components that hold (almost) no samples at the worst-explained sample.
        for c in 0..z {
            let mass: f64 = (0..n).map(|i| resp[i * z + c]).sum();
            if mass < 2.0 + 1e-3 * n as f64 {
                let worst = (0..n).min_by(|&a, &b| logp[a].total_cmp(&logp[b])).expect("n >= 1");
                let centre = row(worst).to_vec();
                for i in 0..n {
                    let near = dist2(row(i), &centre) <= dist2(row(i), &fitted.means[c])
                        && (0..z).all(|o| {
                            o == c || dist2(row(i), &centre) <= dist2(row(i), &fitted.means[o])
                        });
                    if near {
                        resp[i * z..(i + 1) * z].fill(0.0);
                        resp[i * z + c] = 1.0;
                    }
                }
                logp[worst] = f64::INFINITY;
            }
        }
    }
    fitted
}

fn identity(d: usize) -> Vec<f64> {
    (0..d * d).map(|k| if k % (d + 1) == 0 { 1.0 } else { 0.0 }).collect()
}

/// Weights, means and Cholesky factors from responsibilities.
fn m_step(x: &[f64], n: usize, d: usize, resp: &[f64], reg: f64, f: &mut Fitted) {
    let z = f.weights.len();
    for c in 0..z {
        let mass: f64 = (0..n).map(|i| resp[i * z + c]).sum();
        if mass < 1e-9 {
            f.weights[c] = 1e-9;
            continue;
        }
        let mean: Vec<f64> = (0..d)
            .map(|j| (0..n).map(|i| resp[i * z + c] * x[i * d + j]).sum::<f64>() / mass)
            .collect();
        let mut cov = vec![0.0f64; d * d];
        for i in 0..n {
            let r = resp[i * z + c];
            if r < 1e-12 {
                continue;
            }
            for a in 0..d {
                let da = x[i * d + a] - mean[a];
                for b in 0..=a {
                    cov[a * d + b] += r * da * (x[i * d + b] - mean[b]);
                }
            }
        }
        for a in 0..d {
            for b in 0..=a {
                cov[a * d + b] /= mass;
                cov[b * d + a] = cov[a * d + b];
            }
            cov[a * d + a] += reg;
        }
        if cholesky(&mut cov, d) {
            f.chols[c] = cov;
        }
        f.means[c] = mean;
        f.weights[c] = mass / n as f64;
    }
    let total: f64 = f.weights.iter().sum();
    for w in &mut f.weights {
        *w /= total;
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use vdd_core::Seeds;

    #[test]
    fn em_recovers_separated_components_and_least_squares_a_line() {
        let mut rng = Seeds::new(0).stream("t");
        let (n, d) = (3000, 2);
        let centres = [[-5.0, 0.0], [5.0, 1.0], [0.0, 8.0]];
        let mut x = Vec::with_capacity(n * d);
        for i in 0..n {
            let c = centres[if i % 10 < 2 {
                0
            } else if i % 10 < 6 {
                1
            } else {
                2
            }];
            x.push(c[0] + 0.5 * vdd_core::standard_normal(&mut rng) as f64);
            x.push(c[1] + 0.2 * vdd_core::standard_normal(&mut rng) as f64);
        }
        let f = fit_mixture(&x, n, d, 3, 20, 1e-6, &mut rng);
        let mut found: Vec<(f64, f64, f64)> =
            (0..3).map(|c| (f.means[c][0], f.means[c][1], f.weights[c])).collect();
        found.sort_by(|a, b| a.0.total_cmp(&b.0));
        for ((mx, my, w), (c, tw)) in
            found.iter().zip([(centres[0], 0.2), (centres[2], 0.4), (centres[1], 0.4)])
        {
            assert!((mx - c[0]).abs() < 0.1 && (my - c[1]).abs() < 0.1, "{found:?}");
            assert!((w - tw).abs() < 0.02, "{found:?}");
        }
        // y = 2 + 3 x exactly.
        let xs: Vec<f64> = (0..10).flat_map(|i| [1.0, i as f64]).collect();
        let ys: Vec<f64> = (0..10).map(|i| 2.0 + 3.0 * i as f64).collect();
        let beta = least_squares(&xs, &ys, 10, 2, 1, 0.0).unwrap();
        assert!((beta[0] - 2.0).abs() < 1e-9 && (beta[1] - 3.0).abs() < 1e-9);
    }
}
