//! diffusion_policy's `TransformerForDiffusion` from a converted checkpoint: its constructor
//! arguments (the `policy.model` section of the run's cfg, as JSON) and its state dict (as
//! safetensors, under a key prefix such as `model.`). The noise process around it (diffusers'
//! DDPM/DDIM schedulers) is the diffusion_policy importer's; this module only builds and checks
//! the network.

use std::collections::BTreeSet;
use std::path::Path;
use std::time::Instant;

use faer::Mat;
use serde::Deserialize;
use vdd_nn::Parameters;
use vdd_torch::{
    TransformerForDiffusion, TransformerForDiffusionConfig, transformer_for_diffusion_buffer_names,
};

use crate::beso_error::BesoError;

/// Names of the committed `TransformerForDiffusion` fixtures under `tests/fixtures/import/`.
pub const DP_TRANSFORMER_FIXTURES: &[&str] =
    &["dp_transformer", "dp_transformer_enc", "dp_transformer_bert"];

/// `TransformerForDiffusion.__init__`'s arguments as the cfg names them, with its defaults.
#[derive(Debug, Deserialize)]
struct Args {
    input_dim: usize,
    output_dim: usize,
    horizon: usize,
    #[serde(default)]
    n_obs_steps: Option<usize>,
    #[serde(default)]
    cond_dim: usize,
    #[serde(default = "twelve")]
    n_layer: usize,
    #[serde(default = "twelve")]
    n_head: usize,
    #[serde(default = "emb")]
    n_emb: usize,
    #[serde(default)]
    causal_attn: bool,
    #[serde(default = "yes")]
    time_as_cond: bool,
    #[serde(default)]
    n_cond_layers: usize,
}

fn twelve() -> usize {
    12
}
fn emb() -> usize {
    768
}
fn yes() -> bool {
    true
}

/// The network configuration from the cfg's `policy.model` section (a JSON object with
/// `TransformerForDiffusion`'s argument names; absent ones take PyTorch's defaults, dropout
/// rates and `_target_` are ignored). `what` names the source in errors.
pub fn dp_transformer_config(
    what: &str,
    model: &serde_json::Value,
) -> Result<TransformerForDiffusionConfig, BesoError> {
    let a: Args = serde_json::from_value(model.clone())
        .map_err(|source| BesoError::Json { what: what.to_owned(), source })?;
    let config = TransformerForDiffusionConfig {
        input_dim: a.input_dim,
        output_dim: a.output_dim,
        horizon: a.horizon,
        n_obs_steps: a.n_obs_steps.unwrap_or(a.horizon),
        cond_dim: a.cond_dim,
        n_layer: a.n_layer,
        n_head: a.n_head,
        n_emb: a.n_emb,
        causal_attn: a.causal_attn,
        time_as_cond: a.time_as_cond,
        n_cond_layers: a.n_cond_layers,
    };
    // Sizes first: nothing is built for a network past the limits.
    crate::limits::check_transformer(&config)
        .map_err(|r| r.beso(std::path::Path::new(what), ""))?;
    Ok(config)
}

/// A [`Parameters`] view with a key prefix.
struct Prefixed<'a>(&'a mut TransformerForDiffusion, &'a str);

impl Parameters for Prefixed<'_> {
    fn visit_params(&self, p: &str, f: &mut dyn FnMut(&str, &vdd_nn::Param)) {
        self.0.visit_params(&vdd_nn::join_name(p, self.1), f)
    }
    fn visit_params_mut(&mut self, p: &str, f: &mut dyn FnMut(&str, &mut vdd_nn::Param)) {
        self.0.visit_params_mut(&vdd_nn::join_name(p, self.1), f)
    }
}

/// Builds the network of `config` and loads its weights from the safetensors file `path`,
/// whose keys are the state dict's under `prefix` (`""` for the module's own state dict,
/// `"model"` for a diffusion_policy policy's). Only tensors under `prefix` are considered: a
/// missing one is an error naming it, and so is one the configured network does not have
/// (apart from the mask buffers the forward pass rebuilds).
pub fn load_dp_transformer(
    config: TransformerForDiffusionConfig,
    path: &Path,
    prefix: &str,
) -> Result<TransformerForDiffusion, BesoError> {
    let bytes = vdd_core::files::read_bounded(path, vdd_nn::io::MAX_FILE_BYTES)
        .map_err(|source| BesoError::Io { path: path.to_owned(), source })?;
    let (_, meta) = safetensors::SafeTensors::read_metadata(&bytes)
        .map_err(|source| vdd_nn::NnError::Malformed { path: path.to_owned(), source })?;
    let mut net = TransformerForDiffusion::new(config)?;
    let mut view = Prefixed(&mut net, prefix);
    let mut known = BTreeSet::new();
    view.visit_params("", &mut |name, _| {
        known.insert(name.to_owned());
    });
    let head = if prefix.is_empty() { String::new() } else { format!("{prefix}.") };
    let buffers = transformer_for_diffusion_buffer_names();
    for name in meta.tensors().keys() {
        let Some(local) = name.strip_prefix(&head) else { continue };
        let buffer = buffers.contains(&local) || local == "_dummy_variable";
        if !known.contains(name) && !buffer {
            return Err(BesoError::UnexpectedTensor { path: path.to_owned(), name: name.clone() });
        }
    }
    vdd_nn::io::load_safetensors_bytes(path, &bytes, &mut view)?;
    Ok(net)
}

#[derive(Debug, Deserialize)]
struct Fixture {
    network: serde_json::Value,
    sample: Vec<Vec<f64>>,
    timestep: Vec<f64>,
    cond: Option<Vec<Vec<f64>>>,
    output: Vec<Vec<f64>>,
    torch_rows_per_s: f64,
}

fn mat(v: &[Vec<f64>]) -> Mat<f32> {
    let w = v.first().map_or(0, Vec::len);
    Mat::from_fn(v.len(), w, |i, j| v[i].get(j).copied().unwrap_or(f64::NAN) as f32)
}

/// Loads `TransformerForDiffusion` fixture `name` from `dir` and returns the largest
/// `|ours − torch|` of its noise predictions, the fixture's `torch_rows_per_s` and the network.
pub fn check_dp_transformer_fixture(
    dir: &Path,
    name: &str,
) -> Result<(f64, f64, TransformerForDiffusion), BesoError> {
    let json_path = dir.join(format!("{name}.json"));
    let text = vdd_core::files::read_bounded_string(&json_path, crate::limits::MAX_TEXT_BYTES)
        .map_err(|source| BesoError::Io { path: json_path.clone(), source })?;
    let what = json_path.display().to_string();
    let fx: Fixture = serde_json::from_str(&text)
        .map_err(|source| BesoError::Json { what: what.clone(), source })?;
    let config = dp_transformer_config(&what, &fx.network)?;
    let mut net = load_dp_transformer(config, &dir.join(format!("{name}.safetensors")), "")?;
    let (x, want) = (mat(&fx.sample), mat(&fx.output));
    let cond = fx.cond.as_deref().map(mat);
    let t: Vec<f32> = fx.timestep.iter().map(|&v| v as f32).collect();
    let mut out = Mat::<f32>::zeros(want.nrows(), want.ncols());
    net.forward(x.as_ref(), &t, cond.as_ref().map(|c| c.as_ref()), out.as_mut())?;
    let mut diff = 0.0f64;
    for j in 0..want.ncols() {
        for i in 0..want.nrows() {
            let d = (f64::from(out[(i, j)]) - f64::from(want[(i, j)])).abs();
            diff = if d.is_nan() { f64::INFINITY } else { diff.max(d) };
        }
    }
    Ok((diff, fx.torch_rows_per_s, net))
}

/// Rows per second of the network's forward at batch `batch` on the calling thread, timed
/// over at least `min_secs` after one warm-up call.
pub fn dp_transformer_rows_per_s(
    net: &mut TransformerForDiffusion,
    batch: usize,
    min_secs: f64,
) -> Result<f64, BesoError> {
    let c = net.config().clone();
    let x =
        Mat::from_fn(batch, c.horizon * c.input_dim, |i, j| ((i * 7 + j) % 11) as f32 * 0.2 - 1.0);
    let cond = (c.cond_dim > 0).then(|| {
        Mat::from_fn(batch, c.n_obs_steps * c.cond_dim, |i, j| ((i + 3 * j) % 5) as f32 * 0.3)
    });
    let t: Vec<f32> = (0..batch).map(|i| (i % 100) as f32).collect();
    let mut out = Mat::<f32>::zeros(batch, c.horizon * c.output_dim);
    let cref = cond.as_ref().map(|m| m.as_ref());
    net.forward(x.as_ref(), &t, cref, out.as_mut())?;
    let (start, mut reps) = (Instant::now(), 0u64);
    while reps == 0 || start.elapsed().as_secs_f64() < min_secs {
        net.forward(x.as_ref(), &t, cref, out.as_mut())?;
        reps += 1;
    }
    Ok(batch as f64 * reps as f64 / start.elapsed().as_secs_f64())
}
