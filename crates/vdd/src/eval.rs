//! Exact-density evaluation of a distilled mixture on problems whose target density is known
//! (the toy tasks): Monte-Carlo reverse and forward KL, and mode coverage; against an exact
//! Gaussian mixture in raw units, [`evaluate_against_mixture`].

mod mixture;
pub use mixture::{MixtureEval, evaluate_against_mixture};

use faer::{Mat, MatRef};
use rand::Rng as _;
use vdd_core::{Expert, Rng, check_shape, gaussian};
use vdd_moe::{Moe, MoeError};

/// Draws `n` samples `a ~ q(·|state)` from the student (networks' normalised space) into an
/// `n x d` matrix.
pub fn sample_student<E: Expert>(
    student: &mut Moe<E>,
    state: &[f32],
    n: usize,
    rng: &mut Rng,
) -> Result<Mat<f32>, MoeError> {
    let s = MatRef::from_row_major_slice(state, 1, state.len());
    student.forward(s)?;
    let out = student.output();
    let (z_n, d) = (out.num_experts, out.action_dim);
    let probs: Vec<f32> = out.log_gating_row(0).iter().map(|l| l.exp()).collect();
    let mut eps = vec![0.0; d];
    let mut a = vec![0.0; d];
    let mut samples = Mat::zeros(n, d);
    for i in 0..n {
        let u: f32 = rng.random();
        let mut acc = 0.0;
        let mut z = z_n - 1;
        for (k, p) in probs.iter().enumerate() {
            acc += p;
            if u < acc {
                z = k;
                break;
            }
        }
        vdd_core::fill_standard_normal(rng, &mut eps);
        gaussian::sample_into(out.mean(0, z), out.scale(0, z), &eps, &mut a);
        for j in 0..d {
            samples[(i, j)] = a[j];
        }
    }
    Ok(samples)
}

/// `log q(a|state)` for each row of `actions` (networks' normalised space).
pub fn student_log_density<E: Expert>(
    student: &mut Moe<E>,
    state: &[f32],
    actions: MatRef<'_, f32>,
) -> Result<Vec<f32>, MoeError> {
    let s = MatRef::from_row_major_slice(state, 1, state.len());
    student.forward(s)?;
    let out = student.output();
    let d = out.action_dim;
    check_shape("actions", actions, actions.nrows(), d)?;
    let mut resp = vec![0.0; out.num_experts];
    let (mut a, mut work) = (vec![0.0; d], vec![0.0; d]);
    Ok((0..actions.nrows())
        .map(|i| {
            for j in 0..d {
                a[j] = actions[(i, j)];
            }
            out.log_density_and_responsibilities(0, &a, &mut resp, &mut work)
        })
        .collect())
}

/// Reverse KL `E_q[log q − log p]` at one state by Monte Carlo with `n` student samples.
pub fn reverse_kl<E: Expert>(
    student: &mut Moe<E>,
    state: &[f32],
    log_p: impl Fn(&[f32]) -> f32,
    n: usize,
    rng: &mut Rng,
) -> Result<f64, MoeError> {
    let samples = sample_student(student, state, n, rng)?;
    let log_q = student_log_density(student, state, samples.as_ref())?;
    let d = samples.ncols();
    let mut a = vec![0.0; d];
    let mut sum = 0.0f64;
    for (i, lq) in log_q.iter().enumerate() {
        for j in 0..d {
            a[j] = samples[(i, j)];
        }
        sum += f64::from(*lq) - f64::from(log_p(&a));
    }
    Ok(sum / n as f64)
}

/// Forward KL `E_p[log p − log q]` at one state from target samples (`n x d`).
pub fn forward_kl<E: Expert>(
    student: &mut Moe<E>,
    state: &[f32],
    log_p: impl Fn(&[f32]) -> f32,
    target_samples: MatRef<'_, f32>,
) -> Result<f64, MoeError> {
    let log_q = student_log_density(student, state, target_samples)?;
    let d = target_samples.ncols();
    let mut a = vec![0.0; d];
    let mut sum = 0.0f64;
    for (i, lq) in log_q.iter().enumerate() {
        for j in 0..d {
            a[j] = target_samples[(i, j)];
        }
        sum += f64::from(log_p(&a)) - f64::from(*lq);
    }
    Ok(sum / log_q.len().max(1) as f64)
}

/// Number of target modes covered at `state`: a mode counts when some expert whose gating
/// weight is at least `min_weight` has its mean within `radius` of it.
pub fn modes_covered<E: Expert>(
    student: &mut Moe<E>,
    state: &[f32],
    modes: &[Vec<f32>],
    radius: f32,
    min_weight: f32,
) -> Result<usize, MoeError> {
    let s = MatRef::from_row_major_slice(state, 1, state.len());
    student.forward(s)?;
    let out = student.output();
    let lg = out.log_gating_row(0);
    Ok(modes
        .iter()
        .filter(|m| {
            (0..out.num_experts).any(|z| {
                let dist2: f32 =
                    out.mean(0, z).iter().zip(m.iter()).map(|(a, b)| (a - b) * (a - b)).sum();
                lg[z].exp() >= min_weight && dist2.sqrt() <= radius
            })
        })
        .count())
}

#[cfg(test)]
mod tests {
    use crate::test_support::IsoGmm;
    use vdd_core::gaussian;
    use vdd_moe::MoeOutput;

    fn mixture_1d(means: [f32; 2], stds: [f32; 2], weights: [f32; 2]) -> MoeOutput {
        MoeOutput {
            n: 1,
            num_experts: 2,
            action_dim: 1,
            raw: vec![],
            means: means.to_vec(),
            scales: stds.to_vec(),
            log_gating: weights.iter().map(|w| w.ln()).collect(),
        }
    }

    /// KL(q||p) and the bound U(q, q̃) by quadrature on a fine 1-D grid.
    fn kl_and_bound(q: &MoeOutput, q_tilde: &MoeOutput, p: &IsoGmm) -> (f64, f64) {
        let (mut resp, mut resp_t, mut work) = ([0.0f32; 2], [0.0f32; 2], [0.0f32; 1]);
        let h = 1e-3f64;
        let (mut kl, mut bound) = (0.0f64, 0.0f64);
        let mut x = -12.0f64;
        while x < 12.0 {
            let a = [x as f32];
            let log_q = q.log_density_and_responsibilities(0, &a, &mut resp, &mut work);
            q_tilde.log_density_and_responsibilities(0, &a, &mut resp_t, &mut work);
            let log_p = f64::from(p.log_density(&a, 0.0));
            kl += h * f64::from(log_q).exp() * (f64::from(log_q) - log_p);
            for z in 0..2 {
                let log_nz = gaussian::log_density(&a, q.mean(0, z), q.scale(0, z), &mut work);
                let wz = f64::from(q.log_gating[z]).exp();
                let integrand = f64::from(log_nz) - log_p - f64::from(resp_t[z].ln())
                    + f64::from(q.log_gating[z]);
                bound += h * wz * f64::from(log_nz).exp() * integrand;
            }
            x += h;
        }
        (kl, bound)
    }

    #[test]
    fn upper_bound_dominates_reverse_kl_with_equality_at_the_posterior() {
        let p = IsoGmm { means: vec![vec![-2.0], vec![0.5], vec![2.5]], std: 0.7, state_dim: 1 };
        let q = mixture_1d([-1.5, 1.0], [0.8, 1.1], [0.4, 0.6]);
        // q̃ = q's own posterior: the bound is tight.
        let (kl, tight) = kl_and_bound(&q, &q, &p);
        assert!((tight - kl).abs() < 1e-4, "U {tight} vs KL {kl}");
        // Any other q̃ gives a strictly larger bound.
        for other in [
            mixture_1d([-1.0, 1.5], [0.8, 1.1], [0.4, 0.6]),
            mixture_1d([-1.5, 1.0], [0.5, 2.0], [0.7, 0.3]),
        ] {
            let (kl2, loose) = kl_and_bound(&q, &other, &p);
            assert!((kl2 - kl).abs() < 1e-9);
            assert!(loose > kl + 1e-3, "U {loose} vs KL {kl}");
        }
    }
}
