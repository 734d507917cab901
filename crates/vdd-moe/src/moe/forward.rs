//! The batched forward and backward passes on normalised states, the responsibilities and
//! the experts' entropies: what trainers use.

use faer::{Mat, MatRef};
use vdd_core::gaussian::log_sum_exp;
use vdd_core::{Expert, check_finite, check_finite_slice, check_len, check_shape};
use vdd_nn::Module;

use super::{ExpertNets, Moe};
use crate::error::MoeError;

impl<E: Expert> Moe<E> {
    fn check_states(&self, states: MatRef<'_, f32>) -> Result<(), MoeError> {
        check_shape("states", states, states.nrows(), self.config.state_dim)?;
        check_finite("states", states)?;
        Ok(())
    }

    /// Runs the experts' networks on `n x state_dim` (normalised) states and decodes means and
    /// scales into [`Moe::output`].
    pub fn forward_experts(&mut self, states: MatRef<'_, f32>) -> Result<(), MoeError> {
        self.check_states(states)?;
        let (n, z, r, d) = (
            states.nrows(),
            self.config.num_experts,
            self.expert.raw_dim(),
            self.config.action_dim,
        );
        let out = &mut self.out;
        out.n = n;
        out.raw.resize(n * z * r, 0.0);
        out.means.resize(n * z * d, 0.0);
        out.scales.resize(n * z * d * d, 0.0);
        match &mut self.experts.0 {
            ExpertNets::Shared(net) => {
                let y = net.forward(states);
                for b in 0..n {
                    for c in 0..z * r {
                        out.raw[b * z * r + c] = y[(b, c)];
                    }
                }
            }
            ExpertNets::Separate(nets) => {
                for (e, net) in nets.iter_mut().enumerate() {
                    let y = net.forward(states);
                    for b in 0..n {
                        for c in 0..r {
                            out.raw[(b * z + e) * r + c] = y[(b, c)];
                        }
                    }
                }
            }
        }
        for k in 0..n * z {
            self.expert.decode(
                &out.raw[k * r..(k + 1) * r],
                &mut out.means[k * d..(k + 1) * d],
                &mut out.scales[k * d * d..(k + 1) * d * d],
            );
        }
        self.experts_forwarded = true;
        Ok(())
    }

    /// Computes `log q(z|s)` for `n x state_dim` states into [`Moe::output`].
    pub fn forward_gating(&mut self, states: MatRef<'_, f32>) -> Result<(), MoeError> {
        self.gating_pass(states, false)
    }

    /// [`Moe::forward_gating`]; with `inference`, an inference pass that keeps nothing for a
    /// backward one ([`vdd_nn::Module::forward_inference`], the same bits).
    pub(super) fn gating_pass(
        &mut self,
        states: MatRef<'_, f32>,
        inference: bool,
    ) -> Result<(), MoeError> {
        self.check_states(states)?;
        let (n, z) = (states.nrows(), self.config.num_experts);
        self.out.log_gating.resize(n * z, 0.0);
        match &mut self.gating {
            None => self.out.log_gating.fill(-(z as f32).ln()),
            Some(net) => {
                let y = vdd_nn::forward_as(net, states, inference);
                for b in 0..n {
                    let row = &mut self.out.log_gating[b * z..(b + 1) * z];
                    for (e, v) in row.iter_mut().enumerate() {
                        *v = y[(b, e)];
                    }
                    let lse = log_sum_exp(row);
                    for v in row.iter_mut() {
                        *v -= lse;
                    }
                }
            }
        }
        self.gating_forwarded = !inference;
        Ok(())
    }

    /// Both forward passes.
    pub fn forward(&mut self, states: MatRef<'_, f32>) -> Result<(), MoeError> {
        self.forward_experts(states)?;
        self.forward_gating(states)
    }

    /// Back-propagates `∂loss/∂raw` (row-major `n·Z·raw_dim`, for the last
    /// [`Moe::forward_experts`]) into the experts' parameter gradients.
    pub fn backward_experts(&mut self, grad_raw: &[f32]) -> Result<(), MoeError> {
        if !self.experts_forwarded {
            return Err(MoeError::NoForward("backward_experts"));
        }
        let (n, z, r) = (self.out.n, self.config.num_experts, self.expert.raw_dim());
        check_len("raw-output gradient", grad_raw.len(), n * z * r)?;
        check_finite_slice("raw-output gradient", grad_raw)?;
        match &mut self.experts.0 {
            ExpertNets::Shared(net) => {
                if self.grad.nrows() != n || self.grad.ncols() != z * r {
                    self.grad = Mat::zeros(n, z * r);
                }
                for b in 0..n {
                    for c in 0..z * r {
                        self.grad[(b, c)] = grad_raw[b * z * r + c];
                    }
                }
                net.backward(self.grad.as_ref());
            }
            ExpertNets::Separate(nets) => {
                if self.grad.nrows() != n || self.grad.ncols() != r {
                    self.grad = Mat::zeros(n, r);
                }
                for (e, net) in nets.iter_mut().enumerate() {
                    for b in 0..n {
                        for c in 0..r {
                            self.grad[(b, c)] = grad_raw[(b * z + e) * r + c];
                        }
                    }
                    net.backward(self.grad.as_ref());
                }
            }
        }
        Ok(())
    }

    /// Back-propagates `∂loss/∂logits` (`n x Z`, for the last [`Moe::forward_gating`]) into the
    /// gating network's gradients. A no-op for uniform gating.
    pub fn backward_gating(&mut self, grad_logits: MatRef<'_, f32>) -> Result<(), MoeError> {
        if !self.gating_forwarded {
            return Err(MoeError::NoForward("backward_gating"));
        }
        // Rows of the last gating forward (which may differ from the experts' batch).
        let rows = self.out.log_gating.len() / self.config.num_experts;
        check_shape("gating gradient", grad_logits, rows, self.config.num_experts)?;
        check_finite("gating gradient", grad_logits)?;
        if let Some(net) = &mut self.gating {
            net.backward(grad_logits);
        }
        Ok(())
    }

    /// Writes `q(z|a, s)` for each (normalised) state–action row into `out` (`n x Z`).
    pub fn responsibilities(
        &mut self,
        states: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
        mut out: faer::MatMut<'_, f32>,
    ) -> Result<(), MoeError> {
        let n = states.nrows();
        check_shape("actions", actions, n, self.config.action_dim)?;
        check_shape("responsibilities", out.as_ref(), n, self.config.num_experts)?;
        check_finite("actions", actions)?;
        self.forward(states)?;
        let mut a = vec![0.0; self.config.action_dim];
        for b in 0..n {
            for (j, v) in a.iter_mut().enumerate() {
                *v = actions[(b, j)];
            }
            self.out.log_density_and_responsibilities(b, &a, &mut self.resp, &mut self.work);
            for (z, r) in self.resp.iter().enumerate() {
                out[(b, z)] = *r;
            }
        }
        Ok(())
    }

    /// Entropy of each expert at each state (`n x Z`), in nats.
    pub fn expert_entropies(&mut self, states: MatRef<'_, f32>) -> Result<Mat<f32>, MoeError> {
        self.forward_experts(states)?;
        let (n, z) = (states.nrows(), self.config.num_experts);
        Ok(Mat::from_fn(n, z, |b, e| self.expert.entropy(self.out.scale(b, e))))
    }
}
