//! A teacher imported with an observation map rolls out on the task's raw observations, and a
//! VDD student of it, which cannot carry the map yet, is refused before anything trains.

use std::path::{Path, PathBuf};

use vdd_lab::Registry;
use vdd_lab::experiment::{Request, run_with};

fn temp_dir(tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("vdd-lab-imported-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    dir
}

/// The LeRobot fixture (7-D observation) imported with a map from Avoiding's 4-D observation.
fn mapped_teacher(dir: &Path) -> PathBuf {
    let fixture =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/import/lerobot_unet_ddpm");
    let obs_map = "raw_dim=4;observation.state=0,1,2,3;observation.environment_state=0,1,2";
    let options = vdd_import::LerobotOptions {
        obs_map: Some(obs_map.parse().unwrap()),
        sampler: Some("ddim:2".parse().unwrap()),
    };
    let file = dir.join("teacher.safetensors");
    vdd_import::convert::lerobot_to_file_with(&fixture, &file, &options).unwrap();
    file
}

fn run(dir: &Path, teacher: &Path, methods: &str) -> vdd_lab::Result {
    let overrides = vdd_lab::recipe::Overrides {
        quick: true,
        methods: Some(methods.split(',').map(String::from).collect()),
        sets: vec![("eval.rollouts".into(), "4".into()), ("eval.curve_points".into(), "0".into())],
        ..Default::default()
    };
    let request = Request {
        recipe: "avoiding".into(),
        overrides,
        shorthands: vec![("teacher".into(), teacher.to_str().unwrap().to_owned())],
        out: Some(dir.join("run")),
        command: "tests/imported_teacher.rs".into(),
        ..Default::default()
    };
    run_with(&Registry::builtin(), &request)
}

#[test]
fn a_mapped_teacher_rolls_out_and_its_student_is_refused_naming_the_map() {
    let dir = temp_dir("mapped");
    let teacher = mapped_teacher(&dir);
    let e = run(&dir, &teacher, "teacher,vdd").unwrap_err().to_string();
    assert!(e.contains("observation map") && e.contains("--methods teacher"), "{e}");
    assert!(!dir.join("run").exists(), "refused before anything is written");
    run(&dir, &teacher, "teacher").unwrap_or_else(|e| panic!("{e}"));
    let metrics = std::fs::read_to_string(dir.join("run/metrics.json")).unwrap();
    assert!(metrics.contains("\"lerobot\""), "{metrics}");
    std::fs::remove_dir_all(&dir).unwrap();
}
