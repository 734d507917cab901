//! One iteration of the authors' IMC ([`ImcVariant::Authors`]).

use vdd_core::Expert;

use super::{Imc, ImcMetrics, ImcVariant, log_sum_exp};
use crate::error::MixtureError;
use crate::fit;

impl<E: Expert> Imc<E> {
    /// The authors' iteration: unit-variance likelihoods, curricula normalised per data point,
    /// expert steps on uniform minibatches weighted by the curricula; after the last
    /// iteration, the gating.
    pub(super) fn step_authors(&mut self) -> Result<ImcMetrics, MixtureError> {
        debug_assert_eq!(self.config.variant, ImcVariant::Authors);
        let it = self.fit.iteration;
        let (n, z_n, eta) = (self.fit.data.len(), self.fit.student.num_experts(), self.config.eta);

        // 1. ℓ_z(o) = −½‖a_o − μ_z(s_o)‖² with the experts frozen.
        let log_likelihood = self.fit.evaluate_unit(&mut self.log_lik)?;
        if !log_likelihood.is_finite() || self.log_lik.iter().any(|x| !x.is_finite()) {
            return Err(MixtureError::NonFinite { iteration: it, quantity: "log-likelihood" });
        }
        let objective = self.curricula.objective(&self.log_lik, eta)?;

        // 2. log c(o, z) ← ℓ_z(o)/η + log p(z|o), p(z|o) the current curricula's posterior;
        //    the bound is η log Σ_{o,z} c(o, z); then every point's best expert gets weight 1.
        for o in 0..n {
            let row = &mut self.per_point[o * z_n..(o + 1) * z_n];
            let lse = log_sum_exp(row);
            for (c, ll) in row.iter_mut().zip(&self.log_lik[o * z_n..(o + 1) * z_n]) {
                *c = f64::from(*ll) / eta + (*c - lse);
            }
        }
        let lower_bound = eta * log_sum_exp(&self.per_point);
        for o in 0..n {
            let row = &mut self.per_point[o * z_n..(o + 1) * z_n];
            let max = row.iter().copied().fold(f64::NEG_INFINITY, f64::max);
            row.iter_mut().for_each(|c| *c -= max);
            let lse = log_sum_exp(row);
            for (p, c) in self.posterior[o * z_n..(o + 1) * z_n].iter_mut().zip(row.iter()) {
                *p = (*c - lse).exp() as f32;
            }
        }
        // The same curricula normalised jointly, for the metrics and `curricula()`.
        let total = log_sum_exp(&self.per_point);
        for (j, c) in self.curricula.log_joint.iter_mut().zip(&self.per_point) {
            *j = c - total;
        }
        let curriculum_log_likelihood = self.curricula.weighted_log_likelihood(&self.log_lik);
        let effective_data_fraction = self.curricula.data_entropy().exp() / n as f64;
        let active_experts =
            self.curricula.expert_weights().iter().filter(|&&w| w >= 0.1 / z_n as f64).count();

        // 3. Experts: uniform minibatches, weights c(o, z) / B.
        let settings = fit::loop_settings!(&self.config);
        let per_point = &self.per_point;
        let (expert_loss, expert_lr) = self.fit.expert_steps(&settings, None, |row, w| {
            for (z, w) in w.iter_mut().enumerate() {
                *w = per_point[row.o * z_n + z].exp() as f32 / row.len as f32;
            }
        })?;

        // 4. After the last iteration: the gating, fitted to p(z|o) uniformly over the data with
        //    all of the run's gating steps (the batches of iteration i's steps, in turn).
        let (mut gating_loss, mut gating_lr) = (None, 0.0);
        if it + 1 == self.config.iterations {
            let posterior = &self.posterior;
            let mut result = Ok(());
            for i in 0..self.config.iterations {
                self.fit.iteration = i;
                match self.fit.gating_steps(&settings, None, |row, t| {
                    t.copy_from_slice(&posterior[row.o * z_n..(row.o + 1) * z_n]);
                    1.0 / row.len as f32
                }) {
                    Ok((l, lr)) => (gating_loss, gating_lr) = (l, lr),
                    Err(e) => {
                        result = Err(e);
                        break;
                    }
                }
            }
            self.fit.iteration = it;
            result?;
        }

        self.fit.iteration += 1;
        Ok(ImcMetrics {
            iteration: it,
            objective,
            lower_bound,
            curriculum_log_likelihood,
            effective_data_fraction,
            active_experts,
            log_likelihood,
            expert_loss,
            gating_loss,
            expert_lr,
            gating_lr,
        })
    }
}
