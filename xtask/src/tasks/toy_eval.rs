//! Evaluation of a toy student against the exact mixture: KL both ways and mode coverage at a
//! state ([`evaluate_at`]), and one panel of Figure 2 ([`density_panel`]), with their settings
//! (the recipes' `[eval]` and `[plots]`).
//!
//! KL and coverage are computed in the student's (teacher-normalised) action space with the
//! target transformed alike; KL is invariant under that affine map, and coverage distances are
//! measured after mapping the experts' means back to raw actions.

use faer::Mat;
use vdd::eval;
use vdd_core::gmm::Gmm;
use vdd_core::{Affine, ScoreModel, Seeds};
use vdd_moe::Moe;

pub use vdd_tasks::toy::{ToyEval, ToyPlots};

use crate::plots::{DensityPanel, ExpertEllipse};

/// A distilled toy student with what its evaluation needs.
pub struct ToyStudent {
    /// The mixture (its networks work in the normalised space).
    pub student: Moe,
    /// The student's (= teacher's) normalisers.
    pub state_norm: Affine,
    /// ... of the actions.
    pub action_norm: Affine,
    /// The teacher it was distilled from (for the score field of the figure).
    pub teacher: Box<dyn ScoreModel>,
    /// The mean noise level of the distillation.
    pub noise_level: f32,
}

/// KL both ways and coverage of the student at raw state `s` against the exact mixture `truth`.
pub fn evaluate_at(
    d: &mut ToyStudent,
    truth: &Gmm,
    s: f32,
    samples: usize,
    cfg: &ToyEval,
    seeds: &Seeds,
    index: u64,
) -> crate::XResult<(f64, f64, usize)> {
    let an = d.action_norm.clone();
    let log_det: f32 = an.scale.iter().map(|c| c.ln()).sum();
    let s_n = [(s - d.state_norm.offset[0]) / d.state_norm.scale[0]];
    // log p in the normalised space: p_n(a_n) = p(denorm(a_n)) · Π scale.
    let log_p = |a: &[f32]| {
        let raw = [a[0] * an.scale[0] + an.offset[0], a[1] * an.scale[1] + an.offset[1]];
        truth.log_density(&raw, 0.0).map(|l| l + log_det).unwrap_or(f32::NEG_INFINITY)
    };
    let reverse = eval::reverse_kl(
        &mut d.student,
        &s_n,
        log_p,
        samples,
        &mut seeds.stream_indexed("reverse", index),
    )?;
    let mut rng = seeds.stream_indexed("forward", index);
    let mut target = Mat::zeros(samples, 2);
    let mut a = [0.0f32; 2];
    for i in 0..samples {
        truth.sample_into(&mut rng, &mut a);
        for j in 0..2 {
            target[(i, j)] = (a[j] - an.offset[j]) / an.scale[j];
        }
    }
    let forward = eval::forward_kl(&mut d.student, &s_n, log_p, target.as_ref())?;
    // Coverage in raw coordinates.
    d.student.forward(faer::MatRef::from_row_major_slice(&s_n, 1, 1))?;
    let out = d.student.output();
    let lg = out.log_gating_row(0);
    let covered = (0..truth.num_components())
        .filter(|&k| {
            let m = truth.mean(k);
            (0..out.num_experts).any(|z| {
                let mu = out.mean(0, z);
                let raw = [mu[0] * an.scale[0] + an.offset[0], mu[1] * an.scale[1] + an.offset[1]];
                let dist = ((raw[0] - m[0]).powi(2) + (raw[1] - m[1]).powi(2)).sqrt();
                lg[z].exp() >= cfg.min_weight && dist <= cfg.coverage_radius
            })
        })
        .count();
    Ok((reverse, forward, covered))
}

/// One panel of Figure 2 at raw state `s`.
pub fn density_panel(
    d: &mut ToyStudent,
    s: f32,
    title: String,
    modes: Vec<(f32, f32)>,
    p: &ToyPlots,
) -> crate::XResult<DensityPanel> {
    let (sn, an) = (d.state_norm.clone(), d.action_norm.clone());
    let s_n = (s - sn.offset[0]) / sn.scale[0];
    let e = p.extent;
    let n = p.grid.max(2);
    let h = 2.0 * e / n as f32;
    let norm_point =
        |x: f32, y: f32| [(x - an.offset[0]) / an.scale[0], (y - an.offset[1]) / an.scale[1]];
    let mut pts = Mat::<f32>::zeros(n * n, 2);
    for i in 0..n {
        for j in 0..n {
            let q = norm_point(-e + (j as f32 + 0.5) * h, -e + (i as f32 + 0.5) * h);
            pts[(i * n + j, 0)] = q[0];
            pts[(i * n + j, 1)] = q[1];
        }
    }
    let log_q = eval::student_log_density(&mut d.student, &[s_n], pts.as_ref())?;
    let density: Vec<f32> = log_q.iter().map(|l| l.exp()).collect();
    // Score field of the teacher at its VDD noise level, mapped to raw coordinates.
    let k = p.arrows.max(2);
    let spacing = 2.0 * e / k as f32;
    let mut apts = Mat::<f32>::zeros(k * k, 2);
    let mut raw_pos = Vec::with_capacity(k * k);
    for i in 0..k {
        for j in 0..k {
            let (x, y) = (-e + (j as f32 + 0.5) * spacing, -e + (i as f32 + 0.5) * spacing);
            let q = norm_point(x, y);
            apts[(i * k + j, 0)] = q[0];
            apts[(i * k + j, 1)] = q[1];
            raw_pos.push((x, y));
        }
    }
    let states = Mat::from_fn(k * k, 1, |_, _| s_n);
    let levels = vec![d.noise_level; k * k];
    let mut score = Mat::<f32>::zeros(k * k, 2);
    d.teacher.score(apts.as_ref(), states.as_ref(), &levels, score.as_mut())?;
    let arrows = raw_pos
        .iter()
        .enumerate()
        .map(|(r, &pos)| {
            let (gx, gy) = (score[(r, 0)] / an.scale[0], score[(r, 1)] / an.scale[1]);
            let len = (gx * gx + gy * gy).sqrt().max(1e-12);
            // Direction at a fixed length, shortened where the field is weak.
            let l = 0.4 * spacing * (len / (len + 0.5));
            (pos, (gx / len * l, gy / len * l))
        })
        .collect();
    d.student.forward(faer::MatRef::from_row_major_slice(&[s_n], 1, 1))?;
    let out = d.student.output();
    let experts = (0..out.num_experts)
        .map(|z| {
            let mu = out.mean(0, z);
            let l = out.scale(0, z);
            let (l00, l10, l11) = (l[0], l[2], l[3]);
            let (c00, c01, c11) = (l00 * l00, l00 * l10, l10 * l10 + l11 * l11);
            let (s0, s1) = (an.scale[0], an.scale[1]);
            ExpertEllipse {
                mean: (mu[0] * s0 + an.offset[0], mu[1] * s1 + an.offset[1]),
                cov: (c00 * s0 * s0, c01 * s0 * s1, c11 * s1 * s1),
                weight: out.log_gating_row(0)[z].exp(),
            }
        })
        .collect();
    Ok(DensityPanel { title, extent: e, density, n, arrows, experts, modes })
}

/// `k` modes on the circle of radius 2 rotated by `offset`.
pub fn circle_modes(k: usize, offset: f32) -> Vec<(f32, f32)> {
    (0..k)
        .map(|i| {
            let a = offset + std::f32::consts::TAU * i as f32 / k as f32;
            (2.0 * a.cos(), 2.0 * a.sin())
        })
        .collect()
}
