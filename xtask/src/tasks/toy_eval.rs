//! One panel of Figure 2 for a toy student ([`density_panel`]) with its settings (the recipes'
//! `[plots]`). The evaluation against the exact mixture is [`vdd::eval::against_gmm`].

use faer::Mat;
use vdd::eval;
use vdd_core::{Affine, ScoreModel};
use vdd_moe::Moe;

pub use vdd_tasks::toy::ToyPlots;

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

/// One panel of Figure 2 at raw state `s`: the student's density and experts
/// ([`eval::density_map`]) and the teacher's score field at its VDD noise level.
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
    let map = eval::density_map(&mut d.student, &[s], e, p.grid)?;
    // Score field of the teacher at its VDD noise level, mapped to raw coordinates.
    let k = p.arrows.max(2);
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
    let experts = map
        .experts
        .iter()
        .map(|x| ExpertEllipse {
            mean: (x.mean[0], x.mean[1]),
            cov: (x.covariance[0], x.covariance[1], x.covariance[3]),
            weight: x.weight,
        })
        .collect();
    Ok(DensityPanel { title, extent: e, density: map.density, n: map.n, arrows, experts, modes })
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
