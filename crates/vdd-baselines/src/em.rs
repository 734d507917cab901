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
use vdd_core::{CoreError, Expert};
use vdd_moe::{ExpertFamily, Moe};
use vdd_nn::{AdamConfig, LrSchedule};

use crate::dataset::Dataset;
use crate::error::BaselineError;
use crate::fit::{self, MixtureFit};

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
        }
    }

    /// Checks ranges.
    pub fn validate(&self) -> Result<(), CoreError> {
        fit::validate_loop(&fit::loop_settings!(self))
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
    fit: MixtureFit<E>,
    resp: Vec<f32>,
}

impl<E: Expert> Em<E> {
    /// Sets up a run; checks the configuration and that the data fit the mixture's dimensions.
    pub fn new(config: EmConfig, student: Moe<E>, data: Dataset) -> Result<Self, BaselineError> {
        config.validate()?;
        let fit = MixtureFit::new(&fit::loop_settings!(&config), config.seed, student, data)?;
        let resp = vec![0.0; fit.data.len() * fit.student.num_experts()];
        Ok(Self { config, fit, resp })
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
        self.fit.iteration
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
    pub fn log_likelihood(&mut self) -> Result<f64, BaselineError> {
        self.fit.evaluate(None, None)
    }

    /// Runs the remaining iterations, calling `callback` after each.
    pub fn train(&mut self, mut callback: impl FnMut(&EmMetrics)) -> Result<(), BaselineError> {
        while self.fit.iteration < self.config.iterations {
            let m = self.step()?;
            callback(&m);
        }
        Ok(())
    }

    /// One EM iteration. On error the steps already taken stay applied and the iteration
    /// counter does not advance.
    pub fn step(&mut self) -> Result<EmMetrics, BaselineError> {
        let it = self.fit.iteration;
        let (n, z_n) = (self.fit.data.len(), self.fit.student.num_experts());

        // E-step: responsibilities of the dataset actions under the frozen current model.
        let log_likelihood = self.fit.evaluate(None, Some(&mut self.resp))?;
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

        let settings = fit::loop_settings!(&self.config);
        let resp = &self.resp;
        // M-step for the experts: weighted NLL with weights r(z|o)/B.
        let (expert_loss, expert_lr) = self.fit.expert_steps(&settings, None, |row, w| {
            for (z, w) in w.iter_mut().enumerate() {
                *w = resp[row.o * z_n + z] / row.len as f32;
            }
        })?;

        // M-step for the gating: soft cross-entropy towards r(·|o).
        let (gating_loss, gating_lr) = if self.fit.student.has_learned_gating() {
            self.fit.gating_steps(&settings, None, |row, t| {
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
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::test_support::{CLUSTER_MEANS, clusters, full_batch_config, small_moe};
    use faer::Mat;
    use vdd_core::Policy;
    use vdd_moe::{ExpertKind, MoeConfig};
    use vdd_nn::Parameters;

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
            expert_lr_schedule: LrSchedule::LinearDecay { final_factor: 0.05 },
            gating_lr_schedule: LrSchedule::LinearDecay { final_factor: 0.05 },
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
