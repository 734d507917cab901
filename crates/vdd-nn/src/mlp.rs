//! Multi-layer perceptrons: a plain [`Mlp`] and the pre-activation [`ResidualMlp`] that the
//! official VDD and BESO code use for experts, gating and denoisers.

use faer::{Mat, MatRef};
use serde::{Deserialize, Serialize};

use crate::activation::{Activation, ActivationLayer};
use crate::error::NnError;
use crate::init::{BiasInit, Init};
use crate::linear::Linear;
use crate::module::{Module, ensure_shape, forward_as, gather_row};
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

impl Mlp {
    /// [`Module::forward`], or its inference form when `inference`.
    fn run(&mut self, x: MatRef<'_, f32>, inference: bool) -> MatRef<'_, f32> {
        let (first, rest) = self.linears.split_first_mut().expect("an Mlp has a layer");
        let mut h = forward_as(first, x, inference);
        for (act, lin) in self.activations.iter_mut().zip(rest.iter_mut()) {
            h = forward_as(act, h, inference);
            h = forward_as(lin, h, inference);
        }
        h
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
        self.run(x, false)
    }

    fn forward_inference(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32> {
        self.run(x, true)
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

impl ResidualBlock {
    /// [`Module::forward`], or its inference form when `inference`.
    fn run(&mut self, x: MatRef<'_, f32>, inference: bool) -> MatRef<'_, f32> {
        let h = match &mut self.norm1 {
            Some(n) => forward_as(n, x, inference),
            None => x,
        };
        let h = forward_as(&mut self.act1, h, inference);
        let h = forward_as(&mut self.l1, h, inference);
        let h = match &mut self.norm2 {
            Some(n) => forward_as(n, h, inference),
            None => h,
        };
        let h = forward_as(&mut self.act2, h, inference);
        let h = forward_as(&mut self.l2, h, inference);

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
}

impl Module for ResidualBlock {
    fn in_dim(&self) -> usize {
        self.l1.in_dim()
    }
    fn out_dim(&self) -> usize {
        self.l2.out_dim()
    }

    fn forward(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32> {
        self.run(x, false)
    }

    fn forward_inference(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32> {
        self.run(x, true)
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
    /// An inference pass ([`Module::forward_inference`]): run [`Module::forward`] before a
    /// backward pass.
    pub fn forward_hidden(&mut self, x: MatRef<'_, f32>) -> (MatRef<'_, f32>, &Linear) {
        (Self::trunk(&mut self.input, &mut self.blocks, x, true), &self.output)
    }

    /// The input layer and the blocks ([`forward_as`]).
    fn trunk<'a>(
        input: &'a mut Linear,
        blocks: &'a mut [ResidualBlock],
        x: MatRef<'_, f32>,
        inference: bool,
    ) -> MatRef<'a, f32> {
        let mut h = forward_as(input, x, inference);
        for b in blocks {
            h = forward_as(b, h, inference);
        }
        h
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
        let h = Self::trunk(&mut self.input, &mut self.blocks, x, false);
        self.output.forward(h)
    }

    fn forward_inference(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32> {
        let h = Self::trunk(&mut self.input, &mut self.blocks, x, true);
        self.output.forward_inference(h)
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
mod tests;
