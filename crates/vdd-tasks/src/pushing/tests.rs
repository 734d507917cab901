//! Tests of the Pushing environment, demonstrator and rollouts (short runs: the physics runs
//! optimised even in test builds, as every dependency does).

use super::oracle::{OracleConfig, PushingOracle, generate_demonstrations};
use super::rollout::{EvalConfig, Metrics, Outcome, Rollout, Stepping, evaluate_with, rollout};
use super::*;

fn oracle(config: OracleConfig) -> PushingOracle {
    PushingOracle::new(config).unwrap()
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

    // Bad input (shared with Aligning: crate::d3il's tests) and bad demonstrator settings.
    let mut env = PushingEnv::new(EnvConfig::default()).unwrap();
    assert!(env.step(&[0.0]).is_err() && env.step(&[f32::NAN, 0.0]).is_err());
    assert_eq!(env.steps(), 0);
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
    assert!(m.success_rate >= 0.95 && m.p1_rate.is_some_and(|p1| p1 >= m.success_rate), "{m:?}");
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
    assert!(Metrics::from_rollouts::<PushingEnv>(&[]).is_err());
    assert!(Metrics::from_rollouts(&[r(Status::Success, None, 1)]).is_err());
}
