//! Tests of the Block-Push environment, oracle and rollouts (short episodes: the physics runs
//! optimised even in test builds, as every dependency does).

use faer::Mat;
use vdd_core::{CoreError, Policy};

use super::oracle::{BlockPushOracle, OracleConfig, generate_demonstrations};
use super::rollout::{
    EvalConfig, Metrics, Outcome, Rollout, Stepping, evaluate, evaluate_cloned, rollout,
};
use super::*;

fn oracle(config: OracleConfig) -> BlockPushOracle {
    BlockPushOracle::new(config).unwrap()
}

fn bits(m: &Mat<f32>) -> Vec<u32> {
    (0..m.nrows()).flat_map(|i| (0..m.ncols()).map(move |j| m[(i, j)].to_bits())).collect()
}

/// One recorded oracle episode as raw bits: observations, actions, final observation.
fn episode_bits(env_seed: u64, policy_seed: u64) -> (Vec<u32>, Vec<u32>, Vec<u32>) {
    let mut o = oracle(OracleConfig::default());
    let r = rollout(&mut o, env_seed, policy_seed, true).unwrap();
    let t = r.trajectory.unwrap();
    let fin = t.final_observation.iter().map(|x| x.to_bits()).collect();
    (bits(&t.observations), bits(&t.actions), fin)
}

#[test]
fn same_seed_gives_bit_identical_episodes_on_any_thread() {
    let a = episode_bits(11, 5);
    let b = episode_bits(11, 5);
    let c = std::thread::spawn(|| episode_bits(11, 5)).join().unwrap();
    assert!(a.0.len() > 16 * 20, "a short episode: {} observation entries", a.0.len());
    assert_eq!(a, b);
    assert_eq!(a, c);
    // Another start changes the episode.
    assert_ne!(a.0, episode_bits(12, 5).0);
    // Parallel evaluation equals the sequential one, for both steppings.
    for stepping in [Stepping::PerEpisode, Stepping::Lockstep { batch_size: 3 }] {
        let cfg = EvalConfig { n_rollouts: 6, seed: 3, stepping, record: true };
        let seq = evaluate(&mut oracle(OracleConfig::default()), &cfg).unwrap();
        let par = evaluate_cloned(&oracle(OracleConfig::default()), 2, &cfg).unwrap();
        assert_eq!(seq, par);
        // Both steppings start episode i from the same state.
        let mut env = BlockPushEnv::new(EnvConfig::default()).unwrap();
        for (i, r) in seq.rollouts.iter().enumerate() {
            let start = env.reset(env_seed(3, i));
            let first = r.trajectory.as_ref().unwrap().observations.row(0);
            assert!((0..OBS_DIM).all(|j| first[j] == start[j]), "episode {i}");
        }
    }
}

#[test]
fn reset_follows_the_original_start_distribution() {
    let mut env = BlockPushEnv::new(EnvConfig::default()).unwrap();
    let mut left_is_target0 = 0;
    for seed in 0..200 {
        let s = StartState::sample(seed);
        assert!((s.blocks[0][0] - s.blocks[1][0]).abs() > 0.1);
        for b in &s.blocks {
            assert!((0.3..=0.5).contains(&b[0]) && (-0.35..=-0.05).contains(&b[1]), "{b:?}");
            assert!((0.0..std::f32::consts::FRAC_PI_2).contains(&b[2]));
        }
        let [t0, t1] = s.targets;
        assert!(((t0[0] - t1[0]).abs() - 0.24).abs() <= 0.01 + 1e-6);
        assert_eq!(t0[1], t1[1]);
        assert!((t0[1] - 0.2).abs() <= 0.0075);
        left_is_target0 += usize::from(t0[0] < t1[0]);
        let o = env.reset(seed);
        assert_eq!([o[8], o[9]], EFFECTOR_START);
        assert_eq!([o[10], o[11]], EFFECTOR_START);
        assert_eq!([o[12], o[13], o[14], o[15]], [t0[0], t0[1], t1[0], t1[1]]);
        let yaw = yaw_from_encoding(o[2], o[3]);
        let d = (yaw - s.blocks[0][2]).rem_euclid(std::f32::consts::FRAC_PI_2);
        assert!(
            !(1e-4..=std::f32::consts::FRAC_PI_2 - 1e-4).contains(&d),
            "{yaw} vs {:?}",
            s.blocks[0]
        );
    }
    // The colour side is a fair coin flip.
    assert!((70..130).contains(&left_is_target0), "{left_is_target0}");
}

#[test]
fn a_pushed_block_moves_and_stops_soon_after_the_pusher_leaves() {
    let mut env = BlockPushEnv::new(EnvConfig::default()).unwrap();
    let start = StartState {
        blocks: [[0.30, -0.30, 0.0], [0.55, -0.10, 0.0]],
        targets: [[0.28, 0.2], [0.52, 0.2]],
    };
    env.reset_to(&start);
    // Up under the block's centre, then 6 cm further, pushing it.
    for _ in 0..10 {
        env.step(&[0.0, 0.02]).unwrap();
    }
    let moved = env.block_pose(0);
    assert!(moved[1] > -0.30 + 0.04, "block 0 did not move: {moved:?}");
    assert!((moved[0] - 0.30).abs() < 0.01, "a centred push drifted sideways: {moved:?}");
    // The other block is untouched.
    assert_eq!(env.block_pose(1)[..2], [0.55, -0.10]);
    // Pull back: the block stops within a step and stays.
    env.step(&[0.0, -0.05]).unwrap();
    env.step(&[0.0, 0.0]).unwrap();
    let stopped = env.block_pose(0);
    assert_eq!(env.block_velocity(0), [0.0, 0.0]);
    assert!(stopped[1] - moved[1] < 0.01, "slid {} m", stopped[1] - moved[1]);
    env.step(&[0.0, 0.0]).unwrap();
    assert_eq!(env.block_pose(0), stopped);
    // An off-centre push turns the block.
    let mut env = BlockPushEnv::new(EnvConfig::default()).unwrap();
    let start = StartState { blocks: [[0.315, -0.30, 0.0], [0.55, -0.10, 0.0]], ..start };
    env.reset_to(&start);
    for _ in 0..10 {
        env.step(&[0.0, 0.02]).unwrap();
    }
    assert!(env.block_pose(0)[2].abs() > 0.1, "{:?}", env.block_pose(0));
}

#[test]
fn actions_are_clipped_and_the_target_stays_in_the_workspace() {
    let mut env = BlockPushEnv::new(EnvConfig::default()).unwrap();
    env.reset(1);
    env.step(&[0.5, -0.5]).unwrap(); // each component clipped to ±0.1
    assert!((env.commanded()[0] - (EFFECTOR_START[0] + ACTION_LIMIT)).abs() < 1e-6);
    assert_eq!(env.commanded()[1], WORKSPACE[0][1]); // −0.4 − 0.1 = −0.5, the bound
    for _ in 0..10 {
        env.step(&[-0.1, -0.1]).unwrap();
    }
    assert_eq!(env.commanded(), WORKSPACE[0]);
    // The pusher follows the commanded target at its speed limit and ends on it.
    let o = env.observation();
    assert!((o[8] - WORKSPACE[0][0]).abs() < 1e-5 && (o[9] - WORKSPACE[0][1]).abs() < 1e-5);
    for _ in 0..20 {
        env.step(&[0.1, 0.1]).unwrap();
    }
    assert_eq!(env.commanded(), WORKSPACE[1]);
    assert_eq!(BlockPushEnv::clip_action([-3.0, 0.05]), [-ACTION_LIMIT, 0.05]);
}

#[test]
fn bad_input_is_an_error_not_a_panic() {
    let mut env = BlockPushEnv::new(EnvConfig::default()).unwrap();
    let before = env.observation();
    assert!(env.step(&[0.0]).is_err());
    assert!(env.step(&[0.0, 0.0, 0.0]).is_err());
    assert!(env.step(&[f32::NAN, 0.0]).is_err());
    assert!(env.step(&[0.0, f32::NEG_INFINITY]).is_err());
    assert_eq!((env.steps(), env.observation()), (0, before));
    let mut o = oracle(OracleConfig::default());
    assert!(o.act(&[0.0; 15]).is_err());
    let mut nan = before;
    nan[3] = f32::NAN;
    assert!(o.act(&nan).is_err());
    assert!(o.act(&before).is_ok());
    // A batch of another size mid-episode.
    let obs = Mat::<f32>::zeros(2, OBS_DIM);
    let mut act = Mat::<f32>::zeros(2, ACTION_DIM);
    assert!(o.act_batch(obs.as_ref(), act.as_mut()).is_err());
    // A policy of the wrong shape is refused by the rollouts.
    let cfg = EvalConfig { n_rollouts: 1, ..EvalConfig::default() };
    let mut wrong = crate::avoiding::FarLeft;
    assert!(matches!(evaluate(&mut wrong, &cfg), Err(TaskError::PolicyDims { .. })));
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
    let err = evaluate(&mut Nan, &cfg).unwrap_err();
    assert!(matches!(err, TaskError::Policy { episode: 0, step: 0, .. }), "{err}");
    // Bad configurations.
    let bad_env = |f: fn(&mut EnvConfig)| {
        let mut c = EnvConfig::default();
        f(&mut c);
        BlockPushEnv::new(c).is_err()
    };
    assert!(bad_env(|c| c.max_steps = 0));
    assert!(bad_env(|c| c.physics.substeps = 0));
    assert!(bad_env(|c| c.physics.pusher_speed = 0.0));
    assert!(bad_env(|c| c.physics.friction_decel = f32::NAN));
    let bad_oracle = |f: fn(&mut OracleConfig)| {
        let mut c = OracleConfig::default();
        f(&mut c);
        BlockPushOracle::new(c).is_err()
    };
    assert!(bad_oracle(|c| c.ou_reversion = 0.0));
    assert!(bad_oracle(|c| c.ou_std = -1.0));
    assert!(bad_oracle(|c| c.switch_distance = 0.2));
    assert!(bad_oracle(|c| c.speed_jitter = 0.9));
    // Stepping an ended episode.
    let mut env = BlockPushEnv::new(EnvConfig { max_steps: 2, ..EnvConfig::default() }).unwrap();
    env.step(&[0.0, 0.0]).unwrap();
    assert_eq!(env.step(&[0.0, 0.0]).unwrap(), Status::Timeout);
    assert!(matches!(env.step(&[0.0, 0.0]), Err(TaskError::EpisodeOver("timeout"))));
    assert!(BlockPushMode::from_index(4).is_err());
    assert!(BlockPushMode::new(0, 2).is_err());
}

#[test]
fn the_oracle_succeeds_in_each_of_the_four_modes() {
    for m in 0..N_MODES {
        let mode = BlockPushMode::from_index(m).unwrap();
        let mut o = oracle(OracleConfig { fixed_mode: Some(mode), ..OracleConfig::default() });
        for seed in 0..3 {
            let r = rollout(&mut o, env_seed(40, 4 * m + seed), seed as u64, false).unwrap();
            assert!(r.success(), "mode {m} seed {seed}: {:?} after {} steps", r.status, r.steps);
            assert_eq!(r.info.mode, Some(mode));
            assert_eq!(o.planned_mode(0), Some(mode));
            assert!(r.info.p1);
        }
    }
}

#[test]
fn the_oracle_spreads_over_the_modes_and_the_demonstrations_are_consistent() {
    // 100 episodes (about 1 s here; the example measures 200 and 1000 in release).
    let cfg = EvalConfig {
        n_rollouts: 100,
        seed: 2,
        stepping: Stepping::Lockstep { batch_size: 25 },
        record: false,
    };
    let e = evaluate(&mut oracle(OracleConfig::default()), &cfg).unwrap();
    let m = &e.metrics;
    assert!(m.success_rate >= 0.95 && m.p1_rate >= m.success_rate, "{m:?}");
    assert!(m.task_entropy >= 0.95 && m.modes_reached == 4, "{m:?}");
    assert!(m.mode_counts.iter().all(|&c| c >= 15), "{m:?}");
    assert!((60.0..200.0).contains(&m.mean_success_steps), "{m:?}");
    let d = generate_demonstrations(4, 9, &OracleConfig::default()).unwrap();
    assert_eq!(d, generate_demonstrations(4, 9, &OracleConfig::default()).unwrap());
    assert_eq!(d.mode_counts().iter().sum::<usize>(), 4);
    assert!(d.success_rate() > 0.0 && d.success_rate() <= 1.0);
    for (o, a) in d.observations.iter().zip(&d.actions) {
        let t = o.nrows();
        assert_eq!((o.ncols(), a.nrows(), a.ncols()), (OBS_DIM, t, ACTION_DIM));
        for i in 0..t {
            // Oracle steps respect the fastest phase cap (0.35 m/s, +10 % speed variation).
            assert!(a[(i, 0)].hypot(a[(i, 1)]) <= 0.0385 + 1e-6);
            if i + 1 < t {
                for k in 0..2 {
                    let want = (o[(i, 10 + k)] + a[(i, k)]).clamp(WORKSPACE[0][k], WORKSPACE[1][k]);
                    assert!((o[(i + 1, 10 + k)] - want).abs() < 1e-6);
                }
            }
        }
    }
    assert!(generate_demonstrations(0, 0, &OracleConfig::default()).is_err());
    assert_eq!(d.to_episodes().unwrap().lengths(), d.lengths().as_slice());
}

#[test]
fn metrics_count_p1_p2_and_modes_of_successes_only() {
    let r = |status, mode: Option<usize>, p1| Rollout {
        status,
        info: Outcome { mode: mode.map(|m| BlockPushMode::from_index(m).unwrap()), p1 },
        steps: 10,
        trajectory: None,
    };
    let rs = [
        r(Status::Success, Some(0), true),
        r(Status::Success, Some(3), true),
        r(Status::Timeout, Some(1), true),
        r(Status::Timeout, None, false),
    ];
    let m = Metrics::from_rollouts(&rs).unwrap();
    assert_eq!((m.successes, m.p1_count, m.timeouts), (2, 3, 2));
    assert_eq!((m.success_rate, m.p1_rate), (0.5, 0.75));
    assert_eq!(m.mode_counts, vec![1, 0, 0, 1]);
    assert!((m.task_entropy - 0.5).abs() < 1e-6);
    assert!(Metrics::from_rollouts(&[]).is_err());
    assert!(Metrics::from_rollouts(&[r(Status::Success, None, true)]).is_err());
}

#[test]
fn the_noise_is_seeded_and_can_be_switched_off() {
    let mode = Some(BlockPushMode::from_index(1).unwrap());
    let actions = |config: OracleConfig, policy_seed: u64| {
        let mut o = oracle(OracleConfig { fixed_mode: mode, ..config });
        let r = rollout(&mut o, env_seed(5, 0), policy_seed, true).unwrap();
        assert!(r.success(), "{:?}", r.status);
        bits(&r.trajectory.unwrap().actions)
    };
    let quiet = OracleConfig::noise_free();
    assert_eq!(actions(quiet.clone(), 1), actions(quiet, 2));
    let noisy = OracleConfig::default();
    assert_eq!(actions(noisy.clone(), 1), actions(noisy.clone(), 1));
    assert_ne!(actions(noisy.clone(), 1), actions(noisy, 2));
}
