//! The optimiser steps every trainer of a [`Moe`] shares: the gating step and the checked
//! gradient clipping. VDD (`vdd`) and the mixture baselines (`vdd-mixture`: EM, IMC) all fit the
//! gating to responsibilities by a soft cross-entropy and clip gradients the same way; this
//! module holds the one implementation.
//!
//! * [`gating_step`]: one optimiser step of the gating on a loss of its log-probabilities
//!   (forward on a batch of states, the caller's loss and gradient with respect to the logits,
//!   backward, [`clip_or_fail`], Adam);
//! * [`soft_cross_entropy`]: the loss towards per-row soft targets with per-row weights,
//!   `−Σ_b c_b Σ_z t_{bz} log q(z|s_b)`, whose gradient with respect to the gating logits is
//!   `c_b (q(z|s_b) Σ_k t_{bk} − t_{bz})`;
//! * [`clip_or_fail`]: [`vdd_nn::clip_grad_norm_checked`] with the iteration and the quantity
//!   named in the error.
//!
//! Nothing is updated when a loss or a gradient is not finite ([`StepError::NonFinite`]).

use faer::{Mat, MatMut, MatRef};
use vdd_core::{CoreError, Expert, check_finite_slice, check_len, check_shape};
use vdd_nn::{Adam, Parameters};

use crate::{Moe, MoeError, MoeOutput};

/// Errors of a training step.
#[derive(Debug, thiserror::Error)]
pub enum StepError {
    /// A loss or a gradient became NaN or infinite; the update was not applied.
    #[error("non-finite {quantity} at iteration {iteration}; the update was not applied")]
    NonFinite {
        /// Iteration (0-based) at which it happened.
        iteration: usize,
        /// Which quantity.
        quantity: &'static str,
    },
    /// The loss's inputs were invalid (shapes, non-finite targets).
    #[error(transparent)]
    Core(#[from] CoreError),
    /// The mixture's forward or backward pass failed.
    #[error(transparent)]
    Moe(#[from] MoeError),
}

/// Checks that the global gradient norm of `params` is finite and clips it to `max_norm` when
/// one is given ([`vdd_nn::clip_grad_norm_checked`]); a non-finite norm is
/// [`StepError::NonFinite`] with `iteration` and `quantity`.
///
/// ```
/// use vdd_moe::step::{StepError, clip_or_fail};
/// use vdd_moe::{Moe, MoeConfig};
/// use vdd_nn::Parameters;
/// let mut moe = Moe::from_config(MoeConfig::toy(1, 2, 2), 0).unwrap();
/// let nets = moe.expert_networks_mut();
/// assert!(clip_or_fail(nets, Some(1.0), 0, "expert gradient").is_ok()); // zero gradients
/// nets.visit_params_mut("", &mut |_, p| p.grad.fill(f32::NAN));
/// let err = clip_or_fail(nets, Some(1.0), 3, "expert gradient").unwrap_err();
/// assert!(matches!(err, StepError::NonFinite { iteration: 3, .. }));
/// ```
pub fn clip_or_fail(
    params: &mut dyn Parameters,
    max_norm: Option<f32>,
    iteration: usize,
    quantity: &'static str,
) -> Result<(), StepError> {
    vdd_nn::clip_grad_norm_checked(params, max_norm)
        .map_err(|_| StepError::NonFinite { iteration, quantity })
}

/// Soft cross-entropy `−Σ_b c_b Σ_z t_{bz} log q(z|s_b)` of the gating towards `targets`, and
/// its gradient with respect to the gating logits, `c_b (q(z|s_b) Σ_k t_{bk} − t_{bz})`,
/// written into `grad_logits` (`n x Z`).
///
/// `log_gating` and `targets` are `n·Z` row-major, `row_weights` (`c_b`) has length `n`.
///
/// ```
/// use vdd_moe::step::soft_cross_entropy;
/// let log_q = [0.5f32.ln(), 0.5f32.ln()];
/// let mut g = faer::Mat::<f32>::zeros(1, 2);
/// let loss = soft_cross_entropy(&log_q, &[1.0, 0.0], &[1.0], g.as_mut()).unwrap();
/// assert!((loss - 2.0f64.ln()).abs() < 1e-6);
/// assert!((g[(0, 0)] + 0.5).abs() < 1e-6 && (g[(0, 1)] - 0.5).abs() < 1e-6);
/// ```
pub fn soft_cross_entropy(
    log_gating: &[f32],
    targets: &[f32],
    row_weights: &[f32],
    mut grad_logits: MatMut<'_, f32>,
) -> Result<f64, CoreError> {
    let (n, z_n) = (row_weights.len(), grad_logits.ncols());
    check_shape("gating gradient", grad_logits.as_ref(), n, z_n)?;
    check_len("log gating", log_gating.len(), n * z_n)?;
    check_len("gating targets", targets.len(), n * z_n)?;
    check_finite_slice("gating targets", targets)?;
    check_finite_slice("gating row weights", row_weights)?;
    let mut loss = 0.0f64;
    for b in 0..n {
        let c = row_weights[b];
        let t = &targets[b * z_n..(b + 1) * z_n];
        let lg = &log_gating[b * z_n..(b + 1) * z_n];
        let t_sum: f32 = t.iter().sum();
        for k in 0..z_n {
            if t[k] != 0.0 {
                loss -= f64::from(c * t[k]) * f64::from(lg[k]);
            }
            grad_logits[(b, k)] = c * (lg[k].exp() * t_sum - t[k]);
        }
    }
    Ok(loss)
}

/// One optimiser step of the gating of `student` on a batch of `states` (`n x d_s`): a forward
/// pass, `loss(output, grad_logits)` — which returns the loss and writes its gradient with
/// respect to the gating logits into the `n x Z` matrix — then, when the loss is finite, the
/// backward pass, [`clip_or_fail`] to `max_grad_norm` and an Adam step with learning-rate
/// factor `lr_factor`. Returns the loss, or `None` (and does nothing) when the mixture's gating
/// is not learned. `grad_logits` is a reusable buffer (resized to `n x Z` when needed).
///
/// [`soft_cross_entropy`] is the usual loss:
///
/// ```
/// use faer::Mat;
/// use vdd_moe::step::{gating_step, soft_cross_entropy};
/// use vdd_moe::{GatingKind, Moe, MoeConfig};
/// use vdd_nn::{Adam, AdamConfig};
///
/// let mut mc = MoeConfig::toy(1, 2, 2);
/// mc.gating = GatingKind::Learned;
/// let mut moe = Moe::from_config(mc, 0).unwrap();
/// let mut adam = Adam::new(AdamConfig { lr: 1e-2, ..AdamConfig::default() });
/// let (states, mut grad) = (Mat::<f32>::zeros(4, 1), Mat::zeros(0, 0));
/// // Every row belongs to expert 0; rows weigh 1/4 each.
/// let (targets, weights) = ([1.0f32, 0.0].repeat(4), [0.25f32; 4]);
/// let mut losses = Vec::new();
/// for it in 0..50 {
///     let loss = gating_step(&mut moe, states.as_ref(), &mut adam, 1.0, None, it, &mut grad,
///         |out, g| soft_cross_entropy(&out.log_gating, &targets, &weights, g))
///         .unwrap()
///         .unwrap();
///     losses.push(loss);
/// }
/// assert!(losses[49] < losses[0]);
/// ```
#[allow(clippy::too_many_arguments)]
pub fn gating_step<E: Expert>(
    student: &mut Moe<E>,
    states: MatRef<'_, f32>,
    optimizer: &mut Adam,
    lr_factor: f32,
    max_grad_norm: Option<f32>,
    iteration: usize,
    grad_logits: &mut Mat<f32>,
    loss: impl FnOnce(&MoeOutput, MatMut<'_, f32>) -> Result<f64, CoreError>,
) -> Result<Option<f64>, StepError> {
    if !student.has_learned_gating() {
        return Ok(None);
    }
    let (n, z_n) = (states.nrows(), student.num_experts());
    if grad_logits.nrows() != n || grad_logits.ncols() != z_n {
        *grad_logits = Mat::zeros(n, z_n);
    }
    // Both passes, so that the output's batch size is the one `backward_gating` checks against.
    student.forward(states)?;
    let loss = loss(student.output(), grad_logits.as_mut())?;
    if !loss.is_finite() {
        return Err(StepError::NonFinite { iteration, quantity: "gating loss" });
    }
    if let Some(net) = student.gating_network_mut() {
        net.zero_grad();
    }
    student.backward_gating(grad_logits.as_ref())?;
    let Some(net) = student.gating_network_mut() else {
        return Ok(None);
    };
    clip_or_fail(net, max_grad_norm, iteration, "gating gradient")?;
    optimizer.step(net, lr_factor).map_err(MoeError::from)?;
    Ok(Some(loss))
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{GatingKind, MoeConfig};
    use approx::assert_relative_eq;
    use vdd_core::gaussian;

    #[test]
    fn soft_cross_entropy_gradient_matches_finite_differences() {
        let (n, z_n) = (3, 4);
        let logits: Vec<f32> = (0..n * z_n).map(|i| ((i * 7 % 5) as f32 - 2.0) * 0.6).collect();
        let log_softmax = |l: &[f32]| {
            let mut out = l.to_vec();
            for b in 0..n {
                let row = &mut out[b * z_n..(b + 1) * z_n];
                let lse = gaussian::log_sum_exp(row);
                row.iter_mut().for_each(|x| *x -= lse);
            }
            out
        };
        // Targets need not be normalised (row 2 sums to 0.5).
        let t = [0.1f32, 0.2, 0.3, 0.4, 1.0, 0.0, 0.0, 0.0, 0.25, 0.0, 0.25, 0.0];
        let c = [0.5f32, 0.2, 0.3];
        let mut g = Mat::zeros(n, z_n);
        soft_cross_entropy(&log_softmax(&logits), &t, &c, g.as_mut()).unwrap();
        let mut scratch = Mat::zeros(n, z_n);
        for i in 0..n * z_n {
            let h = 1e-2f32;
            let mut p = logits.clone();
            p[i] += h;
            let mut m = logits.clone();
            m[i] -= h;
            let lp = soft_cross_entropy(&log_softmax(&p), &t, &c, scratch.as_mut()).unwrap();
            let lm = soft_cross_entropy(&log_softmax(&m), &t, &c, scratch.as_mut()).unwrap();
            let fd = (lp - lm) / (2.0 * f64::from(h));
            assert_relative_eq!(f64::from(g[(i / z_n, i % z_n)]), fd, epsilon = 1e-4);
        }
    }

    fn learned(seed: u64) -> Moe {
        let mut mc = MoeConfig::toy(1, 2, 3);
        mc.gating = GatingKind::Learned;
        mc.gating_network.hidden_dim = 8;
        Moe::from_config(mc, seed).unwrap()
    }

    fn gating_params(moe: &Moe) -> Vec<f32> {
        let mut out = Vec::new();
        moe.visit_params("", &mut |_, p| out.extend_from_slice(&p.value));
        out
    }

    #[test]
    fn a_non_finite_loss_changes_nothing() {
        let mut moe = learned(1);
        let before = gating_params(&moe);
        let mut adam = Adam::new(vdd_nn::AdamConfig::default());
        let (states, mut grad) = (Mat::<f32>::zeros(2, 1), Mat::zeros(0, 0));
        let err =
            gating_step(&mut moe, states.as_ref(), &mut adam, 1.0, None, 4, &mut grad, |_, _| {
                Ok(f64::NAN)
            })
            .unwrap_err();
        assert!(matches!(err, StepError::NonFinite { iteration: 4, quantity: "gating loss" }));
        assert_eq!(gating_params(&moe), before);
        assert_eq!(adam.steps(), 0);
    }

    #[test]
    fn a_uniform_gating_is_not_stepped() {
        let mut moe = Moe::from_config(MoeConfig::toy(1, 2, 3), 0).unwrap();
        let mut adam = Adam::new(vdd_nn::AdamConfig::default());
        let (states, mut grad) = (Mat::<f32>::zeros(2, 1), Mat::zeros(0, 0));
        let r =
            gating_step(&mut moe, states.as_ref(), &mut adam, 1.0, None, 0, &mut grad, |_, _| {
                Ok(1.0)
            });
        assert!(matches!(r, Ok(None)));
    }
}
