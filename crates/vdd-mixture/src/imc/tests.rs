//! Tests of IMC: the closed-form curriculum update, monotone objective, curricula per cluster, the tempered fixed point.

use super::*;
use crate::test_support::{self, clusters, small_moe};
use faer::Mat;
use vdd_core::Seeds;
use vdd_moe::{ExpertKind, MoeConfig};
use vdd_nn::Parameters;

#[test]
fn curriculum_update_matches_the_closed_form() {
    // N = 3 points, Z = 2 experts, from a non-uniform joint.
    let mut c = Curricula::uniform(3, 2).unwrap();
    let p0 = [0.1f64, 0.2, 0.3, 0.1, 0.05, 0.25];
    c.log_joint = p0.iter().map(|p| p.ln()).collect();
    let ll = [-1.0f32, -3.0, -0.5, -0.2, -4.0, -1.5];
    let eta = 2.0;
    let bound = c.update(&ll, eta).unwrap();
    // By hand: p_new(o, z) ∝ exp(ℓ/η) p_old(z|o).
    let mut unnorm = [0.0f64; 6];
    for o in 0..3 {
        let p_o = p0[2 * o] + p0[2 * o + 1];
        for z in 0..2 {
            unnorm[2 * o + z] = (f64::from(ll[2 * o + z]) / eta).exp() * p0[2 * o + z] / p_o;
        }
    }
    let xi: f64 = unnorm.iter().sum();
    for i in 0..6 {
        assert!((c.log_joint[i].exp() - unnorm[i] / xi).abs() < 1e-12, "pair {i}");
    }
    assert!((bound - eta * xi.ln()).abs() < 1e-12);
    // The bound is the maximum of L over p; J at the new p is at least the bound, and the
    // bound is at least J at the old p (tightness).
    let mut old = Curricula::uniform(3, 2).unwrap();
    old.log_joint = p0.iter().map(|p| p.ln()).collect();
    let j_old = old.objective(&ll, eta).unwrap();
    let j_new = c.objective(&ll, eta).unwrap();
    assert!(j_old <= bound + 1e-12 && bound <= j_new + 1e-12, "{j_old} {bound} {j_new}");
    // Normalisation of the joint, the curricula and the posteriors.
    assert!((c.log_joint.iter().map(|l| l.exp()).sum::<f64>() - 1.0).abs() < 1e-12);
    for z in 0..2 {
        assert!((c.curriculum(z).iter().sum::<f64>() - 1.0).abs() < 1e-12);
    }
    let mut post = [0.0; 2];
    c.posterior_into(1, &mut post);
    assert!((post[0] + post[1] - 1.0).abs() < 1e-12);
    let w = c.expert_weights();
    assert!((w[0] + w[1] - 1.0).abs() < 1e-12);
    assert!(c.update(&ll, 0.0).is_err());
    assert!(c.update(&ll[..5], 1.0).is_err());
    assert!(c.update(&[f32::NAN; 6], 1.0).is_err());
}

fn full_batch_config(iterations: usize, steps: usize, lr: f32) -> ImcConfig {
    ImcConfig::with_loop_of(test_support::full_batch_config(iterations, steps, lr))
}

#[test]
fn objective_never_decreases_on_a_full_batch() {
    let (data, _) = clusters([40, 40, 40], 0.35, 1);
    let mut imc =
        Imc::new(full_batch_config(25, 30, 3e-3), small_moe(ExpertKind::Full, 3, 5), data).unwrap();
    let mut js = Vec::new();
    imc.train(|m| {
        assert!(m.objective <= m.lower_bound + 1e-6, "bound below J at the old curricula");
        js.push(m.objective);
    })
    .unwrap();
    js.push(imc.objective().unwrap());
    for w in js.windows(2) {
        assert!(w[1] >= w[0] - 1e-4, "objective decreased: {js:?}");
    }
    assert!(js[js.len() - 1] > js[0] + 1.0, "IMC did not improve: {js:?}");
}

#[test]
fn each_curriculum_concentrates_on_one_cluster() {
    let sizes = [40, 60, 80];
    let (data, labels) = clusters(sizes, 0.3, 2);
    let n = data.len();
    let config = ImcConfig {
        iterations: 60,
        expert_steps_per_iter: 10,
        gating_steps_per_iter: 10,
        batch_size: Some(128),
        gating_batch_size: Some(128),
        expert_optimizer: AdamConfig { lr: 1e-2, ..AdamConfig::default() },
        gating_optimizer: AdamConfig { lr: 1e-2, ..AdamConfig::default() },
        expert_lr_schedule: LrSchedule::LinearDecay { final_factor: 0.05 },
        gating_lr_schedule: LrSchedule::LinearDecay { final_factor: 0.05 },
        // A milder temperature than the default: at η = 2 the curricula can settle with a small
        // far cluster that no expert owns (a local optimum of IMC's objective; 2 of 8 seeds).
        eta: 4.0,
        ..ImcConfig::toy()
    };
    let mut imc = Imc::new(config, small_moe(ExpertKind::Diagonal, 3, 0), data).unwrap();
    imc.train(|_| {}).unwrap();
    let c = imc.curricula();
    let mut owner = [usize::MAX; 3];
    for z in 0..3 {
        let p = c.curriculum(z);
        assert!((p.iter().sum::<f64>() - 1.0).abs() < 1e-9);
        let mut mass = [0.0f64; 3];
        for o in 0..n {
            mass[labels[o]] += p[o];
        }
        let (best, m) = mass
            .iter()
            .enumerate()
            .max_by(|a, b| a.1.total_cmp(b.1))
            .map(|(i, m)| (i, *m))
            .unwrap();
        assert!(m > 0.99, "expert {z}'s curriculum spreads over clusters: {mass:?}");
        assert_eq!(owner[best], usize::MAX, "two experts took cluster {best}");
        owner[best] = z;
    }
    // The joint covers the data: no cluster is dropped from the data marginal.
    let p_o = c.data_marginal();
    for k in 0..3 {
        let m: f64 = (0..n).filter(|&o| labels[o] == k).map(|o| p_o[o]).sum();
        assert!(m > 0.2, "cluster {k} has marginal mass {m}");
    }
    // The gating follows the curricula's posterior, fitted uniformly over the data: each
    // expert's weight is its cluster's share of the points.
    let mut student = imc.into_student();
    student.forward(Mat::zeros(1, 1).as_ref()).unwrap();
    for (k, &z) in owner.iter().enumerate() {
        let w = student.output().log_gating_row(0)[z].exp();
        let expect = sizes[k] as f32 / n as f32;
        assert!((w - expect).abs() < 0.04, "gating weight of expert {z}: {w} vs {expect}");
    }
}

/// One expert on 1-D Gaussian data: the curriculum weights the data by `N(a; μ, σ²)^{1/η}`,
/// so the weighted maximum-likelihood fit settles at `σ*² = (1 − 1/η) s²` (module docs), in
/// both the full-batch (weights `p(o, z)`) and the minibatch (`o ~ p(o)`) form.
#[test]
fn single_expert_reaches_the_tempered_fixed_point() {
    let n = 400;
    let mut noise = vec![0.0f32; n];
    vdd_core::fill_standard_normal(&mut Seeds::new(4).stream("data"), &mut noise);
    let mean = noise.iter().sum::<f32>() / n as f32;
    let var = noise.iter().map(|x| (x - mean).powi(2)).sum::<f32>() / n as f32;
    let data = Dataset::new(Mat::zeros(n, 1), Mat::from_fn(n, 1, |i, _| noise[i])).unwrap();
    let eta = 2.0;
    let expect = ((1.0 - 1.0 / eta as f32) * var).sqrt();
    for batch in [None, Some(128)] {
        let mut mc = MoeConfig::toy(1, 1, 1);
        mc.gating = vdd_moe::GatingKind::Learned;
        mc.experts_network.hidden_dim = 8;
        mc.gating_network.hidden_dim = 8;
        let config = ImcConfig {
            eta,
            iterations: 40,
            expert_steps_per_iter: 30,
            gating_steps_per_iter: 1,
            batch_size: batch,
            expert_optimizer: AdamConfig { lr: 1e-2, ..AdamConfig::default() },
            expert_lr_schedule: LrSchedule::LinearDecay { final_factor: 0.05 },
            ..ImcConfig::toy()
        };
        let mut student = Imc::fit(config, Moe::from_config(mc, 0).unwrap(), data.clone()).unwrap();
        student.forward(Mat::zeros(1, 1).as_ref()).unwrap();
        let (mu, std) = (student.output().mean(0, 0)[0], student.output().scale(0, 0)[0]);
        assert!((mu - mean).abs() < 0.05, "{batch:?}: mean {mu} vs data mean {mean}");
        assert!((std - expect).abs() < 0.04, "{batch:?}: std {std} vs fixed point {expect}");
    }
}

#[test]
fn same_seed_same_run_and_other_seed_other_run() {
    let run = |seed: u64| {
        let config = ImcConfig {
            iterations: 3,
            batch_size: Some(16),
            gating_batch_size: Some(16),
            gating_data: GatingData::Curriculum,
            seed,
            ..ImcConfig::toy()
        };
        let mut imc =
            Imc::new(config, small_moe(ExpertKind::Full, 3, 1), clusters([10, 10, 10], 0.3, 3).0)
                .unwrap();
        let mut metrics = Vec::new();
        imc.train(|m| metrics.push(*m)).unwrap();
        let mut params = Vec::new();
        imc.student().visit_params("", &mut |_, p| params.push(p.value.clone()));
        (metrics, params, imc.curricula().clone())
    };
    let (a, b, c) = (run(7), run(7), run(8));
    assert_eq!(a, b);
    assert_ne!(a.1, c.1);
}

#[test]
fn bad_inputs_are_rejected() {
    let (data, _) = clusters([4, 3, 3], 0.3, 0);
    let student = small_moe(ExpertKind::Diagonal, 2, 0);
    for config in [
        ImcConfig { eta: 0.0, ..ImcConfig::toy() },
        ImcConfig { eta: f64::INFINITY, ..ImcConfig::toy() },
        ImcConfig { gating_batch_size: Some(0), ..ImcConfig::toy() },
        ImcConfig { iterations: 0, ..ImcConfig::toy() },
    ] {
        assert!(Imc::new(config, student.clone(), data.clone()).is_err());
    }
    let uniform_gating = Moe::from_config(MoeConfig::toy(1, 2, 2), 0).unwrap();
    assert!(Imc::new(ImcConfig::toy(), uniform_gating, data.clone()).is_err());
    let wrong_dims = small_moe(ExpertKind::Diagonal, 2, 0);
    let data3 = Dataset::new(Mat::zeros(4, 1), Mat::zeros(4, 3)).unwrap();
    assert!(Imc::new(ImcConfig::toy(), wrong_dims, data3).is_err());
    assert!(Curricula::uniform(0, 2).is_err());
}

/// The authors' IMC: unit-variance experts settle on the clusters' centres, one each; every
/// point keeps a curriculum (none is dropped); the gating is fitted at the end only, to the
/// clusters' shares.
#[test]
fn the_authors_variant_covers_every_cluster_and_fits_the_gating_last() {
    authors_variant_covers_every_cluster(None);
}

/// As the full authors' variant, with 40 of the 180 points' curricula updated per iteration.
#[test]
fn subsampled_curricula_cover_every_cluster_and_fit_the_gating_last() {
    authors_variant_covers_every_cluster(Some(40));
}

fn authors_config(curriculum_rows: Option<usize>) -> ImcConfig {
    ImcConfig {
        variant: ImcVariant::Authors,
        eta: 1.0,
        iterations: 40,
        expert_steps_per_iter: 10,
        gating_steps_per_iter: 10,
        batch_size: Some(128),
        gating_batch_size: Some(128),
        expert_optimizer: AdamConfig { lr: 1e-2, ..AdamConfig::default() },
        gating_optimizer: AdamConfig { lr: 1e-2, ..AdamConfig::default() },
        curriculum_rows,
        ..ImcConfig::toy()
    }
}

fn authors_variant_covers_every_cluster(curriculum_rows: Option<usize>) {
    let sizes = [40, 60, 80];
    let (data, _) = clusters(sizes, 0.3, 2);
    let n = data.len();
    let config = authors_config(curriculum_rows);
    let mut imc = Imc::new(config, small_moe(ExpertKind::Diagonal, 3, 0), data).unwrap();
    let mut gating = Vec::new();
    let mut coverage = 0.0;
    imc.train(|m| {
        gating.push(m.gating_loss.is_some());
        coverage = m.effective_data_fraction;
    })
    .unwrap();
    assert_eq!(gating.iter().filter(|g| **g).count(), 1, "gating fitted once");
    assert!(gating[gating.len() - 1], "the gating is fitted after the last iteration");
    assert!(coverage > 0.5, "the per-point curricula keep the data: {coverage}");
    let mut student = imc.into_student();
    student.forward(Mat::zeros(1, 1).as_ref()).unwrap();
    let out = student.output();
    let mut owners = [usize::MAX; 3];
    for z in 0..3 {
        let mean = out.mean(0, z);
        let (k, d) = test_support::CLUSTER_MEANS
            .iter()
            .map(|c| ((c[0] - mean[0]).powi(2) + (c[1] - mean[1]).powi(2)).sqrt())
            .enumerate()
            .min_by(|a, b| a.1.total_cmp(&b.1))
            .unwrap();
        assert!(d < 0.3, "expert {z} at {mean:?} is {d} from cluster {k}");
        assert_eq!(owners[k], usize::MAX, "two experts on cluster {k}");
        owners[k] = z;
    }
    for (k, &z) in owners.iter().enumerate() {
        let w = out.log_gating_row(0)[z].exp();
        let expect = sizes[k] as f32 / n as f32;
        assert!((w - expect).abs() < 0.05, "gating weight of expert {z}: {w} vs {expect}");
    }
}

/// Updating every point's curriculum is the full run, bit for bit; updating some is another
/// run, the same for the same seed.
#[test]
fn curriculum_rows_of_the_whole_dataset_are_the_full_run() {
    let (data, _) = clusters([40, 60, 80], 0.3, 2);
    let n = data.len();
    let run = |rows: Option<usize>| {
        let config = ImcConfig { iterations: 6, ..authors_config(rows) };
        let mut imc =
            Imc::new(config, small_moe(ExpertKind::Diagonal, 3, 0), data.clone()).unwrap();
        let mut metrics = Vec::new();
        imc.train(|m| metrics.push(*m)).unwrap();
        let mut params = Vec::new();
        imc.student().visit_params("", &mut |_, p| params.push(p.value.clone()));
        (metrics, params, imc.posterior.clone())
    };
    let full = run(None);
    assert_eq!(run(Some(n)), full);
    assert_eq!(run(Some(n + 7)), full);
    let some = run(Some(50));
    assert_eq!(run(Some(50)), some);
    assert_ne!(some.1, full.1);
    // The drawn iterations fit no gating; the last updates every point and fits it.
    assert!(some.0[..5].iter().all(|m| m.gating_loss.is_none()));
    assert!(some.0[5].gating_loss.is_some());
    // Their bound is η log Σ c(o, z) over the drawn points' curricula before normalisation
    // (a jointly normalised curricula would give exactly 0).
    assert!(some.0[..5].iter().all(|m| m.lower_bound.is_finite()));
    assert!(some.0[..5].iter().any(|m| m.lower_bound.abs() > 1e-6), "{:?}", some.0);
    assert!(some.2.iter().all(|p| p.is_finite()));
}

#[test]
fn curriculum_rows_need_the_authors_variant_and_minibatches() {
    let (data, _) = clusters([10, 10, 10], 0.3, 0);
    let student = small_moe(ExpertKind::Diagonal, 3, 0);
    let bad = [
        (ImcConfig { curriculum_rows: Some(0), ..authors_config(None) }, "positive"),
        (ImcConfig { curriculum_rows: Some(8), ..ImcConfig::toy() }, "authors' variant"),
        (ImcConfig { batch_size: None, ..authors_config(Some(8)) }, "batch_size"),
    ];
    for (config, says) in bad {
        let err = Imc::new(config, student.clone(), data.clone()).err().expect("refused");
        assert!(err.to_string().contains(says), "{err}");
    }
}
