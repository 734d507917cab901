//! Success and task entropy over training: [`CurveProtocol`] evaluates a policy at checkpoints
//! of its training on held-out rollout streams, apart from the final evaluation's
//! ([`EvalProtocol`]), so the curves never see the episodes the reported figures come from.

use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Policy, Seeds};
use vdd_data::{DeploySpec, Windowed};

use super::protocol::EvalProtocol;
use super::rollout::{Metrics, evaluate_cloned};
use crate::{Result, TaskError};

/// Curves over training: `points` evaluations spread evenly over a run
/// ([`CurveProtocol::checkpoints`]), each of `rollouts` episodes (stepped `lockstep_batch` at a
/// time, on one thread: trainings run side by side) whose policy seeds come from
/// [`CurveProtocol::seed`], a stream of its own. Every checkpoint of a run meets the same
/// episode seeds, so the points differ by the policy only.
///
/// ```
/// use vdd_tasks::AvoidingDemonstrator;
/// use vdd_tasks::DemonstratorConfig;
/// use vdd_tasks::avoiding::{CurveProtocol, EvalProtocol};
///
/// let curve = CurveProtocol { points: 5, rollouts: 20, lockstep_batch: 10 };
/// assert_eq!(curve.checkpoints(1000), [200, 400, 600, 800, 1000]);
/// assert_ne!(CurveProtocol::seed(0), EvalProtocol::seed(0));
/// let demo = AvoidingDemonstrator::new(DemonstratorConfig::default())?;
/// let m = curve.evaluate(&demo, 0)?;
/// assert_eq!(m.rollouts, 20);
/// assert!(m.success_rate > 0.5);
/// # Ok::<(), vdd_tasks::TaskError>(())
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct CurveProtocol {
    /// Evaluations per training run (0: no curves).
    pub points: usize,
    /// Episodes per evaluation.
    pub rollouts: usize,
    /// Environments stepped together (0: one episode at a time).
    pub lockstep_batch: usize,
}

/// The most evaluations [`CurveProtocol::check`] accepts per run.
pub const MAX_CURVE_POINTS: usize = 1000;

impl CurveProtocol {
    /// Checks the documented ranges: `points` at most [`MAX_CURVE_POINTS`] and, with points,
    /// the episodes as [`EvalProtocol::check`] wants them.
    pub fn check(&self) -> Result<()> {
        if self.points > MAX_CURVE_POINTS {
            return Err(TaskError::InvalidArgument(format!(
                "curve points must be <= {MAX_CURVE_POINTS}, got {}",
                self.points
            )));
        }
        if self.points > 0 {
            self.episodes().check()?;
        }
        Ok(())
    }

    /// Whether curves are taken at all.
    pub fn enabled(&self) -> bool {
        self.points > 0
    }

    /// The root seed of the curve episodes of run seed `run_seed`:
    /// `Seeds::new(run_seed).child("avoiding-curve")`, apart from the final evaluation's
    /// ([`EvalProtocol::seed`]) and from every training stream.
    pub fn seed(run_seed: u64) -> u64 {
        Seeds::new(run_seed).child("avoiding-curve").root()
    }

    /// The iterations of a run of `iterations` after which to evaluate
    /// ([`vdd_core::trainer::checkpoints`]).
    pub fn checkpoints(&self, iterations: usize) -> Vec<usize> {
        vdd_core::trainer::checkpoints(iterations, self.points)
    }

    /// Rolls `policy` out on one thread on the curve episodes of run seed `run_seed`.
    pub fn evaluate<P: Policy + Clone + Send>(&self, policy: &P, run_seed: u64) -> Result<Metrics> {
        let mut cfg = self.episodes().config(run_seed, false);
        cfg.seed = Self::seed(run_seed);
        Ok(evaluate_cloned(policy, 1, &cfg)?.metrics)
    }

    fn episodes(&self) -> EvalProtocol {
        EvalProtocol { rollouts: self.rollouts, lockstep_batch: self.lockstep_batch }
    }
}

/// The series of [`DeployedCurves`]: held-out success rate.
pub const CURVE_SUCCESS: &str = "held-out success rate";
/// The series of [`DeployedCurves`]: held-out task entropy.
pub const CURVE_ENTROPY: &str = "held-out task entropy";

/// A [`CurveProtocol`] for policies that act through a [`DeploySpec`] (features, observation
/// window, action chunk): the curves over training of a recipe's students
/// ([`vdd_core::curves::CurveEval`]), the series [`CURVE_SUCCESS`] and [`CURVE_ENTROPY`].
#[derive(Debug, Clone, PartialEq, Serialize)]
pub struct DeployedCurves {
    /// Checkpoints and episodes.
    pub protocol: CurveProtocol,
    /// How the policies act on raw observations.
    pub spec: DeploySpec,
}

impl<P: Policy + Clone + Send> vdd_core::curves::CurveEval<P> for DeployedCurves {
    type Error = TaskError;
    fn checkpoints(&self, iterations: usize) -> Vec<usize> {
        self.protocol.checkpoints(iterations)
    }
    fn evaluate(&self, policy: &P, run_seed: u64) -> Result<Vec<(String, f64)>> {
        let wrapped = Windowed::new(policy.clone(), self.spec.clone())
            .map_err(|e| TaskError::Core(CoreError::implementor(e)))?;
        let m = self.protocol.evaluate(&wrapped, run_seed)?;
        let series = [(CURVE_SUCCESS, m.success_rate), (CURVE_ENTROPY, m.task_entropy)];
        Ok(series.into_iter().map(|(k, v)| (k.to_owned(), v)).collect())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{AvoidingDemonstrator, DemonstratorConfig};

    #[test]
    fn curve_episodes_are_held_out_from_the_final_evaluation() {
        let demo = AvoidingDemonstrator::new(DemonstratorConfig::default()).unwrap();
        let curve = CurveProtocol { points: 2, rollouts: 30, lockstep_batch: 0 };
        let final_eval = EvalProtocol { rollouts: 30, lockstep_batch: 0 };
        let a = curve.evaluate(&demo, 1).unwrap();
        assert_eq!(a, curve.evaluate(&demo, 1).unwrap(), "deterministic");
        let b = final_eval.evaluate(&demo, 1, 1, false).unwrap().metrics;
        assert_ne!(a.mode_counts, b.mode_counts, "another stream of episode seeds");
        assert!(curve.check().is_ok());
        let none = CurveProtocol { points: 0, rollouts: 0, lockstep_batch: 0 };
        assert!(none.check().is_ok() && !none.enabled() && none.checkpoints(10).is_empty());
        let deployed = DeployedCurves { protocol: curve, spec: DeploySpec::default() };
        let points = vdd_core::curves::CurveEval::evaluate(&deployed, &demo, 1).unwrap();
        let want = [
            (CURVE_SUCCESS.to_owned(), a.success_rate),
            (CURVE_ENTROPY.to_owned(), a.task_entropy),
        ];
        assert_eq!(points, want, "through the identity spec, the protocol's figures");
        let bad = CurveProtocol { points: 2, rollouts: 0, lockstep_batch: 0 };
        assert!(bad.check().is_err());
        assert!(CurveProtocol { points: MAX_CURVE_POINTS + 1, ..curve }.check().is_err());
    }
}
