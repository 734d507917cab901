//! The evaluation a Block-Push run reports, shaped like Avoiding's
//! ([`crate::avoiding::EvalProtocol`]): how many episodes, how the evaluation seed derives from
//! the run seed, and how the environments are stepped. The same protocol and run seed give the
//! same figures bit for bit, on any number of threads.

use serde::{Deserialize, Serialize};
use vdd_core::{Policy, Seeds};

use super::rollout::{EvalConfig, Evaluation, evaluate_cloned};
use crate::{Result, TaskError};

/// A Block-Push evaluation: `rollouts` episodes from the evaluation seed
/// [`EvalProtocol::seed`]`(run_seed)` (the same start states for every method of a run seed),
/// `lockstep_batch` environments stepped together (0: one episode at a time).
///
/// ```
/// use vdd_tasks::block_push::EvalProtocol;
/// use vdd_tasks::block_push::oracle::{BlockPushOracle, OracleConfig};
///
/// let oracle = BlockPushOracle::new(OracleConfig::default())?;
/// let protocol = EvalProtocol { rollouts: 8, lockstep_batch: 4 };
/// let one = protocol.evaluate(&oracle, 3, 1, false)?;
/// let two = protocol.evaluate(&oracle, 3, 2, false)?;
/// assert_eq!(one.metrics, two.metrics); // threads do not matter
/// assert_eq!(one.metrics.rollouts, 8);
/// # Ok::<(), vdd_tasks::TaskError>(())
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EvalProtocol {
    /// Episodes.
    pub rollouts: usize,
    /// Environments stepped together (0: one episode at a time).
    pub lockstep_batch: usize,
}

impl Default for EvalProtocol {
    /// 200 episodes (VDD's final Block-Push evaluation) in lockstep batches of 50.
    fn default() -> Self {
        Self { rollouts: 200, lockstep_batch: 50 }
    }
}

impl EvalProtocol {
    /// Checks the ranges: `rollouts` in `1..=10^6`, `lockstep_batch` in `0..=10^4`.
    pub fn check(&self) -> Result<()> {
        if !(1..=1_000_000).contains(&self.rollouts) || self.lockstep_batch > 10_000 {
            return Err(TaskError::InvalidArgument(format!(
                "block-push protocol: rollouts {} must be in 1..=1e6 and lockstep_batch {} <= 1e4",
                self.rollouts, self.lockstep_batch
            )));
        }
        Ok(())
    }

    /// The root seed of the evaluation of run seed `run_seed` (start states and policy seeds
    /// derive from it): `Seeds::new(run_seed).child("block-push-eval")`.
    ///
    /// ```
    /// use vdd_tasks::block_push::EvalProtocol;
    /// assert_ne!(EvalProtocol::seed(0), EvalProtocol::seed(1));
    /// ```
    pub fn seed(run_seed: u64) -> u64 {
        Seeds::new(run_seed).child("block-push-eval").root()
    }

    /// The rollouts' configuration for run seed `run_seed` (`record`: keep trajectories).
    pub fn config(&self, run_seed: u64, record: bool) -> EvalConfig {
        EvalConfig::protocol(self.rollouts, self.lockstep_batch, Self::seed(run_seed), record)
    }

    /// Rolls `policy` out for run seed `run_seed` on `threads` clones of it, in the default
    /// environment: success (p2), p1, task entropy and mode counts.
    pub fn evaluate<P: Policy + Clone + Send>(
        &self,
        policy: &P,
        run_seed: u64,
        threads: usize,
        record: bool,
    ) -> Result<Evaluation> {
        self.check()?;
        evaluate_cloned(policy, threads, &self.config(run_seed, record))
    }
}
