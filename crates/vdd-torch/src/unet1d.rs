//! The 1-D conditional U-Net of diffusion_policy (`ConditionalUnet1D`) and LeRobot
//! (`DiffusionConditionalUnet1d`), forward only.
//!
//! Both packages build the same network and differ only in parameter names
//! ([`UnetLayout`]). Sequences are `(batch · horizon) × channels` matrices as in
//! [`crate::Conv1d`]; the network's input and output are `(batch · horizon) × input_dim`,
//! row `b · horizon + t` holding PyTorch's `x[b, t, :]`.

use faer::{Accum, Mat, MatRef};
use serde::{Deserialize, Serialize};
use vdd_nn::matmul;

use super::conv::{Conv1d, ConvTranspose1d, ensure};
use super::flush::{FlushSubnormals, flush_subnormal};
use super::norm::{GroupNorm, mish_mat, sinusoidal_embedding};
use vdd_nn::{NnError, Param, Parameters, join_name};

/// Whose parameter names the U-Net uses (the networks are the same).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum UnetLayout {
    /// LeRobot: residual blocks' `conv1` / `conv2`, bare down/up-sampling convolutions.
    Lerobot,
    /// diffusion_policy: residual blocks' `blocks.0` / `blocks.1`, `Downsample1d.conv` /
    /// `Upsample1d.conv`.
    DiffusionPolicy,
}

/// The U-Net's hyper-parameters, as both packages name them.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Unet1dConfig {
    /// Per-step action dimension (`input_dim`).
    pub input_dim: usize,
    /// Width of the global conditioning vector (observation features × `n_obs_steps`).
    pub global_cond_dim: usize,
    /// `diffusion_step_embed_dim`.
    pub step_embed_dim: usize,
    /// `down_dims`: channels of each resolution level.
    pub down_dims: Vec<usize>,
    /// Convolution kernel size (odd).
    pub kernel_size: usize,
    /// GroupNorm groups of the residual blocks (the final block always uses 8, as both
    /// packages do).
    pub n_groups: usize,
    /// FiLM scale and bias (`cond_predict_scale` / `use_film_scale_modulation`) instead of
    /// bias only.
    pub film_scale: bool,
    /// Parameter names.
    pub layout: UnetLayout,
}

impl Unet1dConfig {
    /// Checks the sizes against what the packages can build.
    pub fn validate(&self) -> Result<(), NnError> {
        let bad = |m: String| Err(NnError::Config(format!("U-Net: {m}")));
        if self.input_dim == 0 || self.down_dims.is_empty() {
            return bad("input_dim and down_dims must be non-empty".into());
        }
        if self.kernel_size % 2 == 0 {
            return bad(format!("kernel_size {} must be odd", self.kernel_size));
        }
        if self.step_embed_dim < 4 || self.step_embed_dim % 2 != 0 {
            return bad(format!(
                "diffusion_step_embed_dim {} must be even >= 4",
                self.step_embed_dim
            ));
        }
        if let Some(d) =
            self.down_dims.iter().find(|&&d| self.n_groups == 0 || d % self.n_groups != 0)
        {
            return bad(format!("down dim {d} does not split into {} groups", self.n_groups));
        }
        if self.down_dims[0] % 8 != 0 {
            return bad(format!("down_dims[0] {} must split into 8 groups", self.down_dims[0]));
        }
        if self.down_dims.iter().any(|&d| d > 1 << 16) || self.step_embed_dim > 1 << 16 {
            return bad("absurd width".into());
        }
        Ok(())
    }

    /// The horizon must be divisible by this (each level but the last halves it).
    pub fn horizon_multiple(&self) -> usize {
        1 << (self.down_dims.len() - 1)
    }
}

/// Conv1d → GroupNorm → Mish (`Conv1dBlock`), parameters `block.0`, `block.1`.
#[derive(Debug, Clone)]
struct ConvBlock {
    conv: Conv1d,
    norm: GroupNorm,
}

impl ConvBlock {
    fn new(cin: usize, cout: usize, k: usize, groups: usize) -> Result<Self, NnError> {
        Ok(Self { conv: Conv1d::new(cin, cout, k, 1, k / 2)?, norm: GroupNorm::new(groups, cout)? })
    }

    /// Runs the block; the output is left in [`ConvBlock::out`].
    fn forward(&mut self, x: MatRef<'_, f32>, batch: usize) -> Result<(), NnError> {
        let y = self.conv.forward_mut(x, batch)?;
        self.norm.forward_mish_inplace(y, batch)
    }

    fn out(&self) -> &Mat<f32> {
        self.conv.output()
    }

    fn out_mut(&mut self) -> &mut Mat<f32> {
        self.conv.output_mut()
    }

    fn visit(&self, p: &str, f: &mut dyn FnMut(&str, &Param)) {
        self.conv.visit_params(&join_name(p, "block.0"), f);
        self.norm.visit_params(&join_name(p, "block.1"), f);
    }

    fn visit_mut(&mut self, p: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        self.conv.visit_params_mut(&join_name(p, "block.0"), f);
        self.norm.visit_params_mut(&join_name(p, "block.1"), f);
    }
}

/// A fully connected layer on `n × in` rows (no input copy, no single-row path).
#[derive(Debug, Clone)]
struct Dense {
    weight: Param,
    bias: Param,
    out: Mat<f32>,
}

impl Dense {
    fn new(cin: usize, cout: usize) -> Self {
        Self {
            weight: Param::buffer(&[cout, cin], vec![0.0; cin * cout]),
            bias: Param::buffer(&[cout], vec![0.0; cout]),
            out: Mat::new(),
        }
    }

    fn forward(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32> {
        let (cout, cin) = (self.weight.shape[0], self.weight.shape[1]);
        ensure(&mut self.out, x.nrows(), cout);
        for (j, &b) in self.bias.value.iter().enumerate() {
            self.out.col_as_slice_mut(j).fill(b);
        }
        let wt = MatRef::from_column_major_slice(&self.weight.value, cin, cout);
        matmul(self.out.as_mut(), Accum::Add, x, wt, 1.0);
        self.out.as_ref()
    }

    fn visit(&self, p: &str, f: &mut dyn FnMut(&str, &Param)) {
        f(&join_name(p, "weight"), &self.weight);
        f(&join_name(p, "bias"), &self.bias);
    }

    fn visit_mut(&mut self, p: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        f(&join_name(p, "weight"), &mut self.weight);
        f(&join_name(p, "bias"), &mut self.bias);
    }
}

/// `ConditionalResidualBlock1D`: two conv blocks with FiLM between them and a (1×1 conv)
/// residual path. The FiLM input is `mish(cond)`, shared by all blocks and computed once.
#[derive(Debug, Clone)]
struct ResBlock {
    conv1: ConvBlock,
    conv2: ConvBlock,
    cond: Dense,
    residual: Option<Conv1d>,
    film_scale: bool,
}

impl ResBlock {
    fn new(cin: usize, cout: usize, c: &Unet1dConfig, cond_dim: usize) -> Result<Self, NnError> {
        let k = c.kernel_size;
        Ok(Self {
            conv1: ConvBlock::new(cin, cout, k, c.n_groups)?,
            conv2: ConvBlock::new(cout, cout, k, c.n_groups)?,
            cond: Dense::new(cond_dim, if c.film_scale { 2 * cout } else { cout }),
            residual: if cin != cout { Some(Conv1d::new(cin, cout, 1, 1, 0)?) } else { None },
            film_scale: c.film_scale,
        })
    }

    /// `x`: `(batch · len) × in`; `mish_cond`: `batch × cond_dim`.
    fn forward(
        &mut self,
        x: MatRef<'_, f32>,
        mish_cond: MatRef<'_, f32>,
        batch: usize,
    ) -> Result<MatRef<'_, f32>, NnError> {
        self.conv1.forward(x, batch)?;
        let emb = self.cond.forward(mish_cond);
        let h = self.conv1.out_mut();
        let (rows, cout) = (h.nrows(), h.ncols());
        let len = rows / batch;
        for c in 0..cout {
            let col = h.col_as_slice_mut(c);
            for b in 0..batch {
                let seg = &mut col[b * len..(b + 1) * len];
                if self.film_scale {
                    let (s, bias) = (emb[(b, c)], emb[(b, cout + c)]);
                    seg.iter_mut().for_each(|v| *v = s * *v + bias);
                } else {
                    let bias = emb[(b, c)];
                    seg.iter_mut().for_each(|v| *v += bias);
                }
            }
        }
        self.conv2.forward(self.conv1.out().as_ref(), batch)?;
        let out = self.conv2.out_mut();
        let res = match &mut self.residual {
            Some(r) => r.forward(x, batch)?,
            None => x,
        };
        let mut scratch = Vec::new();
        for c in 0..cout {
            let src = super::conv::column(res, c, &mut scratch);
            out.col_as_slice_mut(c).iter_mut().zip(src).for_each(|(d, s)| *d += s);
        }
        Ok(self.conv2.out().as_ref())
    }

    fn names(layout: UnetLayout) -> (&'static str, &'static str) {
        match layout {
            UnetLayout::Lerobot => ("conv1", "conv2"),
            UnetLayout::DiffusionPolicy => ("blocks.0", "blocks.1"),
        }
    }

    fn visit(&self, p: &str, layout: UnetLayout, f: &mut dyn FnMut(&str, &Param)) {
        let (a, b) = Self::names(layout);
        self.conv1.visit(&join_name(p, a), f);
        self.cond.visit(&join_name(p, "cond_encoder.1"), f);
        self.conv2.visit(&join_name(p, b), f);
        if let Some(r) = &self.residual {
            r.visit_params(&join_name(p, "residual_conv"), f);
        }
    }

    fn visit_mut(&mut self, p: &str, layout: UnetLayout, f: &mut dyn FnMut(&str, &mut Param)) {
        let (a, b) = Self::names(layout);
        self.conv1.visit_mut(&join_name(p, a), f);
        self.cond.visit_mut(&join_name(p, "cond_encoder.1"), f);
        self.conv2.visit_mut(&join_name(p, b), f);
        if let Some(r) = &mut self.residual {
            r.visit_params_mut(&join_name(p, "residual_conv"), f);
        }
    }
}

/// One encoder level: two residual blocks and (except the last level) a stride-2 convolution.
#[derive(Debug, Clone)]
struct Down {
    res1: ResBlock,
    res2: ResBlock,
    down: Option<Conv1d>,
    /// The skip features (output of `res2`), kept for the decoder.
    skip: Mat<f32>,
}

/// One decoder level: residual blocks on `[x | skip]` and a transposed convolution.
#[derive(Debug, Clone)]
struct Up {
    res1: ResBlock,
    res2: ResBlock,
    up: ConvTranspose1d,
    cat: Mat<f32>,
}

/// The conditional 1-D U-Net of diffusion_policy / LeRobot: `forward(x, timesteps,
/// global_cond)` predicts the noise (or the clean sample) for `batch` action sequences of
/// `horizon` steps.
///
/// Its [`Parameters`] carry the packages' `state_dict` names (relative to the U-Net: LeRobot's
/// `diffusion.unet.` and diffusion_policy's `model.` prefixes are the caller's).
///
/// ```
/// use vdd_torch::{ConditionalUnet1d, Unet1dConfig, UnetLayout};
/// let config = Unet1dConfig {
///     input_dim: 2, global_cond_dim: 3, step_embed_dim: 8, down_dims: vec![8, 16],
///     kernel_size: 3, n_groups: 4, film_scale: true, layout: UnetLayout::Lerobot,
/// };
/// let mut unet = ConditionalUnet1d::new(config).unwrap();
/// let (batch, horizon) = (2, 4);
/// let x = faer::Mat::<f32>::zeros(batch * horizon, 2);
/// let cond = faer::Mat::<f32>::zeros(batch, 3);
/// let y = unet.forward(x.as_ref(), &[5.0, 7.0], cond.as_ref()).unwrap();
/// assert_eq!((y.nrows(), y.ncols()), (8, 2));
/// ```
#[derive(Debug, Clone)]
pub struct ConditionalUnet1d {
    config: Unet1dConfig,
    step1: Dense,
    step2: Dense,
    downs: Vec<Down>,
    mids: Vec<ResBlock>,
    ups: Vec<Up>,
    final_block: ConvBlock,
    final_conv: Conv1d,
    /// `batch × step_embed_dim` sinusoidal embedding.
    emb: Mat<f32>,
    /// `batch × cond_dim`: `mish([step features | global_cond])`.
    cond: Mat<f32>,
    x: Mat<f32>,
}

impl ConditionalUnet1d {
    /// A zero-initialised U-Net (load weights with [`vdd_nn::io::load_safetensors`] or by
    /// visiting its parameters).
    pub fn new(config: Unet1dConfig) -> Result<Self, NnError> {
        config.validate()?;
        let c = &config;
        let cond_dim = c.step_embed_dim + c.global_cond_dim;
        let mut dims = vec![c.input_dim];
        dims.extend(&c.down_dims);
        let levels = c.down_dims.len();
        let mut downs = Vec::with_capacity(levels);
        for i in 0..levels {
            let (cin, cout) = (dims[i], dims[i + 1]);
            downs.push(Down {
                res1: ResBlock::new(cin, cout, c, cond_dim)?,
                res2: ResBlock::new(cout, cout, c, cond_dim)?,
                down: if i + 1 < levels { Some(Conv1d::new(cout, cout, 3, 2, 1)?) } else { None },
                skip: Mat::new(),
            });
        }
        let mid = *c.down_dims.last().unwrap_or(&1);
        let mids =
            vec![ResBlock::new(mid, mid, c, cond_dim)?, ResBlock::new(mid, mid, c, cond_dim)?];
        let mut ups = Vec::new();
        for i in (1..levels).rev() {
            // in_out[i] = (down_dims[i-1], down_dims[i]) for i ≥ 1, walked backwards.
            let (small, big) = (c.down_dims[i - 1], c.down_dims[i]);
            ups.push(Up {
                res1: ResBlock::new(2 * big, small, c, cond_dim)?,
                res2: ResBlock::new(small, small, c, cond_dim)?,
                up: ConvTranspose1d::new(small, small, 4, 2, 1)?,
                cat: Mat::new(),
            });
        }
        let d0 = c.down_dims[0];
        Ok(Self {
            step1: Dense::new(c.step_embed_dim, 4 * c.step_embed_dim),
            step2: Dense::new(4 * c.step_embed_dim, c.step_embed_dim),
            downs,
            mids,
            ups,
            final_block: ConvBlock::new(d0, d0, c.kernel_size, 8)?,
            final_conv: Conv1d::new(d0, c.input_dim, 1, 1, 0)?,
            emb: Mat::new(),
            cond: Mat::new(),
            x: Mat::new(),
            config,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &Unet1dConfig {
        &self.config
    }

    /// Runs the network on `batch = timesteps.len()` sequences: `x` is `(batch · horizon) ×
    /// input_dim`, `timesteps` the (possibly fractional) diffusion step of each sequence,
    /// `global_cond` `batch × global_cond_dim`. Returns `(batch · horizon) × input_dim`.
    ///
    /// Runs under [`FlushSubnormals`] (the caller's floating-point mode is restored before it
    /// returns) and flushes subnormal inputs to zero: subnormal values cost some CPUs a
    /// microcode assist per operation, and a trained network fed tiny inputs (late sampling
    /// steps, near-constant channels) would otherwise run many times slower than on normal ones
    /// for a difference below 1e-38. Outputs on normal values are unchanged, bit for bit.
    pub fn forward(
        &mut self,
        x: MatRef<'_, f32>,
        timesteps: &[f32],
        global_cond: MatRef<'_, f32>,
    ) -> Result<MatRef<'_, f32>, NnError> {
        let _flush = FlushSubnormals::new();
        self.forward_flushed(x, timesteps, global_cond)
    }

    /// [`ConditionalUnet1d::forward`]'s body, run under its guard.
    fn forward_flushed(
        &mut self,
        x: MatRef<'_, f32>,
        timesteps: &[f32],
        global_cond: MatRef<'_, f32>,
    ) -> Result<MatRef<'_, f32>, NnError> {
        let c = &self.config;
        let batch = timesteps.len();
        if batch == 0
            || x.ncols() != c.input_dim
            || x.nrows() % batch != 0
            || global_cond.nrows() != batch
            || global_cond.ncols() != c.global_cond_dim
        {
            return Err(NnError::Config(format!(
                "U-Net: x {}x{}, {} timesteps and global_cond {}x{} do not fit input_dim {} and global_cond_dim {}",
                x.nrows(),
                x.ncols(),
                batch,
                global_cond.nrows(),
                global_cond.ncols(),
                c.input_dim,
                c.global_cond_dim
            )));
        }
        let horizon = x.nrows() / batch;
        if horizon % c.horizon_multiple() != 0 {
            return Err(NnError::Config(format!(
                "U-Net: horizon {horizon} is not a multiple of {}",
                c.horizon_multiple()
            )));
        }
        let (sed, gdim) = (c.step_embed_dim, c.global_cond_dim);
        // Step encoder, then mish([step | global_cond]) for every block's FiLM.
        ensure(&mut self.emb, batch, sed);
        sinusoidal_embedding(timesteps, self.emb.as_mut())?;
        self.step1.forward(self.emb.as_ref());
        mish_mat(self.step1.out.as_mut());
        let s = self.step2.forward(self.step1.out.as_ref());
        ensure(&mut self.cond, batch, sed + gdim);
        self.cond.as_mut().subcols_mut(0, sed).copy_from(s);
        self.cond.as_mut().subcols_mut(sed, gdim).copy_from(global_cond);
        mish_mat(self.cond.as_mut());
        flush_mat(self.cond.as_mut());
        let cond = self.cond.as_ref();

        ensure(&mut self.x, x.nrows(), x.ncols());
        self.x.copy_from(x);
        flush_mat(self.x.as_mut());
        for d in &mut self.downs {
            let h1 = d.res1.forward(self.x.as_ref(), cond, batch)?;
            let h2 = d.res2.forward(h1, cond, batch)?;
            ensure(&mut d.skip, h2.nrows(), h2.ncols());
            d.skip.copy_from(h2);
            let next = match &mut d.down {
                Some(conv) => conv.forward(d.skip.as_ref(), batch)?,
                None => d.skip.as_ref(),
            };
            ensure(&mut self.x, next.nrows(), next.ncols());
            self.x.copy_from(next);
        }
        for m in &mut self.mids {
            let y = m.forward(self.x.as_ref(), cond, batch)?;
            self.x.copy_from(y);
        }
        for (u, d) in self.ups.iter_mut().zip(self.downs.iter().rev()) {
            let (rows, cx, cs) = (self.x.nrows(), self.x.ncols(), d.skip.ncols());
            ensure(&mut u.cat, rows, cx + cs);
            u.cat.as_mut().subcols_mut(0, cx).copy_from(self.x.as_ref());
            u.cat.as_mut().subcols_mut(cx, cs).copy_from(d.skip.as_ref());
            let h1 = u.res1.forward(u.cat.as_ref(), cond, batch)?;
            let h2 = u.res2.forward(h1, cond, batch)?;
            let y = u.up.forward(h2, batch)?;
            ensure(&mut self.x, y.nrows(), y.ncols());
            self.x.copy_from(y);
        }
        self.final_block.forward(self.x.as_ref(), batch)?;
        let out = self.final_conv.forward(self.final_block.out().as_ref(), batch)?;
        Ok(out)
    }
}

/// [`flush_subnormal`] on every element (the portable half of [`FlushSubnormals`]: without
/// the hardware mode, subnormal inputs still become zeros before the first layer).
fn flush_mat(mut m: faer::MatMut<'_, f32>) {
    for j in 0..m.ncols() {
        for i in 0..m.nrows() {
            m[(i, j)] = flush_subnormal(m[(i, j)]);
        }
    }
}

impl Parameters for ConditionalUnet1d {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        let l = self.config.layout;
        let sub = if l == UnetLayout::DiffusionPolicy { ".conv" } else { "" };
        self.step1.visit(&join_name(prefix, "diffusion_step_encoder.1"), f);
        self.step2.visit(&join_name(prefix, "diffusion_step_encoder.3"), f);
        for (i, d) in self.downs.iter().enumerate() {
            let p = join_name(prefix, &format!("down_modules.{i}"));
            d.res1.visit(&join_name(&p, "0"), l, f);
            d.res2.visit(&join_name(&p, "1"), l, f);
            if let Some(c) = &d.down {
                c.visit_params(&format!("{}{sub}", join_name(&p, "2")), f);
            }
        }
        for (i, m) in self.mids.iter().enumerate() {
            m.visit(&join_name(prefix, &format!("mid_modules.{i}")), l, f);
        }
        for (i, u) in self.ups.iter().enumerate() {
            let p = join_name(prefix, &format!("up_modules.{i}"));
            u.res1.visit(&join_name(&p, "0"), l, f);
            u.res2.visit(&join_name(&p, "1"), l, f);
            u.up.visit_params(&format!("{}{sub}", join_name(&p, "2")), f);
        }
        self.final_block.visit(&join_name(prefix, "final_conv.0"), f);
        self.final_conv.visit_params(&join_name(prefix, "final_conv.1"), f);
    }

    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        let l = self.config.layout;
        let sub = if l == UnetLayout::DiffusionPolicy { ".conv" } else { "" };
        self.step1.visit_mut(&join_name(prefix, "diffusion_step_encoder.1"), f);
        self.step2.visit_mut(&join_name(prefix, "diffusion_step_encoder.3"), f);
        for (i, d) in self.downs.iter_mut().enumerate() {
            let p = join_name(prefix, &format!("down_modules.{i}"));
            d.res1.visit_mut(&join_name(&p, "0"), l, f);
            d.res2.visit_mut(&join_name(&p, "1"), l, f);
            if let Some(c) = &mut d.down {
                c.visit_params_mut(&format!("{}{sub}", join_name(&p, "2")), f);
            }
        }
        for (i, m) in self.mids.iter_mut().enumerate() {
            m.visit_mut(&join_name(prefix, &format!("mid_modules.{i}")), l, f);
        }
        for (i, u) in self.ups.iter_mut().enumerate() {
            let p = join_name(prefix, &format!("up_modules.{i}"));
            u.res1.visit_mut(&join_name(&p, "0"), l, f);
            u.res2.visit_mut(&join_name(&p, "1"), l, f);
            u.up.visit_params_mut(&format!("{}{sub}", join_name(&p, "2")), f);
        }
        self.final_block.visit_mut(&join_name(prefix, "final_conv.0"), f);
        self.final_conv.visit_params_mut(&join_name(prefix, "final_conv.1"), f);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn config(layout: UnetLayout) -> Unet1dConfig {
        Unet1dConfig {
            input_dim: 2,
            global_cond_dim: 3,
            step_embed_dim: 8,
            down_dims: vec![8, 16, 16],
            kernel_size: 3,
            n_groups: 4,
            film_scale: true,
            layout,
        }
    }

    #[test]
    fn parameter_names_follow_each_package() {
        let names = |l| {
            let u = ConditionalUnet1d::new(config(l)).unwrap();
            let mut v = Vec::new();
            u.visit_params("", &mut |n, _| v.push(n.to_owned()));
            v
        };
        let lr = names(UnetLayout::Lerobot);
        assert!(lr.contains(&"down_modules.0.0.conv1.block.0.weight".to_owned()));
        assert!(lr.contains(&"down_modules.0.2.weight".to_owned()));
        assert!(lr.contains(&"up_modules.1.2.bias".to_owned()));
        assert!(lr.contains(&"final_conv.0.block.1.weight".to_owned()));
        let dp = names(UnetLayout::DiffusionPolicy);
        assert!(dp.contains(&"down_modules.0.0.blocks.1.block.0.weight".to_owned()));
        assert!(dp.contains(&"down_modules.1.2.conv.weight".to_owned()));
        assert!(dp.contains(&"up_modules.0.2.conv.weight".to_owned()));
        assert!(!dp.contains(&"down_modules.2.2.conv.weight".to_owned()));
        assert_eq!(lr.len(), dp.len());
    }

    fn seeded(layout: UnetLayout) -> ConditionalUnet1d {
        let mut u = ConditionalUnet1d::new(config(layout)).unwrap();
        let mut k = 0u32;
        u.visit_params_mut("", &mut |_, p| {
            for v in &mut p.value {
                k = k.wrapping_mul(1_103_515_245).wrapping_add(12345);
                *v = ((k >> 16) % 1000) as f32 / 2000.0 - 0.25;
            }
        });
        u
    }

    #[test]
    fn subnormal_inputs_give_the_outputs_of_zero_inputs_and_the_mode_is_restored() {
        let mut u = seeded(UnetLayout::Lerobot);
        let h = 8;
        let tiny = f32::MIN_POSITIVE / 8.0;
        let xs = Mat::from_fn(2 * h, 2, |i, j| {
            tiny * (1 + i + j) as f32 * if j == 0 { 1.0 } else { -1.0 }
        });
        let gs = Mat::from_fn(2, 3, |i, j| -tiny * (1 + i + j) as f32);
        let half = |v: f32| std::hint::black_box(std::hint::black_box(v) * 0.5);
        assert!(half(f32::MIN_POSITIVE).is_subnormal());
        let got = u.forward(xs.as_ref(), &[0.0, 3.0], gs.as_ref()).unwrap().to_owned();
        assert!(half(f32::MIN_POSITIVE).is_subnormal(), "the caller's mode is restored");
        let (x0, g0) = (Mat::<f32>::zeros(2 * h, 2), Mat::<f32>::zeros(2, 3));
        let want = u.forward(x0.as_ref(), &[0.0, 3.0], g0.as_ref()).unwrap().to_owned();
        assert_eq!(got, want);
        assert!(got.col_iter().all(|c| c.iter().all(|v| v.is_finite() && !v.is_subnormal())));
        assert!(want.col_iter().any(|c| c.iter().any(|v| v.abs() > 1e-3)));
    }

    #[test]
    fn batch_rows_are_independent_and_shapes_are_checked() {
        let mut u = seeded(UnetLayout::Lerobot);
        let h = 8;
        let x = Mat::from_fn(3 * h, 2, |i, j| ((i * 7 + j * 3) % 5) as f32 * 0.3 - 0.6);
        let g = Mat::from_fn(3, 3, |i, j| (i + j) as f32 * 0.1);
        let all = u.forward(x.as_ref(), &[1.0, 20.0, 55.0], g.as_ref()).unwrap().to_owned();
        let one = u
            .forward(x.as_ref().subrows(h, h), &[20.0], g.as_ref().subrows(1, 1))
            .unwrap()
            .to_owned();
        for i in 0..h {
            for j in 0..2 {
                assert!((all[(h + i, j)] - one[(i, j)]).abs() < 1e-5);
            }
        }
        assert!(u.forward(x.as_ref().subrows(0, 6), &[1.0], g.as_ref().subrows(0, 1)).is_err());
        assert!(u.forward(x.as_ref(), &[1.0, 2.0], g.as_ref().subrows(0, 1)).is_err());
    }
}
