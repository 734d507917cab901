//! The state-conditioned denoiser network shared by both teachers: a [`ResidualMlp`] over
//! `[noisy action (flattened chunk), state, noise-level embedding]`.

use faer::{Mat, MatMut, MatRef};
use serde::{Deserialize, Serialize};
use vdd_nn::{Activation, Module, Param, Parameters, ResidualMlp, ResidualMlpConfig};

use crate::error::{DiffusionError, Result};

/// Architecture of the denoiser network.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NetConfig {
    /// Width of the residual stream.
    pub hidden_dim: usize,
    /// Number of two-layer pre-activation residual blocks.
    pub num_blocks: usize,
    /// Nonlinearity inside the blocks.
    pub activation: Activation,
    /// Size of the sinusoidal noise-level embedding (even, ≥ 2).
    pub embed_dim: usize,
    /// Highest angular frequency of the embedding; frequencies are geometric in
    /// `[1, max_frequency]`. The embedded quantity is `c_noise = ln(σ) / 4`.
    pub max_frequency: f32,
}

impl Default for NetConfig {
    fn default() -> Self {
        Self {
            hidden_dim: 128,
            num_blocks: 2,
            activation: Activation::Mish,
            embed_dim: 16,
            max_frequency: 16.0,
        }
    }
}

impl NetConfig {
    /// Checks the numbers.
    pub fn validate(&self) -> Result<()> {
        use vdd_nn::limits::{MAX_BLOCKS, MAX_WIDTH};
        if self.hidden_dim == 0 || self.hidden_dim > MAX_WIDTH {
            return Err(DiffusionError::Config(format!(
                "hidden_dim must be in 1..={MAX_WIDTH}, got {}",
                self.hidden_dim
            )));
        }
        if self.num_blocks > MAX_BLOCKS {
            return Err(DiffusionError::Config(format!(
                "num_blocks must be <= {MAX_BLOCKS}, got {}",
                self.num_blocks
            )));
        }
        if self.embed_dim < 2 || self.embed_dim % 2 != 0 || self.embed_dim > MAX_WIDTH {
            return Err(DiffusionError::Config(format!(
                "embed_dim must be even and in 2..={MAX_WIDTH}, got {}",
                self.embed_dim
            )));
        }
        if !(self.max_frequency.is_finite() && self.max_frequency >= 1.0) {
            return Err(DiffusionError::Config(format!(
                "max_frequency must be >= 1, got {}",
                self.max_frequency
            )));
        }
        Ok(())
    }

    /// The architecture of the residual MLP of a network over
    /// `[noisy action (action_dim) | state (state_dim) | levels noise-level embeddings]` with
    /// `action_dim` outputs and no layer normalisation: a [`DenoiserNet`] with `levels` noise
    /// conditions (the teachers use one; a consistency trajectory model's `g(x, t, u)` two).
    pub fn mlp_config(
        &self,
        action_dim: usize,
        state_dim: usize,
        levels: usize,
    ) -> ResidualMlpConfig {
        ResidualMlpConfig {
            in_dim: action_dim + state_dim + levels * self.embed_dim,
            hidden_dim: self.hidden_dim,
            num_blocks: self.num_blocks,
            out_dim: action_dim,
            activation: self.activation,
            layer_norm: false,
        }
    }
}

/// The fixed sinusoidal embedding of a noise condition `c` (no parameters):
/// `[sin(ω_k c)]_k` followed by `[cos(ω_k c)]_k`, with the `embed_dim / 2` frequencies `ω_k`
/// geometric in `[1, max_frequency]` of a [`NetConfig`] (a single frequency is 1).
///
/// ```
/// use vdd_diffusion::{NetConfig, NoiseEmbedding};
/// let emb = NoiseEmbedding::new(&NetConfig { embed_dim: 4, max_frequency: 16.0, ..Default::default() });
/// let mut out = [0.0f32; 4];
/// emb.embed(0.5, &mut out);
/// assert_eq!(out, [0.5f32.sin(), 8.0f32.sin(), 0.5f32.cos(), 8.0f32.cos()]);
/// ```
#[derive(Debug, Clone, PartialEq)]
pub struct NoiseEmbedding {
    freqs: Vec<f32>,
}

impl NoiseEmbedding {
    /// The embedding of `config` (`embed_dim` and `max_frequency`, see [`NetConfig::validate`]).
    pub fn new(config: &NetConfig) -> Self {
        let h = config.embed_dim / 2;
        let freqs =
            (0..h)
                .map(|k| {
                    if h == 1 { 1.0 } else { config.max_frequency.powf(k as f32 / (h - 1) as f32) }
                })
                .collect();
        Self { freqs }
    }

    /// Length of one embedding (`embed_dim`).
    pub fn dim(&self) -> usize {
        2 * self.freqs.len()
    }

    /// Writes the embedding of `c` into `out` (`embed_dim` long).
    pub fn embed(&self, c: f32, out: &mut [f32]) {
        let h = self.freqs.len();
        for (k, w) in self.freqs.iter().enumerate() {
            let (s, co) = (w * c).sin_cos();
            out[k] = s;
            out[h + k] = co;
        }
    }

    /// Writes the input rows `[x | states | emb(c_1) | … | emb(c_L)]` of a network conditioned
    /// on `L = conditions.len()` noise levels into `input`, which is resized when its shape
    /// differs: `x` is `n x d_a`, `states` `n x d_s`, and each condition `c_l` has `n` entries.
    ///
    /// # Panics
    /// On mismatched shapes (callers check them first).
    pub fn write_input<C: AsRef<[f32]>>(
        &self,
        input: &mut Mat<f32>,
        x: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        conditions: &[C],
    ) {
        let (n, da, ds, e) = (x.nrows(), x.ncols(), states.ncols(), self.dim());
        let width = da + ds + conditions.len() * e;
        if input.nrows() != n || input.ncols() != width {
            *input = Mat::zeros(n, width);
        }
        input.as_mut().subcols_mut(0, da).copy_from(x);
        input.as_mut().subcols_mut(da, ds).copy_from(states);
        for (level, c) in conditions.iter().enumerate() {
            self.write_columns(c.as_ref(), input.as_mut(), da + ds + level * e);
        }
    }

    /// Writes the embedding of `c[i]` into row `i`, columns `base..base + embed_dim`, of `out`.
    fn write_columns(&self, c: &[f32], mut out: MatMut<'_, f32>, base: usize) {
        let h = self.freqs.len();
        for (k, &w) in self.freqs.iter().enumerate() {
            for (i, &ci) in c.iter().enumerate() {
                let (s, co) = (w * ci).sin_cos();
                out[(i, base + k)] = s;
                out[(i, base + h + k)] = co;
            }
        }
    }
}

/// Per-row coefficients of a preconditioned evaluation of a [`DenoiserNet`] `F`
/// ([`DenoiserNet::forward_preconditioned`]):
///
/// `out_i = c_skip_i x_i + c_out_i F(c_in_i x_i, s_i, c_noise_i^(1), …, c_noise_i^(L))`.
///
/// EDM's denoiser `D(x; σ) = c_skip(σ) x + c_out(σ) F(c_in(σ) x, c_noise(σ))` is the case of one
/// noise condition with [`Preconditioning`](crate::Preconditioning)'s coefficients
/// ([`Preconditioning::write_coefficients`](crate::Preconditioning::write_coefficients)); other
/// preconditionings (a consistency model's boundary condition at `σ_min`, a trajectory model's
/// jump from `t` to `u` with two conditions) write their own coefficients and reuse the same
/// network and evaluation.
///
/// ```
/// use vdd_diffusion::RowCoefficients;
/// let mut coef = RowCoefficients::default();
/// coef.clear(2);
/// coef.push(0.5, &[0.1, -0.2], 1.0, 0.0);
/// assert_eq!((coef.len(), coef.levels()), (1, 2));
/// assert_eq!(coef.c_noise[1], vec![-0.2]);
/// ```
#[derive(Debug, Clone, Default, PartialEq)]
pub struct RowCoefficients {
    /// Input scaling `c_in` per row.
    pub c_in: Vec<f32>,
    /// The noise conditions: one vector per condition of the network, each with one entry per
    /// row.
    pub c_noise: Vec<Vec<f32>>,
    /// Skip-connection weight `c_skip` per row.
    pub c_skip: Vec<f32>,
    /// Output scaling `c_out` per row.
    pub c_out: Vec<f32>,
}

impl RowCoefficients {
    /// Removes every row and sets the number of noise conditions to `levels` (buffers are
    /// kept).
    pub fn clear(&mut self, levels: usize) {
        self.c_in.clear();
        self.c_noise.resize_with(levels, Vec::new);
        self.c_noise.iter_mut().for_each(Vec::clear);
        self.c_skip.clear();
        self.c_out.clear();
    }

    /// Appends a row: `c_noise` has one entry per noise condition.
    ///
    /// # Panics
    /// When `c_noise` does not have [`RowCoefficients::levels`] entries.
    pub fn push(&mut self, c_in: f32, c_noise: &[f32], c_skip: f32, c_out: f32) {
        assert_eq!(c_noise.len(), self.c_noise.len(), "RowCoefficients: noise conditions");
        self.c_in.push(c_in);
        for (v, &c) in self.c_noise.iter_mut().zip(c_noise) {
            v.push(c);
        }
        self.c_skip.push(c_skip);
        self.c_out.push(c_out);
    }

    /// Number of rows.
    pub fn len(&self) -> usize {
        self.c_in.len()
    }

    /// Whether there are no rows.
    pub fn is_empty(&self) -> bool {
        self.c_in.is_empty()
    }

    /// Number of noise conditions.
    pub fn levels(&self) -> usize {
        self.c_noise.len()
    }
}

/// A denoiser network `F(x, s, c_noise)` mapping `n x action_dim` noisy (and, for EDM,
/// `c_in`-scaled) actions, `n x state_dim` states and `n` noise conditions to `n x action_dim`
/// outputs (the `ε` prediction for DDPM, the preconditioned `F` for EDM).
///
/// The noise condition is embedded as `[sin(ω_k c), cos(ω_k c)]_k` with `ω_k` geometric in
/// `[1, max_frequency]` (a fixed sinusoidal embedding, [`NoiseEmbedding`]; no parameters). Parameters are named
/// `net.layers.*` after BESO's `ResidualMLPNetwork`.
///
/// The teachers' networks take one noise condition ([`DenoiserNet::new`]); a network may take
/// several ([`DenoiserNet::with_levels`], each embedded in its own block after the first), as
/// the students of consistency distillation do (one level for a consistency model, two for a
/// trajectory model's jump `g(x, t, u)`). [`DenoiserNet::forward_preconditioned`] evaluates
/// `c_skip x + c_out F(c_in x, …)` with per-row coefficients ([`RowCoefficients`]).
#[derive(Debug, Clone)]
pub struct DenoiserNet {
    config: NetConfig,
    action_dim: usize,
    state_dim: usize,
    levels: usize,
    mlp: ResidualMlp,
    embedding: NoiseEmbedding,
    input: Mat<f32>,
    x_in: Mat<f32>,
}

impl DenoiserNet {
    /// A freshly initialised network with one noise condition (PyTorch's default
    /// initialisation).
    pub fn new(
        config: &NetConfig,
        action_dim: usize,
        state_dim: usize,
        rng: &mut vdd_core::Rng,
    ) -> Result<Self> {
        Self::with_levels(config, action_dim, state_dim, 1, rng)
    }

    /// A freshly initialised network conditioned on `levels ≥ 1` noise levels (PyTorch's
    /// default initialisation; the weights are drawn from `rng` exactly as for one level, only
    /// the input layer is wider).
    ///
    /// ```
    /// use vdd_diffusion::{DenoiserNet, NetConfig};
    /// let cfg = NetConfig { hidden_dim: 16, num_blocks: 1, ..Default::default() };
    /// let mut rng = vdd_core::Seeds::new(0).stream("init");
    /// let mut net = DenoiserNet::with_levels(&cfg, 2, 1, 2, &mut rng).unwrap();
    /// let (x, s) = (faer::Mat::<f32>::zeros(3, 2), faer::Mat::<f32>::zeros(3, 1));
    /// let (t, u) = ([0.1f32, 0.2, 0.3], [0.0f32, 0.0, 0.1]);
    /// let y = net.forward_conditioned(x.as_ref(), s.as_ref(), &[&t[..], &u[..]]);
    /// assert_eq!((y.nrows(), y.ncols()), (3, 2));
    /// assert_eq!(net.levels(), 2);
    /// ```
    pub fn with_levels(
        config: &NetConfig,
        action_dim: usize,
        state_dim: usize,
        levels: usize,
        rng: &mut vdd_core::Rng,
    ) -> Result<Self> {
        config.validate()?;
        let max = vdd_nn::limits::MAX_WIDTH;
        if action_dim == 0 || action_dim > max || state_dim > max {
            return Err(DiffusionError::Config(format!(
                "need 1 <= action_dim <= {max} and state_dim <= {max}, got {action_dim}, {state_dim}"
            )));
        }
        if levels == 0 || levels > 16 {
            return Err(DiffusionError::Config(format!(
                "a denoiser network takes 1 to 16 noise levels, got {levels}"
            )));
        }
        let mlp = ResidualMlp::new(&config.mlp_config(action_dim, state_dim, levels), rng)?;
        Ok(Self {
            config: config.clone(),
            action_dim,
            state_dim,
            levels,
            mlp,
            embedding: NoiseEmbedding::new(config),
            input: Mat::zeros(0, 0),
            x_in: Mat::zeros(0, 0),
        })
    }

    /// The architecture.
    pub fn config(&self) -> &NetConfig {
        &self.config
    }

    /// Action (output) dimension.
    pub fn action_dim(&self) -> usize {
        self.action_dim
    }

    /// State dimension.
    pub fn state_dim(&self) -> usize {
        self.state_dim
    }

    /// Number of noise conditions (1 for the teachers).
    pub fn levels(&self) -> usize {
        self.levels
    }

    /// Writes the embedding of `c` into `out` (`embed_dim` long).
    pub fn embed(&self, c: f32, out: &mut [f32]) {
        self.embedding.embed(c, out);
    }

    /// Forward pass of a network with one noise condition. `x` is `n x action_dim`, `states`
    /// `n x state_dim`, `c_noise` has `n` entries. Returns a view into the network's output
    /// buffer.
    ///
    /// # Panics
    /// On mismatched shapes (callers validate user data first).
    pub fn forward(
        &mut self,
        x: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        c_noise: &[f32],
    ) -> MatRef<'_, f32> {
        self.forward_conditioned(x, states, &[c_noise])
    }

    /// [`DenoiserNet::forward`] for inference: the same output, bit for bit, keeping nothing
    /// for a backward pass ([`Module::forward_inference`](vdd_nn::Module::forward_inference)).
    ///
    /// # Panics
    /// On mismatched shapes (callers validate user data first).
    pub fn forward_inference(
        &mut self,
        x: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        c_noise: &[f32],
    ) -> MatRef<'_, f32> {
        self.conditioned(x, states, &[c_noise], true)
    }

    /// Forward pass with one noise condition per level: `x` is `n x action_dim`, `states`
    /// `n x state_dim`, `conditions` has [`DenoiserNet::levels`] entries of `n` each. Returns a
    /// view into the network's output buffer.
    ///
    /// # Panics
    /// On mismatched shapes (callers validate user data first).
    pub fn forward_conditioned<C: AsRef<[f32]>>(
        &mut self,
        x: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        conditions: &[C],
    ) -> MatRef<'_, f32> {
        self.conditioned(x, states, conditions, false)
    }

    fn conditioned<C: AsRef<[f32]>>(
        &mut self,
        x: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        conditions: &[C],
        inference: bool,
    ) -> MatRef<'_, f32> {
        let n = x.nrows();
        assert!(
            x.ncols() == self.action_dim
                && states.nrows() == n
                && states.ncols() == self.state_dim
                && conditions.len() == self.levels
                && conditions.iter().all(|c| c.as_ref().len() == n),
            "DenoiserNet: input shapes"
        );
        self.embedding.write_input(&mut self.input, x, states, conditions);
        vdd_nn::forward_as(&mut self.mlp, self.input.as_ref(), inference)
    }

    /// The preconditioned evaluation `out_i = c_skip_i x_i + c_out_i F(c_in_i x_i, s_i, c_noise_i)`
    /// for every row of `x` (`n x action_dim`), with the per-row coefficients `coef` (`n` rows,
    /// [`DenoiserNet::levels`] noise conditions); `out` is `n x action_dim`. EDM's denoiser
    /// `D(x; σ, s)` with [`Preconditioning::write_coefficients`](crate::Preconditioning::write_coefficients).
    ///
    /// # Panics
    /// On mismatched shapes (callers validate user data first).
    pub fn forward_preconditioned(
        &mut self,
        x: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        coef: &RowCoefficients,
        out: MatMut<'_, f32>,
    ) {
        self.preconditioned(x, states, coef, out, false)
    }

    /// [`DenoiserNet::forward_preconditioned`] for inference: the same output, bit for bit,
    /// keeping nothing for a backward pass (a teacher's score, a sampler, a target network).
    ///
    /// # Panics
    /// On mismatched shapes (callers validate user data first).
    pub fn forward_preconditioned_inference(
        &mut self,
        x: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        coef: &RowCoefficients,
        out: MatMut<'_, f32>,
    ) {
        self.preconditioned(x, states, coef, out, true)
    }

    fn preconditioned(
        &mut self,
        x: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        coef: &RowCoefficients,
        mut out: MatMut<'_, f32>,
        inference: bool,
    ) {
        let (n, d) = (x.nrows(), x.ncols());
        assert!(
            coef.len() == n
                && coef.c_skip.len() == n
                && coef.c_out.len() == n
                && out.nrows() == n
                && out.ncols() == d,
            "DenoiserNet: preconditioned shapes"
        );
        let mut x_in = std::mem::replace(&mut self.x_in, Mat::zeros(0, 0));
        if x_in.nrows() != n || x_in.ncols() != d {
            x_in = Mat::zeros(n, d);
        }
        for j in 0..d {
            let col = x_in.col_as_slice_mut(j);
            for i in 0..n {
                col[i] = coef.c_in[i] * x[(i, j)];
            }
        }
        let f = self.conditioned(x_in.as_ref(), states, &coef.c_noise[..], inference);
        for j in 0..d {
            for i in 0..n {
                out[(i, j)] = coef.c_skip[i] * x[(i, j)] + coef.c_out[i] * f[(i, j)];
            }
        }
        self.x_in = x_in;
    }

    /// Backward pass for the last forward: accumulates parameter gradients for `grad_out`
    /// (`n x action_dim`) and returns the gradient with respect to the `x` input of that
    /// forward (`n x action_dim`; the state and embedding columns are not differentiated).
    pub fn backward(&mut self, grad_out: MatRef<'_, f32>) -> MatRef<'_, f32> {
        let da = self.action_dim;
        self.mlp.backward(grad_out).subcols(0, da)
    }

    /// The underlying residual MLP.
    pub fn mlp(&self) -> &ResidualMlp {
        &self.mlp
    }
}

impl Parameters for DenoiserNet {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        self.mlp.visit_params(&vdd_nn::join_name(prefix, "net"), f);
    }
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        self.mlp.visit_params_mut(&vdd_nn::join_name(prefix, "net"), f);
    }
}

/// An exponential moving average of a model's parameters,
/// `θ_ema ← d θ_ema + (1 − d) θ` with the warm-up `d = min(decay, (1 + k)/(10 + k))` at update
/// `k`, kept as a plain parameter copy (no allocation after the first update).
#[derive(Debug, Clone)]
pub(crate) struct Ema {
    decay: f32,
    updates: u64,
    flat: Vec<f32>,
}

impl Ema {
    pub(crate) fn new(decay: f32) -> Self {
        Self { decay, updates: 0, flat: Vec::new() }
    }

    /// Moves `ema` towards `live` (same architecture).
    pub(crate) fn update(&mut self, ema: &mut dyn Parameters, live: &dyn Parameters) {
        let k = self.updates as f32;
        let d = self.decay.min((1.0 + k) / (10.0 + k));
        self.updates += 1;
        self.flat.clear();
        let flat = &mut self.flat;
        live.visit_params("", &mut |_, p| flat.extend_from_slice(&p.value));
        let mut off = 0;
        ema.visit_params_mut("", &mut |_, p| {
            let src = &flat[off..off + p.value.len()];
            for (e, &l) in p.value.iter_mut().zip(src) {
                *e = d * *e + (1.0 - d) * l;
            }
            off += p.value.len();
        });
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use vdd_core::Seeds;

    #[test]
    fn embedding_is_placed_after_action_and_state() {
        let mut rng = Seeds::new(0).stream("init");
        let cfg = NetConfig { hidden_dim: 8, num_blocks: 1, embed_dim: 4, ..Default::default() };
        let mut net = DenoiserNet::new(&cfg, 2, 1, &mut rng).unwrap();
        let x = faer::mat![[0.5f32, -0.5]];
        let s = faer::mat![[2.0f32]];
        net.forward(x.as_ref(), s.as_ref(), &[0.3]);
        let mut e = [0.0f32; 4];
        net.embed(0.3, &mut e);
        let row: Vec<f32> = (0..7).map(|j| net.input[(0, j)]).collect();
        assert_eq!(&row[..3], &[0.5, -0.5, 2.0]);
        assert_eq!(&row[3..], &e);
        assert!((e[0] - 0.3f32.sin()).abs() < 1e-7 && (e[3] - (16.0f32 * 0.3).cos()).abs() < 1e-6);
        assert!(
            DenoiserNet::new(&NetConfig { embed_dim: 3, ..cfg.clone() }, 2, 1, &mut rng).is_err()
        );
        assert!(DenoiserNet::new(&cfg, 0, 1, &mut rng).is_err());
    }

    #[test]
    fn inference_passes_give_the_forward_bits() {
        let cfg = NetConfig { hidden_dim: 8, num_blocks: 1, embed_dim: 4, ..Default::default() };
        let mut net =
            DenoiserNet::new(&cfg, 2, 1, &mut vdd_core::Seeds::new(2).stream("init")).unwrap();
        for n in [1, 6] {
            let x = Mat::from_fn(n, 2, |i, j| i as f32 * 0.7 - j as f32 * 1.3);
            let s = Mat::from_fn(n, 1, |i, _| 0.2 * i as f32);
            let c: Vec<f32> = (0..n).map(|i| -1.0 + 0.4 * i as f32).collect();
            let want = net.forward(x.as_ref(), s.as_ref(), &c).to_owned();
            assert_eq!(net.forward_inference(x.as_ref(), s.as_ref(), &c).to_owned(), want);
            let mut coef = RowCoefficients::default();
            coef.clear(1);
            for i in 0..n {
                coef.push(0.5 + 0.1 * i as f32, &[c[i]], 0.3, 1.7);
            }
            let (mut a, mut b) = (Mat::zeros(n, 2), Mat::zeros(n, 2));
            net.forward_preconditioned(x.as_ref(), s.as_ref(), &coef, a.as_mut());
            net.forward_preconditioned_inference(x.as_ref(), s.as_ref(), &coef, b.as_mut());
            assert_eq!(a, b);
        }
    }

    #[test]
    fn noise_embedding_writes_one_block_per_condition() {
        let cfg = NetConfig { embed_dim: 4, ..Default::default() };
        let emb = NoiseEmbedding::new(&cfg);
        assert_eq!(emb.dim(), 4);
        let x = faer::mat![[0.5f32, -0.5], [1.0, 2.0]];
        let s = faer::mat![[3.0f32], [4.0]];
        let (c1, c2) = ([0.3f32, -0.1], [0.7f32, 0.2]);
        let mut input = Mat::zeros(0, 0);
        emb.write_input(&mut input, x.as_ref(), s.as_ref(), &[&c1, &c2]);
        assert_eq!((input.nrows(), input.ncols()), (2, 2 + 1 + 2 * 4));
        let mut e = [0.0f32; 4];
        for i in 0..2 {
            let row: Vec<f32> = (0..11).map(|j| input[(i, j)]).collect();
            assert_eq!(&row[..3], &[x[(i, 0)], x[(i, 1)], s[(i, 0)]]);
            emb.embed(c1[i], &mut e);
            assert_eq!(&row[3..7], &e);
            emb.embed(c2[i], &mut e);
            assert_eq!(&row[7..], &e);
        }
        // One condition: the denoiser network's input width.
        emb.write_input(&mut input, x.as_ref(), s.as_ref(), &[&c1]);
        assert_eq!(input.ncols(), cfg.mlp_config(2, 1, 1).in_dim);
    }

    #[test]
    fn ema_tracks_with_warmup_and_decay() {
        let mut live = Param::new(&[2], vec![1.0, 2.0]);
        let mut ema_p = Param::new(&[2], vec![0.0, 0.0]);
        struct One<'a>(&'a mut Param);
        impl Parameters for One<'_> {
            fn visit_params(&self, p: &str, f: &mut dyn FnMut(&str, &Param)) {
                f(p, self.0)
            }
            fn visit_params_mut(&mut self, p: &str, f: &mut dyn FnMut(&str, &mut Param)) {
                f(p, self.0)
            }
        }
        let mut ema = Ema::new(0.5);
        ema.update(&mut One(&mut ema_p), &One(&mut live));
        // First update: d = min(0.5, 1/10) = 0.1.
        assert!((ema_p.value[0] - 0.9).abs() < 1e-6 && (ema_p.value[1] - 1.8).abs() < 1e-6);
        live.value = vec![0.0, 0.0];
        for _ in 0..20 {
            ema.update(&mut One(&mut ema_p), &One(&mut live));
        }
        // Later updates use d = 0.5: the average has forgotten the old value.
        assert!(ema_p.value[0].abs() < 1e-3);
    }
}
