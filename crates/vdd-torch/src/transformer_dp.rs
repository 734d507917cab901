//! diffusion_policy's `TransformerForDiffusion`
//! (`diffusion_policy/model/diffusion/transformer_for_diffusion.py`): a sinusoidal step
//! embedding, then either a BERT-style encoder over `[time, x₁ … x_T]` (`time_as_cond: false`)
//! or a cond encoder over `[time, obs₁ … obs_To]` (PyTorch `TransformerEncoder`, or a
//! `Linear → Mish → Linear` when `n_cond_layers = 0`) feeding a `TransformerDecoder` over the
//! action tokens; all layers `norm_first`, GELU, optional causal masks.

use faer::{Mat, MatMut, MatRef};
use serde::{Deserialize, Serialize};

use super::cols::{
    Act, Cols, activate, add_row, affine, affine_into, attention, layer_norm, linear, linear_add,
};
use super::conv::ensure;
use vdd_nn::{LayerNorm, Linear, NnError, Param, Parameters, join_name};

/// The constructor arguments of `TransformerForDiffusion`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct TransformerForDiffusionConfig {
    /// `input_dim`.
    pub input_dim: usize,
    /// `output_dim`.
    pub output_dim: usize,
    /// `horizon` (`T`).
    pub horizon: usize,
    /// `n_obs_steps` (`To`; PyTorch's default `None` means `horizon`).
    pub n_obs_steps: usize,
    /// `cond_dim` (observation conditioning when positive).
    pub cond_dim: usize,
    /// `n_layer`.
    pub n_layer: usize,
    /// `n_head`.
    pub n_head: usize,
    /// `n_emb`.
    pub n_emb: usize,
    /// `causal_attn`.
    pub causal_attn: bool,
    /// `time_as_cond`.
    pub time_as_cond: bool,
    /// `n_cond_layers`.
    pub n_cond_layers: usize,
}

impl TransformerForDiffusionConfig {
    fn obs_as_cond(&self) -> bool {
        self.cond_dim > 0
    }
    /// Tokens of the main sequence (`T`, plus one for time when encoder-only).
    fn t(&self) -> usize {
        self.horizon + usize::from(!self.time_as_cond)
    }
    /// Tokens of the cond sequence (`T_cond`).
    fn t_cond(&self) -> usize {
        usize::from(self.time_as_cond) + if self.obs_as_cond() { self.n_obs_steps } else { 0 }
    }
}

/// `nn.MultiheadAttention` (packed `in_proj`, `batch_first`).
#[derive(Debug, Clone)]
struct Mha {
    in_proj: Linear,
    out_proj: Linear,
}

/// One `norm_first` encoder (`cross == None`) or decoder layer.
#[derive(Debug, Clone)]
struct Layer {
    self_attn: Mha,
    cross: Option<(Mha, LayerNorm)>,
    linear1: Linear,
    linear2: Linear,
    norm1: LayerNorm,
    norm2: LayerNorm,
}

fn zl(i: usize, o: usize) -> Linear {
    Linear::from_params(i, o, Param::zeros(&[o, i]), Param::zeros(&[o]))
}

fn mha(d: usize) -> Mha {
    Mha { in_proj: zl(d, 3 * d), out_proj: zl(d, d) }
}

fn layer(d: usize, cross: bool) -> Layer {
    Layer {
        self_attn: mha(d),
        cross: cross.then(|| (mha(d), LayerNorm::new(d))),
        linear1: zl(d, 4 * d),
        linear2: zl(4 * d, d),
        norm1: LayerNorm::new(d),
        norm2: LayerNorm::new(d),
    }
}

/// The cond encoder.
#[derive(Debug, Clone)]
enum CondEncoder {
    Layers(Vec<Layer>),
    Mlp(Box<(Linear, Linear)>),
}

#[derive(Debug, Clone)]
struct Buffers {
    emb: Mat<f32>,
    x: Mat<f32>,
    mem: Mat<f32>,
    h: Mat<f32>,
    qkv: Mat<f32>,
    kv: Mat<f32>,
    y: Mat<f32>,
    f: Mat<f32>,
    p: Vec<f32>,
}

impl Default for Buffers {
    fn default() -> Self {
        Self {
            emb: Mat::new(),
            x: Mat::new(),
            mem: Mat::new(),
            h: Mat::new(),
            qkv: Mat::new(),
            kv: Mat::new(),
            y: Mat::new(),
            f: Mat::new(),
            p: Vec::new(),
        }
    }
}

/// diffusion_policy's `TransformerForDiffusion` (forward only), with PyTorch's parameter names.
///
/// ```
/// use vdd_torch::{TransformerForDiffusion, TransformerForDiffusionConfig};
/// let cfg = TransformerForDiffusionConfig {
///     input_dim: 2, output_dim: 2, horizon: 4, n_obs_steps: 2, cond_dim: 3, n_layer: 1,
///     n_head: 2, n_emb: 8, causal_attn: true, time_as_cond: true, n_cond_layers: 0,
/// };
/// let mut net = TransformerForDiffusion::new(cfg).unwrap();
/// let (x, cond) = (faer::Mat::<f32>::zeros(2, 8), faer::Mat::<f32>::zeros(2, 6));
/// let mut out = faer::Mat::<f32>::zeros(2, 8);
/// net.forward(x.as_ref(), &[10.0, 50.0], Some(cond.as_ref()), out.as_mut()).unwrap();
/// ```
#[derive(Debug, Clone)]
pub struct TransformerForDiffusion {
    config: TransformerForDiffusionConfig,
    input_emb: Linear,
    pos_emb: Param,
    cond_obs_emb: Option<Linear>,
    cond_pos_emb: Option<Param>,
    cond_encoder: Option<CondEncoder>,
    /// Encoder-only layers or decoder layers.
    layers: Vec<Layer>,
    ln_f: LayerNorm,
    head: Linear,
    buf: Buffers,
}

impl TransformerForDiffusion {
    /// The network with zero weights.
    pub fn new(config: TransformerForDiffusionConfig) -> Result<Self, NnError> {
        let c = &config;
        let d = c.n_emb;
        if c.input_dim == 0 || c.output_dim == 0 || c.horizon == 0 || d < 4 || d % 2 != 0 {
            return Err(NnError::Config(format!("TransformerForDiffusion: bad widths in {c:?}")));
        }
        if c.n_head == 0 || d % c.n_head != 0 {
            return Err(NnError::Config(format!(
                "TransformerForDiffusion: n_head must divide n_emb in {c:?}"
            )));
        }
        if d > 1 << 16
            || c.n_layer > 1024
            || c.n_cond_layers > 1024
            || c.horizon > 1 << 16
            || c.n_obs_steps > 1 << 16
        {
            return Err(NnError::Config(format!("TransformerForDiffusion: absurd size in {c:?}")));
        }
        if c.obs_as_cond() && !c.time_as_cond {
            return Err(NnError::Config(
                "TransformerForDiffusion: obs_as_cond needs time_as_cond".into(),
            ));
        }
        let decoder = c.t_cond() > 0;
        let cond_encoder = decoder.then(|| match c.n_cond_layers {
            0 => CondEncoder::Mlp(Box::new((zl(d, 4 * d), zl(4 * d, d)))),
            k => CondEncoder::Layers((0..k).map(|_| layer(d, false)).collect()),
        });
        Ok(Self {
            input_emb: zl(c.input_dim, d),
            pos_emb: Param::zeros(&[1, c.t(), d]),
            cond_obs_emb: c.obs_as_cond().then(|| zl(c.cond_dim, d)),
            cond_pos_emb: decoder.then(|| Param::zeros(&[1, c.t_cond(), d])),
            cond_encoder,
            layers: (0..c.n_layer).map(|_| layer(d, decoder)).collect(),
            ln_f: LayerNorm::new(d),
            head: zl(d, c.output_dim),
            config,
            buf: Buffers::default(),
        })
    }

    /// The constructor arguments.
    pub fn config(&self) -> &TransformerForDiffusionConfig {
        &self.config
    }

    /// `forward(sample, timestep, cond)`: `sample` is `n x (horizon · input_dim)`, `timestep`
    /// one diffusion step per row, `cond` `n x (n_obs_steps · cond_dim)` when the model
    /// conditions on observations (else `None`); `out` is `n x (horizon · output_dim)`.
    pub fn forward(
        &mut self,
        sample: MatRef<'_, f32>,
        timestep: &[f32],
        cond: Option<MatRef<'_, f32>>,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), NnError> {
        let c = &self.config;
        let (n, d, th) = (sample.nrows(), c.n_emb, c.horizon);
        let bad = |w: &str| Err(NnError::Config(format!("TransformerForDiffusion: {w}")));
        if sample.ncols() != th * c.input_dim || timestep.len() != n {
            return bad("sample must be n x (horizon · input_dim), one timestep per row");
        }
        if out.nrows() != n || out.ncols() != th * c.output_dim {
            return bad("output shape");
        }
        match cond {
            Some(m)
                if c.obs_as_cond() && m.nrows() == n && m.ncols() == c.n_obs_steps * c.cond_dim => {
            }
            None if !c.obs_as_cond() => {}
            _ => {
                return bad(
                    "cond must be given exactly when cond_dim > 0, n x (n_obs_steps · cond_dim)",
                );
            }
        }
        let b = &mut self.buf;
        // Sinusoidal time embedding rows (n x d), as SinusoidalPosEmb.
        let half = d / 2;
        let step = (10000f32).ln() / (half as f32 - 1.0);
        ensure(&mut b.emb, n, d);
        for k in 0..half {
            let f = (k as f32 * -step).exp();
            for (i, &ts) in timestep.iter().enumerate() {
                b.emb[(i, k)] = (ts * f).sin();
                b.emb[(i, half + k)] = (ts * f).cos();
            }
        }
        let pos = &self.pos_emb.value;
        let (causal, obs_cond) = (c.causal_attn, c.obs_as_cond());
        let decoder = self.cond_encoder.is_some();
        let len = if decoder { th } else { th + 1 };
        let off = usize::from(!decoder);
        // Token-column layout: token t of sample i is row t·n + i.
        ensure(&mut b.x, n * len, d);
        if !decoder {
            b.x.as_mut().subrows_mut(0, n).copy_from(b.emb.as_ref());
            add_row(&mut b.x, 0, n, &pos[..d]);
        }
        let ind = c.input_dim;
        for k in 0..th {
            let token = off + k;
            let block = b.x.as_mut().submatrix_mut(token * n, 0, n, d);
            let lin = &self.input_emb;
            affine_into(lin.weight_t(), &lin.bias.value, sample.subcols(k * ind, ind), block);
            add_row(&mut b.x, token * n, n, &pos[token * d..(token + 1) * d]);
        }
        let tc = c.t_cond();
        let cond_limits = vec![tc; tc];
        if let Some(enc) = &self.cond_encoder {
            // Cond sequence [time, obs…] with its position embedding.
            ensure(&mut b.mem, n * tc, d);
            let cpos = &self.cond_pos_emb.as_ref().expect("decoder has cond_pos_emb").value;
            b.mem.as_mut().subrows_mut(0, n).copy_from(b.emb.as_ref());
            add_row(&mut b.mem, 0, n, &cpos[..d]);
            if let (Some(m), Some(lin)) = (cond, &self.cond_obs_emb) {
                let cd = c.cond_dim;
                for k in 0..tc - 1 {
                    let block = b.mem.as_mut().submatrix_mut((1 + k) * n, 0, n, d);
                    affine_into(lin.weight_t(), &lin.bias.value, m.subcols(k * cd, cd), block);
                    add_row(&mut b.mem, (1 + k) * n, n, &cpos[(1 + k) * d..(2 + k) * d]);
                }
            }
            match enc {
                CondEncoder::Mlp(mlp) => {
                    let (l1, l2) = mlp.as_ref();
                    linear(l1, b.mem.as_ref(), &mut b.h);
                    activate(Act::Mish, &mut b.h);
                    linear(l2, b.h.as_ref(), &mut b.mem);
                }
                CondEncoder::Layers(layers) => {
                    for l in layers {
                        self_attention(l, b, n, &cond_limits, c.n_head, Which::Mem);
                        ff(&l.linear1, &l.linear2, &l.norm2, &mut b.mem, &mut b.h, &mut b.f);
                    }
                }
            }
        }
        // Causal: token i sees tokens 0..=i; memory (cond) mask t >= s − 1: token t sees cond
        // tokens 0..=t+1.
        let self_limits: Vec<usize> = (0..len).map(|i| if causal { i + 1 } else { len }).collect();
        let masked = causal && obs_cond;
        let mem_limits: Vec<usize> =
            (0..len).map(|t| if masked { (t + 2).min(tc) } else { tc }).collect();
        for l in &self.layers {
            self_attention(l, b, n, &self_limits, c.n_head, Which::X);
            if let Some((cross, norm)) = &l.cross {
                // x = x + MHA(norm2(x), memory, memory): queries from x, keys and values from
                // the memory, each through its part of the packed in_proj.
                let (wt, bias) = (cross.in_proj.weight_t(), &cross.in_proj.bias.value);
                layer_norm(&l.norm2, &b.x, 0..n * len, &mut b.h);
                affine(wt.subcols(0, d), &bias[..d], b.h.as_ref(), &mut b.qkv);
                affine(wt.subcols(d, 2 * d), &bias[d..], b.mem.as_ref(), &mut b.kv);
                let qkv = (Cols::new(&b.qkv, 0), Cols::new(&b.kv, 0), Cols::new(&b.kv, d));
                attention(qkv, n, &mem_limits, d, c.n_head, &mut b.y, &mut b.p);
                linear_add(&cross.out_proj, b.y.as_ref(), &mut b.x);
                ff(&l.linear1, &l.linear2, norm, &mut b.x, &mut b.h, &mut b.f);
            } else {
                ff(&l.linear1, &l.linear2, &l.norm2, &mut b.x, &mut b.h, &mut b.f);
            }
        }
        // Head on the action tokens (all of them, or all but the time token), one token's
        // row block at a time.
        let od = c.output_dim;
        for k in 0..th {
            let token = off + k;
            layer_norm(&self.ln_f, &b.x, token * n..(token + 1) * n, &mut b.h);
            let dst = out.as_mut().subcols_mut(k * od, od);
            affine_into(self.head.weight_t(), &self.head.bias.value, b.h.as_ref(), dst);
        }
        Ok(())
    }
}

/// Which buffer a self-attention block updates.
#[derive(Clone, Copy, PartialEq, Eq)]
enum Which {
    X,
    Mem,
}

/// `x = x + SA(norm1(x))` on the main sequence or the cond encoder's memory.
fn self_attention(
    l: &Layer,
    b: &mut Buffers,
    n: usize,
    limits: &[usize],
    heads: usize,
    which: Which,
) {
    let x = match which {
        Which::X => &mut b.x,
        Which::Mem => &mut b.mem,
    };
    let d = x.ncols();
    layer_norm(&l.norm1, x, 0..x.nrows(), &mut b.h);
    linear(&l.self_attn.in_proj, b.h.as_ref(), &mut b.qkv);
    let qkv = (Cols::new(&b.qkv, 0), Cols::new(&b.qkv, d), Cols::new(&b.qkv, 2 * d));
    attention(qkv, n, limits, d, heads, &mut b.y, &mut b.p);
    linear_add(&l.self_attn.out_proj, b.y.as_ref(), x);
}

/// `x = x + l2(gelu(l1(norm(x))))`.
fn ff(
    l1: &Linear,
    l2: &Linear,
    norm: &LayerNorm,
    x: &mut Mat<f32>,
    h: &mut Mat<f32>,
    f: &mut Mat<f32>,
) {
    layer_norm(norm, x, 0..x.nrows(), h);
    linear(l1, h.as_ref(), f);
    activate(Act::Gelu, f);
    linear_add(l2, f.as_ref(), x);
}

fn visit_layer(l: &Layer, p: &str, f: &mut dyn FnMut(&str, &Param)) {
    let q = |s: &str| join_name(p, s);
    for (name, m) in std::iter::once(("self_attn", &l.self_attn))
        .chain(l.cross.iter().map(|(m, _)| ("multihead_attn", m)))
    {
        f(&q(&format!("{name}.in_proj_weight")), &m.in_proj.weight);
        f(&q(&format!("{name}.in_proj_bias")), &m.in_proj.bias);
        m.out_proj.visit_params(&q(&format!("{name}.out_proj")), f);
    }
    l.linear1.visit_params(&q("linear1"), f);
    l.linear2.visit_params(&q("linear2"), f);
    l.norm1.visit_params(&q("norm1"), f);
    l.norm2.visit_params(&q("norm2"), f);
    if let Some((_, n3)) = &l.cross {
        n3.visit_params(&q("norm3"), f);
    }
}

fn visit_layer_mut(l: &mut Layer, p: &str, f: &mut dyn FnMut(&str, &mut Param)) {
    let q = |s: &str| join_name(p, s);
    let Layer { self_attn, cross, linear1, linear2, norm1, norm2 } = l;
    let (cross_mha, norm3) = match cross {
        Some((m, n3)) => (Some(m), Some(n3)),
        None => (None, None),
    };
    for (name, m) in
        std::iter::once(("self_attn", self_attn)).chain(cross_mha.map(|m| ("multihead_attn", m)))
    {
        f(&q(&format!("{name}.in_proj_weight")), &mut m.in_proj.weight);
        f(&q(&format!("{name}.in_proj_bias")), &mut m.in_proj.bias);
        m.out_proj.visit_params_mut(&q(&format!("{name}.out_proj")), f);
    }
    linear1.visit_params_mut(&q("linear1"), f);
    linear2.visit_params_mut(&q("linear2"), f);
    norm1.visit_params_mut(&q("norm1"), f);
    norm2.visit_params_mut(&q("norm2"), f);
    if let Some(n3) = norm3 {
        n3.visit_params_mut(&q("norm3"), f);
    }
}

impl Parameters for TransformerForDiffusion {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        let p = |s: &str| join_name(prefix, s);
        f(&p("pos_emb"), &self.pos_emb);
        if let Some(c) = &self.cond_pos_emb {
            f(&p("cond_pos_emb"), c);
        }
        self.input_emb.visit_params(&p("input_emb"), f);
        if let Some(l) = &self.cond_obs_emb {
            l.visit_params(&p("cond_obs_emb"), f);
        }
        match &self.cond_encoder {
            Some(CondEncoder::Mlp(mlp)) => {
                let (a, b) = mlp.as_ref();
                a.visit_params(&p("encoder.0"), f);
                b.visit_params(&p("encoder.2"), f);
            }
            Some(CondEncoder::Layers(ls)) => {
                for (i, l) in ls.iter().enumerate() {
                    visit_layer(l, &p(&format!("encoder.layers.{i}")), f);
                }
            }
            None => {}
        }
        let stack = if self.cond_encoder.is_some() { "decoder" } else { "encoder" };
        for (i, l) in self.layers.iter().enumerate() {
            visit_layer(l, &p(&format!("{stack}.layers.{i}")), f);
        }
        self.ln_f.visit_params(&p("ln_f"), f);
        self.head.visit_params(&p("head"), f);
    }

    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        let p = |s: &str| join_name(prefix, s);
        f(&p("pos_emb"), &mut self.pos_emb);
        if let Some(c) = &mut self.cond_pos_emb {
            f(&p("cond_pos_emb"), c);
        }
        self.input_emb.visit_params_mut(&p("input_emb"), f);
        if let Some(l) = &mut self.cond_obs_emb {
            l.visit_params_mut(&p("cond_obs_emb"), f);
        }
        let decoder = self.cond_encoder.is_some();
        match &mut self.cond_encoder {
            Some(CondEncoder::Mlp(mlp)) => {
                let (a, b) = mlp.as_mut();
                a.visit_params_mut(&p("encoder.0"), f);
                b.visit_params_mut(&p("encoder.2"), f);
            }
            Some(CondEncoder::Layers(ls)) => {
                for (i, l) in ls.iter_mut().enumerate() {
                    visit_layer_mut(l, &p(&format!("encoder.layers.{i}")), f);
                }
            }
            None => {}
        }
        let stack = if decoder { "decoder" } else { "encoder" };
        for (i, l) in self.layers.iter_mut().enumerate() {
            visit_layer_mut(l, &p(&format!("{stack}.layers.{i}")), f);
        }
        self.ln_f.visit_params_mut(&p("ln_f"), f);
        self.head.visit_params_mut(&p("head"), f);
    }
}

/// Buffers of `TransformerForDiffusion`'s state dict (its masks), rebuilt by the forward pass.
pub fn transformer_for_diffusion_buffer_names() -> &'static [&'static str] {
    &["mask", "memory_mask"]
}
