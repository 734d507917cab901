//! The components in raw action space: they give the policy's likelihood and greedy action.

use super::*;

/// `log Σ_z q(z|s) N(a; μ_z, L_z L_zᵀ)` from the components, in f64.
fn mixture_log_density(c: &Components, b: usize, a: &[f32]) -> f64 {
    let (z, d) = (c.num_experts, c.action_dim);
    let mut terms = Vec::new();
    for e in 0..z {
        let k = b * z + e;
        let mu = &c.means[k * d..(k + 1) * d];
        let l = &c.scale_tril[k * d * d..(k + 1) * d * d];
        // Forward substitution L y = a − μ.
        let mut y = vec![0.0f64; d];
        let mut log_det = 0.0;
        for i in 0..d {
            let mut s = f64::from(a[i] - mu[i]);
            for j in 0..i {
                s -= f64::from(l[i * d + j]) * y[j];
            }
            y[i] = s / f64::from(l[i * d + i]);
            log_det += f64::from(l[i * d + i]).ln();
        }
        let q: f64 = y.iter().map(|v| v * v).sum();
        let log_n = -0.5 * q - log_det - 0.5 * d as f64 * (2.0 * std::f64::consts::PI).ln();
        terms.push(f64::from(c.log_gating[k]) + log_n);
    }
    let m = terms.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    m + terms.iter().map(|t| (t - m).exp()).sum::<f64>().ln()
}

#[test]
fn components_give_the_likelihood_and_the_greedy_action_in_raw_space() {
    for cfg in all_configs(3, 2) {
        let mut moe = Moe::from_config(cfg.clone(), 5).unwrap();
        moe.set_normalizers(
            Some(Affine::new(vec![0.5, -1.0, 2.0], vec![2.0, 0.5, 3.0]).unwrap()),
            Some(Affine::new(vec![10.0, -3.0], vec![4.0, 0.25]).unwrap()),
        )
        .unwrap();
        moe.set_act_mode(ActMode { greedy_gating: true, sample_action: false, hold_steps: 0 });
        let obs = faer::mat![[0.3f32, -0.2, 1.0], [1.5, 0.7, -2.0]];
        let actions = faer::mat![[11.0f32, -2.9], [8.0, -3.2]];
        let c = moe.components(obs.as_ref()).unwrap();
        assert_eq!((c.n, c.num_experts, c.action_dim), (2, 3, 2));
        let mut ll = [0.0f32; 2];
        moe.log_likelihood(obs.as_ref(), actions.as_ref(), &mut ll).unwrap();
        for b in 0..2 {
            let a = [actions[(b, 0)], actions[(b, 1)]];
            let want = mixture_log_density(&c, b, &a);
            assert!((f64::from(ll[b]) - want).abs() < 1e-3, "{cfg:?}: {} vs {want}", ll[b]);
            let lg = &c.log_gating[b * 3..(b + 1) * 3];
            let z = (0..3).fold(0, |best, k| if lg[k] > lg[best] { k } else { best });
            let action = moe.act(&[obs[(b, 0)], obs[(b, 1)], obs[(b, 2)]]).unwrap();
            for j in 0..2 {
                let mean = c.means[(b * 3 + z) * 2 + j];
                assert!((action[j] - mean).abs() < 1e-5, "{cfg:?}: {action:?} vs {mean}");
            }
        }
    }
}

#[test]
fn deployed_components_apply_the_feature_map_to_each_window_slot() {
    let cfg = config(8, 2, ExpertKind::Full, GatingKind::Learned, true);
    let mut moe = Moe::from_config(cfg, 1).unwrap();
    let spec = DeploySpec { obs_window: 2, ..DeploySpec::identity() }
        .with_features(vdd_data::features::POSITION_AND_LAG);
    moe.set_deploy_spec(spec).unwrap();
    let mut direct = moe.clone();
    let mut policy = moe.into_policy().unwrap();
    let windows = faer::mat![[1.0f32, 2.0, 0.5, 1.0, 3.0, 4.0, 2.0, 5.0]];
    let c = deployed_components(&mut policy, windows.as_ref()).unwrap();
    // (d, c) ↦ (c, d − c) per slot of four.
    let featured = faer::mat![[0.5f32, 1.0, 0.5, 1.0, 2.0, 5.0, 1.0, -1.0]];
    assert_eq!(c, direct.components(featured.as_ref()).unwrap());
    let err = deployed_components(&mut policy, faer::mat![[1.0f32, 2.0]].as_ref()).unwrap_err();
    assert!(err.to_string().contains("observation windows"), "{err}");
}
