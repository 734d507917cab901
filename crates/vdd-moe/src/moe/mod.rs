//! The mixture of experts `q(a|s) = Σ_z q(z|s) N(a; μ_z(s), L_z(s) L_z(s)ᵀ)`.

mod components;
mod config;
mod deploy;
mod forward;
mod io;
mod output;
mod policy;
#[cfg(test)]
mod tests;

pub use components::{
    Components, deployed_components, deployed_log_likelihood, mixture_observations,
};
pub use config::{
    ActMode, GatingKind, MAX_ACTION_DIM, MAX_EXPERTS, MAX_SCALE_ENTRIES, MAX_STD, MoeConfig,
    NetworkConfig,
};
pub use deploy::{DeployedPolicy, load_policy};
pub use output::MoeOutput;

use faer::Mat;
use rand::Rng as _;
use vdd_core::{Affine, Expert, Rng, Seeds, check_len};
use vdd_data::DeploySpec;
use vdd_nn::{Param, Parameters, ResidualMlp, ResidualMlpConfig};

use crate::error::MoeError;
use crate::experts::ExpertFamily;

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

/// A mixture of Gaussian experts with a gating distribution; a [`Policy`](vdd_core::Policy) that acts with one
/// network evaluation and has an exact likelihood.
///
/// The networks see normalised states and emit normalised actions; the optional observation
/// and action normalisers are applied by the [`Policy`](vdd_core::Policy) methods and saved with the model. The
/// likelihood is that of the denormalised action (it includes the normaliser's log-Jacobian
/// `−Σ log scale`), so it is the density [`Policy::act`](vdd_core::Policy::act) samples from.
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
/// moe.set_act_mode(ActMode { greedy_gating: true, sample_action: false, hold_steps: 0 });
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
/// // One file holds weights, architecture, normalisers, act mode and deployment spec.
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
    /// How the mixture meets raw observations when deployed (saved with it).
    deploy_spec: DeploySpec,
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
    /// The expert chosen for each row of the last `act_into` / `act_batch`.
    last_experts: Vec<usize>,
    /// Per row: the held expert and how many more predictions it makes
    /// ([`ActMode::hold_steps`]); emptied by `Policy::reset`.
    held: Vec<Hold>,
}

/// A residual MLP of shape `nc` from `in_dim` states to `out_dim` outputs, without layer norm:
/// the experts' and the gating's networks.
fn residual_net(
    in_dim: usize,
    out_dim: usize,
    nc: &NetworkConfig,
    rng: &mut Rng,
) -> Result<ResidualMlp, vdd_nn::NnError> {
    let config = ResidualMlpConfig {
        in_dim,
        hidden_dim: nc.hidden_dim,
        num_blocks: nc.num_blocks,
        out_dim,
        activation: nc.activation,
        layer_norm: false,
    };
    ResidualMlp::new(&config, rng)
}

/// An expert kept for a row's next predictions ([`ActMode::hold_steps`]).
#[derive(Debug, Clone, Copy, Default)]
struct Hold {
    expert: usize,
    left: u32,
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
}

impl<E: Expert> Moe<E> {
    /// A freshly initialised mixture with a custom expert family (`expert.action_dim()` must
    /// equal `config.action_dim`). Initialisation draws from `Seeds::new(seed).stream("moe-init")`.
    pub fn new(config: MoeConfig, expert: E, seed: u64) -> Result<Self, MoeError> {
        config.validate()?;
        check_len("expert family action_dim", expert.action_dim(), config.action_dim)?;
        vdd_nn::limits::check_params("the mixture", config.num_params(expert.raw_dim()))?;
        let seeds = Seeds::new(seed);
        let mut rng = seeds.stream("moe-init");
        let z = config.num_experts;
        let r = expert.raw_dim();
        let d = config.action_dim;
        let net = |out_dim: usize, nc: &NetworkConfig, rng: &mut Rng| {
            residual_net(config.state_dim, out_dim, nc, rng)
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
            deploy_spec: DeploySpec::identity(),
            rng: seeds.stream("moe-act"),
            out: MoeOutput { num_experts: z, action_dim: d, ..Default::default() },
            experts_forwarded: false,
            gating_forwarded: false,
            states: Mat::zeros(0, 0),
            grad: Mat::zeros(0, 0),
            resp: vec![0.0; z],
            work: vec![0.0; d],
            act_work: Vec::new(),
            last_experts: Vec::new(),
            held: Vec::new(),
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

    /// Replaces a uniform gating by a learned one of architecture `network`, initialised to
    /// the same uniform `q(z|s)`: its hidden layers from `Seeds::new(seed).stream("moe-gating")`,
    /// its output layer zero. The experts are untouched, so the mixture's likelihood is
    /// unchanged until the gating is trained (e.g. fitted to a teacher's samples with
    /// `vdd_mixture::Em` and the experts frozen). On error (the gating is already learned, or
    /// `network` is invalid) nothing changes.
    ///
    /// ```
    /// use vdd_moe::{Moe, MoeConfig, NetworkConfig};
    ///
    /// let mut moe = Moe::from_config(MoeConfig::toy(2, 1, 4), 0)?; // uniform gating
    /// moe.add_learned_gating(NetworkConfig::default(), 1)?;
    /// assert!(moe.has_learned_gating());
    /// moe.forward_gating(faer::mat![[0.3f32, -1.0]].as_ref())?;
    /// assert!(moe.output().log_gating_row(0).iter().all(|l| (l + 4f32.ln()).abs() < 1e-6));
    /// assert!(moe.add_learned_gating(NetworkConfig::default(), 1).is_err());
    /// # Ok::<(), Box<dyn std::error::Error>>(())
    /// ```
    pub fn add_learned_gating(
        &mut self,
        network: NetworkConfig,
        seed: u64,
    ) -> Result<(), MoeError> {
        if self.gating.is_some() {
            return Err(MoeError::Core(vdd_core::CoreError::Config(
                "the mixture's gating is already learned".into(),
            )));
        }
        let config = MoeConfig {
            gating: GatingKind::Learned,
            gating_network: network,
            ..self.config.clone()
        };
        config.validate()?;
        vdd_nn::limits::check_params("the mixture", config.num_params(self.expert.raw_dim()))?;
        let mut rng = Seeds::new(seed).stream("moe-gating");
        let mut net =
            residual_net(config.state_dim, config.num_experts, &config.gating_network, &mut rng)?;
        let out = net.output_layer_mut();
        out.weight.value.fill(0.0);
        out.bias.value.fill(0.0);
        self.gating = Some(net);
        self.config = config;
        self.gating_forwarded = false;
        Ok(())
    }

    /// Sharpens (or flattens) a learned gating by a temperature: afterwards
    /// `q(z|s) ∝ q_old(z|s)^(1/temperature)` at every state, so `temperature < 1` moves weight
    /// to each state's most probable experts (towards greedy acting at 0) and `1` changes
    /// nothing. The gating's output layer is divided by `temperature`, so the change lives in
    /// the weights: a saved, exported or converted policy acts the same in every runtime. The
    /// experts are untouched. A uniform gating, or a temperature that is not finite and
    /// positive (or whose scaled weights would overflow), is an error and changes nothing.
    ///
    /// ```
    /// use vdd_moe::{GatingKind, Moe, MoeConfig};
    ///
    /// let config = MoeConfig { gating: GatingKind::Learned, ..MoeConfig::toy(2, 1, 3) };
    /// let mut moe = Moe::from_config(config, 0)?;
    /// let s = faer::mat![[0.3f32, -1.0]];
    /// moe.forward_gating(s.as_ref())?;
    /// let before = moe.output().log_gating_row(0).to_vec();
    /// moe.sharpen_gating(0.5)?;
    /// moe.forward_gating(s.as_ref())?;
    /// let after = moe.output().log_gating_row(0);
    /// // log q_new = 2 log q_old − log Σ_z q_old(z)²
    /// let norm = before.iter().map(|l| (2.0 * l).exp()).sum::<f32>().ln();
    /// assert!(after.iter().zip(&before).all(|(a, b)| (a - (2.0 * b - norm)).abs() < 1e-5));
    /// assert!(moe.sharpen_gating(0.0).is_err());
    /// # Ok::<(), Box<dyn std::error::Error>>(())
    /// ```
    pub fn sharpen_gating(&mut self, temperature: f32) -> Result<(), MoeError> {
        let config_error = |m: String| MoeError::Core(vdd_core::CoreError::Config(m));
        if !(temperature.is_finite() && temperature > 0.0) {
            return Err(config_error(format!(
                "the gating temperature must be finite and positive, not {temperature}"
            )));
        }
        let Some(net) = self.gating.as_mut() else {
            return Err(config_error("a uniform gating has no temperature to set".into()));
        };
        let out = net.output_layer_mut();
        let scaled = |v: &f32| v / temperature;
        if out.weight.value.iter().chain(&out.bias.value).any(|v| !scaled(v).is_finite()) {
            return Err(config_error(format!(
                "the gating's output layer overflows f32 at temperature {temperature}"
            )));
        }
        out.weight
            .value
            .iter_mut()
            .chain(out.bias.value.iter_mut())
            .for_each(|v| *v /= temperature);
        self.gating_forwarded = false;
        Ok(())
    }

    /// The expert that produced each row's action in the last
    /// [`Policy::act_into`](vdd_core::Policy::act_into) (one entry) or
    /// [`Policy::act_batch`](vdd_core::Policy::act_batch) (one entry per row, in row order) call:
    /// the expert that acted, not a guess from the action. Empty before the first call (and
    /// shorter than the batch after a call that failed).
    ///
    /// ```
    /// use vdd_core::Policy;
    /// use vdd_moe::{Moe, MoeConfig};
    ///
    /// let mut moe = Moe::from_config(MoeConfig::toy(2, 1, 4), 0)?;
    /// let obs = faer::mat![[0.1f32, 0.2], [0.3, 0.4], [0.5, 0.6]];
    /// let mut actions = faer::Mat::<f32>::zeros(3, 1);
    /// moe.act_batch(obs.as_ref(), actions.as_mut())?;
    /// assert_eq!(moe.last_experts().len(), 3);
    /// // With a uniform gating and mean actions, row b's action is its expert's mean.
    /// moe.forward(obs.as_ref())?;
    /// for (b, &z) in moe.last_experts().iter().enumerate() {
    ///     assert_eq!(actions[(b, 0)], moe.output().mean(b, z)[0]);
    /// }
    /// # Ok::<(), Box<dyn std::error::Error>>(())
    /// ```
    pub fn last_experts(&self) -> &[usize] {
        &self.last_experts
    }

    /// Sets how [`Policy::act`](vdd_core::Policy::act) picks the expert and the action, and
    /// ends every row's held expert ([`ActMode::hold_steps`]).
    pub fn set_act_mode(&mut self, mode: ActMode) {
        self.act_mode = mode;
        self.held.clear();
    }

    /// Attaches observation and action normalisers (used by the [`Policy`](vdd_core::Policy) methods only;
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

    /// How [`Policy::act`](vdd_core::Policy::act) picks the expert and the action.
    pub fn act_mode(&self) -> ActMode {
        self.act_mode
    }

    /// The experts' networks (for an optimiser).
    pub fn expert_networks_mut(&mut self) -> &mut ExpertNetworks {
        &mut self.experts
    }

    /// The experts' networks, read-only (to check an optimiser's state against them).
    pub fn expert_networks(&self) -> &ExpertNetworks {
        &self.experts
    }

    /// The gating network, if learned, read-only.
    pub fn gating_network(&self) -> Option<&ResidualMlp> {
        self.gating.as_ref()
    }

    /// The experts' residual MLPs with, for each, the experts whose raw outputs it emits (a
    /// shared trunk emits all `Z`, expert `z` in output columns `z·raw_dim..(z+1)·raw_dim`;
    /// separate networks one each), for custom initialisation.
    pub fn expert_trunks_mut(&mut self) -> Vec<(&mut ResidualMlp, std::ops::Range<usize>)> {
        match &mut self.experts.0 {
            ExpertNets::Shared(net) => vec![(&mut **net, 0..self.config.num_experts)],
            ExpertNets::Separate(nets) => {
                nets.iter_mut().enumerate().map(|(z, n)| (n, z..z + 1)).collect()
            }
        }
    }

    /// The gating network, if learned (for an optimiser).
    pub fn gating_network_mut(&mut self) -> Option<&mut ResidualMlp> {
        self.gating.as_mut()
    }

    /// The outputs of the last forward passes.
    pub fn output(&self) -> &MoeOutput {
        &self.out
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
