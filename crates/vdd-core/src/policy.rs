//! [`Policy`]: anything that maps observations to actions, from a scripted demonstrator to a
//! distilled mixture of experts.

use faer::reborrow::Reborrow;
use faer::{MatMut, MatRef};

use crate::error::{CoreError, Result, check_len, check_shape};

/// A control policy.
///
/// Implementors provide [`Policy::act_into`]; [`Policy::act`] and [`Policy::act_batch`] have
/// default implementations (override `act_batch` when a batched forward pass is faster).
/// Policies that sample (stochastic gating, diffusion noise) draw from their own seeded stream,
/// which [`Policy::seed`] resets.
///
/// ```
/// use vdd_core::{CoreError, Policy};
///
/// /// Moves towards the origin with gain 0.5.
/// struct Home;
/// impl Policy for Home {
///     fn obs_dim(&self) -> usize { 2 }
///     fn action_dim(&self) -> usize { 2 }
///     fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> Result<(), CoreError> {
///         vdd_core::check_len("observation", obs.len(), 2)?;
///         for (a, o) in action.iter_mut().zip(obs) { *a = -0.5 * o; }
///         Ok(())
///     }
/// }
/// assert_eq!(Home.act(&[2.0, -4.0]).unwrap(), vec![-1.0, 2.0]);
/// assert!(Home.act(&[1.0]).is_err());
/// ```
pub trait Policy {
    /// Dimension of one observation.
    fn obs_dim(&self) -> usize;

    /// Dimension of one action.
    fn action_dim(&self) -> usize;

    /// Clears any per-episode state (observation history, buffered action chunk, held expert).
    fn reset(&mut self) {}

    /// Re-seeds the policy's own random stream (no-op for deterministic policies).
    fn seed(&mut self, _seed: u64) {}

    /// For a mixture of experts: the expert each row of the last [`act_into`](Policy::act_into)
    /// or [`act_batch`](Policy::act_batch) acted with (one entry per row). Empty for policies
    /// without experts, the default.
    fn last_experts(&self) -> &[usize] {
        &[]
    }

    /// Writes the action for `obs` into `action` (`action_dim()` long).
    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> Result<()>;

    /// Returns the action for `obs`.
    fn act(&mut self, obs: &[f32]) -> Result<Vec<f32>> {
        let mut action = vec![0.0; self.action_dim()];
        self.act_into(obs, &mut action)?;
        Ok(action)
    }

    /// Acts for a batch of independent observations (`n x obs_dim` into `n x action_dim`).
    fn act_batch(&mut self, obs: MatRef<'_, f32>, mut actions: MatMut<'_, f32>) -> Result<()> {
        let n = obs.nrows();
        check_shape("observations", obs, n, self.obs_dim())?;
        check_shape("actions", actions.rb(), n, self.action_dim())?;
        let mut o = vec![0.0; self.obs_dim()];
        let mut a = vec![0.0; self.action_dim()];
        for i in 0..n {
            for (j, x) in o.iter_mut().enumerate() {
                *x = obs[(i, j)];
            }
            self.act_into(&o, &mut a)?;
            for (j, x) in a.iter().enumerate() {
                actions[(i, j)] = *x;
            }
        }
        Ok(())
    }

    /// Whether [`Policy::log_likelihood`] is available.
    fn has_likelihood(&self) -> bool {
        false
    }

    /// Writes the exact `log π(a|s)` of each row into `out`, for policies that have one.
    fn log_likelihood(
        &mut self,
        _obs: MatRef<'_, f32>,
        _actions: MatRef<'_, f32>,
        _out: &mut [f32],
    ) -> Result<()> {
        Err(CoreError::Unsupported("log-likelihood"))
    }
}

impl<P: Policy + ?Sized> Policy for Box<P> {
    fn obs_dim(&self) -> usize {
        (**self).obs_dim()
    }
    fn action_dim(&self) -> usize {
        (**self).action_dim()
    }
    fn reset(&mut self) {
        (**self).reset()
    }
    fn seed(&mut self, seed: u64) {
        (**self).seed(seed)
    }
    fn last_experts(&self) -> &[usize] {
        (**self).last_experts()
    }
    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> Result<()> {
        (**self).act_into(obs, action)
    }
    fn act_batch(&mut self, obs: MatRef<'_, f32>, actions: MatMut<'_, f32>) -> Result<()> {
        (**self).act_batch(obs, actions)
    }
    fn has_likelihood(&self) -> bool {
        (**self).has_likelihood()
    }
    fn log_likelihood(
        &mut self,
        obs: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
        out: &mut [f32],
    ) -> Result<()> {
        (**self).log_likelihood(obs, actions, out)
    }
}

/// Validates the arguments of [`Policy::act_into`] against the policy's dimensions.
pub fn check_act_args<P: Policy + ?Sized>(policy: &P, obs: &[f32], action: &[f32]) -> Result<()> {
    check_len("observation", obs.len(), policy.obs_dim())?;
    check_len("action", action.len(), policy.action_dim())?;
    if obs.iter().any(|x| !x.is_finite()) {
        return Err(CoreError::NonFinite { what: "observation" });
    }
    Ok(())
}
