//! Tests of the Pushing environment, demonstrator and rollouts (short runs: the physics runs
//! optimised even in test builds, as every dependency does).

use faer::Mat;
use vdd_core::{CoreError, Policy};

use super::oracle::{OracleConfig, PushingOracle, generate_demonstrations};
use super::rollout::{
    EvalConfig, Metrics, Outcome, Rollout, Stepping, evaluate_parallel_with, evaluate_with,
    rollout, start_seed,
};
use super::*;

fn oracle(config: OracleConfig) -> PushingOracle {
    PushingOracle::new(config).unwrap()
}

fn bits(m: &Mat<f32>) -> Vec<u32> {
    (0..m.nrows()).flat_map(|i| (0..m.ncols()).map(move |j| m[(i, j)].to_bits())).collect()
}

/// One recorded demonstrator episode as raw bits: observations, actions, final observation.
fn episode_bits(start: u64, policy_seed: u64) -> (Vec<u32>, Vec<u32>, Vec<u32>) {
    let mut o = oracle(OracleConfig::default());
    let r = rollout(&mut o, start, policy_seed, true).unwrap();
    let t = r.trajectory.unwrap();
    let fin = t.final_observation.iter().map(|x| x.to_bits()).collect();
    (bits(&t.observations), bits(&t.actions), fin)
}

#[test]
fn same_seed_gives_bit_identical_episodes_on_any_thread() {
    let a = episode_bits(11, 5);
    let b = episode_bits(11, 5);
    let c = std::thread::spawn(|| episode_bits(11, 5)).join().unwrap();
    assert!(a.0.len() > OBS_DIM * 50, "a short episode: {} observation entries", a.0.len());
    assert_eq!(a, b);
    assert_eq!(a, c);
    assert_ne!(a.0, episode_bits(12, 5).0);
    // Parallel evaluation equals the sequential one, for both steppings; the episodes of a
    // context share its start.
    let env = EnvConfig { max_steps: 60, episodes_per_context: 2, ..EnvConfig::default() };
    for stepping in [Stepping::PerEpisode, Stepping::Lockstep { batch_size: 3 }] {
        let cfg = EvalConfig { n_rollouts: 6, seed: 3, stepping, record: true };
        let seq = evaluate_with(&mut oracle(OracleConfig::default()), &cfg, &env).unwrap();
        let mut two = vec![oracle(OracleConfig::default()); 2];
        let par = evaluate_parallel_with(&mut two, &cfg, &env).unwrap();
        assert_eq!(seq, par);
        assert_eq!(seq.metrics.contexts, 3);
        let mut e = PushingEnv::new(env.clone()).unwrap();
        for (i, r) in seq.rollouts.iter().enumerate() {
            let start = e.reset(start_seed(3, i / 2));
            let first = r.trajectory.as_ref().unwrap().observations.row(0);
            assert!((0..OBS_DIM).all(|j| first[j] == start[j]), "episode {i}");
            assert_eq!(r.info.context, start_seed(3, i / 2));
        }
    }
}

#[test]
fn reset_follows_the_original_start_distribution() {
    let mut env = PushingEnv::new(EnvConfig::default()).unwrap();
    let h = std::f32::consts::FRAC_PI_2;
    for seed in 0..100 {
        let s = StartState::sample(seed);
        let [r, g] = s.boxes;
        assert!((0.40..=0.50).contains(&r[0]) && (0.55..=0.65).contains(&g[0]), "{s:?}");
        for b in &s.boxes {
            assert!((-0.15..=0.0).contains(&b[1]) && (-h..=h).contains(&b[2]), "{b:?}");
        }
        let o = env.reset(seed);
        assert_eq!([o[0], o[1], o[2], o[3]], [0.525, -0.28, 0.525, -0.28]);
        assert_eq!([o[4], o[5], o[8], o[9]], [r[0], r[1], g[0], g[1]]);
        let yaw = yaw_from_encoding(o[6], o[7]);
        let d = (yaw - r[2]).rem_euclid(h);
        assert!(!(1e-3..=h - 1e-3).contains(&d), "{yaw} vs {r:?}");
        assert_eq!(env.context(), seed);
    }
}

#[test]
fn a_pushed_box_moves_and_stops_soon_after_the_pusher_leaves() {
    let mut env = PushingEnv::new(EnvConfig::default()).unwrap();
    let start = StartState { boxes: [[0.525, -0.20, 0.0], [0.75, -0.10, 0.0]] };
    env.reset_to(&start);
    // Up under the box's centre (contact at 4 cm), then about 5 cm further.
    for _ in 0..13 {
        env.step(&[0.0, 0.01]).unwrap();
    }
    let moved = env.box_pose(0);
    assert!(moved[1] > -0.20 + 0.04, "the box did not move: {moved:?}");
    assert!((moved[0] - 0.525).abs() < 0.01, "a centred push drifted sideways: {moved:?}");
    assert_eq!(env.box_pose(1)[..2], [0.75, -0.10]);
    // Pull back: the box stops and stays.
    for _ in 0..2 {
        env.step(&[0.0, -0.01]).unwrap();
    }
    let stopped = env.box_pose(0);
    assert_eq!(env.box_velocity(0), [0.0, 0.0]);
    assert!(stopped[1] - moved[1] < 0.01, "slid {} m", stopped[1] - moved[1]);
    env.step(&[0.0, 0.0]).unwrap();
    assert_eq!(env.box_pose(0), stopped);
    // The desired position moves by the clipped action; the pusher follows it.
    assert!((env.desired()[1] - (-0.28 + 0.13 - 0.02)).abs() < 1e-5, "{:?}", env.desired());
    assert_eq!(PushingEnv::clip_action([-3.0, 0.005]), [-ACTION_LIMIT, 0.005]);
}

#[test]
fn success_modes_and_the_partial_metric_follow_d3il() {
    let mut env = PushingEnv::new(EnvConfig::default()).unwrap();
    let at = |t: usize| [TARGETS[t][0], TARGETS[t][1], 0.0];
    // Each box in its own target: success, mode 0 (a tie counts red first).
    env.reset_to(&StartState { boxes: [at(0), at(1)] });
    assert_eq!(env.step(&[0.0, 0.0]).unwrap(), Status::Success);
    assert_eq!(env.mode().map(|m| m.index()), Some(0));
    assert!(env.mean_distance() < 1e-6);
    // Swapped: mode 2.
    env.reset_to(&StartState { boxes: [at(1), at(0)] });
    assert_eq!(env.step(&[0.0, 0.0]).unwrap(), Status::Success);
    assert_eq!(env.mode().map(|m| m.index()), Some(2));
    // Both in one target's reach is not a success; one box in: p1 only.
    let near = [TARGETS[0][0] + 0.045, TARGETS[0][1], 0.0];
    env.reset_to(&StartState { boxes: [near, [0.6, -0.1, 0.0]] });
    assert_eq!(env.step(&[0.0, 0.0]).unwrap(), Status::Running);
    assert!(env.p1() && env.mode().is_none());
    assert_eq!(env.visits()[0], [Some(1), None]);
    let d = (0.6f32 - 0.63).hypot(-0.1 - 0.3);
    assert!((env.mean_distance() - 0.5 * (0.045 + d)).abs() < 1e-4, "{}", env.mean_distance());
    // Green first (visits at steps 2 and 5), own targets: mode 1; swapped green first: mode 3.
    for (swapped, index) in [(false, 1), (true, 3)] {
        let mut e = PushingEnv::new(EnvConfig::default()).unwrap();
        e.visits = [[None; 2]; 2];
        let t = |b: usize| if swapped { 1 - b } else { b };
        e.visits[1][t(1)] = Some(2);
        e.visits[0][t(0)] = Some(5);
        let m = e.mode().unwrap();
        assert_eq!((m.index(), m.first(), m.swapped()), (index, 1, swapped));
        assert_eq!(PushingMode::from_index(index).unwrap(), m);
    }
}

#[test]
fn faults_end_the_episode_and_bad_input_is_an_error() {
    // Driving the pusher off the table ends the episode as a failure, not a panic.
    let mut env = PushingEnv::new(EnvConfig::default()).unwrap();
    let mut status = Status::Running;
    while !status.is_done() {
        status = env.step(&[0.0, -0.01]).unwrap();
    }
    assert_eq!(status, Status::OffTable);
    assert!(env.pusher()[1] < TABLE[0][1]);
    assert!(matches!(env.step(&[0.0, 0.0]), Err(TaskError::EpisodeOver("off-table"))));
    // A box started off the table fails at the first step.
    env.reset_to(&StartState { boxes: [[0.95, 0.0, 0.0], [0.6, -0.1, 0.0]] });
    assert_eq!(env.step(&[0.0, 0.0]).unwrap(), Status::OffTable);
    let r = Rollout {
        status: Status::OffTable,
        info: Outcome { mode: None, p1: false, mean_distance: 0.3, context: 0 },
        steps: 3,
        trajectory: None,
    };
    let m = Metrics::from_rollouts(&[r]).unwrap();
    assert_eq!((m.faults, m.successes, m.timeouts), (1, 0, 0));

    let mut env = PushingEnv::new(EnvConfig::default()).unwrap();
    let before = env.observation();
    assert!(env.step(&[0.0]).is_err());
    assert!(env.step(&[0.0, 0.0, 0.0]).is_err());
    assert!(env.step(&[f32::NAN, 0.0]).is_err());
    assert!(env.step(&[0.0, f32::INFINITY]).is_err());
    assert_eq!((env.steps(), env.observation()), (0, before));
    let mut o = oracle(OracleConfig::default());
    assert!(o.act(&[0.0; OBS_DIM - 1]).is_err());
    let mut nan = before;
    nan[5] = f32::NAN;
    assert!(o.act(&nan).is_err());
    // A policy that returns NaN is reported with its episode and step.
    struct Nan;
    impl Policy for Nan {
        fn obs_dim(&self) -> usize {
            OBS_DIM
        }
        fn action_dim(&self) -> usize {
            ACTION_DIM
        }
        fn act_into(&mut self, _: &[f32], a: &mut [f32]) -> std::result::Result<(), CoreError> {
            a.fill(f32::NAN);
            Ok(())
        }
    }
    let cfg = EvalConfig { n_rollouts: 1, ..EvalConfig::default() };
    let err = evaluate_with(&mut Nan, &cfg, &EnvConfig::default()).unwrap_err();
    assert!(matches!(err, TaskError::Policy { episode: 0, step: 0, .. }), "{err}");
    let mut wrong = crate::avoiding::FarLeft;
    let err = evaluate_with(&mut wrong, &cfg, &EnvConfig::default()).unwrap_err();
    assert!(matches!(err, TaskError::PolicyDims { .. }), "{err}");
    // Bad configurations.
    let bad_env = |f: fn(&mut EnvConfig)| {
        let mut c = EnvConfig::default();
        f(&mut c);
        PushingEnv::new(c).is_err()
    };
    assert!(bad_env(|c| c.max_steps = 0));
    assert!(bad_env(|c| c.episodes_per_context = 0));
    assert!(bad_env(|c| c.physics.substeps = 0));
    assert!(bad_env(|c| c.physics.pusher_speed = 0.0));
    assert!(bad_env(|c| c.physics.friction_decel = f32::NAN));
    let bad_oracle = |f: fn(&mut OracleConfig)| {
        let mut c = OracleConfig::default();
        f(&mut c);
        PushingOracle::new(c).is_err()
    };
    assert!(bad_oracle(|c| c.ou_reversion = 0.0));
    assert!(bad_oracle(|c| c.ou_std = -1.0));
    assert!(bad_oracle(|c| c.switch_distance = 0.2));
    assert!(bad_oracle(|c| c.speed_jitter = 0.5));
    assert!(PushingMode::from_index(4).is_err());
    let p = EvalProtocol { contexts: 0, ..EvalProtocol::default() };
    assert!(p.check().is_err());
}

#[test]
fn the_demonstrator_succeeds_in_each_of_the_four_modes() {
    for m in 0..N_MODES {
        let mode = PushingMode::from_index(m).unwrap();
        let mut o = oracle(OracleConfig { fixed_mode: Some(mode), ..OracleConfig::default() });
        for seed in 0..2 {
            let r = rollout(&mut o, env_seed(40, 2 * m + seed), seed as u64, false).unwrap();
            assert!(r.success(), "mode {m} seed {seed}: {:?} after {} steps", r.status, r.steps);
            assert_eq!(r.info.mode, Some(mode));
            assert_eq!(o.planned_mode(0), Some(mode));
        }
    }
}

#[test]
fn the_demonstrator_spreads_over_the_modes_and_the_demonstrations_are_consistent() {
    // 40 episodes in lockstep (the example measures 1000 in release: docs/pushing-tuning.md).
    let cfg = EvalConfig {
        n_rollouts: 40,
        seed: 2,
        stepping: Stepping::Lockstep { batch_size: 20 },
        record: false,
    };
    let e =
        evaluate_with(&mut oracle(OracleConfig::default()), &cfg, &EnvConfig::default()).unwrap();
    let m = &e.metrics;
    assert!(m.success_rate >= 0.95 && m.p1_rate >= m.success_rate, "{m:?}");
    assert!(m.modes_reached == 4 && m.mode_entropy >= 0.9, "{m:?}");
    // One episode per context: the per-context entropy is 0 (D3IL's definition).
    assert_eq!((m.contexts, m.task_entropy), (40, 0.0));
    assert!((150.0..400.0).contains(&m.mean_success_steps), "{m:?}");
    let d = generate_demonstrations(3, 9, &OracleConfig::default()).unwrap();
    assert_eq!(d, generate_demonstrations(3, 9, &OracleConfig::default()).unwrap());
    assert_eq!(d.mode_counts().iter().sum::<usize>(), 3);
    for (o, a) in d.observations.iter().zip(&d.actions) {
        let t = o.nrows();
        assert_eq!((o.ncols(), a.nrows(), a.ncols()), (OBS_DIM, t, ACTION_DIM));
        for i in 0..t {
            // Steps respect the fastest cap (0.24 m/s, +10 % speed variation).
            assert!(a[(i, 0)].hypot(a[(i, 1)]) <= 0.264 * CONTROL_DT + 1e-6);
            if i + 1 < t {
                for k in 0..2 {
                    assert!((o[(i + 1, k)] - (o[(i, k)] + a[(i, k)])).abs() < 1e-6);
                }
            }
        }
    }
    assert!(generate_demonstrations(0, 0, &OracleConfig::default()).is_err());
}

#[test]
fn metrics_take_the_entropy_per_context() {
    let r = |status, mode: Option<usize>, context| Rollout {
        status,
        info: Outcome {
            mode: mode.map(|m| PushingMode::from_index(m).unwrap()),
            p1: mode.is_some(),
            mean_distance: 0.01,
            context,
        },
        steps: 10,
        trajectory: None,
    };
    // Context 7: modes 0 and 3 (entropy 0.5); context 9: mode 1 twice (0).
    let rs = [
        r(Status::Success, Some(0), 7),
        r(Status::Success, Some(3), 7),
        r(Status::Success, Some(1), 9),
        r(Status::Success, Some(1), 9),
        r(Status::Timeout, None, 9),
    ];
    let m = Metrics::from_rollouts(&rs).unwrap();
    assert_eq!((m.contexts, m.successes, m.timeouts), (2, 4, 1));
    assert!((m.task_entropy - 0.25).abs() < 1e-6, "{m:?}");
    assert_eq!(m.mode_counts, vec![1, 2, 0, 1]);
    assert!((m.mode_entropy - 0.75).abs() < 1e-6, "{m:?}");
    assert!(Metrics::from_rollouts(&[]).is_err());
    assert!(Metrics::from_rollouts(&[r(Status::Success, None, 1)]).is_err());
}
