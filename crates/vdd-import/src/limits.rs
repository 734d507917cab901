//! What an imported package's files may ask for, checked before anything is built or parsed.
//!
//! Every architecture size a config names (widths, channels, kernel sizes, sequence lengths,
//! layers, heads) is checked against [`vdd_nn::limits`], and the network's parameter count is
//! computed arithmetically from the config (checked arithmetic, no allocation) and refused past
//! [`vdd_nn::limits::MAX_PARAMS`] *before* the network is built: a config asking for a
//! 65,536-channel U-Net is an error naming the file, the key and the value, not an 86 GB
//! allocation and an abort.
//!
//! Text files are read through the bounded reader ([`vdd_core::files`]) and their nesting is
//! measured by a linear pre-scan before a parser sees them, so a 100,000-deep `[[[…]]]` is
//! refused at once instead of hanging the YAML parser.
//!
//! | limit | value | what it bounds |
//! |---|---|---|
//! | [`vdd_nn::limits::MAX_WIDTH`] | 65,536 | any width, channel count or embedding size |
//! | [`vdd_nn::limits::MAX_BLOCKS`] | 1,024 | layers / residual blocks of one network |
//! | [`vdd_nn::limits::MAX_PARAMS`] | 2^29 | parameters of the imported network |
//! | [`MAX_KERNEL_SIZE`] | 1,024 | a convolution's kernel size |
//! | [`MAX_UNET_LEVELS`] | 16 | resolution levels (`down_dims` entries) of a U-Net |
//! | [`MAX_SEQUENCE`] | 4,096 | horizons, observation windows, token sequences |
//! | [`MAX_TEXT_BYTES`] | 16 MiB | a JSON or YAML file read |
//! | [`MAX_NESTING`] | 64 | nesting depth of a JSON or YAML document |
//!
//! ```
//! use vdd_import::limits;
//! assert_eq!(limits::json_nesting(br#"{"a": [[1], {"b": "[[["}]}"#), 3);
//! let deep = "[".repeat(100_000);
//! assert!(limits::yaml_nesting(&deep) > limits::MAX_NESTING);
//! ```

use vdd_nn::limits::{MAX_BLOCKS, MAX_PARAMS, MAX_WIDTH, linear_params};
use vdd_torch::{
    BlockNorm, DiffusionGptConfig, MlpActivation, ResMlpScoreConfig, SigmaEmbedding,
    TransformerForDiffusionConfig, Unet1dConfig,
};

/// Largest convolution kernel size.
pub const MAX_KERNEL_SIZE: usize = 1024;
/// Largest number of U-Net resolution levels (each but the last halves the horizon).
pub const MAX_UNET_LEVELS: usize = 16;
/// Largest horizon, observation window or token sequence.
pub const MAX_SEQUENCE: usize = 4096;
/// Largest JSON or YAML file read (configs are a few kB).
pub const MAX_TEXT_BYTES: u64 = 16 << 20;
/// Deepest nesting of a JSON or YAML document (hydra configs nest fewer than ten levels).
pub const MAX_NESTING: usize = 64;

/// Why a config's size is refused: the key (as the package names it), its value and the
/// reason. The importers turn it into their error type with the file's name.
#[derive(Debug, Clone, PartialEq)]
pub(crate) struct Refusal {
    pub(crate) key: String,
    pub(crate) value: String,
    pub(crate) reason: String,
}

impl Refusal {
    fn new(key: &str, value: impl ToString, reason: String) -> Self {
        Self { key: key.to_owned(), value: value.to_string(), reason }
    }

    /// As an [`crate::ImportError::BadValue`] of `file`.
    pub(crate) fn import(self, file: &str) -> crate::ImportError {
        crate::ImportError::bad(file, self.key, format!("{} ({})", self.value, self.reason))
    }

    /// As a [`crate::BesoError::BadValue`] of `path`, the key under `prefix`.
    pub(crate) fn beso(self, path: &std::path::Path, prefix: &str) -> crate::BesoError {
        crate::BesoError::BadValue {
            path: path.to_owned(),
            key: if prefix.is_empty() { self.key } else { format!("{prefix}.{}", self.key) },
            value: self.value,
            reason: self.reason,
        }
    }
}

/// `value` of `key` in `min..=max`.
fn size(key: &str, value: usize, min: usize, max: usize) -> Result<(), Refusal> {
    if value < min || value > max {
        return Err(Refusal::new(key, value, format!("must be in {min}..={max}")));
    }
    Ok(())
}

/// The parameter count `count` (of a network whose dominant size is `key` = `value`) within
/// [`MAX_PARAMS`].
fn params(key: &str, value: impl ToString, count: Option<usize>) -> Result<usize, Refusal> {
    match count {
        Some(n) if n <= MAX_PARAMS => Ok(n),
        Some(n) => Err(Refusal::new(
            key,
            value,
            format!("the network would have {n} parameters, more than the limit of {MAX_PARAMS}"),
        )),
        None => Err(Refusal::new(
            key,
            value,
            format!("the network's parameter count overflows (the limit is {MAX_PARAMS})"),
        )),
    }
}

fn add(terms: &[Option<usize>]) -> Option<usize> {
    terms.iter().try_fold(0usize, |acc, t| acc.checked_add((*t)?))
}

fn mul(a: usize, b: usize) -> Option<usize> {
    a.checked_mul(b)
}

/// A `Conv1d` / `ConvTranspose1d` `cin → cout` with kernel `k` (weight and bias).
fn conv_params(cin: usize, cout: usize, k: usize) -> Option<usize> {
    cin.checked_mul(cout)?.checked_mul(k)?.checked_add(cout)
}

/// Parameters of the conditional 1-D U-Net of `c` (`None`: the count overflows).
pub fn unet_params(c: &Unet1dConfig) -> Option<usize> {
    let k = c.kernel_size;
    let cond = c.step_embed_dim.checked_add(c.global_cond_dim)?;
    let res = |cin: usize, cout: usize| -> Option<usize> {
        let film = if c.film_scale { cout.checked_mul(2)? } else { cout };
        add(&[
            conv_params(cin, cout, k),
            mul(cout, 2),
            conv_params(cout, cout, k),
            mul(cout, 2),
            linear_params(cond, film),
            if cin != cout { conv_params(cin, cout, 1) } else { Some(0) },
        ])
    };
    let e = c.step_embed_dim;
    let mut total = add(&[linear_params(e, mul(e, 4)?), linear_params(mul(e, 4)?, e)])?;
    let mut cin = c.input_dim;
    let levels = c.down_dims.len();
    for (i, &cout) in c.down_dims.iter().enumerate() {
        let down = if i + 1 < levels { conv_params(cout, cout, 3) } else { Some(0) };
        total = add(&[Some(total), res(cin, cout), res(cout, cout), down])?;
        cin = cout;
    }
    let mid = *c.down_dims.last()?;
    total = add(&[Some(total), res(mid, mid), res(mid, mid)])?;
    for i in (1..levels).rev() {
        let (small, big) = (c.down_dims[i - 1], c.down_dims[i]);
        let up = conv_params(small, small, 4);
        total = add(&[Some(total), res(mul(big, 2)?, small), res(small, small), up])?;
    }
    let d0 = c.down_dims[0];
    add(&[Some(total), conv_params(d0, d0, k), mul(d0, 2), conv_params(d0, c.input_dim, 1)])
}

/// Checks a U-Net config (and the policy's `horizon` and `n_obs_steps`) against the limits;
/// returns its parameter count.
pub(crate) fn check_unet(
    c: &Unet1dConfig,
    horizon: usize,
    n_obs_steps: usize,
) -> Result<usize, Refusal> {
    size("input_dim", c.input_dim, 1, MAX_WIDTH)?;
    size("global_cond_dim", c.global_cond_dim, 0, MAX_WIDTH)?;
    size("diffusion_step_embed_dim", c.step_embed_dim, 1, MAX_WIDTH)?;
    size("kernel_size", c.kernel_size, 1, MAX_KERNEL_SIZE)?;
    size("n_groups", c.n_groups, 1, MAX_WIDTH)?;
    size("horizon", horizon, 1, MAX_SEQUENCE)?;
    size("n_obs_steps", n_obs_steps, 1, MAX_SEQUENCE)?;
    let dims = || format!("{:?}", c.down_dims);
    if c.down_dims.is_empty() || c.down_dims.len() > MAX_UNET_LEVELS {
        return Err(Refusal::new(
            "down_dims",
            dims(),
            format!("must have 1..={MAX_UNET_LEVELS} levels"),
        ));
    }
    if c.down_dims.iter().any(|&d| d == 0 || d > MAX_WIDTH) {
        return Err(Refusal::new(
            "down_dims",
            dims(),
            format!("widths must be in 1..={MAX_WIDTH}"),
        ));
    }
    params("down_dims", dims(), unet_params(c))
}

/// Parameters of BESO's `DiffusionGPT` of `c`.
pub fn gpt_params(c: &DiffusionGptConfig) -> Option<usize> {
    let d = c.embed_dim;
    let d4 = mul(d, 4)?;
    let block = add(&[
        mul(d, 4), // two LayerNorms
        mul(linear_params(d, d)?, 4),
        linear_params(d, d4),
        linear_params(d4, d),
    ])?;
    let seq = c.goal_tokens().checked_add(c.obs_seq_len)?.checked_add(1)?;
    let head = if c.linear_output {
        linear_params(d, c.action_dim)
    } else {
        add(&[linear_params(d, 100), linear_params(100, c.action_dim)])
    };
    add(&[
        linear_params(c.state_dim, d),
        mul(seq, d),
        mul(block, c.n_layers),
        mul(d, 2),
        linear_params(1, d),
        linear_params(c.action_dim, d),
        head,
    ])
}

/// Parameters of BESO's ResNet-MLP score network of `c`.
pub fn resmlp_params(c: &ResMlpScoreConfig) -> Option<usize> {
    let (te, h) = (c.time_embed_dim, c.hidden_dim);
    let prelu = usize::from(c.activation == MlpActivation::Prelu);
    let norm = if c.norm == BlockNorm::LayerNorm { mul(h, 2)? } else { 0 };
    let mlp = || add(&[linear_params(te, mul(te, 2)?), linear_params(mul(te, 2)?, te)]);
    let embed = match c.embedding {
        SigmaEmbedding::FourierFeatures => Some(te / 2),
        SigmaEmbedding::GaussianFourier => add(&[Some(te / 2), mlp()]),
        SigmaEmbedding::Sinusoidal => mlp(),
    };
    let goal = if c.goal_conditional { c.goal_dim } else { 0 };
    let input = add(&[Some(te), Some(c.obs_dim), Some(c.action_dim), Some(goal)])?;
    let block = add(&[mul(linear_params(h, h)?, 2), Some(norm), Some(prelu)])?;
    add(&[
        embed,
        linear_params(input, h),
        mul(block, c.num_hidden_layers / 2),
        linear_params(h, c.output_dim),
        Some(prelu),
    ])
}

/// Parameters of diffusion_policy's `TransformerForDiffusion` of `c`.
pub fn transformer_params(c: &TransformerForDiffusionConfig) -> Option<usize> {
    let d = c.n_emb;
    let d4 = mul(d, 4)?;
    let mha = add(&[linear_params(d, mul(d, 3)?), linear_params(d, d)])?;
    let layer = |cross: bool| {
        add(&[
            Some(mha),
            if cross { add(&[Some(mha), mul(d, 2)]) } else { Some(0) },
            linear_params(d, d4),
            linear_params(d4, d),
            mul(d, 4),
        ])
    };
    let t = c.horizon.checked_add(usize::from(!c.time_as_cond))?;
    let obs = if c.cond_dim > 0 { c.n_obs_steps } else { 0 };
    let t_cond = obs.checked_add(usize::from(c.time_as_cond))?;
    let decoder = t_cond > 0;
    let cond = if decoder {
        let encoder = match c.n_cond_layers {
            0 => add(&[linear_params(d, d4), linear_params(d4, d)]),
            k => mul(layer(false)?, k),
        };
        add(&[mul(t_cond, d), encoder])
    } else {
        Some(0)
    };
    add(&[
        linear_params(c.input_dim, d),
        mul(t, d),
        if c.cond_dim > 0 { linear_params(c.cond_dim, d) } else { Some(0) },
        cond,
        mul(layer(decoder)?, c.n_layer),
        mul(d, 2),
        linear_params(d, c.output_dim),
    ])
}

/// Checks BESO's `DiffusionGPT` config; returns its parameter count.
pub(crate) fn check_gpt(c: &DiffusionGptConfig) -> Result<usize, Refusal> {
    size("state_dim", c.state_dim, 1, MAX_WIDTH)?;
    size("action_dim", c.action_dim, 1, MAX_WIDTH)?;
    size("embed_dim", c.embed_dim, 1, MAX_WIDTH)?;
    size("n_layers", c.n_layers, 0, MAX_BLOCKS)?;
    size("n_heads", c.n_heads, 1, c.embed_dim)?;
    size("obs_seq_len", c.obs_seq_len, 1, MAX_SEQUENCE)?;
    size("goal_seq_len", c.goal_seq_len, 0, MAX_SEQUENCE)?;
    params("embed_dim", c.embed_dim, gpt_params(c))
}

/// Checks BESO's ResNet-MLP config; returns its parameter count.
pub(crate) fn check_resmlp(c: &ResMlpScoreConfig) -> Result<usize, Refusal> {
    size("obs_dim", c.obs_dim, 0, MAX_WIDTH)?;
    size("plan_dim", c.action_dim, 1, MAX_WIDTH)?;
    size("goal_dim", c.goal_dim, 0, MAX_WIDTH)?;
    size("hidden_dim", c.hidden_dim, 1, MAX_WIDTH)?;
    size("output_dim", c.output_dim, 1, MAX_WIDTH)?;
    size("embed_fn.time_embed_dim", c.time_embed_dim, 1, MAX_WIDTH)?;
    size("num_hidden_layers", c.num_hidden_layers, 0, 2 * MAX_BLOCKS)?;
    params("hidden_dim", c.hidden_dim, resmlp_params(c))
}

/// Checks a `TransformerForDiffusion` config; returns its parameter count.
pub(crate) fn check_transformer(c: &TransformerForDiffusionConfig) -> Result<usize, Refusal> {
    size("input_dim", c.input_dim, 1, MAX_WIDTH)?;
    size("output_dim", c.output_dim, 1, MAX_WIDTH)?;
    size("cond_dim", c.cond_dim, 0, MAX_WIDTH)?;
    size("n_emb", c.n_emb, 1, MAX_WIDTH)?;
    size("n_head", c.n_head, 1, c.n_emb)?;
    size("n_layer", c.n_layer, 0, MAX_BLOCKS)?;
    size("n_cond_layers", c.n_cond_layers, 0, MAX_BLOCKS)?;
    size("horizon", c.horizon, 1, MAX_SEQUENCE)?;
    size("n_obs_steps", c.n_obs_steps, 0, MAX_SEQUENCE)?;
    params("n_emb", c.n_emb, transformer_params(c))
}

/// The nesting depth of the JSON text `bytes` (arrays and objects; brackets inside strings
/// do not count), measured in one pass that stops as soon as it passes [`MAX_NESTING`].
pub fn json_nesting(bytes: &[u8]) -> usize {
    let (mut depth, mut max, mut in_str, mut escaped) = (0usize, 0usize, false, false);
    for &b in bytes {
        if in_str {
            match b {
                _ if escaped => escaped = false,
                b'\\' => escaped = true,
                b'"' => in_str = false,
                _ => {}
            }
            continue;
        }
        match b {
            b'"' => in_str = true,
            b'[' | b'{' => {
                depth += 1;
                max = max.max(depth);
                if max > MAX_NESTING {
                    return max;
                }
            }
            b']' | b'}' => depth = depth.saturating_sub(1),
            _ => {}
        }
    }
    max
}

/// A conservative estimate of the nesting depth of the YAML text `text`, measured in one pass
/// that stops as soon as it passes [`MAX_NESTING`]: block nesting (the stack of indentation
/// columns, each `- ` / `? ` entry indicator opening one more level) plus flow nesting (`[`,
/// `{`), skipping quoted scalars and comments. It may count a level more than the parser
/// would (a scalar after `- `, brackets in a block scalar), never fewer on flow or block
/// collections.
pub fn yaml_nesting(text: &str) -> usize {
    let (mut flow, mut max) = (0usize, 0usize);
    let mut block: Vec<usize> = Vec::new();
    // The open quote (`'` or `"`), which may span lines.
    let mut quote: Option<u8> = None;
    for line in text.lines() {
        let b = line.as_bytes();
        let mut i = 0;
        if flow == 0 && quote.is_none() {
            while i < b.len() && b[i] == b' ' {
                i += 1;
            }
            if i == b.len() || b[i] == b'#' {
                continue;
            }
            loop {
                while block.last().is_some_and(|&c| c >= i) {
                    block.pop();
                }
                block.push(i);
                if block.len() > MAX_NESTING {
                    return block.len();
                }
                let indicator =
                    matches!(b[i], b'-' | b'?') && b.get(i + 1).is_none_or(|&c| c == b' ');
                if !indicator {
                    break;
                }
                i += 1;
                while i < b.len() && b[i] == b' ' {
                    i += 1;
                }
                if i == b.len() {
                    break;
                }
            }
        }
        let mut prev = b' ';
        while i < b.len() {
            let c = b[i];
            match quote {
                Some(b'"') if c == b'\\' => i += 1,
                Some(b'\'') if c == b'\'' && b.get(i + 1) == Some(&b'\'') => i += 1,
                Some(q) if c == q => quote = None,
                Some(_) => {}
                None => match c {
                    b'#' if prev == b' ' || prev == b'\t' => break,
                    b'"' | b'\'' if matches!(prev, b' ' | b'\t' | b'[' | b'{' | b',' | b':') => {
                        quote = Some(c);
                    }
                    b'[' | b'{' => {
                        flow += 1;
                        max = max.max(flow + block.len());
                        if max > MAX_NESTING {
                            return max;
                        }
                    }
                    b']' | b'}' => flow = flow.saturating_sub(1),
                    _ => {}
                },
            }
            prev = c;
            i += 1;
        }
        max = max.max(flow + block.len());
    }
    max
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn lerobot_default_scale_fits_and_four_times_its_width_does_not() {
        // LeRobot 0.6.1's `DiffusionConfig` defaults, 2-D actions, 2 steps of 7 features.
        let c = Unet1dConfig {
            input_dim: 2,
            global_cond_dim: 14,
            step_embed_dim: 128,
            down_dims: vec![512, 1024, 2048],
            kernel_size: 5,
            n_groups: 8,
            film_scale: true,
            layout: vdd_torch::UnetLayout::Lerobot,
        };
        // The parameter count PyTorch reports for that policy (scripts/import/unet_fixtures.py
        // --default-scale): nothing but the U-Net has parameters without images.
        assert_eq!(check_unet(&c, 16, 2), Ok(248_128_642));
        let wide = Unet1dConfig { down_dims: vec![2048, 4096, 8192], ..c };
        let e = check_unet(&wide, 16, 2).unwrap_err();
        assert_eq!(e.key, "down_dims");
        assert!(e.reason.contains("more than the limit"), "{e:?}");
    }

    #[test]
    fn nesting_of_ordinary_documents() {
        assert_eq!(json_nesting(b"{\"a\": {\"b\": [1, 2, \"]]]\"]}}"), 3);
        assert_eq!(json_nesting(b"[\"\\\"[[[\"]"), 1);
        let yaml = "a:\n  b:\n    c: [1, [2, 3]] # [[[[\n  d: \"[[[[\"\n- e\n";
        assert_eq!(yaml_nesting(yaml), 5);
        assert!(yaml_nesting(&"- ".repeat(100_000)) > MAX_NESTING);
        assert!(yaml_nesting(&"{a: ".repeat(100_000)) > MAX_NESTING);
        // A string cannot hide brackets from the scan.
        assert!(yaml_nesting(&"[\"]\", ".repeat(1_000)) > MAX_NESTING);
    }
}
