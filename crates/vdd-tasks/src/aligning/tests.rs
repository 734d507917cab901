//! Tests of the Aligning environment, demonstrator and rollouts (short runs: the physics runs
//! optimised even in test builds, as every dependency does).

use super::oracle::{AligningOracle, OracleConfig, generate_demonstrations};
use super::rollout::{EvalConfig, Metrics, Outcome, Rollout, Stepping, evaluate_with, rollout};
use super::*;

fn oracle(config: OracleConfig) -> AligningOracle {
    AligningOracle::new(config).unwrap()
}

#[test]
fn reset_follows_the_original_start_distribution() {
    let mut env = AligningEnv::new(EnvConfig::default()).unwrap();
    let h = std::f32::consts::FRAC_PI_2;
    for seed in 0..100 {
        let s = StartState::sample(seed);
        let ([x, y, a], [tx, ty, ta]) = (s.tray, s.target);
        assert!((0.40..=0.60).contains(&x) && (-0.25..=-0.10).contains(&y), "{s:?}");
        assert!((0.40..=0.60).contains(&tx) && (0.20..=0.35).contains(&ty), "{s:?}");
        assert!((-h..=h).contains(&a) && (-h..=h).contains(&ta), "{s:?}");
        let o = env.reset(seed);
        assert_eq!(o[..6], [0.525, -0.35, START_HEIGHT, 0.525, -0.35, START_HEIGHT]);
        assert_eq!([o[6], o[7], o[10], o[11]], [x, y, tx, ty]);
        assert!((o[8].atan2(o[9]) - a).abs() < 1e-5 && (o[12].atan2(o[13]) - ta).abs() < 1e-5);
        assert_eq!(env.context(), seed);
    }
}

/// Steps `action` `n` times.
fn repeat(env: &mut AligningEnv, action: [f32; 3], n: usize) {
    for _ in 0..n {
        env.step(&action).unwrap();
    }
}

#[test]
fn a_lifted_rod_passes_over_the_tray_and_a_lowered_one_pushes_it() {
    let start = StartState { tray: [0.525, -0.20, 0.0], target: [0.5, 0.3, 0.0] };
    // Lifted: the rod sweeps across the tray without moving it.
    let mut env = AligningEnv::new(EnvConfig::default()).unwrap();
    env.reset_to(&start);
    repeat(&mut env, [0.0, 0.01, 0.0], 30);
    assert!(env.pusher()[1] > -0.06, "{:?}", env.pusher());
    assert_eq!(env.tray_pose(), [0.525, -0.20, 0.0]);
    // Lowered below the tray: pushing up moves it along its axis without turning it.
    env.reset_to(&start);
    repeat(&mut env, [0.0, 0.0, -0.01], 16);
    assert_eq!(env.height(), 0.0);
    repeat(&mut env, [0.0, 0.01, 0.0], 20);
    let [x, y, yaw] = env.tray_pose();
    assert!(y > -0.20 + 0.05, "the tray did not move: {y}");
    assert!((x - 0.525).abs() < 0.005 && yaw.abs() < 0.05, "{x} {yaw}");
    assert_eq!(env.mode(), AligningMode::Outside);
    // Lowered inside (over the centre) and pushing: the rod stays inside, the tray follows.
    env.reset_to(&start);
    repeat(&mut env, [0.0, 0.01, 0.0], 15);
    repeat(&mut env, [0.0, 0.0, -0.01], 16);
    assert_eq!(env.height(), 0.0);
    repeat(&mut env, [0.0, 0.01, 0.0], 20);
    assert!(env.tray_pose()[1] > -0.20 + 0.1, "{:?}", env.tray_pose());
    assert_eq!(env.mode(), AligningMode::Inside);
    // Lowered onto a wall: the tip rests on the wall top and the tray stays put.
    env.reset_to(&start);
    repeat(&mut env, [0.0, 0.01, 0.0], 10);
    assert!(overlaps_walls([env.pusher()[0] - 0.525, env.pusher()[1] + 0.20]));
    repeat(&mut env, [0.0, 0.0, -0.01], 16);
    assert_eq!(env.height(), WALL_TOP);
    assert_eq!(env.tray_pose(), [0.525, -0.20, 0.0]);
}

#[test]
fn success_modes_and_the_partial_metric_follow_d3il() {
    let mut env = AligningEnv::new(EnvConfig::default()).unwrap();
    let target = [0.5, 0.3, 1.0];
    let at = |dx: f32, dyaw: f32| StartState { tray: [0.5 + dx, 0.3, 1.0 + dyaw], target };
    env.reset_to(&at(0.01, 0.1));
    assert_eq!(env.step(&[0.0; 3]).unwrap(), Status::Success);
    // The rod is far: outside.
    assert_eq!(env.mode(), AligningMode::Outside);
    for off in [at(0.02, 0.0), at(0.0, 0.2), at(0.0, 0.2 - std::f32::consts::TAU)] {
        env.reset_to(&off);
        assert_eq!(env.step(&[0.0; 3]).unwrap(), Status::Running, "{off:?}");
    }
    // No symmetry: a half turn is the largest error.
    env.reset_to(&at(0.0, std::f32::consts::PI));
    env.step(&[0.0; 3]).unwrap();
    assert!((env.mean_distance() - 0.5).abs() < 1e-4, "{}", env.mean_distance());
    let (d, r) = env.errors();
    assert!(d < 1e-6 && (r - std::f32::consts::PI).abs() < 1e-4);
    // The rod at the tray's centre: inside.
    env.reset_to(&StartState { tray: [0.525, -0.35, 0.0], target });
    assert_eq!(env.mode(), AligningMode::Inside);
    assert!((wrap_angle(3.5) - (3.5 - std::f32::consts::TAU)).abs() < 1e-6);
}

#[test]
fn faults_end_the_episode_and_bad_input_is_an_error() {
    let mut env = AligningEnv::new(EnvConfig::default()).unwrap();
    let mut status = Status::Running;
    while !status.is_done() {
        status = env.step(&[0.0, -0.01, 0.0]).unwrap();
    }
    assert_eq!(status, Status::OffTable);
    assert!(matches!(env.step(&[0.0; 3]), Err(TaskError::EpisodeOver("off-table"))));
    env.reset_to(&StartState { tray: [0.95, 0.0, 0.0], target: [0.5, 0.3, 0.0] });
    assert_eq!(env.step(&[0.0; 3]).unwrap(), Status::OffTable);
    let r = Rollout {
        status: Status::OffTable,
        info: Outcome { mode: AligningMode::Outside, mean_distance: 0.3, context: 0 },
        steps: 3,
        trajectory: None,
    };
    let m = Metrics::from_rollouts(&[r]).unwrap();
    assert_eq!((m.faults, m.successes, m.timeouts), (1, 0, 0));

    // Bad input (shared with Pushing: crate::d3il's tests) and bad demonstrator settings.
    let mut env = AligningEnv::new(EnvConfig::default()).unwrap();
    assert!(env.step(&[0.0, 0.0]).is_err() && env.step(&[f32::NAN, 0.0, 0.0]).is_err());
    assert_eq!(env.steps(), 0);
    assert_eq!(AligningEnv::clip_action([-3.0, 0.005, 2.0]), [-ACTION_LIMIT, 0.005, ACTION_LIMIT]);
    let bad_oracle = |f: fn(&mut OracleConfig)| {
        let mut c = OracleConfig::default();
        f(&mut c);
        AligningOracle::new(c).is_err()
    };
    assert!(bad_oracle(|c| c.ou_reversion = 0.0));
    assert!(bad_oracle(|c| c.ou_std = -1.0));
    assert!(bad_oracle(|c| c.speed_jitter = 0.5));
    assert!(AligningMode::from_index(2).is_err());
}

#[test]
fn the_demonstrator_succeeds_in_both_modes() {
    for mode in [AligningMode::Inside, AligningMode::Outside] {
        let mut o = oracle(OracleConfig { fixed_mode: Some(mode), ..OracleConfig::default() });
        for seed in 0..3 {
            let r = rollout(&mut o, env_seed(40, seed), seed as u64, false).unwrap();
            assert!(r.success(), "{mode:?} seed {seed}: {:?} after {} steps", r.status, r.steps);
            assert_eq!(r.info.mode, mode);
            assert_eq!(o.planned_mode(0), Some(mode));
        }
    }
}

#[test]
fn the_demonstrator_spreads_over_the_modes_and_the_demonstrations_are_consistent() {
    // 30 episodes in lockstep (the example measures 1000 in release: docs/aligning-tuning.md).
    let cfg = EvalConfig {
        n_rollouts: 30,
        seed: 2,
        stepping: Stepping::Lockstep { batch_size: 15 },
        record: false,
    };
    let e =
        evaluate_with(&mut oracle(OracleConfig::default()), &cfg, &EnvConfig::default()).unwrap();
    let m = &e.metrics;
    assert!(m.success_rate >= 0.9, "{m:?}");
    assert!(m.modes_reached == 2 && m.mode_entropy >= 0.8, "{m:?}");
    assert_eq!((m.contexts, m.task_entropy), (30, 0.0));
    let d = generate_demonstrations(3, 9, &OracleConfig::default()).unwrap();
    assert_eq!(d, generate_demonstrations(3, 9, &OracleConfig::default()).unwrap());
    for (o, a) in d.observations.iter().zip(&d.actions) {
        let t = o.nrows();
        assert_eq!((o.ncols(), a.nrows(), a.ncols()), (OBS_DIM, t, ACTION_DIM));
        for i in 0..t {
            let n = (0..3).map(|k| a[(i, k)] * a[(i, k)]).sum::<f32>().sqrt();
            assert!(n <= 0.264 * CONTROL_DT + 1e-6, "step {i}: {n}");
            if i + 1 < t {
                for k in 0..3 {
                    assert!((o[(i + 1, k)] - (o[(i, k)] + a[(i, k)])).abs() < 1e-6);
                }
            }
        }
    }
    assert!(generate_demonstrations(0, 0, &OracleConfig::default()).is_err());
}

#[test]
fn metrics_take_the_entropy_per_context_in_base_2() {
    let r = |status, mode: usize, context| Rollout {
        status,
        info: Outcome {
            mode: AligningMode::from_index(mode).unwrap(),
            mean_distance: 0.01,
            context,
        },
        steps: 10,
        trajectory: None,
    };
    // Context 7: both modes (entropy 1); context 9: outside twice (0), a timeout not counted.
    let rs = [
        r(Status::Success, 0, 7),
        r(Status::Success, 1, 7),
        r(Status::Success, 1, 9),
        r(Status::Success, 1, 9),
        r(Status::Timeout, 0, 9),
    ];
    let m = Metrics::from_rollouts(&rs).unwrap();
    assert_eq!((m.contexts, m.successes, m.timeouts), (2, 4, 1));
    assert!((m.task_entropy - 0.5).abs() < 1e-6, "{m:?}");
    assert_eq!(m.mode_counts, vec![1, 3]);
    assert!(Metrics::from_rollouts::<AligningEnv>(&[]).is_err());
}
