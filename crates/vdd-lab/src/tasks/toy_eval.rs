//! One panel of Figure 2 for a toy student ([`density_panel`]) with its settings (the recipes'
//! `[plots]`). The evaluation against the exact mixture is [`vdd::eval::against_gmm`].

use vdd::eval;
use vdd_core::gmm::Gmm;
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
/// ([`eval::density_map`]) and the teacher's score field at its VDD noise level
/// ([`eval::score_arrows`]).
pub fn density_panel(
    d: &mut ToyStudent,
    s: f32,
    title: String,
    modes: Vec<(f32, f32)>,
    p: &ToyPlots,
) -> crate::Result<DensityPanel> {
    let e = p.extent;
    let map = eval::density_map(&mut d.student, &[s], e, p.grid)?;
    let (sn, an, level) = (&d.state_norm, &d.action_norm, d.noise_level);
    let arrows = eval::score_arrows(d.teacher.as_mut(), sn, an, s, e, p.arrows, level)?;
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

/// `k` modes on the circle of radius 2 rotated by `offset` ([`Gmm::circle`]'s means).
pub fn circle_modes(k: usize, offset: f32) -> crate::Result<Vec<(f32, f32)>> {
    let gmm = Gmm::circle(k, 2.0, 0.5, offset)?;
    Ok((0..k).map(|i| (gmm.mean(i)[0], gmm.mean(i)[1])).collect())
}
