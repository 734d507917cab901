//! Multi-layer perceptrons: a plain [`Mlp`] and the pre-activation [`ResidualMlp`] that the
//! official VDD and BESO code use for experts, gating and denoisers.

use faer::{Mat, MatRef};
use serde::{Deserialize, Serialize};

use crate::activation::{Activation, ActivationLayer};
use crate::error::NnError;
use crate::init::{BiasInit, Init};
use crate::linear::Linear;
use crate::module::{Module, ensure_shape, gather_row};
use crate::norm::LayerNorm;
use crate::param::{Param, Parameters, join_name};

/// Configuration of an [`Mlp`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MlpConfig {
    /// Input features.
    pub in_dim: usize,
    /// Widths of the hidden layers (may be empty: then the MLP is one linear layer).
    pub hidden: Vec<usize>,
    /// Output features.
    pub out_dim: usize,
    /// Nonlinearity after every hidden layer.
    pub activation: Activation,
}

/// `Linear → act → Linear → act → … → Linear`, named like `nn.Sequential`
/// (`layers.0.weight`, `layers.2.weight`, … with activations at odd indices).
///
/// ```
/// use vdd_nn::{Activation, Mlp, MlpConfig, Module};
/// let cfg = MlpConfig { in_dim: 2, hidden: vec![16, 16], out_dim: 1, activation: Activation::Tanh };
/// let mut mlp = Mlp::new(&cfg, &mut vdd_core::Seeds::new(0).stream("init")).unwrap();
/// let y = mlp.forward(faer::Mat::<f32>::zeros(5, 2).as_ref());
/// assert_eq!(y.nrows(), 5);
/// ```
#[derive(Debug, Clone)]
pub struct Mlp {
    config: MlpConfig,
    linears: Vec<Linear>,
    activations: Vec<ActivationLayer>,
}

fn check_widths(what: &str, widths: &[usize]) -> Result<(), NnError> {
    if widths.contains(&0) {
        return Err(NnError::Config(format!(
            "{what}: every width must be positive, got {widths:?}"
        )));
    }
    if let Some(w) = widths.iter().find(|&&w| w > crate::limits::MAX_WIDTH) {
        return Err(NnError::Config(format!(
            "{what}: width {w} is above the limit of {} ({widths:?})",
            crate::limits::MAX_WIDTH
        )));
    }
    Ok(())
}

impl Mlp {
    /// Builds the network with PyTorch's default initialisation.
    pub fn new(config: &MlpConfig, rng: &mut vdd_core::Rng) -> Result<Self, NnError> {
        let mut widths = vec![config.in_dim];
        widths.extend(&config.hidden);
        widths.push(config.out_dim);
        check_widths("Mlp", &widths)?;
        let count = widths
            .windows(2)
            .try_fold(0usize, |acc, w| acc.checked_add(crate::limits::linear_params(w[0], w[1])?));
        crate::limits::check_params("Mlp", count)?;
        let linears = widths.windows(2).map(|w| Linear::new(w[0], w[1], rng)).collect();
        let activations =
            config.hidden.iter().map(|&h| ActivationLayer::new(config.activation, h)).collect();
        Ok(Self { config: config.clone(), linears, activations })
    }

    /// The configuration it was built from.
    pub fn config(&self) -> &MlpConfig {
        &self.config
    }

    /// The linear layers, input first (for custom initialisation).
    pub fn linears_mut(&mut self) -> &mut [Linear] {
        &mut self.linears
    }

    /// Re-initialises every linear weight with `init`, input layer first.
    pub fn init_weights(&mut self, init: Init, rng: &mut vdd_core::Rng) -> Result<(), NnError> {
        init.validate()?;
        self.linears.iter_mut().try_for_each(|l| l.init_weight(init, rng))
    }

    /// Re-initialises every linear bias with `init`, input layer first.
    pub fn init_biases(&mut self, init: BiasInit, rng: &mut vdd_core::Rng) -> Result<(), NnError> {
        init.validate()?;
        self.linears.iter_mut().try_for_each(|l| l.init_bias(init, rng))
    }
}

impl Parameters for Mlp {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        for (i, l) in self.linears.iter().enumerate() {
            l.visit_params(&join_name(prefix, &format!("layers.{}", 2 * i)), f);
        }
    }
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        for (i, l) in self.linears.iter_mut().enumerate() {
            l.visit_params_mut(&join_name(prefix, &format!("layers.{}", 2 * i)), f);
        }
    }
}

impl Module for Mlp {
    fn in_dim(&self) -> usize {
        self.config.in_dim
    }
    fn out_dim(&self) -> usize {
        self.config.out_dim
    }

    fn forward(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32> {
        let (first, rest) = self.linears.split_first_mut().expect("an Mlp has a layer");
        let mut h = first.forward(x);
        for (act, lin) in self.activations.iter_mut().zip(rest.iter_mut()) {
            h = act.forward(h);
            h = lin.forward(h);
        }
        h
    }

    fn backward(&mut self, grad_out: MatRef<'_, f32>) -> MatRef<'_, f32> {
        let (last, init) = self.linears.split_last_mut().expect("an Mlp has a layer");
        let mut g = last.backward(grad_out);
        for (act, lin) in self.activations.iter_mut().rev().zip(init.iter_mut().rev()) {
            g = act.backward(g);
            g = lin.backward(g);
        }
        g
    }
}

/// Configuration of a [`ResidualMlp`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ResidualMlpConfig {
    /// Input features.
    pub in_dim: usize,
    /// Width of the residual stream.
    pub hidden_dim: usize,
    /// Number of two-layer pre-activation blocks.
    pub num_blocks: usize,
    /// Output features.
    pub out_dim: usize,
    /// Nonlinearity inside the blocks.
    pub activation: Activation,
    /// Layer normalisation before each of a block's two activations (`normalizer1`,
    /// `normalizer2`, PyTorch's `nn.LayerNorm(hidden_dim)` with `ε = 1e-5`, see
    /// [`ResidualMlp::set_layer_norm_eps`]), as BESO's residual blocks with `use_norm=True`.
    #[serde(default)]
    pub layer_norm: bool,
}

impl ResidualMlpConfig {
    /// Number of parameters of the network (`None` if the count overflows `usize`), computed
    /// without building it; layer norms count their weight and bias.
    pub fn num_params(&self) -> Option<usize> {
        use crate::limits::linear_params;
        let h = self.hidden_dim;
        let norms = if self.layer_norm { h.checked_mul(4)? } else { 0 };
        let block = linear_params(h, h)?.checked_mul(2)?.checked_add(norms)?;
        linear_params(self.in_dim, h)?
            .checked_add(block.checked_mul(self.num_blocks)?)?
            .checked_add(linear_params(h, self.out_dim)?)
    }
}

/// One pre-activation residual block, BESO's `TwoLayerPreActivationResNetLinear`:
///
/// ```text
/// h = x;  h = normalizer1(h)?;  h = l1(act(h));  h = normalizer2(h)?;  h = l2(act(h));  x + h
/// ```
///
/// with the layer norms only when enabled. Parameters `l1.*`, `l2.*` and, with layer norm,
/// `normalizer1.*`, `normalizer2.*`.
#[derive(Debug, Clone)]
pub struct ResidualBlock {
    norm1: Option<LayerNorm>,
    act1: ActivationLayer,
    l1: Linear,
    norm2: Option<LayerNorm>,
    act2: ActivationLayer,
    l2: Linear,
    output: Mat<f32>,
    grad_input: Mat<f32>,
    /// The output of a single-row forward pass (and the input row beside it).
    row: Vec<f32>,
}

impl ResidualBlock {
    /// A block of width `dim` without layer norm.
    pub fn new(dim: usize, activation: Activation, rng: &mut vdd_core::Rng) -> Self {
        Self::with_layer_norm(dim, activation, false, rng)
    }

    /// A block of width `dim`, with layer norms before the activations if `layer_norm`. The
    /// linear layers draw the same numbers from `rng` either way.
    pub fn with_layer_norm(
        dim: usize,
        activation: Activation,
        layer_norm: bool,
        rng: &mut vdd_core::Rng,
    ) -> Self {
        let l1 = Linear::new(dim, dim, rng);
        let l2 = Linear::new(dim, dim, rng);
        Self {
            norm1: layer_norm.then(|| LayerNorm::new(dim)),
            act1: ActivationLayer::new(activation, dim),
            l1,
            norm2: layer_norm.then(|| LayerNorm::new(dim)),
            act2: ActivationLayer::new(activation, dim),
            l2,
            output: Mat::zeros(0, 0),
            grad_input: Mat::zeros(0, 0),
            row: Vec::new(),
        }
    }

    /// The two linear layers (for custom initialisation).
    pub fn linears_mut(&mut self) -> [&mut Linear; 2] {
        [&mut self.l1, &mut self.l2]
    }

    /// The two layer norms, if the block has them.
    pub fn layer_norms_mut(&mut self) -> Option<[&mut LayerNorm; 2]> {
        match (&mut self.norm1, &mut self.norm2) {
            (Some(a), Some(b)) => Some([a, b]),
            _ => None,
        }
    }
}

impl Parameters for ResidualBlock {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        self.l1.visit_params(&join_name(prefix, "l1"), f);
        self.l2.visit_params(&join_name(prefix, "l2"), f);
        if let Some(n) = &self.norm1 {
            n.visit_params(&join_name(prefix, "normalizer1"), f);
        }
        if let Some(n) = &self.norm2 {
            n.visit_params(&join_name(prefix, "normalizer2"), f);
        }
    }
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        self.l1.visit_params_mut(&join_name(prefix, "l1"), f);
        self.l2.visit_params_mut(&join_name(prefix, "l2"), f);
        if let Some(n) = &mut self.norm1 {
            n.visit_params_mut(&join_name(prefix, "normalizer1"), f);
        }
        if let Some(n) = &mut self.norm2 {
            n.visit_params_mut(&join_name(prefix, "normalizer2"), f);
        }
    }
}

impl Module for ResidualBlock {
    fn in_dim(&self) -> usize {
        self.l1.in_dim()
    }
    fn out_dim(&self) -> usize {
        self.l2.out_dim()
    }

    fn forward(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32> {
        let h = match &mut self.norm1 {
            Some(n) => n.forward(x),
            None => x,
        };
        let h = self.act1.forward(h);
        let h = self.l1.forward(h);
        let h = match &mut self.norm2 {
            Some(n) => n.forward(h),
            None => h,
        };
        let h = self.act2.forward(h);
        let h = self.l2.forward(h);
        if x.nrows() == 1 {
            // One row: a contiguous output row (the next layer copies it with one slice copy).
            let d = x.ncols();
            self.row.resize(2 * d, 0.0);
            let (hs, xs) = self.row.split_at_mut(d);
            gather_row(h, hs);
            gather_row(x, xs);
            for (a, b) in hs.iter_mut().zip(xs.iter()) {
                *a += b;
            }
            return MatRef::from_row_major_slice(&self.row[..d], 1, d);
        }
        ensure_shape(&mut self.output, x.nrows(), x.ncols());
        add_into(&mut self.output, h, x);
        self.output.as_ref()
    }

    fn backward(&mut self, grad_out: MatRef<'_, f32>) -> MatRef<'_, f32> {
        let g = self.l2.backward(grad_out);
        let g = self.act2.backward(g);
        let g = match &mut self.norm2 {
            Some(n) => n.backward(g),
            None => g,
        };
        let g = self.l1.backward(g);
        let g = self.act1.backward(g);
        let g = match &mut self.norm1 {
            Some(n) => n.backward(g),
            None => g,
        };
        ensure_shape(&mut self.grad_input, g.nrows(), g.ncols());
        add_into(&mut self.grad_input, g, grad_out);
        self.grad_input.as_ref()
    }
}

/// `dst = a + b` (same shapes; `dst` already sized).
fn add_into(dst: &mut Mat<f32>, a: MatRef<'_, f32>, b: MatRef<'_, f32>) {
    for j in 0..dst.ncols() {
        let d = dst.col_as_slice_mut(j);
        match (a.col(j).try_as_col_major(), b.col(j).try_as_col_major()) {
            (Some(a), Some(b)) => {
                let (a, b) = (a.as_slice(), b.as_slice());
                for i in 0..d.len() {
                    d[i] = a[i] + b[i];
                }
            }
            _ => {
                for i in 0..d.len() {
                    d[i] = a[(i, j)] + b[(i, j)];
                }
            }
        }
    }
}

/// `Linear(in, hidden) → blocks → Linear(hidden, out)`, named like BESO's
/// `ResidualMLPNetwork`: `layers.0`, `layers.1` … `layers.{B}` for the blocks (each with
/// `l1`, `l2` and, with `layer_norm`, `normalizer1`, `normalizer2`; see [`ResidualBlock`]),
/// `layers.{B+1}`. A PyTorch `state_dict` of that architecture loads with
/// [`crate::io::load_safetensors`] and gives the same outputs (checked against a fixture
/// written by Python in `tests/pytorch_fixture.rs`).
///
/// ```
/// use vdd_nn::{Activation, Module, ResidualMlp, ResidualMlpConfig};
/// let cfg = ResidualMlpConfig { in_dim: 3, hidden_dim: 32, num_blocks: 2, out_dim: 4,
///                               activation: Activation::Mish, layer_norm: false };
/// let mut net = ResidualMlp::new(&cfg, &mut vdd_core::Seeds::new(0).stream("init")).unwrap();
/// assert_eq!(net.forward(faer::Mat::<f32>::zeros(8, 3).as_ref()).ncols(), 4);
/// ```
#[derive(Debug, Clone)]
pub struct ResidualMlp {
    config: ResidualMlpConfig,
    input: Linear,
    blocks: Vec<ResidualBlock>,
    output: Linear,
}

impl ResidualMlp {
    /// Builds the network with PyTorch's default initialisation.
    pub fn new(config: &ResidualMlpConfig, rng: &mut vdd_core::Rng) -> Result<Self, NnError> {
        check_widths("ResidualMlp", &[config.in_dim, config.hidden_dim, config.out_dim])?;
        if config.num_blocks > crate::limits::MAX_BLOCKS {
            return Err(NnError::Config(format!(
                "ResidualMlp: {} blocks, above the limit of {}",
                config.num_blocks,
                crate::limits::MAX_BLOCKS
            )));
        }
        crate::limits::check_params("ResidualMlp", config.num_params())?;
        let input = Linear::new(config.in_dim, config.hidden_dim, rng);
        let blocks = (0..config.num_blocks)
            .map(|_| {
                ResidualBlock::with_layer_norm(
                    config.hidden_dim,
                    config.activation,
                    config.layer_norm,
                    rng,
                )
            })
            .collect();
        let output = Linear::new(config.hidden_dim, config.out_dim, rng);
        Ok(Self { config: config.clone(), input, blocks, output })
    }

    /// The configuration it was built from.
    pub fn config(&self) -> &ResidualMlpConfig {
        &self.config
    }

    /// Every linear layer, input first (for custom initialisation).
    pub fn linears_mut(&mut self) -> Vec<&mut Linear> {
        let mut v = vec![&mut self.input];
        for b in &mut self.blocks {
            v.extend(b.linears_mut());
        }
        v.push(&mut self.output);
        v
    }

    /// The last hidden features (`n x hidden_dim`: the input layer and the blocks, without
    /// the output layer) and the output layer, so that a caller needing only some outputs
    /// computes just those columns (a mixture acting with one expert of a shared trunk).
    /// Leaves the output layer's cache stale: run [`Module::forward`] before a backward pass.
    pub fn forward_hidden(&mut self, x: MatRef<'_, f32>) -> (MatRef<'_, f32>, &Linear) {
        let mut h = self.input.forward(x);
        for b in &mut self.blocks {
            h = b.forward(h);
        }
        (h, &self.output)
    }

    /// The output layer (e.g. to initialise its bias in a range).
    pub fn output_layer_mut(&mut self) -> &mut Linear {
        &mut self.output
    }

    /// The residual blocks.
    pub fn blocks_mut(&mut self) -> &mut [ResidualBlock] {
        &mut self.blocks
    }

    /// Re-initialises every linear weight with `init`, input layer first.
    pub fn init_weights(&mut self, init: Init, rng: &mut vdd_core::Rng) -> Result<(), NnError> {
        init.validate()?;
        self.linears_mut().into_iter().try_for_each(|l| l.init_weight(init, rng))
    }

    /// Re-initialises every linear bias with `init`, input layer first.
    pub fn init_biases(&mut self, init: BiasInit, rng: &mut vdd_core::Rng) -> Result<(), NnError> {
        init.validate()?;
        self.linears_mut().into_iter().try_for_each(|l| l.init_bias(init, rng))
    }

    /// Sets the layer norms' `ε` (PyTorch's default `1e-5`; BESO's blocks use `1e-6`). An error
    /// if `eps` is not finite and positive; no effect without layer norm.
    pub fn set_layer_norm_eps(&mut self, eps: f32) -> Result<(), NnError> {
        for b in &mut self.blocks {
            if let Some(norms) = b.layer_norms_mut() {
                for n in norms {
                    n.set_eps(eps)?;
                }
            }
        }
        Ok(())
    }
}

impl Parameters for ResidualMlp {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        self.input.visit_params(&join_name(prefix, "layers.0"), f);
        for (i, b) in self.blocks.iter().enumerate() {
            b.visit_params(&join_name(prefix, &format!("layers.{}", i + 1)), f);
        }
        let last = format!("layers.{}", self.blocks.len() + 1);
        self.output.visit_params(&join_name(prefix, &last), f);
    }
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        self.input.visit_params_mut(&join_name(prefix, "layers.0"), f);
        for (i, b) in self.blocks.iter_mut().enumerate() {
            b.visit_params_mut(&join_name(prefix, &format!("layers.{}", i + 1)), f);
        }
        let last = format!("layers.{}", self.blocks.len() + 1);
        self.output.visit_params_mut(&join_name(prefix, &last), f);
    }
}

impl Module for ResidualMlp {
    fn in_dim(&self) -> usize {
        self.config.in_dim
    }
    fn out_dim(&self) -> usize {
        self.config.out_dim
    }

    fn forward(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32> {
        let mut h = self.input.forward(x);
        for b in &mut self.blocks {
            h = b.forward(h);
        }
        self.output.forward(h)
    }

    fn backward(&mut self, grad_out: MatRef<'_, f32>) -> MatRef<'_, f32> {
        let mut g = self.output.backward(grad_out);
        for b in self.blocks.iter_mut().rev() {
            g = b.backward(g);
        }
        self.input.backward(g)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::gradcheck::check_module;

    fn input(n: usize, d: usize) -> Mat<f32> {
        Mat::from_fn(n, d, |i, j| ((i * 7 + j * 3) % 11) as f32 / 5.5 - 1.0)
    }

    #[test]
    fn residual_mlp_gradients_match_finite_differences() {
        let mut rng = vdd_core::Seeds::new(1).stream("t");
        for act in [Activation::Mish, Activation::Tanh, Activation::Silu, Activation::Gelu] {
            let cfg = ResidualMlpConfig {
                in_dim: 3,
                hidden_dim: 8,
                num_blocks: 2,
                out_dim: 2,
                activation: act,
                layer_norm: false,
            };
            let mut net = ResidualMlp::new(&cfg, &mut rng).unwrap();
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
        want.splice(
            6..6,
            ["layers.1.normalizer1", "layers.1.normalizer2"].iter().flat_map(|p| lin(p)),
        );
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
        let cfg =
            MlpConfig { in_dim: 4, hidden: vec![6, 5], out_dim: 3, activation: Activation::Tanh };
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
}
