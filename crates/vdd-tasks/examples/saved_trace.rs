//! Records one episode of a saved policy acting in a contact task: the raw observations it
//! saw and the actions it returned, step by step, as JSON. The Python package's tests replay
//! the trace through `vdd.Policy.load` (`crates/vdd-py/tests/test_contact_students.py`) and
//! `vdd-tasks`' own (`tests/saved_traces.rs`) through `vdd_moe::load_policy`: both must return
//! the recorded actions for the recorded observations.
//!
//! ```text
//! cargo run --release -p vdd-tasks --example saved_trace -- MODEL --task block-push|pushing|aligning
//!     [--seed S] [--steps N] --out FILE.json
//! ```
//!
//! The episode starts from `S` (default 0) as the task's environment draws it, the policy is
//! seeded with `S` and reset, and at most `N` steps (default 40) are recorded.

use std::path::PathBuf;
use std::process::ExitCode;

use vdd_core::Policy;
use vdd_tasks::episodes::Env;

/// Observations and actions of an episode, step by step.
type Trace = (Vec<Vec<f32>>, Vec<Vec<f32>>);

/// One episode of `policy` in `E` from `seed`: observations and actions, at most `steps`.
fn record<E: Env>(
    config: &E::Config,
    policy: &mut impl Policy,
    seed: u64,
    steps: usize,
) -> Result<Trace, Box<dyn std::error::Error>> {
    let mut env = E::build(config)?;
    env.reset(seed);
    policy.seed(seed);
    policy.reset();
    let (mut obs, mut action, mut applied) =
        (vec![0.0; E::OBS_DIM], vec![0.0; E::ACTION_DIM], vec![0.0; E::ACTION_DIM]);
    let (mut observations, mut actions) = (Vec::new(), Vec::new());
    while observations.len() < steps && !env.is_done() {
        env.observe(&mut obs)?;
        policy.act_into(&obs, &mut action)?;
        observations.push(obs.clone());
        actions.push(action.clone());
        env.apply(&action, &mut applied)?;
    }
    Ok((observations, actions))
}

fn run() -> Result<(), Box<dyn std::error::Error>> {
    let usage = "usage: saved_trace MODEL --task block-push|pushing|aligning [--seed S] \
                 [--steps N] --out FILE.json";
    let (mut model, mut task, mut seed, mut steps, mut out) = (None, None, 0u64, 40usize, None);
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        let mut value = |name: &str| args.next().ok_or_else(|| format!("{name} needs a value"));
        match arg.as_str() {
            "--task" => task = Some(value("--task")?),
            "--seed" => seed = value("--seed")?.parse()?,
            "--steps" => steps = value("--steps")?.parse()?,
            "--out" => out = Some(PathBuf::from(value("--out")?)),
            flag if flag.starts_with('-') => return Err(format!("unknown {flag}\n{usage}").into()),
            path => model = Some(PathBuf::from(path)),
        }
    }
    let (Some(model), Some(task), Some(out)) = (model, task, out) else {
        return Err(usage.into());
    };
    let mut policy =
        vdd_moe::load_policy(&model).map_err(|e| format!("{}: {e}", model.display()))?;
    let (observations, actions) = match task.as_str() {
        "block-push" => {
            use vdd_tasks::block_push::{BlockPushEnv, EnvConfig};
            record::<BlockPushEnv>(&EnvConfig::default(), &mut policy, seed, steps)?
        }
        "pushing" => {
            use vdd_tasks::pushing::{EnvConfig, PushingEnv};
            record::<PushingEnv>(&EnvConfig::default(), &mut policy, seed, steps)?
        }
        "aligning" => {
            use vdd_tasks::aligning::{AligningEnv, EnvConfig};
            record::<AligningEnv>(&EnvConfig::default(), &mut policy, seed, steps)?
        }
        other => return Err(format!("unknown task {other}\n{usage}").into()),
    };
    let json = serde_json::json!({
        "task": task,
        "model": model.file_name().map(|f| f.to_string_lossy().into_owned()),
        "seed": seed,
        "observations": observations,
        "actions": actions,
    });
    std::fs::write(&out, serde_json::to_string(&json)?)?;
    println!("{}: {} steps of {task} recorded", out.display(), actions.len());
    Ok(())
}

fn main() -> ExitCode {
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("saved_trace: {e}");
            ExitCode::FAILURE
        }
    }
}
