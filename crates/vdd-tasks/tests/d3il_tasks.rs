//! What every D3IL contact task (`vdd_tasks::d3il`) must do, checked on Pushing and Aligning with their scripted
//! demonstrators: bit-identical episodes on any thread, sequential and parallel evaluations
//! alike, contexts shared by their episodes, and bad input reported as errors, never panics.

use faer::Mat;
use vdd_core::{CoreError, Policy};

use vdd_tasks::TaskError;
use vdd_tasks::aligning::AligningEnv;
use vdd_tasks::aligning::oracle::{AligningOracle, OracleConfig as AligningConfig};
use vdd_tasks::d3il::rollout::{
    EvalConfig, Stepping, evaluate_parallel_with, evaluate_with, rollout,
};
use vdd_tasks::d3il::{ContextEnv, ContextOutcome, EnvConfig, EvalProtocol};
use vdd_tasks::episodes::{self, Env};
use vdd_tasks::pushing::PushingEnv;
use vdd_tasks::pushing::oracle::{OracleConfig as PushingConfig, PushingOracle};

fn pushing_oracle() -> PushingOracle {
    PushingOracle::new(PushingConfig::default()).unwrap()
}

fn aligning_oracle() -> AligningOracle {
    AligningOracle::new(AligningConfig::default()).unwrap()
}

fn bits(m: &Mat<f32>) -> Vec<u32> {
    (0..m.nrows()).flat_map(|i| (0..m.ncols()).map(move |j| m[(i, j)].to_bits())).collect()
}

/// One recorded episode of `policy` on task `E` as raw bits: observations, actions, final
/// observation.
fn episode_bits<E: ContextEnv, P: Policy>(
    mut policy: P,
    start: u64,
    policy_seed: u64,
) -> (Vec<u32>, Vec<u32>, Vec<u32>) {
    let r = rollout::<E, P>(&mut policy, start, policy_seed, true).unwrap();
    let t = r.trajectory.unwrap();
    let fin = t.final_observation.iter().map(|x| x.to_bits()).collect();
    (bits(&t.observations), bits(&t.actions), fin)
}

/// `oracle()`'s episodes on task `E` are bit-identical on any thread, and its parallel
/// evaluations equal the sequential ones for both steppings, the episodes of a context sharing
/// its start.
fn bit_identical_on_any_thread<E: ContextEnv, P: Policy + Clone + Send + 'static>(
    oracle: fn() -> P,
) {
    let a = episode_bits::<E, P>(oracle(), 11, 5);
    let b = episode_bits::<E, P>(oracle(), 11, 5);
    let c = std::thread::spawn(move || episode_bits::<E, P>(oracle(), 11, 5)).join().unwrap();
    let od = <E as ContextEnv>::OBS_DIM;
    assert!(a.0.len() > od * 50, "{}: a short episode: {} observation entries", E::NAME, a.0.len());
    assert_eq!(a, b);
    assert_eq!(a, c);
    assert_ne!(a.0, episode_bits::<E, P>(oracle(), 12, 5).0);
    let mut env = EnvConfig::<E>::default();
    (env.max_steps, env.episodes_per_context) = (60, 2);
    for stepping in [Stepping::PerEpisode, Stepping::Lockstep { batch_size: 3 }] {
        let cfg = EvalConfig { n_rollouts: 6, seed: 3, stepping, record: true };
        let seq = evaluate_with(&mut oracle(), &cfg, &env).unwrap();
        let mut two = vec![oracle(); 2];
        let par = evaluate_parallel_with(&mut two, &cfg, &env).unwrap();
        assert_eq!(seq, par);
        assert_eq!(seq.metrics.contexts, 3);
        let mut e = E::build(&env).unwrap();
        let mut start = vec![0.0; od];
        for (i, r) in seq.rollouts.iter().enumerate() {
            let context = episodes::start_seed::<E>(3, i / 2);
            Env::reset(&mut e, context);
            e.observe(&mut start).unwrap();
            let first = r.trajectory.as_ref().unwrap().observations.row(0);
            assert!((0..od).all(|j| first[j] == start[j]), "{}: episode {i}", E::NAME);
            assert_eq!(r.info.test_context(), context);
        }
    }
}

#[test]
fn same_seed_gives_bit_identical_episodes_on_any_thread() {
    bit_identical_on_any_thread::<PushingEnv, _>(pushing_oracle);
    bit_identical_on_any_thread::<AligningEnv, _>(aligning_oracle);
}

/// A policy of task `E` that returns NaN.
struct Nan<E>(std::marker::PhantomData<E>);

impl<E: ContextEnv> Policy for Nan<E> {
    fn obs_dim(&self) -> usize {
        <E as ContextEnv>::OBS_DIM
    }
    fn action_dim(&self) -> usize {
        <E as ContextEnv>::ACTION_DIM
    }
    fn act_into(&mut self, _: &[f32], a: &mut [f32]) -> std::result::Result<(), CoreError> {
        a.fill(f32::NAN);
        Ok(())
    }
}

/// Misshapen or non-finite actions and observations, a policy returning NaN, a policy of
/// another task, and out-of-range settings are errors of task `E` (and its demonstrator
/// `oracle`), not panics, and leave the episode unchanged.
fn bad_input_is_an_error<E: ContextEnv, P: Policy>(mut oracle: P) {
    let (od, ad) = (<E as ContextEnv>::OBS_DIM, <E as ContextEnv>::ACTION_DIM);
    let mut env = E::build(&EnvConfig::default()).unwrap();
    let mut before = vec![0.0; od];
    env.observe(&mut before).unwrap();
    let mut applied = vec![0.0; ad];
    assert!(env.apply(&vec![0.0; ad - 1], &mut applied).is_err());
    assert!(env.apply(&vec![0.0; ad + 1], &mut applied).is_err());
    for (k, bad) in [(0, f32::NAN), (ad - 1, f32::INFINITY)] {
        let mut action = vec![0.0; ad];
        action[k] = bad;
        assert!(env.apply(&action, &mut applied).is_err());
    }
    let mut after = vec![0.0; od];
    env.observe(&mut after).unwrap();
    assert_eq!((env.steps(), &after), (0, &before), "{}", E::NAME);
    assert!(env.observe(&mut vec![0.0; od - 1]).is_err());
    assert!(oracle.act(&before[..od - 1]).is_err());
    before[od / 2] = f32::NAN;
    assert!(oracle.act(&before).is_err());
    // A policy that returns NaN is reported with its episode and step.
    let cfg = EvalConfig { n_rollouts: 1, ..EvalConfig::default() };
    let err = evaluate_with(&mut Nan::<E>(Default::default()), &cfg, &EnvConfig::<E>::default())
        .unwrap_err();
    assert!(matches!(err, TaskError::Policy { episode: 0, step: 0, .. }), "{err}");
    let mut wrong = vdd_tasks::avoiding::FarLeft;
    let err = evaluate_with(&mut wrong, &cfg, &EnvConfig::<E>::default()).unwrap_err();
    assert!(matches!(err, TaskError::PolicyDims { .. }), "{err}");
    // Bad configurations.
    let bad_env = |f: fn(&mut EnvConfig<E>)| {
        let mut c = EnvConfig::default();
        f(&mut c);
        E::build(&c).is_err()
    };
    assert!(bad_env(|c| c.max_steps = 0));
    assert!(bad_env(|c| c.episodes_per_context = 0));
    assert!(bad_env(|c| c.physics.substeps = 0));
    assert!(bad_env(|c| c.physics.pusher_speed = 0.0));
    assert!(bad_env(|c| c.physics.friction_decel = f32::NAN));
    assert!(bad_env(|c| c.physics.spin_decel = f32::NAN));
    let mut p = EvalProtocol::<E>::default();
    assert!(p.check().is_ok());
    p.contexts = 0;
    let err = p.check().unwrap_err().to_string();
    assert!(err.contains(&format!("{} protocol", E::NAME)), "{err}");
}

#[test]
fn bad_input_is_an_error_and_leaves_the_episode_unchanged() {
    bad_input_is_an_error::<PushingEnv, _>(pushing_oracle());
    bad_input_is_an_error::<AligningEnv, _>(aligning_oracle());
}

#[test]
fn the_protocols_follow_d3il_and_keep_their_tasks_apart() {
    use vdd_tasks::{aligning, pushing};
    let (p, a) = (pushing::EvalProtocol::default(), aligning::EvalProtocol::default());
    assert_eq!((p.contexts, p.rollouts_per_context, p.rollouts()), (30, 16, 480));
    assert_eq!((a.contexts, a.rollouts_per_context, a.rollouts()), (60, 8, 480));
    assert_eq!(p.env().episodes_per_context, 16);
    assert_ne!(pushing::EvalProtocol::seed(0), aligning::EvalProtocol::seed(0));
    assert_ne!(pushing::env_seed(0, 0), aligning::env_seed(0, 0));
    assert_ne!(pushing::EnvConfig::default().physics, aligning::EnvConfig::default().physics);
}
