//! **Consistency Distillation** (CD; Song, Dhariwal, Chen & Sutskever, "Consistency Models",
//! ICML 2023) of a variance-exploding (BESO / EDM) teacher.
//!
//! The student is a consistency function `f_θ(x, σ, s)` that maps any point of a teacher
//! probability-flow ODE trajectory at level `σ` to the trajectory's end at `σ_min`:
//!
//! `f_θ(x, σ, s) = c_skip(σ) x + c_out(σ) F_θ(c_in(σ) x, s, c_noise(σ))`
//!
//! with the boundary preconditioning of [`BoundaryPreconditioning`] (`c_skip(σ_min) = 1`,
//! `c_out(σ_min) = 0`, so `f_θ(x, σ_min, s) = x` exactly).
//!
//! **Training** (Song et al., Algorithm 2). On the Karras grid `σ_max = σ_0 > … > σ_{N−1} =
//! σ_min` ([`CdConfig::num_scales`] `= N`), per minibatch row: a data pair `(s, a)`, an index
//! `n` uniform in `0..N−1` and `z ~ N(0, I)`; `x = a + σ_n z`; one Heun step of the teacher's
//! probability-flow ODE from `σ_n` to `σ_{n+1}` gives `x̂`; the loss is
//!
//! `L(θ) = 1/(B d) Σ_rows ‖ f_θ(x, σ_n, s) − f_{θ⁻}(x̂, σ_{n+1}, s) ‖²`
//!
//! (squared L2 — the paper's `d` for low-dimensional actions — and uniform weighting
//! `λ(σ) = 1`). The target parameters `θ⁻` are an exponential moving average of `θ`
//! ([`ConsistencyTrainConfig::target_ema_decay`](crate::ConsistencyTrainConfig::target_ema_decay),
//! `θ⁻ ← μ θ⁻ + (1 − μ) θ` after every Adam step); the gradient flows only through the online
//! network (explicit backward of `F_θ`, scaled by `c_out(σ_n)`). The student starts from the
//! teacher's weights when [`CdConfig::init_from_teacher`] is set (the paper's choice; the
//! architectures must match), otherwise from a fresh network.
//!
//! **Sampling** (Song et al., Algorithm 1) along levels `σ_max = l_0 > … > l_k = σ_min`
//! ([`ConsistencyModel::set_sampling_steps`]): `a = f(σ_max ε, σ_max, s)`, then for
//! `i = 1..k−1`: `x = a + sqrt(l_i² − σ_min²) z`, `a = f(x, l_i, s)` — one network evaluation per
//! step.

use faer::reborrow::Reborrow;
use faer::{Mat, MatMut, MatRef};
use rand::Rng as _;
use vdd_core::CoreError;

use vdd_diffusion::RowCoefficients;

use crate::config::ConsistencyConfig;
use crate::error::ConsistencyError;
use crate::network::{BoundaryPreconditioning, ensure};
use crate::policy::{DistilledPolicy, Sampling};
use crate::teacher::ConsistencyTeacher;
use crate::trainer::{ConsistencyTrainer, Distillation, LossTerms, Objective};

/// Configuration of [`CdTrainer`]: the shared consistency settings, all of which CD uses.
pub type CdConfig = ConsistencyConfig;

/// Consistency Distillation of a [`ConsistencyTeacher`] (see the [module docs](self)).
///
/// Distilling a trained BESO teacher (e.g. a [`vdd_diffusion::DiffusionTeacher`]) on the raw
/// demonstrations it was trained on takes a few lines:
///
/// ```
/// use faer::Mat;
/// use vdd_consistency::{CdConfig, CdTrainer};
/// use vdd_core::Policy;
/// use vdd_diffusion::{Beso, BesoConfig, DiffusionTeacher, NetConfig, TrainConfig};
///
/// // Raw demonstrations: 1-D states, 2-D actions ±(1, 1).
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
/// let mut config = CdConfig::for_teacher(&teacher).with_seed(7);
/// config.train.steps = 20; // the default is 3000
/// let mut trainer = CdTrainer::new(config, teacher, states.as_ref(), actions.as_ref()).unwrap();
/// let mut policy = trainer.train(&mut |p| assert!(p.loss.is_finite())).unwrap();
/// assert_eq!(policy.act(&[3.0]).unwrap().len(), 2);
/// ```
pub type CdTrainer<T> = ConsistencyTrainer<T, CdObjective>;

/// A distilled consistency model: the consistency function `f(x, σ, s)` in the teacher's
/// normalised space ([`ConsistencyModel::consistency_fn`]), and a [`vdd_core::Policy`] (raw
/// observations in, raw actions out) that samples with one or more consistency steps (see
/// [`CdTrainer`] for an example).
pub type ConsistencyModel = DistilledPolicy<BoundaryPreconditioning>;

/// Consistency Distillation's part of a [`CdTrainer`] run: the configuration, the
/// preconditioning and the reused buffers of one step (built by [`CdTrainer::new`]).
#[derive(Debug, Clone)]
pub struct CdObjective {
    config: CdConfig,
    pre: BoundaryPreconditioning,
    sigma_hi: Vec<f32>,
    sigma_lo: Vec<f32>,
    noise: Mat<f32>,
    x_hi: Mat<f32>,
    x_lo: Mat<f32>,
    target_out: Mat<f32>,
    online_out: Mat<f32>,
    grad: Mat<f32>,
    coef: RowCoefficients,
}

impl<T: ConsistencyTeacher> Objective<T> for CdObjective {
    type Config = CdConfig;
    type Sampler = BoundaryPreconditioning;
    const QUANTITY: &'static str = "consistency distillation loss";
    const POLICY_STREAM: &'static str = "cd-policy";
    const NOISE_STREAM: &'static str = "cd-noise";

    fn new(config: CdConfig) -> Result<Self, ConsistencyError> {
        config.validate()?;
        Ok(Self {
            pre: BoundaryPreconditioning::new(config.sigma_data, config.sigma_min)?,
            config,
            sigma_hi: Vec::new(),
            sigma_lo: Vec::new(),
            noise: Mat::zeros(0, 0),
            x_hi: Mat::zeros(0, 0),
            x_lo: Mat::zeros(0, 0),
            target_out: Mat::zeros(0, 0),
            online_out: Mat::zeros(0, 0),
            grad: Mat::zeros(0, 0),
            coef: RowCoefficients::default(),
        })
    }

    fn config(&self) -> &CdConfig {
        &self.config
    }

    fn base(&self) -> &ConsistencyConfig {
        &self.config
    }

    fn sampler(&self) -> BoundaryPreconditioning {
        self.pre
    }

    /// A minibatch, grid indices and noise, the teacher's Heun step and the target
    /// `f_{θ⁻}(x̂, σ_{n+1})`.
    fn draw(&mut self, core: &mut Distillation<T>) -> Result<(), ConsistencyError> {
        core.draw_batch();
        let (n, d) = (core.batch.actions.nrows(), core.batch.actions.ncols());
        self.sigma_hi.clear();
        self.sigma_lo.clear();
        let last = core.grid.len() - 1;
        for _ in 0..n {
            let k = core.noise_rng.random_range(0..last);
            self.sigma_hi.push(core.grid[k]);
            self.sigma_lo.push(core.grid[k + 1]);
        }
        core.perturb(&self.sigma_hi, &mut self.noise, &mut self.x_hi);
        for m in [&mut self.x_lo, &mut self.target_out, &mut self.online_out, &mut self.grad] {
            ensure(m, n, d);
        }
        core.teacher_heun(self.x_hi.as_ref(), &self.sigma_hi, &self.sigma_lo, self.x_lo.as_mut())?;
        self.pre.coefficients(&mut self.coef, &self.sigma_lo, &self.sigma_lo);
        core.target.forward_preconditioned_inference(
            self.x_lo.as_ref(),
            core.batch.states.as_ref(),
            &self.coef,
            self.target_out.as_mut(),
        );
        Ok(())
    }

    /// `1/(B d) Σ ‖f_θ(x, σ_n) − target‖²`.
    fn loss(&mut self, core: &mut Distillation<T>, backward: bool) -> LossTerms {
        let (n, d) = (self.x_hi.nrows(), self.x_hi.ncols());
        self.pre.coefficients(&mut self.coef, &self.sigma_hi, &self.sigma_hi);
        core.online.forward_preconditioned(
            self.x_hi.as_ref(),
            core.batch.states.as_ref(),
            &self.coef,
            self.online_out.as_mut(),
        );
        let scale = 1.0 / (n * d) as f32;
        let mut total = 0.0f64;
        for j in 0..d {
            let (f, t) = (self.online_out.col_as_slice(j), self.target_out.col_as_slice(j));
            let g = self.grad.col_as_slice_mut(j);
            for i in 0..n {
                let r = f[i] - t[i];
                total += f64::from(r * r);
                // ∂L/∂F = ∂L/∂f · c_out(σ_n).
                g[i] = 2.0 * r * scale * self.coef.c_out[i];
            }
        }
        if backward {
            core.online.backward(self.grad.as_ref());
        }
        let loss = (total * f64::from(scale)) as f32;
        LossTerms { consistency: loss, dsm: 0.0, total: loss }
    }
}

/// Multistep consistency sampling (Song et al., Algorithm 1): every step evaluates the
/// consistency function at its level; the next step starts from fresh noise of
/// `sqrt(τ² − σ_min²)` around that estimate.
impl Sampling for BoundaryPreconditioning {
    const LEVELS: usize = 1;

    /// The consistency function `f(·, t)` per row (it always maps to `σ_min`: `u` is unused).
    fn coefficients(&self, coef: &mut RowCoefficients, t: &[f32], _u: &[f32]) {
        coef.clear(1);
        for &s in t {
            coef.push(self.c_in(s), &[self.c_noise(s)], self.c_skip(s), self.c_out(s));
        }
    }

    /// `sqrt(τ² − σ_min²)` at the step's level `τ`.
    fn fresh_noise_std(&self, level: f32) -> Option<f32> {
        Some((level * level - self.sigma_min * self.sigma_min).max(0.0).sqrt())
    }
}

impl ConsistencyModel {
    /// The consistency function `f(x, σ, s)` for a batch in the normalised space: `x` is
    /// `n x d_a`, `sigma` has `n` positive levels, `states` is `n x d_s`, `out` `n x d_a`.
    pub fn consistency_fn(
        &mut self,
        x: MatRef<'_, f32>,
        sigma: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        self.check_model_batch(x, states, &[sigma], out.rb())?;
        self.forward_with(x, states, out, |pre, coef| pre.coefficients(coef, sigma, sigma));
        Ok(())
    }
}

#[cfg(test)]
mod tests;
