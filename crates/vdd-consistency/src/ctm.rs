//! **Consistency Trajectory Model** distillation (CTM; Kim, Lai, Liao, Murata, Takida,
//! Uesaka, He, Mitsufuji & Ermon, "Consistency Trajectory Models", ICLR 2024) of a
//! variance-exploding (BESO / EDM) teacher, without the GAN term.
//!
//! The student jumps along the teacher's probability-flow ODE from any level `t` to any lower
//! level `u ≤ t` (the paper's `G_θ(x_t, t, s)`; here `s` is the state):
//!
//! `G_θ(x, t, u, s) = (u/t) x + (1 − u/t) g_θ(x, t, u, s)`,
//! `g_θ(x, t, u, s) = c_skip(t) x + c_out(t) F_θ(c_in(t) x, s, c_noise(t), c_noise(u))`
//!
//! with the teacher's EDM preconditioning ([`vdd_diffusion::Preconditioning`]) and the
//! teacher's network embedding both levels ([`DenoiserNet`] with two noise conditions).
//! `G(x, t, t) = x` exactly, and
//! `g(x, t, t)` is a denoiser `D(x; t)`.
//!
//! **Training.** On the Karras grid `σ_max = σ_0 > … > σ_{N−1} = σ_min`, per minibatch: a
//! number of teacher steps `k` uniform in `1..=K` ([`CtmConfig::max_teacher_steps`]); per row
//! a data pair `(s, a)`, a start index `i` uniform in `0..=N−1−k` (`t = σ_i`), the
//! intermediate level `v = σ_{i+k}` and a target index uniform in `i+k..=N−1` (`u ≤ v`), and
//! `x_t = a + t z`. The teacher integrates `x_t` from `t` to `v` with `k` Heun steps on the
//! grid (`x̂`). The loss is
//!
//! `L = 1/(B d) Σ ‖M(G_θ(x_t, t, u)) − M(G_{θ⁻}(x̂, v, u))‖² + λ_DSM L_DSM`:
//!
//! soft consistency matching — the student's jump from `t` against the teacher's `k` steps
//! followed by the target network's jump from `v` — with squared L2, compared at `σ_min`
//! after mapping both estimates with the stop-gradient student `M = G_sg(θ)(·, u, σ_min)` as
//! in the paper ([`CtmMatching::AtBoundary`], the default; the paper maps to `σ = 0` and uses
//! a feature distance for images) or directly at `u` (`M` the identity,
//! [`CtmMatching::AtTarget`]). `θ⁻` is an EMA of `θ`; the gradient flows only through the
//! online network (at the boundary, through the stop-gradient student's input).
//!
//! `L_DSM = 1/(B d) Σ ω(τ) ‖g_θ(x, τ, τ) − a‖²` is denoising score matching of the student's
//! denoiser, `x = a + τ z'`, `τ` drawn from [`CtmConfig::dsm_sigma`] (EDM's log-normal by
//! default), with `ω = 1` as in Kim et al. ([`DsmWeighting::Uniform`]) or EDM's
//! `ω = 1/c_out(τ)²` ([`DsmWeighting::Edm`]), weighted by the constant
//! [`CtmConfig::dsm_weight`] (the paper's adaptive weighting is not used). Both
//! terms go through the online network in one stacked batch. No GAN term (the VDD paper's
//! setting for policies).
//!
//! **Sampling.** One step: `a = G(σ_max ε, σ_max, σ_min)`. `k` steps: deterministic jumps
//! along levels `σ_max = l_0 > … > l_k = σ_min` (CTM's γ-sampling with `γ = 0`).

use faer::reborrow::Reborrow;
use faer::{Mat, MatMut, MatRef};
use rand::Rng as _;
use serde::{Deserialize, Serialize};
use vdd_core::CoreError;
use vdd_diffusion::{BesoConfig, DenoiserNet, Preconditioning, RowCoefficients, SigmaDistribution};
use vdd_nn::Parameters;

use crate::config::ConsistencyConfig;
use crate::error::ConsistencyError;
use crate::network::ensure;
use crate::policy::{DistilledPolicy, Sampling};
use crate::teacher::ConsistencyTeacher;
use crate::trainer::{ConsistencyTrainer, Distillation, LossTerms, Objective};

/// Consistency Trajectory Model distillation of a [`ConsistencyTeacher`] (see the
/// [module docs](self)).
///
/// Distilling a trained BESO teacher (e.g. a [`vdd_diffusion::DiffusionTeacher`]) on the raw
/// demonstrations it was trained on:
///
/// ```
/// use faer::Mat;
/// use vdd_consistency::{CtmConfig, CtmTrainer};
/// use vdd_core::Policy;
/// use vdd_diffusion::{Beso, BesoConfig, DiffusionTeacher, NetConfig, TrainConfig};
///
/// let states = Mat::from_fn(200, 1, |i, _| (i % 10) as f32);
/// let actions = Mat::from_fn(200, 2, |i, _| if i % 2 == 0 { 1.0 } else { -1.0 });
/// let net = NetConfig { hidden_dim: 16, num_blocks: 1, ..Default::default() };
/// let beso = BesoConfig { net, ..Default::default() };
/// let train = TrainConfig { steps: 20, ..Default::default() };
/// let teacher: DiffusionTeacher =
///     Beso::train(&beso, &train, states.as_ref(), actions.as_ref(), 0, &mut |_| {})
///         .unwrap()
///         .into();
///
/// let mut config = CtmConfig::for_teacher(&teacher).with_seed(7);
/// config.base.train.steps = 20; // the default is 3000
/// let mut trainer = CtmTrainer::new(config, teacher, states.as_ref(), actions.as_ref()).unwrap();
/// let mut policy = trainer.train(&mut |p| assert!(p.dsm_loss.is_finite())).unwrap();
/// assert_eq!(policy.act(&[3.0]).unwrap().len(), 2);
/// ```
pub type CtmTrainer<T> = ConsistencyTrainer<T, CtmObjective>;

/// A distilled consistency trajectory model: the jump `G(x, t, u, s)`
/// ([`TrajectoryModel::jump`]) and the denoiser `g(x, t, t, s)` in the teacher's normalised
/// space, and a [`vdd_core::Policy`] (raw observations in, raw actions out) that samples by
/// jumping from `σ_max` to `σ_min` in one or more steps (see [`CtmTrainer`] for an example).
pub type TrajectoryModel = DistilledPolicy<Preconditioning>;

/// Configuration of [`CtmTrainer`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CtmConfig {
    /// The settings CTM shares with consistency distillation (network, levels, sampling,
    /// optimisation). Started from the teacher's network, the second level's embedding is
    /// added with zero input weights: `g = D_teacher` for every `u`, so `G` starts as the
    /// teacher's DDIM (Euler) jump.
    pub base: ConsistencyConfig,
    /// Most teacher Heun steps `K ≥ 1` from `t` to the intermediate level.
    pub max_teacher_steps: usize,
    /// Weight `λ_DSM` of the denoising-score-matching term (0 disables it).
    pub dsm_weight: f32,
    /// Distribution of the DSM noise levels `τ` (truncated to `[σ_min, σ_max]`).
    pub dsm_sigma: SigmaDistribution,
    /// Per-level weight of the DSM term.
    pub dsm_weighting: DsmWeighting,
    /// Where soft consistency matching compares the two estimates of `x_u`.
    pub matching: CtmMatching,
}

/// The per-level weight `ω(τ)` of CTM's denoising-score-matching term
/// `ω(τ) ‖g_θ(x, τ, τ) − a‖²`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum DsmWeighting {
    /// `ω = 1`: the plain denoising error in the action space (Kim et al.'s `L_DSM`).
    Uniform,
    /// `ω = 1/c_out(τ)²`: EDM's weighting, the teacher's own training loss (emphasises small
    /// levels).
    Edm,
}

/// Where soft consistency matching compares the student's jump `G_θ(x_t, t, u)` with the
/// teacher-and-target estimate `G_{θ⁻}(x̂, v, u)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum CtmMatching {
    /// At the target level `u`, directly.
    AtTarget,
    /// At `σ_min`, after mapping both estimates with the stop-gradient student
    /// `G_sg(θ)(·, u, σ_min)` (Kim et al.'s choice: the distance is measured in the data
    /// space; the gradient flows through the stop-gradient student's input only).
    AtBoundary,
}

impl Default for CtmConfig {
    /// [`ConsistencyConfig::default`], up to 3 teacher steps, matching at `σ_min`, `λ_DSM = 1`
    /// with uniform weighting (Kim et al.'s `L_DSM`) and EDM's log-normal
    /// `ln τ ~ N(−1.2, 1.2²)`.
    fn default() -> Self {
        Self {
            base: ConsistencyConfig::default(),
            max_teacher_steps: 3,
            dsm_weight: 1.0,
            dsm_sigma: SigmaDistribution::LogNormal { mean: -1.2, std: 1.2 },
            dsm_weighting: DsmWeighting::Uniform,
            matching: CtmMatching::AtBoundary,
        }
    }
}

impl CtmConfig {
    /// The configuration for distilling a BESO teacher built with `beso`: its architecture
    /// (started from its weights), levels and `ρ` ([`ConsistencyConfig::for_beso`]) and its
    /// training-σ distribution for the DSM term.
    pub fn for_beso(beso: &BesoConfig) -> Self {
        Self {
            base: ConsistencyConfig::for_beso(beso),
            dsm_sigma: beso.training_sigma,
            ..Self::default()
        }
    }

    /// [`CtmConfig::for_beso`] for a teacher that is a BESO teacher (starting from its network
    /// when it exposes one), the defaults otherwise.
    pub fn for_teacher<T: ConsistencyTeacher + ?Sized>(teacher: &T) -> Self {
        Self {
            base: ConsistencyConfig::for_teacher(teacher),
            dsm_sigma: teacher
                .beso_config()
                .map_or(Self::default().dsm_sigma, |b| b.training_sigma),
            ..Self::default()
        }
    }

    /// The same settings with the root seed of every random draw set to `seed`.
    pub fn with_seed(mut self, seed: u64) -> Self {
        self.base.train.seed = seed;
        self
    }

    /// Checks the numbers.
    pub fn validate(&self) -> Result<(), ConsistencyError> {
        self.base.validate()?;
        if self.max_teacher_steps == 0 {
            return Err(CoreError::Config("max_teacher_steps must be >= 1".into()).into());
        }
        if !(self.dsm_weight.is_finite() && self.dsm_weight >= 0.0) {
            return Err(CoreError::Config(format!(
                "dsm_weight must be finite and >= 0, got {}",
                self.dsm_weight
            ))
            .into());
        }
        Ok(self.dsm_sigma.validate()?)
    }
}

/// Appends the coefficients of `G(x, t, u)` per row: `skip = u/t + (1 − u/t) c_skip(t)`,
/// `out = (1 − u/t) c_out(t)`.
fn push_jump(coef: &mut RowCoefficients, pre: &Preconditioning, t: &[f32], u: &[f32]) {
    for (&t, &u) in t.iter().zip(u) {
        let r = u / t;
        let (skip, out) = (r + (1.0 - r) * pre.c_skip(t), (1.0 - r) * pre.c_out(t));
        coef.push(pre.c_in(t), &[pre.c_noise(t), pre.c_noise(u)], skip, out);
    }
}

/// Appends the coefficients of the student's denoiser `g(x, τ, τ) = c_skip(τ) x +
/// c_out(τ) F(c_in(τ) x, s, c_noise(τ), c_noise(τ))` per row.
fn push_denoiser(coef: &mut RowCoefficients, pre: &Preconditioning, tau: &[f32]) {
    for &t in tau {
        coef.push(pre.c_in(t), &[pre.c_noise(t), pre.c_noise(t)], pre.c_skip(t), pre.c_out(t));
    }
}

/// The Consistency Trajectory Model's part of a [`CtmTrainer`] run: the configuration, the
/// preconditioning and the reused buffers (built by [`CtmTrainer::new`]).
///
/// The online network sees one stacked batch: rows `0..n` are the consistency rows
/// `(x_t, t, u)`, rows `n..2n` the DSM rows `(x_τ, τ, τ)` (absent when `λ_DSM = 0`).
#[derive(Debug, Clone)]
pub struct CtmObjective {
    config: CtmConfig,
    pre: Preconditioning,
    start: Vec<usize>,
    t: Vec<f32>,
    mid: Vec<f32>,
    u: Vec<f32>,
    from: Vec<f32>,
    to: Vec<f32>,
    tau: Vec<f32>,
    noise: Mat<f32>,
    x_t: Mat<f32>,
    x_hat: Mat<f32>,
    x_tmp: Mat<f32>,
    x_dsm: Mat<f32>,
    /// `[x_t; x_dsm]`, `[states; states]`, `[G_{θ⁻}(x̂, v, u); DSM target]`.
    stacked_x: Mat<f32>,
    stacked_states: Mat<f32>,
    target: Mat<f32>,
    online_out: Mat<f32>,
    grad: Mat<f32>,
    coef: RowCoefficients,
    /// `ω(τ)` of the DSM rows.
    dsm_row_weight: Vec<f32>,
    /// [`CtmMatching::AtBoundary`]: the stop-gradient copy of the online network (its weights
    /// refreshed at every draw), its coefficients `G(·, u, σ_min)`, its outputs and
    /// output gradients, and a parameter buffer.
    frozen: Option<DenoiserNet>,
    boundary_coef: RowCoefficients,
    sigma_min_rows: Vec<f32>,
    mapped: Mat<f32>,
    mapped_grad: Mat<f32>,
    params: Vec<f32>,
}

impl CtmObjective {
    /// Rows of the stacked batch for `n` pairs.
    fn rows(&self, n: usize) -> usize {
        if self.config.dsm_weight > 0.0 { 2 * n } else { n }
    }
}

impl<T: ConsistencyTeacher> Objective<T> for CtmObjective {
    type Config = CtmConfig;
    type Sampler = Preconditioning;
    const QUANTITY: &'static str = "consistency trajectory loss";
    const POLICY_STREAM: &'static str = "ctm-policy";
    const NOISE_STREAM: &'static str = "ctm-noise";

    fn new(config: CtmConfig) -> Result<Self, ConsistencyError> {
        config.validate()?;
        let z = || Mat::zeros(0, 0);
        Ok(Self {
            pre: Preconditioning::new(config.base.sigma_data).map_err(CoreError::from)?,
            config,
            start: Vec::new(),
            t: Vec::new(),
            mid: Vec::new(),
            u: Vec::new(),
            from: Vec::new(),
            to: Vec::new(),
            tau: Vec::new(),
            noise: z(),
            x_t: z(),
            x_hat: z(),
            x_tmp: z(),
            x_dsm: z(),
            stacked_x: z(),
            stacked_states: z(),
            target: z(),
            online_out: z(),
            grad: z(),
            coef: RowCoefficients::default(),
            dsm_row_weight: Vec::new(),
            frozen: None,
            boundary_coef: RowCoefficients::default(),
            sigma_min_rows: Vec::new(),
            mapped: z(),
            mapped_grad: z(),
            params: Vec::new(),
        })
    }

    fn config(&self) -> &CtmConfig {
        &self.config
    }

    fn base(&self) -> &ConsistencyConfig {
        &self.config.base
    }

    fn sampler(&self) -> Preconditioning {
        self.pre
    }

    /// A minibatch, levels and noise; the teacher from `t` to `v`; the target
    /// `G_{θ⁻}(x̂, v, u)`; the DSM inputs and targets; the stacked online batch.
    fn draw(&mut self, core: &mut Distillation<T>) -> Result<(), ConsistencyError> {
        core.draw_batch();
        let (n, d) = (core.batch.actions.nrows(), core.batch.actions.ncols());
        let ds = core.batch.states.ncols();
        let last = core.grid.len() - 1;
        let k = core.noise_rng.random_range(1..=self.config.max_teacher_steps.min(last));
        for v in [&mut self.t, &mut self.mid, &mut self.u, &mut self.tau] {
            v.clear();
        }
        self.start.clear();
        for _ in 0..n {
            let i = core.noise_rng.random_range(0..=last - k);
            let j = core.noise_rng.random_range(i + k..=last);
            self.start.push(i);
            self.t.push(core.grid[i]);
            self.mid.push(core.grid[i + k]);
            self.u.push(core.grid[j]);
        }
        for _ in 0..n {
            let c = &self.config;
            let tau = c.dsm_sigma.draw(c.base.sigma_min, c.base.sigma_max, &mut core.noise_rng);
            self.tau.push(tau);
        }
        core.perturb(&self.t, &mut self.noise, &mut self.x_t);
        // Teacher: k Heun steps along the grid from t to v.
        ensure(&mut self.x_tmp, n, d);
        ensure(&mut self.x_hat, n, d);
        self.x_hat.copy_from(&self.x_t);
        for step in 0..k {
            self.from.clear();
            self.to.clear();
            for &i in &self.start {
                self.from.push(core.grid[i + step]);
                self.to.push(core.grid[i + step + 1]);
            }
            core.teacher_heun(self.x_hat.as_ref(), &self.from, &self.to, self.x_tmp.as_mut())?;
            std::mem::swap(&mut self.x_hat, &mut self.x_tmp);
        }
        let rows = self.rows(n);
        for (m, c) in [
            (&mut self.stacked_x, d),
            (&mut self.stacked_states, ds),
            (&mut self.target, d),
            (&mut self.online_out, d),
            (&mut self.grad, d),
        ] {
            ensure(m, rows, c);
        }
        self.pre.coefficients(&mut self.coef, &self.mid, &self.u);
        core.target.forward_preconditioned_inference(
            self.x_hat.as_ref(),
            core.batch.states.as_ref(),
            &self.coef,
            self.target.as_mut().subrows_mut(0, n),
        );
        if self.config.matching == CtmMatching::AtBoundary {
            // Map the target to σ_min with the stop-gradient student (θ as of this step).
            let frozen = self.frozen.get_or_insert_with(|| core.online.clone());
            copy_params(&core.online, frozen, &mut self.params);
            self.sigma_min_rows.clear();
            self.sigma_min_rows.resize(n, self.config.base.sigma_min);
            self.pre.coefficients(&mut self.boundary_coef, &self.u, &self.sigma_min_rows);
            ensure(&mut self.mapped, n, d);
            ensure(&mut self.mapped_grad, n, d);
            frozen.forward_preconditioned_inference(
                self.target.as_ref().subrows(0, n),
                core.batch.states.as_ref(),
                &self.boundary_coef,
                self.mapped.as_mut(),
            );
            self.target.as_mut().subrows_mut(0, n).copy_from(self.mapped.as_ref());
        }
        self.stacked_x.as_mut().subrows_mut(0, n).copy_from(self.x_t.as_ref());
        self.stacked_states.as_mut().subrows_mut(0, n).copy_from(core.batch.states.as_ref());
        if rows > n {
            // DSM rows: x = a + τ z', target a, weight ω(τ).
            core.perturb(&self.tau, &mut self.noise, &mut self.x_dsm);
            self.target.as_mut().subrows_mut(n, n).copy_from(core.batch.actions.as_ref());
            self.dsm_row_weight.clear();
            for &tau in &self.tau {
                self.dsm_row_weight.push(match self.config.dsm_weighting {
                    DsmWeighting::Uniform => 1.0,
                    DsmWeighting::Edm => self.pre.c_out(tau).powi(-2),
                });
            }
            self.stacked_x.as_mut().subrows_mut(n, n).copy_from(self.x_dsm.as_ref());
            self.stacked_states.as_mut().subrows_mut(n, n).copy_from(core.batch.states.as_ref());
        }
        // The online batch's coefficients: jumps (t → u), then denoisers at τ.
        self.pre.coefficients(&mut self.coef, &self.t, &self.u);
        if rows > n {
            push_denoiser(&mut self.coef, &self.pre, &self.tau);
        }
        Ok(())
    }

    /// `1/(B d) Σ ‖M(G_θ(x_t, t, u)) − M(G_{θ⁻}(x̂, v, u))‖² + λ_DSM 1/(B d) Σ ‖F_θ − F*‖²`
    /// with `M` the identity ([`CtmMatching::AtTarget`]) or the stop-gradient student's map
    /// `G_sg(·, u, σ_min)` ([`CtmMatching::AtBoundary`]).
    fn loss(&mut self, core: &mut Distillation<T>, backward: bool) -> LossTerms {
        let (rows, d) = (self.stacked_x.nrows(), self.stacked_x.ncols());
        let n = self.t.len();
        let w = self.config.dsm_weight;
        core.online.forward_preconditioned(
            self.stacked_x.as_ref(),
            self.stacked_states.as_ref(),
            &self.coef,
            self.online_out.as_mut(),
        );
        // The compared estimates of the consistency rows.
        let boundary = match &mut self.frozen {
            Some(frozen) if self.config.matching == CtmMatching::AtBoundary => {
                frozen.forward_preconditioned(
                    self.online_out.as_ref().subrows(0, n),
                    core.batch.states.as_ref(),
                    &self.boundary_coef,
                    self.mapped.as_mut(),
                );
                Some(frozen)
            }
            _ => None,
        };
        let compared = if boundary.is_some() { &self.mapped } else { &self.online_out };
        let scale = 1.0 / (n * d) as f32;
        let (mut ctm, mut dsm) = (0.0f64, 0.0f64);
        for j in 0..d {
            let (c, target) = (compared.col_as_slice(j), self.target.col_as_slice(j));
            let out = self.online_out.col_as_slice(j);
            let g = self.grad.col_as_slice_mut(j);
            for i in 0..n {
                let r = c[i] - target[i];
                ctm += f64::from(r * r);
                g[i] = 2.0 * r * scale;
            }
            for i in n..rows {
                let (r, omega) = (out[i] - target[i], self.dsm_row_weight[i - n]);
                dsm += f64::from(omega * r * r);
                g[i] = 2.0 * w * omega * r * scale;
            }
        }
        if backward {
            if let Some(frozen) = boundary {
                // Through the stop-gradient map y = skip x + out F(c_in x): the input gradient
                // ∂L/∂x = skip ∂L/∂y + c_in ∂F/∂x_inᵀ (out ∂L/∂y); its parameters are not
                // trained.
                let bc = &self.boundary_coef;
                for j in 0..d {
                    let (g, mg) = (self.grad.col_as_slice(j), self.mapped_grad.col_as_slice_mut(j));
                    for i in 0..n {
                        mg[i] = bc.c_out[i] * g[i];
                    }
                }
                frozen.zero_grad();
                let gx = frozen.backward(self.mapped_grad.as_ref());
                for j in 0..d {
                    for i in 0..n {
                        self.grad[(i, j)] =
                            bc.c_skip[i] * self.grad[(i, j)] + bc.c_in[i] * gx[(i, j)];
                    }
                }
            }
            // ∂L/∂F = ∂L/∂G · (1 − u/t) c_out(t) for a jump row, ∂L/∂g · c_out(τ) for a DSM row.
            for j in 0..d {
                let g = self.grad.col_as_slice_mut(j);
                for i in 0..rows {
                    g[i] *= self.coef.c_out[i];
                }
            }
            core.online.backward(self.grad.as_ref());
        }
        let (ctm, dsm) = ((ctm * f64::from(scale)) as f32, (dsm * f64::from(scale)) as f32);
        LossTerms { consistency: ctm, dsm, total: ctm + w * dsm }
    }
}

/// Copies the parameter values of `src` into `dst` (same architecture) through `buf`.
fn copy_params(src: &DenoiserNet, dst: &mut DenoiserNet, buf: &mut Vec<f32>) {
    buf.clear();
    src.visit_params("", &mut |_, p| buf.extend_from_slice(&p.value));
    let mut at = 0;
    dst.visit_params_mut("", &mut |_, p| {
        let k = p.value.len();
        p.value.copy_from_slice(&buf[at..at + k]);
        at += k;
    });
}

/// `x = σ_max ε`, then `x ← G(x, l_i, l_{i+1})` along the levels.
impl Sampling for Preconditioning {
    const LEVELS: usize = 2;

    /// The jump `G(·, t, u)` per row.
    fn coefficients(&self, coef: &mut RowCoefficients, t: &[f32], u: &[f32]) {
        coef.clear(2);
        push_jump(coef, self, t, u);
    }

    /// Deterministic jumps: no fresh noise.
    fn fresh_noise_std(&self, _level: f32) -> Option<f32> {
        None
    }
}

impl TrajectoryModel {
    /// The jump `G(x, t, u, s)` for a batch in the normalised space: `x` `n x d_a`, positive
    /// levels `t` and `u ≤ t` (`n` each), `states` `n x d_s`, `out` `n x d_a`.
    pub fn jump(
        &mut self,
        x: MatRef<'_, f32>,
        t: &[f32],
        u: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        self.check_model_batch(x, states, &[t, u], out.rb())?;
        if t.iter().zip(u).any(|(t, u)| u > t) {
            return Err(CoreError::Config("a jump needs u <= t on every row".into()));
        }
        self.forward_with(x, states, out, |pre, coef| pre.coefficients(coef, t, u));
        Ok(())
    }

    /// The student's denoiser `g(x, t, t, s) = c_skip(t) x + c_out(t) F(…)` (what the DSM term
    /// trains), same shapes as [`TrajectoryModel::jump`].
    pub fn denoise(
        &mut self,
        x: MatRef<'_, f32>,
        t: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        self.check_model_batch(x, states, &[t], out.rb())?;
        self.forward_with(x, states, out, |pre, coef| {
            coef.clear(2);
            push_denoiser(coef, pre, t);
        });
        Ok(())
    }
}

#[cfg(test)]
mod tests;
