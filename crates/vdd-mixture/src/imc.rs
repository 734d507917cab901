//! **IMC, Information Maximizing Curriculum** (Blessing, Celik, Jia, Reuss, Li, Lioutikov,
//! Neumann, NeurIPS 2023, arXiv 2303.15349): a mixture of experts in which every expert keeps a
//! *curriculum*, a distribution over the `N` data points, and fits only the points it can
//! represent, while a joint-entropy term makes the curricula cover the whole dataset.
//!
//! ## Objective
//!
//! Data points are `o = (s_o, a_o)`, `o = 1..N`. Write `ℓ_z(o) = log N(a_o; μ_z(s_o), Σ_z(s_o))`
//! for expert `z`'s log-likelihood of point `o`. The curricula form a joint distribution
//! `p(o, z) = p(z) p(o|z)` over (point, expert) pairs, with data marginal
//! `p(o) = Σ_z p(o, z)` and posterior `p(z|o) = p(o, z) / p(o)`. IMC maximises
//!
//! `J(p, θ) = Σ_z p(z) E_{p(o|z)}[ℓ_z(o)] + η H(o)`,
//!
//! where `H(o) = −Σ_o p(o) log p(o)` is the entropy of the data marginal (the *joint* entropy
//! term: a point that no curriculum takes lowers it) and `η > 0` trades likelihood against
//! coverage. Because `H(o) = H(o, z) − H(z|o)` and `−H(z|o) ≥ E_{p(o,z)}[log q̃(z|o)]` for any
//! `q̃`, `J` has the lower bound
//!
//! `L(p, θ, q̃) = Σ_{o,z} p(o, z) [ℓ_z(o) + η log q̃(z|o)] + η H(o, z)`,
//!
//! tight at `q̃(z|o) = p(z|o)`.
//!
//! ## Closed-form curriculum update (what [`Curricula::update`] does)
//!
//! Maximising `L` over the joint `p(o, z)` with `q̃` fixed is an entropy-regularised linear
//! problem whose solution is a softmax over all `N·Z` pairs:
//!
//! `p_new(o, z) = exp(ℓ_z(o)/η + log q̃(z|o)) / Ξ`, `Ξ = Σ_{o,z} exp(ℓ_z(o)/η + log q̃(z|o))`,
//!
//! and the maximum is `L* = η log Ξ` (reported as [`ImcMetrics::lower_bound`]). With the tight
//! choice `q̃(z|o) = p_old(z|o) = p_old(o, z) / p_old(o)` this reads
//!
//! `log p_new(o, z) = log p_old(o, z) + (ℓ_z(o) − η log p_old(o)) / η − log Ξ`,
//!
//! i.e. per expert `p_new(o|z) = softmax_o(ℓ_z(o)/η + log p_old(z|o))` and the expert weights
//! `p_new(z) ∝ Σ_o exp(ℓ_z(o)/η) p_old(z|o)`. With one expert it is the single-expert curriculum
//! `p(o) ∝ N(a_o; μ(s_o), Σ(s_o))^{1/η}`. Curricula start uniform, `p_0(o, z) = 1/(N·Z)`.
//!
//! ## One iteration
//!
//! 1. `ℓ_z(o)` for every point and expert with the current (frozen) experts; report
//!    `J(p_k, θ_k)` ([`ImcMetrics::objective`]).
//! 2. Curriculum update (above): `p_{k+1}`.
//! 3. Experts: `expert_steps_per_iter` Adam steps of weighted maximum likelihood,
//!    `max_θ Σ_{o,z} p_{k+1}(o, z) ℓ_z(o)`, on minibatches `o_b ~ p_{k+1}(o)` with weights
//!    `p_{k+1}(z|o_b) / B` (unbiased), or on the whole dataset with weights `p_{k+1}(o, z)`.
//! 4. Gating: `gating_steps_per_iter` Adam steps of the soft cross-entropy
//!    `−(1/B) Σ_b Σ_z p_{k+1}(z|o_b) log q(z|s_b)`, i.e. the gating is fitted to the curricula's
//!    posterior over experts `p(z|o) ∝ p(o|z) p(z)`, with `o_b` uniform over the data
//!    ([`GatingData::Uniform`], default) or `o_b ~ p(o)` ([`GatingData::Curriculum`]).
//!
//! Steps 1–3 are coordinate ascent: `J(θ_k, p_k) = L(θ_k, p_k, p_k(z|o)) ≤ L(θ_k, p_{k+1}, ·)
//! ≤ J(θ_k, p_{k+1}) ≤ J(θ_{k+1}, p_{k+1})` as long as the gradient steps increase the weighted
//! likelihood, so `J` never decreases (a test checks it on a full batch).
//!
//! At inference the result is a plain [`Moe`]: `z ~ q(z|s)`, action `μ_z(s)`.
//!
//! ## The temperature `η`
//!
//! For a Gaussian expert on a Gaussian cluster `N(m, S)` that it owns, the curriculum weights
//! the cluster by `N(a; μ, Σ)^{1/η}`; the weighted maximum-likelihood fit then has covariance
//! `(S⁻¹ + Σ⁻¹/η)⁻¹`, whose fixed point is `Σ* = (1 − 1/η) S` (a test checks it). So with
//! learned scales `η ≤ 1` makes every expert shrink onto a few points (down to `min_std`; the
//! objective is unbounded on a finite dataset), and a larger `η` keeps more of each mode at the
//! cost of a weaker ability to ignore points: the curriculum only becomes mode-seeking (an
//! expert between two modes drifts onto one of them instead of widening over both) when the
//! tempering `N^{1/η}` is strong.
//!
//! The default `η = 2` is the smallest round value with a non-degenerate fixed point: a point
//! 2σ from its expert's mean gets `e^{−1}` of the weight of the centre, and each expert keeps
//! half of its mode's variance (std ×0.71). That shrinkage costs ≈0.19 nats of reverse KL and
//! ≈0.31 nats of forward KL on a Gaussian mode — the price of IMC's mode seeking with learned
//! scales; acting with the expert means (the paper's evaluation) is unaffected by it. On the
//! 8-mode toy, `η = 4` and `η = 8` give lower KL but cover fewer modes (they behave more like
//! EM). Implementations that hold the experts' scales fixed can use `η = 1`.

use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Expert, Snapshot, Trainer, check_len};
use vdd_moe::{ExpertFamily, Moe, MoeConfig};
use vdd_nn::{AdamConfig, LrSchedule};

use crate::dataset::Dataset;
use crate::error::MixtureError;
use crate::fit::{self, MixtureFit, RowSampler};

/// Which data points the gating is fitted on.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum GatingData {
    /// Uniformly over the dataset: `q(z|s)` matches the share of points each expert owns.
    #[default]
    Uniform,
    /// From the curricula's data marginal `p(o)` (points no curriculum takes are ignored).
    Curriculum,
}

/// Which IMC [`Imc`] runs.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum ImcVariant {
    /// The paper's equations (the module docs): learned expert scales, curricula normalised
    /// jointly over all (point, expert) pairs, the gating fitted every iteration.
    #[default]
    Paper,
    /// The authors' code (Blessing et al.'s `InformationMaximizingCurriculum`): experts scored
    /// as `N(μ_z, I)` (`ℓ_z(o) = −½‖a_o − μ_z(s_o)‖²`; their scales are neither used nor
    /// trained, and the fitted mixture acts with its means), log curricula
    /// `ℓ_z(o)/η + log p(z|o)` normalised per data point (the best expert of every point gets
    /// weight 1, so no point is dropped), experts fitted on uniform minibatches weighted by
    /// their curricula, and the gating fitted once at the end, to `p(z|o)`, with all of the
    /// run's gating steps. [`ImcMetrics::objective`] and [`Imc::curricula`] then describe the
    /// curricula normalised jointly.
    Authors,
}

impl ImcVariant {
    fn is_paper(&self) -> bool {
        *self == ImcVariant::Paper
    }
}

/// Hyper-parameters of [`Imc`]. [`ImcConfig::toy`] is the one default used on every task.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ImcConfig {
    /// Temperature `η > 0` of the joint-entropy term (see the module docs).
    pub eta: f64,
    /// Number of iterations (curriculum update + expert and gating steps).
    pub iterations: usize,
    /// Expert gradient steps per iteration, all against the same curricula.
    pub expert_steps_per_iter: usize,
    /// Gating gradient steps per iteration.
    pub gating_steps_per_iter: usize,
    /// Pairs per expert step; `None` (or at least the dataset size) uses the whole dataset.
    pub batch_size: Option<usize>,
    /// Pairs per gating step; `None` (or at least the dataset size) uses the whole dataset.
    pub gating_batch_size: Option<usize>,
    /// Which points the gating is fitted on.
    pub gating_data: GatingData,
    /// Adam for the experts.
    pub expert_optimizer: AdamConfig,
    /// Learning-rate schedule of the experts, over expert steps.
    pub expert_lr_schedule: LrSchedule,
    /// Adam for the gating.
    pub gating_optimizer: AdamConfig,
    /// Learning-rate schedule of the gating, over gating steps.
    pub gating_lr_schedule: LrSchedule,
    /// Clip each network's gradient to this global norm.
    pub max_grad_norm: Option<f32>,
    /// Root seed of every random draw of the run.
    pub seed: u64,
    /// The paper's IMC or the authors' (absent in a recipe: the paper's).
    #[serde(default, skip_serializing_if = "ImcVariant::is_paper")]
    pub variant: ImcVariant,
    /// The points whose curricula each iteration updates, with [`ImcVariant::Authors`] only.
    /// `None` (the default): every point, as the authors' code. `Some(k)`: `k` distinct points
    /// drawn afresh each iteration (from the stream `curriculum-rows`); each advances its
    /// curriculum by the iterations it missed, its experts' log-likelihoods held at their
    /// current values ([`advance_curriculum`]), and that iteration's expert steps draw their
    /// minibatches from them only. The last iteration updates every point, so the gating is
    /// fitted to current curricula. The per-iteration scoring of every point costs far more
    /// than the expert steps on a large dataset (30 steps of 256 pairs use 7,680 rows); `k` a
    /// few times that keeps an iteration's cost independent of the dataset's size, as
    /// [`crate::EmConfig::e_step_rows`] does for EM. Needs expert minibatches (`batch_size`).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub curriculum_rows: Option<usize>,
}

impl ImcConfig {
    /// Defaults: `η = 2` and the same optimisation budget as [`crate::EmConfig::toy`] (100
    /// iterations of 30 expert and 30 gating steps on minibatches of 256, Adam `1e-3` decaying
    /// linearly to 0), gating fitted uniformly over the data.
    pub fn toy() -> Self {
        Self::with_loop_of(crate::EmConfig::toy())
    }

    /// `η = 2`, the gating fitted uniformly over the data, and the loop settings (iterations,
    /// steps, batches, optimisers, schedules, clipping, seed) of `em`.
    pub(crate) fn with_loop_of(em: crate::EmConfig) -> Self {
        Self {
            eta: 2.0,
            iterations: em.iterations,
            expert_steps_per_iter: em.expert_steps_per_iter,
            gating_steps_per_iter: em.gating_steps_per_iter,
            batch_size: em.batch_size,
            gating_batch_size: em.gating_batch_size,
            gating_data: GatingData::Uniform,
            expert_optimizer: em.expert_optimizer,
            expert_lr_schedule: em.expert_lr_schedule,
            gating_optimizer: em.gating_optimizer,
            gating_lr_schedule: em.gating_lr_schedule,
            max_grad_norm: em.max_grad_norm,
            seed: em.seed,
            variant: ImcVariant::Paper,
            curriculum_rows: None,
        }
    }

    /// Checks ranges.
    pub fn validate(&self) -> Result<(), CoreError> {
        if !(self.eta.is_finite() && self.eta > 0.0) {
            return Err(CoreError::Config(format!("eta must be positive, got {}", self.eta)));
        }
        match self.curriculum_rows {
            Some(0) => return Err(CoreError::Config("curriculum_rows must be positive".into())),
            Some(k) if self.variant != ImcVariant::Authors => {
                return Err(CoreError::Config(format!(
                    "curriculum_rows = {k} needs the authors' variant: the paper's curricula are \
                     normalised over all points at once, so updating some of them moves all"
                )));
            }
            Some(k) if self.batch_size.is_none() => {
                return Err(CoreError::Config(format!(
                    "curriculum_rows = {k} needs expert minibatches (batch_size): a \
                     whole-dataset step would use points whose curricula are stale"
                )));
            }
            _ => {}
        }
        fit::validate_loop(&fit::loop_settings!(self), false)
    }
}

impl Default for ImcConfig {
    fn default() -> Self {
        Self::toy()
    }
}

/// The joint curriculum `p(o, z)` over `N` data points and `Z` experts, stored as normalised
/// log-probabilities (`f64`, row-major `N·Z`).
///
/// ```
/// use vdd_mixture::imc::Curricula;
/// let mut c = Curricula::uniform(3, 1).unwrap();
/// // One expert: p(o) ∝ exp(ℓ(o)/η).
/// c.update(&[0.0, -1.0, -2.0], 1.0).unwrap();
/// let p = c.data_marginal();
/// assert!((p[0] / p[1] - 1f64.exp()).abs() < 1e-9);
/// assert!((c.curriculum(0).iter().sum::<f64>() - 1.0).abs() < 1e-12);
/// ```
#[derive(Debug, Clone, PartialEq)]
pub struct Curricula {
    n: usize,
    num_experts: usize,
    log_joint: Vec<f64>,
}

impl Curricula {
    /// Uniform curricula `p(o, z) = 1/(N·Z)`.
    pub fn uniform(num_points: usize, num_experts: usize) -> Result<Self, CoreError> {
        if num_points == 0 || num_experts == 0 {
            return Err(CoreError::Config("curricula need points and experts".into()));
        }
        let v = -((num_points * num_experts) as f64).ln();
        Ok(Self { n: num_points, num_experts, log_joint: vec![v; num_points * num_experts] })
    }

    /// Number of data points `N`.
    pub fn num_points(&self) -> usize {
        self.n
    }

    /// Number of experts `Z`.
    pub fn num_experts(&self) -> usize {
        self.num_experts
    }

    /// `log p(o, z)`, row-major `N·Z`.
    pub fn log_joint(&self) -> &[f64] {
        &self.log_joint
    }

    /// `log p(o)` of point `o`.
    fn log_marginal(&self, o: usize) -> f64 {
        log_sum_exp(&self.log_joint[o * self.num_experts..(o + 1) * self.num_experts])
    }

    /// The data marginal `p(o) = Σ_z p(o, z)` (length `N`).
    pub fn data_marginal(&self) -> Vec<f64> {
        (0..self.n).map(|o| self.log_marginal(o).exp()).collect()
    }

    /// The expert weights `p(z) = Σ_o p(o, z)` (length `Z`).
    pub fn expert_weights(&self) -> Vec<f64> {
        let z_n = self.num_experts;
        let mut w = vec![0.0; z_n];
        for (i, l) in self.log_joint.iter().enumerate() {
            w[i % z_n] += l.exp();
        }
        w
    }

    /// Expert `z`'s curriculum `p(o|z)` over the data points (length `N`, sums to 1).
    pub fn curriculum(&self, z: usize) -> Vec<f64> {
        let z_n = self.num_experts;
        let col: Vec<f64> = (0..self.n).map(|o| self.log_joint[o * z_n + z]).collect();
        let lse = log_sum_exp(&col);
        col.iter().map(|l| (l - lse).exp()).collect()
    }

    /// The posterior over experts `p(z|o)` of point `o`, written into `out` (length `Z`).
    pub fn posterior_into(&self, o: usize, out: &mut [f64]) {
        let z_n = self.num_experts;
        let row = &self.log_joint[o * z_n..(o + 1) * z_n];
        let lse = log_sum_exp(row);
        for (p, l) in out.iter_mut().zip(row) {
            *p = (l - lse).exp();
        }
    }

    /// Entropy `H(o)` of the data marginal, in nats.
    pub fn data_entropy(&self) -> f64 {
        -(0..self.n)
            .map(|o| {
                let l = self.log_marginal(o);
                l.exp() * l
            })
            .filter(|x| x.is_finite())
            .sum::<f64>()
    }

    /// The IMC objective `J = Σ_{o,z} p(o, z) ℓ_z(o) + η H(o)` for the experts'
    /// log-likelihoods `log_lik` (`N·Z`, row-major).
    pub fn objective(&self, log_lik: &[f32], eta: f64) -> Result<f64, CoreError> {
        check_len("expert log-likelihoods", log_lik.len(), self.log_joint.len())?;
        Ok(self.weighted_log_likelihood(log_lik) + eta * self.data_entropy())
    }

    /// The metrics of updated curricula ([`ImcMetrics`]): the experts' weighted
    /// log-likelihood `Σ_{o,z} p(o, z) ℓ_z(o)`, the effective data fraction `exp(H(o)) / N`
    /// and the experts of weight at least `0.1/Z`.
    fn summary(&self, log_lik: &[f32]) -> (f64, f64, usize) {
        let z_n = self.num_experts;
        let active = self.expert_weights().iter().filter(|&&w| w >= 0.1 / z_n as f64).count();
        let effective = self.data_entropy().exp() / self.n as f64;
        (self.weighted_log_likelihood(log_lik), effective, active)
    }

    /// `Σ_{o,z} p(o, z) ℓ_z(o)`.
    fn weighted_log_likelihood(&self, log_lik: &[f32]) -> f64 {
        self.log_joint.iter().zip(log_lik).map(|(l, ll)| l.exp() * f64::from(*ll)).sum()
    }

    /// The closed-form curriculum update (module docs):
    /// `log p(o, z) ← log p(o, z) + (ℓ_z(o) − η log p(o)) / η − log Ξ`, normalised over all
    /// pairs. Returns the maximised lower bound `η log Ξ`.
    pub fn update(&mut self, log_lik: &[f32], eta: f64) -> Result<f64, CoreError> {
        check_len("expert log-likelihoods", log_lik.len(), self.log_joint.len())?;
        if !(eta.is_finite() && eta > 0.0) {
            return Err(CoreError::Config(format!("eta must be positive, got {eta}")));
        }
        vdd_core::check_finite_slice("expert log-likelihoods", log_lik)?;
        let z_n = self.num_experts;
        for o in 0..self.n {
            let row = &mut self.log_joint[o * z_n..(o + 1) * z_n];
            let log_p_o = log_sum_exp(row);
            for (l, ll) in row.iter_mut().zip(&log_lik[o * z_n..(o + 1) * z_n]) {
                *l += f64::from(*ll) / eta - log_p_o;
            }
        }
        let log_xi = log_sum_exp(&self.log_joint);
        self.log_joint.iter_mut().for_each(|l| *l -= log_xi);
        Ok(eta * log_xi)
    }
}

pub(crate) fn log_sum_exp(xs: &[f64]) -> f64 {
    let m = xs.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    if !m.is_finite() {
        return m;
    }
    m + xs.iter().map(|x| (x - m).exp()).sum::<f64>().ln()
}

/// What one IMC iteration did; passed to the training callback.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ImcMetrics {
    /// 0-based iteration index.
    pub iteration: usize,
    /// `J(p_k, θ_k)`: the objective with this iteration's starting curricula and experts.
    pub objective: f64,
    /// `η log Ξ`: the lower bound maximised by the curriculum update.
    pub lower_bound: f64,
    /// `Σ_{o,z} p_{k+1}(o, z) ℓ_z(o)`: the experts' likelihood of their updated curricula.
    pub curriculum_log_likelihood: f64,
    /// `exp(H(o)) / N` after the update: the share of the data the curricula effectively
    /// cover (1 for a uniform marginal).
    pub effective_data_fraction: f64,
    /// Experts whose weight `p(z)` is at least `0.1/Z` after the update.
    pub active_experts: usize,
    /// Mean dataset log-likelihood of the mixture (with its gating) at the start of the
    /// iteration, in nats.
    pub log_likelihood: f64,
    /// Weighted NLL of the last expert step (before that step).
    pub expert_loss: f64,
    /// Soft cross-entropy of the last gating step.
    pub gating_loss: Option<f64>,
    /// Experts' learning rate at the last expert step.
    pub expert_lr: f32,
    /// Gating learning rate at the last gating step.
    pub gating_lr: f32,
}

/// What an iteration's curriculum update measured: the fields of [`ImcMetrics`] before the
/// gradient steps.
struct Measured {
    objective: f64,
    lower_bound: f64,
    /// [`Curricula::summary`] of the updated curricula.
    summary: (f64, f64, usize),
    log_likelihood: f64,
}

impl Measured {
    /// The iteration's metrics, with the last expert and gating steps' losses and learning
    /// rates.
    fn into_metrics(
        self,
        iteration: usize,
        (expert_loss, expert_lr): (f64, f32),
        (gating_loss, gating_lr): (Option<f64>, f32),
    ) -> ImcMetrics {
        let (curriculum_log_likelihood, effective_data_fraction, active_experts) = self.summary;
        ImcMetrics {
            iteration,
            objective: self.objective,
            lower_bound: self.lower_bound,
            curriculum_log_likelihood,
            effective_data_fraction,
            active_experts,
            log_likelihood: self.log_likelihood,
            expert_loss,
            gating_loss,
            expert_lr,
            gating_lr,
        }
    }
}

/// Information Maximizing Curriculum for a mixture of experts of family `E` on a [`Dataset`].
/// The mixture must have a learned gating.
///
/// ```
/// use faer::Mat;
/// use vdd_mixture::{Dataset, Imc, ImcConfig};
/// use vdd_moe::{GatingKind, MoeConfig};
/// let actions = Mat::from_fn(64, 1, |i, _| if i % 2 == 0 { 2.0 } else { -2.0 } + 0.05 * (i % 5) as f32);
/// let data = Dataset::new(Mat::zeros(64, 1), actions).unwrap();
/// let mut mc = MoeConfig::toy(1, 1, 2);
/// mc.gating = GatingKind::Learned;
/// mc.experts_network.hidden_dim = 16;
/// mc.gating_network.hidden_dim = 16;
/// let config = ImcConfig { iterations: 40, batch_size: None, gating_batch_size: None,
///                          expert_optimizer: vdd_nn::AdamConfig { lr: 1e-2, ..Default::default() },
///                          ..ImcConfig::toy() };
/// let mut imc = Imc::from_config(config, mc, data).unwrap();
/// imc.train(|_| {}).unwrap();
/// let c = imc.curricula();
/// assert!((c.curriculum(0).iter().sum::<f64>() - 1.0).abs() < 1e-9);
/// let student = imc.into_student(); // a vdd_core::Policy with exact likelihood
/// ```
pub struct Imc<E: Expert = ExpertFamily> {
    config: ImcConfig,
    fit: MixtureFit<E>,
    curricula: Curricula,
    log_lik: Vec<f32>,
    posterior: Vec<f32>,
    marginal: Vec<f64>,
    /// The authors' log curricula `log c(o, z)`, normalised per point (`N·Z`).
    per_point: Vec<f64>,
    /// With [`ImcConfig::curriculum_rows`], the iterations of curriculum updates each point's
    /// `per_point` row holds (`N`).
    advanced_to: Vec<usize>,
}

impl Imc {
    /// Sets up a run with a fresh mixture of configuration `student`, initialised from the
    /// run's seed ([`ImcConfig::seed`]; the mixture draws from its own stream, so one seed
    /// determines the whole run). [`Imc::new`] takes a mixture built elsewhere.
    pub fn from_config(
        config: ImcConfig,
        student: MoeConfig,
        data: Dataset,
    ) -> Result<Self, MixtureError> {
        let student = Moe::from_config(student, config.seed)?;
        Self::new(config, student, data)
    }
}

impl<E: Expert> Imc<E> {
    /// As [`Imc::from_config`] with a custom expert family: the mixture is
    /// `Moe::new(student, expert, config.seed)`.
    pub fn with_family(
        config: ImcConfig,
        student: MoeConfig,
        expert: E,
        data: Dataset,
    ) -> Result<Self, MixtureError> {
        let student = Moe::new(student, expert, config.seed)?;
        Self::new(config, student, data)
    }

    /// Sets up a run with uniform curricula and a mixture built elsewhere; checks the configuration, that the data fit the
    /// mixture's dimensions and that the mixture has a learned gating.
    pub fn new(config: ImcConfig, student: Moe<E>, data: Dataset) -> Result<Self, MixtureError> {
        config.validate()?;
        let fit = MixtureFit::new(&fit::loop_settings!(&config), config.seed, student, data)?;
        if !fit.student.has_learned_gating() {
            return Err(CoreError::Config(
                "IMC fits the gating to the curricula: the mixture needs a learned gating".into(),
            )
            .into());
        }
        let (n, z_n) = (fit.data.len(), fit.student.num_experts());
        let mut fit = fit;
        fit.unit_variance = config.variant == ImcVariant::Authors;
        Ok(Self {
            curricula: Curricula::uniform(n, z_n)?,
            log_lik: vec![0.0; n * z_n],
            posterior: vec![0.0; n * z_n],
            marginal: vec![0.0; n],
            per_point: vec![0.0; n * z_n],
            advanced_to: vec![0; n],
            config,
            fit,
        })
    }

    /// Trains a fresh run to the end and returns the fitted mixture.
    pub fn fit(config: ImcConfig, student: Moe<E>, data: Dataset) -> Result<Moe<E>, MixtureError> {
        let mut imc = Self::new(config, student, data)?;
        imc.train(|_| {})?;
        Ok(imc.into_student())
    }

    /// The configuration.
    pub fn config(&self) -> &ImcConfig {
        &self.config
    }

    /// The data being fitted.
    pub fn data(&self) -> &Dataset {
        &self.fit.data
    }

    /// The current curricula.
    pub fn curricula(&self) -> &Curricula {
        &self.curricula
    }

    /// The mixture being trained.
    pub fn student(&self) -> &Moe<E> {
        &self.fit.student
    }

    /// The mixture, mutably (e.g. to evaluate it between iterations).
    pub fn student_mut(&mut self) -> &mut Moe<E> {
        &mut self.fit.student
    }

    /// Ends training and returns the mixture.
    pub fn into_student(self) -> Moe<E> {
        self.fit.student
    }

    /// Mean dataset log-likelihood `(1/N) Σ_o log q(a_o|s_o)` of the current mixture.
    pub fn log_likelihood(&mut self) -> Result<f64, MixtureError> {
        self.fit.evaluate(None, None)
    }

    /// The IMC objective `J` of the current curricula and experts.
    pub fn objective(&mut self) -> Result<f64, MixtureError> {
        self.fit.evaluate(Some(&mut self.log_lik), None)?;
        Ok(self.curricula.objective(&self.log_lik, self.config.eta)?)
    }

    /// Runs the remaining iterations, calling `callback` after each ([`Trainer::run`]).
    pub fn train(&mut self, callback: impl FnMut(&ImcMetrics)) -> Result<(), MixtureError> {
        self.run(callback)
    }
}

/// One iteration per [`Trainer::step`], reported as [`ImcMetrics`]; the output is the fitted
/// mixture.
impl<E: Expert> Trainer for Imc<E> {
    type Report = ImcMetrics;
    type Output = Moe<E>;
    type Error = MixtureError;

    /// One IMC iteration. On error the steps already taken stay applied and the iteration
    /// counter does not advance (a failed curriculum update leaves the curricula unchanged).
    fn step(&mut self) -> Result<ImcMetrics, MixtureError> {
        if self.config.variant == ImcVariant::Authors {
            return self.step_authors();
        }
        let it = self.fit.iteration;
        let (n, z_n) = (self.fit.data.len(), self.fit.student.num_experts());
        let eta = self.config.eta;

        // 1. Every expert's log-likelihood of every point, with the experts frozen.
        let log_likelihood = self.fit.evaluate(Some(&mut self.log_lik), None)?;
        if !log_likelihood.is_finite() || self.log_lik.iter().any(|x| !x.is_finite()) {
            return Err(MixtureError::NonFinite { iteration: it, quantity: "log-likelihood" });
        }
        let objective = self.curricula.objective(&self.log_lik, eta)?;

        // 2. Closed-form curriculum update.
        let lower_bound = self.curricula.update(&self.log_lik, eta)?;
        let mut post = vec![0.0f64; z_n];
        for o in 0..n {
            self.curricula.posterior_into(o, &mut post);
            for z in 0..z_n {
                self.posterior[o * z_n + z] = post[z] as f32;
            }
        }
        self.marginal.clone_from(&self.curricula.data_marginal());
        let curriculum_sampler = RowSampler::weighted(&self.marginal)?;
        let summary = self.curricula.summary(&self.log_lik);

        let settings = fit::loop_settings!(&self.config);
        let (posterior, marginal) = (&self.posterior, &self.marginal);
        // 3. Experts: weighted maximum likelihood of their curricula, on rows o ~ p(o).
        let (expert_loss, expert_lr) =
            self.fit.expert_steps(&settings, Some(&curriculum_sampler), |row, w| {
                // Full batch: p(o, z); minibatch o ~ p(o): p(z|o) / B.
                let scale = if row.full { marginal[row.o] as f32 } else { 1.0 / row.len as f32 };
                for (z, w) in w.iter_mut().enumerate() {
                    *w = posterior[row.o * z_n + z] * scale;
                }
            })?;

        // 4. Gating: soft cross-entropy towards the curricula's posterior p(z|o).
        let use_curriculum = self.config.gating_data == GatingData::Curriculum;
        let sampler = use_curriculum.then_some(&curriculum_sampler);
        let (gating_loss, gating_lr) = self.fit.gating_steps(&settings, sampler, |row, t| {
            t.copy_from_slice(&posterior[row.o * z_n..(row.o + 1) * z_n]);
            if row.full && use_curriculum { marginal[row.o] as f32 } else { 1.0 / row.len as f32 }
        })?;

        self.fit.iteration += 1;
        let measured = Measured { objective, lower_bound, summary, log_likelihood };
        Ok(measured.into_metrics(it, (expert_loss, expert_lr), (gating_loss, gating_lr)))
    }

    fn iteration(&self) -> usize {
        self.fit.iteration
    }

    fn iterations(&self) -> usize {
        self.config.iterations
    }

    fn finish(self) -> Result<Moe<E>, MixtureError> {
        Ok(self.into_student())
    }
}

/// A copy of the mixture as it is now (with the authors' variant, the gating as it is before its final fit).
impl<E: Expert> Snapshot for Imc<E> {
    fn snapshot(&self) -> Result<Moe<E>, MixtureError> {
        Ok(self.fit.student.clone())
    }
}

mod authors;
pub use authors::advance_curriculum;
#[cfg(test)]
mod tests;
