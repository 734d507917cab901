//! Trained policies as one evaluable type, observation windows and action chunks at rollout
//! time, and the µs-per-action measurement.

use std::time::Instant;

use faer::reborrow::ReborrowMut;
use faer::{Mat, MatMut, MatRef};
use vdd_consistency::{ConsistencyModel, TrajectoryModel};
use vdd_core::{CoreError, Policy, check_act_args, check_shape};
use vdd_diffusion::DiffusionTeacher;
use vdd_moe::Moe;

/// A trained policy of any method.
#[derive(Debug, Clone)]
pub enum TrainedPolicy {
    /// A diffusion teacher (DDPM, BESO, and their one-step versions).
    Teacher(Box<DiffusionTeacher>),
    /// A mixture of experts (VDD, EM, IMC).
    Moe(Box<Moe>),
    /// A consistency model (CD).
    Consistency(Box<ConsistencyModel>),
    /// A consistency trajectory model (CTM).
    Trajectory(Box<TrajectoryModel>),
}

macro_rules! each {
    ($self:expr, $p:ident => $e:expr) => {
        match $self {
            TrainedPolicy::Teacher($p) => $e,
            TrainedPolicy::Moe($p) => $e,
            TrainedPolicy::Consistency($p) => $e,
            TrainedPolicy::Trajectory($p) => $e,
        }
    };
}

impl Policy for TrainedPolicy {
    fn obs_dim(&self) -> usize {
        each!(self, p => Policy::obs_dim(p))
    }
    fn action_dim(&self) -> usize {
        each!(self, p => Policy::action_dim(p))
    }
    fn reset(&mut self) {
        each!(self, p => p.reset())
    }
    fn seed(&mut self, seed: u64) {
        each!(self, p => p.seed(seed))
    }
    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
        each!(self, p => p.act_into(obs, action))
    }
    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        actions: MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        each!(self, p => p.act_batch(obs, actions))
    }
}

/// Runs a policy trained on observation windows of `W` steps and action chunks of `C` steps as
/// a one-observation, one-action policy: it keeps the last `W` observations (the first one
/// repeated at the start of an episode, as windows padded at the start are built) and
/// executes the first `execute ≤ C` actions of each predicted chunk before predicting again.
///
/// State is kept per batch row, so lockstep evaluation (one `act_batch` per step, row `i`
/// always the same environment between `reset`s) works; `act_into` uses row 0. With `W = 1`
/// and `C = execute = 1` it is a pass-through.
#[derive(Debug, Clone)]
pub struct Windowed<P> {
    inner: P,
    window: usize,
    chunk: usize,
    execute: usize,
    obs_dim: usize,
    act_dim: usize,
    rows: Vec<RowState>,
    batch_obs: Mat<f32>,
    batch_act: Mat<f32>,
    need: Vec<usize>,
    features: Option<fn(&mut [f32])>,
}

#[derive(Debug, Clone, Default)]
struct RowState {
    /// The last `W` observations, oldest first (empty at episode start).
    history: Vec<f32>,
    /// The current chunk (`C · d_act`) and the next index to execute.
    chunk: Vec<f32>,
    next: usize,
}

impl<P: Policy> Windowed<P> {
    /// Wraps `inner`, whose observation is `window · obs_dim` and action `chunk · act_dim`.
    pub fn new(inner: P, window: usize, chunk: usize, execute: usize) -> Result<Self, String> {
        if window == 0 || chunk == 0 || execute == 0 || execute > chunk {
            return Err(format!(
                "invalid window {window} / chunk {chunk} / execute {execute} (need 1 <= execute <= chunk)"
            ));
        }
        if inner.obs_dim() % window != 0 || inner.action_dim() % chunk != 0 {
            return Err(format!(
                "policy dims {}x{} do not split into window {window} and chunk {chunk}",
                inner.obs_dim(),
                inner.action_dim()
            ));
        }
        let (obs_dim, act_dim) = (inner.obs_dim() / window, inner.action_dim() / chunk);
        Ok(Self {
            inner,
            window,
            chunk,
            execute,
            obs_dim,
            act_dim,
            rows: Vec::new(),
            batch_obs: Mat::zeros(0, 0),
            batch_act: Mat::zeros(0, 0),
            need: Vec::new(),
            features: None,
        })
    }

    /// Applies `features` (in place, to each raw observation) before the inner policy sees it:
    /// the same map the training observations went through.
    pub fn with_features(mut self, features: fn(&mut [f32])) -> Self {
        self.features = Some(features);
        self
    }

    fn passthrough(&self) -> bool {
        self.window == 1 && self.chunk == 1 && self.features.is_none()
    }

    fn push_obs(&mut self, row: usize, obs: &mut [f32]) {
        if let Some(f) = self.features {
            f(obs);
        }
        let (w, d) = (self.window, self.obs_dim);
        let r = &mut self.rows[row];
        if r.history.is_empty() {
            r.history = obs.repeat(w);
        } else {
            r.history.copy_within(d.., 0);
            r.history[(w - 1) * d..].copy_from_slice(obs);
        }
    }
}

impl<P: Policy> Policy for Windowed<P> {
    fn obs_dim(&self) -> usize {
        self.obs_dim
    }
    fn action_dim(&self) -> usize {
        self.act_dim
    }
    fn reset(&mut self) {
        self.rows.clear();
        self.inner.reset();
    }
    fn seed(&mut self, seed: u64) {
        self.inner.seed(seed);
    }
    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
        if self.passthrough() {
            return self.inner.act_into(obs, action);
        }
        check_act_args(self, obs, action)?;
        let o = MatRef::from_row_major_slice(obs, 1, obs.len());
        let a = MatMut::from_row_major_slice_mut(action, 1, self.act_dim);
        self.act_batch(o, a)
    }
    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        mut actions: MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        if self.passthrough() {
            return self.inner.act_batch(obs, actions);
        }
        let n = obs.nrows();
        check_shape("observations", obs, n, self.obs_dim)?;
        check_shape("actions", actions.rb_mut().as_ref(), n, self.act_dim)?;
        if self.rows.len() != n {
            self.rows = vec![RowState::default(); n];
        }
        let mut o = vec![0.0f32; self.obs_dim];
        self.need.clear();
        for i in 0..n {
            for (j, x) in o.iter_mut().enumerate() {
                *x = obs[(i, j)];
            }
            if o.iter().any(|x| !x.is_finite()) {
                return Err(CoreError::NonFinite { what: "observation" });
            }
            self.push_obs(i, &mut o);
            let r = &self.rows[i];
            if r.chunk.is_empty() || r.next >= self.execute {
                self.need.push(i);
            }
        }
        if !self.need.is_empty() {
            let (m, win_dim, chunk_dim) =
                (self.need.len(), self.window * self.obs_dim, self.chunk * self.act_dim);
            if self.batch_obs.nrows() != m {
                self.batch_obs = Mat::zeros(m, win_dim);
                self.batch_act = Mat::zeros(m, chunk_dim);
            }
            for (b, &i) in self.need.iter().enumerate() {
                for (j, x) in self.rows[i].history.iter().enumerate() {
                    self.batch_obs[(b, j)] = *x;
                }
            }
            self.inner.act_batch(self.batch_obs.as_ref(), self.batch_act.as_mut())?;
            for (b, &i) in self.need.iter().enumerate() {
                let r = &mut self.rows[i];
                r.chunk.clear();
                r.chunk.extend((0..chunk_dim).map(|j| self.batch_act[(b, j)]));
                r.next = 0;
            }
        }
        for i in 0..n {
            let r = &mut self.rows[i];
            let start = r.next * self.act_dim;
            for j in 0..self.act_dim {
                actions[(i, j)] = r.chunk[start + j];
            }
            r.next += 1;
        }
        Ok(())
    }
}

/// How [`us_per_action`] times policies.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Timing {
    /// Timed calls per policy, split over the rounds (at least one a round).
    pub calls: usize,
    /// Untimed calls before timing; their pace also sets how many calls a round needs.
    pub warmup: usize,
    /// The shortest round in milliseconds: a round of a few hundred microsecond-long calls is
    /// shorter than the machine's hiccups, and its figure jumps with them.
    pub min_round_ms: f64,
}

impl Timing {
    /// Checks the settings: calls > 0 and a finite, non-negative minimum round.
    pub fn check(&self) -> Result<(), CoreError> {
        if self.calls == 0 {
            return Err(CoreError::Config("timing needs calls > 0".into()));
        }
        if !(self.min_round_ms.is_finite() && self.min_round_ms >= 0.0) {
            return Err(CoreError::Config(format!(
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
pub fn us_per_action<P: Policy>(
    policies: &mut [P],
    episodes: &[Mat<f32>],
    timing: Timing,
    seed: u64,
) -> Result<Vec<f64>, CoreError> {
    timing.check()?;
    let Timing { calls, warmup, min_round_ms } = timing;
    if episodes.iter().all(|ep| ep.nrows() == 0) {
        return Err(CoreError::Config("timing needs observations".into()));
    }
    let (mut obs, mut action) = (Vec::new(), Vec::new());
    // `n` calls of `policy` over the episodes (from the first, again and again).
    let mut run = |n: usize, policy: &mut P| -> Result<(), CoreError> {
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

    /// Observation window of 2 (4 numbers), chunk of 3 (action = [sum of window, call count, t]).
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
        fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
            self.calls += 1.0;
            action[0] = obs[0] * 1000.0 + obs[2];
            action[1] = self.calls;
            action[2] = obs[1] * 1000.0 + obs[3];
            Ok(())
        }
    }

    #[test]
    fn windows_pad_at_start_and_chunks_are_executed_in_order() {
        // obs_dim 2, act_dim 1; window 2, chunk 3, execute 2.
        let mut w = Windowed::new(Probe { calls: 0.0 }, 2, 3, 2).unwrap();
        assert_eq!((w.obs_dim(), w.action_dim()), (2, 1));
        let a0 = w.act(&[1.0, 2.0]).unwrap(); // window [o0, o0] -> chunk [1001, 1, 2002]
        assert_eq!(a0, vec![1001.0]);
        let a1 = w.act(&[3.0, 4.0]).unwrap(); // second action of the chunk
        assert_eq!(a1, vec![1.0]);
        let a2 = w.act(&[5.0, 6.0]).unwrap(); // new chunk from window [o1, o2]
        assert_eq!(a2, vec![3005.0]);
        w.reset();
        let a = w.act(&[7.0, 8.0]).unwrap();
        assert_eq!(a, vec![7007.0], "reset clears the history");
        assert!(Windowed::new(Probe { calls: 0.0 }, 2, 3, 4).is_err());
        assert!(Windowed::new(Probe { calls: 0.0 }, 3, 3, 1).is_err());
    }

    #[test]
    fn batched_rows_keep_their_own_state() {
        let mut w = Windowed::new(Probe { calls: 0.0 }, 2, 3, 3).unwrap();
        let obs = faer::mat![[1.0f32, 0.0], [2.0, 0.0]];
        let mut act = Mat::<f32>::zeros(2, 1);
        w.act_batch(obs.as_ref(), act.as_mut()).unwrap();
        assert_eq!((act[(0, 0)], act[(1, 0)]), (1001.0, 2002.0));
        w.act_batch(obs.as_ref(), act.as_mut()).unwrap();
        assert_eq!((act[(0, 0)], act[(1, 0)]), (1.0, 2.0), "second chunk entry: call count");
    }

    #[test]
    fn features_are_applied_to_every_observation_before_the_policy() {
        /// Echoes its observation's first entry as the action.
        #[derive(Clone)]
        struct Echo;
        impl Policy for Echo {
            fn obs_dim(&self) -> usize {
                1
            }
            fn action_dim(&self) -> usize {
                1
            }
            fn reset(&mut self) {}
            fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
                action[0] = obs[0];
                Ok(())
            }
        }
        let mut w = Windowed::new(Echo, 1, 1, 1).unwrap().with_features(|o| o[0] *= 10.0);
        let mut a = [0.0f32];
        for x in [1.0f32, 2.0] {
            w.act_into(&[x], &mut a).unwrap();
            assert_eq!(a[0], 10.0 * x);
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
