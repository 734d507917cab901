//! Save and load.

use super::*;

// ---------------------------------------------------------------------------------------
// Save and load.
// ---------------------------------------------------------------------------------------

fn scratch(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("vdd-moe-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

#[test]
fn save_and_load_round_trip_everything_a_deployed_policy_needs() {
    for cfg in all_configs(2, 3) {
        let what = format!("{:?}/{:?}/shared={}", cfg.expert_kind, cfg.gating, cfg.shared_trunk);
        let mut moe = built(cfg, 19);
        let mode = ActMode { greedy_gating: false, sample_action: true, hold_steps: 3 };
        moe.set_act_mode(mode);
        let path = scratch(&format!("rt-{}.safetensors", what.replace('/', "-")));
        moe.save(&path).unwrap();
        let mut loaded = Moe::load(&path).unwrap();
        assert_eq!(loaded.config(), moe.config(), "{what}");
        assert_eq!(loaded.normalizers(), moe.normalizers(), "{what}");
        assert_eq!(loaded.act_mode(), mode, "{what}");
        assert_eq!(loaded.expert(), moe.expert(), "{what}");
        let obs = obs_batch(5, 2);
        let acts = Mat::from_fn(5, 3, |i, j| (i as f32 - j as f32) * 0.5);
        let (mut la, mut lb) = (vec![0.0; 5], vec![0.0; 5]);
        moe.log_likelihood(obs.as_ref(), acts.as_ref(), &mut la).unwrap();
        loaded.log_likelihood(obs.as_ref(), acts.as_ref(), &mut lb).unwrap();
        assert_eq!(la, lb, "{what}");
        moe.seed(4);
        loaded.seed(4);
        for k in 0..10 {
            let o = [0.2 * k as f32, -0.1];
            assert_eq!(moe.act(&o).unwrap(), loaded.act(&o).unwrap(), "{what}");
        }
    }
}

#[test]
fn an_act_mode_saved_before_hold_steps_existed_loads_without_holds() {
    let old: ActMode =
        serde_json::from_str(r#"{"greedy_gating":true,"sample_action":false}"#).unwrap();
    assert_eq!(old, ActMode { greedy_gating: true, sample_action: false, hold_steps: 0 });
}

#[test]
fn loading_with_another_expert_family_is_an_error() {
    let cfg = config(2, 2, ExpertKind::Full, GatingKind::Learned, true);
    let moe = built(cfg.clone(), 20);
    let path = scratch("family.safetensors");
    moe.save(&path).unwrap();
    let mismatch =
        |r: Result<Moe<FullExpert>, MoeError>| matches!(r, Err(MoeError::FamilyMismatch(_)));
    assert!(Moe::load_with_family(&path, FullExpert::new(2, 1.0, 1e-4).unwrap()).is_ok());
    // Same kind and shapes, another scale activation: would silently change every scale.
    assert!(mismatch(Moe::load_with_family(&path, FullExpert::new(2, 0.5, 1e-4).unwrap())));
    assert!(mismatch(Moe::load_with_family(&path, FullExpert::new(2, 1.0, 1e-2).unwrap())));
    assert!(Moe::load_with_family(&path, FullExpert::new(3, 1.0, 1e-4).unwrap()).is_err());
    let diag = Moe::load_with_family(&path, DiagonalExpert::new(2, 1.0, 1e-4).unwrap());
    assert!(matches!(diag, Err(MoeError::FamilyMismatch(_))));

    // A custom-family mixture whose config names another kind: `Moe::load` refuses it,
    // `load_with_family` with the right family reads it.
    let family = FullExpert::new(2, 0.7, 1e-3).unwrap();
    let custom =
        Moe::new(MoeConfig { expert_kind: ExpertKind::Diagonal, ..cfg }, family, 1).unwrap();
    let path = scratch("custom.safetensors");
    custom.save(&path).unwrap();
    assert!(matches!(Moe::load(&path), Err(MoeError::FamilyMismatch(_))));
    let back = Moe::load_with_family(&path, family).unwrap();
    let mut pa = Vec::new();
    let mut pb = Vec::new();
    custom.visit_params("", &mut |_, p| pa.push(p.value.clone()));
    back.visit_params("", &mut |_, p| pb.push(p.value.clone()));
    assert_eq!(pa, pb);
}

#[test]
fn damaged_metadata_is_an_error_not_a_panic() {
    let moe = built(config(2, 3, ExpertKind::Diagonal, GatingKind::Learned, true), 21);
    let path = scratch("meta.safetensors");
    moe.save(&path).unwrap();
    let meta = vdd_nn::io::read_metadata(&path).unwrap();
    for key in ["config", "obs_normalizer", "action_normalizer", "act_mode", "expert_family"] {
        assert!(meta.contains_key(key), "{key}");
    }
    let edited = |key: &str, value: Option<&str>| {
        let mut m = meta.clone();
        match value {
            Some(v) => m.insert(key.to_owned(), v.to_owned()),
            None => m.remove(key),
        };
        let p = scratch(&format!("meta-{key}-{}.safetensors", value.map_or(0, str::len)));
        vdd_nn::io::save_safetensors(&p, &moe, &m).unwrap();
        Moe::load(&p).map(|_| ())
    };
    let config = |edit: &dyn Fn(&mut MoeConfig)| {
        let mut c = moe.config().clone();
        edit(&mut c);
        serde_json::to_string(&c).unwrap()
    };
    let bad = [
        ("config", None),
        ("config", Some("{not json".to_owned())),
        ("config", Some(config(&|c| c.num_experts = 0))),
        ("config", Some(config(&|c| c.experts_network.hidden_dim = 9))),
        ("config", Some(config(&|c| c.state_dim = 3))),
        ("obs_normalizer", None),
        ("obs_normalizer", Some(r#"{"offset":[0.0],"scale":[1.0]}"#.to_owned())),
        ("action_normalizer", Some(r#"{"offset":[0,0,0],"scale":[1,-2,1]}"#.to_owned())),
        ("action_normalizer", Some(r#"{"offset":[0,0,0],"scale":[1,1]}"#.to_owned())),
        ("act_mode", None),
        ("act_mode", Some("3".to_owned())),
        ("expert_family", Some("[]".to_owned())),
    ];
    for (key, value) in &bad {
        assert!(edited(key, value.as_deref()).is_err(), "{key}: {value:?}");
    }
    // Files from before the family fingerprint still load.
    edited("expert_family", None).unwrap();
    assert!(matches!(Moe::load(&scratch("absent.safetensors")), Err(MoeError::Nn(_))));
}

// ---------------------------------------------------------------------------------------
// Deployment.
// ---------------------------------------------------------------------------------------

/// A spec for a mixture with 4-D states and 3-D actions: windows of 2 featured 2-D
/// observations, chunks of 3 1-D actions, 2 executed.
fn windowed_spec() -> DeploySpec {
    DeploySpec { obs_window: 2, action_chunk: 3, execute_steps: 2, ..DeploySpec::identity() }
        .with_features(vdd_data::features::POSITION_AND_LAG)
}

/// Raw 2-D observations of three episodes for a deployed policy.
fn raw_observations() -> Vec<Vec<[f32; 2]>> {
    (0..3)
        .map(|e| (0..7).map(|t| [0.3 * t as f32 - e as f32, 0.1 * (t * e) as f32]).collect())
        .collect()
}

/// Every action of `policy` over [`raw_observations`], one episode after another (seeded and
/// reset per episode), one observation at a time and then in lockstep batches.
fn deployed_actions(policy: &mut DeployedPolicy) -> Vec<f32> {
    let mut out = Vec::new();
    for (e, episode) in raw_observations().iter().enumerate() {
        policy.seed(e as u64);
        policy.reset();
        for o in episode {
            out.extend(policy.act(o).unwrap());
        }
    }
    policy.seed(9);
    policy.reset();
    let episodes = raw_observations();
    let mut actions = Mat::<f32>::zeros(3, 1);
    for t in 0..7 {
        let obs = Mat::from_fn(3, 2, |i, j| episodes[i][t][j]);
        policy.act_batch(obs.as_ref(), actions.as_mut()).unwrap();
        out.extend((0..3).map(|i| actions[(i, 0)]));
    }
    out
}

#[test]
fn a_saved_then_loaded_policy_acts_bit_identically_on_raw_observations() {
    for cfg in all_configs(4, 3) {
        let what = format!("{:?}/{:?}/shared={}", cfg.expert_kind, cfg.gating, cfg.shared_trunk);
        let mut moe = built(cfg, 23);
        moe.set_act_mode(ActMode { greedy_gating: false, sample_action: true, hold_steps: 0 });
        moe.set_deploy_spec(windowed_spec()).unwrap();
        let path = scratch(&format!("deploy-{}.safetensors", what.replace('/', "-")));
        moe.save(&path).unwrap();
        let mut loaded = crate::load_policy(&path).unwrap();
        assert_eq!(loaded.spec(), &windowed_spec(), "{what}");
        assert_eq!((loaded.obs_dim(), loaded.action_dim()), (2, 1), "{what}");
        let mut original = moe.into_policy().unwrap();
        let (a, b) = (deployed_actions(&mut original), deployed_actions(&mut loaded));
        assert_eq!(a, b, "{what}");
        assert!(a.iter().all(|x| x.is_finite()));
    }
}

#[test]
fn a_chunk_start_offset_is_saved_and_applied_after_loading() {
    let mut moe = built(config(4, 3, ExpertKind::Diagonal, GatingKind::Uniform, true), 26);
    let offset = DeploySpec { chunk_start: 1, ..windowed_spec() };
    moe.set_act_mode(ActMode { greedy_gating: true, sample_action: false, hold_steps: 0 });
    moe.set_deploy_spec(offset.clone()).unwrap();
    let path = scratch("deploy-offset.safetensors");
    moe.save(&path).unwrap();
    let mut loaded = crate::load_policy(&path).unwrap();
    assert_eq!(loaded.spec(), &offset);
    // Executed from index 1 of the chunk: the first action is the mixture's second.
    moe.seed(4);
    loaded.seed(4);
    let first = loaded.act(&[0.5, -0.5]).unwrap();
    let window = [0.5f32, -0.5, 0.5, -0.5];
    let mut mapped = window;
    for step in mapped.chunks_mut(2) {
        vdd_data::features::POSITION_AND_LAG.apply(step);
    }
    let chunk = moe.act(&mapped).unwrap();
    assert_eq!(first, [chunk[1]]);
    assert_eq!(loaded.act(&[0.5, -0.5]).unwrap(), [chunk[2]]);
}

#[test]
fn a_file_without_a_spec_loads_with_the_identity_spec() {
    let mut moe = built(config(2, 3, ExpertKind::Diagonal, GatingKind::Learned, true), 24);
    let path = scratch("spec-before.safetensors");
    moe.save(&path).unwrap();
    let mut meta = vdd_nn::io::read_metadata(&path).unwrap();
    assert!(meta.remove("deploy_spec").is_some());
    let old = scratch("spec-absent.safetensors");
    vdd_nn::io::save_safetensors(&old, &moe, &meta).unwrap();
    assert_eq!(Moe::load(&old).unwrap().deploy_spec(), &DeploySpec::identity());
    let mut policy = crate::load_policy(&old).unwrap();
    assert_eq!(policy.spec(), &DeploySpec::identity());
    // Raw observations go straight to the mixture.
    let obs = obs_batch(4, 2);
    let (mut a, mut b) = (Mat::<f32>::zeros(4, 3), Mat::<f32>::zeros(4, 3));
    moe.seed(2);
    policy.seed(2);
    moe.act_batch(obs.as_ref(), a.as_mut()).unwrap();
    policy.act_batch(obs.as_ref(), b.as_mut()).unwrap();
    assert_eq!(a, b);
    assert_eq!(policy.inner().last_experts(), moe.last_experts());
}

#[test]
fn bad_specs_are_refused_naming_the_setting_and_its_value() {
    let mut moe = built(config(4, 3, ExpertKind::Diagonal, GatingKind::Uniform, true), 25);
    // Setting a spec that does not fit leaves the old one.
    let misfit = DeploySpec { obs_window: 3, ..windowed_spec() };
    let e = moe.set_deploy_spec(misfit).unwrap_err();
    assert!(e.to_string().contains("`obs_window` = 3"), "{e}");
    assert_eq!(moe.deploy_spec(), &DeploySpec::identity());

    let path = scratch("spec-good.safetensors");
    moe.set_deploy_spec(windowed_spec()).unwrap();
    moe.save(&path).unwrap();
    let meta = vdd_nn::io::read_metadata(&path).unwrap();
    let load = |spec: &str| {
        let mut m = meta.clone();
        m.insert("deploy_spec".to_owned(), spec.to_owned());
        let p = scratch(&format!("spec-bad-{}.safetensors", spec.len()));
        vdd_nn::io::save_safetensors(&p, &moe, &m).unwrap();
        crate::load_policy(&p).map(|_| ()).unwrap_err().to_string()
    };
    let spec = |features: &str, w: usize, c: usize, e: usize| {
        format!(
            r#"{{"features":{features},"obs_window":{w},"action_chunk":{c},"execute_steps":{e}}}"#
        )
    };
    let with_start = |s: String, k: usize| format!("{},\"chunk_start\":{k}}}", &s[..s.len() - 1]);
    let pal = r#"{"name":"position_and_lag","version":1}"#;
    let cases = [
        (
            spec(r#"{"name":"lag","version":1}"#, 2, 3, 2),
            "`features` = lag v1: unknown feature map",
        ),
        (spec(r#"{"name":"identity","version":7}"#, 2, 3, 2), "`features` = identity v7"),
        (spec(pal, 0, 3, 2), "`obs_window` = 0"),
        (spec(pal, 2, 3, 4), "`execute_steps` = 4: must be between 1 and action_chunk = 3"),
        (spec(pal, 2, 2, 1), "`action_chunk` = 2: the policy's action dimension 3"),
        (spec(pal, 4, 3, 1), "`features` = position_and_lag v1: needs"),
        ("{not json".to_owned(), "bad `deploy_spec` metadata"),
        (spec(pal, 2, 3, 2).replace("obs_window", "window"), "unknown field `window`"),
        (with_start(spec(pal, 2, 3, 1), 3), "`chunk_start` = 3: must be below action_chunk = 3"),
        (
            with_start(spec(pal, 2, 3, 2), 2),
            "`execute_steps` = 2: must be between 1 and action_chunk − chunk_start = 3 − 2",
        ),
    ];
    for (bad, want) in &cases {
        let e = load(bad);
        assert!(e.contains(want), "{bad}: {e}");
    }
    // A metadata entry that is not JSON keeps the parser's error as the source.
    let mut m = meta.clone();
    m.insert("act_mode".to_owned(), "{not json".to_owned());
    let p = scratch("spec-bad-act-mode.safetensors");
    vdd_nn::io::save_safetensors(&p, &moe, &m).unwrap();
    match Moe::load(&p) {
        Err(e @ MoeError::BadMetadata { .. }) => {
            let source = std::error::Error::source(&e).unwrap();
            assert!(source.downcast_ref::<serde_json::Error>().is_some(), "{e}");
            assert!(e.to_string().contains("`act_mode`"), "{e}");
        }
        other => panic!("expected BadMetadata, got {:?}", other.map(|_| ())),
    }
    m.remove("act_mode");
    vdd_nn::io::save_safetensors(&p, &moe, &m).unwrap();
    assert!(matches!(Moe::load(&p), Err(MoeError::MissingMetadata { .. })));
}
