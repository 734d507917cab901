//! The mixture's architecture and how it acts: [`MoeConfig`], [`NetworkConfig`],
//! [`GatingKind`], [`ActMode`].

use serde::{Deserialize, Serialize};
use vdd_core::CoreError;
use vdd_nn::Activation;

use crate::experts::ExpertKind;

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

    /// Checks every setting against its documented range: `state_dim` in
    /// `1..=`[`MAX_WIDTH`](vdd_nn::limits::MAX_WIDTH), `action_dim` in `1..=`[`MAX_ACTION_DIM`],
    /// `num_experts` in `1..=`[`MAX_EXPERTS`] with `num_experts · action_dim²` at most
    /// [`MAX_SCALE_ENTRIES`] (the experts' scales of one state),
    /// the networks' `hidden_dim` in `1..=MAX_WIDTH` and `num_blocks` at most
    /// [`MAX_BLOCKS`](vdd_nn::limits::MAX_BLOCKS), `mean_bias_init` in
    /// `[0, `[`MAX_ABS_WEIGHT`](vdd_nn::limits::MAX_ABS_WEIGHT)`]`, and `min_std`, `init_std`
    /// in `[0, `[`MAX_STD`]`]` (the built-in families also need `min_std < init_std`). The parameter count, which also depends on
    /// the expert family, is checked by [`MoeConfig::num_params`] and [`crate::Moe::new`].
    ///
    /// ```
    /// use vdd_moe::MoeConfig;
    /// assert!(MoeConfig::toy(2, 2, 8).validate().is_ok());
    /// let huge = MoeConfig { mean_bias_init: 3e38, ..MoeConfig::toy(2, 2, 8) };
    /// assert!(huge.validate().unwrap_err().to_string().contains("mean_bias_init"));
    /// ```
    pub fn validate(&self) -> Result<(), CoreError> {
        use vdd_nn::limits::{MAX_ABS_WEIGHT, MAX_BLOCKS, MAX_WIDTH};
        let sizes = [
            ("state_dim", self.state_dim, MAX_WIDTH),
            ("action_dim", self.action_dim, MAX_ACTION_DIM),
            ("num_experts", self.num_experts, MAX_EXPERTS),
            ("experts_network.hidden_dim", self.experts_network.hidden_dim, MAX_WIDTH),
            ("gating_network.hidden_dim", self.gating_network.hidden_dim, MAX_WIDTH),
        ];
        for (name, v, max) in sizes {
            if v == 0 || v > max {
                return Err(CoreError::Config(format!("{name} must be in 1..={max}, got {v}")));
            }
        }
        for (name, v) in [
            ("experts_network.num_blocks", self.experts_network.num_blocks),
            ("gating_network.num_blocks", self.gating_network.num_blocks),
        ] {
            if v > MAX_BLOCKS {
                return Err(CoreError::Config(format!("{name} must be <= {MAX_BLOCKS}, got {v}")));
            }
        }
        // Every row of a forward pass holds a d x d scale per expert.
        let scale_entries = self.num_experts * self.action_dim * self.action_dim;
        if scale_entries > MAX_SCALE_ENTRIES {
            return Err(CoreError::Config(format!(
                "num_experts · action_dim² must be <= {MAX_SCALE_ENTRIES}, got {} · {}²",
                self.num_experts, self.action_dim
            )));
        }
        let w = self.mean_bias_init;
        if !(w.is_finite() && (0.0..=MAX_ABS_WEIGHT).contains(&w)) {
            return Err(CoreError::Config(format!(
                "mean_bias_init must be in [0, {MAX_ABS_WEIGHT:e}], got {w:e}"
            )));
        }
        let (init, min) = (self.init_std, self.min_std);
        if !((0.0..=MAX_STD).contains(&min) && (0.0..=MAX_STD).contains(&init)) {
            return Err(CoreError::Config(format!(
                "min_std and init_std must be in [0, {MAX_STD:e}], got {min} and {init}"
            )));
        }
        Ok(())
    }

    /// Number of parameters of the mixture with experts of `raw_dim` raw outputs each, without
    /// building it (`None` if the count overflows `usize`).
    pub fn num_params(&self, raw_dim: usize) -> Option<usize> {
        let net = |out_dim: usize, nc: &NetworkConfig| {
            vdd_nn::ResidualMlpConfig {
                in_dim: self.state_dim,
                hidden_dim: nc.hidden_dim,
                num_blocks: nc.num_blocks,
                out_dim,
                activation: nc.activation,
                layer_norm: false,
            }
            .num_params()
        };
        let z = self.num_experts;
        let experts = if self.shared_trunk {
            net(z.checked_mul(raw_dim)?, &self.experts_network)?
        } else {
            net(raw_dim, &self.experts_network)?.checked_mul(z)?
        };
        let gating = match self.gating {
            GatingKind::Uniform => 0,
            GatingKind::Learned => net(z, &self.gating_network)?,
        };
        experts.checked_add(gating)
    }
}

/// Largest number of experts of a mixture (far above the paper's 8 to 16).
pub const MAX_EXPERTS: usize = 1 << 12;

/// Largest action dimension (a flattened chunk of actions) of a mixture.
pub const MAX_ACTION_DIM: usize = 1 << 10;

/// Largest `num_experts · action_dim²`: the entries of the experts' scale matrices of one state.
pub const MAX_SCALE_ENTRIES: usize = 1 << 22;

/// Largest initial standard deviation of an expert (`init_std`).
pub const MAX_STD: f32 = 1e6;

/// How [`Policy::act`](vdd_core::Policy::act) turns the mixture into one action.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, Serialize, Deserialize)]
pub struct ActMode {
    /// Pick the most probable expert instead of sampling `z ~ q(z|s)`.
    pub greedy_gating: bool,
    /// Sample `a ~ N(μ_z, Σ_z)` instead of returning `μ_z` (the paper evaluates with `μ_z`).
    pub sample_action: bool,
    /// Keep the expert picked for a row for this many consecutive predictions of that row
    /// before picking again; `0` and `1` pick at every prediction (the paper's acting, with the
    /// same random draws). The held expert acts on each new state.
    /// [`Policy::reset`](vdd_core::Policy::reset) and [`Moe::set_act_mode`](crate::Moe::set_act_mode)
    /// end every hold. Row `i` of [`Policy::act_batch`](vdd_core::Policy::act_batch) must be
    /// the same episode from one call to the next, as the rollouts' lockstep contract says;
    /// behind a `vdd_data::Windowed` with action chunks, the mixture's rows are the rows that
    /// need a new chunk, which stay aligned when every episode starts together. Acting by hand
    /// from exported components (ONNX, Python's `components`), keep `z` yourself.
    ///
    /// On Avoiding, holding hurts at every length (docs/avoiding-tuning.md): there, an expert
    /// steers a stretch of a path, not a whole path.
    #[serde(default)]
    pub hold_steps: u32,
}

impl NetworkConfig {
    /// Floats a residual MLP of this shape from `in_dim` to `out_dim` holds: its parameters,
    /// and per row of a batch its activations (saturating; an upper bound with layer norms).
    fn floats(&self, in_dim: usize, out_dim: usize) -> (u64, u64) {
        use vdd_core::memory::product;
        let h = self.hidden_dim;
        let block = product(&[2, h, h]).saturating_add(product(&[6, h]));
        let params = product(&[in_dim + 1, h])
            .saturating_add(product(&[self.num_blocks]).saturating_mul(block))
            .saturating_add(product(&[h + 1, out_dim]));
        let per_row = product(&[8, h, self.num_blocks + 1]).saturating_add(product(&[2, out_dim]));
        (params, per_row)
    }
}

impl MoeConfig {
    /// Estimated bytes of training this mixture on batches of `batch_rows` states: every
    /// parameter five times (value, gradient, Adam's two moments, an average) and the
    /// activations and gradients of a batch (saturating at `u64::MAX`).
    ///
    /// ```
    /// use vdd_moe::MoeConfig;
    /// let small = MoeConfig::toy(1, 2, 8).training_bytes(256);
    /// assert!(small < 1 << 30);
    /// let huge = MoeConfig { num_experts: 100_000_000, shared_trunk: false, ..MoeConfig::toy(1, 2, 8) };
    /// assert!(huge.training_bytes(256) > 1 << 40);
    /// ```
    pub fn training_bytes(&self, batch_rows: usize) -> u64 {
        use vdd_core::memory::product;
        let (z, d) = (self.num_experts, self.action_dim);
        // Raw outputs per expert: the mean and the (full at most) covariance factor.
        let raw = match self.expert_kind {
            ExpertKind::Diagonal => product(&[2, d]),
            ExpertKind::Full => product(&[d, d + 3]) / 2,
        }
        .min(usize::MAX as u64) as usize;
        let (experts, expert_rows) = if self.shared_trunk {
            self.experts_network.floats(self.state_dim, z.saturating_mul(raw))
        } else {
            let (p, r) = self.experts_network.floats(self.state_dim, raw);
            (p.saturating_mul(z as u64), r.saturating_mul(z as u64))
        };
        let (gating, gating_rows) = match self.gating {
            GatingKind::Uniform => (0, z as u64),
            GatingKind::Learned => self.gating_network.floats(self.state_dim, z),
        };
        let params = experts.saturating_add(gating).saturating_mul(5);
        let rows = expert_rows.saturating_add(gating_rows).saturating_mul(batch_rows as u64);
        params.saturating_add(rows).saturating_mul(4)
    }

    /// The configuration's ranges (as [`crate::Moe::new`] checks them), then
    /// [`MoeConfig::training_bytes`] of batches of `batch_rows` against the memory available
    /// ([`vdd_core::memory::check_fits`]): what a run checks before any work.
    pub fn check(&self, batch_rows: usize) -> Result<(), CoreError> {
        self.validate()?;
        let bytes = self.training_bytes(batch_rows);
        let what = format!(
            "a mixture of {} experts (hidden_dim {} / {}) on batches of {batch_rows}",
            self.num_experts, self.experts_network.hidden_dim, self.gating_network.hidden_dim
        );
        vdd_core::memory::check_fits(&what, bytes)
    }
}
