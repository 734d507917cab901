//! The evaluation the Avoiding recipes report: how many episodes, how the policy is seeded from
//! the run seed, and how the environments are stepped. Anyone who rolls out a saved policy with
//! the same [`EvalProtocol`] and run seed gets the recipe's figures bit for bit.

use serde::{Deserialize, Serialize};
use vdd_core::{Policy, Seeds};

use super::rollout::{EvalConfig, Evaluation, Stepping, evaluate_cloned};
use crate::Result;

/// The recipes' evaluation of a policy trained with run seed `seed`: `rollouts` episodes whose
/// policy seeds come from [`EvalProtocol::seed`]`(seed)` (the same for every method of a run
/// seed, so methods meet the same episode seeds), `lockstep_batch` environments stepped together
/// with one `act_batch` per step (0: one episode at a time; see
/// [`rollout`](super::rollout) for the seeding of each).
///
/// The lockstep batch is part of the protocol: it decides which policy seed each episode gets,
/// so a stochastic policy gives other (equally distributed) figures under another batch size.
/// The number of threads is not: the figures are the same for any number.
///
/// ```
/// use vdd_tasks::avoiding::EvalProtocol;
/// use vdd_tasks::AvoidingDemonstrator;
/// use vdd_tasks::DemonstratorConfig;
///
/// let demo = AvoidingDemonstrator::new(DemonstratorConfig::default())?;
/// let protocol = EvalProtocol { rollouts: 40, ..EvalProtocol::default() };
/// let one = protocol.evaluate(&demo, 3, 1, false)?;
/// let two = protocol.evaluate(&demo, 3, 2, false)?;
/// assert_eq!(one.metrics, two.metrics); // threads do not matter
/// assert_eq!(one.metrics.rollouts, 40);
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
    /// The Avoiding recipe's: 500 episodes in lockstep batches of 50.
    fn default() -> Self {
        Self { rollouts: 500, lockstep_batch: 50 }
    }
}

impl EvalProtocol {
    /// The root seed of the evaluation of run seed `run_seed`: the policy seeds of the episodes
    /// ([`EvalConfig::seed`]) and of the timing
    /// ([`us_per_action`](crate::timing::us_per_action)) derive from it. It is
    /// `Seeds::new(run_seed).child("avoiding-eval")`, independent of every training stream of
    /// the run.
    ///
    /// ```
    /// use vdd_tasks::avoiding::EvalProtocol;
    /// assert_ne!(EvalProtocol::seed(0), EvalProtocol::seed(1));
    /// assert_eq!(EvalProtocol::seed(0), vdd_core::Seeds::new(0).child("avoiding-eval").root());
    /// ```
    pub fn seed(run_seed: u64) -> u64 {
        Seeds::new(run_seed).child("avoiding-eval").root()
    }

    /// The rollouts' configuration for run seed `run_seed` (`record`: keep trajectories).
    ///
    /// ```
    /// use vdd_tasks::avoiding::EvalProtocol;
    /// use vdd_tasks::Stepping;
    /// let c = EvalProtocol::default().config(0, false);
    /// assert_eq!((c.n_rollouts, c.stepping), (500, Stepping::Lockstep { batch_size: 50 }));
    /// let c = EvalProtocol { rollouts: 10, lockstep_batch: 0 }.config(0, true);
    /// assert_eq!((c.stepping, c.record), (Stepping::PerEpisode, true));
    /// ```
    pub fn config(&self, run_seed: u64, record: bool) -> EvalConfig {
        let stepping = match self.lockstep_batch {
            0 => Stepping::PerEpisode,
            b => Stepping::Lockstep { batch_size: b },
        };
        EvalConfig { n_rollouts: self.rollouts, seed: Self::seed(run_seed), stepping, record }
    }

    /// Rolls `policy` out for run seed `run_seed` on `threads` clones of it
    /// ([`evaluate_cloned`]): the recipe's success rate, task entropy and mode counts.
    pub fn evaluate<P: Policy + Clone + Send>(
        &self,
        policy: &P,
        run_seed: u64,
        threads: usize,
        record: bool,
    ) -> Result<Evaluation> {
        evaluate_cloned(policy, threads, &self.config(run_seed, record))
    }
}
