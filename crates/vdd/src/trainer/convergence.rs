//! Whether a run converged: the student's **score mismatch** on a fixed probe, measured at
//! eighths of the run, and the verdict at its end ([`Convergence`]).
//!
//! The mismatch is the relative Fisher divergence between the student and the teacher,
//! `E |score_π(a|s) − ∇_a log q(a|s)|² / E |∇_a log q(a|s)|²` over actions `a ~ q(·|s)` of the
//! student at up to [`PROBE_STATES`] of the data's states (evenly spaced), in the student's
//! action space, with the teacher at the noise level the run ends at. It needs nothing but the
//! teacher's score, is 0 when the student equals the teacher, and is scale-free. The probe's
//! draws are the same at every measurement (their own stream, `"convergence-probe"`), so the
//! values of one run differ only by what the student learned; no draw of the training itself
//! changes, so a run with the probe trains the same student as before it existed.
//!
//! The verdict: a run has **converged** when its final mismatch is at most
//! [`CONVERGED_MISMATCH`]; or else when, on a log scale, at most [`LATE_SHARE`] of its fall
//! from the first measurement (an eighth into the run) happened in the second half (at a
//! learning rate that decays to 0, a run still falling fast at half time was cut short) and it
//! ends within [`RISE`] of the lowest value it reached (a run that got worse is not settled). A
//! run whose mismatch stays high but flat (a teacher the mixture cannot represent exactly) has
//! converged. The mismatch is measured where the student puts its mass, like the reverse KL
//! that VDD minimises: a run that settled with a mode left out has converged too (whether
//! every mode is covered needs the teacher's samples, `crate::eval`).

use faer::Mat;
use rand::Rng as _;
use serde::{Deserialize, Serialize};
use vdd_core::{Expert, ScoreModel, Seeds, gaussian};
use vdd_moe::Moe;

use super::{Vdd, at_iteration};
use crate::error::VddError;
use crate::spaces::with_map;

/// Measurements of the score mismatch per run (at `k/8` of it, `k = 1..=8`).
pub const PROBES: usize = 8;

/// Most data states the probe uses.
pub const PROBE_STATES: usize = 64;

/// Student actions per probe: `PROBE_ACTIONS / states` (rounded down) at each of its states.
pub const PROBE_ACTIONS: usize = 1024;

/// A final score mismatch at most this is converged whatever the trend.
pub const CONVERGED_MISMATCH: f32 = 0.01;

/// Otherwise, a run whose mismatch fell in its second half by more than this share of its
/// whole fall since the first measurement (in logs) has not converged.
pub const LATE_SHARE: f32 = 0.25;

/// ... nor has one that ends above its lowest measured mismatch by more than this factor.
pub const RISE: f32 = 1.25;

/// The verdict at the end of a run (see the module docs): [`Vdd::convergence`] and the last
/// iteration's [`crate::IterationMetrics::converged`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Convergence {
    /// The score mismatch after each measured iteration count (eighths of the run; `f32::MAX`
    /// where the probe overflowed).
    pub mismatches: Vec<(usize, f32)>,
    /// Score mismatch at the end of the run.
    pub mismatch: f32,
    /// Whether the run converged.
    pub converged: bool,
}

impl Convergence {
    /// The verdict from the mismatches of a run of `iterations` iterations, measured after
    /// the iteration counts [`probe_points`] gives (`None` when one of them is missing).
    ///
    /// ```
    /// use vdd::trainer::{Convergence, probe_points};
    /// let run = |values: &[f32]| -> Vec<(usize, f32)> {
    ///     probe_points(800).into_iter().zip(values.iter().copied()).collect()
    /// };
    /// let judge = |v: &[f32]| Convergence::judge(&run(v), 800).unwrap().converged;
    /// assert!(judge(&[9.0, 2.0, 0.5, 0.1, 0.05, 0.02, 0.01, 0.005])); // small at the end
    /// assert!(judge(&[9.0, 1.0, 0.6, 0.52, 0.5, 0.5, 0.5, 0.5])); // high but flat
    /// assert!(!judge(&[9.0, 5.0, 3.0, 1.0, 0.5, 0.2, 0.1, 0.05])); // still falling
    /// assert!(!judge(&[9.0, 1.0, 0.2, 0.2, 0.3, 0.3, 0.4, 0.4])); // got worse
    /// assert!(!judge(&[f32::MAX; 8])); // the probe overflowed every time
    /// assert!(!judge(&[9.0, 1.0, 0.5, 0.5, 0.5, 0.5, 0.5, f32::MAX])); // overflowed at the end
    /// ```
    pub fn judge(mismatches: &[(usize, f32)], iterations: usize) -> Option<Self> {
        let at = |i: usize| mismatches.iter().find(|p| p.0 == i).map(|p| p.1);
        let points = probe_points(iterations);
        let values: Option<Vec<f32>> = points.iter().map(|&i| at(i)).collect();
        let values = values?;
        let (first, end) = (values[0], *values.last()?);
        let half = at(points[(points.len() - 1) / 2])?;
        let lowest = values.iter().copied().fold(f32::INFINITY, f32::min);
        let late = (half / end).ln();
        let whole = (first / end).ln();
        let falling = late > 0.0 && late > LATE_SHARE * whole;
        let rose = end > RISE * lowest;
        let measurable = end.is_finite() && end < f32::MAX;
        let converged = measurable && (end <= CONVERGED_MISMATCH || !(falling || rose));
        Some(Self {
            mismatches: points.iter().copied().zip(values).collect(),
            mismatch: end,
            converged,
        })
    }
}

/// The 1-based iteration counts after which the probe measures (`k/8` of `iterations`,
/// rounded, without repeats).
///
/// ```
/// assert_eq!(vdd::trainer::probe_points(80), vec![10, 20, 30, 40, 50, 60, 70, 80]);
/// ```
pub fn probe_points(iterations: usize) -> Vec<usize> {
    let mut at: Vec<usize> =
        (1..=PROBES).map(|k| ((k * iterations + PROBES / 2) / PROBES).max(1)).collect();
    at.dedup();
    at
}

impl<S: ScoreModel, E: Expert> Vdd<S, E> {
    /// The verdict of a finished run (`None` before its last iteration, or when a resumed run
    /// lacks a measurement).
    ///
    /// ```
    /// use vdd::faer::Mat;
    /// use vdd::gmm::GmmTeacher;
    /// use vdd::{DistillData, MoeConfig, Vdd, VddConfig};
    /// let data = DistillData::from_states(Mat::zeros(16, 1))?;
    /// let config = VddConfig { iterations: 40, ..VddConfig::toy() };
    /// let student = MoeConfig::toy(1, 2, 8);
    /// let mut vdd = Vdd::from_config(config, GmmTeacher::circle_toy(), student, data)?;
    /// assert!(vdd.convergence().is_none()); // not finished
    /// vdd.train(|_| {})?;
    /// let verdict = vdd.convergence().unwrap();
    /// println!("converged: {} (score mismatch {:.4})", verdict.converged, verdict.mismatch);
    /// assert_eq!(verdict.mismatches.len(), 8);
    /// assert_eq!(vdd.score_mismatch()?, verdict.mismatch); // the same probe, the same student
    /// # Ok::<(), Box<dyn std::error::Error>>(())
    /// ```
    pub fn convergence(&self) -> Option<Convergence> {
        let n = self.config.iterations;
        if self.iteration < n {
            return None;
        }
        Convergence::judge(&self.probes, n)
    }

    /// The score mismatch of the student [`vdd_core::Trainer::finish`] would return now (see
    /// the module docs).
    pub fn score_mismatch(&mut self) -> Result<f32, VddError> {
        let mut student = self.student.clone();
        if let Some(ema) = &self.student_ema {
            ema.copy_to(&mut student)?;
        }
        self.mismatch_of(&mut student)
    }

    /// The score mismatch of `student` on the probe.
    fn mismatch_of(&mut self, student: &mut Moe<E>) -> Result<f32, VddError> {
        let n_data = self.data.states.nrows();
        let p = n_data.min(PROBE_STATES);
        let m = PROBE_ACTIONS / p;
        let (ds, d) = (self.data.states.ncols(), student.config().action_dim);
        let rows: Vec<usize> = (0..p).map(|k| k * n_data / p).collect();
        let probe = Mat::from_fn(p, ds, |k, j| self.data.states[(rows[k], j)]);
        let teacher_states = match &self.teacher_states {
            Some(t) => Mat::from_fn(p * m, ds, |r, j| t[(rows[r / m], j)]),
            None => Mat::from_fn(p * m, ds, |r, j| probe[(r / m, j)]),
        };
        student.forward(probe.as_ref())?;
        let out = student.output();
        let z_n = out.num_experts;
        let mut rng = Seeds::new(self.config.seed).stream("convergence-probe");
        let mut actions = Mat::<f32>::zeros(p * m, d);
        let mut own = Mat::<f32>::zeros(p * m, d);
        let (mut eps, mut a, mut grad) = (vec![0.0; d], vec![0.0; d], vec![0.0; d]);
        let (mut resp, mut work) = (vec![0.0; z_n], vec![0.0; d]);
        for r in 0..p * m {
            let b = r / m;
            // z ~ q(z|s) by its cumulative weights, then a ~ N(μ_z, Σ_z).
            let u: f32 = rng.random();
            let lg = out.log_gating_row(b);
            let mut acc = 0.0;
            let z = lg
                .iter()
                .position(|l| {
                    acc += l.exp();
                    u < acc
                })
                .unwrap_or(z_n - 1);
            vdd_core::fill_standard_normal(&mut rng, &mut eps);
            gaussian::sample_into(out.mean(b, z), out.scale(b, z), &eps, &mut a);
            // ∇_a log q(a|s) = Σ_z q(z|a, s) ∇_a log N(a; μ_z, Σ_z).
            out.log_density_and_responsibilities(b, &a, &mut resp, &mut work);
            for j in 0..d {
                actions[(r, j)] = a[j];
            }
            for (k, q) in resp.iter().enumerate() {
                gaussian::log_density_and_grad(&a, out.mean(b, k), out.scale(b, k), &mut grad);
                for j in 0..d {
                    own[(r, j)] += q * grad[j];
                }
            }
        }
        let mut levels = vec![0.0f32; p * m];
        self.teacher.draw_noise_levels(&self.config.noise, 1.0, &mut rng, &mut levels);
        let mut score = Mat::<f32>::zeros(p * m, d);
        let (map, scratch) = (self.action_map.as_ref(), &mut self.map_scratch);
        with_map(&mut self.teacher, map, scratch, |t| {
            t.score(actions.as_ref(), teacher_states.as_ref(), &levels, score.as_mut())
        })
        .map_err(at_iteration(self.iteration))?;
        let (mut diff, mut norm) = (0.0f64, 0.0f64);
        for r in 0..p * m {
            for j in 0..d {
                diff += f64::from(score[(r, j)] - own[(r, j)]).powi(2);
                norm += f64::from(own[(r, j)]).powi(2);
            }
        }
        // A probe that overflows (a very sharp student or teacher) is a measurement, not a
        // failure of the run: it reads as `f32::MAX` (finite, so checkpoints keep it), and the
        // verdict as not converged.
        let mismatch = (diff / norm.max(f64::MIN_POSITIVE)) as f32;
        Ok(if mismatch.is_finite() { mismatch } else { f32::MAX })
    }

    /// After iteration `iteration` (1-based count): the probe's measurement when one is due,
    /// kept for the verdict.
    pub(super) fn probe_after(&mut self, count: usize) -> Result<Option<f32>, VddError> {
        if !probe_points(self.config.iterations).contains(&count) {
            return Ok(None);
        }
        let value = self.score_mismatch()?;
        self.probes.retain(|p| p.0 != count);
        self.probes.push((count, value));
        Ok(Some(value))
    }
}

#[cfg(test)]
mod tests {
    use super::super::tests::small_run;
    use super::*;
    use crate::IterationMetrics;

    /// The four-mode toy of `iterations` iterations: its verdict and every iteration's
    /// metrics.
    fn toy(iterations: usize) -> (Convergence, Vec<IterationMetrics>) {
        let (config, teacher, student, data) = small_run(iterations);
        let mut vdd = Vdd::new(config, teacher, student, data).unwrap();
        let mut metrics = Vec::new();
        vdd.train(|m| metrics.push(*m)).unwrap();
        (vdd.convergence().unwrap(), metrics)
    }

    #[test]
    fn a_truncated_run_says_it_has_not_converged_and_a_full_one_that_it_has() {
        let (cut, metrics) = toy(24);
        assert!(!cut.converged, "{cut:?}");
        assert_eq!(metrics.last().unwrap().converged, Some(false));
        assert!(metrics[..23].iter().all(|m| m.converged.is_none()));
        let measured: Vec<usize> = metrics
            .iter()
            .filter(|m| m.score_mismatch.is_some())
            .map(|m| m.iteration + 1)
            .collect();
        assert_eq!(measured, probe_points(24));
        let (full, metrics) = toy(300);
        assert!(full.converged && full.mismatch < cut.mismatch, "{full:?} {cut:?}");
        assert_eq!(metrics.last().unwrap().converged, Some(true));
    }

    #[test]
    fn probes_fall_on_eighths_and_missing_ones_leave_no_verdict() {
        assert_eq!(probe_points(600), vec![75, 150, 225, 300, 375, 450, 525, 600]);
        assert_eq!(probe_points(3), vec![1, 2, 3]);
        assert_eq!(probe_points(1), vec![1]);
        let all: Vec<(usize, f32)> = probe_points(3).into_iter().map(|i| (i, 1.0)).collect();
        assert!(Convergence::judge(&all, 3).is_some_and(|c| c.converged));
        assert!(Convergence::judge(&all[1..], 3).is_none());
    }
}
