//! Problems of the robustness benchmark beyond the random family: shapes that users met with
//! `Vdd::auto` (issue 33, item 7) and that the random family does not draw
//! ([`robustness_extras`]).
//!
//! * `x100-d2-k3-cond-weights` — **state-conditioned weights**: three modes on a circle of
//!   radius 2 (std 0.3) rotating with a scalar state `s` (mode `k` at angle `s + 2πk/3`), with
//!   weights `softmax([s, −s, 0])`; 256 training states `N(0, 1)`, evaluated at
//!   `s ∈ {−1.5, −0.75, 0, 0.75, 1.5}`.
//! * `x101-d6-k5-score` — **a score-only teacher**: the family's 6-D, 5-component
//!   full-covariance mixture (problem 8) served without `sample_actions`, on 32 identical
//!   states (a state-independent problem given as a handful of dummy states, as the README's
//!   first example does).
//! * `x102-d7-k5-cond-score` — the family's state-conditioned problem 1 served score-only on
//!   its 512 states.
//! * `x103-d2-k3-cond-weights-score` — the state-conditioned weights served score-only.
//! * `x104-d2-k36-ring-banana` — **a target the mixture cannot represent exactly**: a ring of
//!   radius 3 and a banana below it (`y = −7 + 0.6 x²`, `|x| ≤ 2.5`), each a chain of narrow
//!   components along the curve (24 and 12, across-curve std 0.15; 60 % of the mass on the
//!   ring), distilled into 8 experts. Coverage counts 9 regions (six sectors of the ring, three
//!   thirds of the banana) rather than the 36 components.
//!
//! ```
//! use vdd_core::gmm::family::robustness_extras;
//! let extras = robustness_extras(0).unwrap();
//! assert_eq!(extras.len(), 5);
//! let ring = &extras[4];
//! assert_eq!((ring.info.experts, ring.info.regions, ring.info.components), (8, 9, 36));
//! assert!(extras[1].info.score_only && !extras[0].info.score_only);
//! ```

use faer::Mat;

use super::{MixtureProblem, ProblemInfo, robustness_problem};
use crate::gmm::{Gmm, GmmTeacher};
use crate::{Result, Seeds, standard_normal};

/// Index of the first extra problem (they follow the random family's at a distance, so that
/// their indices do not depend on how many random problems a run uses).
pub const FIRST_EXTRA: usize = 100;

/// The extra problems of root seed `seed` (which draws their training states; see the module
/// docs).
pub fn robustness_extras(seed: u64) -> Result<Vec<MixtureProblem>> {
    let weights = rotating_weights(seed)?;
    let mut weights_score = weights.clone();
    weights_score.info.score_only = true;
    weights_score.info.index = FIRST_EXTRA + 3;
    weights_score.info.name = "x103-d2-k3-cond-weights-score".into();
    Ok(vec![
        weights,
        served_score_only(robustness_problem(8, seed)?, FIRST_EXTRA + 1, Some(32)),
        served_score_only(robustness_problem(1, seed)?, FIRST_EXTRA + 2, None),
        weights_score,
        ring_banana()?,
    ])
}

/// `p` served through its score alone: renamed `x<index>-d<d>-k<k>[-cond]-score`, on `states`
/// copies of a zero state when given (else on its own states).
fn served_score_only(mut p: MixtureProblem, index: usize, states: Option<usize>) -> MixtureProblem {
    let cond = if p.info.conditional { "-cond" } else { "" };
    p.info.name = format!("x{index}-d{}-k{}{cond}-score", p.info.action_dim, p.info.components);
    p.info.index = index;
    p.info.score_only = true;
    if let Some(n) = states {
        p.train_states = Mat::zeros(n, p.train_states.ncols());
        p.eval_states = Mat::zeros(1, p.eval_states.ncols());
    }
    p
}

/// Three modes rotating with the state, weights `softmax([s, −s, 0])` (module docs).
fn rotating_weights(seed: u64) -> Result<MixtureProblem> {
    let mixture = |s: &[f32]| {
        let w = [s[0].exp(), (-s[0]).exp(), 1.0];
        let means: Vec<Vec<f32>> = (0..3)
            .map(|k| {
                let a = s[0] + std::f32::consts::TAU * k as f32 / 3.0;
                vec![2.0 * a.cos(), 2.0 * a.sin()]
            })
            .collect();
        Gmm::isotropic(&w, &means, 0.3)
    };
    let teacher = GmmTeacher::conditional(1, 2, mixture);
    let mut rng = Seeds::new(seed).child("robustness-extras").stream("weights-states");
    let train_states = Mat::from_fn(256, 1, |_, _| standard_normal(&mut rng));
    let eval_states = Mat::from_fn(5, 1, |i, _| -1.5 + 0.75 * i as f32);
    let min_weight = {
        let e = (1.5f32).exp();
        1.0 / (e * e + e + 1.0)
    };
    let info = ProblemInfo {
        name: "x100-d2-k3-cond-weights".into(),
        index: FIRST_EXTRA,
        action_dim: 2,
        components: 3,
        conditional: true,
        scale: 1.0,
        offset_norm: 0.0,
        condition: 1.0,
        min_weight,
        score_only: false,
        experts: 3,
        regions: 3,
    };
    Ok(MixtureProblem { info, teacher, train_states, eval_states, regions: vec![0, 1, 2] })
}

/// Narrow components along the points `pts` of a curve (closed or not): component `i` at
/// `pts[i]`, elongated along the curve (std 0.7 of the spacing) and `width` across it, all
/// together weighing `mass`.
fn along_curve(
    pts: &[(f32, f32)],
    closed: bool,
    width: f32,
    mass: f32,
    out: &mut (Vec<f32>, Vec<Vec<f32>>, Vec<Vec<f32>>),
) {
    let n = pts.len();
    for i in 0..n {
        let (a, b, span) = match (closed, i) {
            (true, _) => (pts[(i + n - 1) % n], pts[(i + 1) % n], 2.0),
            (false, 0) => (pts[0], pts[1], 1.0),
            (false, i) if i + 1 == n => (pts[i - 1], pts[i], 1.0),
            (false, i) => (pts[i - 1], pts[i + 1], 2.0),
        };
        let (tx, ty) = (b.0 - a.0, b.1 - a.1);
        let len = (tx * tx + ty * ty).sqrt();
        let (ux, uy) = (tx / len, ty / len);
        let (t2, r2) = ((0.7 * len / span).powi(2), width * width);
        let c01 = ux * uy * (t2 - r2);
        out.0.push(mass / n as f32);
        out.1.push(vec![pts[i].0, pts[i].1]);
        out.2.push(vec![ux * ux * t2 + uy * uy * r2, c01, c01, uy * uy * t2 + ux * ux * r2]);
    }
}

/// The ring and the banana (module docs).
fn ring_banana() -> Result<MixtureProblem> {
    let mut parts = (Vec::new(), Vec::new(), Vec::new());
    let ring: Vec<(f32, f32)> = (0..24)
        .map(|k| {
            let a = std::f32::consts::TAU * k as f32 / 24.0;
            (3.0 * a.cos(), 3.0 * a.sin())
        })
        .collect();
    along_curve(&ring, true, 0.15, 0.6, &mut parts);
    let banana: Vec<(f32, f32)> = (0..12)
        .map(|k| {
            let x = -2.5 + 5.0 * k as f32 / 11.0;
            (x, -7.0 + 0.6 * x * x)
        })
        .collect();
    along_curve(&banana, false, 0.15, 0.4, &mut parts);
    let (weights, means, covs) = parts;
    let gmm = Gmm::new(&weights, &means, &covs)?;
    let condition = covs
        .iter()
        .map(|c| {
            let (tr, det) = (c[0] + c[3], c[0] * c[3] - c[1] * c[2]);
            let disc = (tr * tr / 4.0 - det).max(0.0).sqrt();
            (tr / 2.0 + disc) / (tr / 2.0 - disc)
        })
        .fold(1.0f32, f32::max);
    let min_weight = weights.iter().copied().fold(f32::INFINITY, f32::min);
    let regions: Vec<usize> =
        (0..36).map(|k| if k < 24 { k / 4 } else { 6 + (k - 24) / 4 }).collect();
    let info = ProblemInfo {
        name: format!("x{}-d2-k36-ring-banana", FIRST_EXTRA + 4),
        index: FIRST_EXTRA + 4,
        action_dim: 2,
        components: 36,
        conditional: false,
        scale: 1.0,
        offset_norm: 0.0,
        condition,
        min_weight,
        score_only: false,
        experts: 8,
        regions: 9,
    };
    let teacher = GmmTeacher::fixed(gmm, 1);
    Ok(MixtureProblem {
        info,
        teacher,
        train_states: Mat::zeros(32, 1),
        eval_states: Mat::zeros(1, 1),
        regions,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ScoreModel;

    #[test]
    fn the_weights_follow_the_state_and_the_ring_is_a_closed_chain() {
        let extras = robustness_extras(0).unwrap();
        let w = &extras[0].teacher;
        let (a, b) = (w.mixture_at(&[1.0]).unwrap(), w.mixture_at(&[-1.0]).unwrap());
        let e = 1f32.exp();
        assert!((a.weight(0) - e / (e + 1.0 / e + 1.0)).abs() < 1e-5);
        assert!((a.weight(0) - b.weight(1)).abs() < 1e-5);
        // Mode 0 at angle s.
        assert!((a.mean(0)[0] - 2.0 * 1f32.cos()).abs() < 1e-5);
        let ring = &extras[4];
        let g = ring.teacher.mixture_at(&[0.0]).unwrap();
        assert_eq!((g.num_components(), ring.regions.len()), (36, 36));
        assert_eq!(ring.regions.iter().max(), Some(&8));
        // Neighbouring ring components overlap along the ring: the density between them is
        // no less than a tenth of the density at a component.
        let mid = [
            3.0 * (std::f32::consts::TAU / 48.0).cos(),
            3.0 * (std::f32::consts::TAU / 48.0).sin(),
        ];
        let (at, between) =
            (g.log_density(&[3.0, 0.0], 0.0).unwrap(), g.log_density(&mid, 0.0).unwrap());
        assert!(between > at - 10f32.ln(), "{at} {between}");
        // Served score-only: the same teacher, named so.
        assert!(extras.iter().filter(|p| p.info.score_only).count() == 3);
        assert_eq!(extras[1].train_states.nrows(), 32);
        assert_eq!(extras[2].teacher.state_dim(), extras[2].train_states.ncols());
        let idx: Vec<usize> = extras.iter().map(|p| p.info.index).collect();
        assert_eq!(idx, vec![100, 101, 102, 103, 104]);
    }
}
