//! The evaluation a D3IL contact run reports, shaped like Block-Push's
//! ([`crate::block_push::EvalProtocol`]) with D3IL's test contexts: `contexts` start states,
//! each rolled out `rollouts_per_context` times (D3IL's benchmark, [`ContextEnv::BENCHMARK`]:
//! Pushing 30 × 16, Aligning 60 × 8), the task entropy taken per context. The same protocol and
//! run seed give the same figures bit for bit, on any number of threads.

use std::marker::PhantomData;

use serde::{Deserialize, Serialize};
use vdd_core::{Policy, Seeds};

use super::rollout::{EvalConfig, Evaluation, evaluate_parallel_with};
use super::{ContextEnv, EnvConfig};
use crate::{Result, TaskError};

/// An evaluation of the task of environment `E` (`pushing::EvalProtocol` is
/// `EvalProtocol<PushingEnv>`): `contexts × rollouts_per_context` episodes from the evaluation
/// seed [`EvalProtocol::seed`]`(run_seed)` (the same contexts for every method of a run seed),
/// `lockstep_batch` environments stepped together (0: one episode at a time).
///
/// ```
/// use vdd_tasks::pushing::EvalProtocol;
/// use vdd_tasks::pushing::oracle::{PushingOracle, OracleConfig};
///
/// let oracle = PushingOracle::new(OracleConfig::default())?;
/// let protocol = EvalProtocol::new(2, 3, 4); // contexts, rollouts per context, lockstep batch
/// let one = protocol.evaluate(&oracle, 3, 1, false)?;
/// let two = protocol.evaluate(&oracle, 3, 2, false)?;
/// assert_eq!(one.metrics, two.metrics); // threads do not matter
/// assert_eq!((one.metrics.rollouts, one.metrics.contexts), (6, 2));
/// # Ok::<(), vdd_tasks::TaskError>(())
/// ```
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields, bound = "")]
pub struct EvalProtocol<E> {
    /// Test contexts (start states).
    pub contexts: usize,
    /// Episodes per context.
    pub rollouts_per_context: usize,
    /// Environments stepped together (0: one episode at a time).
    pub lockstep_batch: usize,
    #[serde(skip)]
    task: PhantomData<fn() -> E>,
}

impl<E: ContextEnv> Default for EvalProtocol<E> {
    /// D3IL's benchmark ([`ContextEnv::BENCHMARK`]: Pushing 30 contexts × 16 rollouts,
    /// Aligning 60 × 8), in lockstep batches of 48.
    fn default() -> Self {
        Self::new(E::BENCHMARK.0, E::BENCHMARK.1, 48)
    }
}

impl<E> Clone for EvalProtocol<E> {
    fn clone(&self) -> Self {
        *self
    }
}

impl<E> Copy for EvalProtocol<E> {}

impl<E> PartialEq for EvalProtocol<E> {
    fn eq(&self, other: &Self) -> bool {
        (self.contexts, self.rollouts_per_context, self.lockstep_batch)
            == (other.contexts, other.rollouts_per_context, other.lockstep_batch)
    }
}

impl<E> Eq for EvalProtocol<E> {}

impl<E> std::fmt::Debug for EvalProtocol<E> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("EvalProtocol")
            .field("contexts", &self.contexts)
            .field("rollouts_per_context", &self.rollouts_per_context)
            .field("lockstep_batch", &self.lockstep_batch)
            .finish()
    }
}

impl<E> EvalProtocol<E> {
    /// `contexts` test contexts × `rollouts_per_context` episodes, `lockstep_batch`
    /// environments stepped together (0: one episode at a time).
    pub const fn new(contexts: usize, rollouts_per_context: usize, lockstep_batch: usize) -> Self {
        Self { contexts, rollouts_per_context, lockstep_batch, task: PhantomData }
    }
}

impl<E: ContextEnv> EvalProtocol<E> {
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
                "{} protocol: contexts {} and rollouts_per_context {} must be >= 1 with at \
                 most 1e6 episodes, lockstep_batch {} <= 1e4",
                E::NAME,
                self.contexts,
                self.rollouts_per_context,
                self.lockstep_batch
            )));
        }
        Ok(())
    }

    /// Episodes in all: `contexts × rollouts_per_context`.
    pub fn rollouts(&self) -> usize {
        self.contexts * self.rollouts_per_context
    }

    /// The root seed of the evaluation of run seed `run_seed`:
    /// `Seeds::new(run_seed).child(E::EVAL_STREAM)` (Pushing's stream is `pushing-eval`).
    ///
    /// ```
    /// use vdd_tasks::pushing::EvalProtocol;
    /// assert_ne!(EvalProtocol::seed(0), EvalProtocol::seed(1));
    /// ```
    pub fn seed(run_seed: u64) -> u64 {
        Seeds::new(run_seed).child(E::EVAL_STREAM).root()
    }

    /// The rollouts' configuration for run seed `run_seed` (`record`: keep trajectories).
    pub fn config(&self, run_seed: u64, record: bool) -> EvalConfig {
        EvalConfig::protocol(self.rollouts(), self.lockstep_batch, Self::seed(run_seed), record)
    }

    /// The environment: the default one with `rollouts_per_context` episodes per context.
    pub fn env(&self) -> EnvConfig<E> {
        EnvConfig::with_episodes_per_context(self.rollouts_per_context)
    }

    /// Rolls `policy` out for run seed `run_seed` on `threads` clones of it: success, p1 (on a
    /// task that counts it), mean distance, task entropy and mode counts.
    pub fn evaluate<P: Policy + Clone + Send>(
        &self,
        policy: &P,
        run_seed: u64,
        threads: usize,
        record: bool,
    ) -> Result<Evaluation<E>> {
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
