//! Backward passes against finite differences.

use super::*;

// ---------------------------------------------------------------------------------------
// Gradients.
// ---------------------------------------------------------------------------------------

/// Max relative error between the accumulated gradients of the parameters named
/// `prefix…` and central differences (steps `h`, `h/2`, Richardson) of `loss`: every other
/// entry of the output layers (each row, i.e. each expert's raw output, is covered), every
/// `stride`-th entry of the others. Returns the error and the number of entries checked.
fn finite_difference_error(
    moe: &mut Moe,
    prefix: &str,
    stride: usize,
    loss: &mut dyn FnMut(&mut Moe) -> f64,
) -> (f32, usize) {
    let mut analytic = Vec::new();
    moe.visit_params("", &mut |name, p| {
        analytic.push(if name.starts_with(prefix) {
            let every = if name.contains(OUT_LAYER) { 2 } else { stride };
            p.grad.iter().enumerate().map(|(e, g)| (e % every == 0).then_some(*g)).collect()
        } else {
            Vec::new()
        });
    });
    let set = |moe: &mut Moe, index: usize, entry: usize, v: f32| {
        let mut k = 0;
        moe.visit_params_mut("", &mut |_, p| {
            if k == index {
                p.value[entry] = v;
            }
            k += 1;
        });
    };
    let (h, mut worst, mut checked) = (1e-2f32, 0.0f32, 0);
    for (pi, grads) in analytic.iter().enumerate() {
        for (e, a) in grads.iter().enumerate() {
            let Some(a) = *a else { continue };
            let mut orig = 0.0;
            let mut k = 0;
            moe.visit_params("", &mut |_, p| {
                if k == pi {
                    orig = p.value[e];
                }
                k += 1;
            });
            let mut central = |step: f32| {
                let (xp, xm) = (orig + step, orig - step);
                set(moe, pi, e, xp);
                let fp = loss(moe);
                set(moe, pi, e, xm);
                let fm = loss(moe);
                (fp - fm) / (f64::from(xp) - f64::from(xm))
            };
            let numeric = (4.0 * central(0.5 * h) - central(h)) / 3.0;
            set(moe, pi, e, orig);
            let err = (f64::from(a) - numeric).abs() / numeric.abs().max(1e-2);
            worst = worst.max(err as f32);
            checked += 1;
        }
    }
    (worst, checked)
}

#[test]
fn backward_experts_matches_finite_differences_of_a_loss_through_forward() {
    for kind in [ExpertKind::Diagonal, ExpertKind::Full] {
        for shared in [true, false] {
            let mut moe = built(config(2, 2, kind, GatingKind::Learned, shared), 14);
            let states = obs_batch(5, 2);
            let (z, d, r) = (3, 2, moe.expert().raw_dim());
            // f = Σ c_μ·μ + Σ c_L·L over states and experts, with fixed random weights.
            let mut rng = Seeds::new(1).stream("coefficients");
            let cm: Vec<f32> = (0..5 * z * d).map(|_| rng.random_range(-1.0..1.0)).collect();
            let cl: Vec<f32> = (0..5 * z * d * d).map(|_| rng.random_range(-1.0..1.0)).collect();
            let mut loss = |moe: &mut Moe| -> f64 {
                moe.forward_experts(states.as_ref()).unwrap();
                let out = moe.output();
                let m: f64 = out.means.iter().zip(&cm).map(|(x, c)| f64::from(x * c)).sum();
                let l: f64 = out.scales.iter().zip(&cl).map(|(x, c)| f64::from(x * c)).sum();
                m + l
            };
            loss(&mut moe);
            let out = moe.output().clone();
            let mut grad_raw = vec![0.0; 5 * z * r];
            for k in 0..5 * z {
                moe.expert().backward(
                    &out.raw[k * r..(k + 1) * r],
                    &cm[k * d..(k + 1) * d],
                    &cl[k * d * d..(k + 1) * d * d],
                    &mut grad_raw[k * r..(k + 1) * r],
                );
            }
            moe.forward_gating(states.as_ref()).unwrap();
            moe.zero_grad();
            moe.backward_experts(&grad_raw).unwrap();
            let mut gating_grads = 0.0f32;
            moe.visit_params("", &mut |n, p| {
                if n.starts_with("gating") {
                    gating_grads += p.grad.iter().map(|g| g.abs()).sum::<f32>();
                }
            });
            assert_eq!(gating_grads, 0.0, "experts' backward touched the gating");
            let (err, checked) = finite_difference_error(&mut moe, "experts", 5, &mut loss);
            assert!(checked > 50, "{checked}");
            assert!(err < 1e-2, "{kind:?} shared={shared}: relative error {err}");
        }
    }
}

#[test]
fn backward_gating_matches_finite_differences_of_a_loss_through_forward() {
    let mut moe = built(config(2, 2, ExpertKind::Diagonal, GatingKind::Learned, true), 15);
    let states = obs_batch(5, 2);
    let mut rng = Seeds::new(2).stream("coefficients");
    let c: Vec<f32> = (0..15).map(|_| rng.random_range(-1.0..1.0)).collect();
    // f = Σ c ⊙ log q(z|s); ∂f/∂logit_j = c_j − q_j Σ_k c_k per state.
    let mut loss = |moe: &mut Moe| -> f64 {
        moe.forward(states.as_ref()).unwrap();
        moe.output().log_gating.iter().zip(&c).map(|(l, c)| f64::from(l * c)).sum()
    };
    loss(&mut moe);
    let lg = moe.output().log_gating.clone();
    let grad = Mat::from_fn(5, 3, |b, j| {
        let total: f32 = c[b * 3..(b + 1) * 3].iter().sum();
        c[b * 3 + j] - lg[b * 3 + j].exp() * total
    });
    moe.zero_grad();
    moe.backward_gating(grad.as_ref()).unwrap();
    let mut expert_grads = 0.0f32;
    moe.visit_params("", &mut |n, p| {
        if n.starts_with("experts") {
            expert_grads += p.grad.iter().map(|g| g.abs()).sum::<f32>();
        }
    });
    assert_eq!(expert_grads, 0.0, "gating backward touched the experts");
    let (err, checked) = finite_difference_error(&mut moe, "gating", 3, &mut loss);
    assert!(checked > 40, "{checked}");
    assert!(err < 1e-2, "relative error {err}");

    // Uniform gating: nothing to differentiate, but the shape is still checked.
    let mut uniform = built(config(2, 2, ExpertKind::Diagonal, GatingKind::Uniform, true), 15);
    uniform.forward(states.as_ref()).unwrap();
    uniform.backward_gating(grad.as_ref()).unwrap();
    assert!(uniform.backward_gating(Mat::<f32>::zeros(4, 3).as_ref()).is_err());
}
