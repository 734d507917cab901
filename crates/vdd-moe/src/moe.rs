//! The mixture of experts `q(a|s) = Σ_z q(z|s) N(a; μ_z(s), L_z(s) L_z(s)ᵀ)`.

use std::collections::BTreeMap;
use std::path::Path;

use faer::{Mat, MatRef};
use rand::Rng as _;
use serde::{Deserialize, Serialize};
use vdd_core::gaussian::{self, log_sum_exp};
use vdd_core::{
    Affine, CoreError, Expert, Policy, Rng, Seeds, check_act_args, check_finite,
    check_finite_slice, check_len, check_shape,
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
        if !(self.init_std.is_finite() && self.min_std.is_finite()) {
            return Err(CoreError::Config("init_std and min_std must be finite".into()));
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
    ///
    /// # Panics
    /// If `(b, z)` is out of range for the last forward pass (likewise for the other accessors).
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
    ///
    /// An action so far from every expert that all densities underflow gets `−∞` and the
    /// gating `q(z|s_b)` as responsibilities (the limit of Bayes' rule for equal likelihoods).
    ///
    /// # Panics
    /// If `b` is not a state of the last forward pass or the slices have the wrong lengths.
    pub fn log_density_and_responsibilities(
        &self,
        b: usize,
        a: &[f32],
        resp: &mut [f32],
        work: &mut [f32],
    ) -> f32 {
        let z_count = self.num_experts;
        let resp = &mut resp[..z_count];
        for (z, r) in resp.iter_mut().enumerate() {
            *r = self.log_gating[b * z_count + z]
                + gaussian::log_density(a, self.mean(b, z), self.scale(b, z), work);
        }
        let lse = gaussian::softmax_in_place(resp);
        if lse.is_finite() {
            return lse;
        }
        for (r, lg) in resp.iter_mut().zip(self.log_gating_row(b)) {
            *r = lg.exp();
        }
        f32::NEG_INFINITY
    }
}

/// A mixture of Gaussian experts with a gating distribution; a [`Policy`] that acts with one
/// network evaluation and has an exact likelihood.
///
/// The networks see normalised states and emit normalised actions; the optional observation
/// and action normalisers are applied by the [`Policy`] methods and saved with the model. The
/// likelihood is that of the denormalised action (it includes the normaliser's log-Jacobian
/// `−Σ log scale`), so it is the density [`Policy::act`] samples from.
///
/// ```
/// use vdd_core::{Affine, Policy};
/// use vdd_moe::{ActMode, ExpertKind, GatingKind, Moe, MoeConfig};
///
/// // 3-D states, 2-D actions, 4 full-covariance experts with a learned gating.
/// let config = MoeConfig {
///     expert_kind: ExpertKind::Full,
///     gating: GatingKind::Learned,
///     ..MoeConfig::toy(3, 2, 4)
/// };
/// let mut moe = Moe::from_config(config, 0)?;
/// // Data statistics: the networks see (x − offset) / scale.
/// moe.set_normalizers(
///     Some(Affine::new(vec![0.0, 1.0, -1.0], vec![1.0, 2.0, 0.5])?),
///     Some(Affine::new(vec![0.5, 0.0], vec![0.1, 0.2])?),
/// )?;
///
/// // Deterministic evaluation: the most probable expert's mean.
/// moe.set_act_mode(ActMode { greedy_gating: true, sample_action: false });
/// let obs = [0.2f32, 1.5, -0.7];
/// let action = moe.act(&obs)?;
/// assert_eq!(action.len(), 2);
///
/// // Exact log-likelihood of state–action rows (one row per sample).
/// let states = faer::mat![[0.2f32, 1.5, -0.7], [0.0, 0.0, 0.0]];
/// let actions = faer::mat![[0.5f32, 0.1], [0.4, -0.1]];
/// let mut ll = [0.0f32; 2];
/// moe.log_likelihood(states.as_ref(), actions.as_ref(), &mut ll)?;
/// assert!(ll.iter().all(|l| l.is_finite()));
///
/// // One file holds weights, architecture, normalisers and act mode.
/// let dir = std::env::temp_dir().join(format!("vdd-moe-doc-{}", std::process::id()));
/// std::fs::create_dir_all(&dir)?;
/// let path = dir.join("policy.safetensors");
/// moe.save(&path)?;
/// let mut deployed = Moe::load(&path)?;
/// assert_eq!(deployed.act(&obs)?, action);
/// let mut ll2 = [0.0f32; 2];
/// deployed.log_likelihood(states.as_ref(), actions.as_ref(), &mut ll2)?;
/// assert_eq!(ll, ll2);
/// # std::fs::remove_dir_all(&dir)?;
/// # Ok::<(), Box<dyn std::error::Error>>(())
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
    experts_forwarded: bool,
    gating_forwarded: bool,
    states: Mat<f32>,
    grad: Mat<f32>,
    resp: Vec<f32>,
    work: Vec<f32>,
    /// Acting: raw outputs, mean, scale, noise and action of one state.
    act_work: Vec<f32>,
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
            experts_forwarded: false,
            gating_forwarded: false,
            states: Mat::zeros(0, 0),
            grad: Mat::zeros(0, 0),
            resp: vec![0.0; z],
            work: vec![0.0; d],
            act_work: Vec::new(),
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
    /// the networks work in normalised space). Each must have the matching dimension, finite
    /// offsets and positive finite scales; on error nothing changes.
    pub fn set_normalizers(
        &mut self,
        obs: Option<Affine>,
        action: Option<Affine>,
    ) -> Result<(), MoeError> {
        if let Some(o) = &obs {
            check_len("observation normalizer", o.dim(), self.config.state_dim)?;
            // The fields are public: re-check what `Affine::new` guarantees.
            Affine::new(o.offset.clone(), o.scale.clone())?;
        }
        if let Some(a) = &action {
            check_len("action normalizer", a.dim(), self.config.action_dim)?;
            Affine::new(a.offset.clone(), a.scale.clone())?;
        }
        self.obs_normalizer = obs;
        self.action_normalizer = action;
        Ok(())
    }

    /// The observation and action normalisers.
    pub fn normalizers(&self) -> (Option<&Affine>, Option<&Affine>) {
        (self.obs_normalizer.as_ref(), self.action_normalizer.as_ref())
    }

    /// How [`Policy::act`] picks the expert and the action.
    pub fn act_mode(&self) -> ActMode {
        self.act_mode
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
        self.experts_forwarded = true;
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
        self.gating_forwarded = true;
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
        if !self.experts_forwarded {
            return Err(MoeError::NoForward("backward_experts"));
        }
        let (n, z, r) = (self.out.n, self.config.num_experts, self.expert.raw_dim());
        check_len("raw-output gradient", grad_raw.len(), n * z * r)?;
        check_finite_slice("raw-output gradient", grad_raw)?;
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
        if !self.gating_forwarded {
            return Err(MoeError::NoForward("backward_gating"));
        }
        // Rows of the last gating forward (which may differ from the experts' batch).
        let rows = self.out.log_gating.len() / self.config.num_experts;
        check_shape("gating gradient", grad_logits, rows, self.config.num_experts)?;
        check_finite("gating gradient", grad_logits)?;
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
        let (n, z) = (states.nrows(), self.config.num_experts);
        Ok(Mat::from_fn(n, z, |b, e| self.expert.entropy(self.out.scale(b, e))))
    }

    /// Saves weights, configuration, normalisers, act mode and a fingerprint of the expert
    /// family to one `safetensors` file (atomically), so a deployed policy needs nothing else.
    pub fn save(&self, path: &Path) -> Result<(), MoeError> {
        fn json<T: Serialize>(v: &T) -> Result<String, MoeError> {
            serde_json::to_string(v).map_err(|e| MoeError::Config(e.to_string()))
        }
        let mut meta = BTreeMap::new();
        meta.insert("config".to_owned(), json(&self.config)?);
        meta.insert("obs_normalizer".to_owned(), json(&self.obs_normalizer)?);
        meta.insert("action_normalizer".to_owned(), json(&self.action_normalizer)?);
        meta.insert("act_mode".to_owned(), json(&self.act_mode)?);
        meta.insert("expert_family".to_owned(), json(&FamilyFingerprint::of(&self.expert))?);
        vdd_nn::io::save_safetensors(path, self, &meta)?;
        Ok(())
    }

    /// Loads a mixture saved by [`Moe::save`] with a custom expert family. An error
    /// ([`MoeError::FamilyMismatch`]) if `expert` decodes raw outputs differently from the
    /// family the file was saved with (other kind, dimension or scale activation).
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
        let bad = |e: serde_json::Error| MoeError::Config(e.to_string());
        if let Some(saved) = meta.get("expert_family") {
            // Files written before the fingerprint existed load without this check.
            let saved: FamilyFingerprint = serde_json::from_str(saved).map_err(bad)?;
            let given = FamilyFingerprint::of(&expert);
            if !saved.matches(&given) {
                return Err(MoeError::FamilyMismatch(format!(
                    "{} was saved with {saved}, loading with {given} ({:?}); a mixture built \
                     with a custom family loads with `Moe::load_with_family`",
                    path.display(),
                    expert
                )));
            }
        }
        let mut moe = Self::new(config, expert, 0)?;
        vdd_nn::io::load_safetensors(path, &mut moe)?;
        let parse = |key: &str| -> Result<&str, MoeError> {
            meta.get(key)
                .map(String::as_str)
                .ok_or_else(|| MoeError::Config(format!("missing `{key}` metadata")))
        };
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
}

/// What a saved mixture records of its expert family, so that loading it with another family
/// is an error rather than silently different means and scales: the dimensions and the decoded
/// `(μ, L)` of a few fixed raw vectors (which pins down the kind and the scale activation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct FamilyFingerprint {
    action_dim: usize,
    raw_dim: usize,
    is_diagonal: bool,
    /// Per probe: `μ` (`d`) followed by `L` (`d·d`, row-major).
    probes: Vec<Vec<f32>>,
}

impl FamilyFingerprint {
    const PROBES: usize = 3;

    fn of<E: Expert>(expert: &E) -> Self {
        let (d, r) = (expert.action_dim(), expert.raw_dim());
        let probes = (0..Self::PROBES)
            .map(|k| {
                // Probe 0 is the all-zero raw vector (the initial scale); the others spread over
                // [−1, 1] so that means, diagonal and off-diagonal scale entries all differ.
                let raw: Vec<f32> = (0..r)
                    .map(|i| if k == 0 { 0.0 } else { ((i * 7 + k * 5) % 11) as f32 / 5.0 - 1.0 })
                    .collect();
                let mut decoded = vec![0.0; d + d * d];
                let (mean, scale) = decoded.split_at_mut(d);
                expert.decode(&raw, mean, scale);
                decoded
            })
            .collect();
        Self { action_dim: d, raw_dim: r, is_diagonal: expert.is_diagonal(), probes }
    }

    fn matches(&self, other: &Self) -> bool {
        self.action_dim == other.action_dim
            && self.raw_dim == other.raw_dim
            && self.is_diagonal == other.is_diagonal
            && self.probes.len() == other.probes.len()
            && self.probes.iter().zip(&other.probes).all(|(a, b)| {
                a.len() == b.len()
                    && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= 1e-5 * (1.0 + x.abs()))
            })
    }
}

impl std::fmt::Display for FamilyFingerprint {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let kind = if self.is_diagonal { "a diagonal" } else { "a non-diagonal" };
        let d = self.action_dim;
        let std0: Vec<f32> =
            self.probes.first().map_or(Vec::new(), |p| (0..d).map(|i| p[d + i * d + i]).collect());
        write!(f, "{kind} family (action_dim {d}, raw_dim {}, initial stds {std0:?})", self.raw_dim)
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
        let d = action.len();
        self.act_rows(o, faer::MatMut::from_row_major_slice_mut(action, 1, d))
    }

    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        actions: faer::MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        check_shape("actions", actions.as_ref(), obs.nrows(), self.config.action_dim)?;
        self.act_rows(obs, actions)
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
        self.forward_observations(obs)?;
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
    /// Acting (`Policy::act_into` and `act_batch`): the gating for every state, then for each
    /// state in turn an expert `z ~ q(z|s)` (or the most likely one) and only that expert's
    /// outputs: its columns of the shared trunk's output layer (or its own network), decoded
    /// into `(μ_z, L_z)`. The action is `μ_z`, or a sample of `N(μ_z, L_z L_zᵀ)`.
    fn act_rows(
        &mut self,
        obs: MatRef<'_, f32>,
        actions: faer::MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        self.on_observations(obs, |moe, states| moe.act_on_states(states, actions))
    }

    /// Checks and normalises observations, then runs `f` on the normalised states.
    fn on_observations<T>(
        &mut self,
        obs: MatRef<'_, f32>,
        f: impl FnOnce(&mut Self, MatRef<'_, f32>) -> vdd_core::Result<T>,
    ) -> vdd_core::Result<T> {
        check_shape("observations", obs, obs.nrows(), self.config.state_dim)?;
        check_finite("observations", obs)?;
        self.load_normalized_states(obs);
        let states = std::mem::replace(&mut self.states, Mat::zeros(0, 0));
        let r = f(self, states.as_ref());
        self.states = states;
        r
    }

    fn act_on_states(
        &mut self,
        states: MatRef<'_, f32>,
        mut actions: faer::MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        self.forward_gating(states).map_err(to_core)?;
        // The experts' caches no longer match `output()`: a backward pass needs a forward.
        self.experts_forwarded = false;
        let (z, r, d) = (self.config.num_experts, self.expert.raw_dim(), self.config.action_dim);
        let h = self.config.experts_network.hidden_dim;
        let Self { experts, expert, rng, out, act_work, act_mode, action_normalizer, .. } = self;
        act_work.resize(r + 3 * d + d * d + h, 0.0);
        let (raw, rest) = act_work.split_at_mut(r);
        let (hidden_row, rest) = rest.split_at_mut(h);
        let (mean, rest) = rest.split_at_mut(d);
        let (scale, rest) = rest.split_at_mut(d * d);
        let (noise, action) = rest.split_at_mut(d);
        /// Where the chosen expert's raw outputs come from.
        enum Source<'a> {
            /// The shared trunk's last hidden features and its output layer.
            Trunk(MatRef<'a, f32>, &'a vdd_nn::Linear),
            /// One network per expert.
            Nets(&'a mut [ResidualMlp]),
        }
        let mut source = match &mut experts.0 {
            ExpertNets::Shared(net) => {
                let (hidden, layer) = net.forward_hidden(states);
                Source::Trunk(hidden, layer)
            }
            ExpertNets::Separate(nets) => Source::Nets(nets),
        };
        for b in 0..states.nrows() {
            let lg = &out.log_gating[b * z..(b + 1) * z];
            let e = if act_mode.greedy_gating {
                (0..z).fold(0, |best, k| if lg[k] > lg[best] { k } else { best })
            } else {
                let u: f32 = rng.random();
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
            match &mut source {
                // The kernel the output layer's full forward pass uses on this many rows (a
                // row kernel for one, a matrix product for more), so the same bits.
                Source::Trunk(hidden, layer) if hidden.nrows() == 1 => {
                    for (j, v) in hidden_row.iter_mut().enumerate() {
                        *v = hidden[(0, j)];
                    }
                    layer.forward_row_cols(hidden_row, e * r..(e + 1) * r, raw);
                }
                Source::Trunk(hidden, layer) => {
                    raw.copy_from_slice(&layer.bias.value[e * r..(e + 1) * r]);
                    faer::linalg::matmul::matmul(
                        faer::MatMut::from_row_major_slice_mut(raw, 1, r),
                        faer::Accum::Add,
                        hidden.subrows(b, 1),
                        layer.weight_t().subcols(e * r, r),
                        1.0,
                        faer::Par::Seq,
                    );
                }
                Source::Nets(nets) => {
                    let y = nets[e].forward(states.subrows(b, 1));
                    for (c, v) in raw.iter_mut().enumerate() {
                        *v = y[(0, c)];
                    }
                }
            }
            expert.decode(raw, mean, scale);
            if act_mode.sample_action {
                vdd_core::fill_standard_normal(rng, noise);
                gaussian::sample_into(mean, scale, noise, action);
            } else {
                action.copy_from_slice(mean);
            }
            if let Some(norm) = action_normalizer.as_ref() {
                norm.denormalize(action);
            }
            for (j, &a) in action.iter().enumerate() {
                actions[(b, j)] = a;
            }
        }
        Ok(())
    }

    /// Both forward passes on observations (normalised here): for the likelihood.
    fn forward_observations(&mut self, obs: MatRef<'_, f32>) -> vdd_core::Result<()> {
        self.on_observations(obs, |moe, states| moe.forward(states).map_err(to_core))
    }
}

/// A mixture error as the [`Policy`] trait's error.
fn to_core(e: MoeError) -> CoreError {
    match e {
        MoeError::Core(c) => c,
        other => CoreError::Config(other.to_string()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::experts::{DiagonalExpert, FullExpert};

    // ---------------------------------------------------------------------------------------
    // Fixtures and independent f64 references.
    // ---------------------------------------------------------------------------------------

    const OUT_LAYER: &str = "layers.2"; // input layer, one residual block, output layer

    fn small_net() -> NetworkConfig {
        NetworkConfig { hidden_dim: 8, num_blocks: 1, activation: Activation::Mish }
    }

    fn config(
        state_dim: usize,
        action_dim: usize,
        kind: ExpertKind,
        gating: GatingKind,
        shared: bool,
    ) -> MoeConfig {
        MoeConfig {
            expert_kind: kind,
            experts_network: small_net(),
            shared_trunk: shared,
            gating,
            gating_network: small_net(),
            ..MoeConfig::toy(state_dim, action_dim, 3)
        }
    }

    /// Every combination of family, trunk and gating.
    fn all_configs(state_dim: usize, action_dim: usize) -> Vec<MoeConfig> {
        let mut v = Vec::new();
        for kind in [ExpertKind::Diagonal, ExpertKind::Full] {
            for shared in [true, false] {
                for gating in [GatingKind::Learned, GatingKind::Uniform] {
                    v.push(config(state_dim, action_dim, kind, gating, shared));
                }
            }
        }
        v
    }

    /// Calls `f(z, c, &mut bias)` for every output bias of the experts' networks, where `z` is
    /// the expert and `c` the index into its raw outputs (shared trunk or separate networks).
    fn edit_expert_bias(moe: &mut Moe, mut f: impl FnMut(usize, usize, &mut f32)) {
        let r = moe.expert().raw_dim();
        moe.expert_networks_mut().visit_params_mut("", &mut |name, p| {
            if name == format!("{OUT_LAYER}.bias") {
                for (k, b) in p.value.iter_mut().enumerate() {
                    f(k / r, k % r, b);
                }
            } else if let Some(z) = name.strip_suffix(&format!(".{OUT_LAYER}.bias")) {
                let z: usize = z.parse().unwrap();
                for (c, b) in p.value.iter_mut().enumerate() {
                    f(z, c, b);
                }
            }
        });
    }

    /// Moves the experts apart, varies their scales and correlations, and makes the gating
    /// clearly non-uniform, so that mistakes in weighting or indexing cannot hide.
    fn spread(moe: &mut Moe) {
        let d = moe.config().action_dim;
        let zc = moe.num_experts() as f32;
        edit_expert_bias(moe, |z, c, b| {
            if c < d {
                let sign = if c % 2 == 0 { 1.0 } else { -0.6 };
                *b += 1.5 * sign * (z as f32 - 0.5 * (zc - 1.0));
            } else {
                *b += 0.5 * ((z * 3 + c) as f32).sin();
            }
        });
        if let Some(g) = moe.gating_network_mut() {
            g.output_layer_mut().bias.value =
                (0..g.out_dim()).map(|z| [0.9, 0.0, -0.8, 0.3][z % 4]).collect();
        }
    }

    fn normalizers(state_dim: usize, action_dim: usize) -> (Affine, Affine) {
        let obs = Affine::new(
            (0..state_dim).map(|i| 0.3 * i as f32 - 0.2).collect(),
            (0..state_dim).map(|i| 1.5 + 0.5 * i as f32).collect(),
        )
        .unwrap();
        let act = Affine::new(
            (0..action_dim).map(|i| 1.0 - 1.5 * i as f32).collect(),
            (0..action_dim).map(|i| [3.0, 0.5, 2.0][i % 3]).collect(),
        )
        .unwrap();
        (obs, act)
    }

    fn built(cfg: MoeConfig, seed: u64) -> Moe {
        let (sd, ad) = (cfg.state_dim, cfg.action_dim);
        let mut moe = Moe::from_config(cfg, seed).unwrap();
        spread(&mut moe);
        let (o, a) = normalizers(sd, ad);
        moe.set_normalizers(Some(o), Some(a)).unwrap();
        moe
    }

    fn obs_batch(n: usize, state_dim: usize) -> Mat<f32> {
        Mat::from_fn(n, state_dim, |i, j| ((i * 5 + j * 3) % 7) as f32 * 0.4 - 1.1)
    }

    fn normalized(m: MatRef<'_, f32>, norm: &Affine) -> Mat<f32> {
        Mat::from_fn(m.nrows(), m.ncols(), |i, j| (m[(i, j)] - norm.offset[j]) / norm.scale[j])
    }

    /// `Σ = L Lᵀ` in f64.
    fn covariance(l: &[f32], d: usize) -> Vec<f64> {
        let mut s = vec![0.0; d * d];
        for i in 0..d {
            for j in 0..d {
                s[i * d + j] =
                    (0..d).map(|k| f64::from(l[i * d + k]) * f64::from(l[j * d + k])).sum();
            }
        }
        s
    }

    /// Inverse and log-determinant by Gauss–Jordan elimination with partial pivoting.
    fn inverse_and_log_det(m: &[f64], d: usize) -> (Vec<f64>, f64) {
        let mut a = m.to_vec();
        let mut inv: Vec<f64> =
            (0..d * d).map(|k| if k / d == k % d { 1.0 } else { 0.0 }).collect();
        let mut log_det = 0.0;
        for c in 0..d {
            let p =
                (c..d).max_by(|&x, &y| a[x * d + c].abs().total_cmp(&a[y * d + c].abs())).unwrap();
            if p != c {
                for k in 0..d {
                    a.swap(p * d + k, c * d + k);
                    inv.swap(p * d + k, c * d + k);
                }
            }
            let piv = a[c * d + c];
            assert!(piv != 0.0, "singular covariance");
            log_det += piv.abs().ln();
            for k in 0..d {
                a[c * d + k] /= piv;
                inv[c * d + k] /= piv;
            }
            for r in 0..d {
                if r != c {
                    let f = a[r * d + c];
                    for k in 0..d {
                        a[r * d + k] -= f * a[c * d + k];
                        inv[r * d + k] -= f * inv[c * d + k];
                    }
                }
            }
        }
        (inv, log_det)
    }

    fn ref_log_normal(x: &[f64], mean: &[f32], l: &[f32]) -> f64 {
        let d = x.len();
        let (inv, log_det) = inverse_and_log_det(&covariance(l, d), d);
        let diff: Vec<f64> = (0..d).map(|i| x[i] - f64::from(mean[i])).collect();
        let mut maha = 0.0;
        for i in 0..d {
            for j in 0..d {
                maha += diff[i] * inv[i * d + j] * diff[j];
            }
        }
        -0.5 * maha - 0.5 * log_det - 0.5 * d as f64 * (2.0 * std::f64::consts::PI).ln()
    }

    fn ref_log_sum_exp(xs: &[f64]) -> f64 {
        let m = xs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        m + xs.iter().map(|x| (x - m).exp()).sum::<f64>().ln()
    }

    /// `log q(z|s)` recomputed from the gating network's logits (or `log 1/Z`).
    fn ref_log_gating(moe: &mut Moe, states: MatRef<'_, f32>) -> Vec<Vec<f64>> {
        let z = moe.num_experts();
        match moe.gating_network_mut() {
            None => vec![vec![(1.0 / z as f64).ln(); z]; states.nrows()],
            Some(net) => {
                let y = net.forward(states);
                (0..states.nrows())
                    .map(|b| {
                        let logits: Vec<f64> = (0..z).map(|k| f64::from(y[(b, k)])).collect();
                        let lse = ref_log_sum_exp(&logits);
                        logits.iter().map(|l| l - lse).collect()
                    })
                    .collect()
            }
        }
    }

    fn assert_close(got: f64, want: f64, tol: f64, what: &str) {
        assert!((got - want).abs() <= tol, "{what}: got {got}, want {want} (tol {tol})");
    }

    // ---------------------------------------------------------------------------------------
    // Architecture.
    // ---------------------------------------------------------------------------------------

    #[test]
    fn shared_trunk_and_separate_networks_have_the_configured_shapes_and_layout() {
        for kind in [ExpertKind::Diagonal, ExpertKind::Full] {
            for shared in [true, false] {
                let cfg = config(2, 3, kind, GatingKind::Learned, shared);
                let mut moe = Moe::from_config(cfg, 1).unwrap();
                let (z, d, r) = (3, 3, moe.expert().raw_dim());
                assert_eq!(r, if kind == ExpertKind::Full { 9 } else { 6 });

                let mut shapes = BTreeMap::new();
                moe.visit_params("", &mut |name, p| {
                    shapes.insert(name.to_owned(), p.shape.clone());
                });
                if shared {
                    assert_eq!(shapes[&format!("experts.{OUT_LAYER}.weight")], [z * r, 8]);
                    assert!(!shapes.contains_key(&format!("experts.0.{OUT_LAYER}.weight")));
                } else {
                    for e in 0..z {
                        assert_eq!(shapes[&format!("experts.{e}.{OUT_LAYER}.weight")], [r, 8]);
                        assert_eq!(shapes[&format!("experts.{e}.layers.0.weight")], [8, 2]);
                    }
                    assert!(!shapes.contains_key(&format!("experts.{OUT_LAYER}.weight")));
                }
                assert_eq!(shapes[&format!("gating.{OUT_LAYER}.weight")], [z, 8]);

                // With zero output weights the raw outputs are the biases: each (state, expert)
                // row must hold its own expert's biases, decoded by the family.
                moe.expert_networks_mut().visit_params_mut("", &mut |name, p| {
                    if name.ends_with(&format!("{OUT_LAYER}.weight")) {
                        p.value.fill(0.0);
                    }
                });
                edit_expert_bias(&mut moe, |e, c, b| *b = 0.1 * c as f32 - 0.5 * e as f32);
                let n = 4;
                moe.forward(obs_batch(n, 2).as_ref()).unwrap();
                let out = moe.output().clone();
                assert_eq!((out.n, out.num_experts, out.action_dim), (n, z, d));
                assert_eq!(out.raw.len(), n * z * r);
                assert_eq!(out.means.len(), n * z * d);
                assert_eq!(out.scales.len(), n * z * d * d);
                assert_eq!(out.log_gating.len(), n * z);
                let (mut mean, mut scale) = (vec![0.0; d], vec![0.0; d * d]);
                for b in 0..n {
                    for e in 0..z {
                        let raw = &out.raw[(b * z + e) * r..(b * z + e + 1) * r];
                        for (c, v) in raw.iter().enumerate() {
                            assert_eq!(*v, 0.1 * c as f32 - 0.5 * e as f32, "{kind:?} {shared}");
                        }
                        moe.expert().decode(raw, &mut mean, &mut scale);
                        assert_eq!(out.mean(b, e), mean);
                        assert_eq!(out.scale(b, e), scale);
                    }
                }
            }
        }
    }

    #[test]
    fn separate_networks_are_independent_and_seeds_reproduce_initialisation() {
        let cfg = config(2, 2, ExpertKind::Diagonal, GatingKind::Learned, false);
        let params = |moe: &Moe| {
            let mut v = Vec::new();
            moe.visit_params("", &mut |n, p| v.push((n.to_owned(), p.value.clone())));
            v
        };
        let a = Moe::from_config(cfg.clone(), 3).unwrap();
        let b = Moe::from_config(cfg.clone(), 3).unwrap();
        let c = Moe::from_config(cfg, 4).unwrap();
        assert_eq!(params(&a), params(&b));
        assert_ne!(params(&a), params(&c));
        let pa = params(&a);
        let w = |e: usize| pa.iter().find(|(n, _)| *n == format!("experts.{e}.layers.0.weight"));
        assert_ne!(w(0).unwrap().1, w(1).unwrap().1, "separate experts share weights");
    }

    // ---------------------------------------------------------------------------------------
    // Likelihood, responsibilities, gating, entropies.
    // ---------------------------------------------------------------------------------------

    #[test]
    fn log_likelihood_is_an_independent_log_sum_exp_over_the_experts() {
        for cfg in all_configs(2, 3) {
            let what =
                format!("{:?}/{:?}/shared={}", cfg.expert_kind, cfg.gating, cfg.shared_trunk);
            let mut moe = built(cfg, 2);
            let (obs_norm, act_norm) = normalizers(2, 3);
            let n = 6;
            let obs = obs_batch(n, 2);
            let actions = Mat::from_fn(n, 3, |i, j| ((i * 3 + j * 5) % 9) as f32 * 0.7 - 2.0);
            let mut ll = vec![0.0; n];
            moe.log_likelihood(obs.as_ref(), actions.as_ref(), &mut ll).unwrap();

            let states = normalized(obs.as_ref(), &obs_norm);
            moe.forward(states.as_ref()).unwrap();
            let out = moe.output().clone();
            let log_gating = ref_log_gating(&mut moe, states.as_ref());
            let log_det: f64 = act_norm.scale.iter().map(|s| f64::from(*s).ln()).sum();
            let norm_actions = normalized(actions.as_ref(), &act_norm);
            let mut resp = Mat::<f32>::zeros(n, 3);
            moe.responsibilities(states.as_ref(), norm_actions.as_ref(), resp.as_mut()).unwrap();
            for b in 0..n {
                let x: Vec<f64> = (0..3)
                    .map(|j| {
                        (f64::from(actions[(b, j)]) - f64::from(act_norm.offset[j]))
                            / f64::from(act_norm.scale[j])
                    })
                    .collect();
                let joint: Vec<f64> = (0..3)
                    .map(|z| log_gating[b][z] + ref_log_normal(&x, out.mean(b, z), out.scale(b, z)))
                    .collect();
                let lse = ref_log_sum_exp(&joint);
                assert_close(f64::from(ll[b]), lse - log_det, 1e-4 * (1.0 + lse.abs()), &what);
                // Bayes' rule, and a probability vector.
                let mut sum = 0.0;
                for z in 0..3 {
                    let want = (joint[z] - lse).exp();
                    assert_close(f64::from(resp[(b, z)]), want, 1e-5, &what);
                    sum += f64::from(resp[(b, z)]);
                }
                assert_close(sum, 1.0, 1e-5, &what);
            }
        }
    }

    #[test]
    fn gating_is_a_softmax_of_the_network_or_exactly_uniform() {
        for gating in [GatingKind::Learned, GatingKind::Uniform] {
            let mut moe = built(config(2, 2, ExpertKind::Diagonal, gating, true), 5);
            let states = obs_batch(5, 2);
            moe.forward_gating(states.as_ref()).unwrap();
            let got = moe.output().log_gating.clone();
            let want = ref_log_gating(&mut moe, states.as_ref());
            for b in 0..5 {
                let row = &got[b * 3..(b + 1) * 3];
                let total: f64 = row.iter().map(|l| f64::from(*l).exp()).sum();
                assert_close(total, 1.0, 1e-5, "gating sums to one");
                for z in 0..3 {
                    assert_close(f64::from(row[z]), want[b][z], 1e-5, "log q(z|s)");
                }
                if gating == GatingKind::Uniform {
                    assert!(row.iter().all(|l| *l == -(3.0f32).ln()));
                } else {
                    assert!((row[0] - row[2]).abs() > 0.5, "learned gating is not uniform here");
                }
            }
            assert_eq!(moe.has_learned_gating(), gating == GatingKind::Learned);
            let mut gating_params = 0;
            moe.visit_params("", &mut |n, _| gating_params += usize::from(n.starts_with("gating")));
            assert_eq!(gating_params > 0, gating == GatingKind::Learned);
        }
    }

    #[test]
    fn expert_entropies_are_the_closed_form_gaussian_entropies() {
        for kind in [ExpertKind::Diagonal, ExpertKind::Full] {
            let mut moe = built(config(2, 3, kind, GatingKind::Learned, true), 6);
            let states = obs_batch(4, 2);
            let h = moe.expert_entropies(states.as_ref()).unwrap();
            assert_eq!((h.nrows(), h.ncols()), (4, 3));
            let out = moe.output();
            for b in 0..4 {
                for z in 0..3 {
                    let (_, log_det) = inverse_and_log_det(&covariance(out.scale(b, z), 3), 3);
                    let want = 0.5
                        * (3.0 * (2.0 * std::f64::consts::PI * std::f64::consts::E).ln() + log_det);
                    assert_close(f64::from(h[(b, z)]), want, 1e-4, "entropy");
                }
            }
            // The experts differ, so the entropies must too (catches a constant result).
            assert!((h[(0, 0)] - h[(0, 1)]).abs() > 1e-3);
        }
    }

    #[test]
    fn an_action_beyond_every_expert_has_minus_infinite_likelihood_not_nan() {
        let mut moe = built(config(2, 2, ExpertKind::Full, GatingKind::Learned, true), 7);
        let obs = obs_batch(1, 2);
        let far = faer::mat![[1e30f32, -1e30]];
        let mut ll = [0.0];
        moe.log_likelihood(obs.as_ref(), far.as_ref(), &mut ll).unwrap();
        assert_eq!(ll[0], f32::NEG_INFINITY);
        let states = normalized(obs.as_ref(), &normalizers(2, 2).0);
        let mut resp = Mat::<f32>::zeros(1, 3);
        moe.responsibilities(states.as_ref(), far.as_ref(), resp.as_mut()).unwrap();
        let prior = moe.output().log_gating_row(0).to_vec();
        for z in 0..3 {
            assert_close(f64::from(resp[(0, z)]), f64::from(prior[z]).exp(), 1e-6, "fallback");
        }
    }

    // ---------------------------------------------------------------------------------------
    // Acting.
    // ---------------------------------------------------------------------------------------

    /// Mean and covariance of the (denormalised) mixture at state 0 of the last forward.
    fn mixture_moments(moe: &Moe, act_norm: &Affine, only: Option<usize>) -> (Vec<f64>, Vec<f64>) {
        let out = moe.output();
        let d = out.action_dim;
        let (mut mean, mut second) = (vec![0.0; d], vec![0.0; d * d]);
        for z in 0..out.num_experts {
            let q = match only {
                Some(k) => f64::from(u8::from(k == z)),
                None => f64::from(out.log_gating_row(0)[z]).exp(),
            };
            let s = |i: usize| f64::from(act_norm.scale[i]);
            let mu: Vec<f64> = (0..d)
                .map(|i| f64::from(act_norm.offset[i]) + s(i) * f64::from(out.mean(0, z)[i]))
                .collect();
            let cov = covariance(out.scale(0, z), d);
            for i in 0..d {
                mean[i] += q * mu[i];
                for j in 0..d {
                    second[i * d + j] += q * (s(i) * s(j) * cov[i * d + j] + mu[i] * mu[j]);
                }
            }
        }
        for i in 0..d {
            for j in 0..d {
                second[i * d + j] -= mean[i] * mean[j];
            }
        }
        (mean, second)
    }

    fn sample_moments(a: MatRef<'_, f32>) -> (Vec<f64>, Vec<f64>) {
        let (n, d) = (a.nrows(), a.ncols());
        let mean: Vec<f64> =
            (0..d).map(|j| (0..n).map(|i| f64::from(a[(i, j)])).sum::<f64>() / n as f64).collect();
        let mut cov = vec![0.0; d * d];
        for i in 0..n {
            for p in 0..d {
                for q in 0..d {
                    cov[p * d + q] += (f64::from(a[(i, p)]) - mean[p])
                        * (f64::from(a[(i, q)]) - mean[q])
                        / (n - 1) as f64;
                }
            }
        }
        (mean, cov)
    }

    /// The density `log_likelihood` reports (normalisers and their Jacobian included) is the one
    /// `act` samples from: it integrates to one, and its moments, the closed-form mixture
    /// moments and the moments of sampled actions agree.
    #[test]
    fn likelihood_and_sampling_describe_the_same_distribution() {
        // ReLU networks: cheaper on many rows, and smoothness does not matter here.
        let relu = NetworkConfig { activation: Activation::Relu, ..small_net() };
        let cfg = MoeConfig {
            experts_network: relu.clone(),
            gating_network: relu,
            ..config(1, 2, ExpertKind::Full, GatingKind::Learned, true)
        };
        let mut moe = built(cfg, 8);
        let act_norm = normalizers(1, 2).1;
        let obs = [0.9f32];
        let mut ll0 = [0.0];
        moe.log_likelihood(
            faer::mat![[0.9f32]].as_ref(),
            faer::mat![[0.0f32, 0.0]].as_ref(),
            &mut ll0,
        )
        .unwrap();
        let (mean, cov) = mixture_moments(&moe, &act_norm, None);
        let sd = |i: usize| cov[i * 2 + i].sqrt();
        assert!(cov[1].abs() > 0.05 * sd(0) * sd(1), "test needs correlated actions");

        // Midpoint quadrature of exp(log q) over a box holding every expert.
        let out = moe.output().clone();
        let (mut lo, mut hi) = ([f64::INFINITY; 2], [f64::NEG_INFINITY; 2]);
        for z in 0..3 {
            let c = covariance(out.scale(0, z), 2);
            for i in 0..2 {
                let s = f64::from(act_norm.scale[i]);
                let mu = f64::from(act_norm.offset[i]) + s * f64::from(out.mean(0, z)[i]);
                lo[i] = lo[i].min(mu - 8.0 * s * c[i * 2 + i].sqrt());
                hi[i] = hi[i].max(mu + 8.0 * s * c[i * 2 + i].sqrt());
            }
        }
        let g = 128;
        let step = [(hi[0] - lo[0]) / g as f64, (hi[1] - lo[1]) / g as f64];
        let grid = Mat::from_fn(g * g, 2, |k, j| {
            let idx = if j == 0 { k / g } else { k % g };
            (lo[j] + (idx as f64 + 0.5) * step[j]) as f32
        });
        let states = Mat::from_fn(g * g, 1, |_, _| obs[0]);
        let mut ll = vec![0.0; g * g];
        moe.log_likelihood(states.as_ref(), grid.as_ref(), &mut ll).unwrap();
        let (mut mass, mut qm, mut qs) = (0.0, [0.0; 2], [0.0; 4]);
        for k in 0..g * g {
            let w = f64::from(ll[k]).exp() * step[0] * step[1];
            let x = [f64::from(grid[(k, 0)]), f64::from(grid[(k, 1)])];
            mass += w;
            for i in 0..2 {
                qm[i] += w * x[i];
                for j in 0..2 {
                    qs[i * 2 + j] += w * x[i] * x[j];
                }
            }
        }
        assert_close(mass, 1.0, 2e-3, "∫ q(a|s) da");
        for i in 0..2 {
            assert_close(qm[i], mean[i], 2e-3 * sd(i), "quadrature mean");
            for j in 0..2 {
                let c = qs[i * 2 + j] - qm[i] * qm[j];
                assert_close(c, cov[i * 2 + j], 5e-3 * sd(i) * sd(j), "quadrature covariance");
            }
        }

        // Sampled gating and sampled actions.
        let n = 16_000;
        let repeated = Mat::from_fn(n, 1, |_, _| obs[0]);
        let mut actions = Mat::<f32>::zeros(n, 2);
        moe.set_act_mode(ActMode { greedy_gating: false, sample_action: true });
        moe.seed(11);
        moe.act_batch(repeated.as_ref(), actions.as_mut()).unwrap();
        let (sm, sc) = sample_moments(actions.as_ref());
        for i in 0..2 {
            assert_close(sm[i], mean[i], 4.0 * sd(i) / (n as f64).sqrt(), "sample mean");
            for j in 0..2 {
                assert_close(sc[i * 2 + j], cov[i * 2 + j], 0.05 * sd(i) * sd(j), "sample cov");
            }
        }

        // Greedy gating with sampled actions: the most probable expert's Gaussian only.
        let lg = moe.output().log_gating_row(0).to_vec();
        let best = (0..3).max_by(|&a, &b| lg[a].total_cmp(&lg[b])).unwrap();
        let (bm, bc) = mixture_moments(&moe, &act_norm, Some(best));
        moe.set_act_mode(ActMode { greedy_gating: true, sample_action: true });
        moe.act_batch(repeated.as_ref(), actions.as_mut()).unwrap();
        let (sm, sc) = sample_moments(actions.as_ref());
        for i in 0..2 {
            let sdi = bc[i * 2 + i].sqrt();
            assert_close(sm[i], bm[i], 4.0 * sdi / (n as f64).sqrt(), "greedy sample mean");
            for j in 0..2 {
                let sdj = bc[j * 2 + j].sqrt();
                assert_close(sc[i * 2 + j], bc[i * 2 + j], 0.05 * sdi * sdj, "greedy sample cov");
            }
        }
    }

    /// Equal up to `f32` rounding of differently ordered sums.
    fn assert_all_close(a: &[f32], b: &[f32]) {
        assert_eq!(a.len(), b.len());
        for (x, y) in a.iter().zip(b) {
            assert!((x - y).abs() <= 1e-5 * (1.0 + y.abs()), "{a:?} vs {b:?}");
        }
    }

    /// The denormalised mean of every expert at state `b` of the last forward.
    fn denormalized_means(moe: &Moe, b: usize) -> Vec<Vec<f32>> {
        let act_norm = moe.normalizers().1.unwrap().clone();
        (0..moe.num_experts())
            .map(|z| {
                let mut m = moe.output().mean(b, z).to_vec();
                act_norm.denormalize(&mut m);
                m
            })
            .collect()
    }

    #[test]
    fn greedy_mean_mode_returns_the_most_probable_experts_mean() {
        for cfg in all_configs(2, 2).into_iter().filter(|c| c.gating == GatingKind::Learned) {
            let mut moe = built(cfg, 9);
            moe.set_act_mode(ActMode { greedy_gating: true, sample_action: false });
            let obs = obs_batch(5, 2);
            let mut batch = Mat::<f32>::zeros(5, 2);
            moe.act_batch(obs.as_ref(), batch.as_mut()).unwrap();
            // Acting computes only the chosen expert: the full forward pass for comparison.
            moe.forward_observations(obs.as_ref()).unwrap();
            let mut picked = Vec::new();
            for b in 0..5 {
                let lg = moe.output().log_gating_row(b).to_vec();
                let best = (0..3).max_by(|&x, &y| lg[x].total_cmp(&lg[y])).unwrap();
                picked.push(best);
                // Separate experts' networks act on one state at a time (a row kernel).
                let want = &denormalized_means(&moe, b)[best];
                assert_all_close(&[batch[(b, 0)], batch[(b, 1)]], want);
            }
            // One state at a time: the one-row forward pass's bits (a row kernel, not the
            // batch's matrix product, so the batch's actions up to rounding).
            for b in 0..5 {
                let state = [obs[(b, 0)], obs[(b, 1)]];
                let a = moe.act(&state).unwrap();
                moe.forward_observations(MatRef::from_row_major_slice(&state, 1, 2)).unwrap();
                assert_eq!(a, denormalized_means(&moe, 0)[picked[b]], "state {b}");
                assert_all_close(&a, &[batch[(b, 0)], batch[(b, 1)]]);
            }
            assert_eq!(picked[0], 0, "the spread gating favours expert 0");
            // Acting leaves no experts' forward pass to back-propagate through.
            moe.act(&[obs[(0, 0)], obs[(0, 1)]]).unwrap();
            let grad = vec![0.0; moe.num_experts() * moe.expert().raw_dim()];
            assert!(matches!(moe.backward_experts(&grad), Err(MoeError::NoForward(_))));
        }
    }

    #[test]
    fn sampled_gating_picks_experts_with_the_gating_probabilities() {
        let mut moe = built(config(2, 2, ExpertKind::Diagonal, GatingKind::Learned, true), 10);
        moe.set_act_mode(ActMode { greedy_gating: false, sample_action: false });
        moe.seed(3);
        let n = 20_000;
        let obs = Mat::from_fn(n, 2, |_, j| [0.4f32, -0.3][j]);
        let mut actions = Mat::<f32>::zeros(n, 2);
        moe.act_batch(obs.as_ref(), actions.as_mut()).unwrap();
        moe.forward_observations(obs.subrows(0, 1)).unwrap();
        let means = denormalized_means(&moe, 0);
        let mut counts = [0usize; 3];
        for b in 0..n {
            let a = [actions[(b, 0)], actions[(b, 1)]];
            let z = means
                .iter()
                .position(|m| m.iter().zip(&a).all(|(x, y)| (x - y).abs() < 1e-5))
                .expect("an action is an expert's mean");
            counts[z] += 1;
        }
        let q: Vec<f64> =
            moe.output().log_gating_row(0).iter().map(|l| f64::from(*l).exp()).collect();
        assert!(q.iter().all(|p| *p > 0.05) && (q[0] - q[2]).abs() > 0.2, "{q:?}");
        for z in 0..3 {
            let freq = counts[z] as f64 / n as f64;
            let se = (q[z] * (1.0 - q[z]) / n as f64).sqrt();
            assert_close(freq, q[z], 4.0 * se, "gating frequency");
        }
    }

    #[test]
    fn the_same_seed_gives_the_same_actions_and_seed_resets_the_stream() {
        for mode in [
            ActMode { greedy_gating: false, sample_action: true },
            ActMode { greedy_gating: false, sample_action: false },
            ActMode { greedy_gating: true, sample_action: true },
        ] {
            let mut moe = built(config(2, 2, ExpertKind::Full, GatingKind::Learned, true), 12);
            moe.set_act_mode(mode);
            let run = |moe: &mut Moe| -> Vec<Vec<f32>> {
                (0..40).map(|k| moe.act(&[0.1 * k as f32, -0.2]).unwrap()).collect()
            };
            moe.seed(5);
            let a = run(&mut moe);
            let continued = run(&mut moe);
            moe.seed(5);
            let b = run(&mut moe);
            moe.seed(6);
            let c = run(&mut moe);
            assert_eq!(a, b, "{mode:?}: seed() resets the stream");
            assert_ne!(a, continued, "{mode:?}: the stream advances");
            assert_ne!(a, c, "{mode:?}: another seed, other actions");

            // A clone with the same seed (and a freshly built copy) acts identically.
            let mut twin = built(config(2, 2, ExpertKind::Full, GatingKind::Learned, true), 12);
            twin.set_act_mode(mode);
            twin.seed(5);
            assert_eq!(run(&mut twin), a, "{mode:?}: same weights and seed");
        }
    }

    #[test]
    fn act_batch_matches_repeated_act_into_in_deterministic_mode() {
        for cfg in all_configs(3, 2) {
            let mut moe = built(cfg, 13);
            moe.set_act_mode(ActMode { greedy_gating: true, sample_action: false });
            let obs = obs_batch(7, 3);
            let mut batch = Mat::<f32>::zeros(7, 2);
            moe.act_batch(obs.as_ref(), batch.as_mut()).unwrap();
            let mut one = [0.0f32; 2];
            for b in 0..7 {
                moe.act_into(&[obs[(b, 0)], obs[(b, 1)], obs[(b, 2)]], &mut one).unwrap();
                // One row runs a row kernel, a batch a matrix product: equal up to rounding.
                assert_all_close(&one, &[batch[(b, 0)], batch[(b, 1)]]);
            }
            // An empty batch is fine.
            moe.act_batch(Mat::<f32>::zeros(0, 3).as_ref(), Mat::<f32>::zeros(0, 2).as_mut())
                .unwrap();
        }
    }

    // ---------------------------------------------------------------------------------------
    // Gradients.
    // ---------------------------------------------------------------------------------------

    /// Max relative error between the accumulated gradients of the parameters named
    /// `prefix…` and central differences (steps `h`, `h/2`, Richardson) of `loss`: every other
    /// entry of the output layers (each row, i.e. each expert's raw output, is covered), every
    /// `stride`-th entry of the others. Returns the error and the number of entries checked.
    fn finite_difference_error(
        moe: &mut Moe,
        prefix: &str,
        stride: usize,
        loss: &mut dyn FnMut(&mut Moe) -> f64,
    ) -> (f32, usize) {
        let mut analytic = Vec::new();
        moe.visit_params("", &mut |name, p| {
            analytic.push(if name.starts_with(prefix) {
                let every = if name.contains(OUT_LAYER) { 2 } else { stride };
                p.grad.iter().enumerate().map(|(e, g)| (e % every == 0).then_some(*g)).collect()
            } else {
                Vec::new()
            });
        });
        let set = |moe: &mut Moe, index: usize, entry: usize, v: f32| {
            let mut k = 0;
            moe.visit_params_mut("", &mut |_, p| {
                if k == index {
                    p.value[entry] = v;
                }
                k += 1;
            });
        };
        let (h, mut worst, mut checked) = (1e-2f32, 0.0f32, 0);
        for (pi, grads) in analytic.iter().enumerate() {
            for (e, a) in grads.iter().enumerate() {
                let Some(a) = *a else { continue };
                let mut orig = 0.0;
                let mut k = 0;
                moe.visit_params("", &mut |_, p| {
                    if k == pi {
                        orig = p.value[e];
                    }
                    k += 1;
                });
                let mut central = |step: f32| {
                    let (xp, xm) = (orig + step, orig - step);
                    set(moe, pi, e, xp);
                    let fp = loss(moe);
                    set(moe, pi, e, xm);
                    let fm = loss(moe);
                    (fp - fm) / (f64::from(xp) - f64::from(xm))
                };
                let numeric = (4.0 * central(0.5 * h) - central(h)) / 3.0;
                set(moe, pi, e, orig);
                let err = (f64::from(a) - numeric).abs() / numeric.abs().max(1e-2);
                worst = worst.max(err as f32);
                checked += 1;
            }
        }
        (worst, checked)
    }

    #[test]
    fn backward_experts_matches_finite_differences_of_a_loss_through_forward() {
        for kind in [ExpertKind::Diagonal, ExpertKind::Full] {
            for shared in [true, false] {
                let mut moe = built(config(2, 2, kind, GatingKind::Learned, shared), 14);
                let states = obs_batch(5, 2);
                let (z, d, r) = (3, 2, moe.expert().raw_dim());
                // f = Σ c_μ·μ + Σ c_L·L over states and experts, with fixed random weights.
                let mut rng = Seeds::new(1).stream("coefficients");
                let cm: Vec<f32> = (0..5 * z * d).map(|_| rng.random_range(-1.0..1.0)).collect();
                let cl: Vec<f32> =
                    (0..5 * z * d * d).map(|_| rng.random_range(-1.0..1.0)).collect();
                let mut loss = |moe: &mut Moe| -> f64 {
                    moe.forward_experts(states.as_ref()).unwrap();
                    let out = moe.output();
                    let m: f64 = out.means.iter().zip(&cm).map(|(x, c)| f64::from(x * c)).sum();
                    let l: f64 = out.scales.iter().zip(&cl).map(|(x, c)| f64::from(x * c)).sum();
                    m + l
                };
                loss(&mut moe);
                let out = moe.output().clone();
                let mut grad_raw = vec![0.0; 5 * z * r];
                for k in 0..5 * z {
                    moe.expert().backward(
                        &out.raw[k * r..(k + 1) * r],
                        &cm[k * d..(k + 1) * d],
                        &cl[k * d * d..(k + 1) * d * d],
                        &mut grad_raw[k * r..(k + 1) * r],
                    );
                }
                moe.forward_gating(states.as_ref()).unwrap();
                moe.zero_grad();
                moe.backward_experts(&grad_raw).unwrap();
                let mut gating_grads = 0.0f32;
                moe.visit_params("", &mut |n, p| {
                    if n.starts_with("gating") {
                        gating_grads += p.grad.iter().map(|g| g.abs()).sum::<f32>();
                    }
                });
                assert_eq!(gating_grads, 0.0, "experts' backward touched the gating");
                let (err, checked) = finite_difference_error(&mut moe, "experts", 5, &mut loss);
                assert!(checked > 50, "{checked}");
                assert!(err < 1e-2, "{kind:?} shared={shared}: relative error {err}");
            }
        }
    }

    #[test]
    fn backward_gating_matches_finite_differences_of_a_loss_through_forward() {
        let mut moe = built(config(2, 2, ExpertKind::Diagonal, GatingKind::Learned, true), 15);
        let states = obs_batch(5, 2);
        let mut rng = Seeds::new(2).stream("coefficients");
        let c: Vec<f32> = (0..15).map(|_| rng.random_range(-1.0..1.0)).collect();
        // f = Σ c ⊙ log q(z|s); ∂f/∂logit_j = c_j − q_j Σ_k c_k per state.
        let mut loss = |moe: &mut Moe| -> f64 {
            moe.forward(states.as_ref()).unwrap();
            moe.output().log_gating.iter().zip(&c).map(|(l, c)| f64::from(l * c)).sum()
        };
        loss(&mut moe);
        let lg = moe.output().log_gating.clone();
        let grad = Mat::from_fn(5, 3, |b, j| {
            let total: f32 = c[b * 3..(b + 1) * 3].iter().sum();
            c[b * 3 + j] - lg[b * 3 + j].exp() * total
        });
        moe.zero_grad();
        moe.backward_gating(grad.as_ref()).unwrap();
        let mut expert_grads = 0.0f32;
        moe.visit_params("", &mut |n, p| {
            if n.starts_with("experts") {
                expert_grads += p.grad.iter().map(|g| g.abs()).sum::<f32>();
            }
        });
        assert_eq!(expert_grads, 0.0, "gating backward touched the experts");
        let (err, checked) = finite_difference_error(&mut moe, "gating", 3, &mut loss);
        assert!(checked > 40, "{checked}");
        assert!(err < 1e-2, "relative error {err}");

        // Uniform gating: nothing to differentiate, but the shape is still checked.
        let mut uniform = built(config(2, 2, ExpertKind::Diagonal, GatingKind::Uniform, true), 15);
        uniform.forward(states.as_ref()).unwrap();
        uniform.backward_gating(grad.as_ref()).unwrap();
        assert!(uniform.backward_gating(Mat::<f32>::zeros(4, 3).as_ref()).is_err());
    }

    // ---------------------------------------------------------------------------------------
    // Bad input.
    // ---------------------------------------------------------------------------------------

    fn is_shape(e: &MoeError) -> bool {
        matches!(e, MoeError::Core(CoreError::Shape { .. }))
    }

    #[test]
    fn invalid_configurations_are_errors() {
        let base = config(2, 2, ExpertKind::Diagonal, GatingKind::Learned, true);
        let bad = [
            MoeConfig { state_dim: 0, ..base.clone() },
            MoeConfig { action_dim: 0, ..base.clone() },
            MoeConfig { num_experts: 0, ..base.clone() },
            MoeConfig { mean_bias_init: -1.0, ..base.clone() },
            MoeConfig { mean_bias_init: f32::NAN, ..base.clone() },
            MoeConfig { init_std: 1e-5, ..base.clone() },
            MoeConfig { init_std: f32::NAN, ..base.clone() },
            MoeConfig { min_std: -1.0, ..base.clone() },
            MoeConfig {
                experts_network: NetworkConfig { hidden_dim: 0, ..small_net() },
                ..base.clone()
            },
            MoeConfig {
                gating_network: NetworkConfig { hidden_dim: 0, ..small_net() },
                ..base.clone()
            },
        ];
        for cfg in bad {
            assert!(Moe::from_config(cfg.clone(), 0).is_err(), "{cfg:?}");
        }
        let family = DiagonalExpert::new(3, 1.0, 1e-4).unwrap();
        assert!(matches!(Moe::new(base, family, 0), Err(e) if is_shape(&e)));
    }

    #[test]
    fn wrong_shapes_and_non_finite_inputs_are_errors() {
        let mut moe = built(config(2, 3, ExpertKind::Full, GatingKind::Learned, true), 16);
        let shape = |r: vdd_core::Result<()>| matches!(r, Err(CoreError::Shape { .. }));
        let nonfinite = |r: vdd_core::Result<()>| matches!(r, Err(CoreError::NonFinite { .. }));
        let mut a3 = [0.0f32; 3];

        // act / act_into
        assert!(matches!(moe.act(&[0.0]), Err(CoreError::Shape { .. })));
        assert!(shape(moe.act_into(&[0.0, 0.0], &mut [0.0; 2])));
        assert!(nonfinite(moe.act_into(&[f32::NAN, 0.0], &mut a3)));
        assert!(nonfinite(moe.act_into(&[f32::INFINITY, 0.0], &mut a3)));
        // act_batch
        let obs = obs_batch(4, 2);
        assert!(shape(moe.act_batch(obs_batch(4, 3).as_ref(), Mat::zeros(4, 3).as_mut())));
        assert!(shape(moe.act_batch(obs.as_ref(), Mat::zeros(3, 3).as_mut())));
        assert!(shape(moe.act_batch(obs.as_ref(), Mat::zeros(4, 2).as_mut())));
        let mut nan_obs = obs.clone();
        nan_obs[(2, 1)] = f32::NAN;
        assert!(nonfinite(moe.act_batch(nan_obs.as_ref(), Mat::zeros(4, 3).as_mut())));
        // log_likelihood
        let acts = Mat::<f32>::zeros(4, 3);
        let mut ll = vec![0.0; 4];
        assert!(shape(moe.log_likelihood(obs_batch(4, 1).as_ref(), acts.as_ref(), &mut ll)));
        assert!(shape(moe.log_likelihood(obs.as_ref(), Mat::zeros(4, 2).as_ref(), &mut ll)));
        assert!(shape(moe.log_likelihood(obs.as_ref(), Mat::zeros(3, 3).as_ref(), &mut ll)));
        assert!(shape(moe.log_likelihood(obs.as_ref(), acts.as_ref(), &mut [0.0; 3])));
        assert!(nonfinite(moe.log_likelihood(nan_obs.as_ref(), acts.as_ref(), &mut ll)));
        let mut nan_acts = acts.clone();
        nan_acts[(0, 2)] = f32::NEG_INFINITY;
        assert!(nonfinite(moe.log_likelihood(obs.as_ref(), nan_acts.as_ref(), &mut ll)));
        // An observation the normaliser maps out of f32 range.
        let huge = faer::mat![[3e38f32, 0.0]];
        moe.set_normalizers(Some(Affine::new(vec![-3e38, 0.0], vec![0.5, 1.0]).unwrap()), None)
            .unwrap();
        assert!(nonfinite(moe.act_batch(huge.as_ref(), Mat::zeros(1, 3).as_mut())));

        // The trainer-facing API on normalised states.
        assert!(matches!(moe.forward(obs_batch(4, 3).as_ref()), Err(e) if is_shape(&e)));
        assert!(moe.forward_experts(nan_obs.as_ref()).is_err());
        assert!(moe.forward_gating(nan_obs.as_ref()).is_err());
        assert!(moe.expert_entropies(obs_batch(4, 1).as_ref()).is_err());
        let mut resp = Mat::<f32>::zeros(4, 3);
        assert!(
            moe.responsibilities(obs.as_ref(), acts.as_ref(), Mat::zeros(4, 2).as_mut()).is_err()
        );
        assert!(moe.responsibilities(obs.as_ref(), nan_acts.as_ref(), resp.as_mut()).is_err());
        assert!(moe.responsibilities(nan_obs.as_ref(), acts.as_ref(), resp.as_mut()).is_err());
        assert!(moe.responsibilities(obs.as_ref(), acts.as_ref(), resp.as_mut()).is_ok());
    }

    #[test]
    fn backward_passes_validate_their_gradients_and_need_a_forward() {
        let mut moe = built(config(2, 2, ExpertKind::Diagonal, GatingKind::Learned, false), 17);
        assert!(matches!(moe.backward_experts(&[]), Err(MoeError::NoForward(_))));
        assert!(matches!(
            moe.backward_gating(Mat::<f32>::zeros(0, 3).as_ref()),
            Err(MoeError::NoForward(_))
        ));
        moe.forward(obs_batch(4, 2).as_ref()).unwrap();
        let r = moe.expert().raw_dim();
        assert!(matches!(moe.backward_experts(&vec![0.0; 4 * 3 * r - 1]), Err(e) if is_shape(&e)));
        let mut g = vec![0.0; 4 * 3 * r];
        g[5] = f32::NAN;
        assert!(moe.backward_experts(&g).is_err());
        assert!(matches!(
            moe.backward_gating(Mat::<f32>::zeros(4, 2).as_ref()),
            Err(e) if is_shape(&e)
        ));
        assert!(moe.backward_gating(Mat::from_fn(4, 3, |_, _| f32::NAN).as_ref()).is_err());
        moe.backward_experts(&vec![0.0; 4 * 3 * r]).unwrap();
        moe.backward_gating(Mat::<f32>::zeros(4, 3).as_ref()).unwrap();
    }

    #[test]
    fn invalid_normalizers_are_errors_and_change_nothing() {
        let mut moe = built(config(2, 3, ExpertKind::Diagonal, GatingKind::Uniform, true), 18);
        let before = (moe.normalizers().0.cloned(), moe.normalizers().1.cloned());
        let bad: [(Option<Affine>, Option<Affine>); 6] = [
            (Some(Affine::identity(3)), None),
            (None, Some(Affine::identity(2))),
            // Public fields allow what `Affine::new` rejects.
            (Some(Affine { offset: vec![0.0, 0.0], scale: vec![1.0] }), None),
            (None, Some(Affine { offset: vec![0.0; 3], scale: vec![1.0, -1.0, 1.0] })),
            (None, Some(Affine { offset: vec![0.0; 3], scale: vec![1.0, 0.0, 1.0] })),
            (Some(Affine { offset: vec![f32::NAN, 0.0], scale: vec![1.0; 2] }), None),
        ];
        for (o, a) in bad {
            assert!(moe.set_normalizers(o.clone(), a.clone()).is_err(), "{o:?} {a:?}");
            assert_eq!((moe.normalizers().0.cloned(), moe.normalizers().1.cloned()), before);
        }
        moe.set_normalizers(None, None).unwrap();
        assert_eq!(moe.normalizers(), (None, None));
    }

    // ---------------------------------------------------------------------------------------
    // Save and load.
    // ---------------------------------------------------------------------------------------

    fn scratch(name: &str) -> std::path::PathBuf {
        let dir = std::env::temp_dir().join(format!("vdd-moe-test-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    #[test]
    fn save_and_load_round_trip_everything_a_deployed_policy_needs() {
        for cfg in all_configs(2, 3) {
            let what =
                format!("{:?}/{:?}/shared={}", cfg.expert_kind, cfg.gating, cfg.shared_trunk);
            let mut moe = built(cfg, 19);
            let mode = ActMode { greedy_gating: false, sample_action: true };
            moe.set_act_mode(mode);
            let path = scratch(&format!("rt-{}.safetensors", what.replace('/', "-")));
            moe.save(&path).unwrap();
            let mut loaded = Moe::load(&path).unwrap();
            assert_eq!(loaded.config(), moe.config(), "{what}");
            assert_eq!(loaded.normalizers(), moe.normalizers(), "{what}");
            assert_eq!(loaded.act_mode(), mode, "{what}");
            assert_eq!(loaded.expert(), moe.expert(), "{what}");
            let obs = obs_batch(5, 2);
            let acts = Mat::from_fn(5, 3, |i, j| (i as f32 - j as f32) * 0.5);
            let (mut la, mut lb) = (vec![0.0; 5], vec![0.0; 5]);
            moe.log_likelihood(obs.as_ref(), acts.as_ref(), &mut la).unwrap();
            loaded.log_likelihood(obs.as_ref(), acts.as_ref(), &mut lb).unwrap();
            assert_eq!(la, lb, "{what}");
            moe.seed(4);
            loaded.seed(4);
            for k in 0..10 {
                let o = [0.2 * k as f32, -0.1];
                assert_eq!(moe.act(&o).unwrap(), loaded.act(&o).unwrap(), "{what}");
            }
        }
    }

    #[test]
    fn loading_with_another_expert_family_is_an_error() {
        let cfg = config(2, 2, ExpertKind::Full, GatingKind::Learned, true);
        let moe = built(cfg.clone(), 20);
        let path = scratch("family.safetensors");
        moe.save(&path).unwrap();
        let mismatch =
            |r: Result<Moe<FullExpert>, MoeError>| matches!(r, Err(MoeError::FamilyMismatch(_)));
        assert!(Moe::load_with_family(&path, FullExpert::new(2, 1.0, 1e-4).unwrap()).is_ok());
        // Same kind and shapes, another scale activation: would silently change every scale.
        assert!(mismatch(Moe::load_with_family(&path, FullExpert::new(2, 0.5, 1e-4).unwrap())));
        assert!(mismatch(Moe::load_with_family(&path, FullExpert::new(2, 1.0, 1e-2).unwrap())));
        assert!(Moe::load_with_family(&path, FullExpert::new(3, 1.0, 1e-4).unwrap()).is_err());
        let diag = Moe::load_with_family(&path, DiagonalExpert::new(2, 1.0, 1e-4).unwrap());
        assert!(matches!(diag, Err(MoeError::FamilyMismatch(_))));

        // A custom-family mixture whose config names another kind: `Moe::load` refuses it,
        // `load_with_family` with the right family reads it.
        let family = FullExpert::new(2, 0.7, 1e-3).unwrap();
        let custom =
            Moe::new(MoeConfig { expert_kind: ExpertKind::Diagonal, ..cfg }, family, 1).unwrap();
        let path = scratch("custom.safetensors");
        custom.save(&path).unwrap();
        assert!(matches!(Moe::load(&path), Err(MoeError::FamilyMismatch(_))));
        let back = Moe::load_with_family(&path, family).unwrap();
        let mut pa = Vec::new();
        let mut pb = Vec::new();
        custom.visit_params("", &mut |_, p| pa.push(p.value.clone()));
        back.visit_params("", &mut |_, p| pb.push(p.value.clone()));
        assert_eq!(pa, pb);
    }

    #[test]
    fn damaged_metadata_is_an_error_not_a_panic() {
        let moe = built(config(2, 3, ExpertKind::Diagonal, GatingKind::Learned, true), 21);
        let path = scratch("meta.safetensors");
        moe.save(&path).unwrap();
        let meta = vdd_nn::io::read_metadata(&path).unwrap();
        for key in ["config", "obs_normalizer", "action_normalizer", "act_mode", "expert_family"] {
            assert!(meta.contains_key(key), "{key}");
        }
        let edited = |key: &str, value: Option<&str>| {
            let mut m = meta.clone();
            match value {
                Some(v) => m.insert(key.to_owned(), v.to_owned()),
                None => m.remove(key),
            };
            let p = scratch(&format!("meta-{key}-{}.safetensors", value.map_or(0, str::len)));
            vdd_nn::io::save_safetensors(&p, &moe, &m).unwrap();
            Moe::load(&p).map(|_| ())
        };
        let config = |edit: &dyn Fn(&mut MoeConfig)| {
            let mut c = moe.config().clone();
            edit(&mut c);
            serde_json::to_string(&c).unwrap()
        };
        let bad = [
            ("config", None),
            ("config", Some("{not json".to_owned())),
            ("config", Some(config(&|c| c.num_experts = 0))),
            ("config", Some(config(&|c| c.experts_network.hidden_dim = 9))),
            ("config", Some(config(&|c| c.state_dim = 3))),
            ("obs_normalizer", None),
            ("obs_normalizer", Some(r#"{"offset":[0.0],"scale":[1.0]}"#.to_owned())),
            ("action_normalizer", Some(r#"{"offset":[0,0,0],"scale":[1,-2,1]}"#.to_owned())),
            ("action_normalizer", Some(r#"{"offset":[0,0,0],"scale":[1,1]}"#.to_owned())),
            ("act_mode", None),
            ("act_mode", Some("3".to_owned())),
            ("expert_family", Some("[]".to_owned())),
        ];
        for (key, value) in &bad {
            assert!(edited(key, value.as_deref()).is_err(), "{key}: {value:?}");
        }
        // Files from before the family fingerprint still load.
        edited("expert_family", None).unwrap();
        assert!(matches!(Moe::load(&scratch("absent.safetensors")), Err(MoeError::Nn(_))));
    }
}
