//! The imported U-Nets against the outputs LeRobot and diffusion_policy recorded.

use std::path::{Path, PathBuf};

use faer::Mat;
use vdd_core::{Policy, ScoreModel};
use vdd_import::convert::{lerobot_to_file, lerobot_to_file_with};
use vdd_import::fixture::{check_unet_fixture, check_unet_fixture_with};
use vdd_import::{
    ImportError, ImportedTeacher, LerobotOptions, ObsMap, Sampler, import_lerobot,
    import_lerobot_with, load_teacher, save_unet_teacher,
};

const TOL: f32 = 1e-4;

fn fixture(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/import").join(name)
}

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("vdd-import-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    d
}

fn check(name: &str) {
    let (_, c) = check_unet_fixture(&fixture(name)).unwrap();
    assert!(c.unet_max_abs_diff < TOL, "{name}: U-Net differs by {}", c.unet_max_abs_diff);
    assert!(c.sample_max_abs_diff < TOL, "{name}: sampling differs by {}", c.sample_max_abs_diff);
}

#[test]
fn lerobot_ddpm_epsilon_cosine_film_scale_matches_pytorch() {
    check("lerobot_unet_ddpm");
}

#[test]
fn lerobot_ddim_sample_linear_mean_std_matches_pytorch() {
    check("lerobot_unet_ddim");
}

#[test]
fn diffusion_policy_lowdim_unet_matches_pytorch() {
    check("diffusion_policy_unet");
}

#[test]
fn the_teacher_file_round_trips_and_acts_as_score_model_and_policy() {
    let dir = scratch("roundtrip");
    let mut t = import_lerobot(&fixture("lerobot_unet_ddpm")).unwrap();
    let path = dir.join("teacher.safetensors");
    save_unet_teacher(&path, &t).unwrap();
    let mut back = load_teacher(&path).unwrap();
    let (n, ad, sd) = (3, ScoreModel::action_dim(&t), ScoreModel::state_dim(&t));
    assert_eq!((ScoreModel::action_dim(&back), back.state_dim()), (ad, sd));
    let a = Mat::from_fn(n, ad, |i, j| ((i * 7 + j) % 5) as f32 * 0.2 - 0.4);
    let s = Mat::from_fn(n, sd, |i, j| ((i + 3 * j) % 4) as f32 * 0.3 - 0.5);
    let levels = [1.0, 30.0, 100.0];
    let (mut x, mut y) = (Mat::zeros(n, ad), Mat::zeros(n, ad));
    t.score(a.as_ref(), s.as_ref(), &levels, x.as_mut()).unwrap();
    back.score(a.as_ref(), s.as_ref(), &levels, y.as_mut()).unwrap();
    assert_eq!(x, y);
    assert!(x.col_iter().all(|c| c.iter().all(|v| v.is_finite())));
    // A fork (chunks of VDD's batch on several threads) scores bit for bit the same.
    let mut fork = back.fork().expect("imported U-Nets fork");
    fork.score(a.as_ref(), s.as_ref(), &levels, y.as_mut()).unwrap();
    assert_eq!(x, y);
    assert_eq!(back.noise_range(), Some((1.0, 100.0)));
    // Step by step on raw observations: a chunk of n_action_steps actions, then a new one.
    let mut policy = back.into_policy().unwrap();
    policy.seed(3);
    let od = policy.obs_dim();
    assert_eq!((od, policy.action_dim()), (7, 2));
    for _ in 0..10 {
        let act = policy.act(&vec![0.2; od]).unwrap();
        assert!(act.iter().all(|v| v.is_finite()));
    }
    std::fs::remove_dir_all(dir).unwrap();
}

fn copy_fixture(name: &str, to: &Path) {
    for e in std::fs::read_dir(fixture(name)).unwrap() {
        let e = e.unwrap();
        std::fs::copy(e.path(), to.join(e.file_name())).unwrap();
    }
}

#[test]
fn malformed_lerobot_directories_are_refused_naming_the_key() {
    let dir = scratch("malformed");
    copy_fixture("lerobot_unet_ddpm", &dir);
    let cfg = std::fs::read_to_string(dir.join("config.json")).unwrap();
    let edit = |from: &str, to: &str| {
        std::fs::write(dir.join("config.json"), cfg.replacen(from, to, 1)).unwrap();
        import_lerobot(&dir).unwrap_err()
    };
    let e = edit("\"horizon\"", "\"horizon_\"");
    assert!(matches!(&e, ImportError::MissingKey { key, .. } if key == "horizon"), "{e}");
    let e = edit("\"squaredcos_cap_v2\"", "\"sigmoid\"");
    assert!(e.to_string().contains("beta_schedule"), "{e}");
    let e = edit("\"down_dims\": [\n        16,", "\"down_dims\": [\n        24,");
    assert!(e.to_string().contains("diffusion.unet."), "{e}");
    // A tensor missing from the weights.
    std::fs::write(dir.join("config.json"), &cfg).unwrap();
    let w = std::fs::read(dir.join("model.safetensors")).unwrap();
    let st = safetensors::SafeTensors::deserialize(&w).unwrap();
    let gone = "diffusion.unet.mid_modules.1.conv2.block.1.bias";
    let kept: Vec<(String, safetensors::tensor::TensorView<'_>)> =
        st.tensors().into_iter().filter(|(k, _)| k != gone).collect();
    std::fs::write(dir.join("model.safetensors"), safetensors::serialize(kept, None).unwrap())
        .unwrap();
    let e = import_lerobot(&dir).unwrap_err();
    assert!(e.to_string().contains(gone), "{e}");
    // Non-finite statistics.
    copy_fixture("lerobot_unet_ddpm", &dir);
    let f = dir.join("policy_preprocessor_step_3_normalizer_processor.safetensors");
    let b = std::fs::read(&f).unwrap();
    let st = safetensors::SafeTensors::deserialize(&b).unwrap();
    let nan = [f32::NAN; 4].iter().flat_map(|v| v.to_le_bytes()).collect::<Vec<u8>>();
    let mut ts: Vec<(String, safetensors::tensor::TensorView<'_>)> = st.tensors();
    for (k, v) in ts.iter_mut() {
        if k == "observation.state.min" {
            *v = safetensors::tensor::TensorView::new(safetensors::Dtype::F32, vec![4], &nan)
                .unwrap();
        }
    }
    std::fs::write(&f, safetensors::serialize(ts, None).unwrap()).unwrap();
    let e = import_lerobot(&dir).unwrap_err();
    assert!(e.to_string().contains("observation.state"), "{e}");
    std::fs::remove_dir_all(dir).unwrap();
}

/// A copy of the DDIM-10 fixture whose `config.json` says DDPM over the 100 trained steps.
fn ddim_fixture_saying_ddpm(name: &str) -> PathBuf {
    let dir = scratch(name);
    copy_fixture("lerobot_unet_ddim", &dir);
    let cfg = std::fs::read_to_string(dir.join("config.json")).unwrap();
    let cfg = cfg
        .replacen("\"noise_scheduler_type\": \"DDIM\"", "\"noise_scheduler_type\": \"DDPM\"", 1)
        .replacen("\"num_inference_steps\": 10", "\"num_inference_steps\": null", 1);
    std::fs::write(dir.join("config.json"), cfg).unwrap();
    dir
}

#[test]
fn ddim_chosen_at_run_time_matches_the_recorded_ddim_run() {
    let dir = ddim_fixture_saying_ddpm("sampler");
    let teacher = import_lerobot(&dir).unwrap();
    assert_eq!(teacher.spec().sampler(), Sampler::Ddpm { steps: None });
    // As the file says (DDPM-100), it is not the recorded DDIM-10 run.
    let as_file = check_unet_fixture_with(&dir, teacher.clone());
    assert!(as_file.map_or(true, |(_, c)| c.sample_max_abs_diff > TOL));
    // DDIM-10 chosen on the loaded teacher ...
    let (_, c) =
        check_unet_fixture_with(&dir, teacher.with_sampler(Sampler::Ddim { steps: 10 }).unwrap())
            .unwrap();
    assert!(c.sample_max_abs_diff < TOL, "{}", c.sample_max_abs_diff);
    // ... at import, and on a teacher file after loading it.
    let opts = LerobotOptions { sampler: Some("ddim:10".parse().unwrap()), obs_map: None };
    let (_, c) = check_unet_fixture_with(&dir, import_lerobot_with(&dir, &opts).unwrap()).unwrap();
    assert!(c.sample_max_abs_diff < TOL, "{}", c.sample_max_abs_diff);
    let path = dir.join("teacher.safetensors");
    save_unet_teacher(&path, &import_lerobot(&dir).unwrap()).unwrap();
    let mut loaded = load_teacher(&path).unwrap();
    assert_eq!(loaded.sampler(), Sampler::Ddpm { steps: None });
    loaded.set_sampler(Sampler::Ddim { steps: 10 }).unwrap();
    assert_eq!(loaded.sampler(), Sampler::Ddim { steps: 10 });
    let ImportedTeacher::Unet1d(t) = loaded;
    let (_, c) = check_unet_fixture_with(&dir, *t).unwrap();
    assert!(c.sample_max_abs_diff < TOL, "{}", c.sample_max_abs_diff);
    // A step count the schedule does not have is refused, naming the sampler.
    let e = import_lerobot(&dir).unwrap().with_sampler(Sampler::Ddim { steps: 101 }).unwrap_err();
    assert!(e.to_string().contains("ddim:101"), "{e}");
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn a_reordered_observation_map_acts_as_the_recorded_run_and_is_stored() {
    // The fixture's policy: observation.state [4], observation.environment_state [3]. The
    // user's raw observation (8 wide) holds the env state first, then the state scrambled,
    // then an entry the policy does not use.
    let dir = fixture("lerobot_unet_ddim");
    let map: ObsMap =
        "raw_dim=8;observation.environment_state=0..3;observation.state=6,3,5,4".parse().unwrap();
    let opts = LerobotOptions { obs_map: Some(map.clone()), sampler: None };
    let teacher = import_lerobot_with(&dir, &opts).unwrap();
    assert_eq!(teacher.spec().raw_obs_dim(), 8);
    assert_eq!(Policy::obs_dim(&teacher), 8);
    let (teacher, c) = check_unet_fixture_with(&dir, teacher).unwrap();
    assert!(c.sample_max_abs_diff < TOL, "{}", c.sample_max_abs_diff);
    // Stored in the teacher file, said in the summary, and applied after loading.
    let out = scratch("obsmap");
    let path = out.join("teacher.safetensors");
    let summary = lerobot_to_file_with(&dir, &path, &opts).unwrap();
    assert!(
        summary.contains("observation.state=6,3,5,4;observation.environment_state=0,1,2"),
        "{summary}"
    );
    let ImportedTeacher::Unet1d(loaded) = load_teacher(&path).unwrap();
    assert_eq!(loaded.spec().obs_map.as_ref(), teacher.spec().obs_map.as_ref());
    let (_, c) = check_unet_fixture_with(&dir, *loaded).unwrap();
    assert!(c.sample_max_abs_diff < TOL, "{}", c.sample_max_abs_diff);
    // Without a stated map the summary says the in-order layout it assumed.
    let summary = lerobot_to_file(&dir, &path).unwrap();
    assert!(summary.contains("none stated"), "{summary}");
    std::fs::remove_dir_all(out).unwrap();
}

#[test]
fn observation_maps_that_do_not_fit_are_refused_naming_the_key() {
    let dir = fixture("lerobot_unet_ddim");
    let refuse = |m: &str, key: &str, what: &str| {
        let e = match m.parse::<ObsMap>() {
            Err(e) => e,
            Ok(map) => {
                let opts = LerobotOptions { obs_map: Some(map), sampler: None };
                import_lerobot_with(&dir, &opts).unwrap_err()
            }
        };
        assert!(matches!(e, ImportError::BadValue { .. }), "{m}: {e}");
        let s = e.to_string();
        assert!(s.contains(key) && s.contains(what), "{m}: {s}");
    };
    // Out of range, repeated within a feature, a count that is not the feature's shape, a
    // feature left out, a key the policy does not have.
    refuse(
        "raw_dim=7;observation.state=3..7;observation.environment_state=0,1,7",
        "observation.environment_state",
        "out of range",
    );
    refuse(
        "observation.state=3,4,5,5;observation.environment_state=0..3",
        "observation.state",
        "repeated",
    );
    refuse(
        "observation.state=3..6;observation.environment_state=0..3",
        "obs_map.observation.state",
        "3 indices for a feature of shape [4]",
    );
    refuse("observation.state=0..4", "obs_map.observation.environment_state", "not mapped");
    refuse(
        "observation.state=0..4;observation.environment_state=4..7;observation.images=7",
        "obs_map.observation.images",
        "not a feature of the policy",
    );
}
