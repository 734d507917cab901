//! BESO/D3IL's ResNet-MLP score network: `GCTimeScoreNetwork` (`score_plan_mlp.py`) with
//! `model_style: true`, i.e. a `ResidualMLPNetwork` (`networks/mlps/mlps.py`) over
//! `[state, action, (goal,) embed(ln σ / 4)]`, applied to each time step of a window alike.

use faer::{Accum, Mat, MatMut, MatRef};
use serde::{Deserialize, Serialize};
use vdd_nn::matmul;

use super::cols::{Act, activate, affine, affine_into, layer_norm, linear, linear_add};
use super::conv::ensure;
use super::ops::affine_rows;
use vdd_nn::{Activation, LayerNorm, Linear, NnError, Param, Parameters, join_name};

/// The noise-level embedding (`embed_fn.embedding_type` of BESO's
/// `return_time_sigma_embedding_model`) applied to `t = ln(σ)/4`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum SigmaEmbedding {
    /// `FourierFeatures`: `[cos(2π t w), sin(2π t w)]`, buffer `embed.weight` `[dim/2, 1]`.
    FourierFeatures,
    /// `GaussianFourier`: `[sin(2π t W), cos(2π t W)]` (`embed.embed.0.W`), then
    /// `Linear(dim, 2 dim) → Mish → Linear(2 dim, dim)`.
    GaussianFourier,
    /// `Sinusoidal`: `[sin(t f), cos(t f)]` with `f_k = exp(−k ln(10⁴)/(dim/2 − 1))`, then
    /// `Linear(dim, 2 dim) → Mish → Linear(2 dim, dim)`.
    Sinusoidal,
}

/// The activation as `return_activiation_fcn` maps its name: `"ReLU"`, `"Mish"`, `"sigmoid"`
/// (and `"tanh"`, which that function maps to a sigmoid too); every other name gives a
/// `PReLU` with one learned slope.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum MlpActivation {
    /// `nn.ReLU`.
    Relu,
    /// `nn.Mish`.
    Mish,
    /// `nn.Sigmoid`.
    Sigmoid,
    /// `nn.PReLU` (one parameter, key `…act.weight`).
    Prelu,
}

impl MlpActivation {
    /// The activation BESO builds for the config string `name`.
    pub fn from_beso_name(name: &str) -> Self {
        match name {
            "ReLU" => Self::Relu,
            "Mish" => Self::Mish,
            "sigmoid" | "tanh" => Self::Sigmoid,
            _ => Self::Prelu,
        }
    }
}

/// The normalisation inside the residual blocks (`use_norm`, `norm_style`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum BlockNorm {
    /// `use_norm: false`.
    None,
    /// `norm_style: LayerNorm` (`eps = 1e-6`, one norm shared by both layers of a block).
    LayerNorm,
}

/// The constructor arguments of `GCTimeScoreNetwork` that shape its weights.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ResMlpScoreConfig {
    /// `obs_dim`.
    pub obs_dim: usize,
    /// `plan_dim`: the action width.
    pub action_dim: usize,
    /// `goal_dim` (used only when `goal_conditional`).
    pub goal_dim: usize,
    /// `goal_conditional`.
    pub goal_conditional: bool,
    /// `hidden_dim`.
    pub hidden_dim: usize,
    /// `num_hidden_layers` (even: one residual block per two).
    pub num_hidden_layers: usize,
    /// `output_dim` (the action width for a score network).
    pub output_dim: usize,
    /// `embed_fn.time_embed_dim`.
    pub time_embed_dim: usize,
    /// `embed_fn.embedding_type`.
    pub embedding: SigmaEmbedding,
    /// `activation`.
    pub activation: MlpActivation,
    /// `use_norm` / `norm_style`.
    pub norm: BlockNorm,
}

#[derive(Debug, Clone)]
struct ResBlock {
    l1: Linear,
    l2: Linear,
    norm: Option<LayerNorm>,
    prelu: Option<Param>,
}

fn zero_linear(i: usize, o: usize) -> Linear {
    Linear::from_params(i, o, Param::zeros(&[o, i]), Param::zeros(&[o]))
}

/// Scratch buffers kept between calls.
#[derive(Debug, Clone)]
struct Buffers {
    e: Vec<f32>,
    e2: Vec<f32>,
    eh: Mat<f32>,
    h: Mat<f32>,
    u: Mat<f32>,
    v: Mat<f32>,
}

impl Default for Buffers {
    fn default() -> Self {
        Self {
            e: Vec::new(),
            e2: Vec::new(),
            eh: Mat::new(),
            h: Mat::new(),
            u: Mat::new(),
            v: Mat::new(),
        }
    }
}

/// BESO/D3IL's ResNet-MLP score network (forward only), with PyTorch's parameter names.
///
/// ```
/// use vdd_torch::{BlockNorm, MlpActivation, ResMlpScore, ResMlpScoreConfig, SigmaEmbedding};
/// let cfg = ResMlpScoreConfig {
///     obs_dim: 3, action_dim: 2, goal_dim: 0, goal_conditional: false, hidden_dim: 16,
///     num_hidden_layers: 2, output_dim: 2, time_embed_dim: 4,
///     embedding: SigmaEmbedding::FourierFeatures, activation: MlpActivation::Mish,
///     norm: BlockNorm::None,
/// };
/// let mut net = ResMlpScore::new(cfg).unwrap();
/// let (s, a) = (faer::Mat::<f32>::zeros(2, 3), faer::Mat::<f32>::zeros(2, 2));
/// let mut out = faer::Mat::<f32>::zeros(2, 2);
/// net.forward(s.as_ref(), a.as_ref(), None, &[0.5, 1.0], out.as_mut()).unwrap();
/// ```
#[derive(Debug, Clone)]
pub struct ResMlpScore {
    config: ResMlpScoreConfig,
    /// `FourierFeatures`' buffer or `GaussianFourier`'s `W` (empty for `Sinusoidal`).
    embed_w: Param,
    /// The embedding MLP (`GaussianFourier`, `Sinusoidal`).
    embed_mlp: Option<(Linear, Linear)>,
    first: Linear,
    blocks: Vec<ResBlock>,
    last: Linear,
    /// `GCTimeScoreNetwork.act`'s slope when it is a `PReLU` (unused in the forward pass).
    outer_prelu: Option<Param>,
    buf: Buffers,
}

impl ResMlpScore {
    /// The network with zero weights.
    pub fn new(config: ResMlpScoreConfig) -> Result<Self, NnError> {
        let c = &config;
        if c.hidden_dim == 0 || c.output_dim == 0 || c.time_embed_dim < 4 {
            return Err(NnError::Config(format!("ResMlpScore: zero width in {c:?}")));
        }
        if c.num_hidden_layers % 2 != 0 || c.time_embed_dim % 2 != 0 {
            return Err(NnError::Config(format!(
                "ResMlpScore: num_hidden_layers and time_embed_dim must be even, got {c:?}"
            )));
        }
        if c.hidden_dim > 1 << 16 || c.num_hidden_layers > 2048 || c.time_embed_dim > 1 << 16 {
            return Err(NnError::Config(format!("ResMlpScore: absurd size in {c:?}")));
        }
        let te = c.time_embed_dim;
        let goal = if c.goal_conditional { c.goal_dim } else { 0 };
        let input = te + c.obs_dim + c.action_dim + goal;
        let prelu = || (c.activation == MlpActivation::Prelu).then(|| Param::new(&[1], vec![0.25]));
        let norm = || (c.norm == BlockNorm::LayerNorm).then(|| LayerNorm::new(c.hidden_dim));
        let mut blocks = Vec::new();
        for _ in (1..c.num_hidden_layers).step_by(2) {
            let mut ln = norm();
            if let Some(l) = ln.as_mut() {
                l.set_eps(1e-6)?;
            }
            blocks.push(ResBlock {
                l1: zero_linear(c.hidden_dim, c.hidden_dim),
                l2: zero_linear(c.hidden_dim, c.hidden_dim),
                norm: ln,
                prelu: prelu(),
            });
        }
        let (embed_w, embed_mlp) = match c.embedding {
            SigmaEmbedding::FourierFeatures => (Param::zeros(&[te / 2, 1]), None),
            SigmaEmbedding::GaussianFourier => {
                (Param::zeros(&[te / 2]), Some((zero_linear(te, 2 * te), zero_linear(2 * te, te))))
            }
            SigmaEmbedding::Sinusoidal => {
                (Param::zeros(&[0]), Some((zero_linear(te, 2 * te), zero_linear(2 * te, te))))
            }
        };
        Ok(Self {
            embed_w,
            embed_mlp,
            first: zero_linear(input, c.hidden_dim),
            blocks,
            last: zero_linear(c.hidden_dim, c.output_dim),
            outer_prelu: prelu(),
            config,
            buf: Buffers::default(),
        })
    }

    /// The constructor arguments.
    pub fn config(&self) -> &ResMlpScoreConfig {
        &self.config
    }

    /// `GCTimeScoreNetwork.forward(state, plan, goal, sigma)` for `n` samples of a window of
    /// `t` steps: `states` is `n x (t · obs_dim)`, `actions` `n x (t · action_dim)`, `goals`
    /// `n x (t · goal_dim)` when goal-conditional, `sigma` one level per sample, `out`
    /// `n x (t · output_dim)`. Every step sees the same σ embedding.
    pub fn forward(
        &mut self,
        states: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
        goals: Option<MatRef<'_, f32>>,
        sigma: &[f32],
        mut out: MatMut<'_, f32>,
    ) -> Result<(), NnError> {
        let c = &self.config;
        let n = actions.nrows();
        let t = actions.ncols() / c.action_dim.max(1);
        let gd = if c.goal_conditional { c.goal_dim } else { 0 };
        let bad = |w: &str| Err(NnError::Config(format!("ResMlpScore: {w}")));
        if t == 0 || actions.ncols() != t * c.action_dim || sigma.len() != n {
            return bad("action columns or sigma length");
        }
        if states.nrows() != n || states.ncols() != t * c.obs_dim {
            return bad("state shape");
        }
        if out.nrows() != n || out.ncols() != t * c.output_dim {
            return bad("output shape");
        }
        match goals {
            Some(g) if gd > 0 && g.nrows() == n && g.ncols() == t * gd => {}
            None if gd == 0 => {}
            _ => return bad("goals must be given exactly when goal-conditional"),
        }
        let te = c.time_embed_dim;
        let half = te / 2;
        let b = &mut self.buf;
        // The σ embedding, one row per sample.
        b.e.resize(n * te, 0.0);
        for (i, &s) in sigma.iter().enumerate() {
            let z = s.ln() / 4.0;
            let row = &mut b.e[i * te..(i + 1) * te];
            match c.embedding {
                SigmaEmbedding::FourierFeatures => {
                    for k in 0..half {
                        let f = 2.0 * std::f32::consts::PI * z * self.embed_w.value[k];
                        (row[k], row[half + k]) = (f.cos(), f.sin());
                    }
                }
                SigmaEmbedding::GaussianFourier => {
                    for k in 0..half {
                        let f = z * self.embed_w.value[k] * 2.0 * std::f32::consts::PI;
                        (row[k], row[half + k]) = (f.sin(), f.cos());
                    }
                }
                SigmaEmbedding::Sinusoidal => {
                    let step = (10000f32).ln() / (half as f32 - 1.0);
                    for k in 0..half {
                        let f = z * (k as f32 * -step).exp();
                        (row[k], row[half + k]) = (f.sin(), f.cos());
                    }
                }
            }
        }
        if let Some((l1, l2)) = &self.embed_mlp {
            affine_rows(l1, &b.e, n, &mut b.e2);
            b.e2.iter_mut().for_each(|v| *v = Activation::Mish.apply(*v));
            affine_rows(l2, &b.e2, n, &mut b.e);
        }
        // Token-column layout: step k of sample i is row k·n + i. The first layer's product
        // splits along its input [state, action, (goal,) embed]; the σ embedding's share (with
        // the bias) is the same for every step.
        let (od, ad, hd) = (c.obs_dim, c.action_dim, c.hidden_dim);
        let rows = n * t;
        let wt = self.first.weight_t();
        let e = MatRef::from_row_major_slice(&b.e, n, te);
        affine(wt.subrows(od + ad + gd, te), &self.first.bias.value, e, &mut b.eh);
        ensure(&mut b.h, rows, hd);
        for k in 0..t {
            let mut block = b.h.as_mut().subrows_mut(k * n, n);
            block.copy_from(b.eh.as_ref());
            let parts = [(Some(states), od, 0), (Some(actions), ad, od), (goals, gd, od + ad)];
            for (m, w, at) in parts {
                if let Some(m) = m.filter(|_| w > 0) {
                    let (x, wp) = (m.subcols(k * w, w), wt.subrows(at, w));
                    matmul(block.as_mut(), Accum::Add, x, wp, 1.0);
                }
            }
        }
        for blk in &self.blocks {
            let act = match c.activation {
                MlpActivation::Relu => Act::Relu,
                MlpActivation::Mish => Act::Mish,
                MlpActivation::Sigmoid => Act::Sigmoid,
                MlpActivation::Prelu => Act::Prelu(blk.prelu.as_ref().map_or(0.25, |p| p.value[0])),
            };
            match &blk.norm {
                Some(ln) => layer_norm(ln, &b.h, 0..rows, &mut b.u),
                None => {
                    ensure(&mut b.u, rows, hd);
                    b.u.copy_from(&b.h);
                }
            }
            activate(act, &mut b.u);
            linear(&blk.l1, b.u.as_ref(), &mut b.v);
            if let Some(ln) = &blk.norm {
                layer_norm(ln, &b.v, 0..rows, &mut b.u);
                std::mem::swap(&mut b.u, &mut b.v);
            }
            activate(act, &mut b.v);
            linear_add(&blk.l2, b.v.as_ref(), &mut b.h);
        }
        let (wl, bl, w) = (self.last.weight_t(), &self.last.bias.value, c.output_dim);
        for k in 0..t {
            let dst = out.as_mut().subcols_mut(k * w, w);
            affine_into(wl, bl, b.h.as_ref().subrows(k * n, n), dst);
        }
        Ok(())
    }
}

impl Parameters for ResMlpScore {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        let p = |s: &str| join_name(prefix, s);
        match self.config.embedding {
            SigmaEmbedding::FourierFeatures => f(&p("embed.weight"), &self.embed_w),
            SigmaEmbedding::GaussianFourier => f(&p("embed.embed.0.W"), &self.embed_w),
            SigmaEmbedding::Sinusoidal => {}
        }
        if let Some((l1, l2)) = &self.embed_mlp {
            l1.visit_params(&p("embed.embed.1"), f);
            l2.visit_params(&p("embed.embed.3"), f);
        }
        self.first.visit_params(&p("layers.layers.0"), f);
        for (i, b) in self.blocks.iter().enumerate() {
            let q = |s: &str| p(&format!("layers.layers.{}.{s}", i + 1));
            b.l1.visit_params(&q("l1"), f);
            b.l2.visit_params(&q("l2"), f);
            if let Some(ln) = &b.norm {
                ln.visit_params(&q("normalizer"), f);
            }
            if let Some(w) = &b.prelu {
                f(&q("act.weight"), w);
            }
        }
        self.last.visit_params(&p(&format!("layers.layers.{}", self.blocks.len() + 1)), f);
        if let Some(w) = &self.outer_prelu {
            f(&p("act.weight"), w);
        }
    }

    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        let p = |s: &str| join_name(prefix, s);
        match self.config.embedding {
            SigmaEmbedding::FourierFeatures => f(&p("embed.weight"), &mut self.embed_w),
            SigmaEmbedding::GaussianFourier => f(&p("embed.embed.0.W"), &mut self.embed_w),
            SigmaEmbedding::Sinusoidal => {}
        }
        if let Some((l1, l2)) = &mut self.embed_mlp {
            l1.visit_params_mut(&p("embed.embed.1"), f);
            l2.visit_params_mut(&p("embed.embed.3"), f);
        }
        self.first.visit_params_mut(&p("layers.layers.0"), f);
        let nb = self.blocks.len();
        for (i, b) in self.blocks.iter_mut().enumerate() {
            let q = |s: &str| p(&format!("layers.layers.{}.{s}", i + 1));
            b.l1.visit_params_mut(&q("l1"), f);
            b.l2.visit_params_mut(&q("l2"), f);
            if let Some(ln) = &mut b.norm {
                ln.visit_params_mut(&q("normalizer"), f);
            }
            if let Some(w) = &mut b.prelu {
                f(&q("act.weight"), w);
            }
        }
        self.last.visit_params_mut(&p(&format!("layers.layers.{}", nb + 1)), f);
        if let Some(w) = &mut self.outer_prelu {
            f(&p("act.weight"), w);
        }
    }
}
