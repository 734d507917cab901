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

use faer::Mat;
use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Expert, Seeds};
use vdd_moe::{ExpertFamily, Moe};
use vdd_nn::{Adam, AdamConfig, LrSchedule};

use crate::dataset::Dataset;
use crate::error::BaselineError;
use crate::fit::{self, FitBuffers, RowSampler};

/// Hyper-parameters of [`Em`]. [`EmConfig::toy`] is the one default used on every task.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct EmConfig {
    /// Number of EM iterations (E-step + M-step).
    pub iterations: usize,
    /// Expert gradient steps per iteration, all against the same E-step responsibilities.
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
}

impl EmConfig {
    /// Defaults for the toy tasks (and the starting point everywhere else): 100 iterations of
    /// 30 expert and 30 gating steps on minibatches of 256 pairs, Adam `1e-3` decaying
    /// linearly to 0 over the run.
    pub fn toy() -> Self {
        let (iterations, steps) = (100, 30);
        let total = (iterations * steps) as u64;
        let schedule = LrSchedule::LinearDecay { total_steps: total, final_factor: 0.0 };
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
        }
    }

    /// Checks ranges.
    pub fn validate(&self) -> Result<(), CoreError> {
        fit::validate_loop(&fit::LoopSettings {
            iterations: self.iterations,
            expert_steps_per_iter: self.expert_steps_per_iter,
            batch_size: self.batch_size,
            gating_batch_size: self.gating_batch_size,
            optimizers: [&self.expert_optimizer, &self.gating_optimizer],
            schedules: [&self.expert_lr_schedule, &self.gating_lr_schedule],
            max_grad_norm: self.max_grad_norm,
        })
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
    /// Weighted NLL per pair of the last expert step (before that step).
    pub expert_loss: f64,
    /// Soft cross-entropy of the last gating step (if the gating was trained).
    pub gating_loss: Option<f64>,
    /// Experts' learning rate at the last expert step.
    pub expert_lr: f32,
    /// Gating learning rate at the last gating step (0 when not trained).
    pub gating_lr: f32,
}

/// EM for a mixture of experts of family `E` on a [`Dataset`].
///
/// ```
/// use faer::Mat;
/// use vdd_baselines::{Dataset, Em, EmConfig};
/// use vdd_moe::{GatingKind, Moe, MoeConfig};
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
/// let mut em = Em::new(config, Moe::from_config(mc, 0).unwrap(), data).unwrap();
/// let mut first = None;
/// em.train(|m| { first.get_or_insert(m.log_likelihood); }).unwrap();
/// assert!(em.log_likelihood().unwrap() > first.unwrap() + 0.5);
/// let student = em.into_student(); // a vdd_core::Policy with exact likelihood
/// ```
pub struct Em<E: Expert = ExpertFamily> {
    config: EmConfig,
    student: Moe<E>,
    data: Dataset,
    expert_optimizer: Adam,
    gating_optimizer: Adam,
    iteration: usize,
    seeds: Seeds,
    sampler: RowSampler,
    resp: Vec<f32>,
    idx: Vec<usize>,
    batch_states: Mat<f32>,
    batch_actions: Mat<f32>,
    weights: Vec<f32>,
    row_weights: Vec<f32>,
    grad_logits: Mat<f32>,
    buf: FitBuffers,
}

impl<E: Expert> Em<E> {
    /// Sets up a run; checks the configuration and that the data fit the mixture's dimensions.
    pub fn new(config: EmConfig, student: Moe<E>, data: Dataset) -> Result<Self, BaselineError> {
        config.validate()?;
        let mc = student.config();
        data.check_dims(mc.state_dim, mc.action_dim)?;
        let n = data.len();
        Ok(Self {
            expert_optimizer: Adam::new(config.expert_optimizer),
            gating_optimizer: Adam::new(config.gating_optimizer),
            iteration: 0,
            seeds: Seeds::new(config.seed),
            sampler: RowSampler::uniform(n)?,
            resp: vec![0.0; n * mc.num_experts],
            idx: Vec::new(),
            batch_states: Mat::zeros(0, 0),
            batch_actions: Mat::zeros(0, 0),
            weights: Vec::new(),
            row_weights: Vec::new(),
            grad_logits: Mat::zeros(0, 0),
            buf: FitBuffers::default(),
            config,
            student,
            data,
        })
    }

    /// Trains a fresh run to the end and returns the fitted mixture.
    pub fn fit(config: EmConfig, student: Moe<E>, data: Dataset) -> Result<Moe<E>, BaselineError> {
        let mut em = Self::new(config, student, data)?;
        em.train(|_| {})?;
        Ok(em.into_student())
    }

    /// The configuration.
    pub fn config(&self) -> &EmConfig {
        &self.config
    }

    /// Iterations done so far.
    pub fn iteration(&self) -> usize {
        self.iteration
    }

    /// The data being fitted.
    pub fn data(&self) -> &Dataset {
        &self.data
    }

    /// The mixture being trained.
    pub fn student(&self) -> &Moe<E> {
        &self.student
    }

    /// The mixture, mutably (e.g. to evaluate it between iterations).
    pub fn student_mut(&mut self) -> &mut Moe<E> {
        &mut self.student
    }

    /// Ends training and returns the mixture.
    pub fn into_student(self) -> Moe<E> {
        self.student
    }

    /// The responsibilities `r(z|o)` of the last E-step (`N·Z`, row-major; zeros before the
    /// first iteration).
    pub fn responsibilities(&self) -> &[f32] {
        &self.resp
    }

    /// Mean dataset log-likelihood `(1/N) Σ_o log q(a_o|s_o)` of the current model.
    pub fn log_likelihood(&mut self) -> Result<f64, BaselineError> {
        fit::evaluate_dataset(&mut self.student, &self.data, None, None)
    }

    /// Runs the remaining iterations, calling `callback` after each.
    pub fn train(&mut self, mut callback: impl FnMut(&EmMetrics)) -> Result<(), BaselineError> {
        while self.iteration < self.config.iterations {
            let m = self.step()?;
            callback(&m);
        }
        Ok(())
    }

    /// One EM iteration. On error the steps already taken stay applied and the iteration
    /// counter does not advance.
    pub fn step(&mut self) -> Result<EmMetrics, BaselineError> {
        let it = self.iteration;
        let (n, z_n) = (self.data.len(), self.student.num_experts());

        // E-step: responsibilities of the dataset actions under the frozen current model.
        let log_likelihood =
            fit::evaluate_dataset(&mut self.student, &self.data, None, Some(&mut self.resp))?;
        if !log_likelihood.is_finite() {
            return Err(BaselineError::NonFinite { iteration: it, quantity: "log-likelihood" });
        }
        let responsibility_entropy = -self
            .resp
            .iter()
            .filter(|&&r| r > 0.0)
            .map(|&r| f64::from(r) * f64::from(r).ln())
            .sum::<f64>()
            / n as f64;

        // M-step for the experts: weighted NLL with weights r(z|o)/B.
        let mut expert_loss = 0.0;
        let mut expert_lr = 0.0;
        for k in 0..self.config.expert_steps_per_iter {
            let stream = (it * self.config.expert_steps_per_iter + k) as u64;
            let full = self.draw_batch(self.config.batch_size, "expert-batch", stream);
            let b_n = self.idx.len();
            self.weights.resize(b_n * z_n, 0.0);
            for (b, &o) in self.idx.iter().enumerate() {
                for z in 0..z_n {
                    self.weights[b * z_n + z] = self.resp[o * z_n + z] / b_n as f32;
                }
            }
            let factor = self.config.expert_lr_schedule.factor(self.expert_optimizer.steps());
            expert_lr = self.config.expert_optimizer.lr * factor;
            let (states, actions) = if full {
                (self.data.states(), self.data.actions())
            } else {
                (self.batch_states.as_ref(), self.batch_actions.as_ref())
            };
            expert_loss = fit::expert_step(
                &mut self.student,
                states,
                actions,
                &self.weights,
                &mut self.expert_optimizer,
                factor,
                self.config.max_grad_norm,
                it,
                &mut self.buf,
            )?;
        }

        // M-step for the gating: soft cross-entropy towards r(·|o).
        let mut gating_loss = None;
        let mut gating_lr = 0.0;
        if self.student.has_learned_gating() {
            for k in 0..self.config.gating_steps_per_iter {
                let stream = (it * self.config.gating_steps_per_iter + k) as u64;
                let full = self.draw_batch(self.config.gating_batch_size, "gating-batch", stream);
                let b_n = self.idx.len();
                self.weights.resize(b_n * z_n, 0.0);
                for (b, &o) in self.idx.iter().enumerate() {
                    self.weights[b * z_n..(b + 1) * z_n]
                        .copy_from_slice(&self.resp[o * z_n..(o + 1) * z_n]);
                }
                self.row_weights.clear();
                self.row_weights.resize(b_n, 1.0 / b_n as f32);
                let factor = self.config.gating_lr_schedule.factor(self.gating_optimizer.steps());
                gating_lr = self.config.gating_optimizer.lr * factor;
                let states = if full { self.data.states() } else { self.batch_states.as_ref() };
                gating_loss = fit::gating_step(
                    &mut self.student,
                    states,
                    &self.weights,
                    &self.row_weights,
                    &mut self.gating_optimizer,
                    factor,
                    self.config.max_grad_norm,
                    it,
                    &mut self.grad_logits,
                )?;
            }
        }

        self.iteration += 1;
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

    /// Fills `self.idx` with a minibatch (uniform rows) and gathers its states and actions, or
    /// selects the whole dataset (`idx = 0..N`, nothing gathered) and returns `true`.
    fn draw_batch(&mut self, size: Option<usize>, purpose: &str, stream: u64) -> bool {
        let n = self.data.len();
        match size {
            Some(b) if b < n => {
                let mut rng = self.seeds.stream_indexed(purpose, stream);
                self.sampler.draw(&mut rng, b, &mut self.idx);
                fit::gather_rows(self.data.states(), &self.idx, &mut self.batch_states);
                fit::gather_rows(self.data.actions(), &self.idx, &mut self.batch_actions);
                false
            }
            _ => {
                self.idx.clear();
                self.idx.extend(0..n);
                true
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::{CLUSTER_MEANS, clusters, small_moe};
    use vdd_core::Policy;
    use vdd_moe::{ExpertKind, MoeConfig};
    use vdd_nn::Parameters;

    fn full_batch_config(iterations: usize, steps: usize, lr: f32) -> EmConfig {
        // Decaying steps, so that Adam's jitter near the M-step optimum cannot undo an ascent.
        let total = (iterations * steps) as u64;
        let schedule = LrSchedule::Cosine { total_steps: total, final_factor: 0.05 };
        EmConfig {
            iterations,
            expert_steps_per_iter: steps,
            gating_steps_per_iter: steps,
            batch_size: None,
            gating_batch_size: None,
            expert_optimizer: AdamConfig { lr, ..AdamConfig::default() },
            expert_lr_schedule: schedule.clone(),
            gating_optimizer: AdamConfig { lr, ..AdamConfig::default() },
            gating_lr_schedule: schedule,
            ..EmConfig::toy()
        }
    }

    #[test]
    fn log_likelihood_never_decreases_on_a_full_batch() {
        for kind in [ExpertKind::Diagonal, ExpertKind::Full] {
            let (data, _) = clusters([40, 40, 40], 0.35, 1);
            let student = small_moe(kind, 3, 5);
            let config = full_batch_config(25, 30, 3e-3);
            let mut em = Em::new(config, student, data).unwrap();
            let mut lls = Vec::new();
            em.train(|m| lls.push(m.log_likelihood)).unwrap();
            lls.push(em.log_likelihood().unwrap());
            for w in lls.windows(2) {
                assert!(w[1] >= w[0] - 1e-4, "{kind:?}: log-likelihood decreased: {lls:?}");
            }
            assert!(lls[lls.len() - 1] > lls[0] + 1.0, "{kind:?}: EM did not improve: {lls:?}");
        }
    }

    #[test]
    fn finds_the_means_of_three_separated_clusters() {
        // Unequal clusters, so that the gating must learn unequal weights.
        let sizes = [60, 120, 180];
        let (data, _) = clusters(sizes, 0.3, 2);
        let student = small_moe(ExpertKind::Diagonal, 3, 0);
        let config = EmConfig {
            iterations: 60,
            expert_steps_per_iter: 10,
            gating_steps_per_iter: 10,
            batch_size: Some(128),
            gating_batch_size: Some(128),
            expert_optimizer: AdamConfig { lr: 1e-2, ..AdamConfig::default() },
            gating_optimizer: AdamConfig { lr: 1e-2, ..AdamConfig::default() },
            expert_lr_schedule: LrSchedule::LinearDecay { total_steps: 600, final_factor: 0.05 },
            gating_lr_schedule: LrSchedule::LinearDecay { total_steps: 600, final_factor: 0.05 },
            ..EmConfig::toy()
        };
        let mut student = Em::fit(config, student, data).unwrap();
        student.forward(Mat::zeros(1, 1).as_ref()).unwrap();
        let out = student.output();
        let mut found = [false; 3];
        for z in 0..3 {
            let m = out.mean(0, z);
            let (c, dist) = CLUSTER_MEANS
                .iter()
                .enumerate()
                .map(|(c, mu)| (c, ((m[0] - mu[0]).powi(2) + (m[1] - mu[1]).powi(2)).sqrt()))
                .min_by(|a, b| a.1.total_cmp(&b.1))
                .unwrap();
            assert!(dist < 0.15, "expert {z} mean {m:?} is {dist} from cluster {c}");
            found[c] = true;
            let w = out.log_gating_row(0)[z].exp();
            let expect = sizes[c] as f32 / 360.0;
            assert!((w - expect).abs() < 0.04, "expert {z} weight {w}, cluster share {expect}");
            let std = out.scale(0, z)[0];
            assert!((std - 0.3).abs() < 0.06, "expert {z} std {std}");
        }
        assert_eq!(found, [true; 3], "two experts share a cluster");
    }

    #[test]
    fn same_seed_same_run_and_other_seed_other_run() {
        let run = |seed: u64| {
            let (data, _) = clusters([10, 10, 10], 0.3, 3);
            let config = EmConfig { iterations: 3, seed, ..EmConfig::toy() };
            let config = EmConfig { batch_size: Some(16), gating_batch_size: Some(16), ..config };
            let mut em = Em::new(config, small_moe(ExpertKind::Full, 3, 1), data).unwrap();
            let mut metrics = Vec::new();
            em.train(|m| metrics.push(*m)).unwrap();
            let mut params = Vec::new();
            em.student().visit_params("", &mut |_, p| params.push(p.value.clone()));
            (metrics, params)
        };
        let (a, b, c) = (run(7), run(7), run(8));
        assert_eq!(a, b);
        assert_ne!(a.1, c.1);
    }

    #[test]
    fn bad_inputs_are_rejected() {
        let (data, _) = clusters([4, 3, 3], 0.3, 0);
        let student = small_moe(ExpertKind::Diagonal, 2, 0);
        let bad = [
            EmConfig { iterations: 0, ..EmConfig::toy() },
            EmConfig { expert_steps_per_iter: 0, ..EmConfig::toy() },
            EmConfig { batch_size: Some(0), ..EmConfig::toy() },
            EmConfig { max_grad_norm: Some(-1.0), ..EmConfig::toy() },
            EmConfig {
                expert_optimizer: AdamConfig { lr: f32::NAN, ..AdamConfig::default() },
                ..EmConfig::toy()
            },
        ];
        for config in bad {
            assert!(Em::new(config, student.clone(), data.clone()).is_err());
        }
        let wrong_dims = Moe::from_config(MoeConfig::toy(1, 3, 2), 0).unwrap();
        assert!(Em::new(EmConfig::toy(), wrong_dims, data.clone()).is_err());
        let wrong_state = Moe::from_config(MoeConfig::toy(2, 2, 2), 0).unwrap();
        assert!(Em::new(EmConfig::toy(), wrong_state, data).is_err());
    }

    #[test]
    fn uniform_gating_stays_uniform() {
        let (data, _) = clusters([7, 7, 6], 0.3, 0);
        let mut mc = MoeConfig::toy(1, 2, 3);
        mc.experts_network.hidden_dim = 8;
        let student = Moe::from_config(mc, 0).unwrap();
        let config = EmConfig { iterations: 2, ..full_batch_config(2, 3, 1e-3) };
        let mut em = Em::new(config, student, data).unwrap();
        let mut gating_losses = Vec::new();
        em.train(|m| gating_losses.push(m.gating_loss)).unwrap();
        assert_eq!(gating_losses, vec![None, None]);
        let mut student = em.into_student();
        let a = student.act(&[0.0]).unwrap();
        assert!(a.iter().all(|x| x.is_finite()));
    }
}
