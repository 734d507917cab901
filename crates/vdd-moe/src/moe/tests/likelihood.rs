//! Architecture, likelihood, responsibilities, gating and entropies.

use super::*;

// ---------------------------------------------------------------------------------------
// Architecture.
// ---------------------------------------------------------------------------------------

#[test]
fn shared_trunk_and_separate_networks_have_the_configured_shapes_and_layout() {
    for kind in [ExpertKind::Diagonal, ExpertKind::Full] {
        for shared in [true, false] {
            let cfg = config(2, 3, kind, GatingKind::Learned, shared);
            let mut moe = Moe::from_config(cfg, 1).unwrap();
            let (z, d, r) = (3, 3, moe.expert().raw_dim());
            assert_eq!(r, if kind == ExpertKind::Full { 9 } else { 6 });

            let mut shapes = BTreeMap::new();
            moe.visit_params("", &mut |name, p| {
                shapes.insert(name.to_owned(), p.shape.clone());
            });
            if shared {
                assert_eq!(shapes[&format!("experts.{OUT_LAYER}.weight")], [z * r, 8]);
                assert!(!shapes.contains_key(&format!("experts.0.{OUT_LAYER}.weight")));
            } else {
                for e in 0..z {
                    assert_eq!(shapes[&format!("experts.{e}.{OUT_LAYER}.weight")], [r, 8]);
                    assert_eq!(shapes[&format!("experts.{e}.layers.0.weight")], [8, 2]);
                }
                assert!(!shapes.contains_key(&format!("experts.{OUT_LAYER}.weight")));
            }
            assert_eq!(shapes[&format!("gating.{OUT_LAYER}.weight")], [z, 8]);

            // With zero output weights the raw outputs are the biases: each (state, expert)
            // row must hold its own expert's biases, decoded by the family.
            moe.expert_networks_mut().visit_params_mut("", &mut |name, p| {
                if name.ends_with(&format!("{OUT_LAYER}.weight")) {
                    p.value.fill(0.0);
                }
            });
            edit_expert_bias(&mut moe, |e, c, b| *b = 0.1 * c as f32 - 0.5 * e as f32);
            let n = 4;
            moe.forward(obs_batch(n, 2).as_ref()).unwrap();
            let out = moe.output().clone();
            assert_eq!((out.n, out.num_experts, out.action_dim), (n, z, d));
            assert_eq!(out.raw.len(), n * z * r);
            assert_eq!(out.means.len(), n * z * d);
            assert_eq!(out.scales.len(), n * z * d * d);
            assert_eq!(out.log_gating.len(), n * z);
            let (mut mean, mut scale) = (vec![0.0; d], vec![0.0; d * d]);
            for b in 0..n {
                for e in 0..z {
                    let raw = &out.raw[(b * z + e) * r..(b * z + e + 1) * r];
                    for (c, v) in raw.iter().enumerate() {
                        assert_eq!(*v, 0.1 * c as f32 - 0.5 * e as f32, "{kind:?} {shared}");
                    }
                    moe.expert().decode(raw, &mut mean, &mut scale);
                    assert_eq!(out.mean(b, e), mean);
                    assert_eq!(out.scale(b, e), scale);
                }
            }
        }
    }
}

#[test]
fn separate_networks_are_independent_and_seeds_reproduce_initialisation() {
    let cfg = config(2, 2, ExpertKind::Diagonal, GatingKind::Learned, false);
    let params = |moe: &Moe| {
        let mut v = Vec::new();
        moe.visit_params("", &mut |n, p| v.push((n.to_owned(), p.value.clone())));
        v
    };
    let a = Moe::from_config(cfg.clone(), 3).unwrap();
    let b = Moe::from_config(cfg.clone(), 3).unwrap();
    let c = Moe::from_config(cfg, 4).unwrap();
    assert_eq!(params(&a), params(&b));
    assert_ne!(params(&a), params(&c));
    let pa = params(&a);
    let w = |e: usize| pa.iter().find(|(n, _)| *n == format!("experts.{e}.layers.0.weight"));
    assert_ne!(w(0).unwrap().1, w(1).unwrap().1, "separate experts share weights");
}

// ---------------------------------------------------------------------------------------
// Likelihood, responsibilities, gating, entropies.
// ---------------------------------------------------------------------------------------

#[test]
fn log_likelihood_is_an_independent_log_sum_exp_over_the_experts() {
    for cfg in all_configs(2, 3) {
        let what = format!("{:?}/{:?}/shared={}", cfg.expert_kind, cfg.gating, cfg.shared_trunk);
        let mut moe = built(cfg, 2);
        let (obs_norm, act_norm) = normalizers(2, 3);
        let n = 6;
        let obs = obs_batch(n, 2);
        let actions = Mat::from_fn(n, 3, |i, j| ((i * 3 + j * 5) % 9) as f32 * 0.7 - 2.0);
        let mut ll = vec![0.0; n];
        moe.log_likelihood(obs.as_ref(), actions.as_ref(), &mut ll).unwrap();

        let states = normalized(obs.as_ref(), &obs_norm);
        moe.forward(states.as_ref()).unwrap();
        let out = moe.output().clone();
        let log_gating = ref_log_gating(&mut moe, states.as_ref());
        let log_det: f64 = act_norm.scale.iter().map(|s| f64::from(*s).ln()).sum();
        let norm_actions = normalized(actions.as_ref(), &act_norm);
        let mut resp = Mat::<f32>::zeros(n, 3);
        moe.responsibilities(states.as_ref(), norm_actions.as_ref(), resp.as_mut()).unwrap();
        for b in 0..n {
            let x: Vec<f64> = (0..3)
                .map(|j| {
                    (f64::from(actions[(b, j)]) - f64::from(act_norm.offset[j]))
                        / f64::from(act_norm.scale[j])
                })
                .collect();
            let joint: Vec<f64> = (0..3)
                .map(|z| log_gating[b][z] + ref_log_normal(&x, out.mean(b, z), out.scale(b, z)))
                .collect();
            let lse = ref_log_sum_exp(&joint);
            assert_close(f64::from(ll[b]), lse - log_det, 1e-4 * (1.0 + lse.abs()), &what);
            // Bayes' rule, and a probability vector.
            let mut sum = 0.0;
            for z in 0..3 {
                let want = (joint[z] - lse).exp();
                assert_close(f64::from(resp[(b, z)]), want, 1e-5, &what);
                sum += f64::from(resp[(b, z)]);
            }
            assert_close(sum, 1.0, 1e-5, &what);
        }
    }
}

#[test]
fn gating_is_a_softmax_of_the_network_or_exactly_uniform() {
    for gating in [GatingKind::Learned, GatingKind::Uniform] {
        let mut moe = built(config(2, 2, ExpertKind::Diagonal, gating, true), 5);
        let states = obs_batch(5, 2);
        moe.forward_gating(states.as_ref()).unwrap();
        let got = moe.output().log_gating.clone();
        let want = ref_log_gating(&mut moe, states.as_ref());
        for b in 0..5 {
            let row = &got[b * 3..(b + 1) * 3];
            let total: f64 = row.iter().map(|l| f64::from(*l).exp()).sum();
            assert_close(total, 1.0, 1e-5, "gating sums to one");
            for z in 0..3 {
                assert_close(f64::from(row[z]), want[b][z], 1e-5, "log q(z|s)");
            }
            if gating == GatingKind::Uniform {
                assert!(row.iter().all(|l| *l == -(3.0f32).ln()));
            } else {
                assert!((row[0] - row[2]).abs() > 0.5, "learned gating is not uniform here");
            }
        }
        assert_eq!(moe.has_learned_gating(), gating == GatingKind::Learned);
        let mut gating_params = 0;
        moe.visit_params("", &mut |n, _| gating_params += usize::from(n.starts_with("gating")));
        assert_eq!(gating_params > 0, gating == GatingKind::Learned);
    }
}

#[test]
fn expert_entropies_are_the_closed_form_gaussian_entropies() {
    for kind in [ExpertKind::Diagonal, ExpertKind::Full] {
        let mut moe = built(config(2, 3, kind, GatingKind::Learned, true), 6);
        let states = obs_batch(4, 2);
        let h = moe.expert_entropies(states.as_ref()).unwrap();
        assert_eq!((h.nrows(), h.ncols()), (4, 3));
        let out = moe.output();
        for b in 0..4 {
            for z in 0..3 {
                let (_, log_det) = inverse_and_log_det(&covariance(out.scale(b, z), 3), 3);
                let want =
                    0.5 * (3.0 * (2.0 * std::f64::consts::PI * std::f64::consts::E).ln() + log_det);
                assert_close(f64::from(h[(b, z)]), want, 1e-4, "entropy");
            }
        }
        // The experts differ, so the entropies must too (catches a constant result).
        assert!((h[(0, 0)] - h[(0, 1)]).abs() > 1e-3);
    }
}

#[test]
fn an_action_beyond_every_expert_has_minus_infinite_likelihood_not_nan() {
    let mut moe = built(config(2, 2, ExpertKind::Full, GatingKind::Learned, true), 7);
    let obs = obs_batch(1, 2);
    let far = faer::mat![[1e30f32, -1e30]];
    let mut ll = [0.0];
    moe.log_likelihood(obs.as_ref(), far.as_ref(), &mut ll).unwrap();
    assert_eq!(ll[0], f32::NEG_INFINITY);
    let states = normalized(obs.as_ref(), &normalizers(2, 2).0);
    let mut resp = Mat::<f32>::zeros(1, 3);
    moe.responsibilities(states.as_ref(), far.as_ref(), resp.as_mut()).unwrap();
    let prior = moe.output().log_gating_row(0).to_vec();
    for z in 0..3 {
        assert_close(f64::from(resp[(0, z)]), f64::from(prior[z]).exp(), 1e-6, "fallback");
    }
}
