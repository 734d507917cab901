//! Tests of explicit spaces: the trainer queries the teacher in the teacher's space, whatever
//! the student's normalisers, and computes exactly what it did when the spaces coincide.

use super::*;
use crate::test_support::IsoGmm;
use vdd_core::{Affine, Policy};
use vdd_moe::{GatingKind, MoeConfig};

/// Trains to the end: every iteration's metrics and the student's parameters, to compare runs
/// bit for bit.
fn trained<S: ScoreModel>(mut vdd: Vdd<S>) -> (Vec<IterationMetrics>, Vec<Vec<f32>>) {
    let mut metrics = Vec::new();
    vdd.train(|m| metrics.push(*m)).unwrap();
    let mut p = Vec::new();
    vdd.student().visit_params("", &mut |_, t| p.push(t.value.clone()));
    (metrics, p)
}

/// `N((10, 10), 0.5² I)` in raw units.
fn offset_teacher() -> IsoGmm {
    IsoGmm { means: vec![vec![10.0, 10.0]], std: 0.5, state_dim: 1 }
}

fn student(gating: GatingKind, actions: Option<Affine>) -> Moe {
    let mut mc = MoeConfig::toy(1, 2, 2);
    mc.experts_network.hidden_dim = 16;
    mc.gating = gating;
    mc.gating_network.hidden_dim = 16;
    let mut m = Moe::from_config(mc, 5).unwrap();
    m.set_normalizers(None, actions).unwrap();
    m
}

fn config() -> VddConfig {
    VddConfig {
        iterations: 300,
        batch_size: 8,
        vi_samples: 16,
        gating_batch_size: 32,
        expert_optimizer: vdd_nn::AdamConfig { lr: 1e-2, ..Default::default() },
        ..VddConfig::toy()
    }
}

/// The experts' means and standard deviations at state 0, in the student's space.
fn experts(student: &mut Moe) -> Vec<(Vec<f32>, Vec<f32>)> {
    student.forward(Mat::<f32>::zeros(1, 1).as_ref()).unwrap();
    let out = student.output();
    (0..2)
        .map(|z| {
            let l = out.scale(0, z);
            (out.mean(0, z).to_vec(), vec![l[0], l[3]])
        })
        .collect()
}

/// The trap: a teacher centred at (10, 10) in raw units and a student whose action
/// normaliser subtracts 10. The student acts near (10, 10), not (20, 20).
#[test]
fn an_offset_teacher_gives_actions_at_its_centre() {
    let norm = Affine::new(vec![10.0, 10.0], vec![1.0, 1.0]).unwrap();
    for gating in [GatingKind::Uniform, GatingKind::Learned] {
        let data = DistillData::from_states(Mat::zeros(8, 1)).unwrap();
        let s = student(gating, Some(norm.clone()));
        let mut vdd = Vdd::new(config(), offset_teacher(), s, data).unwrap();
        vdd.train(|_| {}).unwrap();
        let mut s = vdd.into_student();
        for (mean, _) in experts(&mut s) {
            assert!(mean.iter().all(|m| m.abs() < 0.3), "{gating:?}: normalised mean {mean:?}");
        }
        let a = s.act(&[0.0]).unwrap();
        assert!(a.iter().all(|x| (x - 10.0).abs() < 0.3), "{gating:?}: action {a:?}");
    }
}

/// The chain rule of a scaled normaliser: with `x = (a − o)/2` the teacher's `N(10, 0.5²)`
/// is `N((10 − o)/2, 0.25²)` in the student's space.
#[test]
fn a_scaled_student_space_learns_the_scaled_teacher() {
    let norm = Affine::new(vec![4.0, -2.0], vec![2.0, 2.0]).unwrap();
    let data = DistillData::from_states(Mat::zeros(8, 1)).unwrap();
    let s = student(GatingKind::Uniform, Some(norm));
    let mut vdd = Vdd::new(config(), offset_teacher(), s, data).unwrap();
    vdd.train(|_| {}).unwrap();
    let mut s = vdd.into_student();
    for (mean, std) in experts(&mut s) {
        assert!((mean[0] - 3.0).abs() < 0.1 && (mean[1] - 6.0).abs() < 0.1, "mean {mean:?}");
        assert!(std.iter().all(|s| (s - 0.25).abs() < 0.05), "std {std:?}");
    }
    let a = s.act(&[0.0]).unwrap();
    assert!(a.iter().all(|x| (x - 10.0).abs() < 0.3), "action {a:?}");
}

/// A teacher working in its own normalised space (as the learned diffusion teachers do):
/// `N(0, 0.5²)` there, with the map `(a − 10)/2`, is `N(10, 1)` in raw units.
#[test]
fn a_teacher_in_its_own_normalised_space_is_mapped() {
    let teacher = IsoGmm { means: vec![vec![0.0, 0.0]], std: 0.5, state_dim: 1 };
    let space = TeacherSpace {
        states: None,
        actions: Some(Affine::new(vec![10.0, 10.0], vec![2.0, 2.0]).unwrap()),
    };
    let norm = Affine::new(vec![5.0, 5.0], vec![1.0, 1.0]).unwrap();
    let data = DistillData::from_states(Mat::zeros(8, 1)).unwrap().with_teacher_space(space);
    let mut vdd =
        Vdd::new(config(), teacher, student(GatingKind::Uniform, Some(norm)), data).unwrap();
    vdd.train(|_| {}).unwrap();
    let mut s = vdd.into_student();
    for (mean, std) in experts(&mut s) {
        assert!(mean.iter().all(|m| (m - 5.0).abs() < 0.2), "mean {mean:?}");
        assert!(std.iter().all(|s| (s - 1.0).abs() < 0.15), "std {std:?}");
    }
}

/// When the student's and the teacher's spaces coincide, nothing is mapped: raw data with a
/// student and a teacher normalised alike gives, bit for bit, the run on pre-normalised data
/// with neither (how the recipes call the trainer).
#[test]
fn coinciding_spaces_change_no_number() {
    let states = Mat::from_fn(16, 1, |i, _| i as f32);
    let actions = Mat::from_fn(16, 2, |i, j| if (i + j) % 2 == 0 { 11.0 } else { 9.0 });
    let (sn, an) = (
        Affine::new(vec![7.0], vec![3.0]).unwrap(),
        Affine::new(vec![10.0, 10.0], vec![2.0, 0.5]).unwrap(),
    );
    let teacher =
        || IsoGmm { means: vec![vec![0.5, -0.5], vec![-0.5, 0.5]], std: 0.3, state_dim: 1 };
    let normalized = |m: &Mat<f32>, a: &Affine| {
        let mut m = m.clone();
        normalize_rows(&mut m, a);
        m
    };
    let mut c = config();
    c.iterations = 5;
    let run = |student: Moe, data: DistillData| {
        trained(Vdd::new(c.clone(), teacher(), student, data).unwrap())
    };
    let plain = run(
        student(GatingKind::Learned, None),
        DistillData::new(normalized(&states, &sn), Some(normalized(&actions, &an))).unwrap(),
    );
    let mut s = student(GatingKind::Learned, None);
    s.set_normalizers(Some(sn.clone()), Some(an.clone())).unwrap();
    let spaced = run(
        s,
        DistillData::new(states, Some(actions))
            .unwrap()
            .with_teacher_space(TeacherSpace::normalized(sn, an)),
    );
    assert_eq!(plain, spaced);
}

/// Perturbed states ([`VddConfig::state_noise`]) move by the same raw amount in the student's
/// and the teacher's spaces, in about the configured share of the batch, from their own stream.
#[test]
fn perturbed_states_agree_between_the_spaces() {
    let states = Mat::from_fn(64, 1, |i, _| i as f32);
    let data = DistillData::from_states(states).unwrap().with_teacher_space(
        TeacherSpace::normalized(Affine::new(vec![3.0], vec![4.0]).unwrap(), Affine::identity(2)),
    );
    let mut s = student(GatingKind::Uniform, None);
    s.set_normalizers(Some(Affine::new(vec![-1.0], vec![0.5]).unwrap()), None).unwrap();
    let noise = crate::StateNoise { share: 0.5, std: 0.3 };
    let config = VddConfig { iterations: 20, state_noise: Some(noise), ..config() };
    let mut vdd = Vdd::new(config.clone(), offset_teacher(), s.clone(), data.clone()).unwrap();
    let mut moved = 0;
    for _ in 0..20 {
        vdd.step().unwrap();
        for b in 0..vdd.batch.nrows() {
            let raw = vdd.batch[(b, 0)] * 0.5 - 1.0;
            assert!((vdd.teacher_batch[(b, 0)] - (raw - 3.0) / 4.0).abs() < 1e-5);
            // The data's raw states are whole numbers; perturbed ones are not.
            moved += usize::from((raw - raw.round()).abs() > 1e-3);
        }
    }
    let share = moved as f32 / (20 * 8) as f32;
    assert!((share - 0.5).abs() < 0.15, "share of perturbed states {share}");
    // Without the setting the batches are the data's, and the state stream is unchanged.
    let plain = VddConfig { state_noise: None, ..config };
    let mut a = Vdd::new(plain, offset_teacher(), s, data).unwrap();
    a.step().unwrap();
    for b in 0..a.batch.nrows() {
        let raw = a.batch[(b, 0)] * 0.5 - 1.0;
        assert!((raw - raw.round()).abs() < 1e-4);
    }
}

#[test]
fn a_state_noise_out_of_range_is_refused() {
    for (share, std) in [(-0.1, 0.1), (1.5, 0.1), (f32::NAN, 0.1), (0.5, 0.0), (0.5, f32::NAN)] {
        let c = VddConfig { state_noise: Some(crate::StateNoise { share, std }), ..config() };
        assert!(c.validate().unwrap_err().to_string().contains("state_noise"));
    }
}

/// A share of 0 turns the perturbation off: the same training as no `state_noise`, bit for bit.
#[test]
fn a_state_noise_share_of_zero_trains_as_none() {
    let data = DistillData::from_states(Mat::from_fn(64, 1, |i, _| i as f32)).unwrap();
    let s = student(GatingKind::Uniform, None);
    let off = crate::StateNoise { share: 0.0, std: 0.3 };
    let run = |state_noise| {
        let config = VddConfig { iterations: 5, state_noise, ..config() };
        trained(Vdd::new(config, offset_teacher(), s.clone(), data.clone()).unwrap())
    };
    assert_eq!(run(Some(off)), run(None));
    assert_ne!(run(Some(crate::StateNoise { share: 0.5, std: 0.3 })), run(None));
}
