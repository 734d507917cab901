//! What `cargo xtask experiment avoiding --teacher FILE` takes from an imported teacher: the
//! recorded feature map, the samples it was trained on, its space and the student's deployment
//! spec (executed from `n_obs_steps − 1`), through a saved teacher file.

use std::path::{Path, PathBuf};

use faer::Mat;
use vdd_core::ScoreModel;
use vdd_data::Episodes;
use vdd_data::features::FeatureMapId;
use vdd_import::{FEATURES_FILE, ImportedTeacher, import_lerobot, load_teacher, save_unet_teacher};

/// A copy of the LeRobot DDPM fixture (window 2, horizon 16, 8 executed; 4 + 3 observation
/// features, 2-D actions), with `features` as its feature-map file when given.
fn fixture_copy(name: &str, features: Option<&str>) -> PathBuf {
    let src =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/import/lerobot_unet_ddpm");
    let d = std::env::temp_dir().join(format!("vdd-import-distil-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    std::fs::create_dir_all(&d).unwrap();
    for f in std::fs::read_dir(&src).unwrap() {
        let f = f.unwrap();
        std::fs::copy(f.path(), d.join(f.file_name())).unwrap();
    }
    if let Some(json) = features {
        std::fs::write(d.join(FEATURES_FILE), json).unwrap();
    }
    d
}

#[test]
fn the_feature_map_and_the_offset_chunk_spec_survive_the_teacher_file() {
    let dir = fixture_copy("identity", Some(r#"{"name": "identity", "version": 1}"#));
    let teacher = import_lerobot(&dir).unwrap();
    assert_eq!(teacher.spec().features, FeatureMapId::new("identity", 1));
    let path = dir.join("teacher.safetensors");
    save_unet_teacher(&path, &teacher).unwrap();
    let ImportedTeacher::Unet1d(loaded) = load_teacher(&path).unwrap();
    assert_eq!(loaded.spec(), teacher.spec());
    let spec = loaded.chunk_deploy_spec();
    assert_eq!(
        (spec.obs_window, spec.action_chunk, spec.chunk_start, spec.execute_steps),
        (2, 16, 1, 8),
        "LeRobot executes 8 actions from index n_obs_steps − 1"
    );
    // A student emitting the whole chunk (state: the 2 × 7 window, action: 16 × 2) fits it.
    spec.check_policy_dims(loaded.state_dim(), ScoreModel::action_dim(&*loaded)).unwrap();
    assert_eq!(spec, teacher.chunk_deploy_spec());
    assert_eq!(loaded.deploy_spec().features, spec.features);
}

#[test]
fn feature_map_files_that_do_not_fit_are_refused_naming_the_map() {
    for (name, json, want) in [
        ("unknown", r#"{"name": "lag", "version": 1}"#, "unknown feature map `lag`"),
        ("odd", r#"{"name": "position_and_lag", "version": 1}"#, "position_and_lag v1"),
        ("junk", r#"{"name": 3}"#, FEATURES_FILE),
    ] {
        let e = import_lerobot(&fixture_copy(name, Some(json))).unwrap_err().to_string();
        assert!(e.contains(want), "{name}: {e}");
    }
    // Without the file, the policy sees raw observations.
    let t = import_lerobot(&fixture_copy("none", None)).unwrap();
    assert!(t.spec().features.resolve().unwrap().is_identity());
}

#[test]
fn training_windows_and_teacher_space_are_the_teachers_own_inputs() {
    let teacher = import_lerobot(&fixture_copy("windows", None)).unwrap();
    // One episode of 5 steps: observation t is 0.1 t + j / 10, action t is (t, −t).
    let obs = Mat::from_fn(5, 7, |t, j| 0.1 * t as f32 + j as f32 / 10.0);
    let act = Mat::from_fn(5, 2, |t, j| if j == 0 { t as f32 } else { -(t as f32) });
    let episodes = Episodes::from_episodes(vec![obs.clone()], vec![act]).unwrap();
    let (states, chunks) = teacher.training_windows(&episodes).unwrap();
    assert_eq!((states.nrows(), states.ncols(), chunks.ncols()), (5, 14, 32));
    // Step 0: the window repeats observation 0; the chunk starts at action 0 (clamped from −1)
    // and runs to the last action, repeated.
    assert_eq!((states[(0, 0)], states[(0, 7)]), (obs[(0, 0)], obs[(0, 0)]));
    let firsts: Vec<f32> = (0..16).map(|k| chunks[(0, 2 * k)]).collect();
    assert_eq!(&firsts[..6], &[0.0, 0.0, 1.0, 2.0, 3.0, 4.0]);
    assert!(firsts[6..].iter().all(|&x| x == 4.0));
    // Step 3: observations 2, 3; actions from 2.
    assert_eq!((states[(3, 0)], states[(3, 7)]), (obs[(2, 0)], obs[(3, 0)]));
    assert_eq!((chunks[(3, 0)], chunks[(3, 1)], chunks[(3, 2)]), (2.0, -2.0, 3.0));

    // The space: exactly the teacher's normalisation of a window.
    let (sn, an) = teacher.teacher_space().unwrap();
    assert_eq!((sn.dim(), an.dim()), (14, 32));
    let mapped = sn.normalize_rows(states.as_ref()).unwrap();
    let mut window: Vec<f32> = (0..14).map(|j| states[(3, j)]).collect();
    teacher.normalize_obs_window(&mut window);
    for (j, w) in window.iter().enumerate() {
        assert!((mapped[(3, j)] - w).abs() < 1e-5, "{j}: {} vs {w}", mapped[(3, j)]);
    }
    let mut wrong =
        Episodes::from_episodes(vec![Mat::zeros(3, 4)], vec![Mat::zeros(3, 2)]).unwrap();
    assert!(teacher.training_windows(&wrong).is_err());
    wrong = Episodes::from_episodes(vec![Mat::zeros(3, 7)], vec![Mat::zeros(3, 3)]).unwrap();
    assert!(teacher.training_windows(&wrong).is_err());
}
