//! The committed traces of saved contact-task students (`tests/fixtures/contact/`, written by
//! the `saved_trace` example) still hold: the environment gives the recorded observations and
//! the loaded student the recorded actions, bit for bit. The Python package replays the same
//! traces (`crates/vdd-py/tests/test_contact_students.py`). After a deliberate change to a
//! task's physics or to the policy format, regenerate them with the commands in
//! `tests/fixtures/contact/README.md`.

use std::path::{Path, PathBuf};

use vdd_core::Policy;
use vdd_tasks::episodes::Env;

fn fixtures() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/contact")
}

#[derive(serde::Deserialize)]
struct Trace {
    seed: u64,
    observations: Vec<Vec<f32>>,
    actions: Vec<Vec<f32>>,
}

fn replay<E: Env>(task: &str, config: &E::Config) {
    let dir = fixtures();
    let trace: Trace =
        serde_json::from_slice(&std::fs::read(dir.join(format!("{task}.json"))).unwrap()).unwrap();
    assert!(trace.actions.len() >= 10, "{task}: a trace of {} steps", trace.actions.len());
    let mut policy = vdd_moe::load_policy(&dir.join(format!("{task}.safetensors"))).unwrap();
    let mut env = E::build(config).unwrap();
    env.reset(trace.seed);
    policy.seed(trace.seed);
    policy.reset();
    let (mut obs, mut action, mut applied) =
        (vec![0.0; E::OBS_DIM], vec![0.0; E::ACTION_DIM], vec![0.0; E::ACTION_DIM]);
    for (t, (o, a)) in trace.observations.iter().zip(&trace.actions).enumerate() {
        env.observe(&mut obs).unwrap();
        assert_eq!(&obs, o, "{task}: the observation of step {t}");
        policy.act_into(&obs, &mut action).unwrap();
        assert_eq!(&action, a, "{task}: the action of step {t}");
        env.apply(&action, &mut applied).unwrap();
    }
}

#[test]
fn a_saved_pushing_student_replays_its_trace() {
    replay::<vdd_tasks::pushing::PushingEnv>("pushing", &Default::default());
}

#[test]
fn a_saved_aligning_student_replays_its_trace() {
    replay::<vdd_tasks::aligning::AligningEnv>("aligning", &Default::default());
}
