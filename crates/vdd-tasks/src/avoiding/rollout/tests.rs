//! Tests of the rollouts and their metrics.

use super::*;
use faer::{MatMut, MatRef};
use rand::Rng as _;
use vdd_core::Rng;
use vdd_core::Seeds;

/// Memoryless and stochastic: at the start position it picks a side at random; afterwards
/// it keeps steering towards the side of the start it is on, with jitter, moving up at 0.008
/// per step. Different seeds give different modes (0 and 23).
#[derive(Clone)]
struct Wobbly {
    rng: Rng,
    batch_calls: usize,
}

impl Wobbly {
    fn new() -> Self {
        Self { rng: Seeds::new(0).stream("wobbly"), batch_calls: 0 }
    }
    fn one(&mut self, obs: &[f32], action: &mut [f32]) {
        let offset = obs[2] - super::super::START[0];
        let left = if offset == 0.0 { self.rng.random::<bool>() } else { offset < 0.0 };
        let target = if left { 0.28 } else { 0.74 };
        action[0] = (target - obs[0]).clamp(-0.01, 0.01) + 0.004 * (self.rng.random::<f32>() - 0.5);
        action[1] = 0.008;
    }
}

impl Policy for Wobbly {
    fn obs_dim(&self) -> usize {
        4
    }
    fn action_dim(&self) -> usize {
        2
    }
    fn seed(&mut self, seed: u64) {
        self.rng = Seeds::new(seed).stream("wobbly");
    }
    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> std::result::Result<(), CoreError> {
        vdd_core::check_act_args(self, obs, action)?;
        self.one(obs, action);
        Ok(())
    }
    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        mut actions: MatMut<'_, f32>,
    ) -> std::result::Result<(), CoreError> {
        self.batch_calls += 1;
        let mut a = [0.0f32; 2];
        for i in 0..obs.nrows() {
            self.one(&[obs[(i, 0)], obs[(i, 1)], obs[(i, 2)], obs[(i, 3)]], &mut a);
            actions[(i, 0)] = a[0];
            actions[(i, 1)] = a[1];
        }
        Ok(())
    }
}

/// Fails (or returns NaN) at a given step.
#[derive(Clone)]
struct Faulty {
    fail_at: usize,
    nan: bool,
    t: usize,
}

impl Policy for Faulty {
    fn obs_dim(&self) -> usize {
        4
    }
    fn action_dim(&self) -> usize {
        2
    }
    fn reset(&mut self) {
        self.t = 0;
    }
    fn act_into(&mut self, _: &[f32], action: &mut [f32]) -> std::result::Result<(), CoreError> {
        self.t += 1;
        if self.t > self.fail_at {
            if self.nan {
                action[0] = f32::NAN;
                return Ok(());
            }
            return Err(CoreError::Config("boom".into()));
        }
        action.fill(0.0);
        Ok(())
    }
}

fn cfg(n: usize, stepping: Stepping) -> EvalConfig {
    EvalConfig { n_rollouts: n, seed: 11, stepping, record: false }
}

#[test]
fn evaluation_is_seeded_and_thread_count_invariant() {
    for stepping in [Stepping::PerEpisode, Stepping::Lockstep { batch_size: 5 }] {
        let c = cfg(23, stepping);
        let a = evaluate(&mut Wobbly::new(), &c).unwrap();
        assert_eq!(a, evaluate(&mut Wobbly::new(), &c).unwrap());
        for threads in [1, 2, 3] {
            assert_eq!(a, evaluate_cloned(&Wobbly::new(), threads, &c).unwrap());
        }
        let other = evaluate(&mut Wobbly::new(), &EvalConfig { seed: 12, ..c }).unwrap();
        assert_ne!(a.rollouts, other.rollouts);
        assert_eq!(a.rollouts.len(), 23);
        // The wobbly policy is genuinely multimodal, and sometimes crashes.
        assert!(a.metrics.modes_reached >= 2, "{:?}", a.metrics);
        assert!(a.metrics.success_rate > 0.5, "{:?}", a.metrics);
    }
}

#[test]
fn lockstep_makes_one_batched_call_per_step() {
    let mut p = Wobbly::new();
    let c = cfg(10, Stepping::Lockstep { batch_size: 10 });
    let e = evaluate(&mut p, &c).unwrap();
    let longest = e.rollouts.iter().map(|r| r.steps).max().unwrap();
    assert_eq!(p.batch_calls, longest);
    // Per-episode stepping never calls act_batch.
    let mut p = Wobbly::new();
    evaluate(&mut p, &cfg(3, Stepping::PerEpisode)).unwrap();
    assert_eq!(p.batch_calls, 0);
}

#[test]
fn recorded_trajectories_replay_the_dynamics() {
    for stepping in [Stepping::PerEpisode, Stepping::Lockstep { batch_size: 4 }] {
        let c = EvalConfig { record: true, ..cfg(6, stepping) };
        let e = evaluate(&mut Wobbly::new(), &c).unwrap();
        for r in &e.rollouts {
            let tr = r.trajectory.as_ref().unwrap();
            assert_eq!(tr.observations.nrows(), r.steps);
            assert_eq!(tr.actions.nrows(), r.steps);
            let mut env = AvoidingEnv::new();
            for t in 0..r.steps {
                let o = env.observation();
                for j in 0..4 {
                    assert_eq!(tr.observations[(t, j)], o[j]);
                }
                env.step(&[tr.actions[(t, 0)], tr.actions[(t, 1)]]).unwrap();
            }
            assert_eq!(env.status(), r.status);
            assert_eq!(env.gaps(), r.info);
            assert_eq!(env.observation()[..], tr.final_observation[..]);
        }
    }
}

#[test]
fn a_panicking_worker_is_an_error() {
    #[derive(Clone)]
    struct Panics;
    impl Policy for Panics {
        fn obs_dim(&self) -> usize {
            4
        }
        fn action_dim(&self) -> usize {
            2
        }
        fn act_into(&mut self, _: &[f32], _: &mut [f32]) -> std::result::Result<(), CoreError> {
            panic!("policy bug (expected by this test)")
        }
    }
    let r = evaluate_cloned(&Panics, 2, &cfg(4, Stepping::PerEpisode));
    assert!(matches!(r, Err(TaskError::WorkerPanicked)), "{r:?}");
}

#[test]
fn metrics_count_outcomes_and_entropy_over_successes() {
    let ok = |m: usize| Rollout {
        status: Status::Success,
        info: AvoidingMode::from_index(m).unwrap().gaps().map(Some),
        steps: 100,
        trajectory: None,
    };
    let crash = Rollout {
        status: Status::Collision,
        info: [Some(0), None, None],
        steps: 20,
        trajectory: None,
    };
    let mut rs: Vec<Rollout> = (0..24).map(ok).collect();
    rs.push(crash.clone());
    let m = Metrics::from_rollouts(&rs).unwrap();
    assert_eq!(m.successes, 24);
    assert_eq!(m.collisions, 1);
    assert!((m.task_entropy - 1.0).abs() < 1e-6);
    assert_eq!(m.modes_reached, 24);
    assert_eq!(m.total_steps, 2420);
    assert!((m.success_rate - 24.0 / 25.0).abs() < 1e-12);
    // Two equally used modes: log 2 / log 24.
    let m = Metrics::from_rollouts(&[ok(3), ok(5), ok(3), ok(5), crash]).unwrap();
    assert!((m.task_entropy - 2f64.ln() / 24f64.ln()).abs() < 1e-6);
    assert_eq!(m.mean_success_steps, 100.0);
    assert!(Metrics::from_rollouts(&[]).is_err());
}

#[test]
fn bad_configurations_and_policies_are_errors() {
    let mut p = Wobbly::new();
    assert!(evaluate(&mut p, &cfg(0, Stepping::PerEpisode)).is_err());
    assert!(evaluate(&mut p, &cfg(3, Stepping::Lockstep { batch_size: 0 })).is_err());
    assert!(evaluate_cloned(&p, 0, &cfg(3, Stepping::PerEpisode)).is_err());
    assert!(evaluate_parallel::<Wobbly>(&mut [], &cfg(3, Stepping::PerEpisode)).is_err());
    struct Wrong;
    impl Policy for Wrong {
        fn obs_dim(&self) -> usize {
            3
        }
        fn action_dim(&self) -> usize {
            2
        }
        fn act_into(&mut self, _: &[f32], _: &mut [f32]) -> std::result::Result<(), CoreError> {
            Ok(())
        }
    }
    assert!(matches!(rollout(&mut Wrong, 0, false), Err(TaskError::PolicyDims { .. })));
    // Policy errors and non-finite actions carry the episode and step.
    // Lockstep with two rows: the 8th call is row 1 of step 3; an error from `act_batch`
    // names the chunk's first episode, a NaN names the row's episode.
    let cases = [
        (Stepping::PerEpisode, false, 0, 7),
        (Stepping::PerEpisode, true, 0, 7),
        (Stepping::Lockstep { batch_size: 2 }, false, 0, 3),
        (Stepping::Lockstep { batch_size: 2 }, true, 1, 3),
    ];
    for (stepping, nan, episode, step) in cases {
        let mut f = Faulty { fail_at: 7, nan, t: 0 };
        match evaluate(&mut f, &cfg(3, stepping)) {
            Err(TaskError::Policy { episode: e, step: s, .. }) => {
                assert_eq!((e, s), (episode, step), "{stepping:?} nan {nan}")
            }
            other => panic!("{other:?}"),
        }
    }
    // In parallel, the lowest failing episode is reported whatever the timing.
    for threads in [2, 3] {
        let f = Faulty { fail_at: 7, nan: false, t: 0 };
        let r = evaluate_cloned(&f, threads, &cfg(9, Stepping::PerEpisode));
        assert!(matches!(r, Err(TaskError::Policy { episode: 0, step: 7, .. })), "{r:?}");
    }
}
