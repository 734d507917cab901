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
        let mode = ActMode { greedy_gating: false, sample_action: true };
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
