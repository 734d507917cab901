//! What `Moe::save` writes, `Moe::load` reads: the writer checks the loader's rules, the same
//! model gives the same bytes, and values that would act or score non-finite are refused.

use super::hostile::{load_edited, scratch};
use super::*;

/// The examples: an offset of 2^63 acted at 1e18, a scale of 1e-38 at 1e38 and gave a
/// log-likelihood of −inf, all with `Ok`. Now the load is refused, naming the file and entry.
#[test]
fn a_normalizer_offset_of_2_pow_63_or_a_scale_of_1e_38_is_refused_at_load() {
    let moe = built(MoeConfig::toy(2, 2, 3), 5);
    let e = load_edited(&moe, "offset", "obs_normalizer", |n| {
        n["offset"][0] = serde_json::json!(9_223_372_036_854_775_808.0f64)
    })
    .unwrap_err()
    .to_string();
    assert!(e.contains("offset.safetensors") && e.contains("obs_normalizer"), "{e}");
    assert!(e.contains("9.223372e18"), "{e}");
    let e = load_edited(&moe, "scale", "action_normalizer", |n| {
        n["scale"][1] = serde_json::json!(1e-38)
    })
    .unwrap_err()
    .to_string();
    assert!(e.contains("scale.safetensors") && e.contains("action_normalizer"), "{e}");
    assert!(e.contains("1e-38"), "{e}");
    // And a scale of 1e7 or an offset of -2e6 likewise.
    assert!(load_edited(&moe, "big", "obs_normalizer", |n| n["scale"][0] = 1e7.into()).is_err());
    assert!(
        load_edited(&moe, "neg", "action_normalizer", |n| n["offset"][0] = (-2e6).into()).is_err()
    );
    // The bounds themselves load.
    let m = load_edited(&moe, "edge", "obs_normalizer", |n| {
        n["offset"][0] = (-1e6).into();
        n["scale"][0] = 1e-6.into();
        n["scale"][1] = 1e6.into();
    });
    assert!(m.is_ok(), "{:?}", m.err());
}

/// Before, a student that drifted past |w| = 1e6 was saved, and its own loader refused it.
#[test]
fn save_refuses_what_load_would_refuse_and_writes_nothing() {
    let mut moe = built(MoeConfig::toy(2, 2, 3), 6);
    edit_expert_bias(&mut moe, |z, k, b| {
        if z == 1 && k == 0 {
            *b = -2.5e6;
        }
    });
    let path = scratch("drifted.safetensors");
    let _ = std::fs::remove_file(&path);
    let e = moe.save(&path).unwrap_err().to_string();
    assert!(e.contains("-2.5e6") && e.contains("bias"), "{e}");
    assert!(!path.exists());
    edit_expert_bias(&mut moe, |_, _, b| *b = b.clamp(-1e6, 1e6));
    moe.save(&path).unwrap();
    Moe::load(&path).unwrap();
}

/// Before, the metadata's order came from a `HashMap`: two saves differed.
#[test]
fn two_saves_of_one_model_give_identical_bytes() {
    for cfg in all_configs(2, 3) {
        let moe = built(cfg, 7);
        let (a, b) = (scratch("same-a.safetensors"), scratch("same-b.safetensors"));
        moe.save(&a).unwrap();
        for _ in 0..3 {
            moe.save(&b).unwrap();
            assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
        }
        // Loaded and saved again: the same bytes still.
        Moe::load(&a).unwrap().save(&b).unwrap();
        assert_eq!(std::fs::read(&a).unwrap(), std::fs::read(&b).unwrap());
    }
}

/// Finite observations that overflow once normalised: errors. Before, the likelihood's forward
/// pass ran on infinite states and returned `Ok` with NaN.
#[test]
fn observations_overflowing_the_normaliser_are_errors_not_nan() {
    let mut moe = built(MoeConfig::toy(2, 2, 3), 8);
    let tight = Affine::new(vec![0.0, 0.0], vec![1e-6, 1e-6]).unwrap();
    let act_norm = moe.normalizers().1.cloned();
    moe.set_normalizers(Some(tight), act_norm).unwrap();
    let obs = Mat::from_fn(2, 2, |_, _| 3e38f32);
    let acts = Mat::from_fn(2, 2, |i, j| 0.1 * (i + j) as f32);
    let mut ll = vec![0.0; 2];
    let e = moe.log_likelihood(obs.as_ref(), acts.as_ref(), &mut ll).unwrap_err();
    assert!(matches!(e, CoreError::NonFinite { what: "normalised observations" }), "{e}");
    let mut out = Mat::<f32>::zeros(2, 2);
    assert!(matches!(moe.act_batch(obs.as_ref(), out.as_mut()), Err(CoreError::NonFinite { .. })));
    // Ordinary observations are unaffected.
    let obs = obs_batch(2, 2);
    moe.log_likelihood(obs.as_ref(), acts.as_ref(), &mut ll).unwrap();
    assert!(ll.iter().all(|v| v.is_finite()));
}
