//! Acting: sampling agrees with the likelihood, greedy and sampled gating, seeds, batches.

use super::*;

// ---------------------------------------------------------------------------------------
// Acting.
// ---------------------------------------------------------------------------------------

/// Mean and covariance of the (denormalised) mixture at state 0 of the last forward.
fn mixture_moments(moe: &Moe, act_norm: &Affine, only: Option<usize>) -> (Vec<f64>, Vec<f64>) {
    let out = moe.output();
    let d = out.action_dim;
    let (mut mean, mut second) = (vec![0.0; d], vec![0.0; d * d]);
    for z in 0..out.num_experts {
        let q = match only {
            Some(k) => f64::from(u8::from(k == z)),
            None => f64::from(out.log_gating_row(0)[z]).exp(),
        };
        let s = |i: usize| f64::from(act_norm.scale[i]);
        let mu: Vec<f64> = (0..d)
            .map(|i| f64::from(act_norm.offset[i]) + s(i) * f64::from(out.mean(0, z)[i]))
            .collect();
        let cov = covariance(out.scale(0, z), d);
        for i in 0..d {
            mean[i] += q * mu[i];
            for j in 0..d {
                second[i * d + j] += q * (s(i) * s(j) * cov[i * d + j] + mu[i] * mu[j]);
            }
        }
    }
    for i in 0..d {
        for j in 0..d {
            second[i * d + j] -= mean[i] * mean[j];
        }
    }
    (mean, second)
}

fn sample_moments(a: MatRef<'_, f32>) -> (Vec<f64>, Vec<f64>) {
    let (n, d) = (a.nrows(), a.ncols());
    let mean: Vec<f64> =
        (0..d).map(|j| (0..n).map(|i| f64::from(a[(i, j)])).sum::<f64>() / n as f64).collect();
    let mut cov = vec![0.0; d * d];
    for i in 0..n {
        for p in 0..d {
            for q in 0..d {
                cov[p * d + q] += (f64::from(a[(i, p)]) - mean[p])
                    * (f64::from(a[(i, q)]) - mean[q])
                    / (n - 1) as f64;
            }
        }
    }
    (mean, cov)
}

/// The density `log_likelihood` reports (normalisers and their Jacobian included) is the one
/// `act` samples from: it integrates to one, and its moments, the closed-form mixture
/// moments and the moments of sampled actions agree.
#[test]
fn likelihood_and_sampling_describe_the_same_distribution() {
    // ReLU networks: cheaper on many rows, and smoothness does not matter here.
    let relu = NetworkConfig { activation: Activation::Relu, ..small_net() };
    let cfg = MoeConfig {
        experts_network: relu.clone(),
        gating_network: relu,
        ..config(1, 2, ExpertKind::Full, GatingKind::Learned, true)
    };
    let mut moe = built(cfg, 8);
    let act_norm = normalizers(1, 2).1;
    let obs = [0.9f32];
    let mut ll0 = [0.0];
    moe.log_likelihood(faer::mat![[0.9f32]].as_ref(), faer::mat![[0.0f32, 0.0]].as_ref(), &mut ll0)
        .unwrap();
    let (mean, cov) = mixture_moments(&moe, &act_norm, None);
    let sd = |i: usize| cov[i * 2 + i].sqrt();
    assert!(cov[1].abs() > 0.05 * sd(0) * sd(1), "test needs correlated actions");

    // Midpoint quadrature of exp(log q) over a box holding every expert.
    let out = moe.output().clone();
    let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
    for z in 0..3 {
        let c = covariance(out.scale(0, z), 2);
        for i in 0..2 {
            let s = f64::from(act_norm.scale[i]);
            let mu = f64::from(act_norm.offset[i]) + s * f64::from(out.mean(0, z)[i]);
            lo[i] = lo[i].min(mu - 8.0 * s * c[i * 2 + i].sqrt());
            hi[i] = hi[i].max(mu + 8.0 * s * c[i * 2 + i].sqrt());
        }
    }
    let g = 128;
    let step = [(hi[0] - lo[0]) / g as f64, (hi[1] - lo[1]) / g as f64];
    let grid = Mat::from_fn(g * g, 2, |k, j| {
        let idx = if j == 0 { k / g } else { k % g };
        (lo[j] + (idx as f64 + 0.5) * step[j]) as f32
    });
    let states = Mat::from_fn(g * g, 1, |_, _| obs[0]);
    let mut ll = vec![0.0; g * g];
    moe.log_likelihood(states.as_ref(), grid.as_ref(), &mut ll).unwrap();
    let (mut mass, mut qm, mut qs) = (0.0, [0.0; 2], [0.0; 4]);
    for k in 0..g * g {
        let w = f64::from(ll[k]).exp() * step[0] * step[1];
        let x = [f64::from(grid[(k, 0)]), f64::from(grid[(k, 1)])];
        mass += w;
        for i in 0..2 {
            qm[i] += w * x[i];
            for j in 0..2 {
                qs[i * 2 + j] += w * x[i] * x[j];
            }
        }
    }
    assert_close(mass, 1.0, 2e-3, "∫ q(a|s) da");
    for i in 0..2 {
        assert_close(qm[i], mean[i], 2e-3 * sd(i), "quadrature mean");
        for j in 0..2 {
            let c = qs[i * 2 + j] - qm[i] * qm[j];
            assert_close(c, cov[i * 2 + j], 5e-3 * sd(i) * sd(j), "quadrature covariance");
        }
    }

    // Sampled gating and sampled actions.
    let n = 16_000;
    let repeated = Mat::from_fn(n, 1, |_, _| obs[0]);
    let mut actions = Mat::<f32>::zeros(n, 2);
    moe.set_act_mode(ActMode { greedy_gating: false, sample_action: true, hold_steps: 0 });
    moe.seed(11);
    moe.act_batch(repeated.as_ref(), actions.as_mut()).unwrap();
    let (sm, sc) = sample_moments(actions.as_ref());
    for i in 0..2 {
        assert_close(sm[i], mean[i], 4.0 * sd(i) / (n as f64).sqrt(), "sample mean");
        for j in 0..2 {
            assert_close(sc[i * 2 + j], cov[i * 2 + j], 0.05 * sd(i) * sd(j), "sample cov");
        }
    }

    // Greedy gating with sampled actions: the most probable expert's Gaussian only.
    let lg = moe.output().log_gating_row(0).to_vec();
    let best = (0..3).max_by(|&a, &b| lg[a].total_cmp(&lg[b])).unwrap();
    let (bm, bc) = mixture_moments(&moe, &act_norm, Some(best));
    moe.set_act_mode(ActMode { greedy_gating: true, sample_action: true, hold_steps: 0 });
    moe.act_batch(repeated.as_ref(), actions.as_mut()).unwrap();
    let (sm, sc) = sample_moments(actions.as_ref());
    for i in 0..2 {
        let sdi = bc[i * 2 + i].sqrt();
        assert_close(sm[i], bm[i], 4.0 * sdi / (n as f64).sqrt(), "greedy sample mean");
        for j in 0..2 {
            let sdj = bc[j * 2 + j].sqrt();
            assert_close(sc[i * 2 + j], bc[i * 2 + j], 0.05 * sdi * sdj, "greedy sample cov");
        }
    }
}

/// Equal up to `f32` rounding of differently ordered sums.
fn assert_all_close(a: &[f32], b: &[f32]) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        assert!((x - y).abs() <= 1e-5 * (1.0 + y.abs()), "{a:?} vs {b:?}");
    }
}

/// The denormalised mean of every expert at state `b` of the last forward.
fn denormalized_means(moe: &Moe, b: usize) -> Vec<Vec<f32>> {
    let act_norm = moe.normalizers().1.unwrap().clone();
    (0..moe.num_experts())
        .map(|z| {
            let mut m = moe.output().mean(b, z).to_vec();
            act_norm.denormalize(&mut m);
            m
        })
        .collect()
}

#[test]
fn greedy_mean_mode_returns_the_most_probable_experts_mean() {
    for cfg in all_configs(2, 2).into_iter().filter(|c| c.gating == GatingKind::Learned) {
        let mut moe = built(cfg, 9);
        moe.set_act_mode(ActMode { greedy_gating: true, sample_action: false, hold_steps: 0 });
        let obs = obs_batch(5, 2);
        let mut batch = Mat::<f32>::zeros(5, 2);
        moe.act_batch(obs.as_ref(), batch.as_mut()).unwrap();
        // Acting computes only the chosen expert: the full forward pass for comparison.
        moe.forward_observations(obs.as_ref()).unwrap();
        let mut picked = Vec::new();
        for b in 0..5 {
            let lg = moe.output().log_gating_row(b).to_vec();
            let best = (0..3).max_by(|&x, &y| lg[x].total_cmp(&lg[y])).unwrap();
            picked.push(best);
            // Separate experts' networks act on one state at a time (a row kernel).
            let want = &denormalized_means(&moe, b)[best];
            assert_all_close(&[batch[(b, 0)], batch[(b, 1)]], want);
        }
        // One state at a time: the one-row forward pass's bits (a row kernel, not the
        // batch's matrix product, so the batch's actions up to rounding).
        for b in 0..5 {
            let state = [obs[(b, 0)], obs[(b, 1)]];
            let a = moe.act(&state).unwrap();
            moe.forward_observations(MatRef::from_row_major_slice(&state, 1, 2)).unwrap();
            assert_eq!(a, denormalized_means(&moe, 0)[picked[b]], "state {b}");
            assert_all_close(&a, &[batch[(b, 0)], batch[(b, 1)]]);
        }
        assert_eq!(picked[0], 0, "the spread gating favours expert 0");
        // Acting leaves no experts' forward pass to back-propagate through.
        moe.act(&[obs[(0, 0)], obs[(0, 1)]]).unwrap();
        let grad = vec![0.0; moe.num_experts() * moe.expert().raw_dim()];
        assert!(matches!(moe.backward_experts(&grad), Err(MoeError::NoForward(_))));
    }
}

#[test]
fn last_experts_name_the_expert_that_acted() {
    for cfg in all_configs(2, 2) {
        let mut moe = built(cfg, 12);
        assert!(moe.last_experts().is_empty());
        let mut used = std::collections::BTreeSet::new();
        for greedy in [true, false] {
            moe.set_act_mode(ActMode {
                greedy_gating: greedy,
                sample_action: false,
                hold_steps: 0,
            });
            moe.seed(5);
            let obs = obs_batch(8, 2);
            let mut batch = Mat::<f32>::zeros(8, 2);
            moe.act_batch(obs.as_ref(), batch.as_mut()).unwrap();
            let experts = moe.last_experts().to_vec();
            assert_eq!(experts.len(), 8);
            used.extend(experts.iter().copied());
            moe.forward_observations(obs.as_ref()).unwrap();
            for (b, &z) in experts.iter().enumerate() {
                let means = denormalized_means(&moe, b);
                assert_all_close(&[batch[(b, 0)], batch[(b, 1)]], &means[z]);
                for (other, m) in means.iter().enumerate().filter(|(k, _)| *k != z) {
                    assert!((m[0] - batch[(b, 0)]).abs() > 1e-3, "expert {other} acts alike");
                }
            }
            moe.act(&[obs[(0, 0)], obs[(0, 1)]]).unwrap();
            assert_eq!(moe.last_experts().len(), 1, "one entry for one observation");
        }
        assert!(used.len() >= 2, "sampled gating uses several experts: {used:?}");
    }
}

#[test]
fn sampled_gating_picks_experts_with_the_gating_probabilities() {
    let mut moe = built(config(2, 2, ExpertKind::Diagonal, GatingKind::Learned, true), 10);
    moe.set_act_mode(ActMode { greedy_gating: false, sample_action: false, hold_steps: 0 });
    moe.seed(3);
    let n = 20_000;
    let obs = Mat::from_fn(n, 2, |_, j| [0.4f32, -0.3][j]);
    let mut actions = Mat::<f32>::zeros(n, 2);
    moe.act_batch(obs.as_ref(), actions.as_mut()).unwrap();
    moe.forward_observations(obs.subrows(0, 1)).unwrap();
    let means = denormalized_means(&moe, 0);
    let mut counts = [0usize; 3];
    for b in 0..n {
        let a = [actions[(b, 0)], actions[(b, 1)]];
        let z = means
            .iter()
            .position(|m| m.iter().zip(&a).all(|(x, y)| (x - y).abs() < 1e-5))
            .expect("an action is an expert's mean");
        counts[z] += 1;
    }
    let q: Vec<f64> = moe.output().log_gating_row(0).iter().map(|l| f64::from(*l).exp()).collect();
    assert!(q.iter().all(|p| *p > 0.05) && (q[0] - q[2]).abs() > 0.2, "{q:?}");
    for z in 0..3 {
        let freq = counts[z] as f64 / n as f64;
        let se = (q[z] * (1.0 - q[z]) / n as f64).sqrt();
        assert_close(freq, q[z], 4.0 * se, "gating frequency");
    }
}

#[test]
fn a_sharpened_gating_is_the_old_one_to_the_power_one_over_t_and_bad_temperatures_change_nothing() {
    let mut moe = built(config(2, 2, ExpertKind::Diagonal, GatingKind::Learned, true), 10);
    let obs = Mat::from_fn(3, 2, |i, j| [0.4f32, -0.3][j] * (i as f32 - 1.0));
    let gating = |moe: &mut Moe| {
        moe.forward_gating(obs.as_ref()).unwrap();
        (0..3).map(|b| moe.output().log_gating_row(b).to_vec()).collect::<Vec<_>>()
    };
    let before = gating(&mut moe);
    moe.forward_observations(obs.as_ref()).unwrap();
    let means = denormalized_means(&moe, 2);
    for bad in [0.0, -1.0, f32::NAN, f32::INFINITY, 1e-44] {
        assert!(moe.sharpen_gating(bad).is_err(), "{bad}");
        assert_eq!(gating(&mut moe), before, "{bad} changed the gating");
    }
    moe.sharpen_gating(0.25).unwrap();
    for (new, old) in gating(&mut moe).iter().zip(&before) {
        let norm = old.iter().map(|l| (4.0 * l).exp()).sum::<f32>().ln();
        assert_all_close(new, &old.iter().map(|l| 4.0 * l - norm).collect::<Vec<_>>());
    }
    // The experts are untouched, and a uniform gating has no temperature.
    moe.forward_observations(obs.as_ref()).unwrap();
    assert_eq!(denormalized_means(&moe, 2), means);
    let mut uniform = built(config(2, 2, ExpertKind::Diagonal, GatingKind::Uniform, true), 10);
    assert!(uniform.sharpen_gating(0.5).is_err());
}

#[test]
fn the_same_seed_gives_the_same_actions_and_seed_resets_the_stream() {
    for mode in [
        ActMode { greedy_gating: false, sample_action: true, hold_steps: 0 },
        ActMode { greedy_gating: false, sample_action: false, hold_steps: 0 },
        ActMode { greedy_gating: true, sample_action: true, hold_steps: 0 },
    ] {
        let mut moe = built(config(2, 2, ExpertKind::Full, GatingKind::Learned, true), 12);
        moe.set_act_mode(mode);
        let run = |moe: &mut Moe| -> Vec<Vec<f32>> {
            (0..40).map(|k| moe.act(&[0.1 * k as f32, -0.2]).unwrap()).collect()
        };
        moe.seed(5);
        let a = run(&mut moe);
        let continued = run(&mut moe);
        moe.seed(5);
        let b = run(&mut moe);
        moe.seed(6);
        let c = run(&mut moe);
        assert_eq!(a, b, "{mode:?}: seed() resets the stream");
        assert_ne!(a, continued, "{mode:?}: the stream advances");
        assert_ne!(a, c, "{mode:?}: another seed, other actions");

        // A clone with the same seed (and a freshly built copy) acts identically.
        let mut twin = built(config(2, 2, ExpertKind::Full, GatingKind::Learned, true), 12);
        twin.set_act_mode(mode);
        twin.seed(5);
        assert_eq!(run(&mut twin), a, "{mode:?}: same weights and seed");
    }
}

#[test]
fn act_batch_matches_repeated_act_into_in_deterministic_mode() {
    for cfg in all_configs(3, 2) {
        let mut moe = built(cfg, 13);
        moe.set_act_mode(ActMode { greedy_gating: true, sample_action: false, hold_steps: 0 });
        let obs = obs_batch(7, 3);
        let mut batch = Mat::<f32>::zeros(7, 2);
        moe.act_batch(obs.as_ref(), batch.as_mut()).unwrap();
        let mut one = [0.0f32; 2];
        for b in 0..7 {
            moe.act_into(&[obs[(b, 0)], obs[(b, 1)], obs[(b, 2)]], &mut one).unwrap();
            // One row runs a row kernel, a batch a matrix product: equal up to rounding.
            assert_all_close(&one, &[batch[(b, 0)], batch[(b, 1)]]);
        }
        // An empty batch is fine.
        moe.act_batch(Mat::<f32>::zeros(0, 3).as_ref(), Mat::<f32>::zeros(0, 2).as_mut()).unwrap();
    }
}

/// The observations of call `k` of a run: every row moves, so a held expert must act on a new
/// state at every call.
fn moving_obs(rows: usize, k: usize) -> Mat<f32> {
    let base = obs_batch(rows, 2);
    Mat::from_fn(rows, 2, |i, j| base[(i, j)] + 0.05 * k as f32)
}

/// `calls` act calls on `rows_of(k)` rows of [`moving_obs`]; per call the experts that acted,
/// each checked to have returned its mean at that call's state.
fn act_calls(moe: &mut Moe, calls: usize, rows_of: impl Fn(usize) -> usize) -> Vec<Vec<usize>> {
    (0..calls)
        .map(|k| {
            let obs = moving_obs(rows_of(k), k);
            let mut actions = Mat::<f32>::zeros(obs.nrows(), 2);
            moe.act_batch(obs.as_ref(), actions.as_mut()).unwrap();
            let experts = moe.last_experts().to_vec();
            moe.forward_observations(obs.as_ref()).unwrap();
            for (b, &z) in experts.iter().enumerate() {
                assert_all_close(
                    &[actions[(b, 0)], actions[(b, 1)]],
                    &denormalized_means(moe, b)[z],
                );
            }
            experts
        })
        .collect()
}

#[test]
fn held_experts_act_for_hold_steps_predictions_of_their_row_until_reset() {
    use rand::Rng as _;
    let rows = 24;
    for gating in [GatingKind::Uniform, GatingKind::Learned] {
        let mut moe = built(config(2, 2, ExpertKind::Diagonal, gating, true), 13);
        let mode = |hold_steps| ActMode { greedy_gating: false, sample_action: false, hold_steps };

        // 0 and 1: one draw u ~ U[0, 1) per row and call, in row order, from the seed's stream,
        // inverted through the gating's cumulative weights, as before holds existed.
        let mut rng = vdd_core::Seeds::new(4).stream("moe-act");
        let reference: Vec<Vec<usize>> = (0..6)
            .map(|k| {
                moe.forward_observations(moving_obs(rows, k).as_ref()).unwrap();
                (0..rows)
                    .map(|b| {
                        let u: f32 = rng.random();
                        let (mut acc, lg) = (0.0, moe.output().log_gating_row(b).to_vec());
                        lg.iter()
                            .position(|l| {
                                acc += l.exp();
                                u < acc
                            })
                            .unwrap_or(2)
                    })
                    .collect()
            })
            .collect();
        for hold in [0, 1] {
            moe.set_act_mode(mode(hold));
            moe.seed(4);
            moe.reset();
            assert_eq!(act_calls(&mut moe, 6, |_| rows), reference, "{gating:?}, hold {hold}");
        }
        assert_ne!(reference[0], reference[1], "{gating:?}: a pick at every prediction");

        // 3: each row keeps its pick for its own three predictions. The first call acts on the
        // first half of the rows only, so the halves pick again on different calls.
        moe.set_act_mode(mode(3));
        moe.seed(4);
        moe.reset();
        let held = act_calls(&mut moe, 10, |k| if k == 0 { rows / 2 } else { rows });
        assert_eq!(held[0], reference[0][..rows / 2], "{gating:?}: the first pick is unheld");
        for b in 0..rows {
            let first = if b < rows / 2 { 0 } else { 1 };
            let picks: Vec<usize> = held[first..].iter().map(|c| c[b]).collect();
            for block in picks.chunks(3) {
                assert!(block.iter().all(|&z| z == block[0]), "{gating:?}: row {b} {picks:?}");
            }
        }
        let row_changes = |b: usize, at: usize| held[at - 1][b] != held[at][b];
        assert!((0..rows / 2).any(|b| row_changes(b, 3)), "{gating:?}: first half re-picks at 3");
        assert!((rows / 2..rows).any(|b| row_changes(b, 4)), "{gating:?}: second half at 4");

        // `reset` and `set_act_mode` end every hold; `seed` alone does not.
        for end in ["reset", "set_act_mode"] {
            moe.set_act_mode(mode(1000));
            moe.seed(4);
            moe.reset();
            let first = act_calls(&mut moe, 1, |_| rows).remove(0);
            moe.seed(9);
            assert_eq!(act_calls(&mut moe, 1, |_| rows)[0], first, "{gating:?}: held after seed");
            match end {
                "reset" => moe.reset(),
                _ => moe.set_act_mode(mode(1000)),
            }
            assert_ne!(act_calls(&mut moe, 1, |_| rows)[0], first, "{gating:?}: picks after {end}");
        }
    }
}
