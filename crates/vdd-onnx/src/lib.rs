//! # vdd-onnx
//!
//! ONNX export of a saved mixture-of-experts policy, for deployment with ONNX Runtime,
//! TensorRT or any other ONNX runtime: [`export`] writes a graph (opset 17, IR version 8) with
//!
//! * input `obs`, `n x (obs_window · obs_dim)` float32: raw observations (`n` is dynamic). For
//!   a policy with an observation window (`DeploySpec::obs_window > 1`) a row is the whole
//!   window of raw observations, oldest first, as the Rust policy stacks them (at an episode's
//!   start it repeats the first observation); the spec's feature map is applied inside the
//!   graph to each observation of the window;
//! * outputs `log_gating` (`n x Z`), `means` (`n x Z x A`) and `scale_tril`
//!   (`n x Z x A x A`), the mixture `q(a|s) = Σ_z q(z|s) N(a; μ_z, L_z L_zᵀ)` in raw action
//!   space, equal to [`vdd_moe::Moe::components`]. `A = action_chunk · action_dim`: for a
//!   chunked policy a mean is the whole chunk of actions, in order.
//!
//! Acting with the outputs: pick an expert `z` with probability `exp(log_gating[i, z])` (or
//! `argmax` for greedy gating), then take `a = means[i, z]` (the mean, what the recipes
//! evaluate) or sample `a = means[i, z] + scale_tril[i, z] · ε` with `ε ~ N(0, I)`. Execute the
//! `execute_steps` actions of a chunk, from index `chunk_start` (`DeploySpec::chunk_start`, 0
//! unless set), before asking again. The graph holds no act mode: to act as a saved
//! [`vdd_moe::ActMode`] with `hold_steps > 1`, keep each episode's `z` for that many
//! predictions yourself.
//!
//! Supported: both expert families, shared or separate expert networks, learned or uniform
//! gating, every [`vdd_nn::Activation`], and the linear feature maps of `vdd_data::features`
//! (`identity`, `position_and_lag`); anything else is an [`OnnxError::Unsupported`].
//!
//! The protobuf is written by a small writer of our own ([`proto`]): the export needs a dozen
//! message types, and a protobuf code generator would bring a build-time compiler and a
//! runtime crate for them.
//!
//! ```
//! use vdd_moe::{Moe, MoeConfig};
//!
//! let moe = Moe::from_config(MoeConfig::toy(3, 2, 4), 0)?;
//! let bytes = vdd_onnx::export(&moe)?;
//! assert!(bytes.len() > 1000);
//! # Ok::<(), vdd_onnx::OnnxError>(())
//! ```
#![warn(missing_docs)]

mod graph;
pub mod proto;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};

use vdd_core::{Expert, ScaleActivation};
use vdd_moe::{GatingKind, Moe, NetworkConfig};
use vdd_nn::Parameters;

use graph::Graph;
use proto::{Attr, Dim, Msg};

/// Why an export failed.
#[derive(Debug, thiserror::Error)]
pub enum OnnxError {
    /// The policy uses something the exporter has no ONNX form for.
    #[error("cannot export to ONNX: {0}")]
    Unsupported(String),
    /// The policy could not be loaded or its spec is invalid.
    #[error(transparent)]
    Moe(#[from] vdd_moe::MoeError),
    /// A configuration value is invalid.
    #[error(transparent)]
    Core(#[from] vdd_core::CoreError),
    /// The deployment spec is invalid.
    #[error(transparent)]
    Data(#[from] vdd_data::DataError),
    /// Writing the file failed.
    #[error("cannot write {path}: {source}")]
    Io {
        /// The file.
        path: PathBuf,
        /// The I/O error.
        #[source]
        source: std::io::Error,
    },
}

/// The graph's opset (the default ONNX domain).
pub const OPSET: i64 = 17;
/// The file format's IR version.
pub const IR_VERSION: i64 = 8;

/// Loads the policy saved at `model` and writes its ONNX graph to `out`.
pub fn export_file(model: &Path, out: &Path) -> Result<(), OnnxError> {
    let moe = Moe::load(model)?;
    let bytes = export(&moe)?;
    std::fs::write(out, bytes).map_err(|source| OnnxError::Io { path: out.into(), source })
}

/// The mixture's ONNX model (see the [crate docs](crate)) as protobuf bytes.
pub fn export(moe: &Moe) -> Result<Vec<u8>, OnnxError> {
    let cfg = moe.config();
    let spec = moe.deploy_spec();
    let (raw_obs, _) = spec.raw_dims(cfg.state_dim, cfg.action_dim)?;
    let mut params = BTreeMap::new();
    moe.visit_params("", &mut |name, p| {
        params.insert(name.to_string(), p.value.clone());
    });
    if let Some(name) = params.keys().find(|k| k.contains("normalizer")) {
        return Err(OnnxError::Unsupported(format!("layer norm parameter `{name}`")));
    }
    let mut g = Graph::default();

    // Raw observations → the mixture's observations → normalised states.
    let map = spec.validate()?;
    let mut x = "obs".to_string();
    if !map.is_identity() {
        let m = linear_map_matrix(&map, raw_obs, spec.obs_window)?;
        let w = cfg.state_dim;
        let m = g.f32s("features", &[w, w], &m);
        x = g.op("MatMul", &[&x, &m], &[]);
    }
    if let Some(norm) = moe.normalizers().0 {
        let o = g.f32s("obs_offset", &[cfg.state_dim], &norm.offset);
        let s = g.f32s("obs_scale", &[cfg.state_dim], &norm.scale);
        let centred = g.op("Sub", &[&x, &o], &[]);
        x = g.op("Div", &[&centred, &s], &[]);
    }

    // The experts' raw outputs, (n, Z·r).
    let (z, d, r) = (cfg.num_experts, cfg.action_dim, moe.expert().raw_dim());
    let raw = if cfg.shared_trunk {
        residual_mlp(&mut g, &x, &params, "experts", &cfg.experts_network, cfg.state_dim)?
    } else {
        let outs: Vec<String> = (0..z)
            .map(|e| {
                let prefix = format!("experts.{e}");
                residual_mlp(&mut g, &x, &params, &prefix, &cfg.experts_network, cfg.state_dim)
            })
            .collect::<Result<_, _>>()?;
        let refs: Vec<&str> = outs.iter().map(String::as_str).collect();
        g.op("Concat", &refs, &[("axis", Attr::Int(1))])
    };
    let shape = g.i64s("shape", &[-1, z as i64, r as i64]);
    let raw = g.op("Reshape", &[&raw, &shape], &[]);
    let slice = |g: &mut Graph, from: usize, to: usize| {
        let (s, e, a) =
            (g.i64s("start", &[from as i64]), g.i64s("end", &[to as i64]), g.i64s("axis", &[2]));
        g.op("Slice", &[&raw, &s, &e, &a], &[])
    };
    let mean = slice(&mut g, 0, d);
    let scale_raw = slice(&mut g, d, r);

    // Scale factors: softplus(x + shift) + min_std on the diagonal, raw values below it,
    // scattered into a d x d lower-triangular matrix by a 0/1 matrix.
    let act = ScaleActivation::new(cfg.init_std, cfg.min_std)?;
    let shift = g.scalar(act.shift());
    let shifted = g.op("Add", &[&scale_raw, &shift], &[]);
    let sp = g.softplus(&shifted);
    let min_std = g.scalar(act.min_std());
    let diag_vals = g.op("Add", &[&sp, &min_std], &[]);
    let positions: Vec<(usize, usize)> = if moe.expert().is_diagonal() {
        (0..d).map(|i| (i, i)).collect()
    } else {
        (0..d).flat_map(|i| (0..=i).map(move |j| (i, j))).collect()
    };
    if positions.len() != r - d {
        return Err(OnnxError::Unsupported(format!(
            "an expert family with {r} raw outputs for {d}-D actions"
        )));
    }
    let entries = if moe.expert().is_diagonal() {
        diag_vals
    } else {
        let mask: Vec<bool> = positions.iter().map(|(i, j)| i == j).collect();
        let mask = g.bools("diagonal", &mask);
        g.op("Where", &[&mask, &diag_vals, &scale_raw], &[])
    };
    let mut scatter = vec![0.0f32; positions.len() * d * d];
    for (k, (i, j)) in positions.iter().enumerate() {
        scatter[k * d * d + i * d + j] = 1.0;
    }
    let scatter = g.f32s("tril_scatter", &[positions.len(), d * d], &scatter);
    let flat = g.op("MatMul", &[&entries, &scatter], &[]);
    let tril_shape = g.i64s("shape", &[-1, z as i64, d as i64, d as i64]);

    // Raw action space: μ = offset + scale ⊙ μ̃, L = diag(scale) L̃.
    match moe.normalizers().1 {
        Some(norm) => {
            let s = g.f32s("action_scale", &[d], &norm.scale);
            let o = g.f32s("action_offset", &[d], &norm.offset);
            let scaled = g.op("Mul", &[&mean, &s], &[]);
            g.op_into("Add", &[&scaled, &o], "means", &[]);
            let l = g.op("Reshape", &[&flat, &tril_shape], &[]);
            let rows = g.f32s("action_scale_rows", &[d, 1], &norm.scale);
            g.op_into("Mul", &[&l, &rows], "scale_tril", &[]);
        }
        None => {
            g.op_into("Identity", &[&mean], "means", &[]);
            g.op_into("Reshape", &[&flat, &tril_shape], "scale_tril", &[]);
        }
    }

    // Gating.
    match cfg.gating {
        GatingKind::Learned => {
            let logits =
                residual_mlp(&mut g, &x, &params, "gating", &cfg.gating_network, cfg.state_dim)?;
            g.op_into("LogSoftmax", &[&logits], "log_gating", &[("axis", Attr::Int(1))]);
        }
        GatingKind::Uniform => {
            let row = g.f32s("uniform", &[1, z], &vec![-(z as f32).ln(); z]);
            let obs_shape = g.op("Shape", &["obs"], &[]);
            let (s, e, a) = (g.i64s("start", &[0]), g.i64s("end", &[1]), g.i64s("axis", &[0]));
            let n = g.op("Slice", &[&obs_shape, &s, &e, &a], &[]);
            let zc = g.i64s("experts", &[z as i64]);
            let shape = g.op("Concat", &[&n, &zc], &[("axis", Attr::Int(0))]);
            g.op_into("Expand", &[&row, &shape], "log_gating", &[]);
        }
    }

    let n = Dim::Named("n");
    let inputs = [proto::value_info("obs", &[n.clone(), Dim::Fixed(cfg.state_dim)])];
    let outputs = [
        proto::value_info("log_gating", &[n.clone(), Dim::Fixed(z)]),
        proto::value_info("means", &[n.clone(), Dim::Fixed(z), Dim::Fixed(d)]),
        proto::value_info("scale_tril", &[n, Dim::Fixed(z), Dim::Fixed(d), Dim::Fixed(d)]),
    ];
    let graph = g.finish("vdd_policy", &inputs, &outputs);
    let opset = Msg::new().string(1, "").int(2, OPSET);
    let doc = format!(
        "VDD mixture-of-experts policy: {z} experts, obs {} ({} x {raw_obs} raw, features {}), \
         actions {d} ({} x {}). Pick z ~ exp(log_gating), act means[z] or means[z] + scale_tril[z] @ eps.",
        cfg.state_dim,
        spec.obs_window,
        spec.features,
        spec.action_chunk,
        d / spec.action_chunk,
    );
    let model = Msg::new()
        .int(1, IR_VERSION)
        .string(2, "vdd-onnx")
        .string(3, env!("CARGO_PKG_VERSION"))
        .string(6, &doc)
        .msg(7, &graph)
        .msg(8, &opset);
    Ok(model.0)
}

/// The matrix `M` (`W·k x W·k`) with `features(window) = window · M` for a linear feature map
/// applied to each of the `W` observations of `k` entries: found by mapping unit vectors, and
/// checked on a test vector (a map that is not linear is unsupported).
fn linear_map_matrix(
    map: &vdd_data::features::FeatureMap,
    k: usize,
    w: usize,
) -> Result<Vec<f32>, OnnxError> {
    let mut block = vec![0.0f32; k * k];
    for i in 0..k {
        let mut e = vec![0.0f32; k];
        e[i] = 1.0;
        map.apply(&mut e);
        block[i * k..(i + 1) * k].copy_from_slice(&e);
    }
    let probe: Vec<f32> = (0..k).map(|i| 0.37 * i as f32 - 1.3).collect();
    let mut mapped = probe.clone();
    map.apply(&mut mapped);
    for (j, m) in mapped.iter().enumerate() {
        let via: f32 = (0..k).map(|i| probe[i] * block[i * k + j]).sum();
        if (via - m).abs() > 1e-5 * (1.0 + m.abs()) {
            return Err(OnnxError::Unsupported(format!("the non-linear feature map {}", map.id())));
        }
    }
    let n = w * k;
    let mut full = vec![0.0f32; n * n];
    for s in 0..w {
        for i in 0..k {
            for j in 0..k {
                full[(s * k + i) * n + s * k + j] = block[i * k + j];
            }
        }
    }
    Ok(full)
}

/// A `vdd_nn::ResidualMlp` (input layer, pre-activation residual blocks, output layer) whose
/// parameters are `{prefix}.layers.{i}.*`.
fn residual_mlp(
    g: &mut Graph,
    x: &str,
    params: &BTreeMap<String, Vec<f32>>,
    prefix: &str,
    net: &NetworkConfig,
    in_dim: usize,
) -> Result<String, OnnxError> {
    let get = |name: String| {
        params
            .get(&name)
            .ok_or_else(|| OnnxError::Unsupported(format!("no parameter `{name}` in the model")))
    };
    let h = net.hidden_dim;
    let lin = |g: &mut Graph, x: &str, layer: String, in_dim: usize| -> Result<String, OnnxError> {
        let w = get(format!("{layer}.weight"))?;
        let b = get(format!("{layer}.bias"))?;
        if w.len() != b.len() * in_dim {
            return Err(OnnxError::Unsupported(format!("`{layer}.weight` has {} values", w.len())));
        }
        Ok(g.linear(x, w, b, in_dim))
    };
    let mut y = lin(g, x, format!("{prefix}.layers.0"), in_dim)?;
    for b in 1..=net.num_blocks {
        let a1 = g.activation(&y, net.activation);
        let l1 = lin(g, &a1, format!("{prefix}.layers.{b}.l1"), h)?;
        let a2 = g.activation(&l1, net.activation);
        let l2 = lin(g, &a2, format!("{prefix}.layers.{b}.l2"), h)?;
        y = g.op("Add", &[&y, &l2], &[]);
    }
    lin(g, &y, format!("{prefix}.layers.{}", net.num_blocks + 1), h)
}
