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
    // The official start needs more smoothing to carry its experts to the modes.
    let data = DistillData::from_states(states.clone()).unwrap();
    let start_of = |init: InitKind| {
        let options = AutoOptions { init, samples: 512, ..AutoOptions::new(3, 0) };
        match AutoPlan::inspect(&mut far_teacher(1.0), &data, &options).unwrap().vdd.noise {
            NoiseSchedule::Annealed { start, .. } => start,
            other => panic!("{other:?}"),
        }
    };
    let ratio = start_of(InitKind::Official) / start_of(InitKind::FromTeacher);
    assert!((ratio - START_NOISE_OFFICIAL / START_NOISE_FROM_TEACHER).abs() < 1e-3, "{ratio}");
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
struct ScoreOnly<S>(S);
impl<S: ScoreModel> ScoreModel for ScoreOnly<S> {
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
    // The gating learns from every score-sampled action, not from one per data state.
    let pairs = plan.gating_pairs.as_ref().map(|(s, a)| (s.nrows(), a.nrows()));
    assert_eq!(pairs, Some((2000, 2000)));
    assert!(plan.notes.iter().any(|n| n.contains("sample_actions")), "{}", plan.summary());
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

/// Two modes at ±3 along the first axis whose weights are `softmax([k u, −k u])` with
/// `u = s² − 1/3`: with `k` large the state decides the mode, with `k = 0` it does not matter.
/// (An even function of the state, which the shared linear motion cannot absorb.)
fn switching_teacher(k: f32) -> GmmTeacher {
    GmmTeacher::conditional(1, 2, move |s| {
        let u = s[0] * s[0] - 1.0 / 3.0;
        let w = [(k * u).exp(), (-k * u).exp()];
        Gmm::isotropic(&w, &[vec![3.0, 0.0], vec![-3.0, 0.0]], 0.5)
    })
}

#[test]
fn the_run_grows_with_the_state_dependence_and_the_anneal_keeps_its_length() {
    let data = DistillData::from_states(Mat::from_fn(64, 1, |i, _| i as f32 / 32.0 - 1.0)).unwrap();
    let options = AutoOptions { samples: 2048, ..AutoOptions::new(2, 0) };
    let plan = |k: f32| AutoPlan::inspect(&mut switching_teacher(k), &data, &options).unwrap();
    let (free, decided) = (plan(0.0), plan(20.0));
    assert!(free.state_dependence < 0.02, "{}", free.summary());
    assert!(decided.state_dependence > 0.5, "{}", decided.summary());
    assert_eq!(free.vdd.iterations, BASE_ITERATIONS);
    assert_eq!(decided.vdd.iterations, MAX_AUTO_ITERATIONS);
    // The noise is annealed over the same 420 iterations whatever the run's length.
    for p in [&free, &decided] {
        let until = p.vdd.noise_anneal_until.unwrap() * p.vdd.iterations as f32;
        assert!((until - ANNEAL_ITERATIONS as f32).abs() < 1.0, "{}", p.summary());
    }
    // A length the user gives is kept.
    let given = AutoOptions { iterations: Some(100), ..options.clone() };
    let p = AutoPlan::inspect(&mut switching_teacher(20.0), &data, &given).unwrap();
    assert_eq!((p.vdd.iterations, p.vdd.noise_anneal_until), (100, Some(0.7)));
    let none = AutoOptions { iterations: Some(0), ..options };
    assert!(AutoPlan::inspect(&mut switching_teacher(0.0), &data, &none).is_err());
}

#[test]
fn a_score_only_teachers_gating_pairs_sit_at_their_own_states() {
    // Modes that move with the state (mean 10 s) on more states than the plan inspects.
    let teacher = GmmTeacher::conditional(1, 1, |s| {
        Gmm::isotropic(&[1.0, 1.0], &[vec![10.0 * s[0] - 1.0], vec![10.0 * s[0] + 1.0]], 0.1)
    });
    let data = DistillData::from_states(Mat::from_fn(300, 1, |i, _| i as f32 / 300.0)).unwrap();
    let options = AutoOptions { samples: 1024, ..AutoOptions::new(2, 0) };
    let plan = AutoPlan::inspect(&mut ScoreOnly(teacher), &data, &options).unwrap();
    let (states, actions) = plan.gating_pairs.as_ref().unwrap();
    assert!(states.nrows() >= 1024 && states.nrows() == actions.nrows());
    for i in 0..states.nrows() {
        let off = actions[(i, 0)] - 10.0 * states[(i, 0)];
        assert!(
            (off.abs() - 1.0).abs() < 0.6,
            "pair {i}: state {} action {}",
            states[(i, 0)],
            actions[(i, 0)]
        );
    }
}

#[test]
fn a_score_only_teachers_gating_learns_weights_finer_than_its_states() {
    // Weights 0.6 / 0.4 on 4 dummy states: one action per state could only give multiples
    // of 1/4.
    let gmm = Gmm::isotropic(&[0.6, 0.4], &[vec![3.0, 0.0], vec![-3.0, 0.0]], 0.5).unwrap();
    let teacher = ScoreOnly(GmmTeacher::fixed(gmm, 1));
    let data = DistillData::from_states(Mat::zeros(4, 1)).unwrap();
    let options = AutoOptions { samples: 2048, iterations: Some(150), ..AutoOptions::new(2, 1) };
    let mut vdd = Vdd::auto(teacher, data, &options).unwrap();
    vdd.train(|_| {}).unwrap();
    let mut student = vdd.into_student();
    student.forward(Mat::<f32>::zeros(1, 1).as_ref()).unwrap();
    let out = student.output();
    let a = student.normalizers().1.unwrap().clone();
    let right = (0..2).find(|&z| out.mean(0, z)[0] * a.scale[0] + a.offset[0] > 0.0).unwrap();
    let w = out.log_gating_row(0)[right].exp();
    assert!((w - 0.6).abs() < 0.05, "weight of the 0.6 mode: {w}");
}
