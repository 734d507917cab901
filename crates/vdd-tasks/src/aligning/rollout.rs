//! Rollouts of any [`Policy`] on Aligning, and their aggregate metrics: success, D3IL's mean
//! distance, task entropy per test context (log base 2, as D3IL), the entropy of the
//! pooled modes, and the mode histogram.
//!
//! # Seeding, stepping and contexts
//!
//! The shared engine's ([`crate::episodes`]; [`AligningEnv`] is its
//! [`Env`](crate::episodes::Env) through [`ContextEnv`], as every D3IL task's, [`crate::d3il`]), with one
//! difference: [`EnvConfig::episodes_per_context`] consecutive episodes share a start (D3IL's
//! test contexts, each rolled out several times), so episode `i` of an evaluation with root
//! seed `s` starts from [`start_seed`]`(s, i / episodes_per_context)`. The policy is seeded per
//! episode or per lockstep chunk as everywhere; the results do not depend on the number of
//! threads.
//!
//! ```
//! use vdd_tasks::aligning::oracle::{AligningOracle, OracleConfig};
//! use vdd_tasks::aligning::rollout::{evaluate_cloned, EvalConfig, Stepping};
//! let oracle = AligningOracle::new(OracleConfig::default()).unwrap();
//! let cfg = EvalConfig { n_rollouts: 8, seed: 0, stepping: Stepping::PerEpisode, record: false };
//! let eval = evaluate_cloned(&oracle, 2, &cfg, 4).unwrap();
//! assert!(eval.metrics.success_rate > 0.6);
//! assert_eq!(eval.metrics.contexts, 2);
//! ```

use vdd_core::Policy;

pub use crate::d3il::rollout::{Metrics, evaluate_parallel_with, evaluate_with};
use crate::d3il::{ContextEnv, ContextOutcome, PhysicsConfig};
use crate::episodes::{self, SeedStreams};
pub use crate::episodes::{EvalConfig, Stepping, Trajectory};

use super::{
    ACTION_DIM, AligningEnv, AligningMode, EnvConfig, MAX_STEPS, N_MODES, OBS_DIM, Status,
};
use crate::Result;

/// What Aligning records of an episode beyond its status.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Outcome {
    /// The mode at the last step ([`AligningEnv::mode`]).
    pub mode: AligningMode,
    /// D3IL's mean distance at the last step ([`AligningEnv::mean_distance`]).
    pub mean_distance: f32,
    /// The start seed: the episode's test context.
    pub context: u64,
}

impl ContextOutcome for Outcome {
    type Mode = AligningMode;
    fn reached_mode(&self) -> Option<AligningMode> {
        Some(self.mode)
    }
    fn reached_p1(&self) -> Option<bool> {
        None
    }
    fn final_distance(&self) -> f32 {
        self.mean_distance
    }
    fn test_context(&self) -> u64 {
        self.context
    }
}

impl ContextEnv for AligningEnv {
    const NAME: &'static str = "aligning";
    const OBS_DIM: usize = OBS_DIM;
    const ACTION_DIM: usize = ACTION_DIM;
    const N_MODES: usize = N_MODES;
    const MAX_STEPS: usize = MAX_STEPS;
    const PHYSICS: PhysicsConfig = super::PHYSICS;
    const BENCHMARK: (usize, usize) = (60, 8);
    const STREAMS: SeedStreams = SeedStreams {
        episode: "aligning-episode",
        chunk: "aligning-chunk",
        start: "aligning-context",
    };
    const EVAL_STREAM: &'static str = "aligning-eval";
    const DEMO_STREAM: &'static str = "aligning-env";
    type Outcome = Outcome;

    fn from_config(config: EnvConfig) -> Result<Self> {
        AligningEnv::new(config)
    }

    fn start(&mut self, seed: u64) {
        AligningEnv::reset(self, seed);
    }

    fn observe_into(&self, out: &mut [f32]) {
        out.copy_from_slice(&self.observation());
    }

    fn step_checked(&mut self, action: &[f32], applied: &mut [f32]) {
        let a = AligningEnv::clip_action([action[0], action[1], action[2]]);
        applied.copy_from_slice(&a);
        self.step_clipped(a);
    }

    fn progress(&self) -> (Status, usize) {
        (AligningEnv::status(self), AligningEnv::steps(self))
    }

    fn outcome(&self) -> Outcome {
        Outcome { mode: self.mode(), mean_distance: self.mean_distance(), context: self.context() }
    }
}

/// The outcome of one Aligning episode: its [`Status`] (never [`Status::Running`]), its mode,
/// mean distance and context in `info`, its steps and, when asked for, its trajectory.
pub type Rollout = episodes::Rollout<AligningEnv>;

/// Every rollout of an Aligning evaluation, in episode order, and their [`Metrics`].
pub type Evaluation = crate::d3il::rollout::Evaluation<AligningEnv>;

/// The policy seed of episode `episode` under per-episode stepping.
pub fn episode_seed(seed: u64, episode: usize) -> u64 {
    episodes::episode_seed::<AligningEnv>(seed, episode)
}

/// The policy seed of chunk `chunk` under lockstep stepping.
pub fn chunk_seed(seed: u64, chunk: usize) -> u64 {
    episodes::chunk_seed::<AligningEnv>(seed, chunk)
}

/// The start seed of test context `context` of an evaluation with root seed `seed`.
pub fn start_seed(seed: u64, context: usize) -> u64 {
    episodes::start_seed::<AligningEnv>(seed, context)
}

/// Runs one episode from start seed `start` with the default environment: seeds the policy
/// with `policy_seed`, resets it, and acts through [`Policy::act_into`] until the episode ends.
pub fn rollout<P: Policy + ?Sized>(
    policy: &mut P,
    start: u64,
    policy_seed: u64,
    record: bool,
) -> Result<Rollout> {
    crate::d3il::rollout::rollout::<AligningEnv, P>(policy, start, policy_seed, record)
}

/// [`evaluate_parallel_with`] with `threads` clones of `policy` in the default environment,
/// `episodes_per_context` episodes per test context.
pub fn evaluate_cloned<P: Policy + Clone + Send>(
    policy: &P,
    threads: usize,
    cfg: &EvalConfig,
    episodes_per_context: usize,
) -> Result<Evaluation> {
    crate::d3il::rollout::evaluate_cloned::<AligningEnv, P>(
        policy,
        threads,
        cfg,
        episodes_per_context,
    )
}
