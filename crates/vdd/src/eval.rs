//! Exact-density evaluation of a distilled mixture on problems whose target density is known
//! (the toy tasks): Monte-Carlo reverse and forward KL, and mode coverage. [`against_gmm`]
//! does all three against an exact Gaussian mixture in raw coordinates with the toy recipes'
//! coverage rule (an expert mean near each mode); [`evaluate_against_mixture`] with the
//! robustness benchmark's rule (a component covered when >= 1 % of student samples have it as
//! their most likely component).

mod mixture;
pub use mixture::{MixtureEval, evaluate_against_mixture, evaluate_against_mixture_in_regions};

use std::cell::RefCell;

use faer::{Mat, MatRef};
use rand::Rng as _;
use serde::{Deserialize, Serialize};
use vdd_core::gmm::Gmm;
use vdd_core::{Affine, Expert, Rng, Seeds, check_len, check_shape, gaussian};
use vdd_moe::{Moe, MoeError};

/// Settings of the evaluation against a known mixture ([`against_gmm`]; the toy recipes'
/// `[eval]`).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GmmEval {
    /// Monte-Carlo samples per KL estimate (each way, at each evaluation state).
    pub kl_samples: usize,
    /// Evaluation states of a conditional problem (the toy's `s_i = (i + 0.5) 2π / n`; the
    /// caller spreads them).
    pub eval_states: usize,
    /// A mode is covered when an expert mean lies within this distance of it (raw units)...
    pub coverage_radius: f32,
    /// ... and that expert's gating weight is at least this.
    pub min_weight: f32,
}

impl GmmEval {
    /// Checks the documented ranges: `kl_samples` in `1..=10^8`, `eval_states` in `1..=10^4`,
    /// `coverage_radius` finite and `> 0`, `min_weight` in `[0, 1]`.
    ///
    /// ```
    /// use vdd::eval::GmmEval;
    /// let eval = GmmEval { kl_samples: 1000, eval_states: 8, coverage_radius: 0.5, min_weight: 0.01 };
    /// assert!(eval.validate().is_ok());
    /// assert!(GmmEval { kl_samples: 0, ..eval.clone() }.validate().is_err());
    /// assert!(GmmEval { coverage_radius: f32::NAN, ..eval }.validate().is_err());
    /// ```
    pub fn validate(&self) -> Result<(), vdd_core::CoreError> {
        let bad = |what: String| Err(vdd_core::CoreError::Config(format!("eval.{what}")));
        if !(1..=100_000_000).contains(&self.kl_samples) {
            return bad(format!("kl_samples must be in 1..=1e8, got {}", self.kl_samples));
        }
        if !(1..=10_000).contains(&self.eval_states) {
            return bad(format!("eval_states must be in 1..=1e4, got {}", self.eval_states));
        }
        if !(self.coverage_radius.is_finite() && self.coverage_radius > 0.0) {
            return bad(format!(
                "coverage_radius must be finite and > 0, got {}",
                self.coverage_radius
            ));
        }
        if !(0.0..=1.0).contains(&self.min_weight) {
            return bad(format!("min_weight must be in [0, 1], got {}", self.min_weight));
        }
        Ok(())
    }
}

/// What [`against_gmm`] measures at one state.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GmmScores {
    /// `KL(q || p)` in nats (Monte Carlo).
    pub reverse_kl: f64,
    /// `KL(p || q)` in nats (Monte Carlo).
    pub forward_kl: f64,
    /// Components of the target covered by some expert ([`GmmEval::coverage_radius`],
    /// [`GmmEval::min_weight`]).
    pub modes_covered: usize,
}

/// Reverse and forward KL and mode coverage of `student` at raw state `state` against the exact
/// mixture `truth` of raw actions.
///
/// KL is computed in the student's normalised action space ([`Moe::normalizers`]; identity
/// when unset) with the target transformed alike (KL is invariant under that affine map);
/// coverage distances are measured after mapping the experts' means back to raw actions. The
/// student's samples come from `seeds`' stream `"reverse"`, the target's from `"forward"`,
/// both indexed by `index` (one index per evaluation state).
///
/// ```
/// use vdd::eval::{GmmEval, against_gmm};
/// use vdd::{Moe, MoeConfig, Seeds};
/// use vdd_core::gmm::Gmm;
/// let truth = Gmm::circle(8, 2.0, 0.5, 0.0)?;
/// let mut student = Moe::from_config(MoeConfig::toy(1, 2, 8), 0)?; // untrained
/// let settings = GmmEval { kl_samples: 500, eval_states: 1, coverage_radius: 0.5, min_weight: 0.05 };
/// let scores = against_gmm(&mut student, &truth, &[0.0], &settings, &Seeds::new(0), 0)?;
/// assert!(scores.reverse_kl > 0.0 && scores.forward_kl > 0.0 && scores.modes_covered <= 8);
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
pub fn against_gmm<E: Expert>(
    student: &mut Moe<E>,
    truth: &Gmm,
    state: &[f32],
    settings: &GmmEval,
    seeds: &Seeds,
    index: u64,
) -> Result<GmmScores, MoeError> {
    let (d, ds) = (student.config().action_dim, student.config().state_dim);
    check_len("target mixture dimension", truth.dim(), d)?;
    check_len("state", state.len(), ds)?;
    let (sn, an) = normalizers(student);
    let log_det: f32 = an.scale.iter().map(|c| c.ln()).sum();
    let s_n: Vec<f32> = (0..ds).map(|j| (state[j] - sn.offset[j]) / sn.scale[j]).collect();
    let to_raw = |a: &[f32], raw: &mut [f32]| {
        for j in 0..d {
            raw[j] = a[j] * an.scale[j] + an.offset[j];
        }
    };
    // log p in the normalised space: p_n(a_n) = p(denorm(a_n)) · Π scale.
    let raw = RefCell::new(vec![0.0f32; d]);
    let log_p = |a: &[f32]| {
        let mut raw = raw.borrow_mut();
        to_raw(a, &mut raw);
        truth.log_density(&raw, 0.0).map(|l| l + log_det).unwrap_or(f32::NEG_INFINITY)
    };
    let n = settings.kl_samples;
    let reverse_kl =
        reverse_kl(student, &s_n, log_p, n, &mut seeds.stream_indexed("reverse", index))?;
    let mut rng = seeds.stream_indexed("forward", index);
    let mut target = Mat::zeros(n, d);
    let mut a = vec![0.0f32; d];
    for i in 0..n {
        truth.sample_into(&mut rng, &mut a);
        for j in 0..d {
            target[(i, j)] = (a[j] - an.offset[j]) / an.scale[j];
        }
    }
    let forward_kl = forward_kl(student, &s_n, log_p, target.as_ref())?;
    // Coverage in raw coordinates.
    student.forward(MatRef::from_row_major_slice(&s_n, 1, ds))?;
    let out = student.output();
    let lg = out.log_gating_row(0);
    let mut mu = vec![0.0f32; d];
    let modes_covered = (0..truth.num_components())
        .filter(|&k| {
            let m = truth.mean(k);
            (0..out.num_experts).any(|z| {
                to_raw(out.mean(0, z), &mut mu);
                let dist = mu.iter().zip(m).map(|(x, y)| (x - y).powi(2)).sum::<f32>().sqrt();
                lg[z].exp() >= settings.min_weight && dist <= settings.coverage_radius
            })
        })
        .count();
    Ok(GmmScores { reverse_kl, forward_kl, modes_covered })
}

/// The toys' evaluation states: `s_i = (i + 0.5) 2π / n`, `i < n`.
///
/// ```
/// let s = vdd::eval::circle_states(4);
/// assert_eq!(s.len(), 4);
/// assert!((s[0] - std::f32::consts::FRAC_PI_4).abs() < 1e-6);
/// ```
pub fn circle_states(n: usize) -> Vec<f32> {
    (0..n).map(|i| (i as f32 + 0.5) * std::f32::consts::TAU / n as f32).collect()
}

/// [`against_gmm`] at each raw scalar state `states[i]` (index `i`) against the toys' mixture
/// there: `modes` modes on the circle of radius 2, std 0.5, rotated by the state
/// ([`Gmm::circle`]).
pub fn against_circle<E: Expert>(
    student: &mut Moe<E>,
    modes: usize,
    states: &[f32],
    settings: &GmmEval,
    seeds: &Seeds,
) -> Result<Vec<GmmScores>, MoeError> {
    let mut out = Vec::with_capacity(states.len());
    for (i, &s) in states.iter().enumerate() {
        let truth = Gmm::circle(modes, 2.0, 0.5, s)?;
        out.push(against_gmm(student, &truth, &[s], settings, seeds, i as u64)?);
    }
    Ok(out)
}

/// An arrow of a figure: its position and its vector, in raw action coordinates.
pub type Arrow = ((f32, f32), (f32, f32));

/// The score field of `teacher` (2-D actions, scalar state) for a figure: its score at noise
/// level `sigma` at the centres of a `k x k` grid (`k` at least 2) over the raw square
/// `[−extent, extent]²` at raw state `s`, the teacher seeing normalised states and actions
/// (`state_norm`, `action_norm`). Returns `(position, arrow)` pairs in raw coordinates, row
/// (second coordinate) major: the score's direction mapped to raw units, drawn `0.4` cells
/// long where the field is strong and shorter where it is weak (`len / (len + 0.5)`).
///
/// ```
/// use vdd::{Affine, gmm::GmmTeacher};
/// let (sn, an) = (Affine::identity(1), Affine::identity(2));
/// let mut teacher = GmmTeacher::circle_toy();
/// let arrows = vdd::eval::score_arrows(&mut teacher, &sn, &an, 0.0, 4.0, 4, 0.1)?;
/// assert_eq!(arrows.len(), 16);
/// let ((x, y), (dx, dy)) = arrows[0]; // the corner cell: towards the modes on the circle
/// assert!((x, y) == (-3.0, -3.0) && dx > 0.0 && dy > 0.0 && dx.hypot(dy) <= 0.8);
/// # Ok::<(), vdd::CoreError>(())
/// ```
pub fn score_arrows(
    teacher: &mut dyn vdd_core::ScoreModel,
    state_norm: &Affine,
    action_norm: &Affine,
    s: f32,
    extent: f32,
    k: usize,
    sigma: f32,
) -> Result<Vec<Arrow>, vdd_core::CoreError> {
    let (an, e, k) = (action_norm, extent, k.max(2));
    check_len("state normaliser", state_norm.dim(), 1)?;
    check_len("action normaliser", an.dim(), 2)?;
    let s_n = (s - state_norm.offset[0]) / state_norm.scale[0];
    let spacing = 2.0 * e / k as f32;
    let mut apts = Mat::<f32>::zeros(k * k, 2);
    let mut raw_pos = Vec::with_capacity(k * k);
    for i in 0..k {
        for j in 0..k {
            let (x, y) = (-e + (j as f32 + 0.5) * spacing, -e + (i as f32 + 0.5) * spacing);
            apts[(i * k + j, 0)] = (x - an.offset[0]) / an.scale[0];
            apts[(i * k + j, 1)] = (y - an.offset[1]) / an.scale[1];
            raw_pos.push((x, y));
        }
    }
    let states = Mat::from_fn(k * k, 1, |_, _| s_n);
    let mut score = Mat::<f32>::zeros(k * k, 2);
    teacher.score(apts.as_ref(), states.as_ref(), &vec![sigma; k * k], score.as_mut())?;
    let arrow = |(r, &pos): (usize, &(f32, f32))| {
        let (gx, gy) = (score[(r, 0)] / an.scale[0], score[(r, 1)] / an.scale[1]);
        let len = (gx * gx + gy * gy).sqrt().max(1e-12);
        let l = 0.4 * spacing * (len / (len + 0.5));
        (pos, (gx / len * l, gy / len * l))
    };
    Ok(raw_pos.iter().enumerate().map(arrow).collect())
}

/// One expert at a state in raw action coordinates ([`density_map`]).
#[derive(Debug, Clone, PartialEq)]
pub struct RawExpert {
    /// Mean.
    pub mean: Vec<f32>,
    /// Covariance `S L Lᵀ S` (`d x d`, row-major; `S` the action normaliser's scales).
    pub covariance: Vec<f32>,
    /// Gating weight.
    pub weight: f32,
}

/// The student's density on a grid and its experts at raw `state`, for figures of 2-D actions
/// ([`density_map`]).
#[derive(Debug, Clone, PartialEq)]
pub struct DensityMap {
    /// Cells per side.
    pub n: usize,
    /// `q` of the student's normalised actions at the centres of the `n x n` cells of the raw
    /// square `[−extent, extent]²`, row `i` (second coordinate) major.
    pub density: Vec<f32>,
    /// The experts in raw coordinates.
    pub experts: Vec<RawExpert>,
}

/// The density of `student` (2-D actions) at raw `state` on an `n x n` grid over the raw square
/// `[−extent, extent]²` (`n` at least 2), and its experts in raw coordinates: what a figure
/// of the mixture draws. Normalisers as in [`against_gmm`].
///
/// ```
/// use vdd::{Moe, MoeConfig};
/// let mut student = Moe::from_config(MoeConfig::toy(1, 2, 3), 0)?;
/// let map = vdd::eval::density_map(&mut student, &[0.0], 3.0, 20)?;
/// assert_eq!((map.density.len(), map.experts.len()), (400, 3));
/// assert!((map.experts.iter().map(|e| e.weight).sum::<f32>() - 1.0).abs() < 1e-5);
/// # Ok::<(), vdd::MoeError>(())
/// ```
pub fn density_map<E: Expert>(
    student: &mut Moe<E>,
    state: &[f32],
    extent: f32,
    n: usize,
) -> Result<DensityMap, MoeError> {
    let (d, ds) = (student.config().action_dim, student.config().state_dim);
    check_len("action dimension of a density map", d, 2)?;
    check_len("state", state.len(), ds)?;
    let (sn, an) = normalizers(student);
    let s_n: Vec<f32> = (0..ds).map(|j| (state[j] - sn.offset[j]) / sn.scale[j]).collect();
    let (e, n) = (extent, n.max(2));
    let h = 2.0 * e / n as f32;
    let mut pts = Mat::<f32>::zeros(n * n, 2);
    for i in 0..n {
        for j in 0..n {
            let (x, y) = (-e + (j as f32 + 0.5) * h, -e + (i as f32 + 0.5) * h);
            pts[(i * n + j, 0)] = (x - an.offset[0]) / an.scale[0];
            pts[(i * n + j, 1)] = (y - an.offset[1]) / an.scale[1];
        }
    }
    let log_q = student_log_density(student, &s_n, pts.as_ref())?;
    let density = log_q.iter().map(|l| l.exp()).collect();
    student.forward(MatRef::from_row_major_slice(&s_n, 1, ds))?;
    let out = student.output();
    let experts = (0..out.num_experts)
        .map(|z| {
            let (mu, l) = (out.mean(0, z), out.scale(0, z));
            let mut covariance = vec![0.0f32; d * d];
            for r in 0..d {
                for c in 0..d {
                    let llt: f32 = (0..=r.min(c)).map(|k| l[r * d + k] * l[c * d + k]).sum();
                    covariance[r * d + c] = llt * an.scale[r] * an.scale[c];
                }
            }
            RawExpert {
                mean: (0..d).map(|j| mu[j] * an.scale[j] + an.offset[j]).collect(),
                covariance,
                weight: out.log_gating_row(0)[z].exp(),
            }
        })
        .collect();
    Ok(DensityMap { n, density, experts })
}

/// The student's state and action normalisers (identity when unset).
fn normalizers<E: Expert>(student: &Moe<E>) -> (Affine, Affine) {
    let (d, ds) = (student.config().action_dim, student.config().state_dim);
    let (sn, an) = student.normalizers();
    (
        sn.cloned().unwrap_or_else(|| Affine::identity(ds)),
        an.cloned().unwrap_or_else(|| Affine::identity(d)),
    )
}

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
