//! Rollouts of any [`Policy`] on Pushing, and their aggregate metrics: success, p1, D3IL's
//! mean distance, task entropy per test context (log base 4, as D3IL), the entropy of the
//! pooled modes, and the mode histogram.
//!
//! # Seeding, stepping and contexts
//!
//! The shared engine's ([`crate::episodes`]; [`PushingEnv`] is its
//! [`Env`](crate::episodes::Env) through [`ContextEnv`], as every D3IL task's, [`crate::d3il`]), with one
//! difference: [`EnvConfig::episodes_per_context`] consecutive episodes share a start (D3IL's
//! test contexts, each rolled out several times), so episode `i` of an evaluation with root
//! seed `s` starts from [`start_seed`]`(s, i / episodes_per_context)`. The policy is seeded per
//! episode or per lockstep chunk as everywhere; the results do not depend on the number of
//! threads.
//!
//! ```
//! use vdd_tasks::pushing::oracle::{PushingOracle, OracleConfig};
//! use vdd_tasks::pushing::rollout::{evaluate_cloned, EvalConfig, Stepping};
//! let oracle = PushingOracle::new(OracleConfig::default()).unwrap();
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

use super::{ACTION_DIM, EnvConfig, MAX_STEPS, N_MODES, OBS_DIM, PushingEnv, PushingMode, Status};
use crate::Result;

/// What Pushing records of an episode beyond its status.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Outcome {
    /// The mode, once both boxes visited complementary targets ([`PushingEnv::mode`]).
    pub mode: Option<PushingMode>,
    /// Whether at least one box reached a target (p1).
    pub p1: bool,
    /// D3IL's mean distance at the last step ([`PushingEnv::mean_distance`]).
    pub mean_distance: f32,
    /// The start seed: the episode's test context.
    pub context: u64,
}

impl ContextOutcome for Outcome {
    type Mode = PushingMode;
    fn reached_mode(&self) -> Option<PushingMode> {
        self.mode
    }
    fn reached_p1(&self) -> Option<bool> {
        Some(self.p1)
    }
    fn final_distance(&self) -> f32 {
        self.mean_distance
    }
    fn test_context(&self) -> u64 {
        self.context
    }
}

impl ContextEnv for PushingEnv {
    const NAME: &'static str = "pushing";
    const OBS_DIM: usize = OBS_DIM;
    const ACTION_DIM: usize = ACTION_DIM;
    const N_MODES: usize = N_MODES;
    const MAX_STEPS: usize = MAX_STEPS;
    const PHYSICS: PhysicsConfig = super::PHYSICS;
    const BENCHMARK: (usize, usize) = (30, 16);
    const STREAMS: SeedStreams = SeedStreams {
        episode: "pushing-episode",
        chunk: "pushing-chunk",
        start: "pushing-context",
    };
    const EVAL_STREAM: &'static str = "pushing-eval";
    const DEMO_STREAM: &'static str = "pushing-env";
    type Outcome = Outcome;

    fn from_config(config: EnvConfig) -> Result<Self> {
        PushingEnv::new(config)
    }

    fn start(&mut self, seed: u64) {
        PushingEnv::reset(self, seed);
    }

    fn observe_into(&self, out: &mut [f32]) {
        out.copy_from_slice(&self.observation());
    }

    fn step_checked(&mut self, action: &[f32], applied: &mut [f32]) {
        let a = PushingEnv::clip_action([action[0], action[1]]);
        applied.copy_from_slice(&a);
        self.step_clipped(a);
    }

    fn progress(&self) -> (Status, usize) {
        (PushingEnv::status(self), PushingEnv::steps(self))
    }

    fn outcome(&self) -> Outcome {
        Outcome {
            mode: self.mode(),
            p1: self.p1(),
            mean_distance: self.mean_distance(),
            context: self.context(),
        }
    }
}

/// The outcome of one Pushing episode: its [`Status`] (never [`Status::Running`]), its mode,
/// p1, mean distance and context in `info`, its steps and, when asked for, its trajectory.
pub type Rollout = episodes::Rollout<PushingEnv>;

/// Every rollout of a Pushing evaluation, in episode order, and their [`Metrics`].
pub type Evaluation = crate::d3il::rollout::Evaluation<PushingEnv>;

/// The policy seed of episode `episode` under per-episode stepping.
pub fn episode_seed(seed: u64, episode: usize) -> u64 {
    episodes::episode_seed::<PushingEnv>(seed, episode)
}

/// The policy seed of chunk `chunk` under lockstep stepping.
pub fn chunk_seed(seed: u64, chunk: usize) -> u64 {
    episodes::chunk_seed::<PushingEnv>(seed, chunk)
}

/// The start seed of test context `context` of an evaluation with root seed `seed`.
pub fn start_seed(seed: u64, context: usize) -> u64 {
    episodes::start_seed::<PushingEnv>(seed, context)
}

/// Runs one episode from start seed `start` with the default environment: seeds the policy
/// with `policy_seed`, resets it, and acts through [`Policy::act_into`] until the episode ends.
pub fn rollout<P: Policy + ?Sized>(
    policy: &mut P,
    start: u64,
    policy_seed: u64,
    record: bool,
) -> Result<Rollout> {
    crate::d3il::rollout::rollout::<PushingEnv, P>(policy, start, policy_seed, record)
}

/// [`evaluate_parallel_with`] with `threads` clones of `policy` in the default environment,
/// `episodes_per_context` episodes per test context.
pub fn evaluate_cloned<P: Policy + Clone + Send>(
    policy: &P,
    threads: usize,
    cfg: &EvalConfig,
    episodes_per_context: usize,
) -> Result<Evaluation> {
    crate::d3il::rollout::evaluate_cloned::<PushingEnv, P>(
        policy,
        threads,
        cfg,
        episodes_per_context,
    )
}
