//! **Consistency Trajectory Model** distillation (CTM; Kim, Lai, Liao, Murata, Takida,
//! Uesaka, He, Mitsufuji & Ermon, "Consistency Trajectory Models", ICLR 2024) of a
//! variance-exploding (BESO / EDM) teacher, without the GAN term.
//!
//! The student jumps along the teacher's probability-flow ODE from any level `t` to any lower
//! level `u ≤ t`:
//!
//! `G_θ(x, t, u, s) = (u/t) x + (1 − u/t) g_θ(x, t, u, s)`,
//! `g_θ(x, t, u, s) = c_skip(t) x + c_out(t) F_θ(c_in(t) x, s, c_noise(t), c_noise(u))`
//!
//! with the teacher's EDM preconditioning ([`vdd_diffusion::Preconditioning`]) and a network
//! that embeds both levels ([`ConditionedNet`] with two levels). `G(x, t, t) = x` exactly, and
//! `g(x, t, t)` is a denoiser `D(x; t)`.
//!
//! **Training.** On the Karras grid `σ_max = σ_0 > … > σ_{N−1} = σ_min`, per minibatch row: a
//! data pair `(s, a)`, a start index `i` uniform in `0..N−1` (`t = σ_i`), an intermediate index
//! `m = i + k` with `k` uniform in `1..=min(K, N−1−i)` (`s_mid = σ_m`, `K =`
//! [`CtmConfig::max_teacher_steps`]), a target index uniform in `m..=N−1` (`u ≤ s_mid`) and
//! `x_t = a + t z`. The teacher integrates `x_t` from `t` to `s_mid` with `k` Heun steps on the
//! grid (`x̂`). The loss is
//!
//! `L = 1/(B d) Σ ‖G_θ(x_t, t, u) − G_{θ⁻}(x̂, s_mid, u)‖² + λ_DSM L_DSM`,
//!
//! soft consistency matching compared directly at level `u` with squared L2 (the paper
//! compares after mapping both sides to `σ = 0` with the stop-gradient student and a feature
//! distance; for low-dimensional actions the direct comparison is the natural choice), where
//! `θ⁻` is an EMA of `θ` and the gradient flows only through the online network. `L_DSM` is
//! the EDM denoising loss of `g(x, τ, τ)` in the preconditioned form
//! `1/(B d) Σ ‖F_θ(c_in x, s, c_noise(τ), c_noise(τ)) − (a − c_skip(τ) x)/c_out(τ)‖²`
//! (`= λ(τ)‖g − a‖²` with EDM's weight `λ = 1/c_out²`), `x = a + τ z'`, `τ` drawn from
//! [`CtmConfig::dsm_sigma`] (EDM's log-normal by default), weighted by
//! [`CtmConfig::dsm_weight`] (default 1; the paper's adaptive weighting is not used). No
//! GAN term (the VDD paper's setting for policies).
//!
//! **Sampling.** One step: `a = G(σ_max ε, σ_max, σ_min)`. `k` steps: deterministic jumps
//! along a `(k+1)`-level Karras grid from `σ_max` to `σ_min` (CTM's γ-sampling with `γ = 0`).

use std::time::Instant;

use faer::reborrow::{Reborrow, ReborrowMut};
use faer::{Mat, MatMut, MatRef};
use rand::{Rng as _, RngCore};
use serde::{Deserialize, Serialize};
use vdd_core::{Affine, CoreError, Policy, Seeds, check_act_args};
use vdd_diffusion::{BesoConfig, NetConfig, Preconditioning, SamplerBuffers, SigmaDistribution};
use vdd_nn::Parameters;

use crate::consistency::{
    self, Coefficients, ConditionedNet, ConsistencyProgress, ConsistencyTeacher,
    ConsistencyTrainConfig, LossMeter, Minibatch, Optimisation, PolicyIo, check_model_batch,
    check_policy_batch, ensure, fill_normal,
};
use crate::dataset::Dataset;
use crate::error::BaselineError;
use crate::fit::RowSampler;

const POLICY_STREAM: &str = "ctm-policy";

/// Configuration of [`CtmTrainer`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct CtmConfig {
    /// Architecture of `F_θ` (the teacher's to start from its weights; the second level's
    /// embedding is added).
    pub net: NetConfig,
    /// Start from the teacher's network (it must have one of the same architecture); the
    /// student then initially ignores `u` and `g = D_teacher`, so `G` is the teacher's DDIM
    /// (Euler) jump. Otherwise fresh weights from the seed's `"init"` stream.
    pub init_from_teacher: bool,
    /// `σ_data` of the preconditioning (normalised action space).
    pub sigma_data: f32,
    /// Smallest level (one-step sampling jumps to it).
    pub sigma_min: f32,
    /// Largest level (sampling starts there).
    pub sigma_max: f32,
    /// The Karras grid's `ρ`.
    pub rho: f32,
    /// Number of grid levels `N`.
    pub num_scales: usize,
    /// Most teacher Heun steps from `t` to the intermediate level `s_mid` (`K ≥ 1`).
    pub max_teacher_steps: usize,
    /// Weight `λ_DSM` of the denoising-score-matching term (0 disables it).
    pub dsm_weight: f32,
    /// Distribution of the DSM noise levels `τ` (truncated to `[σ_min, σ_max]`).
    pub dsm_sigma: SigmaDistribution,
    /// Sampling steps of the returned policy (1: one-step `G(σ_max ε, σ_max, σ_min)`).
    pub sampling_steps: usize,
    /// Optimisation.
    pub train: ConsistencyTrainConfig,
}

impl Default for CtmConfig {
    /// BESO's default levels, `N = 18`, up to 4 teacher steps, `λ_DSM = 1` with EDM's
    /// log-normal `ln τ ~ N(−1.2, 1.2²)`, a fresh student, one-step sampling.
    fn default() -> Self {
        Self {
            net: NetConfig::default(),
            init_from_teacher: false,
            sigma_data: 0.5,
            sigma_min: 0.002,
            sigma_max: 80.0,
            rho: 7.0,
            num_scales: 18,
            max_teacher_steps: 4,
            dsm_weight: 1.0,
            dsm_sigma: SigmaDistribution::LogNormal { mean: -1.2, std: 1.2 },
            sampling_steps: 1,
            train: ConsistencyTrainConfig::default(),
        }
    }
}

impl CtmConfig {
    /// The configuration for distilling a BESO teacher built with `beso`: its architecture
    /// (started from its weights), levels, `ρ` and training-σ distribution for the DSM term.
    pub fn for_beso(beso: &BesoConfig) -> Self {
        Self {
            net: beso.net.clone(),
            init_from_teacher: true,
            sigma_data: beso.sigma_data,
            sigma_min: beso.sigma_min,
            sigma_max: beso.sigma_max,
            rho: beso.rho,
            dsm_sigma: beso.training_sigma,
            ..Self::default()
        }
    }

    /// Checks the numbers.
    pub fn validate(&self) -> Result<(), CoreError> {
        self.net.validate().map_err(CoreError::from)?;
        consistency::validate_levels(
            self.sigma_data,
            self.sigma_min,
            self.sigma_max,
            self.rho,
            self.num_scales,
        )?;
        if self.max_teacher_steps == 0 || self.sampling_steps == 0 {
            return Err(CoreError::Config(
                "max_teacher_steps and sampling_steps must be >= 1".into(),
            ));
        }
        if !(self.dsm_weight.is_finite() && self.dsm_weight >= 0.0) {
            return Err(CoreError::Config(format!(
                "dsm_weight must be finite and >= 0, got {}",
                self.dsm_weight
            )));
        }
        self.dsm_sigma.validate().map_err(CoreError::from)?;
        self.train.validate()
    }
}

/// Fills `coef` for `G(x, t, u)`: `skip = u/t + (1 − u/t) c_skip(t)`,
/// `out = (1 − u/t) c_out(t)`.
fn trajectory_coefficients(coef: &mut Coefficients, pre: &Preconditioning, t: &[f32], u: &[f32]) {
    coef.clear();
    for (&t, &u) in t.iter().zip(u) {
        let r = u / t;
        coef.c_in.push(pre.c_in(t));
        coef.noise.push(pre.c_noise(t));
        coef.noise_to.push(pre.c_noise(u));
        coef.skip.push(r + (1.0 - r) * pre.c_skip(t));
        coef.out.push((1.0 - r) * pre.c_out(t));
    }
}

/// Fills `coef` for the raw network output `F(c_in(τ) x, s, c_noise(τ), c_noise(τ))`.
fn raw_coefficients(coef: &mut Coefficients, pre: &Preconditioning, tau: &[f32]) {
    coef.clear();
    for &t in tau {
        coef.c_in.push(pre.c_in(t));
        coef.noise.push(pre.c_noise(t));
        coef.noise_to.push(pre.c_noise(t));
        coef.skip.push(0.0);
        coef.out.push(1.0);
    }
}

/// Reused buffers of one CTM step.
#[derive(Debug, Clone)]
struct CtmBuffers {
    batch: Minibatch,
    start: Vec<usize>,
    mid: Vec<usize>,
    t: Vec<f32>,
    s_mid: Vec<f32>,
    u: Vec<f32>,
    from: Vec<f32>,
    to: Vec<f32>,
    tau: Vec<f32>,
    noise: Mat<f32>,
    x_t: Mat<f32>,
    x_hat: Mat<f32>,
    x_tmp: Mat<f32>,
    x_dsm: Mat<f32>,
    dsm_target: Mat<f32>,
    target_out: Mat<f32>,
    online_out: Mat<f32>,
    grad: Mat<f32>,
    coef: Coefficients,
    heun: SamplerBuffers,
}

impl Default for CtmBuffers {
    fn default() -> Self {
        let z = || Mat::zeros(0, 0);
        Self {
            batch: Minibatch::default(),
            start: Vec::new(),
            mid: Vec::new(),
            t: Vec::new(),
            s_mid: Vec::new(),
            u: Vec::new(),
            from: Vec::new(),
            to: Vec::new(),
            tau: Vec::new(),
            noise: z(),
            x_t: z(),
            x_hat: z(),
            x_tmp: z(),
            x_dsm: z(),
            dsm_target: z(),
            target_out: z(),
            online_out: z(),
            grad: z(),
            coef: Coefficients::default(),
            heun: SamplerBuffers::default(),
        }
    }
}

/// Consistency Trajectory Model distillation of a [`ConsistencyTeacher`] (see the
/// [module docs](self)).
///
/// ```
/// use faer::{Mat, MatMut, MatRef};
/// use vdd_baselines::consistency::DenoiserFn;
/// use vdd_baselines::ctm::{CtmConfig, CtmTrainer};
/// use vdd_core::{Affine, CoreError, Policy};
/// use vdd_diffusion::NetConfig;
///
/// // Teacher: the exact denoiser of N(0, 0.5²) actions.
/// let teacher = DenoiserFn::new(
///     Affine::identity(1),
///     Affine::identity(1),
///     |x: MatRef<'_, f32>, s: &[f32], _: MatRef<'_, f32>, mut out: MatMut<'_, f32>| {
///         for i in 0..x.nrows() {
///             out[(i, 0)] = 0.25 / (0.25 + s[i] * s[i]) * x[(i, 0)];
///         }
///         Ok::<(), CoreError>(())
///     },
/// );
/// let states = Mat::<f32>::zeros(64, 1);
/// let actions = Mat::from_fn(64, 1, |i, _| 0.5 * ((i as f32) / 32.0 - 1.0));
/// let mut config = CtmConfig::default();
/// config.net = NetConfig { hidden_dim: 16, num_blocks: 1, ..Default::default() };
/// config.train.steps = 20;
/// config.train.batch_size = 16;
/// let mut trainer = CtmTrainer::new(config, teacher, states.as_ref(), actions.as_ref()).unwrap();
/// let mut policy = trainer.train(&mut |_| {}).unwrap();
/// assert!(policy.act(&[0.0]).unwrap()[0].is_finite());
/// ```
pub struct CtmTrainer<T: ConsistencyTeacher> {
    config: CtmConfig,
    teacher: T,
    data: Dataset,
    sampler: RowSampler,
    pre: Preconditioning,
    grid: Vec<f32>,
    online: ConditionedNet,
    target: ConditionedNet,
    opt: Optimisation,
    batch_rng: vdd_core::Rng,
    noise_rng: vdd_core::Rng,
    steps_done: u64,
    buf: CtmBuffers,
}

impl<T: ConsistencyTeacher> std::fmt::Debug for CtmTrainer<T> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("CtmTrainer")
            .field("config", &self.config)
            .field("steps_done", &self.steps_done)
            .field("data_len", &self.data.len())
            .finish_non_exhaustive()
    }
}

/// The two loss terms of one CTM evaluation.
#[derive(Debug, Clone, Copy, PartialEq)]
struct CtmLoss {
    consistency: f32,
    dsm: f32,
    total: f32,
}

impl<T: ConsistencyTeacher> CtmTrainer<T> {
    /// Sets up distillation of `teacher` on raw `states` (`n x d_s`) and `actions`
    /// (`n x d_a`), which are normalised with the teacher's normalisers.
    pub fn new(
        config: CtmConfig,
        teacher: T,
        states: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
    ) -> Result<Self, BaselineError> {
        config.validate()?;
        let data = consistency::normalised_data(&teacher, states, actions)?;
        let online = consistency::initial_network(
            &teacher,
            &config.net,
            config.init_from_teacher,
            2,
            config.train.seed,
        )?;
        let seeds = Seeds::new(config.train.seed);
        Ok(Self {
            pre: Preconditioning::new(config.sigma_data).map_err(CoreError::from)?,
            grid: consistency::karras_levels(
                config.num_scales,
                config.sigma_min,
                config.sigma_max,
                config.rho,
            )?,
            sampler: RowSampler::uniform(data.len())?,
            opt: Optimisation::new(&config.train, &online)?,
            target: online.clone(),
            online,
            data,
            teacher,
            batch_rng: seeds.stream("minibatch"),
            noise_rng: seeds.stream("ctm-noise"),
            steps_done: 0,
            buf: CtmBuffers::default(),
            config,
        })
    }

    /// The configuration.
    pub fn config(&self) -> &CtmConfig {
        &self.config
    }

    /// Optimisation steps taken so far.
    pub fn steps_done(&self) -> u64 {
        self.steps_done
    }

    /// The teacher.
    pub fn teacher(&self) -> &T {
        &self.teacher
    }

    /// The normalised training data.
    pub fn data(&self) -> &Dataset {
        &self.data
    }

    /// The Karras grid `σ_0 = σ_max > … > σ_{N−1} = σ_min`.
    pub fn grid(&self) -> &[f32] {
        &self.grid
    }

    /// The online network `F_θ`.
    pub fn online(&self) -> &ConditionedNet {
        &self.online
    }

    /// Draws a minibatch, levels and noise, runs the teacher from `t` to `s_mid`, evaluates
    /// the target `G_{θ⁻}(x̂, s_mid, u)` and prepares the DSM batch: everything of the loss
    /// that does not depend on `θ`.
    fn draw(&mut self) -> Result<(), BaselineError> {
        let n = self.config.train.batch_size;
        let d = self.data.action_dim();
        let last = self.grid.len() - 1;
        let b = &mut self.buf;
        b.batch.draw(&self.data, &self.sampler, n, &mut self.batch_rng);
        for v in [&mut b.t, &mut b.s_mid, &mut b.u, &mut b.tau] {
            v.clear();
        }
        b.start.clear();
        b.mid.clear();
        let mut max_steps = 0;
        for _ in 0..n {
            let i = self.noise_rng.random_range(0..last);
            let k = self.noise_rng.random_range(1..=self.config.max_teacher_steps.min(last - i));
            let m = i + k;
            let j = self.noise_rng.random_range(m..=last);
            max_steps = max_steps.max(k);
            b.start.push(i);
            b.mid.push(m);
            b.t.push(self.grid[i]);
            b.s_mid.push(self.grid[m]);
            b.u.push(self.grid[j]);
        }
        for _ in 0..n {
            let tau = self.config.dsm_sigma.draw(
                self.config.sigma_min,
                self.config.sigma_max,
                &mut self.noise_rng,
            );
            b.tau.push(tau);
        }
        for m in [
            &mut b.noise,
            &mut b.x_t,
            &mut b.x_hat,
            &mut b.x_tmp,
            &mut b.x_dsm,
            &mut b.dsm_target,
            &mut b.target_out,
            &mut b.online_out,
            &mut b.grad,
        ] {
            ensure(m, n, d);
        }
        fill_normal(&mut b.noise, &mut self.noise_rng);
        for j in 0..d {
            let (a, z) = (b.batch.actions.col_as_slice(j), b.noise.col_as_slice(j));
            let x = b.x_t.col_as_slice_mut(j);
            for i in 0..n {
                x[i] = a[i] + b.t[i] * z[i];
            }
        }
        // Teacher: Heun steps along the grid from t to s_mid (rows already there stay put).
        b.x_hat.copy_from(b.x_t.as_ref());
        for step in 0..max_steps {
            b.from.clear();
            b.to.clear();
            for r in 0..n {
                let (i, m) = (b.start[r], b.mid[r]);
                b.from.push(self.grid[(i + step).min(m)]);
                b.to.push(self.grid[(i + step + 1).min(m)]);
            }
            consistency::teacher_heun_step(
                &mut self.teacher,
                b.x_hat.as_ref(),
                &b.from,
                &b.to,
                b.batch.states.as_ref(),
                b.x_tmp.as_mut(),
                &mut b.heun,
            )?;
            std::mem::swap(&mut b.x_hat, &mut b.x_tmp);
        }
        trajectory_coefficients(&mut b.coef, &self.pre, &b.s_mid, &b.u);
        self.target.forward_preconditioned(
            b.x_hat.as_ref(),
            b.batch.states.as_ref(),
            &b.coef,
            b.target_out.as_mut(),
        );
        // DSM batch: x = a + τ z', target (a − c_skip x)/c_out.
        fill_normal(&mut b.noise, &mut self.noise_rng);
        for j in 0..d {
            let (a, z) = (b.batch.actions.col_as_slice(j), b.noise.col_as_slice(j));
            for i in 0..n {
                let tau = b.tau[i];
                let x = a[i] + tau * z[i];
                b.x_dsm[(i, j)] = x;
                b.dsm_target[(i, j)] = (a[i] - self.pre.c_skip(tau) * x) / self.pre.c_out(tau);
            }
        }
        Ok(())
    }

    /// The loss of the drawn batch and, with `backward`, its gradient accumulated into the
    /// online network's parameters.
    fn online_loss(&mut self, backward: bool) -> CtmLoss {
        let b = &mut self.buf;
        let (n, d) = (b.x_t.nrows(), b.x_t.ncols());
        let scale = 1.0 / (n * d) as f32;
        // Soft consistency matching at level u.
        trajectory_coefficients(&mut b.coef, &self.pre, &b.t, &b.u);
        self.online.forward_preconditioned(
            b.x_t.as_ref(),
            b.batch.states.as_ref(),
            &b.coef,
            b.online_out.as_mut(),
        );
        let mut ctm = 0.0f64;
        for j in 0..d {
            let (g_out, t_out) = (b.online_out.col_as_slice(j), b.target_out.col_as_slice(j));
            let g = b.grad.col_as_slice_mut(j);
            for i in 0..n {
                let r = g_out[i] - t_out[i];
                ctm += f64::from(r * r);
                // ∂L/∂F = ∂L/∂G · (1 − u/t) c_out(t).
                g[i] = 2.0 * r * scale * b.coef.out[i];
            }
        }
        if backward {
            self.online.backward(b.grad.as_ref());
        }
        let ctm = (ctm * f64::from(scale)) as f32;
        // Denoising score matching on g(x, τ, τ), in the preconditioned form.
        let w = self.config.dsm_weight;
        let mut dsm = 0.0f64;
        if w > 0.0 {
            raw_coefficients(&mut b.coef, &self.pre, &b.tau);
            self.online.forward_preconditioned(
                b.x_dsm.as_ref(),
                b.batch.states.as_ref(),
                &b.coef,
                b.online_out.as_mut(),
            );
            for j in 0..d {
                let (f, target) = (b.online_out.col_as_slice(j), b.dsm_target.col_as_slice(j));
                let g = b.grad.col_as_slice_mut(j);
                for i in 0..n {
                    let r = f[i] - target[i];
                    dsm += f64::from(r * r);
                    g[i] = 2.0 * w * r * scale;
                }
            }
            if backward {
                self.online.backward(b.grad.as_ref());
            }
        }
        let dsm = (dsm * f64::from(scale)) as f32;
        CtmLoss { consistency: ctm, dsm, total: ctm + w * dsm }
    }

    /// One optimisation step; returns the total loss before the update. Nothing is updated
    /// when the loss or a gradient is not finite.
    pub fn step(&mut self) -> Result<f32, BaselineError> {
        self.step_with_lr().map(|(loss, _)| loss.total)
    }

    fn step_with_lr(&mut self) -> Result<(CtmLoss, f32), BaselineError> {
        self.draw()?;
        self.online.zero_grad();
        let loss = self.online_loss(true);
        if !loss.total.is_finite() {
            return Err(BaselineError::NonFinite {
                iteration: self.steps_done as usize,
                quantity: "consistency trajectory loss",
            });
        }
        let lr = self.opt.apply(&mut self.online, &mut self.target, self.steps_done)?;
        self.steps_done += 1;
        Ok((loss, lr))
    }

    /// Runs the remaining configured steps, calling `progress` every `log_every` steps and after
    /// the last, and returns the distilled policy (evaluation-averaged weights).
    pub fn train(
        &mut self,
        progress: &mut dyn FnMut(&ConsistencyProgress),
    ) -> Result<TrajectoryModel, BaselineError> {
        let start = Instant::now();
        let total = self.config.train.steps;
        let mut meter = LossMeter::default();
        while self.steps_done < total {
            let (loss, lr) = self.step_with_lr()?;
            meter.add(loss.consistency, loss.dsm, loss.total);
            let done = self.steps_done;
            if done % self.config.train.log_every == 0 || done == total {
                progress(&meter.report(done, total, lr, start.elapsed().as_secs_f64()));
            }
        }
        self.model()
    }

    /// The current student as a policy (evaluation-averaged weights, the configured sampling
    /// steps, the teacher's normalisers, policy stream seeded with the training seed).
    pub fn model(&self) -> Result<TrajectoryModel, BaselineError> {
        let (sn, an) = self.teacher.normalizers();
        let c = &self.config;
        TrajectoryModel::new(
            self.opt.averaged(&self.online)?,
            self.pre,
            c.sigma_min,
            c.sigma_max,
            c.rho,
            c.sampling_steps,
            sn.clone(),
            an.clone(),
            c.train.seed,
        )
    }
}

/// A distilled consistency trajectory model: the jump `G(x, t, u, s)` in the teacher's
/// normalised space, and a [`Policy`] (raw observations in, raw actions out) that samples by
/// jumping from `σ_max` to `σ_min` in one or more steps.
#[derive(Debug, Clone)]
pub struct TrajectoryModel {
    net: ConditionedNet,
    pre: Preconditioning,
    sigma_min: f32,
    sigma_max: f32,
    rho: f32,
    /// `σ_max = l_0 > … > l_k = σ_min`: sampling jumps between consecutive levels.
    levels: Vec<f32>,
    state_norm: Affine,
    action_norm: Affine,
    rng: vdd_core::Rng,
    io: PolicyIo,
    scratch: JumpScratch,
}

#[derive(Debug, Clone)]
struct JumpScratch {
    x: Mat<f32>,
    t: Vec<f32>,
    u: Vec<f32>,
    coef: Coefficients,
}

impl Default for JumpScratch {
    fn default() -> Self {
        Self { x: Mat::zeros(0, 0), t: Vec::new(), u: Vec::new(), coef: Coefficients::default() }
    }
}

impl TrajectoryModel {
    /// Assembles a model from a two-level network and its settings.
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        net: ConditionedNet,
        pre: Preconditioning,
        sigma_min: f32,
        sigma_max: f32,
        rho: f32,
        sampling_steps: usize,
        state_norm: Affine,
        action_norm: Affine,
        seed: u64,
    ) -> Result<Self, BaselineError> {
        if net.levels() != 2 {
            return Err(
                CoreError::Config("a trajectory model takes two noise levels".into()).into()
            );
        }
        vdd_core::check_len("state normaliser", state_norm.dim(), net.state_dim())?;
        vdd_core::check_len("action normaliser", action_norm.dim(), net.action_dim())?;
        consistency::validate_levels(pre.sigma_data, sigma_min, sigma_max, rho, 2)?;
        let mut model = Self {
            net,
            pre,
            sigma_min,
            sigma_max,
            rho,
            levels: Vec::new(),
            state_norm,
            action_norm,
            rng: Seeds::new(seed).stream(POLICY_STREAM),
            io: PolicyIo::default(),
            scratch: JumpScratch::default(),
        };
        model.set_sampling_steps(sampling_steps)?;
        Ok(model)
    }

    /// The network `F`.
    pub fn net(&self) -> &ConditionedNet {
        &self.net
    }

    /// The EDM preconditioning of `g`.
    pub fn preconditioning(&self) -> Preconditioning {
        self.pre
    }

    /// The `(state, action)` normalisers (the teacher's).
    pub fn normalizers(&self) -> (&Affine, &Affine) {
        (&self.state_norm, &self.action_norm)
    }

    /// Number of sampling jumps (network evaluations per action).
    pub fn sampling_steps(&self) -> usize {
        self.levels.len() - 1
    }

    /// The levels sampling jumps between, `σ_max` first and `σ_min` last.
    pub fn sampling_levels(&self) -> &[f32] {
        &self.levels
    }

    /// Sets the number of jumps `k ≥ 1` along a `(k + 1)`-level Karras grid from `σ_max` to
    /// `σ_min`.
    pub fn set_sampling_steps(&mut self, steps: usize) -> Result<(), BaselineError> {
        if steps == 0 {
            return Err(CoreError::Config("sampling steps must be >= 1".into()).into());
        }
        self.levels =
            consistency::karras_levels(steps + 1, self.sigma_min, self.sigma_max, self.rho)?;
        Ok(())
    }

    /// The jump `G(x, t, u, s)` for a batch in the normalised space: `x` `n x d_a`, positive
    /// levels `t` and `u ≤ t` (`n` each), `states` `n x d_s`, `out` `n x d_a`.
    pub fn jump(
        &mut self,
        x: MatRef<'_, f32>,
        t: &[f32],
        u: &[f32],
        states: MatRef<'_, f32>,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let (da, ds) = (self.net.action_dim(), self.net.state_dim());
        check_model_batch(x, states, &[t, u], out.rb(), da, ds)?;
        if t.iter().zip(u).any(|(t, u)| u > t) {
            return Err(CoreError::Config("a jump needs u <= t on every row".into()));
        }
        trajectory_coefficients(&mut self.scratch.coef, &self.pre, t, u);
        self.net.forward_preconditioned(x, states, &self.scratch.coef, out.as_mut());
        Ok(())
    }

    /// The student's denoiser `g(x, t, t, s)` (the output the DSM term trains).
    pub fn denoise(
        &mut self,
        x: MatRef<'_, f32>,
        t: &[f32],
        states: MatRef<'_, f32>,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let (da, ds) = (self.net.action_dim(), self.net.state_dim());
        check_model_batch(x, states, &[t], out.rb(), da, ds)?;
        let c = &mut self.scratch.coef;
        c.clear();
        for &s in t {
            c.c_in.push(self.pre.c_in(s));
            c.noise.push(self.pre.c_noise(s));
            c.noise_to.push(self.pre.c_noise(s));
            c.skip.push(self.pre.c_skip(s));
            c.out.push(self.pre.c_out(s));
        }
        self.net.forward_preconditioned(x, states, c, out.as_mut());
        Ok(())
    }

    /// Samples one action per row of normalised `states` into `out` (normalised space) with
    /// the configured jumps, drawing the initial noise from `rng`.
    pub fn sample(
        &mut self,
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let n = states.nrows();
        vdd_core::check_shape("states", states, n, self.net.state_dim())?;
        vdd_core::check_finite("states", states)?;
        vdd_core::check_shape("sampled actions", out.rb(), n, self.net.action_dim())?;
        let Self { net, pre, levels, scratch, .. } = self;
        jump_chain(net, pre, levels, scratch, states, rng, out.as_mut());
        Ok(())
    }
}

/// `x = σ_max ε`, then `x ← G(x, l_i, l_{i+1})` along `levels`, result in `out`.
fn jump_chain(
    net: &mut ConditionedNet,
    pre: &Preconditioning,
    levels: &[f32],
    scratch: &mut JumpScratch,
    states: MatRef<'_, f32>,
    rng: &mut dyn RngCore,
    mut out: MatMut<'_, f32>,
) {
    let (n, d) = (out.nrows(), out.ncols());
    ensure(&mut scratch.x, n, d);
    let s0 = levels[0];
    for j in 0..d {
        for v in scratch.x.col_as_slice_mut(j) {
            *v = s0 * vdd_core::standard_normal(rng);
        }
    }
    for (k, w) in levels.windows(2).enumerate() {
        if k > 0 {
            scratch.x.copy_from(out.rb());
        }
        scratch.t.clear();
        scratch.t.resize(n, w[0]);
        scratch.u.clear();
        scratch.u.resize(n, w[1]);
        trajectory_coefficients(&mut scratch.coef, pre, &scratch.t, &scratch.u);
        net.forward_preconditioned(scratch.x.as_ref(), states, &scratch.coef, out.rb_mut());
    }
}

impl Policy for TrajectoryModel {
    fn obs_dim(&self) -> usize {
        self.state_norm.dim()
    }

    fn action_dim(&self) -> usize {
        self.action_norm.dim()
    }

    fn seed(&mut self, seed: u64) {
        self.rng = Seeds::new(seed).stream(POLICY_STREAM);
    }

    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> Result<(), CoreError> {
        check_act_args(self, obs, action)?;
        let (ds, da) = (self.obs_dim(), self.action_dim());
        self.act_batch(
            MatRef::from_row_major_slice(obs, 1, ds),
            MatMut::from_row_major_slice_mut(action, 1, da),
        )
    }

    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        actions: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let (ds, da) = (self.obs_dim(), self.action_dim());
        check_policy_batch(obs, actions.rb(), ds, da)?;
        self.io.load(obs, &self.state_norm, da);
        let Self { net, pre, levels, scratch, io, rng, .. } = self;
        jump_chain(net, pre, levels, scratch, io.obs.as_ref(), rng, io.act.as_mut());
        self.io.store(&self.action_norm, actions);
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_consistency::{FOUR_MODES, four_mode_teacher, near_mode_fraction};
    use vdd_diffusion::Beso;

    fn tiny_config() -> CtmConfig {
        let mut c = CtmConfig {
            net: NetConfig { hidden_dim: 6, num_blocks: 1, embed_dim: 4, ..Default::default() },
            num_scales: 6,
            max_teacher_steps: 3,
            sigma_max: 10.0,
            ..Default::default()
        };
        c.train.batch_size = 5;
        c
    }

    fn toy_data(n: usize, seed: u64) -> (Mat<f32>, Mat<f32>) {
        let mut rng = Seeds::new(seed).stream("data");
        let actions = Mat::from_fn(n, 2, |_, _| rng.random_range(-1.5f32..1.5));
        (Mat::zeros(n, 1), actions)
    }

    #[test]
    fn jump_to_the_same_level_is_the_identity() {
        let (s, a) = toy_data(16, 0);
        let mut t =
            CtmTrainer::new(tiny_config(), four_mode_teacher(), s.as_ref(), a.as_ref()).unwrap();
        for _ in 0..3 {
            t.step().unwrap();
        }
        let mut model = t.model().unwrap();
        let x = Mat::from_fn(6, 2, |i, j| 2.0 * (i as f32 - 2.5) - 0.3 * j as f32);
        let states = Mat::from_fn(6, 1, |i, _| i as f32);
        let levels = [0.002f32, 0.01, 0.3, 1.0, 7.0, 80.0];
        let mut out = Mat::zeros(6, 2);
        model.jump(x.as_ref(), &levels, &levels, states.as_ref(), out.as_mut()).unwrap();
        assert_eq!(out, x, "G(x, t, t) must be exactly x");
        let lower = levels.map(|l| 0.5 * l);
        model.jump(x.as_ref(), &levels, &lower, states.as_ref(), out.as_mut()).unwrap();
        assert_ne!(out, x);
        // u > t is rejected.
        assert!(model.jump(x.as_ref(), &lower, &levels, states.as_ref(), out.as_mut()).is_err());
    }

    /// The analytic gradient of the CTM loss (consistency and DSM terms) matches central
    /// finite differences.
    #[test]
    fn ctm_loss_gradient_matches_finite_differences() {
        let (s, a) = toy_data(16, 1);
        let mut c = tiny_config();
        c.dsm_weight = 0.7;
        let mut t = CtmTrainer::new(c, four_mode_teacher(), s.as_ref(), a.as_ref()).unwrap();
        for _ in 0..5 {
            t.step().unwrap();
        }
        t.draw().unwrap();
        t.online.zero_grad();
        let loss0 = t.online_loss(true);
        assert!(loss0.consistency > 1e-5 && loss0.dsm > 1e-3, "{loss0:?}");
        let mut analytic = Vec::new();
        t.online.visit_params("", &mut |_, p| analytic.push(p.grad.clone()));
        let h = 3e-3f32;
        let mut worst = 0.0f64;
        for (pi, grads) in analytic.iter().enumerate() {
            for (e, &g) in grads.iter().enumerate() {
                let set = |t: &mut CtmTrainer<_>, delta: f32| {
                    let mut k = 0;
                    t.online.visit_params_mut("", &mut |_, p| {
                        if k == pi {
                            p.value[e] += delta;
                        }
                        k += 1;
                    });
                };
                set(&mut t, h);
                let up = f64::from(t.online_loss(false).total);
                set(&mut t, -2.0 * h);
                let down = f64::from(t.online_loss(false).total);
                set(&mut t, h);
                let fd = (up - down) / (2.0 * f64::from(h));
                worst = worst.max((fd - f64::from(g)).abs() / fd.abs().max(1e-2));
            }
        }
        assert!(worst < 2e-2, "worst relative gradient error {worst}");
    }

    /// Started from a BESO teacher, `G(x, t, u)` is the teacher's DDIM jump
    /// `(u/t) x + (1 − u/t) D(x; t)` for every `u`.
    #[test]
    fn student_from_a_beso_teacher_starts_as_its_ddim_jump() {
        let net = NetConfig { hidden_dim: 8, num_blocks: 1, ..Default::default() };
        let bc = BesoConfig { net, ..Default::default() };
        let mut beso = Beso::new(&bc, Affine::identity(1), Affine::identity(2), 0).unwrap();
        let (s, a) = toy_data(16, 3);
        let mut c = CtmConfig::for_beso(&bc);
        c.train.batch_size = 4;
        let mut model =
            CtmTrainer::new(c.clone(), &mut beso, s.as_ref(), a.as_ref()).unwrap().model().unwrap();
        let x = Mat::from_fn(3, 2, |i, j| i as f32 - j as f32);
        let st = Mat::<f32>::zeros(3, 1);
        let (t, u) = ([5.0f32, 1.0, 0.3], [0.002f32, 0.5, 0.3]);
        let (mut g, mut dn) = (Mat::zeros(3, 2), Mat::zeros(3, 2));
        model.jump(x.as_ref(), &t, &u, st.as_ref(), g.as_mut()).unwrap();
        beso.denoise(x.as_ref(), &t, st.as_ref(), dn.as_mut()).unwrap();
        for i in 0..3 {
            let r = u[i] / t[i];
            for j in 0..2 {
                let want = r * x[(i, j)] + (1.0 - r) * dn[(i, j)];
                assert!((g[(i, j)] - want).abs() < 1e-5, "{g:?} vs {want}");
            }
        }
        model.set_sampling_steps(3).unwrap();
        assert_eq!(model.sampling_levels().len(), 4);
        assert!(model.act(&[0.0]).unwrap().iter().all(|v| v.is_finite()));
        let mut other = c;
        other.net.embed_dim = 8;
        assert!(CtmTrainer::new(other, &mut beso, s.as_ref(), a.as_ref()).is_err());
    }

    /// A CTM student of the exact four-mode denoiser puts its one-step samples on the modes.
    #[test]
    fn ctm_student_of_an_exact_gmm_teacher_samples_near_the_modes() {
        let mut rng = Seeds::new(5).stream("data");
        let n = 2000;
        let labels: Vec<usize> = (0..n).map(|_| rng.random_range(0..4)).collect();
        let actions = Mat::from_fn(n, 2, |i, j| {
            FOUR_MODES[labels[i]][j] + 0.1 * vdd_core::standard_normal(&mut rng)
        });
        let states = Mat::<f32>::zeros(n, 1);
        let mut config = CtmConfig {
            net: NetConfig { hidden_dim: 32, num_blocks: 1, ..Default::default() },
            num_scales: 10,
            sigma_max: 20.0,
            ..Default::default()
        };
        config.train.steps = 1000;
        config.train.batch_size = 128;
        config.train.adam.lr = 1e-2;
        config.train.lr_schedule =
            vdd_nn::LrSchedule::Cosine { total_steps: 1000, final_factor: 0.05 };
        config.train.target_ema_decay = 0.9;
        config.train.ema_decay = 0.9;
        config.train.seed = 2;
        let mut t = CtmTrainer::new(config, four_mode_teacher(), states.as_ref(), actions.as_ref())
            .unwrap();
        let obs = Mat::<f32>::zeros(1000, 1);
        let mut out = Mat::zeros(1000, 2);
        // Untrained, the one-step samples are spread out: the test discriminates.
        t.model().unwrap().act_batch(obs.as_ref(), out.as_mut()).unwrap();
        let (near_untrained, _) = near_mode_fraction(out.as_ref(), 0.3);
        assert!(near_untrained < 0.3, "untrained: {near_untrained}");
        let mut model = t.train(&mut |_| {}).unwrap();
        model.act_batch(obs.as_ref(), out.as_mut()).unwrap();
        let (near, per_mode) = near_mode_fraction(out.as_ref(), 0.3);
        assert!(near > 0.5, "only {near} of the samples within 0.3 of a mode");
        assert!(per_mode.iter().all(|&f| f > 0.15), "mode fractions {per_mode:?}");
    }

    #[test]
    fn training_is_deterministic_for_a_seed() {
        let (s, a) = toy_data(32, 2);
        let run = |seed: u64| {
            let mut c = tiny_config();
            c.train.steps = 5;
            c.train.seed = seed;
            let mut t = CtmTrainer::new(c, four_mode_teacher(), s.as_ref(), a.as_ref()).unwrap();
            let mut reports = Vec::new();
            let mut m = t.train(&mut |p| reports.push((p.loss, p.dsm_loss))).unwrap();
            (reports, m.act(&[0.0]).unwrap())
        };
        assert_eq!(run(7), run(7));
        assert_ne!(run(7).1, run(8).1);
    }

    #[test]
    fn bad_configs_are_errors() {
        let (s, a) = toy_data(8, 0);
        for c in [
            CtmConfig { max_teacher_steps: 0, ..tiny_config() },
            CtmConfig { dsm_weight: -1.0, ..tiny_config() },
            CtmConfig { num_scales: 1, ..tiny_config() },
            CtmConfig { init_from_teacher: true, ..tiny_config() },
        ] {
            assert!(CtmTrainer::new(c, four_mode_teacher(), s.as_ref(), a.as_ref()).is_err());
        }
        let mut m = CtmTrainer::new(tiny_config(), four_mode_teacher(), s.as_ref(), a.as_ref())
            .unwrap()
            .model()
            .unwrap();
        assert!(m.act(&[1.0, 2.0]).is_err());
        assert!(m.set_sampling_steps(0).is_err());
    }
}
