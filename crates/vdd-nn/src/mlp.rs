//! Multi-layer perceptrons: a plain [`Mlp`] and the pre-activation [`ResidualMlp`] that the
//! official VDD and BESO code use for experts, gating and denoisers.

use faer::{Mat, MatRef};
use serde::{Deserialize, Serialize};

use crate::activation::{Activation, ActivationLayer};
use crate::error::NnError;
use crate::linear::Linear;
use crate::module::{ensure_shape, Module};
use crate::param::{join_name, Param, Parameters};

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
    Ok(())
}

impl Mlp {
    /// Builds the network with PyTorch's default initialisation.
    pub fn new(config: &MlpConfig, rng: &mut vdd_core::Rng) -> Result<Self, NnError> {
        let mut widths = vec![config.in_dim];
        widths.extend(&config.hidden);
        widths.push(config.out_dim);
        check_widths("Mlp", &widths)?;
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
    /// Layer normalisation before each block's activations (`norm1`, `norm2`), as in the
    /// official VDD/BESO residual blocks with `use_norm=True`.
    #[serde(default)]
    pub layer_norm: bool,
}

/// One pre-activation residual block: `x + l2(act(l1(act(x))))`, named `l1`, `l2` as in BESO's
/// `TwoLayerPreActivationResNetLinear`.
#[derive(Debug, Clone)]
pub struct ResidualBlock {
    act1: ActivationLayer,
    l1: Linear,
    act2: ActivationLayer,
    l2: Linear,
    output: Mat<f32>,
    grad_input: Mat<f32>,
}

impl ResidualBlock {
    /// A block of width `dim`.
    pub fn new(dim: usize, activation: Activation, rng: &mut vdd_core::Rng) -> Self {
        Self {
            act1: ActivationLayer::new(activation, dim),
            l1: Linear::new(dim, dim, rng),
            act2: ActivationLayer::new(activation, dim),
            l2: Linear::new(dim, dim, rng),
            output: Mat::zeros(0, 0),
            grad_input: Mat::zeros(0, 0),
        }
    }

    /// The two linear layers (for custom initialisation).
    pub fn linears_mut(&mut self) -> [&mut Linear; 2] {
        [&mut self.l1, &mut self.l2]
    }
}

impl Parameters for ResidualBlock {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        self.l1.visit_params(&join_name(prefix, "l1"), f);
        self.l2.visit_params(&join_name(prefix, "l2"), f);
    }
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        self.l1.visit_params_mut(&join_name(prefix, "l1"), f);
        self.l2.visit_params_mut(&join_name(prefix, "l2"), f);
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
        let h = self.act1.forward(x);
        let h = self.l1.forward(h);
        let h = self.act2.forward(h);
        let h = self.l2.forward(h);
        ensure_shape(&mut self.output, x.nrows(), x.ncols());
        self.output.copy_from(h);
        self.output += x;
        self.output.as_ref()
    }

    fn backward(&mut self, grad_out: MatRef<'_, f32>) -> MatRef<'_, f32> {
        let g = self.l2.backward(grad_out);
        let g = self.act2.backward(g);
        let g = self.l1.backward(g);
        let g = self.act1.backward(g);
        ensure_shape(&mut self.grad_input, g.nrows(), g.ncols());
        self.grad_input.copy_from(g);
        self.grad_input += grad_out;
        self.grad_input.as_ref()
    }
}

/// `Linear(in, hidden) → blocks → Linear(hidden, out)`, named like BESO's
/// `ResidualMLPNetwork`: `layers.0`, `layers.1` … `layers.{B}` for the blocks, `layers.{B+1}`.
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
        if config.layer_norm {
            return Err(NnError::Config(
                "layer_norm residual blocks are not implemented yet".into(),
            ));
        }
        let input = Linear::new(config.in_dim, config.hidden_dim, rng);
        let blocks = (0..config.num_blocks)
            .map(|_| ResidualBlock::new(config.hidden_dim, config.activation, rng))
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

    /// The output layer (e.g. to initialise its bias in a range).
    pub fn output_layer_mut(&mut self) -> &mut Linear {
        &mut self.output
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
        }
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
