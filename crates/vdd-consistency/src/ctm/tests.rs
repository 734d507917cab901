//! Tests of the Consistency Trajectory Model: jumps, gradients of both matchings, distillation of an exact teacher.

use super::*;
use crate::test_support::{
    distils_the_modes, four_mode_teacher, gradient_error, tiny_net, uniform_actions,
};
use vdd_core::Trainer as _;
use vdd_core::{Affine, Policy};
use vdd_diffusion::{Beso, NetConfig};

fn tiny_config() -> CtmConfig {
    let mut c = CtmConfig {
        base: ConsistencyConfig {
            net: tiny_net(),
            num_scales: 6,
            sigma_max: 10.0,
            ..Default::default()
        },
        max_teacher_steps: 3,
        ..Default::default()
    };
    c.base.train.batch_size = 5;
    c
}

#[test]
fn jump_to_the_same_level_is_the_identity() {
    let (s, a) = uniform_actions(16, 0);
    let mut t =
        CtmTrainer::new(tiny_config(), four_mode_teacher(), s.as_ref(), a.as_ref()).unwrap();
    for _ in 0..3 {
        t.step().unwrap();
    }
    let mut model = t.model().unwrap();
    let x = Mat::from_fn(6, 2, |i, j| 2.0 * (i as f32 - 2.5) - 0.3 * j as f32);
    let states = Mat::from_fn(6, 1, |i, _| i as f32);
    let levels = [0.002f32, 0.01, 0.3, 1.0, 7.0, 80.0];
    let mut out = Mat::zeros(6, 2);
    model.jump(x.as_ref(), &levels, &levels, states.as_ref(), out.as_mut()).unwrap();
    assert_eq!(out, x, "G(x, t, t) must be exactly x");
    let lower = levels.map(|l| 0.5 * l);
    model.jump(x.as_ref(), &levels, &lower, states.as_ref(), out.as_mut()).unwrap();
    assert_ne!(out, x);
    // u > t is rejected.
    assert!(model.jump(x.as_ref(), &lower, &levels, states.as_ref(), out.as_mut()).is_err());
}

/// The analytic gradient of the CTM loss (consistency and DSM terms in one stacked batch,
/// the consistency term compared at `u` or through the stop-gradient student at `σ_min`)
/// matches central finite differences; so does the consistency term alone.
#[test]
fn ctm_loss_gradient_matches_finite_differences() {
    for (matching, dsm_weight, dsm_weighting) in [
        (CtmMatching::AtTarget, 0.7f32, DsmWeighting::Edm),
        (CtmMatching::AtBoundary, 0.7, DsmWeighting::Uniform),
        (CtmMatching::AtBoundary, 0.0, DsmWeighting::Uniform),
    ] {
        {
            let (s, a) = uniform_actions(16, 1);
            let c = CtmConfig { dsm_weight, dsm_weighting, matching, ..tiny_config() };
            let mut t = CtmTrainer::new(c, four_mode_teacher(), s.as_ref(), a.as_ref()).unwrap();
            for _ in 0..5 {
                t.step().unwrap();
            }
            t.objective.draw(&mut t.core).unwrap();
            let CtmTrainer { core, objective, .. } = &mut t;
            let probe = objective.loss(core, false);
            assert!(probe.consistency > 1e-5, "{probe:?}");
            assert_eq!(probe.dsm > 1e-4, dsm_weight > 0.0, "{probe:?}");
            let (_, worst, checked) =
                gradient_error(core, |core, backward| objective.loss(core, backward).total);
            assert!(checked > 50);
            assert!(worst < 2e-2, "{matching:?}, λ_DSM {dsm_weight}: worst error {worst}");
        }
    }
}

/// Mapped to `σ_min`, rows whose target level is `σ_min` compare exactly what the direct
/// comparison does (`G(·, σ_min, σ_min)` is the identity), and the others differ.
#[test]
fn boundary_matching_agrees_with_direct_matching_at_sigma_min() {
    let (s, a) = uniform_actions(16, 4);
    let run = |matching| {
        let c = CtmConfig { dsm_weight: 0.0, matching, ..tiny_config() };
        // Untrained, so that both runs have the same networks and draws.
        let mut t = CtmTrainer::new(c, four_mode_teacher(), s.as_ref(), a.as_ref()).unwrap();
        t.objective.draw(&mut t.core).unwrap();
        let CtmTrainer { core, objective, .. } = &mut t;
        objective.loss(core, false);
        (objective.u.clone(), objective.target.clone())
    };
    let ((u, direct), (u2, mapped)) = (run(CtmMatching::AtTarget), run(CtmMatching::AtBoundary));
    assert_eq!(u, u2);
    let sigma_min = tiny_config().base.sigma_min;
    let (mut same, mut different) = (0, 0);
    for (i, &ui) in u.iter().enumerate() {
        let equal = (0..2).all(|j| direct[(i, j)] == mapped[(i, j)]);
        if ui == sigma_min {
            assert!(equal, "row {i} at σ_min");
            same += 1;
        } else if !equal {
            different += 1;
        }
    }
    assert!(same > 0 && different > 0, "{same} rows at σ_min, {different} mapped rows");
}

/// Started from a BESO teacher, `G(x, t, u)` is the teacher's DDIM jump
/// `(u/t) x + (1 − u/t) D(x; t)` for every `u`.
#[test]
fn student_from_a_beso_teacher_starts_as_its_ddim_jump() {
    let net = NetConfig { hidden_dim: 8, num_blocks: 1, ..Default::default() };
    let bc = BesoConfig { net, ..Default::default() };
    let mut beso = Beso::new(&bc, Affine::identity(1), Affine::identity(2), 0).unwrap();
    let (s, a) = uniform_actions(16, 3);
    let mut c = CtmConfig::for_teacher(&beso);
    c.base.train.batch_size = 4;
    let mut model =
        CtmTrainer::new(c.clone(), &mut beso, s.as_ref(), a.as_ref()).unwrap().model().unwrap();
    let x = Mat::from_fn(3, 2, |i, j| i as f32 - j as f32);
    let st = Mat::<f32>::zeros(3, 1);
    let (t, u) = ([5.0f32, 1.0, 0.3], [0.002f32, 0.5, 0.3]);
    let (mut g, mut dn, mut own) = (Mat::zeros(3, 2), Mat::zeros(3, 2), Mat::zeros(3, 2));
    model.jump(x.as_ref(), &t, &u, st.as_ref(), g.as_mut()).unwrap();
    model.denoise(x.as_ref(), &t, st.as_ref(), own.as_mut()).unwrap();
    beso.denoise(x.as_ref(), &t, st.as_ref(), dn.as_mut()).unwrap();
    for i in 0..3 {
        let r = u[i] / t[i];
        for j in 0..2 {
            let want = r * x[(i, j)] + (1.0 - r) * dn[(i, j)];
            assert!((g[(i, j)] - want).abs() < 1e-5, "{g:?} vs {want}");
            assert!((own[(i, j)] - dn[(i, j)]).abs() < 1e-5, "{own:?} vs {dn:?}");
        }
    }
    model.set_sampling_steps(3).unwrap();
    assert_eq!(model.sampling_levels().len(), 4);
    assert!(model.act(&[0.0]).unwrap().iter().all(|v| v.is_finite()));
    let mut other = c;
    other.base.net.embed_dim = 8;
    assert!(CtmTrainer::new(other, &mut beso, s.as_ref(), a.as_ref()).is_err());
}

/// A CTM student of the exact four-mode denoiser puts its one-step samples on the modes.
#[test]
fn ctm_student_of_an_exact_gmm_teacher_samples_near_the_modes() {
    distils_the_modes(|base, states, actions| {
        let config = CtmConfig { base, ..Default::default() };
        let mut t = CtmTrainer::new(config, four_mode_teacher(), states, actions).unwrap();
        let untrained = t.model().unwrap();
        (Box::new(untrained), Box::new(t.train(&mut |_| {}).unwrap()))
    });
}

#[test]
fn training_is_deterministic_for_a_seed() {
    let (s, a) = uniform_actions(32, 2);
    let run = |seed: u64| {
        let mut c = tiny_config().with_seed(seed);
        c.base.train.steps = 5;
        let mut t = CtmTrainer::new(c, four_mode_teacher(), s.as_ref(), a.as_ref()).unwrap();
        let mut reports = Vec::new();
        let mut m = t.train(&mut |p| reports.push((p.loss, p.dsm_loss))).unwrap();
        (reports, m.act(&[0.0]).unwrap())
    };
    assert_eq!(run(7), run(7));
    assert_ne!(run(7).1, run(8).1);
}

#[test]
fn bad_configs_are_errors() {
    let (s, a) = uniform_actions(8, 0);
    let mut c = tiny_config();
    c.base.init_from_teacher = true;
    for c in [
        CtmConfig { max_teacher_steps: 0, ..tiny_config() },
        CtmConfig { dsm_weight: -1.0, ..tiny_config() },
        CtmConfig {
            dsm_sigma: SigmaDistribution::LogNormal { mean: 0.0, std: 0.0 },
            ..tiny_config()
        },
        c,
    ] {
        assert!(CtmTrainer::new(c, four_mode_teacher(), s.as_ref(), a.as_ref()).is_err());
    }
    let mut m = CtmTrainer::new(tiny_config(), four_mode_teacher(), s.as_ref(), a.as_ref())
        .unwrap()
        .model()
        .unwrap();
    assert!(m.act(&[1.0, 2.0]).is_err());
    assert!(m.set_sampling_steps(0).is_err());
    let x = Mat::<f32>::zeros(2, 2);
    let mut out = Mat::zeros(2, 2);
    let st = Mat::<f32>::zeros(2, 1);
    assert!(m.jump(x.as_ref(), &[1.0, 1.0], &[0.5], st.as_ref(), out.as_mut()).is_err());
    assert!(m.denoise(x.as_ref(), &[1.0, -1.0], st.as_ref(), out.as_mut()).is_err());
}

/// The distilled policies (this one and CD's) can move to evaluation threads.
#[test]
fn distilled_policies_are_send_and_clone() {
    fn check<P: Policy + Send + Clone>() {}
    check::<crate::ConsistencyModel>();
    check::<TrajectoryModel>();
}
