//! One iteration of the authors' IMC ([`ImcVariant::Authors`]), over every point or, with
//! [`ImcConfig::curriculum_rows`], over the iteration's drawn points.

use vdd_core::Expert;

use super::{Curricula, Imc, ImcMetrics, ImcVariant, Measured, log_sum_exp};
use crate::error::MixtureError;
use crate::fit::{self, RowSampler};

#[cfg(doc)]
use super::ImcConfig;

/// Advances one point's log curriculum `row` (`Z` entries) by `steps` of the authors' updates
/// with the experts' log-likelihoods `ll` held fixed: `log c(o, z) ← steps·ℓ_z(o)/η + log
/// p(z|o)`, `p(z|o)` the row normalised. One step is the authors' update; `k` steps give the
/// posterior of `k` single steps with the same `ℓ`, which is how a point that
/// [`ImcConfig::curriculum_rows`] skipped catches up when it is drawn again.
///
/// ```
/// use vdd_mixture::imc::advance_curriculum;
/// let (ll, eta) = ([-1.0f32, -3.0], 2.0);
/// let mut once = [0.0f64, 0.0];
/// advance_curriculum(&mut once, &ll, 3.0, eta);
/// let mut thrice = [0.0f64, 0.0];
/// for _ in 0..3 {
///     advance_curriculum(&mut thrice, &ll, 1.0, eta);
/// }
/// // The same posterior p(z|o): the rows differ by a constant only.
/// assert!(((once[0] - once[1]) - (thrice[0] - thrice[1])).abs() < 1e-12);
/// assert!(((once[0] - once[1]) - 3.0).abs() < 1e-12); // 3 · (−1 − (−3)) / 2
/// ```
pub fn advance_curriculum(row: &mut [f64], ll: &[f32], steps: f64, eta: f64) {
    let lse = log_sum_exp(row);
    for (c, ll) in row.iter_mut().zip(ll) {
        *c = steps * f64::from(*ll) / eta + (*c - lse);
    }
}

/// Shifts a log curriculum row so that its best expert has weight 1 (no point is dropped) and
/// writes its posterior `p(z|o)` into `posterior`.
fn settle(row: &mut [f64], posterior: &mut [f32]) {
    let max = row.iter().copied().fold(f64::NEG_INFINITY, f64::max);
    row.iter_mut().for_each(|c| *c -= max);
    let lse = log_sum_exp(row);
    for (p, c) in posterior.iter_mut().zip(row.iter()) {
        *p = (*c - lse).exp() as f32;
    }
}

/// The per-point log curricula `per_point` (`N·Z`) of the points `rows` (all when `None`).
fn rows_of(per_point: &[f64], rows: Option<&[usize]>, z_n: usize) -> Vec<f64> {
    match rows {
        None => per_point.to_vec(),
        Some(rows) => {
            rows.iter().flat_map(|&o| &per_point[o * z_n..(o + 1) * z_n]).copied().collect()
        }
    }
}

/// The per-point log curricula `per_point` (`N·Z`) of the points `rows` (all when `None`),
/// normalised jointly.
fn joint_of(per_point: &[f64], rows: Option<&[usize]>, z_n: usize) -> Curricula {
    let log_joint = rows_of(per_point, rows, z_n);
    let total = log_sum_exp(&log_joint);
    let n = log_joint.len() / z_n;
    Curricula { n, num_experts: z_n, log_joint: log_joint.into_iter().map(|c| c - total).collect() }
}

impl<E: Expert> Imc<E> {
    /// The authors' iteration: unit-variance likelihoods, curricula normalised per data point,
    /// expert steps on uniform minibatches weighted by the curricula; after the last
    /// iteration, the gating. With [`ImcConfig::curriculum_rows`], every iteration but the
    /// last updates and trains on its drawn points only.
    pub(super) fn step_authors(&mut self) -> Result<ImcMetrics, MixtureError> {
        debug_assert_eq!(self.config.variant, ImcVariant::Authors);
        let it = self.fit.iteration;
        let last = it + 1 == self.config.iterations;
        // 1–2. The curricula of every point, or of the iteration's drawn points.
        let (measured, rows) = match self.config.curriculum_rows {
            Some(k) if k < self.fit.data.len() && !last => {
                let rows = self.fit.draw_rows("curriculum-rows", k);
                (self.update_curricula_on(&rows)?, Some(rows))
            }
            _ => (self.update_curricula()?, None),
        };
        // 3. Experts: minibatches (uniform, or from the drawn points), weights c(o, z) / B.
        let sampler = rows.map(RowSampler::subset).transpose()?;
        let expert = self.expert_steps(sampler.as_ref())?;
        // 4. After the last iteration: the gating.
        let gating = if last { self.fit_gating_last()? } else { (None, 0.0) };
        self.fit.iteration += 1;
        Ok(measured.into_metrics(it, expert, gating))
    }

    /// Every point's curricula: `ℓ_z(o) = −½‖a_o − μ_z(s_o)‖²` with the experts frozen, then
    /// `log c(o, z) ← ℓ_z(o)/η + log p(z|o)`, `p(z|o)` the current curricula's posterior (once
    /// per iteration the point missed); the bound is `η log Σ_{o,z} c(o, z)`; then every
    /// point's best expert gets weight 1.
    fn update_curricula(&mut self) -> Result<Measured, MixtureError> {
        let it = self.fit.iteration;
        let (n, z_n, eta) = (self.fit.data.len(), self.fit.student.num_experts(), self.config.eta);
        let log_likelihood = self.fit.evaluate_unit(&mut self.log_lik)?;
        check_finite(log_likelihood, &self.log_lik, it)?;
        if self.config.curriculum_rows.is_some() {
            // Earlier iterations updated some points only, and not the joint curricula.
            self.curricula = joint_of(&self.per_point, None, z_n);
        }
        let objective = self.curricula.objective(&self.log_lik, eta)?;
        for o in 0..n {
            let steps = (it + 1 - self.advanced_to[o]) as f64;
            let (row, ll) = (o * z_n..(o + 1) * z_n, &self.log_lik[o * z_n..(o + 1) * z_n]);
            advance_curriculum(&mut self.per_point[row], ll, steps, eta);
            self.advanced_to[o] = it + 1;
        }
        let lower_bound = eta * log_sum_exp(&self.per_point);
        for o in 0..n {
            let row = o * z_n..(o + 1) * z_n;
            settle(&mut self.per_point[row.clone()], &mut self.posterior[row]);
        }
        // The same curricula normalised jointly, for the metrics and `curricula()`.
        self.curricula = joint_of(&self.per_point, None, z_n);
        let summary = self.curricula.summary(&self.log_lik);
        Ok(Measured { objective, lower_bound, summary, log_likelihood })
    }

    /// As [`Imc::update_curricula`] for the points `rows` only
    /// ([`ImcConfig::curriculum_rows`]); the metrics describe them.
    fn update_curricula_on(&mut self, rows: &[usize]) -> Result<Measured, MixtureError> {
        let it = self.fit.iteration;
        let (z_n, eta) = (self.fit.student.num_experts(), self.config.eta);
        let subset = self.fit.rows_of(rows)?;
        let mut ll = vec![0.0f32; rows.len() * z_n];
        let log_likelihood = self.fit.evaluate_unit_on(&subset, &mut ll)?;
        check_finite(log_likelihood, &ll, it)?;
        let objective = joint_of(&self.per_point, Some(rows), z_n).objective(&ll, eta)?;
        for (b, &o) in rows.iter().enumerate() {
            let steps = (it + 1 - self.advanced_to[o]) as f64;
            let row = o * z_n..(o + 1) * z_n;
            advance_curriculum(&mut self.per_point[row], &ll[b * z_n..(b + 1) * z_n], steps, eta);
            self.advanced_to[o] = it + 1;
        }
        let lower_bound = eta * log_sum_exp(&rows_of(&self.per_point, Some(rows), z_n));
        for &o in rows {
            let row = o * z_n..(o + 1) * z_n;
            settle(&mut self.per_point[row.clone()], &mut self.posterior[row]);
        }
        let summary = joint_of(&self.per_point, Some(rows), z_n).summary(&ll);
        Ok(Measured { objective, lower_bound, summary, log_likelihood })
    }

    /// The iteration's expert steps on minibatches from `sampler` (uniform when `None`), each
    /// row weighted by its curricula `c(o, z) / B`.
    fn expert_steps(&mut self, sampler: Option<&RowSampler>) -> Result<(f64, f32), MixtureError> {
        let settings = fit::loop_settings!(&self.config);
        let (per_point, z_n) = (&self.per_point, self.fit.student.num_experts());
        self.fit.expert_steps(&settings, sampler, |row, w| {
            for (z, w) in w.iter_mut().enumerate() {
                *w = per_point[row.o * z_n + z].exp() as f32 / row.len as f32;
            }
        })
    }

    /// The gating, fitted to `p(z|o)` uniformly over the data with all of the run's gating
    /// steps (the batches of iteration `i`'s steps, in turn). Returns the last step's loss and
    /// learning rate.
    fn fit_gating_last(&mut self) -> Result<(Option<f64>, f32), MixtureError> {
        let (it, z_n) = (self.fit.iteration, self.fit.student.num_experts());
        let settings = fit::loop_settings!(&self.config);
        let posterior = &self.posterior;
        let (mut last, mut result) = ((None, 0.0), Ok(()));
        for i in 0..self.config.iterations {
            self.fit.iteration = i;
            match self.fit.gating_steps(&settings, None, |row, t| {
                t.copy_from_slice(&posterior[row.o * z_n..(row.o + 1) * z_n]);
                1.0 / row.len as f32
            }) {
                Ok(step) => last = step,
                Err(e) => {
                    result = Err(e);
                    break;
                }
            }
        }
        self.fit.iteration = it;
        result.map(|()| last)
    }
}

/// An error unless the mean log-likelihood and every expert's are finite.
fn check_finite(log_likelihood: f64, ll: &[f32], iteration: usize) -> Result<(), MixtureError> {
    if !log_likelihood.is_finite() || ll.iter().any(|x| !x.is_finite()) {
        return Err(MixtureError::NonFinite { iteration, quantity: "log-likelihood" });
    }
    Ok(())
}
