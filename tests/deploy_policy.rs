//! Deployment: a distilled mixture (`vdd`, `vdd-moe`) saved with its normalisation acts
//! identically after loading, as a `Policy` in the Avoiding task (`vdd-tasks`).
//!
//! Deployment needs nothing but the saved file: the loaded policy must reproduce the
//! original's rollouts (same seed, sampled gating and actions) and exact log-likelihoods bit
//! for bit, and damaged files must fail with an error rather than a panic or a wrong policy.
//! A mixture trained on featured observations (`vdd-data`'s feature maps, named by
//! `vdd-tasks`' `ObsFeatures`) is saved with its deployment spec, and `vdd_moe::load_policy`
//! gives a policy on the environment's raw observations whose evaluation (the recipes'
//! `EvalProtocol`) equals the recipe's wrapping of the original, for any number of threads.

use std::path::PathBuf;

use faer::Mat;
use vdd_core::{Affine, Policy};
use vdd_data::{DeploySpec, Windowed};
use vdd_moe::{ActMode, ExpertKind, GatingKind, Moe, MoeConfig};
use vdd_tasks::avoiding::{ACTION_DIM, EvalProtocol, OBS_DIM, ObsFeatures};
use vdd_tasks::{DemonstratorConfig, generate_demonstrations};

fn scratch(name: &str) -> PathBuf {
    let dir = PathBuf::from(env!("CARGO_TARGET_TMPDIR")).join("deploy_policy");
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// A mixture for Avoiding with a learned gating, normalised by statistics of the demonstrator.
fn avoiding_policy(kind: ExpertKind) -> (Moe, Mat<f32>, Mat<f32>) {
    let demos = generate_demonstrations(4, 0, &DemonstratorConfig::default()).unwrap();
    let (obs, actions) = (&demos.observations[0], &demos.actions[0]);
    let stats = |m: &Mat<f32>| {
        let n = m.nrows() as f32;
        let mean: Vec<f32> =
            (0..m.ncols()).map(|j| (0..m.nrows()).map(|i| m[(i, j)]).sum::<f32>() / n).collect();
        let std: Vec<f32> = (0..m.ncols())
            .map(|j| {
                ((0..m.nrows()).map(|i| (m[(i, j)] - mean[j]).powi(2)).sum::<f32>() / n)
                    .sqrt()
                    .max(1e-3)
            })
            .collect();
        Affine::new(mean, std).unwrap()
    };
    let config = MoeConfig {
        expert_kind: kind,
        gating: GatingKind::Learned,
        ..MoeConfig::toy(OBS_DIM, ACTION_DIM, 4)
    };
    let mut moe = Moe::from_config(config, 7).unwrap();
    moe.set_normalizers(Some(stats(obs)), Some(stats(actions))).unwrap();
    moe.set_act_mode(ActMode { greedy_gating: false, sample_action: true, hold_steps: 0 });
    (moe, obs.clone(), actions.clone())
}

#[test]
fn a_loaded_policy_reproduces_rollouts_and_likelihoods() {
    for kind in [ExpertKind::Diagonal, ExpertKind::Full] {
        let (mut original, obs, actions) = avoiding_policy(kind);
        let path = scratch(&format!("{kind:?}.safetensors"));
        original.save(&path).unwrap();
        let mut loaded = Moe::load(&path).unwrap();

        for seed in [1, 2] {
            let a = vdd_tasks::avoiding::rollout::rollout(&mut original, seed, true).unwrap();
            let b = vdd_tasks::avoiding::rollout::rollout(&mut loaded, seed, true).unwrap();
            assert_eq!(a, b, "{kind:?}: rollout with seed {seed}");
            assert!(a.steps > 1);
        }
        let n = obs.nrows();
        let (mut la, mut lb) = (vec![0.0; n], vec![0.0; n]);
        original.log_likelihood(obs.as_ref(), actions.as_ref(), &mut la).unwrap();
        loaded.log_likelihood(obs.as_ref(), actions.as_ref(), &mut lb).unwrap();
        assert_eq!(la, lb, "{kind:?}: log-likelihoods");
        assert!(la.iter().all(|l| l.is_finite()));
    }
}

#[test]
fn damaged_or_mismatched_files_are_errors() {
    let (original, ..) = avoiding_policy(ExpertKind::Diagonal);
    let path = scratch("damaged.safetensors");
    original.save(&path).unwrap();
    let bytes = std::fs::read(&path).unwrap();

    let truncated = scratch("truncated.safetensors");
    std::fs::write(&truncated, &bytes[..bytes.len() / 2]).unwrap();
    assert!(Moe::load(&truncated).is_err());

    assert!(Moe::load(&scratch("missing.safetensors")).is_err());

    // A full-covariance family cannot read diagonal experts' outputs.
    let family = vdd_moe::FullExpert::new(ACTION_DIM, 1.0, 1e-4).unwrap();
    assert!(Moe::load_with_family(&path, family).is_err());
}

#[test]
fn a_saved_policy_on_raw_observations_reproduces_the_recipes_evaluation() {
    // The mixture sees position-and-lag features, normalised by their statistics.
    let (mut moe, obs, _) = avoiding_policy(ExpertKind::Diagonal);
    let features = ObsFeatures::PositionAndLag.feature_map();
    let featured = features.apply_rows(obs.as_ref()).unwrap();
    let mean: Vec<f32> = (0..OBS_DIM)
        .map(|j| {
            (0..featured.nrows()).map(|i| featured[(i, j)]).sum::<f32>() / featured.nrows() as f32
        })
        .collect();
    let act_norm = moe.normalizers().1.cloned();
    moe.set_normalizers(Some(Affine::new(mean, vec![0.05; OBS_DIM]).unwrap()), act_norm).unwrap();
    let spec = DeploySpec::identity().with_features(features);
    moe.set_deploy_spec(spec.clone()).unwrap();
    let path = scratch("deployed.safetensors");
    moe.save(&path).unwrap();

    let recipe = Windowed::new(moe.clone(), spec).unwrap();
    let deployed = vdd_moe::load_policy(&path).unwrap();
    assert_eq!(deployed.spec(), recipe.spec());
    let protocol = EvalProtocol { rollouts: 24, lockstep_batch: 8 };
    let want = protocol.evaluate(&recipe, 3, 1, true).unwrap();
    for threads in [1, 2] {
        let got = protocol.evaluate(&deployed, 3, threads, true).unwrap();
        assert_eq!(got, want, "{threads} thread(s)");
    }
    assert!(want.rollouts.iter().all(|r| r.steps > 1));
    // Without its features the same weights act otherwise: the spec is what makes it deployable.
    let raw = Moe::load(&path).unwrap();
    let plain = protocol.evaluate(&raw, 3, 1, true).unwrap();
    assert_ne!(plain.rollouts, want.rollouts);
}
