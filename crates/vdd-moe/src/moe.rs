//! The mixture of experts `q(a|s) = Σ_z q(z|s) N(a; μ_z(s), L_z(s) L_z(s)ᵀ)`.

use std::collections::BTreeMap;
use std::path::Path;

use faer::{Mat, MatRef};
use rand::{Rng as _, SeedableRng};
use serde::{Deserialize, Serialize};
use vdd_core::gaussian::{self, log_sum_exp};
use vdd_core::{
    Affine, CoreError, Expert, Policy, Rng, Seeds, check_act_args, check_finite, check_len,
    check_shape,
};
use vdd_nn::{Activation, Module, Param, Parameters, ResidualMlp, ResidualMlpConfig};

use crate::error::MoeError;
use crate::experts::{ExpertFamily, ExpertKind};

/// Shape of one residual MLP (experts or gating).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct NetworkConfig {
    /// Width of the residual stream.
    pub hidden_dim: usize,
    /// Number of two-layer residual blocks.
    pub num_blocks: usize,
    /// Nonlinearity.
    pub activation: Activation,
}

impl Default for NetworkConfig {
    /// The paper's toy network: Mish, 64 wide, one residual block (two hidden layers).
    fn default() -> Self {
        Self { hidden_dim: 64, num_blocks: 1, activation: Activation::Mish }
    }
}

/// How the gating `q(z|s)` is represented.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum GatingKind {
    /// Fixed `q(z|s) = 1/Z` (higher diversity in the paper's ablation).
    #[default]
    Uniform,
    /// A softmax over the logits of a network of the state.
    Learned,
}

/// Everything that defines a mixture's architecture and initialisation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct MoeConfig {
    /// Dimension of the (normalised) state the networks see.
    pub state_dim: usize,
    /// Dimension of an action (a flattened chunk for chunked policies).
    pub action_dim: usize,
    /// Number of experts `Z`.
    pub num_experts: usize,
    /// Diagonal or full-covariance experts.
    pub expert_kind: ExpertKind,
    /// Standard deviation of every expert at initialisation.
    pub init_std: f32,
    /// Lower bound of every expert's standard deviations.
    pub min_std: f32,
    /// Network producing the experts' means and scales.
    pub experts_network: NetworkConfig,
    /// One trunk emitting all experts' outputs (`true`) or one network per expert (`false`).
    pub shared_trunk: bool,
    /// Gating representation.
    pub gating: GatingKind,
    /// Network producing the gating logits (when learned).
    pub gating_network: NetworkConfig,
    /// Mean output biases are initialised `U[−w, w]` with this half-width `w` (the official
    /// code's `U[−0.5, 0.5]` spreads the experts at the start).
    pub mean_bias_init: f32,
}

impl MoeConfig {
    /// The paper's toy defaults for a `state_dim → action_dim` mixture of `num_experts`
    /// diagonal experts with uniform gating.
    pub fn toy(state_dim: usize, action_dim: usize, num_experts: usize) -> Self {
        Self {
            state_dim,
            action_dim,
            num_experts,
            expert_kind: ExpertKind::Diagonal,
            init_std: 1.0,
            min_std: 1e-4,
            experts_network: NetworkConfig::default(),
            shared_trunk: true,
            gating: GatingKind::Uniform,
            gating_network: NetworkConfig::default(),
            mean_bias_init: 0.5,
        }
    }

    fn validate(&self) -> Result<(), CoreError> {
        if self.state_dim == 0 || self.action_dim == 0 || self.num_experts == 0 {
            return Err(CoreError::Config(
                "state_dim, action_dim and num_experts must be positive".into(),
            ));
        }
        if !(self.mean_bias_init.is_finite() && self.mean_bias_init >= 0.0) {
            return Err(CoreError::Config("mean_bias_init must be finite and >= 0".into()));
        }
        Ok(())
    }
}

/// How [`Policy::act`] turns the mixture into one action.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ActMode {
    /// Pick the most probable expert instead of sampling `z ~ q(z|s)`.
    pub greedy_gating: bool,
    /// Sample `a ~ N(μ_z, Σ_z)` instead of returning `μ_z` (the paper evaluates with `μ_z`).
    pub sample_action: bool,
}

#[derive(Debug, Clone)]
enum ExpertNets {
    Shared(Box<ResidualMlp>),
    Separate(Vec<ResidualMlp>),
}

/// The experts' networks, as one [`Parameters`] for an optimiser.
#[derive(Debug, Clone)]
pub struct ExpertNetworks(ExpertNets);

impl Parameters for ExpertNetworks {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        match &self.0 {
            ExpertNets::Shared(net) => net.visit_params(prefix, f),
            ExpertNets::Separate(nets) => {
                for (z, net) in nets.iter().enumerate() {
                    net.visit_params(&vdd_nn::join_name(prefix, &z.to_string()), f);
                }
            }
        }
    }
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        match &mut self.0 {
            ExpertNets::Shared(net) => net.visit_params_mut(prefix, f),
            ExpertNets::Separate(nets) => {
                for (z, net) in nets.iter_mut().enumerate() {
                    net.visit_params_mut(&vdd_nn::join_name(prefix, &z.to_string()), f);
                }
            }
        }
    }
}

/// The per-state outputs of the last forward pass: for `n` states and `Z` experts, row-major
/// `raw` (`n·Z·raw_dim`), `means` (`n·Z·d`), `scales` (`n·Z·d·d`, lower-triangular `L`) and
/// `log_gating` (`n·Z`, `log q(z|s)`).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct MoeOutput {
    /// Number of states.
    pub n: usize,
    /// Number of experts.
    pub num_experts: usize,
    /// Action dimension.
    pub action_dim: usize,
    /// Raw network outputs per (state, expert).
    pub raw: Vec<f32>,
    /// Means per (state, expert).
    pub means: Vec<f32>,
    /// Scale factors `L` per (state, expert).
    pub scales: Vec<f32>,
    /// `log q(z|s)` per (state, expert).
    pub log_gating: Vec<f32>,
}

impl MoeOutput {
    /// `μ_z(s_b)`.
    pub fn mean(&self, b: usize, z: usize) -> &[f32] {
        let d = self.action_dim;
        let k = b * self.num_experts + z;
        &self.means[k * d..(k + 1) * d]
    }

    /// `L_z(s_b)` (`d·d`, row-major).
    pub fn scale(&self, b: usize, z: usize) -> &[f32] {
        let dd = self.action_dim * self.action_dim;
        let k = b * self.num_experts + z;
        &self.scales[k * dd..(k + 1) * dd]
    }

    /// `log q(·|s_b)` over the experts.
    pub fn log_gating_row(&self, b: usize) -> &[f32] {
        &self.log_gating[b * self.num_experts..(b + 1) * self.num_experts]
    }

    /// `log q(a|s_b) = logsumexp_z [log q(z|s_b) + log N(a; μ_z, Σ_z)]`; also writes the
    /// responsibilities `q(z|a, s_b)` into `resp` (length `Z`). `work` is scratch of length `d`.
    pub fn log_density_and_responsibilities(
        &self,
        b: usize,
        a: &[f32],
        resp: &mut [f32],
        work: &mut [f32],
    ) -> f32 {
        for (z, r) in resp.iter_mut().enumerate() {
            *r = self.log_gating[b * self.num_experts + z]
                + gaussian::log_density(a, self.mean(b, z), self.scale(b, z), work);
        }
        gaussian::softmax_in_place(resp)
    }
}

/// A mixture of Gaussian experts with a gating distribution; a [`Policy`] that acts with one
/// network evaluation and has an exact likelihood.
///
/// The networks see normalised states and emit normalised actions; the optional observation
/// and action normalisers are applied by the [`Policy`] methods and saved with the model.
///
/// ```
/// use vdd_core::Policy;
/// use vdd_moe::{Moe, MoeConfig};
/// let mut moe = Moe::from_config(MoeConfig::toy(1, 2, 4), 0).unwrap();
/// let a = moe.act(&[0.0]).unwrap();
/// assert_eq!(a.len(), 2);
/// let mut ll = [0.0];
/// moe.log_likelihood(faer::mat![[0.0f32]].as_ref(), faer::mat![[0.1f32, 0.2]].as_ref(), &mut ll).unwrap();
/// assert!(ll[0].is_finite());
/// ```
#[derive(Debug, Clone)]
pub struct Moe<E: Expert = ExpertFamily> {
    config: MoeConfig,
    expert: E,
    experts: ExpertNetworks,
    gating: Option<ResidualMlp>,
    obs_normalizer: Option<Affine>,
    action_normalizer: Option<Affine>,
    act_mode: ActMode,
    rng: Rng,
    out: MoeOutput,
    states: Mat<f32>,
    grad: Mat<f32>,
    resp: Vec<f32>,
    work: Vec<f32>,
}

impl Moe<ExpertFamily> {
    /// A mixture whose expert family is chosen by `config.expert_kind`.
    pub fn from_config(config: MoeConfig, seed: u64) -> Result<Self, MoeError> {
        let family = ExpertFamily::new(
            config.expert_kind,
            config.action_dim,
            config.init_std,
            config.min_std,
        )?;
        Self::new(config, family, seed)
    }

    /// Loads a mixture saved by [`Moe::save`] (family from the saved configuration).
    pub fn load(path: &Path) -> Result<Self, MoeError> {
        let (config, meta) = read_config(path)?;
        let family = ExpertFamily::new(
            config.expert_kind,
            config.action_dim,
            config.init_std,
            config.min_std,
        )?;
        Self::load_with(path, family, Some((config, meta)))
    }
}

fn read_config(path: &Path) -> Result<(MoeConfig, BTreeMap<String, String>), MoeError> {
    let meta = vdd_nn::io::read_metadata(path)?;
    let cfg = meta
        .get("config")
        .ok_or_else(|| MoeError::Config(format!("{} has no `config` metadata", path.display())))?;
    let config: MoeConfig =
        serde_json::from_str(cfg).map_err(|e| MoeError::Config(e.to_string()))?;
    Ok((config, meta))
}

impl<E: Expert> Moe<E> {
    /// A freshly initialised mixture with a custom expert family (`expert.action_dim()` must
    /// equal `config.action_dim`). Initialisation draws from `Seeds::new(seed).stream("moe-init")`.
    pub fn new(config: MoeConfig, expert: E, seed: u64) -> Result<Self, MoeError> {
        config.validate()?;
        check_len("expert family action_dim", expert.action_dim(), config.action_dim)?;
        let seeds = Seeds::new(seed);
        let mut rng = seeds.stream("moe-init");
        let z = config.num_experts;
        let r = expert.raw_dim();
        let d = config.action_dim;
        let net = |out_dim: usize, nc: &NetworkConfig, rng: &mut Rng| {
            ResidualMlp::new(
                &ResidualMlpConfig {
                    in_dim: config.state_dim,
                    hidden_dim: nc.hidden_dim,
                    num_blocks: nc.num_blocks,
                    out_dim,
                    activation: nc.activation,
                    layer_norm: false,
                },
                rng,
            )
        };
        let w = config.mean_bias_init;
        let init_mean_bias = |net: &mut ResidualMlp, experts: usize, rng: &mut Rng| {
            let bias = &mut net.output_layer_mut().bias.value;
            for e in 0..experts {
                for (k, b) in bias[e * r..(e + 1) * r].iter_mut().enumerate() {
                    *b = if k < d && w > 0.0 { rng.random_range(-w..=w) } else { 0.0 };
                }
            }
        };
        let experts = if config.shared_trunk {
            let mut n = net(z * r, &config.experts_network, &mut rng)?;
            init_mean_bias(&mut n, z, &mut rng);
            ExpertNets::Shared(Box::new(n))
        } else {
            let mut nets = Vec::with_capacity(z);
            for _ in 0..z {
                let mut n = net(r, &config.experts_network, &mut rng)?;
                init_mean_bias(&mut n, 1, &mut rng);
                nets.push(n);
            }
            ExpertNets::Separate(nets)
        };
        let gating = match config.gating {
            GatingKind::Uniform => None,
            GatingKind::Learned => Some(net(z, &config.gating_network, &mut rng)?),
        };
        Ok(Self {
            expert,
            experts: ExpertNetworks(experts),
            gating,
            obs_normalizer: None,
            action_normalizer: None,
            act_mode: ActMode::default(),
            rng: seeds.stream("moe-act"),
            out: MoeOutput { num_experts: z, action_dim: d, ..Default::default() },
            states: Mat::zeros(0, 0),
            grad: Mat::zeros(0, 0),
            resp: vec![0.0; z],
            work: vec![0.0; d],
            config,
        })
    }

    /// The architecture.
    pub fn config(&self) -> &MoeConfig {
        &self.config
    }

    /// The expert family.
    pub fn expert(&self) -> &E {
        &self.expert
    }

    /// Number of experts `Z`.
    pub fn num_experts(&self) -> usize {
        self.config.num_experts
    }

    /// Whether the gating is a learned network.
    pub fn has_learned_gating(&self) -> bool {
        self.gating.is_some()
    }

    /// Sets how [`Policy::act`] picks the expert and the action.
    pub fn set_act_mode(&mut self, mode: ActMode) {
        self.act_mode = mode;
    }

    /// Attaches observation and action normalisers (used by the [`Policy`] methods only;
    /// the networks work in normalised space).
    pub fn set_normalizers(
        &mut self,
        obs: Option<Affine>,
        action: Option<Affine>,
    ) -> Result<(), MoeError> {
        if let Some(o) = &obs {
            check_len("observation normalizer", o.dim(), self.config.state_dim)?;
        }
        if let Some(a) = &action {
            check_len("action normalizer", a.dim(), self.config.action_dim)?;
        }
        self.obs_normalizer = obs;
        self.action_normalizer = action;
        Ok(())
    }

    /// The experts' networks (for an optimiser).
    pub fn expert_networks_mut(&mut self) -> &mut ExpertNetworks {
        &mut self.experts
    }

    /// The gating network, if learned (for an optimiser).
    pub fn gating_network_mut(&mut self) -> Option<&mut ResidualMlp> {
        self.gating.as_mut()
    }

    /// The outputs of the last forward passes.
    pub fn output(&self) -> &MoeOutput {
        &self.out
    }

    fn check_states(&self, states: MatRef<'_, f32>) -> Result<(), MoeError> {
        check_shape("states", states, states.nrows(), self.config.state_dim)?;
        check_finite("states", states)?;
        Ok(())
    }

    /// Runs the experts' networks on `n x state_dim` (normalised) states and decodes means and
    /// scales into [`Moe::output`].
    pub fn forward_experts(&mut self, states: MatRef<'_, f32>) -> Result<(), MoeError> {
        self.check_states(states)?;
        let (n, z, r, d) = (
            states.nrows(),
            self.config.num_experts,
            self.expert.raw_dim(),
            self.config.action_dim,
        );
        let out = &mut self.out;
        out.n = n;
        out.raw.resize(n * z * r, 0.0);
        out.means.resize(n * z * d, 0.0);
        out.scales.resize(n * z * d * d, 0.0);
        match &mut self.experts.0 {
            ExpertNets::Shared(net) => {
                let y = net.forward(states);
                for b in 0..n {
                    for c in 0..z * r {
                        out.raw[b * z * r + c] = y[(b, c)];
                    }
                }
            }
            ExpertNets::Separate(nets) => {
                for (e, net) in nets.iter_mut().enumerate() {
                    let y = net.forward(states);
                    for b in 0..n {
                        for c in 0..r {
                            out.raw[(b * z + e) * r + c] = y[(b, c)];
                        }
                    }
                }
            }
        }
        for k in 0..n * z {
            self.expert.decode(
                &out.raw[k * r..(k + 1) * r],
                &mut out.means[k * d..(k + 1) * d],
                &mut out.scales[k * d * d..(k + 1) * d * d],
            );
        }
        Ok(())
    }

    /// Computes `log q(z|s)` for `n x state_dim` states into [`Moe::output`].
    pub fn forward_gating(&mut self, states: MatRef<'_, f32>) -> Result<(), MoeError> {
        self.check_states(states)?;
        let (n, z) = (states.nrows(), self.config.num_experts);
        self.out.log_gating.resize(n * z, 0.0);
        match &mut self.gating {
            None => self.out.log_gating.fill(-(z as f32).ln()),
            Some(net) => {
                let y = net.forward(states);
                for b in 0..n {
                    let row = &mut self.out.log_gating[b * z..(b + 1) * z];
                    for (e, v) in row.iter_mut().enumerate() {
                        *v = y[(b, e)];
                    }
                    let lse = log_sum_exp(row);
                    for v in row.iter_mut() {
                        *v -= lse;
                    }
                }
            }
        }
        Ok(())
    }

    /// Both forward passes.
    pub fn forward(&mut self, states: MatRef<'_, f32>) -> Result<(), MoeError> {
        self.forward_experts(states)?;
        self.forward_gating(states)
    }

    /// Back-propagates `∂loss/∂raw` (row-major `n·Z·raw_dim`, for the last
    /// [`Moe::forward_experts`]) into the experts' parameter gradients.
    pub fn backward_experts(&mut self, grad_raw: &[f32]) -> Result<(), MoeError> {
        let (n, z, r) = (self.out.n, self.config.num_experts, self.expert.raw_dim());
        check_len("raw-output gradient", grad_raw.len(), n * z * r)?;
        match &mut self.experts.0 {
            ExpertNets::Shared(net) => {
                if self.grad.nrows() != n || self.grad.ncols() != z * r {
                    self.grad = Mat::zeros(n, z * r);
                }
                for b in 0..n {
                    for c in 0..z * r {
                        self.grad[(b, c)] = grad_raw[b * z * r + c];
                    }
                }
                net.backward(self.grad.as_ref());
            }
            ExpertNets::Separate(nets) => {
                if self.grad.nrows() != n || self.grad.ncols() != r {
                    self.grad = Mat::zeros(n, r);
                }
                for (e, net) in nets.iter_mut().enumerate() {
                    for b in 0..n {
                        for c in 0..r {
                            self.grad[(b, c)] = grad_raw[(b * z + e) * r + c];
                        }
                    }
                    net.backward(self.grad.as_ref());
                }
            }
        }
        Ok(())
    }

    /// Back-propagates `∂loss/∂logits` (`n x Z`, for the last [`Moe::forward_gating`]) into the
    /// gating network's gradients. A no-op for uniform gating.
    pub fn backward_gating(&mut self, grad_logits: MatRef<'_, f32>) -> Result<(), MoeError> {
        // Rows of the last gating forward (which may differ from the experts' batch).
        let rows = self.out.log_gating.len() / self.config.num_experts;
        check_shape("gating gradient", grad_logits, rows, self.config.num_experts)?;
        if let Some(net) = &mut self.gating {
            net.backward(grad_logits);
        }
        Ok(())
    }

    /// Writes `q(z|a, s)` for each (normalised) state–action row into `out` (`n x Z`).
    pub fn responsibilities(
        &mut self,
        states: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
        mut out: faer::MatMut<'_, f32>,
    ) -> Result<(), MoeError> {
        let n = states.nrows();
        check_shape("actions", actions, n, self.config.action_dim)?;
        check_shape("responsibilities", out.as_ref(), n, self.config.num_experts)?;
        check_finite("actions", actions)?;
        self.forward(states)?;
        let mut a = vec![0.0; self.config.action_dim];
        for b in 0..n {
            for (j, v) in a.iter_mut().enumerate() {
                *v = actions[(b, j)];
            }
            self.out.log_density_and_responsibilities(b, &a, &mut self.resp, &mut self.work);
            for (z, r) in self.resp.iter().enumerate() {
                out[(b, z)] = *r;
            }
        }
        Ok(())
    }

    /// Entropy of each expert at each state (`n x Z`), in nats.
    pub fn expert_entropies(&mut self, states: MatRef<'_, f32>) -> Result<Mat<f32>, MoeError> {
        self.forward_experts(states)?;
        let (n, z, d) = (states.nrows(), self.config.num_experts, self.config.action_dim);
        Ok(Mat::from_fn(n, z, |b, e| gaussian::entropy(self.out.scale(b, e), d)))
    }

    /// Saves weights, configuration and normalisers to one `safetensors` file (atomically).
    pub fn save(&self, path: &Path) -> Result<(), MoeError> {
        let mut meta = BTreeMap::new();
        let json = |v: &dyn erased::Json| v.to_json();
        meta.insert("config".to_owned(), json(&self.config));
        meta.insert("obs_normalizer".to_owned(), json(&self.obs_normalizer));
        meta.insert("action_normalizer".to_owned(), json(&self.action_normalizer));
        meta.insert("act_mode".to_owned(), json(&self.act_mode));
        vdd_nn::io::save_safetensors(path, self, &meta)?;
        Ok(())
    }

    /// Loads a mixture saved by [`Moe::save`] with a custom expert family.
    pub fn load_with_family(path: &Path, expert: E) -> Result<Self, MoeError> {
        Self::load_with(path, expert, None)
    }

    fn load_with(
        path: &Path,
        expert: E,
        config: Option<(MoeConfig, BTreeMap<String, String>)>,
    ) -> Result<Self, MoeError> {
        let (config, meta) = match config {
            Some(c) => c,
            None => read_config(path)?,
        };
        let mut moe = Self::new(config, expert, 0)?;
        vdd_nn::io::load_safetensors(path, &mut moe)?;
        let parse = |key: &str| -> Result<&str, MoeError> {
            meta.get(key)
                .map(String::as_str)
                .ok_or_else(|| MoeError::Config(format!("missing `{key}` metadata")))
        };
        let bad = |e: serde_json::Error| MoeError::Config(e.to_string());
        let obs: Option<Affine> = serde_json::from_str(parse("obs_normalizer")?).map_err(bad)?;
        let act: Option<Affine> = serde_json::from_str(parse("action_normalizer")?).map_err(bad)?;
        moe.act_mode = serde_json::from_str(parse("act_mode")?).map_err(bad)?;
        moe.set_normalizers(obs, act)?;
        Ok(moe)
    }

    fn load_normalized_states(&mut self, obs: MatRef<'_, f32>) {
        let (n, ds) = (obs.nrows(), self.config.state_dim);
        if self.states.nrows() != n || self.states.ncols() != ds {
            self.states = Mat::zeros(n, ds);
        }
        self.states.copy_from(obs);
        if let Some(norm) = &self.obs_normalizer {
            for j in 0..ds {
                let (o, s) = (norm.offset[j], norm.scale[j]);
                for v in self.states.col_as_slice_mut(j) {
                    *v = (*v - o) / s;
                }
            }
        }
    }

    fn log_det_action_scale(&self) -> f32 {
        self.action_normalizer.as_ref().map_or(0.0, |a| a.scale.iter().map(|s| s.ln()).sum())
    }

    /// Picks an expert for state `b` of the last forward and writes the action (normalised).
    fn choose_action(&mut self, b: usize, action: &mut [f32]) {
        let z = self.config.num_experts;
        let lg = &self.out.log_gating[b * z..(b + 1) * z];
        let e = if self.act_mode.greedy_gating {
            (0..z).fold(0, |best, k| if lg[k] > lg[best] { k } else { best })
        } else {
            let u: f32 = self.rng.random();
            let mut acc = 0.0;
            let mut pick = z - 1;
            for (k, l) in lg.iter().enumerate() {
                acc += l.exp();
                if u < acc {
                    pick = k;
                    break;
                }
            }
            pick
        };
        let mean = self.out.mean(b, e);
        if self.act_mode.sample_action {
            let d = self.config.action_dim;
            vdd_core::fill_standard_normal(&mut self.rng, &mut self.work[..d]);
            gaussian::sample_into(mean, self.out.scale(b, e), &self.work[..d], action);
        } else {
            action.copy_from_slice(mean);
        }
        if let Some(norm) = &self.action_normalizer {
            norm.denormalize(action);
        }
    }
}

mod erased {
    pub trait Json {
        fn to_json(&self) -> String;
    }
    impl<T: serde::Serialize> Json for T {
        fn to_json(&self) -> String {
            serde_json::to_string(self).expect("configuration types serialise")
        }
    }
}

impl<E: Expert> Parameters for Moe<E> {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        self.experts.visit_params(&vdd_nn::join_name(prefix, "experts"), f);
        if let Some(g) = &self.gating {
            g.visit_params(&vdd_nn::join_name(prefix, "gating"), f);
        }
    }
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        self.experts.visit_params_mut(&vdd_nn::join_name(prefix, "experts"), f);
        if let Some(g) = &mut self.gating {
            g.visit_params_mut(&vdd_nn::join_name(prefix, "gating"), f);
        }
    }
}

impl<E: Expert> Policy for Moe<E> {
    fn obs_dim(&self) -> usize {
        self.config.state_dim
    }
    fn action_dim(&self) -> usize {
        self.config.action_dim
    }
    fn seed(&mut self, seed: u64) {
        self.rng = Seeds::new(seed).stream("moe-act");
    }

    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
        check_act_args(self, obs, action)?;
        let o = MatRef::from_row_major_slice(obs, 1, obs.len());
        self.act_batch_inner(o)?;
        self.choose_action(0, action);
        Ok(())
    }

    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        mut actions: faer::MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        let n = obs.nrows();
        check_shape("actions", actions.as_ref(), n, self.config.action_dim)?;
        self.act_batch_inner(obs)?;
        let mut a = std::mem::take(&mut self.resp);
        a.resize(self.config.action_dim.max(self.config.num_experts), 0.0);
        for b in 0..n {
            let d = self.config.action_dim;
            self.choose_action(b, &mut a[..d]);
            for j in 0..d {
                actions[(b, j)] = a[j];
            }
        }
        a.truncate(self.config.num_experts);
        self.resp = a;
        Ok(())
    }

    fn has_likelihood(&self) -> bool {
        true
    }

    fn log_likelihood(
        &mut self,
        obs: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
        out: &mut [f32],
    ) -> vdd_core::Result<()> {
        let n = obs.nrows();
        check_shape("observations", obs, n, self.config.state_dim)?;
        check_shape("actions", actions, n, self.config.action_dim)?;
        check_len("log-likelihood output", out.len(), n)?;
        check_finite("actions", actions)?;
        self.act_batch_inner(obs)?;
        let log_det = self.log_det_action_scale();
        let mut a = vec![0.0; self.config.action_dim];
        for (b, o) in out.iter_mut().enumerate() {
            for (j, v) in a.iter_mut().enumerate() {
                *v = actions[(b, j)];
            }
            if let Some(norm) = &self.action_normalizer {
                norm.normalize(&mut a);
            }
            *o = self.out.log_density_and_responsibilities(b, &a, &mut self.resp, &mut self.work)
                - log_det;
        }
        Ok(())
    }
}

impl<E: Expert> Moe<E> {
    fn act_batch_inner(&mut self, obs: MatRef<'_, f32>) -> vdd_core::Result<()> {
        check_shape("observations", obs, obs.nrows(), self.config.state_dim)?;
        check_finite("observations", obs)?;
        self.load_normalized_states(obs);
        let states = std::mem::replace(&mut self.states, Mat::zeros(0, 0));
        let r = self.forward(states.as_ref());
        self.states = states;
        r.map_err(|e| match e {
            MoeError::Core(c) => c,
            other => CoreError::Config(other.to_string()),
        })
    }
}

#[allow(dead_code)]
fn _assert_rng_seedable() -> Rng {
    Rng::seed_from_u64(0)
}
