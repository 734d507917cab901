//! BESO/D3IL's `DiffusionGPT` score network (`k_diffusion/score_gpts.py` in both packages):
//! a minGPT over the token sequence `[σ, (g₁ … g_G), s₁, a₁, s₂, a₂, …, s_t, a_t]` with causal
//! self-attention, pre-norm blocks (LayerNorm, GELU MLP) and the action tokens' outputs read
//! out by a linear head (or `Linear → SiLU → Linear` when `linear_output` is false).

use faer::{Mat, MatMut, MatRef};
use serde::{Deserialize, Serialize};

use super::cols::{
    Act, Cols, activate, add_row, affine_into, attention, causal_limits, layer_norm, linear,
    linear_add,
};
use super::conv::ensure;
use vdd_nn::{LayerNorm, Linear, NnError, Param, Parameters, join_name};

/// The constructor arguments of `DiffusionGPT` that fix its weights' shapes and its forward.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct DiffusionGptConfig {
    /// `state_dim`: one observation's width.
    pub state_dim: usize,
    /// `action_dim`: one action's width.
    pub action_dim: usize,
    /// `embed_dim`.
    pub embed_dim: usize,
    /// `n_layers`.
    pub n_layers: usize,
    /// `n_heads` (divides `embed_dim`).
    pub n_heads: usize,
    /// `obs_seq_len`: the observation window the model was built for.
    pub obs_seq_len: usize,
    /// `goal_seq_len` (ignored, as in PyTorch, unless `goal_conditioned`).
    pub goal_seq_len: usize,
    /// `goal_conditioned`: goal tokens follow the σ token.
    pub goal_conditioned: bool,
    /// `linear_output`: a linear action head (else `Linear(d, 100) → SiLU → Linear`).
    pub linear_output: bool,
}

impl DiffusionGptConfig {
    /// Goal tokens in the sequence (0 unless goal-conditioned).
    pub fn goal_tokens(&self) -> usize {
        if self.goal_conditioned { self.goal_seq_len } else { 0 }
    }

    fn validate(&self) -> Result<(), NnError> {
        let c = self;
        if c.state_dim == 0 || c.action_dim == 0 || c.embed_dim == 0 || c.obs_seq_len == 0 {
            return Err(NnError::Config(format!("DiffusionGPT: zero width in {c:?}")));
        }
        if c.n_heads == 0 || c.embed_dim % c.n_heads != 0 {
            return Err(NnError::Config(format!(
                "DiffusionGPT: n_heads {} does not divide embed_dim {}",
                c.n_heads, c.embed_dim
            )));
        }
        if c.embed_dim > 1 << 16 || c.n_layers > 1024 || c.obs_seq_len + c.goal_seq_len > 1 << 16 {
            return Err(NnError::Config(format!("DiffusionGPT: absurd size in {c:?}")));
        }
        Ok(())
    }
}

/// One pre-norm transformer block (`Block` in `score_gpts.py`).
#[derive(Debug, Clone)]
struct Block {
    ln1: LayerNorm,
    ln2: LayerNorm,
    key: Linear,
    query: Linear,
    value: Linear,
    proj: Linear,
    fc1: Linear,
    fc2: Linear,
}

fn zero_linear(i: usize, o: usize) -> Linear {
    Linear::from_params(i, o, Param::zeros(&[o, i]), Param::zeros(&[o]))
}

/// Scratch buffers of one forward pass, kept between calls.
#[derive(Debug, Clone)]
struct Buffers {
    x: Mat<f32>,
    h: Mat<f32>,
    q: Mat<f32>,
    k: Mat<f32>,
    v: Mat<f32>,
    y: Mat<f32>,
    f: Mat<f32>,
    p: Vec<f32>,
    limits: Vec<usize>,
}

impl Default for Buffers {
    fn default() -> Self {
        Self {
            x: Mat::new(),
            h: Mat::new(),
            q: Mat::new(),
            k: Mat::new(),
            v: Mat::new(),
            y: Mat::new(),
            f: Mat::new(),
            p: Vec::new(),
            limits: Vec::new(),
        }
    }
}

/// BESO/D3IL's `DiffusionGPT` (forward only), with PyTorch's parameter names.
///
/// ```
/// use vdd_torch::{DiffusionGpt, DiffusionGptConfig};
/// let cfg = DiffusionGptConfig {
///     state_dim: 4, action_dim: 2, embed_dim: 8, n_layers: 1, n_heads: 2,
///     obs_seq_len: 3, goal_seq_len: 0, goal_conditioned: false, linear_output: true,
/// };
/// let mut net = DiffusionGpt::new(cfg).unwrap();
/// // Two samples, a window of 3 observations and 3 actions each.
/// let s = faer::Mat::<f32>::zeros(2, 12);
/// let a = faer::Mat::<f32>::zeros(2, 6);
/// let mut out = faer::Mat::<f32>::zeros(2, 6);
/// net.forward(s.as_ref(), a.as_ref(), None, &[0.5, 1.0], out.as_mut()).unwrap();
/// ```
#[derive(Debug, Clone)]
pub struct DiffusionGpt {
    config: DiffusionGptConfig,
    tok_emb: Linear,
    pos_emb: Param,
    blocks: Vec<Block>,
    ln_f: LayerNorm,
    sigma_emb: Linear,
    action_emb: Linear,
    /// The linear head, or the first layer of the MLP head.
    head0: Linear,
    /// The MLP head's second layer.
    head2: Option<Linear>,
    buf: Buffers,
}

impl DiffusionGpt {
    /// The network with zero weights (load them with [`vdd_nn::io::load_safetensors`] or
    /// [`Parameters::visit_params_mut`]).
    pub fn new(config: DiffusionGptConfig) -> Result<Self, NnError> {
        config.validate()?;
        let d = config.embed_dim;
        let seq = config.goal_tokens() + config.obs_seq_len + 1;
        let block = || Block {
            ln1: LayerNorm::new(d),
            ln2: LayerNorm::new(d),
            key: zero_linear(d, d),
            query: zero_linear(d, d),
            value: zero_linear(d, d),
            proj: zero_linear(d, d),
            fc1: zero_linear(d, 4 * d),
            fc2: zero_linear(4 * d, d),
        };
        let (head0, head2) = match config.linear_output {
            true => (zero_linear(d, config.action_dim), None),
            false => (zero_linear(d, 100), Some(zero_linear(100, config.action_dim))),
        };
        Ok(Self {
            tok_emb: zero_linear(config.state_dim, d),
            pos_emb: Param::zeros(&[1, seq, d]),
            blocks: (0..config.n_layers).map(|_| block()).collect(),
            ln_f: LayerNorm::new(d),
            sigma_emb: zero_linear(1, d),
            action_emb: zero_linear(config.action_dim, d),
            head0,
            head2,
            config,
            buf: Buffers::default(),
        })
    }

    /// The constructor arguments.
    pub fn config(&self) -> &DiffusionGptConfig {
        &self.config
    }

    /// `DiffusionGPT.forward(states, actions, goals, sigma)` for `n` samples.
    ///
    /// `states` is `n x (t · state_dim)` (a window of `t ≤ obs_seq_len` observations, oldest
    /// first), `actions` is `n x (t · action_dim)`, `goals` is `n x (goal_seq_len · state_dim)`
    /// when goal-conditioned (else `None`), `sigma` holds each row's noise level (the network
    /// embeds `ln(σ)/4`), and `out` (`n x (t · action_dim)`) receives the action tokens' outputs.
    pub fn forward(
        &mut self,
        states: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
        goals: Option<MatRef<'_, f32>>,
        sigma: &[f32],
        mut out: MatMut<'_, f32>,
    ) -> Result<(), NnError> {
        let c = &self.config;
        let (n, sd, ad, d) = (actions.nrows(), c.state_dim, c.action_dim, c.embed_dim);
        let t = actions.ncols() / ad;
        let g = c.goal_tokens();
        let shape_err = |what: &str| NnError::Config(format!("DiffusionGPT: {what}"));
        if t == 0 || t > c.obs_seq_len || actions.ncols() != t * ad {
            return Err(shape_err(&format!(
                "{} action columns for {ad}-wide actions",
                actions.ncols()
            )));
        }
        if states.nrows() != n || states.ncols() != t * sd || sigma.len() != n {
            return Err(shape_err("states, sigma and actions disagree in rows or window"));
        }
        if out.nrows() != n || out.ncols() != t * ad {
            return Err(shape_err("output shape"));
        }
        match goals {
            Some(gm) if g > 0 && gm.nrows() == n && gm.ncols() == g * sd => {}
            None if g == 0 => {}
            _ => return Err(shape_err("goals must be given exactly when goal-conditioned")),
        }
        let len = 1 + g + 2 * t;
        let rows = n * len;
        let b = &mut self.buf;
        ensure(&mut b.x, rows, d);
        let pos = &self.pos_emb.value;
        // σ token (rows 0..n): sigma_emb(ln σ / 4).
        for (j, (&w, &bias)) in
            self.sigma_emb.weight.value.iter().zip(&self.sigma_emb.bias.value).enumerate()
        {
            let col = &mut b.x.col_as_slice_mut(j)[..n];
            for (x, &s) in col.iter_mut().zip(sigma) {
                *x = w * (s.ln() / 4.0) + bias;
            }
        }
        // Goal tokens (positions 0..g), then state/action pairs (positions g..g+t), each token
        // one row block written by one product.
        let mut embed = |m: MatRef<'_, f32>, lin: &Linear, token: usize, p: usize| {
            let block = b.x.as_mut().submatrix_mut(token * n, 0, n, d);
            affine_into(lin.weight_t(), &lin.bias.value, m, block);
            add_row(&mut b.x, token * n, n, &pos[p * d..(p + 1) * d]);
        };
        if let Some(gm) = goals {
            for k in 0..g {
                embed(gm.subcols(k * sd, sd), &self.tok_emb, 1 + k, k);
            }
        }
        for k in 0..t {
            embed(states.subcols(k * sd, sd), &self.tok_emb, 1 + g + 2 * k, g + k);
            embed(actions.subcols(k * ad, ad), &self.action_emb, 2 + g + 2 * k, g + k);
        }
        causal_limits(len, &mut b.limits);
        for blk in &self.blocks {
            layer_norm(&blk.ln1, &b.x, 0..rows, &mut b.h);
            linear(&blk.query, b.h.as_ref(), &mut b.q);
            linear(&blk.key, b.h.as_ref(), &mut b.k);
            linear(&blk.value, b.h.as_ref(), &mut b.v);
            let qkv = (Cols::new(&b.q, 0), Cols::new(&b.k, 0), Cols::new(&b.v, 0));
            attention(qkv, n, &b.limits, d, c.n_heads, &mut b.y, &mut b.p);
            linear_add(&blk.proj, b.y.as_ref(), &mut b.x);
            layer_norm(&blk.ln2, &b.x, 0..rows, &mut b.h);
            linear(&blk.fc1, b.h.as_ref(), &mut b.f);
            activate(Act::Gelu, &mut b.f);
            linear_add(&blk.fc2, b.f.as_ref(), &mut b.x);
        }
        // Only the action tokens reach the head: ln_f, then the head, per token.
        for k in 0..t {
            let token = 2 + g + 2 * k;
            layer_norm(&self.ln_f, &b.x, token * n..(token + 1) * n, &mut b.h);
            let dst = out.as_mut().subcols_mut(k * ad, ad);
            match &self.head2 {
                None => {
                    affine_into(self.head0.weight_t(), &self.head0.bias.value, b.h.as_ref(), dst)
                }
                Some(h2) => {
                    linear(&self.head0, b.h.as_ref(), &mut b.f);
                    activate(Act::Silu, &mut b.f);
                    affine_into(h2.weight_t(), &h2.bias.value, b.f.as_ref(), dst);
                }
            }
        }
        Ok(())
    }
}

impl Parameters for DiffusionGpt {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        let p = |s: &str| join_name(prefix, s);
        self.tok_emb.visit_params(&p("tok_emb"), f);
        f(&p("pos_emb"), &self.pos_emb);
        for (i, b) in self.blocks.iter().enumerate() {
            let q = |s: &str| p(&format!("blocks.{i}.{s}"));
            b.ln1.visit_params(&q("ln1"), f);
            b.ln2.visit_params(&q("ln2"), f);
            b.key.visit_params(&q("attn.key"), f);
            b.query.visit_params(&q("attn.query"), f);
            b.value.visit_params(&q("attn.value"), f);
            b.proj.visit_params(&q("attn.proj"), f);
            b.fc1.visit_params(&q("mlp.0"), f);
            b.fc2.visit_params(&q("mlp.2"), f);
        }
        self.ln_f.visit_params(&p("ln_f"), f);
        self.sigma_emb.visit_params(&p("sigma_emb"), f);
        self.action_emb.visit_params(&p("action_emb"), f);
        match &self.head2 {
            None => self.head0.visit_params(&p("action_pred"), f),
            Some(h2) => {
                self.head0.visit_params(&p("action_pred.0"), f);
                h2.visit_params(&p("action_pred.2"), f);
            }
        }
    }

    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        let p = |s: &str| join_name(prefix, s);
        self.tok_emb.visit_params_mut(&p("tok_emb"), f);
        f(&p("pos_emb"), &mut self.pos_emb);
        for (i, b) in self.blocks.iter_mut().enumerate() {
            let q = |s: &str| p(&format!("blocks.{i}.{s}"));
            b.ln1.visit_params_mut(&q("ln1"), f);
            b.ln2.visit_params_mut(&q("ln2"), f);
            b.key.visit_params_mut(&q("attn.key"), f);
            b.query.visit_params_mut(&q("attn.query"), f);
            b.value.visit_params_mut(&q("attn.value"), f);
            b.proj.visit_params_mut(&q("attn.proj"), f);
            b.fc1.visit_params_mut(&q("mlp.0"), f);
            b.fc2.visit_params_mut(&q("mlp.2"), f);
        }
        self.ln_f.visit_params_mut(&p("ln_f"), f);
        self.sigma_emb.visit_params_mut(&p("sigma_emb"), f);
        self.action_emb.visit_params_mut(&p("action_emb"), f);
        match &mut self.head2 {
            None => self.head0.visit_params_mut(&p("action_pred"), f),
            Some(h2) => {
                self.head0.visit_params_mut(&p("action_pred.0"), f);
                h2.visit_params_mut(&p("action_pred.2"), f);
            }
        }
    }
}

/// Buffers `DiffusionGPT`'s state dict holds beside its parameters (the causal masks), which
/// the forward pass rebuilds: an importer may accept these names without loading them.
pub fn diffusion_gpt_buffer_suffixes() -> &'static [&'static str] {
    &["attn.mask"]
}
