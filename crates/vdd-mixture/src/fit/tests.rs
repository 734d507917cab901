//! Tests of the mixture-fitting pieces: gradients against finite differences, sampling, evaluation.

use super::*;
use approx::assert_relative_eq;
use vdd_core::Seeds;
use vdd_moe::{DiagonalExpert, ExpertFamily, ExpertKind, FullExpert, GatingKind, MoeConfig};

/// An output for `n` rows and `Z` experts decoded from given raw rows.
fn output<E: Expert>(expert: &E, raw: &[f32], n: usize, z_n: usize) -> MoeOutput {
    let (d, r) = (expert.action_dim(), expert.raw_dim());
    let mut out = MoeOutput {
        n,
        num_experts: z_n,
        action_dim: d,
        raw: raw.to_vec(),
        means: vec![0.0; n * z_n * d],
        scales: vec![0.0; n * z_n * d * d],
        log_gating: vec![-(z_n as f32).ln(); n * z_n],
    };
    for k in 0..n * z_n {
        expert.decode(
            &raw[k * r..(k + 1) * r],
            &mut out.means[k * d..(k + 1) * d],
            &mut out.scales[k * d * d..(k + 1) * d * d],
        );
    }
    out
}

fn weighted_nll(
    expert: &impl Expert,
    raw: &[f32],
    n: usize,
    z_n: usize,
    a: &Mat<f32>,
    w: &[f32],
) -> f64 {
    let out = output(expert, raw, n, z_n);
    let d = expert.action_dim();
    let mut work = vec![0.0; d];
    let mut s = 0.0f64;
    for b in 0..n {
        let row: Vec<f32> = (0..d).map(|j| a[(b, j)]).collect();
        for k in 0..z_n {
            let lp = gaussian::log_density(&row, out.mean(b, k), out.scale(b, k), &mut work);
            s -= f64::from(w[b * z_n + k]) * f64::from(lp);
        }
    }
    s
}

fn check_raw_gradient<E: Expert>(expert: E) {
    let (n, z_n, d, r) = (3, 2, expert.action_dim(), expert.raw_dim());
    let raw: Vec<f32> =
        (0..n * z_n * r).map(|i| ((i * 37 % 13) as f32 / 13.0 - 0.5) * 0.8).collect();
    let a = Mat::from_fn(n, d, |i, j| ((i * 3 + j * 5) % 7) as f32 * 0.4 - 1.1);
    let w = [0.7f32, 0.3, 0.0, 1.0, 0.25, 0.5];
    let out = output(&expert, &raw, n, z_n);
    let mut buf = FitBuffers::default();
    let loss = weighted_nll_gradients(&expert, &out, a.as_ref(), &w, &mut buf).unwrap();
    assert_relative_eq!(loss, weighted_nll(&expert, &raw, n, z_n, &a, &w), epsilon = 1e-4);
    for i in 0..raw.len() {
        let h = 1e-3f32;
        let mut p = raw.clone();
        p[i] += h;
        let mut m = raw.clone();
        m[i] -= h;
        let fd = (weighted_nll(&expert, &p, n, z_n, &a, &w)
            - weighted_nll(&expert, &m, n, z_n, &a, &w))
            / (2.0 * f64::from(h));
        assert_relative_eq!(f64::from(buf.grad_raw[i]), fd, epsilon = 3e-3, max_relative = 3e-3);
    }
}

#[test]
fn weighted_nll_gradient_matches_finite_differences_diagonal() {
    check_raw_gradient(DiagonalExpert::new(3, 0.8, 1e-3).unwrap());
}

#[test]
fn weighted_nll_gradient_matches_finite_differences_full() {
    check_raw_gradient(FullExpert::new(3, 0.8, 1e-3).unwrap());
}

/// The same loss through the networks: parameter gradients from `backward_experts` against
/// central differences of the parameters.
fn check_network_gradient(kind: ExpertKind, shared_trunk: bool) {
    let mut mc = MoeConfig::toy(2, 2, 2);
    mc.expert_kind = kind;
    mc.shared_trunk = shared_trunk;
    mc.experts_network.hidden_dim = 8;
    mc.init_std = 0.7;
    let mut moe = Moe::from_config(mc, 4).unwrap();
    let n = 5;
    let states = Mat::from_fn(n, 2, |i, j| (i as f32 - 2.0) * 0.3 + j as f32 * 0.2);
    let actions = Mat::from_fn(n, 2, |i, j| ((i * 2 + j) % 5) as f32 * 0.3 - 0.6);
    let w: Vec<f32> = (0..n * 2).map(|i| 0.1 + (i % 3) as f32 * 0.2).collect();
    let mut buf = FitBuffers::default();
    let loss_at = |moe: &mut Moe, buf: &mut FitBuffers| {
        moe.forward_experts(states.as_ref()).unwrap();
        weighted_nll_gradients(moe.expert(), moe.output(), actions.as_ref(), &w, buf).unwrap()
    };
    loss_at(&mut moe, &mut buf);
    moe.expert_networks_mut().zero_grad();
    let g = buf.grad_raw.clone();
    moe.backward_experts(&g).unwrap();
    let mut analytic = Vec::new();
    moe.expert_networks_mut().visit_params("", &mut |_, p| analytic.push(p.grad.clone()));
    let mut worst = 0.0f64;
    for (pi, grads) in analytic.iter().enumerate() {
        for e in (0..grads.len()).step_by(3) {
            let h = 2e-3f32;
            let mut value = 0.0;
            set(&mut moe, pi, e, |v| {
                value = *v;
                *v += h;
            });
            let lp = loss_at(&mut moe, &mut buf);
            set(&mut moe, pi, e, |v| *v = value - h);
            let lm = loss_at(&mut moe, &mut buf);
            set(&mut moe, pi, e, |v| *v = value);
            let fd = (lp - lm) / (2.0 * f64::from(h));
            let err = (f64::from(grads[e]) - fd).abs() / fd.abs().max(1e-2);
            worst = worst.max(err);
        }
    }
    assert!(worst < 2e-2, "{kind:?} shared={shared_trunk}: worst relative error {worst}");
}

fn set(moe: &mut Moe, index: usize, entry: usize, f: impl FnOnce(&mut f32)) {
    let mut k = 0;
    let mut f = Some(f);
    moe.expert_networks_mut().visit_params_mut("", &mut |_, p| {
        if k == index {
            (f.take().expect("visited once"))(&mut p.value[entry]);
        }
        k += 1;
    });
}

#[test]
fn network_gradients_of_the_weighted_nll_match_finite_differences() {
    check_network_gradient(ExpertKind::Diagonal, true);
    check_network_gradient(ExpertKind::Full, false);
}

#[test]
fn weighted_sampler_follows_its_weights() {
    let w = [1.0, 0.0, 3.0, 6.0];
    let s = RowSampler::weighted(&w).unwrap();
    let mut idx = Vec::new();
    s.draw(&mut Seeds::new(1).stream("t"), 20_000, &mut idx);
    let mut counts = [0usize; 4];
    idx.iter().for_each(|&i| counts[i] += 1);
    assert_eq!(counts[1], 0);
    for (c, w) in counts.iter().zip(w) {
        assert!((*c as f64 / 20_000.0 - w / 10.0).abs() < 0.01, "{counts:?}");
    }
    assert!(RowSampler::weighted(&[0.0, 0.0]).is_err());
    assert!(RowSampler::weighted(&[1.0, -1.0]).is_err());
    assert!(RowSampler::uniform(0).is_err());
}

#[test]
fn dataset_evaluation_matches_the_policy_likelihood() {
    use vdd_core::Policy;
    let mut mc = MoeConfig::toy(1, 2, 3);
    mc.gating = GatingKind::Learned;
    mc.experts_network.hidden_dim = 8;
    mc.gating_network.hidden_dim = 8;
    let mut moe = Moe::from_config(mc, 2).unwrap();
    let n = EVAL_CHUNK + 5; // two chunks
    let states = Mat::from_fn(n, 1, |i, _| (i % 17) as f32 * 0.1);
    let actions = Mat::from_fn(n, 2, |i, j| ((i * 3 + j) % 11) as f32 * 0.2 - 1.0);
    let data = Dataset::new(states.clone(), actions.clone()).unwrap();
    let mut resp = vec![0.0; n * 3];
    let mut ell = vec![0.0; n * 3];
    let mean = evaluate_dataset(&mut moe, &data, Some(&mut ell), Some(&mut resp)).unwrap();
    let mut ll = vec![0.0; n];
    moe.log_likelihood(states.as_ref(), actions.as_ref(), &mut ll).unwrap();
    let expect = ll.iter().map(|&x| f64::from(x)).sum::<f64>() / n as f64;
    assert_relative_eq!(mean, expect, epsilon = 1e-4);
    for o in [0, n - 1] {
        assert_relative_eq!(resp[o * 3..o * 3 + 3].iter().sum::<f32>(), 1.0, epsilon = 1e-5);
        // log q = logsumexp_z (log q(z|s) + log N_z): rebuild it from the experts' values.
        moe.forward(states.as_ref().subrows(o, 1)).unwrap();
        let lg = moe.output().log_gating_row(0).to_vec();
        let joint: Vec<f32> = (0..3).map(|z| lg[z] + ell[o * 3 + z]).collect();
        assert_relative_eq!(gaussian::log_sum_exp(&joint), ll[o], epsilon = 1e-4);
    }
}

/// A mixture with a learned gating and data of three whole blocks and a part.
fn mixture_and_blocks() -> (Moe, Dataset) {
    let mut mc = MoeConfig::toy(2, 2, 3);
    mc.gating = GatingKind::Learned;
    mc.experts_network.hidden_dim = 8;
    mc.gating_network.hidden_dim = 8;
    let moe = Moe::from_config(mc, 4).unwrap();
    let n = 3 * EVAL_CHUNK + 5;
    let states = Mat::from_fn(n, 2, |i, j| ((i * 7 + j) % 23) as f32 * 0.1 - 1.0);
    let actions = Mat::from_fn(n, 2, |i, j| ((i * 3 + j) % 11) as f32 * 0.2 - 1.0);
    (moe, Dataset::new(states, actions).unwrap())
}

/// `(mean, expert log-likelihoods, responsibilities)` of `evaluate`.
type Evaluation = (f64, Vec<f32>, Vec<f32>);

fn evaluate_with(
    eval: &mut ParallelEval<ExpertFamily>,
    moe: &mut Moe,
    data: &Dataset,
) -> Evaluation {
    let len = data.len() * moe.num_experts();
    let (mut ell, mut resp) = (vec![0.0; len], vec![0.0; len]);
    let mean =
        eval.evaluate(Scoring::Gaussian, moe, data, Some(&mut ell), Some(&mut resp)).unwrap();
    (mean, ell, resp)
}

#[test]
fn parallel_evaluation_gives_the_bits_of_one_thread() {
    let (mut moe, data) = mixture_and_blocks();
    let len = data.len() * 3;
    let (mut ell, mut resp) = (vec![0.0; len], vec![0.0; len]);
    let mean = evaluate_dataset(&mut moe, &data, Some(&mut ell), Some(&mut resp)).unwrap();
    let one = (mean, ell, resp);
    for threads in [2, 3, 5] {
        let mut eval = ParallelEval::new(vdd_nn::parallel::Workers::new(threads).unwrap());
        let got = evaluate_with(&mut eval, &mut moe, &data);
        assert_eq!(got.0.to_bits(), one.0.to_bits(), "{threads} threads");
        assert_eq!(got.1, one.1, "{threads} threads");
        assert_eq!(got.2, one.2, "{threads} threads");
        // Without outputs: the same mean.
        let mean = eval.evaluate(Scoring::Gaussian, &mut moe, &data, None, None).unwrap();
        assert_eq!(mean.to_bits(), one.0.to_bits());
    }
}

#[test]
fn parallel_evaluation_follows_the_mixture_between_calls() {
    let (mut moe, data) = mixture_and_blocks();
    let mut eval = ParallelEval::new(vdd_nn::parallel::Workers::new(2).unwrap());
    let before = evaluate_with(&mut eval, &mut moe, &data);
    // New parameter values: the replicas take them.
    moe.visit_params_mut("", &mut |_, p| p.value.iter_mut().for_each(|v| *v *= 1.5));
    let after = evaluate_with(&mut eval, &mut moe, &data);
    let mut single = ParallelEval::new(vdd_nn::parallel::Workers::inline());
    assert_eq!(after, evaluate_with(&mut single, &mut moe, &data));
    assert_ne!(after.0, before.0);
    // Another configuration (a uniform gating has no gating network): new replicas.
    let mut uniform = moe.config().clone();
    uniform.gating = GatingKind::Uniform;
    let mut moe = Moe::from_config(uniform, 4).unwrap();
    assert_eq!(
        evaluate_with(&mut eval, &mut moe, &data),
        evaluate_with(&mut single, &mut moe, &data)
    );
}

#[test]
fn parallel_evaluation_checks_its_outputs() {
    let (mut moe, data) = mixture_and_blocks();
    let mut eval = ParallelEval::new(vdd_nn::parallel::Workers::new(2).unwrap());
    let mut short = vec![0.0; 5];
    assert!(eval.evaluate(Scoring::Gaussian, &mut moe, &data, Some(&mut short), None).is_err());
    assert!(eval.evaluate(Scoring::Gaussian, &mut moe, &data, None, Some(&mut short)).is_err());
}

#[test]
fn unit_variance_scoring_is_the_authors_and_the_same_in_parallel() {
    let (mut moe, data) = mixture_and_blocks();
    let len = data.len() * 3;
    let mut outputs = Vec::new();
    for workers in [vdd_nn::parallel::Workers::inline(), vdd_nn::parallel::Workers::new(2).unwrap()]
    {
        let mut eval = ParallelEval::new(workers);
        let mut ell = vec![0.0; len];
        let mean = eval.evaluate(Scoring::UnitVariance, &mut moe, &data, Some(&mut ell), None);
        outputs.push((mean.unwrap(), ell));
    }
    assert_eq!(outputs[0], outputs[1]);
    let (mean, ell) = &outputs[0];
    // Row o, expert z: −½‖a − μ_z‖²; the mean is that of log Σ_z q(z|s) N(a; μ_z, I).
    let o = data.len() - 1;
    moe.forward(data.states().subrows(o, 1)).unwrap();
    let out = moe.output();
    let a = [data.actions()[(o, 0)], data.actions()[(o, 1)]];
    for z in 0..3 {
        let m = out.mean(0, z);
        let want = -0.5 * ((a[0] - m[0]).powi(2) + (a[1] - m[1]).powi(2));
        assert_relative_eq!(ell[o * 3 + z], want, epsilon = 1e-5);
    }
    let gaussian = eval_mean(&mut moe, &data);
    assert!(mean.is_finite() && *mean != gaussian);
}

fn eval_mean(moe: &mut Moe, data: &Dataset) -> f64 {
    evaluate_dataset(moe, data, None, None).unwrap()
}
