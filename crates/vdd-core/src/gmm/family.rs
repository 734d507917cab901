//! A seeded family of exact Gaussian-mixture teachers of every shape a user might bring: the
//! problems of the robustness benchmark (`cargo xtask bench robustness`).
//!
//! Problem `i` of [`robustness_problem`] is a mixture of `K ∈ [2, 8]` full-covariance Gaussians
//! in `d ∈ [2, 10]` action dimensions. In unit space the means are drawn `N(0, 3² I)`, at least
//! [`MIN_SEPARATION`] apart; each covariance is a random rotation of eigenvalues between
//! `s²/c` and `s²` (`s ∈ [0.5, 1]`, condition number `c` up to 100); weights are at least 5 %.
//! The problem is then scaled by a factor between 0.01 and 100 and shifted by an offset of
//! norm up to 50. Odd problems are state-conditioned: at state `s ∈ R²` component `k` sits at
//! `μ_k + B s + C_k s` (a shared motion `B` and a smaller one `C_k` of its own), so the modes
//! move with the state. The ranges are swept deterministically over the first 24 problems so
//! that every extreme occurs. [`robustness_extras`] adds shapes the random draw does not make:
//! weights that depend on the state, teachers served through their score alone, and a curved
//! target that fewer experts than components must cover.
//!
//! ```
//! use vdd_core::ScoreModel;
//! use vdd_core::gmm::family::robustness_problem;
//!
//! let p = robustness_problem(5, 0).unwrap();
//! assert_eq!(p.teacher.action_dim(), p.info.action_dim);
//! assert!(p.info.conditional);
//! assert!((2..=8).contains(&p.info.components));
//! ```

use faer::Mat;
use rand::Rng as _;
use serde::{Deserialize, Serialize};

use super::{Gmm, GmmTeacher};
use crate::{Result, Rng, Seeds, gaussian, standard_normal};

mod extras;
pub use extras::{FIRST_EXTRA, robustness_extras};

/// Minimum distance between two component means in unit space (component stds are ≤ 1).
pub const MIN_SEPARATION: f32 = 3.5;

/// Dimension of the states of every problem (ignored by the unconditional ones).
pub const STATE_DIM: usize = 2;

/// What a problem is, for reports.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ProblemInfo {
    /// `p<index>-d<dim>-k<components>[-cond]`.
    pub name: String,
    /// Index in the family.
    pub index: usize,
    /// Action dimension `d`.
    pub action_dim: usize,
    /// Number of components `K`.
    pub components: usize,
    /// Whether the modes move with the state.
    pub conditional: bool,
    /// Factor applied to the unit-space problem.
    pub scale: f32,
    /// Norm of the offset added to every mean.
    pub offset_norm: f32,
    /// Largest condition number of a covariance.
    pub condition: f32,
    /// Smallest component weight.
    pub min_weight: f32,
    /// Served to the student through its score alone (a teacher without `sample_actions`).
    #[serde(default)]
    pub score_only: bool,
    /// Experts the benchmark distils it into (and twice as many): its number of components,
    /// or fewer for a target made of many small components along a curve.
    #[serde(default)]
    pub experts: usize,
    /// Regions its coverage counts (groups of components, [`MixtureProblem::regions`]).
    #[serde(default)]
    pub regions: usize,
}

/// One problem: the teacher, the states to distil on and the states to evaluate at.
#[derive(Debug, Clone)]
pub struct MixtureProblem {
    /// Its description.
    pub info: ProblemInfo,
    /// The exact teacher (raw units).
    pub teacher: GmmTeacher,
    /// 512 states `N(0, I)` to distil on (`STATE_DIM` columns).
    pub train_states: Mat<f32>,
    /// States to evaluate at: 4 for a conditional problem, 1 otherwise.
    pub eval_states: Mat<f32>,
    /// Region of each component for coverage (each its own for the random family).
    pub regions: Vec<usize>,
}

/// The first `n` problems of the family of root seed `seed`.
pub fn robustness_family(n: usize, seed: u64) -> Result<Vec<MixtureProblem>> {
    (0..n).map(|i| robustness_problem(i, seed)).collect()
}

/// Sweep position of problem `i` in `[0, 1]`: a permutation of the first 24 by `stride`,
/// random beyond.
fn sweep(i: usize, stride: usize, rng: &mut Rng) -> f32 {
    if i < 24 { ((i * stride) % 24) as f32 / 23.0 } else { rng.random() }
}

/// Problem `i` of the family of root seed `seed` (see the module docs).
pub fn robustness_problem(i: usize, seed: u64) -> Result<MixtureProblem> {
    let seeds = Seeds::new(seed).child("robustness-family");
    let mut rng = seeds.stream_indexed("problem", i as u64);
    let d = if i < 24 { 2 + (i * 5) % 9 } else { rng.random_range(2..=10) };
    let k = if i < 24 { 2 + (i * 3) % 7 } else { rng.random_range(2..=8) };
    let scale = 10f32.powf(-2.0 + 4.0 * sweep(i, 7, &mut rng));
    let offset_norm = 50.0 * sweep(i, 11, &mut rng);
    let condition = 10f32.powf(2.0 * sweep(i, 13, &mut rng));
    let conditional = i % 2 == 1;

    // Unit-space means, at least MIN_SEPARATION apart.
    let mut means: Vec<Vec<f32>> = Vec::with_capacity(k);
    while means.len() < k {
        let mut best: Option<(f32, Vec<f32>)> = None;
        for _ in 0..200 {
            let m: Vec<f32> = (0..d).map(|_| 3.0 * standard_normal(&mut rng)).collect();
            let gap = means.iter().map(|o| dist(o, &m)).fold(f32::INFINITY, f32::min);
            if best.as_ref().is_none_or(|(g, _)| gap > *g) {
                best = Some((gap, m));
            }
            if gap >= MIN_SEPARATION {
                break;
            }
        }
        means.push(best.expect("200 draws").1);
    }
    let covs: Vec<Vec<f32>> = (0..k)
        .map(|c| {
            let s = rng.random_range(0.5f32..1.0);
            // The first component has the problem's condition number; the others up to it.
            let cond = if c == 0 { condition } else { condition.powf(rng.random()) };
            let eig: Vec<f32> = (0..d)
                .map(|j| {
                    let t = match j {
                        0 => 0.0,
                        j if j == d - 1 => 1.0,
                        _ => rng.random(),
                    };
                    s * s * cond.powf(-t)
                })
                .collect();
            rotated(&eig, &random_rotation(d, &mut rng))
        })
        .collect();
    let u: Vec<f32> = (0..k).map(|_| rng.random_range(0.0f32..1.0)).collect();
    let total: f32 = u.iter().sum::<f32>().max(1e-6);
    let weights: Vec<f32> = u.iter().map(|x| 0.05 + (1.0 - 0.05 * k as f32) * x / total).collect();
    let min_weight = weights.iter().copied().fold(f32::INFINITY, f32::min);
    let dir: Vec<f32> = (0..d).map(|_| standard_normal(&mut rng)).collect();
    let norm = dir.iter().map(|x| x * x).sum::<f32>().sqrt().max(1e-6);
    let offset: Vec<f32> = dir.iter().map(|x| offset_norm * x / norm).collect();
    let raw_means: Vec<Vec<f32>> =
        means.iter().map(|m| m.iter().zip(&offset).map(|(x, o)| o + scale * x).collect()).collect();
    let raw_covs: Vec<Vec<f32>> =
        covs.iter().map(|c| c.iter().map(|x| x * scale * scale).collect()).collect();
    let gmm = Gmm::new(&weights, &raw_means, &raw_covs)?;
    let teacher = if conditional {
        // Shared motion B (d x STATE_DIM) and each component's own C_k, in unit space.
        let shared: Vec<f32> =
            (0..d * STATE_DIM).map(|_| 1.5 * standard_normal(&mut rng)).collect();
        let own: Vec<Vec<f32>> = (0..k)
            .map(|_| (0..d * STATE_DIM).map(|_| 0.3 * standard_normal(&mut rng)).collect())
            .collect();
        GmmTeacher::conditional(STATE_DIM, d, move |s| {
            let moved: Vec<Vec<f32>> = raw_means
                .iter()
                .zip(&own)
                .map(|(m, c)| {
                    (0..d)
                        .map(|j| {
                            let shift: f32 = (0..STATE_DIM)
                                .map(|t| (shared[j * STATE_DIM + t] + c[j * STATE_DIM + t]) * s[t])
                                .sum();
                            m[j] + scale * shift
                        })
                        .collect()
                })
                .collect();
            Gmm::new(&weights, &moved, &raw_covs)
        })
    } else {
        GmmTeacher::fixed(gmm, STATE_DIM)
    };
    let mut states = seeds.stream_indexed("states", i as u64);
    let train_states = Mat::from_fn(512, STATE_DIM, |_, _| standard_normal(&mut states));
    let n_eval = if conditional { 4 } else { 1 };
    let eval_states = Mat::from_fn(n_eval, STATE_DIM, |_, _| standard_normal(&mut states));
    let name = format!("p{i:02}-d{d}-k{k}{}", if conditional { "-cond" } else { "" });
    Ok(MixtureProblem {
        info: ProblemInfo {
            name,
            index: i,
            action_dim: d,
            components: k,
            conditional,
            scale,
            offset_norm,
            condition,
            min_weight,
            score_only: false,
            experts: k,
            regions: k,
        },
        teacher,
        train_states,
        eval_states,
        regions: (0..k).collect(),
    })
}

fn dist(a: &[f32], b: &[f32]) -> f32 {
    a.iter().zip(b).map(|(x, y)| (x - y) * (x - y)).sum::<f32>().sqrt()
}

/// A random rotation (`d x d`, row-major): Gram–Schmidt on a Gaussian matrix.
fn random_rotation(d: usize, rng: &mut Rng) -> Vec<f32> {
    let mut q = vec![0.0f32; d * d];
    for r in 0..d {
        loop {
            let mut v: Vec<f32> = (0..d).map(|_| standard_normal(rng)).collect();
            for p in 0..r {
                let dot: f32 = (0..d).map(|j| v[j] * q[p * d + j]).sum();
                for j in 0..d {
                    v[j] -= dot * q[p * d + j];
                }
            }
            let n = v.iter().map(|x| x * x).sum::<f32>().sqrt();
            if n > 1e-3 {
                for j in 0..d {
                    q[r * d + j] = v[j] / n;
                }
                break;
            }
        }
    }
    q
}

/// `Qᵀ diag(eig) Q`, symmetrised exactly.
fn rotated(eig: &[f32], q: &[f32]) -> Vec<f32> {
    let d = eig.len();
    let mut c = vec![0.0f32; d * d];
    for r in 0..d {
        for s in 0..=r {
            let v: f32 = (0..d).map(|t| q[t * d + r] * eig[t] * q[t * d + s]).sum();
            c[r * d + s] = v;
            c[s * d + r] = v;
        }
    }
    // Keep it safely positive definite in f32.
    let mut l = c.clone();
    if !gaussian::cholesky_in_place(&mut l, d) {
        let floor = eig.iter().copied().fold(f32::INFINITY, f32::min) * 1e-3;
        for j in 0..d {
            c[j * d + j] += floor;
        }
    }
    c
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ScoreModel;

    #[test]
    fn the_family_sweeps_its_ranges_and_is_deterministic() {
        let family = robustness_family(24, 0).unwrap();
        let infos: Vec<&ProblemInfo> = family.iter().map(|p| &p.info).collect();
        let dims: Vec<usize> = infos.iter().map(|p| p.action_dim).collect();
        let ks: Vec<usize> = infos.iter().map(|p| p.components).collect();
        assert_eq!((dims.iter().min(), dims.iter().max()), (Some(&2), Some(&10)));
        assert_eq!((ks.iter().min(), ks.iter().max()), (Some(&2), Some(&8)));
        let scales: Vec<f32> = infos.iter().map(|p| p.scale).collect();
        assert!(scales.iter().any(|s| (s - 0.01).abs() < 1e-5));
        assert!(scales.iter().any(|s| (s - 100.0).abs() < 1e-2));
        assert!(infos.iter().any(|p| (p.condition - 100.0).abs() < 1e-2));
        assert!(infos.iter().any(|p| (p.offset_norm - 50.0).abs() < 1e-3));
        assert!(infos.iter().all(|p| p.min_weight >= 0.05 - 1e-6));
        assert_eq!(infos.iter().filter(|p| p.conditional).count(), 12);
        let again = robustness_problem(7, 0).unwrap();
        assert_eq!(again.info, family[7].info);
        let other = robustness_problem(7, 1).unwrap();
        let (x, y) =
            (other.teacher.mixture_at(&[0.0, 0.0]), family[7].teacher.mixture_at(&[0.0; 2]));
        assert_ne!(x.unwrap().mean(0), y.unwrap().mean(0));
    }

    #[test]
    fn conditional_modes_move_with_the_state_and_covariances_have_their_condition() {
        let p = robustness_problem(1, 0).unwrap();
        let a = p.teacher.mixture_at(&[0.0, 0.0]).unwrap();
        let b = p.teacher.mixture_at(&[1.0, 0.0]).unwrap();
        assert!(dist(a.mean(0), b.mean(0)) > 0.1 * p.info.scale);
        assert_eq!(p.teacher.state_dim(), STATE_DIM);
        // The first component's covariance has the problem's condition number.
        let q = robustness_problem(4, 0).unwrap();
        let g = q.teacher.mixture_at(&[0.0, 0.0]).unwrap();
        let d = g.dim();
        let c = g.covariance(0);
        let m = faer::Mat::from_fn(d, d, |r, s| f64::from(c[r * d + s]));
        let eig = m.self_adjoint_eigenvalues(faer::Side::Lower).unwrap();
        let ratio = eig[d - 1] / eig[0];
        assert!((ratio / f64::from(q.info.condition) - 1.0).abs() < 0.05, "{ratio}");
    }
}
