//! A student against an exact Gaussian-mixture teacher, in raw (environment) units: the
//! figures of the robustness benchmark.

use faer::{Mat, MatRef};
use serde::{Deserialize, Serialize};
use vdd_core::gmm::GmmTeacher;
use vdd_core::{Expert, Rng, gaussian};
use vdd_moe::Moe;

use crate::error::VddError;

/// KL estimates and coverage of one student against an exact mixture, averaged over states.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct MixtureEval {
    /// `E_q[log q − log p]` in nats, by Monte Carlo, mean over the states.
    pub reverse_kl: f64,
    /// `E_p[log p − log q]` in nats, by Monte Carlo, mean over the states.
    pub forward_kl: f64,
    /// Components of the teacher (at the first state), or regions of components
    /// ([`evaluate_against_mixture_in_regions`]).
    pub components: usize,
    /// Components (or regions) covered at every state: at least `min_share` of the student's
    /// samples have the component (a component of the region) as their most likely one.
    pub components_covered: usize,
}

/// Evaluates `student` (with its normalisers: it is compared in raw units, its density
/// including the normaliser's Jacobian) against `teacher` at each row of the raw `states`,
/// with `samples` student and `samples` teacher samples per state.
///
/// ```
/// use faer::Mat;
/// use vdd::eval::evaluate_against_mixture;
/// use vdd::gmm::GmmTeacher;
/// use vdd::{Moe, MoeConfig, Seeds};
///
/// let mut teacher = GmmTeacher::circle_toy();
/// let mut student = Moe::from_config(MoeConfig::toy(1, 2, 8), 0)?;
/// let mut rng = Seeds::new(0).stream("eval");
/// let e = evaluate_against_mixture(&mut student, &mut teacher, Mat::zeros(1, 1).as_ref(), 2000, 0.01, &mut rng)?;
/// assert_eq!(e.components, 8);
/// assert!(e.reverse_kl > 0.1); // an untrained student
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
pub fn evaluate_against_mixture<E: Expert>(
    student: &mut Moe<E>,
    teacher: &mut GmmTeacher,
    states: MatRef<'_, f32>,
    samples: usize,
    min_share: f32,
    rng: &mut Rng,
) -> Result<MixtureEval, VddError> {
    evaluate_against_mixture_in_regions(student, teacher, states, samples, min_share, None, rng)
}

/// [`evaluate_against_mixture`] with coverage counted by regions: `regions[k]` is the region
/// of the teacher's component `k` (`None`: every component its own region), and a region is
/// covered when at least `min_share` of the student's samples have one of its components as
/// their most likely one. For a teacher that is a curve or a surface approximated by many
/// small components, fewer experts than components can cover every region.
///
/// ```
/// use faer::Mat;
/// use vdd::eval::evaluate_against_mixture_in_regions;
/// use vdd::gmm::GmmTeacher;
/// use vdd::{Moe, MoeConfig, Seeds};
///
/// let mut teacher = GmmTeacher::circle_toy();
/// let mut student = Moe::from_config(MoeConfig::toy(1, 2, 8), 0)?;
/// let halves = [0, 0, 0, 0, 1, 1, 1, 1]; // the circle's two halves
/// let mut rng = Seeds::new(0).stream("eval");
/// let states = Mat::zeros(1, 1);
/// let e = evaluate_against_mixture_in_regions(
///     &mut student, &mut teacher, states.as_ref(), 2000, 0.01, Some(&halves), &mut rng,
/// )?;
/// assert_eq!(e.components, 2);
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
pub fn evaluate_against_mixture_in_regions<E: Expert>(
    student: &mut Moe<E>,
    teacher: &mut GmmTeacher,
    states: MatRef<'_, f32>,
    samples: usize,
    min_share: f32,
    regions: Option<&[usize]>,
    rng: &mut Rng,
) -> Result<MixtureEval, VddError> {
    let n_states = states.nrows();
    if n_states == 0 || samples == 0 {
        return Err(
            vdd_core::CoreError::Config("evaluation needs states and samples".into()).into()
        );
    }
    let (obs, act) = student.normalizers();
    let (obs, act) = (obs.cloned(), act.cloned());
    let d = student.config().action_dim;
    let log_jacobian: f64 =
        act.as_ref().map_or(0.0, |a| a.scale.iter().map(|s| f64::from(s.ln())).sum());
    let (mut reverse, mut forward) = (0.0f64, 0.0f64);
    let mut covered: Option<Vec<bool>> = None;
    let mut components = 0;
    for s in 0..n_states {
        let raw_state: Vec<f32> = (0..states.ncols()).map(|j| states[(s, j)]).collect();
        let mut state = raw_state.clone();
        if let Some(o) = &obs {
            o.normalize(&mut state);
        }
        let gmm = teacher.mixture_at(&raw_state)?;
        let k = gmm.num_components();
        let region_of = |c: usize| regions.map_or(c, |r| r[c]);
        if let Some(r) = regions {
            vdd_core::check_len("regions (one per component)", r.len(), k)?;
        }
        let n_regions = (0..k).map(region_of).max().map_or(0, |m| m + 1);
        if s == 0 {
            components = n_regions;
        }
        // Student samples, raw.
        let mut x = super::sample_student(student, &state, samples, rng)?;
        let log_q = super::student_log_density(student, &state, x.as_ref())?;
        if let Some(a) = &act {
            for i in 0..samples {
                for j in 0..d {
                    x[(i, j)] = x[(i, j)] * a.scale[j] + a.offset[j];
                }
            }
        }
        let rep = Mat::from_fn(samples, raw_state.len(), |_, j| raw_state[j]);
        let mut log_p = vec![0.0f32; samples];
        teacher.log_density_batch(x.as_ref(), rep.as_ref(), 0.0, &mut log_p)?;
        reverse += (0..samples)
            .map(|i| f64::from(log_q[i]) - log_jacobian - f64::from(log_p[i]))
            .sum::<f64>()
            / samples as f64;
        // Coverage: the most likely component of each student sample.
        let chols: Vec<Vec<f32>> = (0..k)
            .map(|c| {
                let mut l = gmm.covariance(c).to_vec();
                gaussian::cholesky_in_place(&mut l, d);
                l
            })
            .collect();
        let mut counts = vec![0usize; n_regions];
        let (mut a, mut work) = (vec![0.0f32; d], vec![0.0f32; d]);
        for i in 0..samples {
            for j in 0..d {
                a[j] = x[(i, j)];
            }
            let best = (0..k)
                .map(|c| {
                    gmm.weight(c).ln()
                        + gaussian::log_density(&a, gmm.mean(c), &chols[c], &mut work)
                })
                .enumerate()
                .fold((0, f32::NEG_INFINITY), |b, (c, v)| if v > b.1 { (c, v) } else { b })
                .0;
            counts[region_of(best)] += 1;
        }
        let here: Vec<bool> =
            counts.iter().map(|&c| c as f32 >= min_share * samples as f32).collect();
        covered = Some(match covered {
            None => here,
            Some(prev) => prev.iter().zip(&here).map(|(a, b)| *a && *b).collect(),
        });
        // Forward KL from teacher samples.
        let mut y = Mat::zeros(samples, d);
        for i in 0..samples {
            gmm.sample_into(rng, &mut a);
            for j in 0..d {
                y[(i, j)] = a[j];
            }
        }
        teacher.log_density_batch(y.as_ref(), rep.as_ref(), 0.0, &mut log_p)?;
        if let Some(m) = &act {
            for i in 0..samples {
                for j in 0..d {
                    y[(i, j)] = (y[(i, j)] - m.offset[j]) / m.scale[j];
                }
            }
        }
        let log_q = super::student_log_density(student, &state, y.as_ref())?;
        forward += (0..samples)
            .map(|i| f64::from(log_p[i]) - f64::from(log_q[i]) + log_jacobian)
            .sum::<f64>()
            / samples as f64;
    }
    Ok(MixtureEval {
        reverse_kl: reverse / n_states as f64,
        forward_kl: forward / n_states as f64,
        components,
        components_covered: covered.map_or(0, |c| c.iter().filter(|x| **x).count()),
    })
}
