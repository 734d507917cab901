//! **EM for a mixture of experts**: maximum likelihood of the demonstrations under the same
//! [`Moe`] architecture that VDD distils into (the paper's "EM" baseline).
//!
//! The objective is the dataset log-likelihood
//! `ℓ(θ) = (1/N) Σ_o log Σ_z q(z|s_o) N(a_o; μ_z(s_o), Σ_z(s_o))`. One iteration is:
//!
//! 1. **E-step.** With the current model frozen, compute the responsibilities of every
//!    dataset action, `r(z|o) = q(z|s_o) N(a_o; μ_z, Σ_z) / Σ_k q(k|s_o) N(a_o; μ_k, Σ_k)`
//!    (and `ℓ`, reported as [`EmMetrics::log_likelihood`]).
//! 2. **M-step, experts.** `expert_steps_per_iter` Adam steps on the weighted Gaussian NLL
//!    `(1/B) Σ_{b} Σ_z r(z|o_b) (−log N(a_b; μ_z(s_b), Σ_z(s_b)))` over minibatches drawn
//!    uniformly from the data (or the whole dataset), with the closed-form gradients of
//!    [`crate::fit`] pushed through [`vdd_core::Expert::backward`] and the expert networks.
//! 3. **M-step, gating.** `gating_steps_per_iter` Adam steps on the soft cross-entropy
//!    `−(1/B) Σ_b Σ_z r(z|o_b) log q(z|s_b)` (skipped for a uniform gating).
//!
//! Both M-step losses are the negative of EM's `Q(θ, θ_old)`, so as long as the gradient
//! steps increase `Q`, `ℓ` never decreases (generalised EM); a test checks this on a full
//! batch.

use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Expert, Snapshot, Trainer};
use vdd_moe::{ExpertFamily, Moe, MoeConfig};
use vdd_nn::{AdamConfig, LrSchedule};

use crate::dataset::Dataset;
use crate::error::MixtureError;
use crate::fit::{self, MixtureFit, RowSampler};

/// Hyper-parameters of [`Em`]. [`EmConfig::toy`] is the one default used on every task.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EmConfig {
    /// Number of EM iterations (E-step + M-step).
    pub iterations: usize,
    /// Expert gradient steps per iteration, all against the same E-step responsibilities.
    /// `0` freezes the experts: EM then fits the gating alone, the maximum-likelihood gating
    /// for the given experts (for instance a VDD student's gating fitted to samples of its
    /// teacher); the mixture's gating must then be learned.
    pub expert_steps_per_iter: usize,
    /// Gating gradient steps per iteration (ignored for a uniform gating).
    pub gating_steps_per_iter: usize,
    /// Pairs per expert step; `None` (or at least the dataset size) uses the whole dataset.
    pub batch_size: Option<usize>,
    /// Pairs per gating step; `None` (or at least the dataset size) uses the whole dataset.
    pub gating_batch_size: Option<usize>,
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
    /// The rows each iteration's E-step computes responsibilities for. `None` (the default):
    /// every row, classic EM. `Some(k)`: `k` distinct rows drawn afresh each iteration (from
    /// the stream `e-step-rows`), and that iteration's M-steps draw their minibatches from
    /// them only (stochastic EM). On a large dataset the full E-step costs far more than the
    /// M-steps it feeds (30 steps of 256 pairs use 7,680 rows); `k` a few times that keeps
    /// each iteration's cost independent of the dataset's size. Needs minibatches
    /// (`batch_size` and `gating_batch_size` set).
    #[serde(default)]
    pub e_step_rows: Option<usize>,
}

impl EmConfig {
    /// Defaults for the toy tasks (and the starting point everywhere else): 100 iterations of
    /// 30 expert and 30 gating steps on minibatches of 256 pairs, Adam `1e-3` decaying
    /// linearly to 0 over the run.
    pub fn toy() -> Self {
        let (iterations, steps) = (100, 30);
        let schedule = LrSchedule::LinearDecay { final_factor: 0.0 };
        Self {
            iterations,
            expert_steps_per_iter: steps,
            gating_steps_per_iter: steps,
            batch_size: Some(256),
            gating_batch_size: Some(256),
            expert_optimizer: AdamConfig { lr: 1e-3, ..AdamConfig::default() },
            expert_lr_schedule: schedule.clone(),
            gating_optimizer: AdamConfig { lr: 1e-3, ..AdamConfig::default() },
            gating_lr_schedule: schedule,
            max_grad_norm: None,
            seed: 0,
            e_step_rows: None,
        }
    }

    /// Checks ranges.
    pub fn validate(&self) -> Result<(), CoreError> {
        fit::validate_loop(&fit::loop_settings!(self), true)?;
        match self.e_step_rows {
            Some(0) => Err(CoreError::Config("e_step_rows must be positive".into())),
            Some(k) if self.batch_size.is_none() || self.gating_batch_size.is_none() => {
                Err(CoreError::Config(format!(
                    "e_step_rows = {k} needs minibatches (batch_size and gating_batch_size): a \
                     whole-dataset step would use rows without responsibilities"
                )))
            }
            _ => Ok(()),
        }
    }
}

impl Default for EmConfig {
    fn default() -> Self {
        Self::toy()
    }
}

/// What one EM iteration did; passed to the training callback.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct EmMetrics {
    /// 0-based iteration index.
    pub iteration: usize,
    /// Mean dataset log-likelihood `(1/N) Σ_o log q(a_o|s_o)` of the model at this iteration's
    /// E-step (before its M-step), in nats.
    pub log_likelihood: f64,
    /// Mean entropy of the responsibilities `r(·|o)` over the dataset, in nats (0 when every
    /// pair belongs to one expert).
    pub responsibility_entropy: f64,
    /// Weighted NLL per pair of the last expert step (before that step; 0 when the experts
    /// are frozen).
    pub expert_loss: f64,
    /// Soft cross-entropy of the last gating step (if the gating was trained).
    pub gating_loss: Option<f64>,
    /// Experts' learning rate at the last expert step (0 when the experts are frozen).
    pub expert_lr: f32,
    /// Gating learning rate at the last gating step (0 when not trained).
    pub gating_lr: f32,
}

/// EM for a mixture of experts of family `E` on a [`Dataset`].
///
/// ```
/// use faer::Mat;
/// use vdd_mixture::{Dataset, Em, EmConfig};
/// use vdd_moe::{GatingKind, MoeConfig};
/// // Two clusters of 1-D actions at ±2 (state constant).
/// let actions = Mat::from_fn(64, 1, |i, _| if i % 2 == 0 { 2.0 } else { -2.0 } + 0.01 * (i % 5) as f32);
/// let data = Dataset::new(Mat::zeros(64, 1), actions).unwrap();
/// let mut mc = MoeConfig::toy(1, 1, 2);
/// mc.gating = GatingKind::Learned;
/// mc.experts_network.hidden_dim = 16;
/// mc.gating_network.hidden_dim = 16;
/// let config = EmConfig { iterations: 40, batch_size: None, gating_batch_size: None,
///                         expert_optimizer: vdd_nn::AdamConfig { lr: 1e-2, ..Default::default() },
///                         ..EmConfig::toy() };
/// let mut em = Em::from_config(config, mc, data).unwrap();
/// let mut first = None;
/// em.train(|m| { first.get_or_insert(m.log_likelihood); }).unwrap();
/// assert!(em.log_likelihood().unwrap() > first.unwrap() + 0.5);
/// let student = em.into_student(); // a vdd_core::Policy with exact likelihood
/// ```
pub struct Em<E: Expert = ExpertFamily> {
    config: EmConfig,
    fit: MixtureFit<E>,
    resp: Vec<f32>,
}

impl Em {
    /// Sets up a run with a fresh mixture of configuration `student`, initialised from the
    /// run's seed ([`EmConfig::seed`]; the mixture draws from its own stream, so one seed
    /// determines the whole run). [`Em::new`] takes a mixture built elsewhere.
    pub fn from_config(
        config: EmConfig,
        student: MoeConfig,
        data: Dataset,
    ) -> Result<Self, MixtureError> {
        let student = Moe::from_config(student, config.seed)?;
        Self::new(config, student, data)
    }
}

impl<E: Expert> Em<E> {
    /// As [`Em::from_config`] with a custom expert family: the mixture is
    /// `Moe::new(student, expert, config.seed)`.
    pub fn with_family(
        config: EmConfig,
        student: MoeConfig,
        expert: E,
        data: Dataset,
    ) -> Result<Self, MixtureError> {
        let student = Moe::new(student, expert, config.seed)?;
        Self::new(config, student, data)
    }

    /// Sets up a run with a mixture built elsewhere (pretrained, or initialised with a seed of
    /// its own); checks the configuration and that the data fit the mixture's dimensions.
    pub fn new(config: EmConfig, student: Moe<E>, data: Dataset) -> Result<Self, MixtureError> {
        config.validate()?;
        if config.expert_steps_per_iter == 0 && !student.has_learned_gating() {
            return Err(CoreError::Config(
                "expert_steps_per_iter = 0 freezes the experts, and the mixture's gating is \
                 uniform: nothing would be trained"
                    .into(),
            )
            .into());
        }
        let fit = MixtureFit::new(&fit::loop_settings!(&config), config.seed, student, data)?;
        let resp = vec![0.0; fit.data.len() * fit.student.num_experts()];
        Ok(Self { config, fit, resp })
    }

    /// Trains a fresh run to the end and returns the fitted mixture.
    pub fn fit(config: EmConfig, student: Moe<E>, data: Dataset) -> Result<Moe<E>, MixtureError> {
        let mut em = Self::new(config, student, data)?;
        em.train(|_| {})?;
        Ok(em.into_student())
    }

    /// The configuration.
    pub fn config(&self) -> &EmConfig {
        &self.config
    }

    /// The data being fitted.
    pub fn data(&self) -> &Dataset {
        &self.fit.data
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

    /// The responsibilities `r(z|o)` of the last E-step (`N·Z`, row-major; zeros before the
    /// first iteration).
    pub fn responsibilities(&self) -> &[f32] {
        &self.resp
    }

    /// Mean dataset log-likelihood `(1/N) Σ_o log q(a_o|s_o)` of the current model.
    pub fn log_likelihood(&mut self) -> Result<f64, MixtureError> {
        self.fit.evaluate(None, None)
    }

    /// The E-step on `rows` only ([`EmConfig::e_step_rows`]): their responsibilities into
    /// the rows' places of the responsibilities, and their mean log-likelihood.
    fn e_step_on(&mut self, rows: &[usize]) -> Result<f64, MixtureError> {
        let z_n = self.fit.student.num_experts();
        let subset = self.fit.rows_of(rows)?;
        let mut resp = vec![0.0; rows.len() * z_n];
        let ll = self.fit.evaluate_on(&subset, &mut resp)?;
        for (b, &o) in rows.iter().enumerate() {
            self.resp[o * z_n..(o + 1) * z_n].copy_from_slice(&resp[b * z_n..(b + 1) * z_n]);
        }
        Ok(ll)
    }

    /// Runs the remaining iterations, calling `callback` after each ([`Trainer::run`]).
    pub fn train(&mut self, callback: impl FnMut(&EmMetrics)) -> Result<(), MixtureError> {
        self.run(callback)
    }
}

/// One iteration per [`Trainer::step`], reported as [`EmMetrics`]; the output is the fitted
/// mixture.
impl<E: Expert> Trainer for Em<E> {
    type Report = EmMetrics;
    type Output = Moe<E>;
    type Error = MixtureError;

    /// One EM iteration. On error the steps already taken stay applied and the iteration
    /// counter does not advance.
    fn step(&mut self) -> Result<EmMetrics, MixtureError> {
        let it = self.fit.iteration;
        let (n, z_n) = (self.fit.data.len(), self.fit.student.num_experts());

        // E-step: responsibilities of the dataset actions (or of this iteration's rows) under
        // the frozen current model, and their mean entropy.
        let entropy = |r: &[f32]| {
            -r.iter().filter(|&&r| r > 0.0).map(|&r| f64::from(r) * f64::from(r).ln()).sum::<f64>()
        };
        let (log_likelihood, responsibility_entropy, sampler) = match self.config.e_step_rows {
            Some(k) if k < n => {
                let rows = self.fit.draw_rows("e-step-rows", k);
                let ll = self.e_step_on(&rows)?;
                let h = rows.iter().map(|&o| entropy(&self.resp[o * z_n..(o + 1) * z_n]));
                (ll, h.sum::<f64>() / k as f64, Some(RowSampler::subset(rows)?))
            }
            _ => {
                let ll = self.fit.evaluate(None, Some(&mut self.resp))?;
                (ll, entropy(&self.resp) / n as f64, None)
            }
        };
        if !log_likelihood.is_finite() {
            return Err(MixtureError::NonFinite { iteration: it, quantity: "log-likelihood" });
        }

        let settings = fit::loop_settings!(&self.config);
        let resp = &self.resp;
        // M-step for the experts: weighted NLL with weights r(z|o)/B.
        let sampler = sampler.as_ref();
        let (expert_loss, expert_lr) = self.fit.expert_steps(&settings, sampler, |row, w| {
            for (z, w) in w.iter_mut().enumerate() {
                *w = resp[row.o * z_n + z] / row.len as f32;
            }
        })?;

        // M-step for the gating: soft cross-entropy towards r(·|o).
        let (gating_loss, gating_lr) = if self.fit.student.has_learned_gating() {
            self.fit.gating_steps(&settings, sampler, |row, t| {
                t.copy_from_slice(&resp[row.o * z_n..(row.o + 1) * z_n]);
                1.0 / row.len as f32
            })?
        } else {
            (None, 0.0)
        };

        self.fit.iteration += 1;
        Ok(EmMetrics {
            iteration: it,
            log_likelihood,
            responsibility_entropy,
            expert_loss,
            gating_loss,
            expert_lr,
            gating_lr,
        })
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

/// A copy of the mixture as it is now.
impl<E: Expert> Snapshot for Em<E> {
    fn snapshot(&self) -> Result<Moe<E>, MixtureError> {
        Ok(self.fit.student.clone())
    }
}

#[cfg(test)]
mod tests;
