//! Tests of the automatic set-up.

use faer::Mat;
use vdd_core::gmm::{Gmm, GmmTeacher};
use vdd_core::{NoiseSchedule, ScoreModel};

use super::*;
use crate::test_support::IsoGmm;

/// Three modes far from the origin at scale `scale`.
fn far_teacher(scale: f32) -> GmmTeacher {
    let means: Vec<Vec<f32>> = [[0.0, 0.0], [4.0, 0.0], [0.0, 4.0]]
        .iter()
        .map(|m| vec![30.0 + scale * m[0], -7.0 + scale * m[1]])
        .collect();
    GmmTeacher::fixed(Gmm::isotropic(&[0.6, 0.3, 0.1], &means, 0.5 * scale).unwrap(), 1)
}

#[test]
fn the_schedule_follows_the_teachers_scale() {
    let states = Mat::<f32>::zeros(8, 1);
    let start = |scale: f32| {
        let c = VddConfig::for_teacher(&mut far_teacher(scale), states.as_ref(), 3, 0).unwrap();
        match c.noise {
            NoiseSchedule::Annealed { start, end } => (start, end, c.noise_anneal_until),
            other => panic!("{other:?}"),
        }
    };
    let (a, b) = (start(1.0), start(100.0));
    assert!((b.0 / a.0 - 100.0).abs() < 5.0, "{a:?} {b:?}");
    assert!((b.1 / a.1 - 100.0).abs() < 5.0, "{a:?} {b:?}");
    assert!(a.0 > 10.0 * a.1 && a.2 == Some(0.7));
}

#[test]
fn the_student_starts_on_the_teachers_components_with_their_weights() {
    let mut teacher = far_teacher(0.01);
    let data = DistillData::from_states(Mat::zeros(16, 1)).unwrap();
    let plan = AutoPlan::inspect(&mut teacher, &data, &AutoOptions::new(3, 1)).unwrap();
    assert_eq!(plan.source, SampleSource::Teacher);
    let mut student = plan.build_student().unwrap();
    student.forward(Mat::<f32>::zeros(1, 1).as_ref()).unwrap();
    let out = student.output().clone();
    let a = &plan.action_normalizer;
    let gmm = teacher.mixture_at(&[0.0]).unwrap();
    for k in 0..3 {
        // Some expert's (denormalised) mean lies within a tenth of a std of mode k, with the
        // mode's weight.
        let hit = (0..3).find(|&z| {
            let m = out.mean(0, z);
            (0..2).all(|j| (m[j] * a.scale[j] + a.offset[j] - gmm.mean(k)[j]).abs() < 5e-4)
        });
        let z = hit.unwrap_or_else(|| panic!("mode {k} has no expert: {}", plan.summary()));
        assert!((out.log_gating_row(0)[z].exp() - gmm.weight(k)).abs() < 0.03);
    }
}

/// A teacher seen through its score only.
struct ScoreOnly(IsoGmm);
impl ScoreModel for ScoreOnly {
    fn action_dim(&self) -> usize {
        self.0.action_dim()
    }
    fn state_dim(&self) -> usize {
        self.0.state_dim()
    }
    fn score(
        &mut self,
        a: faer::MatRef<'_, f32>,
        s: faer::MatRef<'_, f32>,
        sigma: &[f32],
        out: faer::MatMut<'_, f32>,
    ) -> Result<(), vdd_core::CoreError> {
        self.0.score(a, s, sigma, out)
    }
}

#[test]
fn a_teacher_without_a_sampler_is_sampled_through_its_score() {
    let mut teacher = ScoreOnly(IsoGmm::circle(4, 3.0, 0.3));
    let data = DistillData::from_states(Mat::zeros(4, 1)).unwrap();
    let options = AutoOptions { samples: 2000, ..AutoOptions::new(4, 0) };
    let plan = AutoPlan::inspect(&mut teacher, &data, &options).unwrap();
    assert_eq!(plan.source, SampleSource::ScoreSampling);
    // Modes at radius 3, std 0.3: per-dimension std sqrt(4.5 + 0.09).
    let s = plan.action_normalizer.scale.clone();
    assert!(s.iter().all(|s| (s - 4.59f32.sqrt()).abs() < 0.15), "{s:?}");
    assert_eq!(plan.gating_actions.as_ref().map(|a| a.nrows()), Some(4));
    // And the run can train its learned gating on those actions.
    let mut vdd = Vdd::from_plan(&plan, teacher, data).unwrap();
    vdd.step().unwrap();
}

#[test]
fn the_official_initialisation_has_state_independent_means_near_zero() {
    let mut teacher = far_teacher(1.0);
    let data = DistillData::from_states(Mat::from_fn(16, 1, |i, _| i as f32)).unwrap();
    let options = AutoOptions { init: InitKind::Official, ..AutoOptions::new(3, 0) };
    let mut student =
        AutoPlan::inspect(&mut teacher, &data, &options).unwrap().build_student().unwrap();
    student.forward(Mat::from_fn(2, 1, |i, _| 3.0 * i as f32 - 1.0).as_ref()).unwrap();
    let out = student.output();
    for z in 0..3 {
        let (m0, m1) = (out.mean(0, z), out.mean(1, z));
        assert!(m0.iter().all(|m| m.abs() <= 0.5) && m0 == m1, "{m0:?} {m1:?}");
    }
}
