//! Tests of the VDD trainer: distillation, checkpoints, the moving average, errors, the
//! gating step and noise schedules.

use super::*;
use crate::eval::{modes_covered, reverse_kl};
use crate::test_support::IsoGmm;
use faer::MatMut;
use vdd_core::NoiseSchedule;
use vdd_moe::{GatingKind, MoeConfig};

pub(super) fn small_run(iterations: usize) -> (VddConfig, IsoGmm, Moe, DistillData) {
    let teacher = IsoGmm::circle(4, 2.0, 0.5);
    let mut mc = MoeConfig::toy(1, 2, 4);
    mc.experts_network.hidden_dim = 16;
    mc.gating = GatingKind::Learned;
    mc.gating_network.hidden_dim = 16;
    let student = Moe::from_config(mc, 3).unwrap();
    let config = VddConfig {
        iterations,
        batch_size: 8,
        vi_samples: 16,
        gating_batch_size: 32,
        expert_optimizer: vdd_nn::AdamConfig { lr: 1e-2, ..Default::default() },
        ..VddConfig::toy()
    };
    let data = DistillData::from_states(Mat::zeros(8, 1)).unwrap();
    (config, teacher, student, data)
}

#[test]
fn distils_a_four_mode_mixture() {
    let (config, teacher, student, data) = small_run(300);
    let mut vdd = Vdd::new(config, teacher.clone(), student, data).unwrap();
    vdd.train(|_| {}).unwrap();
    let mut student = vdd.into_student();
    let modes = teacher.means.clone();
    assert_eq!(modes_covered(&mut student, &[0.0], &modes, 0.3, 0.05).unwrap(), 4);
    let mut rng = Seeds::new(9).stream("eval");
    let kl = reverse_kl(&mut student, &[0.0], |a| teacher.log_density(a, 0.0), 20_000, &mut rng)
        .unwrap();
    assert!(kl < 0.05, "reverse KL {kl}");
}

/// The mean expert standard deviation of `student` at state 0 (diagonal experts).
fn mean_expert_std(student: &mut Moe) -> f32 {
    student.forward(Mat::<f32>::zeros(1, 1).as_ref()).unwrap();
    let out = student.output();
    let z_n = out.num_experts;
    let sum: f32 = (0..z_n).map(|z| (out.scale(0, z)[0] + out.scale(0, z)[3]) / 2.0).sum();
    sum / z_n as f32
}

#[test]
fn noise_on_both_sides_recovers_the_mixture_not_its_blur() {
    // Modes of std 0.15, queried only at σ in [0.3, 0.6]: the paper's expert step settles on
    // the blurred modes (std 0.34 to 0.62), noise on both sides on the modes themselves.
    let teacher = IsoGmm::circle(4, 2.0, 0.15);
    let std_with = |score_at| {
        let (mut config, _, student, data) = small_run(300);
        config.noise = NoiseSchedule::Uniform { min: 0.3, max: 0.6 };
        config.score_at = score_at;
        let mut vdd = Vdd::new(config, teacher.clone(), student, data).unwrap();
        vdd.train(|_| {}).unwrap();
        let mut student = vdd.into_student();
        let covered = modes_covered(&mut student, &[0.0], &teacher.means, 0.3, 0.05).unwrap();
        (mean_expert_std(&mut student), covered)
    };
    let (blurred, covered) = std_with(ScoreAt::CleanSample);
    assert!(blurred > 0.3, "clean samples: std {blurred}, {covered} modes");
    let (sharp, covered) = std_with(ScoreAt::NoisedSample);
    assert!((sharp - 0.15).abs() < 0.03 && covered == 4, "noised: std {sharp}, {covered} modes");
}

#[test]
fn noise_on_both_sides_recovers_the_mixture_from_a_vp_teacher() {
    // The same modes behind a variance-preserving process (ᾱ = e^(−t)), queried only at
    // t in [0.2, 0.6]: the noised student is √ᾱ a + √(1 − ᾱ) η, and the experts find the
    // modes themselves.
    let teacher = crate::test_support::VpGmm(IsoGmm::circle(4, 2.0, 0.15));
    let (mut config, _, student, data) = small_run(300);
    config.noise = NoiseSchedule::Uniform { min: 0.2, max: 0.6 };
    config.score_at = ScoreAt::NoisedSample;
    let mut vdd = Vdd::new(config, teacher.clone(), student, data).unwrap();
    vdd.train(|_| {}).unwrap();
    let mut student = vdd.into_student();
    let covered = modes_covered(&mut student, &[0.0], &teacher.0.means, 0.3, 0.05).unwrap();
    let std = mean_expert_std(&mut student);
    assert!((std - 0.15).abs() < 0.03 && covered == 4, "std {std}, {covered} modes");
}

#[test]
fn resuming_from_a_checkpoint_reproduces_an_uninterrupted_run() {
    let dir = std::env::temp_dir().join(format!("vdd-resume-{}", std::process::id()));
    let (mut config, teacher, student, data) = small_run(12);
    config.student_ema = Some(0.9);
    let mut straight =
        Vdd::new(config.clone(), teacher.clone(), student.clone(), data.clone()).unwrap();
    straight.train(|_| {}).unwrap();

    let mut first = Vdd::new(config, teacher.clone(), student, data.clone()).unwrap();
    for _ in 0..5 {
        first.step().unwrap();
    }
    let store = vdd_nn::checkpoint::CheckpointDir::open(&dir).unwrap();
    first.save_checkpoint(&store).unwrap();
    drop((first, store));
    let mut resumed = Vdd::resume(&dir, teacher, data).unwrap();
    assert_eq!(resumed.iteration(), 5);
    resumed.train(|_| {}).unwrap();
    assert_eq!(params(straight.student()), params(resumed.student()));
    // The moving average is part of the checkpoint too.
    assert_eq!(params(&straight.into_student()), params(&resumed.into_student()));
    std::fs::remove_dir_all(&dir).ok();
}

pub(super) fn params(student: &Moe) -> Vec<(String, Vec<f32>)> {
    let mut out = Vec::new();
    student.visit_params("", &mut |n, p| out.push((n.to_owned(), p.value.clone())));
    out
}

#[test]
fn the_returned_student_is_the_moving_average_of_the_iterates() {
    let (mut config, teacher, student, data) = small_run(6);
    let decay = 0.7;
    config.student_ema = Some(decay);
    let mut average = params(&student);
    let mut vdd = Vdd::new(config, teacher, student, data).unwrap();
    let mut trainable = Vec::new();
    vdd.student().visit_params("", &mut |_, p| trainable.push(p.trainable));
    for _ in 0..6 {
        vdd.step().unwrap();
        for ((avg, (_, now)), &t) in average.iter_mut().zip(params(vdd.student())).zip(&trainable) {
            for (a, v) in avg.1.iter_mut().zip(now) {
                *a = if t { *a + (1.0 - decay) * (v - *a) } else { v };
            }
        }
    }
    let last = params(vdd.student());
    let averaged = params(&vdd.into_student());
    assert_ne!(averaged, last);
    for ((name, got), (_, want)) in averaged.iter().zip(&average) {
        for (g, w) in got.iter().zip(want) {
            assert!((g - w).abs() < 1e-6, "{name}: {g} vs {w}");
        }
    }
}

#[test]
fn an_ema_decay_outside_zero_to_one_is_rejected() {
    let (mut config, teacher, student, data) = small_run(2);
    config.student_ema = Some(1.0);
    assert!(Vdd::new(config, teacher, student, data).is_err());
}

/// Scores that turn non-finite after the given number of expert steps (the convergence
/// probe's queries, of `PROBE_ACTIONS` rows, are not counted).
struct NanAfter(IsoGmm, usize);
impl ScoreModel for NanAfter {
    fn action_dim(&self) -> usize {
        2
    }
    fn state_dim(&self) -> usize {
        1
    }
    fn score(
        &mut self,
        a: MatRef<'_, f32>,
        s: MatRef<'_, f32>,
        l: &[f32],
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        self.0.score(a, s, l, out.as_mut())?;
        if a.nrows() == super::PROBE_ACTIONS {
            return Ok(());
        }
        if self.1 == 0 {
            out[(0, 0)] = f32::NAN;
        } else {
            self.1 -= 1;
        }
        Ok(())
    }
    fn sample_actions(
        &mut self,
        s: MatRef<'_, f32>,
        rng: &mut dyn rand::RngCore,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        self.0.sample_actions(s, rng, out)
    }
}

#[test]
fn a_non_finite_score_stops_training_with_the_iteration() {
    let (config, teacher, student, data) = small_run(10);
    let before = student.clone();
    let mut vdd = Vdd::new(config, NanAfter(teacher, 3), student, data).unwrap();
    let err = vdd.train(|_| {}).unwrap_err();
    match err {
        VddError::NonFinite { iteration, quantity } => {
            assert_eq!(iteration, 3);
            assert_eq!(quantity, "teacher score");
        }
        other => panic!("unexpected error {other}"),
    }
    assert_eq!(vdd.iteration(), 3);
    let mut changed = false;
    let mut old = Vec::new();
    before.visit_params("", &mut |_, p| old.push(p.value.clone()));
    let mut k = 0;
    vdd.student().visit_params("", &mut |_, p| {
        changed |= p.value != old[k];
        k += 1;
    });
    assert!(changed, "three iterations should have trained");
    assert!(vdd.student().clone().act(&[0.0]).unwrap().iter().all(|x| x.is_finite()));
}

/// Gating weights of the student at state 0.
fn gating_at_zero(student: &mut Moe) -> Vec<f32> {
    student.forward(Mat::<f32>::zeros(1, 1).as_ref()).unwrap();
    student.output().log_gating_row(0).iter().map(|l| l.exp()).collect()
}

/// With a dataset, the gating step learns the responsibilities of the dataset's actions:
/// a teacher with equal modes but data that visits one mode 3x as often gives a gating
/// that follows the data, not the teacher.
#[test]
fn the_gating_follows_the_responsibilities_of_dataset_actions() {
    let teacher = IsoGmm { means: vec![vec![2.0, 0.0], vec![-2.0, 0.0]], std: 0.3, state_dim: 1 };
    let mut mc = MoeConfig::toy(1, 2, 2);
    mc.experts_network.hidden_dim = 16;
    mc.gating = GatingKind::Learned;
    mc.gating_network.hidden_dim = 16;
    let student = Moe::from_config(mc, 1).unwrap();
    let n = 400;
    let actions = Mat::from_fn(n, 2, |i, j| match (i % 4, j) {
        (3, 0) => -2.0,
        (_, 0) => 2.0,
        _ => 0.0,
    });
    let data = DistillData::new(Mat::zeros(n, 1), Some(actions)).unwrap();
    let config = VddConfig {
        iterations: 300,
        batch_size: 4,
        vi_samples: 16,
        gating_batch_size: 64,
        expert_optimizer: vdd_nn::AdamConfig { lr: 1e-2, ..Default::default() },
        gating_optimizer: vdd_nn::AdamConfig { lr: 1e-2, ..Default::default() },
        ..VddConfig::toy()
    };
    let mut vdd = Vdd::new(config, teacher, student, data).unwrap();
    vdd.train(|_| {}).unwrap();
    let mut student = vdd.into_student();
    let w = gating_at_zero(&mut student);
    let out = student.output();
    // The expert at +2 carries 3/4 of the weight.
    let right = if out.mean(0, 0)[0] > out.mean(0, 1)[0] { 0 } else { 1 };
    assert!((out.mean(0, right)[0] - 2.0).abs() < 0.2, "means {:?}", out.means);
    assert!((w[right] - 0.75).abs() < 0.05, "gating {w:?}");
}

/// `freeze_gating_after: Some(n)` stops gating updates from iteration n on.
#[test]
fn a_frozen_gating_stops_changing() {
    let (mut config, teacher, student, data) = small_run(8);
    config.freeze_gating_after = Some(4);
    config.gating_optimizer.lr = 1e-2;
    let mut vdd = Vdd::new(config, teacher, student, data).unwrap();
    let mut gating = Vec::new();
    let mut losses = Vec::new();
    for _ in 0..8 {
        losses.push(vdd.step().unwrap().gating_loss);
        let mut student = vdd.student().clone();
        gating.push(gating_at_zero(&mut student));
    }
    assert!(losses[..4].iter().all(Option::is_some));
    assert!(losses[4..].iter().all(Option::is_none));
    assert_ne!(gating[2], gating[3], "the gating trains before the freeze");
    assert!(gating[3..].windows(2).all(|w| w[0] == w[1]), "{gating:?}");
}

/// The expert step queries the teacher at the configured noise levels: fixed, uniform in a
/// range, or annealed from start to end over the run.
#[test]
fn noise_levels_follow_the_configured_schedule() {
    let levels = |noise: NoiseSchedule| {
        let (mut config, teacher, student, data) = small_run(10);
        config.noise = noise;
        let mut vdd = Vdd::new(config, teacher, student, data).unwrap();
        let mut out = Vec::new();
        vdd.train(|m| out.push(m.expert.noise_level)).unwrap();
        out
    };
    let fixed = levels(NoiseSchedule::Fixed { level: 0.3 });
    assert!(fixed.iter().all(|&l| (l - 0.3).abs() < 1e-6), "{fixed:?}");
    let uniform = levels(NoiseSchedule::Uniform { min: 0.2, max: 0.6 });
    // Means over 8·4·16 draws: close to 0.4, never at the ends.
    assert!(uniform.iter().all(|&l| (l - 0.4).abs() < 0.03), "{uniform:?}");
    let annealed = levels(NoiseSchedule::Annealed { start: 1.0, end: 0.1 });
    assert!((annealed[0] - 1.0).abs() < 1e-6, "{annealed:?}");
    assert!(annealed.windows(2).all(|w| w[1] < w[0]), "{annealed:?}");
    assert!(annealed[9] < 0.2 && annealed[9] > 0.1, "{annealed:?}");
}

#[test]
fn mismatched_dimensions_are_rejected() {
    let (config, teacher, _, data) = small_run(1);
    let student = Moe::from_config(MoeConfig::toy(1, 3, 2), 0).unwrap();
    assert!(Vdd::new(config, teacher, student, data).is_err());
}

use vdd_core::Policy;

/// One seed per run: `Vdd::from_config` initialises the student from the run's seed, the same
/// student `Moe::from_config(config, seed)` gives, and trains it to the same numbers.
#[test]
fn the_run_seed_initialises_the_student() {
    let (mut config, teacher, _, data) = small_run(3);
    config.seed = 11;
    let mut mc = MoeConfig::toy(1, 2, 4);
    mc.experts_network.hidden_dim = 16;
    let built = Moe::from_config(mc.clone(), 11).unwrap();
    let mut a =
        Vdd::from_config(config.clone(), teacher.clone(), mc.clone(), data.clone()).unwrap();
    assert_eq!(params(a.student()), params(&built));
    let mut b = Vdd::new(config, teacher, built, data).unwrap();
    a.train(|_| {}).unwrap();
    b.train(|_| {}).unwrap();
    assert_eq!(params(a.student()), params(b.student()));
    assert_ne!(params(a.student()), params(&Moe::from_config(mc, 12).unwrap()));
}

/// Learning-rate schedules are relative to the run: the toy's linear decay spans whatever
/// number of iterations the run has (it never trains at learning rate 0 before the end), and
/// a frozen gating's decay ends at the freeze.
#[test]
fn learning_rates_decay_over_the_run_whatever_its_length() {
    for iterations in [6, 20] {
        let (mut config, teacher, student, data) = small_run(iterations);
        config.expert_optimizer.lr = 5e-4;
        config.gating_optimizer.lr = 5e-4;
        config.freeze_gating_after = Some(iterations / 2);
        let mut vdd = Vdd::new(config, teacher, student, data).unwrap();
        let mut lrs = Vec::new();
        vdd.train(|m| lrs.push((m.expert_lr, m.gating_lr))).unwrap();
        for (i, (e, g)) in lrs.into_iter().enumerate() {
            let want = 5e-4 * (1.0 - i as f32 / iterations as f32);
            assert!((e - want).abs() < 1e-9, "{iterations}: expert lr {e} at {i}, want {want}");
            assert!(e > 0.0);
            if i < iterations / 2 {
                let want = 5e-4 * (1.0 - i as f32 / (iterations / 2) as f32);
                assert!((g - want).abs() < 1e-9, "{iterations}: gating lr {g} at {i}");
            } else {
                assert_eq!(g, 0.0, "frozen");
            }
        }
    }
}

/// VDD is a `vdd_core::Trainer`: code written against the trait drives it, and `finish` returns
/// the student `into_student` would (the moving average when configured).
#[test]
fn vdd_runs_through_the_trainer_trait() {
    fn drive<T: Trainer>(mut t: T) -> (usize, T::Output) {
        let mut reports = 0;
        t.run(|_| reports += 1).unwrap();
        assert!(t.done() && t.progress() == 1.0);
        (reports, t.finish().unwrap())
    }
    let (mut config, teacher, student, data) = small_run(4);
    config.student_ema = Some(0.5);
    let direct = Vdd::new(config.clone(), teacher.clone(), student.clone(), data.clone()).unwrap();
    let (reports, finished) = drive(direct);
    assert_eq!(reports, 4);
    let mut vdd = Vdd::new(config, teacher, student, data).unwrap();
    vdd.train(|_| {}).unwrap();
    assert_eq!(params(&finished), params(&vdd.into_student()));
}

/// A user's teacher fails in its own way (here: a file it reads is missing). Its error comes
/// back through `Vdd::step` with the source chain intact: the user's error, then its cause.
#[test]
fn a_teachers_own_error_keeps_its_source_chain() {
    #[derive(Debug, thiserror::Error)]
    #[error("cannot read the teacher's lookup table")]
    struct TableError(#[source] std::io::Error);

    struct FileTeacher;
    impl ScoreModel for FileTeacher {
        fn action_dim(&self) -> usize {
            2
        }
        fn state_dim(&self) -> usize {
            1
        }
        fn score(
            &mut self,
            _: MatRef<'_, f32>,
            _: MatRef<'_, f32>,
            _: &[f32],
            _: MatMut<'_, f32>,
        ) -> Result<(), CoreError> {
            let io = std::io::Error::new(std::io::ErrorKind::NotFound, "table.bin");
            Err(CoreError::implementor(TableError(io)))
        }
    }

    let (config, _, _, data) = small_run(3);
    let student = Moe::from_config(MoeConfig::toy(1, 2, 2), 0).unwrap();
    let mut vdd = Vdd::new(config, FileTeacher, student, data).unwrap();
    let err = vdd.step().unwrap_err();
    assert!(matches!(err, VddError::Core(CoreError::Implementor(_))), "{err:?}");
    assert_eq!(vdd.iteration(), 0);
    let mut chain = Vec::new();
    let mut e: Option<&(dyn std::error::Error + 'static)> = Some(&err);
    while let Some(x) = e {
        chain.push(x);
        e = x.source();
    }
    let table = chain.iter().find_map(|x| x.downcast_ref::<TableError>());
    assert!(table.is_some(), "the user's error is in the chain: {chain:?}");
    let io = chain.iter().find_map(|x| x.downcast_ref::<std::io::Error>()).expect("its cause too");
    assert_eq!(io.kind(), std::io::ErrorKind::NotFound);
}

/// A learned gating without dataset actions needs a teacher that samples; the teacher's
/// refusal is the error's source.
#[test]
fn a_learned_gating_without_actions_keeps_the_teachers_refusal() {
    let (config, _, student, data) = small_run(1);
    let teacher = IsoGmmNoSampling(IsoGmm::circle(4, 2.0, 0.5));
    let err = Vdd::new(config, teacher, student, data).err().expect("no gating actions");
    match &err {
        VddError::NoGatingActions { source: CoreError::Unsupported(_) } => {}
        other => panic!("unexpected {other:?}"),
    }
    assert!(std::error::Error::source(&err).is_some());
}

struct IsoGmmNoSampling(IsoGmm);
impl ScoreModel for IsoGmmNoSampling {
    fn action_dim(&self) -> usize {
        self.0.action_dim()
    }
    fn state_dim(&self) -> usize {
        self.0.state_dim()
    }
    fn score(
        &mut self,
        a: MatRef<'_, f32>,
        s: MatRef<'_, f32>,
        l: &[f32],
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        self.0.score(a, s, l, out)
    }
}

#[test]
fn sizes_beyond_the_limits_are_refused_before_allocating() {
    for (what, edit) in [
        ("batch_size", &(|c: &mut VddConfig| c.batch_size = 1 << 31) as &dyn Fn(&mut VddConfig)),
        ("gating_batch_size", &|c: &mut VddConfig| c.gating_batch_size = 1 << 31),
        ("vi_samples", &|c: &mut VddConfig| c.vi_samples = usize::MAX),
        ("expert_steps_per_iter", &|c: &mut VddConfig| c.expert_steps_per_iter = 1 << 40),
        ("batch_size · vi_samples", &|c: &mut VddConfig| {
            c.batch_size = 1 << 16;
            c.vi_samples = 1 << 12;
        }),
        ("student_ema", &|c: &mut VddConfig| c.student_ema = Some(f32::INFINITY)),
    ] {
        let (mut config, teacher, student, data) = small_run(1);
        edit(&mut config);
        let e = Vdd::new(config, teacher, student, data).map(drop).unwrap_err();
        assert!(e.to_string().contains(what), "{what}: {e}");
    }
    // Within each limit, but too many samples over all experts.
    let (mut config, teacher, _, data) = small_run(1);
    (config.batch_size, config.vi_samples) = (1 << 10, 1 << 10);
    let student = Moe::from_config(MoeConfig::toy(1, 2, 8), 0).unwrap();
    let e = Vdd::new(config, teacher, student, data).map(drop).unwrap_err();
    assert!(e.to_string().contains("num_experts"), "{e}");
}

#[test]
fn a_schedule_in_another_unit_or_outside_the_teachers_range_is_refused() {
    use crate::test_support::VpGmm;
    use vdd_core::NoiseConvention;
    /// [`IsoGmm`] that says it was trained on σ ∈ [0.002, 80].
    struct Ranged(IsoGmm);
    impl ScoreModel for Ranged {
        fn action_dim(&self) -> usize {
            self.0.action_dim()
        }
        fn state_dim(&self) -> usize {
            self.0.state_dim()
        }
        fn score(
            &mut self,
            a: MatRef<'_, f32>,
            s: MatRef<'_, f32>,
            l: &[f32],
            out: MatMut<'_, f32>,
        ) -> Result<(), CoreError> {
            self.0.score(a, s, l, out)
        }
        fn noise_range(&self) -> Option<(f32, f32)> {
            Some((0.002, 80.0))
        }
    }
    let (config, teacher, student, data) = small_run(1);
    let vp = VpGmm(teacher.clone());
    let sigma = VddConfig { noise_unit: Some(NoiseConvention::Sigma), ..config.clone() };
    let e = Vdd::new(sigma.clone(), vp, student.clone(), data.clone()).err().unwrap();
    assert!(e.to_string().contains("noise_unit is sigma"), "{e}");
    assert!(Vdd::new(sigma.clone(), teacher.clone(), student.clone(), data.clone()).is_ok());
    let wide = VddConfig { noise: NoiseSchedule::Uniform { min: 0.1, max: 100.0 }, ..sigma };
    let e = Vdd::new(wide.clone(), Ranged(teacher.clone()), student.clone(), data.clone());
    assert!(e.err().unwrap().to_string().contains("outside the teacher's range 0.002..=80"));
    // Without a range (the exact mixture here), any level goes.
    assert!(Vdd::new(wide, teacher, student, data).is_ok());
}

#[test]
fn training_a_subset_of_experts_per_state_still_distils_the_mixture() {
    // Two of the four experts per state and step: each expert sees half the states, and the
    // four modes are still found.
    let (mut config, teacher, student, data) = small_run(600);
    config.experts_per_state = Some(2);
    let mut vdd = Vdd::new(config, teacher.clone(), student, data).unwrap();
    vdd.train(|_| {}).unwrap();
    let mut student = vdd.into_student();
    assert_eq!(modes_covered(&mut student, &[0.0], &teacher.means, 0.3, 0.05).unwrap(), 4);
    let mut rng = Seeds::new(9).stream("eval");
    let kl = reverse_kl(&mut student, &[0.0], |a| teacher.log_density(a, 0.0), 20_000, &mut rng)
        .unwrap();
    assert!(kl < 0.05, "reverse KL {kl}");
}

#[test]
fn experts_per_state_of_all_experts_or_more_is_the_full_step() {
    let train = |k: Option<usize>| {
        let (mut config, teacher, student, data) = small_run(20);
        config.experts_per_state = k;
        let mut vdd = Vdd::new(config, teacher, student, data).unwrap();
        vdd.train(|_| {}).unwrap();
        params(vdd.student())
    };
    let full = train(None);
    assert!(full == train(Some(4)) && full == train(Some(9)));
    assert!(full != train(Some(3)));
    let (mut config, teacher, student, data) = small_run(20);
    config.experts_per_state = Some(0);
    let err = Vdd::new(config, teacher, student, data).err().expect("k = 0 is refused");
    assert!(err.to_string().contains("experts_per_state"), "{err}");
}

#[test]
fn each_state_trains_distinct_experts_and_each_expert_as_many_states() {
    // Eight states, four experts, three per state: 24 slots, six per expert.
    let (mut config, teacher, student, data) = small_run(1);
    config.experts_per_state = Some(3);
    let mut vdd = Vdd::new(config, teacher, student, data).unwrap();
    let mut draws = Vec::new();
    for stream in 0..5 {
        vdd.draw_subset(stream);
        assert_eq!(vdd.subset.len(), 24);
        for state in vdd.subset.chunks(3) {
            assert!(state[0] != state[1] && state[0] != state[2] && state[1] != state[2]);
        }
        for z in 0..4 {
            assert_eq!(vdd.subset.iter().filter(|&&x| x == z).count(), 6, "expert {z}");
        }
        draws.push(vdd.subset.clone());
    }
    // Each step draws its own permutation, from its own stream.
    assert!(draws.windows(2).any(|w| w[0] != w[1]));
    vdd.draw_subset(3);
    assert_eq!(vdd.subset, draws[3]);
}
