//! Hostile files and settings: refused with errors naming what is wrong, before anything
//! large is allocated; no panic, abort or non-finite action.

use super::*;
use vdd_core::{CoreError, Policy};

pub(super) fn scratch(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("vdd-moe-hostile-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

/// Saves `moe` with its metadata entry `key` edited by `edit` (a JSON value), then loads it.
pub(super) fn load_edited(
    moe: &Moe,
    name: &str,
    key: &str,
    edit: impl FnOnce(&mut serde_json::Value),
) -> Result<Moe, MoeError> {
    let path = scratch(&format!("{name}-base.safetensors"));
    moe.save(&path).unwrap();
    let mut meta = vdd_nn::io::read_metadata(&path).unwrap();
    let mut v: serde_json::Value = serde_json::from_str(&meta[key]).unwrap();
    edit(&mut v);
    meta.insert(key.to_owned(), v.to_string());
    let edited = scratch(&format!("{name}.safetensors"));
    vdd_nn::io::save_safetensors(&edited, moe, &meta).unwrap();
    Moe::load(&edited)
}

#[test]
fn a_config_asking_for_more_than_the_file_holds_is_refused_before_building() {
    let moe = built(MoeConfig::toy(2, 2, 4), 1);
    // 65536 wide: 17 GB if built; the file holds a few thousand values.
    let e =
        load_edited(&moe, "wide", "config", |c| c["experts_network"]["hidden_dim"] = 65536.into())
            .unwrap_err();
    let msg = e.to_string();
    assert!(msg.contains("wide.safetensors") && msg.contains("parameters"), "{msg}");
    // Sizes whose products overflow, and counts beyond the documented limits.
    for (key, value) in [
        ("num_experts", serde_json::json!(4_611_686_018_427_387_905u64)),
        ("num_experts", serde_json::json!(100_000_000)),
        ("state_dim", serde_json::json!(u64::MAX)),
        ("action_dim", serde_json::json!(1u64 << 62)),
    ] {
        let e = load_edited(&moe, key, "config", |c| c[key] = value.clone()).unwrap_err();
        assert!(e.to_string().contains(key), "{key}: {e}");
    }
    let e = load_edited(&moe, "blocks", "config", |c| {
        c["experts_network"]["num_blocks"] = 1_000_000.into()
    })
    .unwrap_err();
    assert!(e.to_string().contains("num_blocks"), "{e}");
}

#[test]
fn settings_whose_use_overflows_are_refused() {
    for (what, cfg) in [
        ("mean_bias_init", MoeConfig { mean_bias_init: 3.4e38, ..MoeConfig::toy(1, 2, 4) }),
        ("mean_bias_init", MoeConfig { mean_bias_init: f32::INFINITY, ..MoeConfig::toy(1, 2, 4) }),
        ("num_experts", MoeConfig { num_experts: (1 << 62) + 1, ..MoeConfig::toy(1, 2, 4) }),
        ("init_std", MoeConfig { init_std: 3e38, ..MoeConfig::toy(1, 2, 4) }),
    ] {
        let e = Moe::from_config(cfg, 0).unwrap_err();
        assert!(e.to_string().contains(what), "{what}: {e}");
    }
    // The largest accepted bias half-width initialises without overflow.
    let cfg =
        MoeConfig { mean_bias_init: vdd_nn::limits::MAX_ABS_WEIGHT, ..MoeConfig::toy(1, 2, 4) };
    assert!(Moe::from_config(cfg, 0).is_ok());
}

#[test]
fn a_damaged_family_fingerprint_is_an_error_not_a_panic() {
    let moe = built(MoeConfig::toy(2, 3, 4), 2);
    for probes in [serde_json::json!([]), serde_json::json!([[0.5]]), serde_json::json!([[]])] {
        let e = load_edited(&moe, "fingerprint", "expert_family", |f| f["probes"] = probes.clone())
            .unwrap_err();
        assert!(matches!(e, MoeError::FamilyMismatch(_)), "{e}");
    }
    let e = load_edited(&moe, "fingerprint-dim", "expert_family", |f| {
        f["action_dim"] = u64::MAX.into()
    })
    .unwrap_err();
    assert!(matches!(e, MoeError::FamilyMismatch(_)), "{e}");
}

/// Replaces the one occurrence of `from`'s bytes in the file `path` by `to`'s (to write a value
/// that `Moe::save` refuses).
fn patch_f32(path: &std::path::Path, from: f32, to: f32) {
    let mut bytes = std::fs::read(path).unwrap();
    let at = bytes.windows(4).position(|w| w == from.to_le_bytes()).unwrap();
    bytes[at..at + 4].copy_from_slice(&to.to_le_bytes());
    std::fs::write(path, bytes).unwrap();
}

#[test]
fn weights_beyond_the_limit_are_refused_and_overflowing_actions_are_errors() {
    let mut moe = built(MoeConfig::toy(2, 2, 4), 3);
    edit_expert_bias(&mut moe, |_, k, b| {
        if k == 0 {
            *b = 0.123_456_7;
        }
    });
    let path = scratch("huge-weight.safetensors");
    moe.save(&path).unwrap();
    patch_f32(&path, 0.123_456_7, 3.4e38);
    let e = Moe::load(&path).unwrap_err().to_string();
    assert!(e.contains("huge-weight.safetensors") && e.contains("3.4e38"), "{e}");

    // Weights and normalisers within their bounds can still overflow through the network and
    // the normaliser: an error, not an infinite action.
    let mut moe = built(MoeConfig::toy(2, 2, 4), 3);
    moe.expert_networks_mut().visit_params_mut("", &mut |_, p| p.value.fill(1e6));
    let wide = Affine::new(vec![0.0, 0.0], vec![1e6, 1e6]).unwrap();
    let obs_norm = moe.normalizers().0.cloned();
    moe.set_normalizers(obs_norm, Some(wide)).unwrap();
    let e = moe.act(&[1e5, 1e5]).unwrap_err();
    assert!(matches!(e, CoreError::NonFinite { .. }), "{e}");
    let mut out = Mat::<f32>::zeros(2, 2);
    let obs = Mat::from_fn(2, 2, |_, _| 1e5f32);
    assert!(matches!(moe.act_batch(obs.as_ref(), out.as_mut()), Err(CoreError::NonFinite { .. })));
}
