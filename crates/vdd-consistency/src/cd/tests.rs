//! Tests of Consistency Distillation: the boundary condition, gradients, distillation of an exact teacher, sampling.

use super::*;
use crate::teacher::ScoreTeacher;
use crate::test_support::{
    distils_the_modes, four_mode_teacher, gradient_error, tiny_net, uniform_actions,
};
use vdd_core::Trainer as _;
use vdd_core::{Affine, Policy, Seeds};
use vdd_diffusion::{Beso, BesoConfig, NetConfig};
use vdd_nn::Parameters;

fn tiny_config() -> CdConfig {
    let mut c = CdConfig { net: tiny_net(), num_scales: 6, sigma_max: 10.0, ..Default::default() };
    c.train.batch_size = 5;
    c
}

#[test]
fn consistency_function_is_the_identity_at_sigma_min() {
    let (s, a) = uniform_actions(16, 0);
    let mut t = CdTrainer::new(tiny_config(), four_mode_teacher(), s.as_ref(), a.as_ref()).unwrap();
    for _ in 0..3 {
        t.step().unwrap();
    }
    let mut model = t.model().unwrap();
    let x = Mat::from_fn(7, 2, |i, j| 3.0 * (i as f32 - 3.0) + 0.37 * j as f32);
    let states = Mat::from_fn(7, 1, |i, _| i as f32);
    let mut out = Mat::zeros(7, 2);
    model.consistency_fn(x.as_ref(), &[0.002; 7], states.as_ref(), out.as_mut()).unwrap();
    assert_eq!(out, x, "f(x, σ_min) must be exactly x");
    // Away from the boundary it is not the identity.
    model.consistency_fn(x.as_ref(), &[1.0; 7], states.as_ref(), out.as_mut()).unwrap();
    assert_ne!(out, x);
    // Bad inputs are errors.
    assert!(model.consistency_fn(x.as_ref(), &[0.0; 7], states.as_ref(), out.as_mut()).is_err());
    assert!(model.consistency_fn(x.as_ref(), &[1.0; 6], states.as_ref(), out.as_mut()).is_err());
}

/// The analytic gradient of the CD loss w.r.t. every parameter matches central finite
/// differences of the loss (teacher step and target fixed, as the method prescribes).
#[test]
fn cd_loss_gradient_matches_finite_differences() {
    let (s, a) = uniform_actions(16, 1);
    let mut t = CdTrainer::new(tiny_config(), four_mode_teacher(), s.as_ref(), a.as_ref()).unwrap();
    // Move the online network away from the target so the loss is not ~0.
    for _ in 0..5 {
        t.step().unwrap();
    }
    t.objective.draw(&mut t.core).unwrap();
    let CdTrainer { core, objective, .. } = &mut t;
    let (loss0, worst, checked) =
        gradient_error(core, |core, backward| objective.loss(core, backward).total);
    assert!(loss0 > 1e-4, "loss {loss0}");
    assert!(checked > 50);
    assert!(worst < 2e-2, "worst relative gradient error {worst}");
}

/// A CD student of the exact denoiser of a 4-mode mixture puts its one-step samples on the
/// modes, all four of them (and an untrained one does not).
#[test]
fn cd_student_of_an_exact_gmm_teacher_samples_near_the_modes() {
    distils_the_modes(|config, states, actions| {
        let mut t = CdTrainer::new(config, four_mode_teacher(), states, actions).unwrap();
        let untrained = t.model().unwrap();
        (Box::new(untrained), Box::new(t.train(&mut |_| {}).unwrap()))
    });
}

#[test]
fn training_is_deterministic_for_a_seed() {
    let (s, a) = uniform_actions(32, 2);
    let run = |seed: u64| {
        let mut c = tiny_config().with_seed(seed);
        c.train.steps = 5;
        let mut t = CdTrainer::new(c, four_mode_teacher(), s.as_ref(), a.as_ref()).unwrap();
        let mut reports = Vec::new();
        let mut m = t.train(&mut |p| reports.push(p.loss)).unwrap();
        (reports, m.act(&[0.0]).unwrap())
    };
    assert_eq!(run(7), run(7));
    assert_ne!(run(7).1, run(8).1);
}

#[test]
fn bad_configs_and_data_are_errors() {
    let (s, a) = uniform_actions(8, 0);
    let teacher = four_mode_teacher;
    assert!(
        CdTrainer::new(
            CdConfig { num_scales: 1, ..tiny_config() },
            teacher(),
            s.as_ref(),
            a.as_ref()
        )
        .is_err()
    );
    // The analytic teacher has no network to start from.
    let c = CdConfig { init_from_teacher: true, ..tiny_config() };
    assert!(CdTrainer::new(c, teacher(), s.as_ref(), a.as_ref()).is_err());
    // Wrong data shapes and values.
    let bad = Mat::<f32>::zeros(8, 3);
    assert!(CdTrainer::new(tiny_config(), teacher(), s.as_ref(), bad.as_ref()).is_err());
    let mut nan = a.clone();
    nan[(0, 0)] = f32::NAN;
    assert!(CdTrainer::new(tiny_config(), teacher(), s.as_ref(), nan.as_ref()).is_err());
    // A DDPM teacher cannot be distilled.
    let ddpm = vdd_diffusion::Ddpm::new(
        &vdd_diffusion::DdpmConfig::default(),
        Affine::identity(1),
        Affine::identity(2),
        0,
    )
    .unwrap();
    let ddpm = vdd_diffusion::DiffusionTeacher::from(ddpm);
    assert!(CdTrainer::new(tiny_config(), ddpm, s.as_ref(), a.as_ref()).is_err());
    // The policy checks its inputs.
    let mut m =
        CdTrainer::new(tiny_config(), teacher(), s.as_ref(), a.as_ref()).unwrap().model().unwrap();
    assert!(m.act(&[0.0, 1.0]).is_err());
    assert!(m.act(&[f32::NAN]).is_err());
    assert!(m.set_sampling_steps(0).is_err());
    assert!(m.set_sampling_levels(&[1.0, 2.0]).is_err());
    assert!(m.set_sampling_levels(&[1.0, 0.001]).is_err());
}

/// Started from a BESO teacher, `f(x, σ)` differs from the teacher's `D(x; σ)` only
/// through the boundary-shifted `c_skip` and `c_out`; multistep sampling runs the
/// configured levels.
#[test]
fn student_starts_from_a_beso_teacher_and_multistep_sampling_runs() {
    let net = NetConfig { hidden_dim: 8, num_blocks: 1, ..Default::default() };
    let bc = BesoConfig { net, ..Default::default() };
    let mut beso = Beso::new(&bc, Affine::identity(1), Affine::identity(2), 0).unwrap();
    let (s, a) = uniform_actions(16, 3);
    let mut c = CdConfig::for_teacher(&beso);
    c.train.batch_size = 4;
    let t = CdTrainer::new(c.clone(), &mut beso, s.as_ref(), a.as_ref()).unwrap();
    let mut model = t.model().unwrap();
    let x = Mat::from_fn(3, 2, |i, j| i as f32 - j as f32);
    let st = Mat::<f32>::zeros(3, 1);
    let (mut f, mut dn) = (Mat::zeros(3, 2), Mat::zeros(3, 2));
    model.consistency_fn(x.as_ref(), &[5.0; 3], st.as_ref(), f.as_mut()).unwrap();
    drop(t);
    beso.denoise(x.as_ref(), &[5.0; 3], st.as_ref(), dn.as_mut()).unwrap();
    for i in 0..3 {
        for j in 0..2 {
            assert!((f[(i, j)] - dn[(i, j)]).abs() < 1e-2, "{f:?} vs {dn:?}");
        }
    }
    // Two steps: f at σ_max, fresh noise, f at the middle level (differs from one step).
    let obs = Mat::<f32>::zeros(64, 1);
    let (mut one, mut two) = (Mat::zeros(64, 2), Mat::zeros(64, 2));
    model.act_batch(obs.as_ref(), one.as_mut()).unwrap();
    model.set_sampling_steps(2).unwrap();
    assert_eq!(model.sampling_levels().len(), 3);
    assert_eq!(model.sampling_levels()[0], 80.0);
    model.seed(0);
    model.act_batch(obs.as_ref(), two.as_mut()).unwrap();
    assert!(two.col_as_slice(0).iter().all(|v| v.is_finite()));
    assert_ne!(one, two);
    // A different architecture cannot start from the teacher.
    let mut other = c;
    other.net.hidden_dim = 16;
    assert!(CdTrainer::new(other, &mut beso, s.as_ref(), a.as_ref()).is_err());
}

/// Multistep sampling is Song et al.'s Algorithm 1: with `F ≡ 0` (all weights zero) each
/// step is `a = c_skip(l_i) x`, so the output can be replayed from the same noise draws.
#[test]
fn multistep_sampling_follows_algorithm_one() {
    let gmm = crate::test_support::four_mode_gmm();
    let (s, a) = uniform_actions(8, 4);
    let mut model =
        CdTrainer::new(tiny_config(), ScoreTeacher::identity(gmm).unwrap(), s.as_ref(), a.as_ref())
            .unwrap()
            .model()
            .unwrap();
    // Zero every parameter: the residual MLP then outputs exactly 0.
    model.net.visit_params_mut("", &mut |_, p| p.value.fill(0.0));
    let pre = model.preconditioning();
    model.set_sampling_levels(&[10.0, 1.0]).unwrap();
    let st = Mat::<f32>::zeros(1, 1);
    let mut rng = Seeds::new(9).stream("s");
    let mut out = Mat::zeros(1, 2);
    model.sample(st.as_ref(), &mut rng, out.as_mut()).unwrap();
    // Replay the draws: x0 = 10 z0, a = c_skip(10) x0, x1 = a + sqrt(1 − σ_min²) z1,
    // a = c_skip(1) x1.
    let mut rng = Seeds::new(9).stream("s");
    let mut z = [0.0f32; 4];
    vdd_core::fill_standard_normal(&mut rng, &mut z[..2]);
    vdd_core::fill_standard_normal(&mut rng, &mut z[2..]);
    let std1 = (1.0f32 - pre.sigma_min * pre.sigma_min).sqrt();
    for j in 0..2 {
        let a0 = pre.c_skip(10.0) * 10.0 * z[j];
        let want = pre.c_skip(1.0) * (a0 + std1 * z[2 + j]);
        assert!((out[(0, j)] - want).abs() < 1e-5, "{} vs {want}", out[(0, j)]);
    }
}
