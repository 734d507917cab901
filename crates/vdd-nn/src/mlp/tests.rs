//! Tests of the MLPs: gradients, inference passes, naming.

use super::*;
use crate::gradcheck::check_module;

fn input(n: usize, d: usize) -> Mat<f32> {
    Mat::from_fn(n, d, |i, j| ((i * 7 + j * 3) % 11) as f32 / 5.5 - 1.0)
}

/// A `3 → 8 → 2` residual MLP with two blocks.
fn small_net(activation: Activation, layer_norm: bool, rng: &mut vdd_core::Rng) -> ResidualMlp {
    let cfg = ResidualMlpConfig {
        in_dim: 3,
        hidden_dim: 8,
        num_blocks: 2,
        out_dim: 2,
        activation,
        layer_norm,
    };
    ResidualMlp::new(&cfg, rng).unwrap()
}

/// `forward_inference` gives `forward`'s bits, on one row and on many, for every
/// activation, with and without layer norm; a backward right after it panics.
#[test]
fn inference_passes_give_the_forward_bits() {
    let mut rng = vdd_core::Seeds::new(4).stream("t");
    for act in crate::activation::tests::ALL {
        for layer_norm in [false, true] {
            let mut net = small_net(act, layer_norm, &mut rng);
            let plain = MlpConfig { in_dim: 3, hidden: vec![8, 5], out_dim: 2, activation: act };
            let mut mlp = Mlp::new(&plain, &mut rng).unwrap();
            for n in [1, 7] {
                // Large inputs reach the activations' saturated ends.
                let x = Mat::from_fn(n, 3, |i, j| (input(n, 3)[(i, j)]) * 9.0);
                let want = net.forward(x.as_ref()).to_owned();
                let got = net.forward_inference(x.as_ref()).to_owned();
                let bits = |m: &Mat<f32>| {
                    m.col_iter()
                        .flat_map(|c| c.iter().map(|v| v.to_bits()).collect::<Vec<_>>())
                        .collect::<Vec<_>>()
                };
                assert_eq!(bits(&got), bits(&want), "{act:?} norm {layer_norm} n {n}");
                let want = mlp.forward(x.as_ref()).to_owned();
                assert_eq!(bits(&mlp.forward_inference(x.as_ref()).to_owned()), bits(&want));
            }
        }
    }
    let mut net = small_net(Activation::Mish, false, &mut rng);
    for n in [1, 5] {
        net.forward_inference(input(n, 3).as_ref());
        let g = Mat::<f32>::zeros(n, 2);
        let r = std::panic::catch_unwind(std::panic::AssertUnwindSafe(|| {
            net.backward(g.as_ref());
        }));
        assert!(r.is_err(), "a backward after an inference pass (n = {n}) must panic");
        // A training forward makes the backward valid again.
        net.forward(input(n, 3).as_ref());
        net.backward(g.as_ref());
    }
}

#[test]
fn residual_mlp_gradients_match_finite_differences() {
    let mut rng = vdd_core::Seeds::new(1).stream("t");
    for act in [Activation::Mish, Activation::Tanh, Activation::Silu, Activation::Gelu] {
        let mut net = small_net(act, false, &mut rng);
        let r = check_module(&mut net, input(5, 3).as_ref(), 1e-2, 1e-2, &mut rng);
        assert!(r.input_error < 5e-3 && r.param_error < 5e-3, "{act:?}: {r:?}");
        // One row takes the layers' single-row paths (row kernels, contiguous outputs).
        let r = check_module(&mut net, input(1, 3).as_ref(), 1e-2, 1e-2, &mut rng);
        assert!(r.input_error < 5e-3 && r.param_error < 5e-3, "{act:?}, one row: {r:?}");
    }
}

#[test]
fn one_row_at_a_time_gives_the_batch_rows() {
    let cfg = ResidualMlpConfig {
        in_dim: 5,
        hidden_dim: 40,
        num_blocks: 2,
        out_dim: 3,
        activation: Activation::Mish,
        layer_norm: false,
    };
    let mut net = ResidualMlp::new(&cfg, &mut vdd_core::Seeds::new(2).stream("t")).unwrap();
    let x = input(6, 5);
    let batch = net.forward(x.as_ref()).to_owned();
    for i in 0..6 {
        let one = net.forward(x.subrows(i, 1)).to_owned();
        for j in 0..3 {
            let (a, b) = (one[(0, j)], batch[(i, j)]);
            assert!((a - b).abs() <= 1e-5 * (1.0 + b.abs()), "row {i}: {a} vs {b}");
        }
    }
}

#[test]
fn residual_mlp_with_layer_norm_gradients_match_finite_differences() {
    let mut rng = vdd_core::Seeds::new(8).stream("t");
    for act in [Activation::Mish, Activation::Tanh] {
        let cfg = ResidualMlpConfig {
            in_dim: 3,
            hidden_dim: 6,
            num_blocks: 2,
            out_dim: 2,
            activation: act,
            layer_norm: true,
        };
        let mut net = ResidualMlp::new(&cfg, &mut rng).unwrap();
        // Non-trivial affine parameters so that their gradients are exercised.
        net.visit_params_mut("", &mut |name, p| {
            if name.contains("normalizer") {
                let base = if name.ends_with("weight") { 1.0 } else { 0.0 };
                p.value.iter_mut().enumerate().for_each(|(k, v)| *v = base + 0.1 * k as f32);
            }
        });
        // Layer norm makes the f32 network curved enough that the finite differences need
        // a larger step (with Richardson extrapolation its truncation error is O(h⁴)).
        let r = check_module(&mut net, input(5, 3).as_ref(), 3e-2, 1e-2, &mut rng);
        assert!(r.input_error < 3e-3 && r.param_error < 3e-3, "{act:?}: {r:?}");
    }
}

fn names(net: &dyn Parameters) -> Vec<String> {
    let mut v = Vec::new();
    net.visit_params("", &mut |n, _| v.push(n.to_owned()));
    v
}

fn cfg(layer_norm: bool) -> ResidualMlpConfig {
    ResidualMlpConfig {
        in_dim: 3,
        hidden_dim: 5,
        num_blocks: 1,
        out_dim: 2,
        activation: Activation::Mish,
        layer_norm,
    }
}

#[test]
fn parameter_names_follow_beso() {
    let seeds = vdd_core::Seeds::new(9);
    let plain = ResidualMlp::new(&cfg(false), &mut seeds.stream("i")).unwrap();
    let lin = |p: &str| [format!("{p}.weight"), format!("{p}.bias")];
    let mut want: Vec<String> = ["layers.0", "layers.1.l1", "layers.1.l2", "layers.2"]
        .iter()
        .flat_map(|p| lin(p))
        .collect();
    assert_eq!(names(&plain), want);
    let normed = ResidualMlp::new(&cfg(true), &mut seeds.stream("i")).unwrap();
    want.splice(6..6, ["layers.1.normalizer1", "layers.1.normalizer2"].iter().flat_map(|p| lin(p)));
    assert_eq!(names(&normed), want);
    // The linear layers draw the same numbers with and without layer norm.
    let mut a = plain.clone();
    let mut b = normed.clone();
    let wa: Vec<_> = a.linears_mut().iter().map(|l| l.weight.value.clone()).collect();
    let wb: Vec<_> = b.linears_mut().iter().map(|l| l.weight.value.clone()).collect();
    assert_eq!(wa, wb);
}

/// The residual MLP in f64 from its parameters: `layers.0`, then per block
/// `x + l2(act(n2(l1(act(n1(x))))))`, then the output layer.
fn reference_forward(net: &mut ResidualMlp, x: &Mat<f32>) -> Vec<Vec<f64>> {
    let act = net.config().activation;
    let ln = net.config().layer_norm;
    let lin = |l: &Linear, h: &[f64]| -> Vec<f64> {
        (0..l.out_dim())
            .map(|o| {
                f64::from(l.bias.value[o])
                    + (0..l.in_dim())
                        .map(|i| f64::from(l.weight.value[o * l.in_dim() + i]) * h[i])
                        .sum::<f64>()
            })
            .collect()
    };
    let norm = |n: &LayerNorm, h: &[f64]| -> Vec<f64> {
        let d = h.len() as f64;
        let m = h.iter().sum::<f64>() / d;
        let v = h.iter().map(|a| (a - m).powi(2)).sum::<f64>() / d;
        h.iter()
            .enumerate()
            .map(|(k, a)| {
                (a - m) / (v + f64::from(n.eps())).sqrt() * f64::from(n.weight.value[k])
                    + f64::from(n.bias.value[k])
            })
            .collect()
    };
    let a = |h: Vec<f64>| -> Vec<f64> {
        h.into_iter().map(|v| f64::from(act.apply(v as f32))).collect()
    };
    (0..x.nrows())
        .map(|i| {
            let row: Vec<f64> = (0..x.ncols()).map(|j| f64::from(x[(i, j)])).collect();
            let mut h = lin(&net.input, &row);
            for b in &net.blocks {
                let mut t = h.clone();
                if ln {
                    t = norm(b.norm1.as_ref().unwrap(), &t);
                }
                t = lin(&b.l1, &a(t));
                if ln {
                    t = norm(b.norm2.as_ref().unwrap(), &t);
                }
                t = lin(&b.l2, &a(t));
                h = h.iter().zip(&t).map(|(u, v)| u + v).collect();
            }
            lin(&net.output, &h)
        })
        .collect()
}

#[test]
fn forward_matches_the_reference_composition() {
    let seeds = vdd_core::Seeds::new(10);
    let x = input(7, 3);
    for ln in [false, true] {
        let mut net = ResidualMlp::new(&cfg(ln), &mut seeds.stream("i")).unwrap();
        net.visit_params_mut("", &mut |name, p| {
            if name.contains("normalizer") {
                p.value.iter_mut().enumerate().for_each(|(k, v)| *v += 0.2 * k as f32);
            }
        });
        let want = reference_forward(&mut net, &x);
        let got = net.forward(x.as_ref()).to_owned();
        for (i, row) in want.iter().enumerate() {
            for (j, w) in row.iter().enumerate() {
                assert!((f64::from(got[(i, j)]) - w).abs() < 1e-5, "ln={ln} ({i},{j})");
            }
        }
    }
    // Layer norm changes the function (it is not silently skipped).
    let mut a = ResidualMlp::new(&cfg(false), &mut seeds.stream("i")).unwrap();
    let mut b = ResidualMlp::new(&cfg(true), &mut seeds.stream("i")).unwrap();
    assert_ne!(a.forward(x.as_ref()).to_owned(), b.forward(x.as_ref()).to_owned());
    assert!(b.set_layer_norm_eps(-1.0).is_err());
    b.set_layer_norm_eps(1e-6).unwrap();
    assert_eq!(b.blocks_mut()[0].layer_norms_mut().unwrap()[1].eps(), 1e-6);
}

#[test]
fn init_weights_reaches_every_linear() {
    let mut rng = vdd_core::Seeds::new(11).stream("i");
    let mut net = ResidualMlp::new(&cfg(true), &mut rng).unwrap();
    net.init_weights(crate::init::Init::Orthogonal { gain: 2.0 }, &mut rng).unwrap();
    net.init_biases(crate::init::BiasInit::Zero, &mut rng).unwrap();
    for l in net.linears_mut() {
        let (o, i) = (l.out_dim(), l.in_dim());
        let w = Mat::from_fn(o, i, |r, c| l.weight.value[r * i + c]);
        // The smaller Gram matrix is gain² I = 4 I.
        let g = if o <= i { &w * w.transpose() } else { w.transpose() * &w };
        for a in 0..g.nrows() {
            for b in 0..g.ncols() {
                assert!((g[(a, b)] - if a == b { 4.0 } else { 0.0 }).abs() < 1e-4);
            }
        }
        assert!(l.bias.value.iter().all(|&v| v == 0.0));
    }
    let mut mlp = Mlp::new(
        &MlpConfig { in_dim: 2, hidden: vec![4], out_dim: 1, activation: Activation::Relu },
        &mut rng,
    )
    .unwrap();
    mlp.init_biases(crate::init::BiasInit::Uniform { low: 1.0, high: 1.0 }, &mut rng).unwrap();
    assert!(mlp.linears_mut().iter().all(|l| l.bias.value.iter().all(|&b| b == 1.0)));
    let before = mlp.linears_mut()[0].weight.value.clone();
    let bad = crate::init::Init::Uniform { low: 1.0, high: 0.0 };
    assert!(mlp.init_weights(bad, &mut rng).is_err());
    assert_eq!(mlp.linears_mut()[0].weight.value, before, "unchanged on error");
}

#[test]
fn mlp_gradients_match_finite_differences() {
    let mut rng = vdd_core::Seeds::new(2).stream("t");
    let cfg = MlpConfig { in_dim: 4, hidden: vec![6, 5], out_dim: 3, activation: Activation::Tanh };
    let mut net = Mlp::new(&cfg, &mut rng).unwrap();
    let r = check_module(&mut net, input(6, 4).as_ref(), 1e-2, 1e-2, &mut rng);
    assert!(r.input_error < 5e-3 && r.param_error < 5e-3, "{r:?}");
}

#[test]
fn a_wrong_backward_is_caught() {
    // Sanity check of the checker itself: scaling a weight gradient must be detected.
    let mut rng = vdd_core::Seeds::new(3).stream("t");
    let mut layer = Linear::new(3, 2, &mut rng);
    let x = input(4, 3);
    layer.zero_grad();
    layer.forward(x.as_ref());
    let r = check_module(&mut layer, x.as_ref(), 1e-2, 1e-2, &mut rng);
    assert!(r.param_error < 5e-3);
    let mut broken = BrokenLinear(layer);
    let r = check_module(&mut broken, x.as_ref(), 1e-2, 1e-2, &mut rng);
    assert!(r.param_error > 0.1, "{r:?}");
}

struct BrokenLinear(Linear);
impl Parameters for BrokenLinear {
    fn visit_params(&self, p: &str, f: &mut dyn FnMut(&str, &Param)) {
        self.0.visit_params(p, f)
    }
    fn visit_params_mut(&mut self, p: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        self.0.visit_params_mut(p, f)
    }
}
impl Module for BrokenLinear {
    fn in_dim(&self) -> usize {
        self.0.in_dim()
    }
    fn out_dim(&self) -> usize {
        self.0.out_dim()
    }
    fn forward(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32> {
        self.0.forward(x)
    }
    fn backward(&mut self, g: MatRef<'_, f32>) -> MatRef<'_, f32> {
        // Accumulates the parameter gradients twice; the input gradient stays right.
        self.0.backward(g);
        self.0.backward(g)
    }
}
