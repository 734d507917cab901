//! µs per action: the wall-clock time of one single-threaded `Policy::act` call, measured so
//! that the figures of several policies timed together stay comparable on a busy machine
//! ([`us_per_action`]). The Avoiding recipes report it for every method; it lives here, beside
//! the rollouts, so that a library user measures a policy the way the recipes do.

use std::time::Instant;

use faer::Mat;
use serde::{Deserialize, Serialize};
use vdd_core::Policy;

use crate::{Result, TaskError};

/// How [`us_per_action`] times policies.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Timing {
    /// Timed calls per policy, split over the rounds (at least one a round).
    pub calls: usize,
    /// Untimed calls before timing; their pace also sets how many calls a round needs.
    pub warmup: usize,
    /// The shortest round in milliseconds: a round of a few hundred microsecond-long calls is
    /// shorter than the machine's hiccups, and its figure jumps with them.
    pub min_round_ms: f64,
}

impl Default for Timing {
    /// The Avoiding recipe's: 2,000 calls after 100 untimed ones, rounds of at least 20 ms.
    fn default() -> Self {
        Self { calls: 2000, warmup: 100, min_round_ms: 20.0 }
    }
}

impl Timing {
    /// Checks the settings: calls > 0 and a finite, non-negative minimum round.
    ///
    /// ```
    /// use vdd_tasks::timing::Timing;
    /// assert!(Timing::default().check().is_ok());
    /// assert!(Timing { calls: 0, ..Timing::default() }.check().is_err());
    /// assert!(Timing { min_round_ms: f64::NAN, ..Timing::default() }.check().is_err());
    /// ```
    pub fn check(&self) -> Result<()> {
        if self.calls == 0 {
            return Err(TaskError::InvalidArgument("timing needs calls > 0".into()));
        }
        if !(self.min_round_ms.is_finite() && self.min_round_ms >= 0.0) {
            return Err(TaskError::InvalidArgument(format!(
                "the minimum timing round must be finite and >= 0 ms, got {}",
                self.min_round_ms
            )));
        }
        Ok(())
    }
}

/// Wall-clock µs of one `Policy::act` call of each policy, over the given episodes'
/// observations (a policy is seeded with `seed` at the start of each round and reset at each
/// episode start); single-threaded.
///
/// Each policy makes `timing.warmup` untimed calls, then [`TIMING_ROUNDS`] timed rounds over
/// the same observations, and its figure is the median round. A round makes `calls / rounds`
/// calls (rounded up), or more where the warm-up's pace says that many would take less than
/// `min_round_ms`. The policies take their rounds in turn (round 1 of every policy, then round
/// 2, ...), so a slow spell of the machine lasting a few rounds lands on every policy's
/// figures rather than on one policy's, and the ratios between policies stay fair.
///
/// ```
/// use faer::Mat;
/// use vdd_tasks::timing::{Timing, us_per_action};
/// use vdd_tasks::{AvoidingDemonstrator, DemonstratorConfig};
///
/// let demo = AvoidingDemonstrator::new(DemonstratorConfig::default())?;
/// let episodes = vec![Mat::from_fn(20, 4, |t, j| [0.525, -0.28 + 0.01 * t as f32][j % 2])];
/// let timing = Timing { calls: 50, warmup: 10, min_round_ms: 0.0 };
/// let us = us_per_action(&mut [demo], &episodes, timing, 0)?;
/// assert!(us[0] > 0.0 && us[0].is_finite());
/// # Ok::<(), vdd_tasks::TaskError>(())
/// ```
pub fn us_per_action<P: Policy>(
    policies: &mut [P],
    episodes: &[Mat<f32>],
    timing: Timing,
    seed: u64,
) -> Result<Vec<f64>> {
    timing.check()?;
    let Timing { calls, warmup, min_round_ms } = timing;
    if episodes.iter().all(|ep| ep.nrows() == 0) {
        return Err(TaskError::InvalidArgument("timing needs observations".into()));
    }
    let (mut obs, mut action) = (Vec::new(), Vec::new());
    // `n` calls of `policy` over the episodes (from the first, again and again).
    let mut run = |n: usize, policy: &mut P| -> Result<()> {
        obs.resize(policy.obs_dim(), 0.0);
        action.resize(policy.action_dim(), 0.0);
        let mut done = 0;
        'outer: loop {
            for ep in episodes {
                policy.reset();
                for t in 0..ep.nrows() {
                    if done == n {
                        break 'outer;
                    }
                    for (j, x) in obs.iter_mut().enumerate() {
                        *x = ep[(t, j)];
                    }
                    policy.act_into(&obs, &mut action)?;
                    done += 1;
                }
            }
        }
        Ok(())
    };
    let mut per_round = vec![calls.div_ceil(TIMING_ROUNDS); policies.len()];
    for (policy, n) in policies.iter_mut().zip(&mut per_round) {
        policy.seed(seed);
        let t0 = Instant::now();
        run(warmup, policy)?;
        if warmup > 0 && min_round_ms > 0.0 {
            let us_per_call = t0.elapsed().as_secs_f64() * 1e6 / warmup as f64;
            let needed = (min_round_ms * 1e3 / us_per_call.max(1e-3)).ceil();
            *n = (*n).max(needed.min(MAX_ROUND_CALLS as f64) as usize);
        }
    }
    let mut rounds = vec![[0.0f64; TIMING_ROUNDS]; policies.len()];
    for r in 0..TIMING_ROUNDS {
        for ((policy, &n), times) in policies.iter_mut().zip(&per_round).zip(&mut rounds) {
            policy.seed(seed);
            let t0 = Instant::now();
            run(n, policy)?;
            times[r] = t0.elapsed().as_secs_f64() * 1e6 / n as f64;
        }
    }
    Ok(rounds
        .into_iter()
        .map(|mut times| {
            times.sort_by(f64::total_cmp);
            times[TIMING_ROUNDS / 2]
        })
        .collect())
}

/// The most calls a timing round makes however fast the policy (a policy that does nothing
/// would otherwise be called billions of times).
const MAX_ROUND_CALLS: usize = 1_000_000;

/// Rounds [`us_per_action`] takes the median of.
pub const TIMING_ROUNDS: usize = 5;

#[cfg(test)]
mod tests {
    use super::*;

    /// Counts its calls (and is reset per episode).
    #[derive(Clone)]
    struct Probe {
        calls: f32,
    }
    impl Policy for Probe {
        fn obs_dim(&self) -> usize {
            4
        }
        fn action_dim(&self) -> usize {
            3
        }
        fn reset(&mut self) {
            self.calls = 0.0;
        }
        fn act_into(&mut self, _: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
            self.calls += 1.0;
            action.fill(self.calls);
            Ok(())
        }
    }

    /// Timing settings, positionally.
    fn timing(calls: usize, warmup: usize, min_round_ms: f64) -> Timing {
        Timing { calls, warmup, min_round_ms }
    }

    /// Counts every call (across resets); each call takes at least `.1` µs.
    struct Count(usize, f64);
    impl Policy for Count {
        fn obs_dim(&self) -> usize {
            4
        }
        fn action_dim(&self) -> usize {
            1
        }
        fn act_into(&mut self, _: &[f32], _: &mut [f32]) -> vdd_core::Result<()> {
            let t0 = Instant::now();
            while t0.elapsed().as_secs_f64() * 1e6 < self.1 {}
            self.0 += 1;
            Ok(())
        }
    }

    #[test]
    fn timing_counts_calls() {
        let eps = vec![Mat::<f32>::zeros(5, 4)];
        let us = us_per_action(&mut [Probe { calls: 0.0 }], &eps, timing(12, 3, 0.0), 0).unwrap();
        assert!(us.len() == 1 && us[0] >= 0.0 && us[0].is_finite());
        assert!(us_per_action(&mut [Probe { calls: 0.0 }], &[], timing(12, 3, 0.0), 0).is_err());
        for bad in [timing(12, 3, -1.0), timing(12, 3, f64::NAN), timing(0, 3, 0.0)] {
            assert!(bad.check().is_err(), "{bad:?}");
            assert!(us_per_action(&mut [Probe { calls: 0.0 }], &eps, bad, 0).is_err());
        }
        assert!(timing(12, 3, 20.0).check().is_ok());

        let mut c = [Count(0, 0.0), Count(0, 0.0)];
        assert_eq!(us_per_action(&mut c, &eps, timing(12, 3, 0.0), 0).unwrap().len(), 2);
        for c in c {
            assert_eq!(c.0, 3 + 5 * 3, "warm-up, then 5 rounds of ceil(12 / 5) calls");
        }
    }

    #[test]
    fn fast_policies_are_timed_over_rounds_of_the_minimum_length() {
        let eps = vec![Mat::<f32>::zeros(7, 4)];
        // A slow policy (20 µs a call) and one 10x faster.
        let mut p = [Count(0, 20.0), Count(0, 2.0)];
        let us = us_per_action(&mut p, &eps, timing(10, 50, 2.0), 0).unwrap();
        assert!(us[0] >= 20.0 && us[1] >= 2.0, "{us:?}");
        // 2 ms rounds need about 100 calls of 20 µs; without the minimum a round makes 2. Only
        // a warm-up of 50 calls preempted for 8 ms or more would give fewer than 11 a round.
        assert!(p[0].0 > 50 + 5 * 10, "{} calls", p[0].0);
        assert!(p[0].0 <= 50 + 5 * 100, "{} calls: rounds longer than the minimum needs", p[0].0);
        // Each policy's rounds are sized by its own pace: the fast one makes more calls.
        assert!(p[1].0 > p[0].0, "{} vs {} calls", p[1].0, p[0].0);
    }
}
