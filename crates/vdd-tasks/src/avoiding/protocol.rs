//! The evaluation the Avoiding recipes report: how many episodes, how the policy is seeded from
//! the run seed, and how the environments are stepped. Anyone who rolls out a saved policy with
//! the same [`EvalProtocol`] and run seed gets the recipe's figures bit for bit.

use serde::{Deserialize, Serialize};
use vdd_core::{Policy, Seeds};

use super::CurveProtocol;
use super::rollout::{EvalConfig, Evaluation, evaluate_cloned};
use crate::timing::Timing;
use crate::{Result, TaskError};

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
    /// Checks the documented ranges: `rollouts` in `1..=10^7`, `lockstep_batch` in
    /// `0..=10^5` (0: one episode at a time), and the memory of the recorded episodes.
    pub fn check(&self) -> crate::Result<()> {
        if !(1..=10_000_000).contains(&self.rollouts) {
            let n = self.rollouts;
            return Err(TaskError::InvalidArgument(format!(
                "rollouts must be in 1..=1e7, got {n}"
            )));
        }
        if self.lockstep_batch > 100_000 {
            let b = self.lockstep_batch;
            return Err(TaskError::InvalidArgument(format!(
                "lockstep_batch must be <= 1e5, got {b}"
            )));
        }
        let bytes = vdd_core::memory::product(&[self.rollouts, super::MAX_STEPS, 8, 4]);
        vdd_core::memory::check_fits(&format!("{} rollouts", self.rollouts), bytes)?;
        Ok(())
    }

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
        EvalConfig::protocol(self.rollouts, self.lockstep_batch, Self::seed(run_seed), record)
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

    /// For each step of each of the first `n` recorded rollouts of `eval` (this protocol's
    /// evaluation of `policy` for run seed `run_seed`), the expert the policy acted with
    /// ([`Policy::last_experts`]): the evaluation units holding those rollouts run again on this
    /// thread with a copy of the policy (the same seeds, so the same rollouts, which is checked).
    /// It needs a policy asked at every step for every row: a mixture with observation window
    /// and action chunk 1.
    ///
    /// Errors: [`TaskError::InvalidArgument`] when the replay differs from `eval` or the policy
    /// reports no expert for some step; the rollouts' own errors.
    pub fn replay_experts<P: Policy + Clone>(
        &self,
        policy: &P,
        run_seed: u64,
        eval: &Evaluation,
        n: usize,
    ) -> Result<Vec<Vec<usize>>> {
        let unit = self.lockstep_batch.max(1);
        let rollouts = n.div_ceil(unit).saturating_mul(unit).min(self.rollouts);
        let cfg = EvalProtocol { rollouts, ..*self }.config(run_seed, true);
        let mut log = ExpertLog { policy: policy.clone(), units: Vec::new() };
        let again = super::rollout::evaluate(&mut log, &cfg)?;
        if eval.rollouts.get(..rollouts) != Some(&again.rollouts[..]) {
            let why =
                "the rollouts did not replay for expert attribution (another policy or seed?)";
            return Err(TaskError::InvalidArgument(why.into()));
        }
        let mut out = Vec::with_capacity(n);
        for (i, r) in again.rollouts.iter().take(n).enumerate() {
            let steps = log.units.get(i / unit).map_or(&[][..], |u| &u[..]);
            let ids: Option<Vec<usize>> =
                (0..r.steps).map(|t| steps.get(t)?.get(i % unit).copied()).collect();
            let why = "the policy did not report an expert for every row and step";
            out.push(ids.ok_or_else(|| TaskError::InvalidArgument(why.into()))?);
        }
        Ok(out)
    }
}

/// A policy that logs, for each evaluation unit (from one `reset` to the next) and each call,
/// the expert of each row ([`Policy::last_experts`]).
struct ExpertLog<P> {
    policy: P,
    units: Vec<Vec<Vec<usize>>>,
}

impl<P: Policy> ExpertLog<P> {
    fn log(&mut self) {
        let experts = self.policy.last_experts().to_vec();
        if let Some(unit) = self.units.last_mut() {
            unit.push(experts);
        }
    }
}

impl<P: Policy> Policy for ExpertLog<P> {
    fn obs_dim(&self) -> usize {
        self.policy.obs_dim()
    }
    fn action_dim(&self) -> usize {
        self.policy.action_dim()
    }
    fn reset(&mut self) {
        self.policy.reset();
        self.units.push(Vec::new());
    }
    fn seed(&mut self, seed: u64) {
        self.policy.seed(seed);
    }
    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
        self.policy.act_into(obs, action)?;
        self.log();
        Ok(())
    }
    fn act_batch(
        &mut self,
        obs: faer::MatRef<'_, f32>,
        actions: faer::MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        self.policy.act_batch(obs, actions)?;
        self.log();
        Ok(())
    }
}

/// The Avoiding recipes' `[eval]` table: the final evaluation ([`Self::protocol`]), the
/// timing ([`Self::timing`]) and the curves over training ([`Self::curves`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AvoidingEval {
    /// Rollouts per method and seed.
    pub rollouts: usize,
    /// Environments stepped together with one batched `act_batch` (0: one episode at a time).
    pub lockstep_batch: usize,
    /// Evaluation threads (0: all cores).
    pub threads: usize,
    /// Timed single-observation `Policy::act` calls for µs per action (single thread).
    pub timing_calls: usize,
    /// Untimed calls before timing.
    pub timing_warmup: usize,
    /// The shortest timing round in milliseconds: a fast policy makes more than
    /// `timing_calls / 5` calls a round (see [`us_per_action`](crate::timing::us_per_action)).
    pub timing_min_round_ms: f64,
    /// Curves over training: evaluations per training run of every method trained in the run
    /// (0: none; see [`CurveProtocol`]).
    pub curve_points: usize,
    /// Episodes per curve evaluation (held out from the final evaluation's), stepped
    /// `lockstep_batch` at a time on one thread.
    pub curve_rollouts: usize,
}

impl AvoidingEval {
    /// The rollouts' protocol (episodes and lockstep batch; the seed comes from the run seed).
    pub fn protocol(&self) -> EvalProtocol {
        EvalProtocol { rollouts: self.rollouts, lockstep_batch: self.lockstep_batch }
    }

    /// The curves over training.
    pub fn curves(&self) -> CurveProtocol {
        CurveProtocol {
            points: self.curve_points,
            rollouts: self.curve_rollouts,
            lockstep_batch: self.lockstep_batch,
        }
    }

    /// Checks the documented ranges of the rollouts ([`EvalProtocol::check`]), the timing
    /// ([`Timing::check`]) and the curves ([`CurveProtocol::check`]).
    pub fn check(&self) -> Result<()> {
        self.timing().check()?;
        self.protocol().check()?;
        self.curves().check()
    }

    /// The threads the rollouts run on: `threads`, or every core when it is 0.
    pub fn eval_threads(&self) -> usize {
        match self.threads {
            0 => std::thread::available_parallelism().map_or(1, |p| p.get()),
            n => n,
        }
    }

    /// The settings of `us_per_action`.
    pub fn timing(&self) -> Timing {
        Timing {
            calls: self.timing_calls,
            warmup: self.timing_warmup,
            min_round_ms: self.timing_min_round_ms,
        }
    }
}

/// The Avoiding recipes' `[plots]` table: the figures of a run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlotSettings {
    /// Write plots at all.
    pub enabled: bool,
    /// Rollouts drawn per method in the trajectory figure.
    pub trajectories: usize,
    /// Also write PNGs (SVG always).
    pub png: bool,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::avoiding::FarLeft;

    /// [`FarLeft`] reporting expert 7 for every row it acts on, one entry per row of a call.
    #[derive(Clone)]
    struct Tagged {
        rows: Vec<usize>,
    }

    impl Policy for Tagged {
        fn obs_dim(&self) -> usize {
            4
        }
        fn action_dim(&self) -> usize {
            2
        }
        fn last_experts(&self) -> &[usize] {
            &self.rows
        }
        fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
            self.rows = vec![7];
            FarLeft.act_into(obs, action)
        }
        fn act_batch(
            &mut self,
            obs: faer::MatRef<'_, f32>,
            actions: faer::MatMut<'_, f32>,
        ) -> vdd_core::Result<()> {
            self.rows = vec![7; obs.nrows()];
            FarLeft.act_batch(obs, actions)
        }
    }

    #[test]
    fn replayed_experts_cover_every_step_of_the_recorded_rollouts() {
        let protocol = EvalProtocol { rollouts: 6, lockstep_batch: 4 };
        let policy = Tagged { rows: Vec::new() };
        let eval = protocol.evaluate(&policy, 1, 2, true).unwrap();
        let experts = protocol.replay_experts(&policy, 1, &eval, 5).unwrap();
        assert_eq!(experts.len(), 5);
        for (ids, r) in experts.iter().zip(&eval.rollouts) {
            assert_eq!(ids.len(), r.steps);
            assert!(ids.iter().all(|&z| z == 7));
        }
        // Another run seed replays other rollouts: refused, not misattributed.
        let other = protocol.evaluate(&FarLeft, 2, 1, true).unwrap();
        assert!(protocol.replay_experts(&FarLeft, 1, &other, 5).is_err());
        // A policy without experts cannot be attributed.
        let plain = protocol.evaluate(&FarLeft, 1, 1, true).unwrap();
        assert!(protocol.replay_experts(&FarLeft, 1, &plain, 2).is_err());
    }

    #[test]
    fn the_eval_table_checks_its_rollouts_timing_and_curves() {
        let ok = AvoidingEval {
            rollouts: 10,
            lockstep_batch: 5,
            threads: 0,
            timing_calls: 100,
            timing_warmup: 10,
            timing_min_round_ms: 1.0,
            curve_points: 2,
            curve_rollouts: 10,
        };
        assert!(ok.check().is_ok() && ok.eval_threads() >= 1);
        assert_eq!(AvoidingEval { threads: 3, ..ok.clone() }.eval_threads(), 3);
        assert!(AvoidingEval { rollouts: 0, ..ok.clone() }.check().is_err());
        assert!(AvoidingEval { timing_min_round_ms: f64::NAN, ..ok.clone() }.check().is_err());
        assert!(AvoidingEval { curve_points: 1001, ..ok }.check().is_err());
    }
}
