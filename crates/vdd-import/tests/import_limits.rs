//! Regression tests of issue 36: an importer checks a config's architecture sizes against
//! `vdd_nn::limits` before building anything, and refuses deeply nested YAML/JSON at once.

use std::path::{Path, PathBuf};
use std::sync::mpsc;
use std::time::Duration;

use vdd_nn::Parameters;

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/import")
}

/// A copy of fixture directory `name` under a fresh temporary directory.
fn copy_fixture(name: &str, tag: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("vdd-import-limits-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    for entry in std::fs::read_dir(fixtures().join(name)).unwrap() {
        let entry = entry.unwrap();
        std::fs::copy(entry.path(), dir.join(entry.file_name())).unwrap();
    }
    dir
}

/// Runs `f` on another thread and fails the test if it takes longer than `secs`.
fn bounded<T: Send + 'static>(secs: u64, f: impl FnOnce() -> T + Send + 'static) -> T {
    let (tx, rx) = mpsc::channel();
    std::thread::spawn(move || {
        let _ = tx.send(f());
    });
    rx.recv_timeout(Duration::from_secs(secs)).expect("the import must not hang")
}

fn edit_json(path: &Path, edit: impl FnOnce(&mut serde_json::Value)) {
    let mut v: serde_json::Value =
        serde_json::from_str(&std::fs::read_to_string(path).unwrap()).unwrap();
    edit(&mut v);
    std::fs::write(path, serde_json::to_string_pretty(&v).unwrap()).unwrap();
}

/// Before: `down_dims[0] = 65536` built the U-Net (86 GB requested, SIGABRT).
#[test]
fn lerobot_down_dims_past_the_parameter_limit_is_refused_before_building() {
    let dir = copy_fixture("lerobot_unet_ddim", "lerobot-wide");
    let cfg = dir.join("config.json");
    edit_json(&cfg, |v| v["down_dims"][0] = 65536.into());
    let e = vdd_import::import_lerobot(&dir).unwrap_err().to_string();
    assert!(e.contains("config.json") && e.contains("down_dims") && e.contains("65536"), "{e}");
    assert!(e.contains("parameters"), "{e}");
    for (key, value) in [("kernel_size", 100_001u64), ("horizon", 1 << 20)] {
        std::fs::copy(fixtures().join("lerobot_unet_ddim/config.json"), &cfg).unwrap();
        edit_json(&cfg, |v| v[key] = value.into());
        let e = vdd_import::import_lerobot(&dir).unwrap_err().to_string();
        assert!(
            e.contains("config.json") && e.contains(key) && e.contains(&value.to_string()),
            "{e}"
        );
    }
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn diffusion_policy_down_dims_past_the_parameter_limit_is_refused() {
    let dir = copy_fixture("diffusion_policy_unet", "dp-wide");
    let cfg = dir.join("config.json");
    edit_json(&cfg, |v| v["policy"]["model"]["down_dims"] = serde_json::json!([65536, 65536]));
    let e = vdd_import::import_diffusion_policy(&dir).unwrap_err().to_string();
    assert!(e.contains("config.json") && e.contains("down_dims") && e.contains("65536"), "{e}");
    std::fs::remove_dir_all(dir).unwrap();
}

/// The arithmetic parameter count is the built network's, for every U-Net fixture.
#[test]
fn unet_parameter_count_matches_the_built_network() {
    for name in ["lerobot_unet_ddim", "lerobot_unet_ddpm", "diffusion_policy_unet"] {
        let mut teacher = vdd_import::fixture::import_fixture(&fixtures().join(name)).unwrap();
        let want = vdd_import::limits::unet_params(&teacher.spec().unet.clone()).unwrap();
        let mut have = 0;
        teacher.unet_mut().visit_params("", &mut |_, p| have += p.value.len());
        assert_eq!(want, have, "{name}");
    }
}

#[test]
fn beso_and_transformer_sizes_past_the_limits_are_refused() {
    let path = fixtures().join("beso_gpt.yaml");
    let yaml = std::fs::read_to_string(&path).unwrap();
    let (from, to) = ("embed_dim: ", "embed_dim: 65536 #");
    assert!(yaml.contains(from));
    let wide = yaml.replacen(from, to, 1);
    let e = vdd_import::beso_config_from_yaml(&path, &wide, None).unwrap_err().to_string();
    assert!(e.contains("beso_gpt.yaml") && e.contains("embed_dim") && e.contains("65536"), "{e}");

    let model = serde_json::json!({"input_dim": 2, "output_dim": 2, "horizon": 8,
        "n_layer": 1024, "n_head": 8, "n_emb": 4096});
    let e = vdd_import::dp_transformer_config("cfg.json", &model).unwrap_err().to_string();
    assert!(e.contains("cfg.json") && e.contains("n_emb") && e.contains("parameters"), "{e}");
}

/// Before: a 100,000-deep flow sequence hung the BESO import.
#[test]
fn deep_yaml_is_refused_quickly() {
    let dir = std::env::temp_dir().join(format!("vdd-import-deep-yaml-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&dir);
    std::fs::create_dir_all(&dir).unwrap();
    let deep = format!("agents: {}{}\n", "[".repeat(100_000), "]".repeat(100_000));
    std::fs::write(dir.join("config.yaml"), deep).unwrap();
    let run = dir.clone();
    let e = bounded(20, move || vdd_import::import_beso_run(&run).map(drop)).unwrap_err();
    let e = e.to_string();
    assert!(e.contains("config.yaml") && e.contains("nest"), "{e}");
    std::fs::remove_dir_all(dir).unwrap();
}

#[test]
fn deep_json_is_refused_quickly() {
    let dir = copy_fixture("lerobot_unet_ddim", "deep-json");
    let deep = format!("{{\"type\": {}1{}}}", "[".repeat(100_000), "]".repeat(100_000));
    std::fs::write(dir.join("config.json"), deep).unwrap();
    let run = dir.clone();
    let e = bounded(20, move || vdd_import::import_lerobot(&run).map(drop)).unwrap_err();
    let e = e.to_string();
    assert!(e.contains("config.json") && e.contains("nesting"), "{e}");
    std::fs::remove_dir_all(dir).unwrap();
}
