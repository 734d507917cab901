//! Tests of EM: monotone likelihood, recovered clusters, determinism, bad inputs.

use super::*;
use crate::test_support::{
    CLUSTER_MEANS, assert_gating_matches_shares, clusters, expert_params, full_batch_config,
    small_moe, small_moe_config, uniform_cluster_experts,
};
use faer::Mat;
use vdd_core::Policy;
use vdd_moe::{ExpertKind, MoeConfig};
use vdd_nn::Parameters;

#[test]
fn log_likelihood_never_decreases_on_a_full_batch() {
    for kind in [ExpertKind::Diagonal, ExpertKind::Full] {
        let (data, _) = clusters([40, 40, 40], 0.35, 1);
        let student = small_moe(kind, 3, 5);
        let config = full_batch_config(25, 30, 3e-3);
        let mut em = Em::new(config, student, data).unwrap();
        let mut lls = Vec::new();
        em.train(|m| lls.push(m.log_likelihood)).unwrap();
        lls.push(em.log_likelihood().unwrap());
        for w in lls.windows(2) {
            assert!(w[1] >= w[0] - 1e-4, "{kind:?}: log-likelihood decreased: {lls:?}");
        }
        assert!(lls[lls.len() - 1] > lls[0] + 1.0, "{kind:?}: EM did not improve: {lls:?}");
    }
}

#[test]
fn finds_the_means_of_three_separated_clusters() {
    // Unequal clusters, so that the gating must learn unequal weights.
    let sizes = [60, 120, 180];
    let (data, _) = clusters(sizes, 0.3, 2);
    let student = small_moe(ExpertKind::Diagonal, 3, 0);
    let config = EmConfig {
        iterations: 60,
        expert_steps_per_iter: 10,
        gating_steps_per_iter: 10,
        batch_size: Some(128),
        gating_batch_size: Some(128),
        expert_optimizer: AdamConfig { lr: 1e-2, ..AdamConfig::default() },
        gating_optimizer: AdamConfig { lr: 1e-2, ..AdamConfig::default() },
        expert_lr_schedule: LrSchedule::LinearDecay { final_factor: 0.05 },
        gating_lr_schedule: LrSchedule::LinearDecay { final_factor: 0.05 },
        ..EmConfig::toy()
    };
    let mut student = Em::fit(config, student, data).unwrap();
    student.forward(Mat::zeros(1, 1).as_ref()).unwrap();
    let out = student.output();
    let mut found = [false; 3];
    for z in 0..3 {
        let m = out.mean(0, z);
        let (c, dist) = CLUSTER_MEANS
            .iter()
            .enumerate()
            .map(|(c, mu)| (c, ((m[0] - mu[0]).powi(2) + (m[1] - mu[1]).powi(2)).sqrt()))
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap();
        assert!(dist < 0.15, "expert {z} mean {m:?} is {dist} from cluster {c}");
        found[c] = true;
        let w = out.log_gating_row(0)[z].exp();
        let expect = sizes[c] as f32 / 360.0;
        assert!((w - expect).abs() < 0.04, "expert {z} weight {w}, cluster share {expect}");
        let std = out.scale(0, z)[0];
        assert!((std - 0.3).abs() < 0.06, "expert {z} std {std}");
    }
    assert_eq!(found, [true; 3], "two experts share a cluster");
}

#[test]
fn same_seed_same_run_and_other_seed_other_run() {
    let run = |seed: u64| {
        let (data, _) = clusters([10, 10, 10], 0.3, 3);
        let config = EmConfig { iterations: 3, seed, ..EmConfig::toy() };
        let config = EmConfig { batch_size: Some(16), gating_batch_size: Some(16), ..config };
        let mut em = Em::new(config, small_moe(ExpertKind::Full, 3, 1), data).unwrap();
        let mut metrics = Vec::new();
        em.train(|m| metrics.push(*m)).unwrap();
        let mut params = Vec::new();
        em.student().visit_params("", &mut |_, p| params.push(p.value.clone()));
        (metrics, params)
    };
    let (a, b, c) = (run(7), run(7), run(8));
    assert_eq!(a, b);
    assert_ne!(a.1, c.1);
}

#[test]
fn one_seed_initialises_the_mixture_and_drives_the_fit() {
    let (data, _) = clusters([10, 10, 10], 0.3, 3);
    let config = |seed| EmConfig { iterations: 2, seed, batch_size: Some(16), ..EmConfig::toy() };
    let run = |mut em: Em| {
        let mut params = Vec::new();
        em.student().visit_params("", &mut |_, p| params.push(p.value.clone()));
        let mut metrics = Vec::new();
        em.train(|m| metrics.push(*m)).unwrap();
        (params, metrics)
    };
    let mc = small_moe_config(ExpertKind::Full, 3);
    let one = run(Em::from_config(config(5), mc.clone(), data.clone()).unwrap());
    // The same as a mixture initialised separately with the run's seed.
    let apart = run(Em::new(config(5), small_moe(ExpertKind::Full, 3, 5), data.clone()).unwrap());
    assert_eq!(one, apart);
    let family = vdd_moe::ExpertFamily::new(ExpertKind::Full, 2, mc.init_std, mc.min_std);
    let family = Em::with_family(config(5), mc.clone(), family.unwrap(), data.clone());
    assert_eq!(run(family.unwrap()), one);
    let other = run(Em::from_config(config(6), mc, data).unwrap());
    assert_ne!(other.0, one.0, "another seed, another initial mixture");
}

#[test]
fn bad_inputs_are_rejected() {
    let (data, _) = clusters([4, 3, 3], 0.3, 0);
    let student = small_moe(ExpertKind::Diagonal, 2, 0);
    let bad = [
        EmConfig { iterations: 0, ..EmConfig::toy() },
        EmConfig { batch_size: Some(0), ..EmConfig::toy() },
        EmConfig { max_grad_norm: Some(-1.0), ..EmConfig::toy() },
        EmConfig {
            expert_optimizer: AdamConfig { lr: f32::NAN, ..AdamConfig::default() },
            ..EmConfig::toy()
        },
    ];
    for config in bad {
        assert!(Em::new(config, student.clone(), data.clone()).is_err());
    }
    // Frozen experts and a uniform gating: nothing to train.
    let uniform = Moe::from_config(MoeConfig::toy(1, 2, 2), 0).unwrap();
    let frozen = EmConfig { expert_steps_per_iter: 0, ..EmConfig::toy() };
    assert!(Em::new(frozen.clone(), uniform, data.clone()).is_err());
    assert!(Em::new(frozen, student.clone(), data.clone()).is_ok());
    let wrong_dims = Moe::from_config(MoeConfig::toy(1, 3, 2), 0).unwrap();
    assert!(Em::new(EmConfig::toy(), wrong_dims, data.clone()).is_err());
    let wrong_state = Moe::from_config(MoeConfig::toy(2, 2, 2), 0).unwrap();
    assert!(Em::new(EmConfig::toy(), wrong_state, data).is_err());
}

#[test]
fn an_e_step_on_a_subset_computes_only_its_rows_and_still_fits() {
    let (data, _) = clusters([60, 120, 180], 0.3, 2);
    let n = data.len();
    let config = EmConfig {
        iterations: 1,
        batch_size: Some(32),
        gating_batch_size: Some(32),
        e_step_rows: Some(50),
        ..EmConfig::toy()
    };
    let mut em =
        Em::new(config.clone(), small_moe(ExpertKind::Diagonal, 3, 0), data.clone()).unwrap();
    em.train(|_| {}).unwrap();
    let z_n = 3;
    let filled = (0..n)
        .filter(|&o| em.responsibilities()[o * z_n..(o + 1) * z_n].iter().sum::<f32>() > 0.5)
        .count();
    assert_eq!(filled, 50, "the E-step computed {filled} rows, not 50");

    // Over many iterations the subsets cover the data and EM still raises the likelihood, the
    // same seed giving the same run.
    let run = |seed| {
        let config = EmConfig {
            iterations: 60,
            expert_steps_per_iter: 10,
            gating_steps_per_iter: 10,
            expert_optimizer: AdamConfig { lr: 1e-2, ..AdamConfig::default() },
            gating_optimizer: AdamConfig { lr: 1e-2, ..AdamConfig::default() },
            seed,
            ..config.clone()
        };
        let mut em = Em::new(config, small_moe(ExpertKind::Diagonal, 3, 0), data.clone()).unwrap();
        let before = em.log_likelihood().unwrap();
        let mut metrics = Vec::new();
        em.train(|m| metrics.push(*m)).unwrap();
        (before, em.log_likelihood().unwrap(), metrics)
    };
    let (before, after, metrics) = run(3);
    assert!(after > before + 1.0, "EM on subsets did not fit: {before} -> {after}");
    assert_eq!(run(3).2, metrics);
    assert_ne!(run(4).2, metrics);
}

#[test]
fn an_e_step_subset_needs_minibatches_and_rows() {
    let (data, _) = clusters([4, 3, 3], 0.3, 0);
    let student = small_moe(ExpertKind::Diagonal, 2, 0);
    let zero = EmConfig { e_step_rows: Some(0), ..EmConfig::toy() };
    let err = Em::new(zero, student.clone(), data.clone()).err().unwrap().to_string();
    assert!(err.contains("e_step_rows"), "{err}");
    let full = EmConfig { e_step_rows: Some(4), ..full_batch_config(2, 3, 1e-3) };
    let err = Em::new(full, student.clone(), data.clone()).err().unwrap().to_string();
    assert!(err.contains("minibatches"), "{err}");
    // More rows than the data: the classic E-step.
    let all = EmConfig { e_step_rows: Some(1000), iterations: 1, ..EmConfig::toy() };
    let mut em = Em::new(all, student, data).unwrap();
    em.train(|_| {}).unwrap();
    assert!(em.responsibilities().chunks(2).all(|r| (r.iter().sum::<f32>() - 1.0).abs() < 1e-4));
}

#[test]
fn uniform_gating_stays_uniform() {
    let (data, _) = clusters([7, 7, 6], 0.3, 0);
    let mut mc = MoeConfig::toy(1, 2, 3);
    mc.experts_network.hidden_dim = 8;
    let student = Moe::from_config(mc, 0).unwrap();
    let config = EmConfig { iterations: 2, ..full_batch_config(2, 3, 1e-3) };
    let mut em = Em::new(config, student, data).unwrap();
    let mut gating_losses = Vec::new();
    em.train(|m| gating_losses.push(m.gating_loss)).unwrap();
    assert_eq!(gating_losses, vec![None, None]);
    let mut student = em.into_student();
    let a = student.act(&[0.0]).unwrap();
    assert!(a.iter().all(|x| x.is_finite()));
}

#[test]
fn frozen_experts_fit_the_gating_alone() {
    // Experts fitted under a uniform gating to clusters of unequal sizes, then a learned
    // gating added and fitted with the experts frozen: the gating learns the cluster shares
    // and the experts do not move.
    let sizes = [60, 120, 180];
    let (mut student, data) = uniform_cluster_experts(sizes);
    student
        .add_learned_gating(small_moe_config(ExpertKind::Diagonal, 3).gating_network, 1)
        .unwrap();
    let experts_before = expert_params(&mut student);

    let config = EmConfig { expert_steps_per_iter: 0, ..full_batch_config(30, 20, 1e-2) };
    let mut em = Em::new(config, student, data).unwrap();
    let before = em.log_likelihood().unwrap();
    let mut metrics = Vec::new();
    em.train(|m| metrics.push(*m)).unwrap();
    assert!(metrics.iter().all(|m| m.expert_loss == 0.0 && m.expert_lr == 0.0));
    assert!(metrics.iter().all(|m| m.gating_loss.is_some()));
    let after = em.log_likelihood().unwrap();
    assert!(
        after > before + 0.05,
        "the gating fit did not raise the likelihood: {before} -> {after}"
    );

    let mut student = em.into_student();
    assert_eq!(expert_params(&mut student), experts_before, "the frozen experts moved");
    // Each expert's gating weight is the share of the cluster it covers.
    let shares = sizes.map(|n| n as f32 / 360.0);
    assert_gating_matches_shares(&mut student, shares, 0.03);
}
