//! The evaluation a Aligning run reports, shaped like Block-Push's
//! ([`crate::block_push::EvalProtocol`]) with D3IL's test contexts: `contexts` start states,
//! each rolled out `rollouts_per_context` times (D3IL's `aligning_config.yaml`: 60 × 8), the task
//! entropy taken per context. The same protocol and run seed give the same figures bit for
//! bit, on any number of threads.

use serde::{Deserialize, Serialize};
use vdd_core::{Policy, Seeds};

use super::EnvConfig;
use super::rollout::{EvalConfig, Evaluation, evaluate_parallel_with};
use crate::{Result, TaskError};

/// A Aligning evaluation: `contexts × rollouts_per_context` episodes from the evaluation seed
/// [`EvalProtocol::seed`]`(run_seed)` (the same contexts for every method of a run seed),
/// `lockstep_batch` environments stepped together (0: one episode at a time).
///
/// ```
/// use vdd_tasks::aligning::EvalProtocol;
/// use vdd_tasks::aligning::oracle::{AligningOracle, OracleConfig};
///
/// let oracle = AligningOracle::new(OracleConfig::default())?;
/// let protocol = EvalProtocol { contexts: 2, rollouts_per_context: 3, lockstep_batch: 4 };
/// let one = protocol.evaluate(&oracle, 3, 1, false)?;
/// let two = protocol.evaluate(&oracle, 3, 2, false)?;
/// assert_eq!(one.metrics, two.metrics); // threads do not matter
/// assert_eq!((one.metrics.rollouts, one.metrics.contexts), (6, 2));
/// # Ok::<(), vdd_tasks::TaskError>(())
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct EvalProtocol {
    /// Test contexts (start states).
    pub contexts: usize,
    /// Episodes per context.
    pub rollouts_per_context: usize,
    /// Environments stepped together (0: one episode at a time).
    pub lockstep_batch: usize,
}

impl Default for EvalProtocol {
    /// D3IL's benchmark: 60 contexts × 8 rollouts, in lockstep batches of 48.
    fn default() -> Self {
        Self { contexts: 60, rollouts_per_context: 8, lockstep_batch: 48 }
    }
}

impl EvalProtocol {
    /// Checks the ranges: `contexts` and `rollouts_per_context` at least 1 with at most `10^6`
    /// episodes, `lockstep_batch` in `0..=10^4`.
    pub fn check(&self) -> Result<()> {
        let n = self.contexts.saturating_mul(self.rollouts_per_context);
        if self.contexts == 0
            || self.rollouts_per_context == 0
            || n > 1_000_000
            || self.lockstep_batch > 10_000
        {
            return Err(TaskError::InvalidArgument(format!(
                "aligning protocol: contexts {} and rollouts_per_context {} must be >= 1 with at \
                 most 1e6 episodes, lockstep_batch {} <= 1e4",
                self.contexts, self.rollouts_per_context, self.lockstep_batch
            )));
        }
        Ok(())
    }

    /// Episodes in all: `contexts × rollouts_per_context`.
    pub fn rollouts(&self) -> usize {
        self.contexts * self.rollouts_per_context
    }

    /// The root seed of the evaluation of run seed `run_seed`:
    /// `Seeds::new(run_seed).child("aligning-eval")`.
    ///
    /// ```
    /// use vdd_tasks::aligning::EvalProtocol;
    /// assert_ne!(EvalProtocol::seed(0), EvalProtocol::seed(1));
    /// ```
    pub fn seed(run_seed: u64) -> u64 {
        Seeds::new(run_seed).child("aligning-eval").root()
    }

    /// The rollouts' configuration for run seed `run_seed` (`record`: keep trajectories).
    pub fn config(&self, run_seed: u64, record: bool) -> EvalConfig {
        EvalConfig::protocol(self.rollouts(), self.lockstep_batch, Self::seed(run_seed), record)
    }

    /// The environment: the default one with `rollouts_per_context` episodes per context.
    pub fn env(&self) -> EnvConfig {
        EnvConfig { episodes_per_context: self.rollouts_per_context, ..EnvConfig::default() }
    }

    /// Rolls `policy` out for run seed `run_seed` on `threads` clones of it: success, mean distance,
    /// task entropy and mode counts.
    pub fn evaluate<P: Policy + Clone + Send>(
        &self,
        policy: &P,
        run_seed: u64,
        threads: usize,
        record: bool,
    ) -> Result<Evaluation> {
        self.check()?;
        if threads == 0 {
            return Err(TaskError::InvalidArgument("threads must be at least 1".into()));
        }
        let cfg = self.config(run_seed, record);
        let mut policies: Vec<P> =
            (0..threads.min(cfg.n_units().max(1))).map(|_| policy.clone()).collect();
        evaluate_parallel_with(&mut policies, &cfg, &self.env())
    }
}
