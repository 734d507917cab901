//! The states a policy visits: [`Visiting`] keeps every observation row a policy is asked to
//! act on, and [`visited_states`] rolls a policy out through its deployment spec and returns
//! the states its model saw, in the model's own state space (features and observation window
//! applied), the space of a training set's states. What a distilled student's gating is
//! fitted on beyond the demonstrations (the states the student itself reaches).

use faer::{Mat, MatMut, MatRef};
use vdd_core::{CoreError, Policy};
use vdd_data::{DeploySpec, Windowed};

use crate::episodes::{Env, EvalConfig, Stepping, TaskMetrics, evaluate};
use crate::{Result, TaskError};

/// A policy that keeps every observation row it acts on (up to a limit), then acts as `P`.
///
/// ```
/// use vdd_core::{CoreError, Policy};
/// use vdd_tasks::visits::Visiting;
///
/// struct Still;
/// impl Policy for Still {
///     fn obs_dim(&self) -> usize { 2 }
///     fn action_dim(&self) -> usize { 1 }
///     fn act_into(&mut self, _: &[f32], a: &mut [f32]) -> Result<(), CoreError> {
///         a[0] = 0.0;
///         Ok(())
///     }
/// }
/// let mut v = Visiting::new(Still, 2);
/// for obs in [[0.0f32, 1.0], [2.0, 3.0], [4.0, 5.0]] {
///     v.act(&obs)?;
/// }
/// let states = v.into_states();
/// assert_eq!((states.nrows(), states[(1, 1)]), (2, 3.0)); // the first two rows only
/// # Ok::<(), CoreError>(())
/// ```
#[derive(Debug, Clone)]
pub struct Visiting<P> {
    inner: P,
    rows: Vec<f32>,
    max_rows: usize,
}

impl<P: Policy> Visiting<P> {
    /// Wraps `inner`, keeping at most `max_rows` observation rows.
    pub fn new(inner: P, max_rows: usize) -> Self {
        Self { inner, rows: Vec::new(), max_rows }
    }

    /// The rows kept so far, in the order they were acted on (`n x obs_dim`).
    pub fn into_states(self) -> Mat<f32> {
        let d = self.inner.obs_dim().max(1);
        let n = self.rows.len() / d;
        Mat::from_fn(n, d, |i, j| self.rows[i * d + j])
    }

    fn keep(&mut self, row: impl Iterator<Item = f32>) {
        if self.rows.len() < self.max_rows.saturating_mul(self.inner.obs_dim()) {
            self.rows.extend(row);
        }
    }
}

impl<P: Policy> Policy for Visiting<P> {
    fn obs_dim(&self) -> usize {
        self.inner.obs_dim()
    }
    fn action_dim(&self) -> usize {
        self.inner.action_dim()
    }
    fn reset(&mut self) {
        self.inner.reset();
    }
    fn seed(&mut self, seed: u64) {
        self.inner.seed(seed);
    }
    fn last_experts(&self) -> &[usize] {
        self.inner.last_experts()
    }
    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
        self.inner.act_into(obs, action)?;
        self.keep(obs.iter().copied());
        Ok(())
    }
    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        actions: MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        self.inner.act_batch(obs, actions)?;
        for i in 0..obs.nrows() {
            self.keep((0..obs.ncols()).map(|j| obs[(i, j)]));
        }
        Ok(())
    }
}

/// Rolls `policy` (acting on the model's states) out through `spec` for `cfg.n_rollouts`
/// episodes of task `E`, one at a time on the calling thread (per-episode stepping whatever
/// `cfg` says, so ended episodes add no rows), and returns the states it acted on, in episode
/// order, at most `max_rows` of them. Deterministic for `cfg.seed`.
pub fn visited_states<E: Env, M: TaskMetrics<E>, P: Policy + Clone>(
    env: &E::Config,
    policy: &P,
    spec: &DeploySpec,
    cfg: &EvalConfig,
    max_rows: usize,
) -> Result<Mat<f32>> {
    let wrap = |e: vdd_data::DataError| TaskError::Core(CoreError::implementor(e));
    let visiting = Visiting::new(policy.clone(), max_rows);
    let mut windowed = Windowed::new(visiting, spec.clone()).map_err(wrap)?;
    let cfg = EvalConfig { stepping: Stepping::PerEpisode, record: false, ..cfg.clone() };
    evaluate::<E, M, _>(env, &mut windowed, &cfg)?;
    Ok(windowed.into_inner().into_states())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Metrics;
    use crate::{AvoidingDemonstrator, AvoidingEnv, DemonstratorConfig};

    #[test]
    fn visited_states_are_the_episodes_observations_in_order_and_seeded() {
        let demo = AvoidingDemonstrator::new(DemonstratorConfig::default()).unwrap();
        let spec = DeploySpec::default();
        let cfg = EvalConfig::protocol(3, 2, 11, false); // lockstep asked: visits step per episode
        let states = visited_states::<AvoidingEnv, Metrics, _>(&(), &demo, &spec, &cfg, 1 << 20);
        let states = states.unwrap();
        let mut recorded = EvalConfig { stepping: Stepping::PerEpisode, record: true, ..cfg };
        recorded.n_rollouts = 3;
        let mut d = demo.clone();
        let eval: crate::avoiding::rollout::Evaluation =
            crate::episodes::evaluate(&(), &mut d, &recorded).unwrap();
        let steps: usize = eval.rollouts.iter().map(|r| r.steps).sum();
        assert_eq!(states.nrows(), steps);
        let first = eval.rollouts[0].trajectory.as_ref().unwrap();
        assert_eq!(states[(1, 0)], first.observations[(1, 0)]);
        let again = visited_states::<AvoidingEnv, Metrics, _>(&(), &demo, &spec, &cfg, 1 << 20);
        assert_eq!(states, again.unwrap());
        let capped = visited_states::<AvoidingEnv, Metrics, _>(&(), &demo, &spec, &cfg, 5);
        assert_eq!(capped.unwrap().nrows(), 5);
        let other = EvalConfig { seed: 12, ..cfg };
        let moved = visited_states::<AvoidingEnv, Metrics, _>(&(), &demo, &spec, &other, 1 << 20);
        assert_ne!(states, moved.unwrap());
    }
}
