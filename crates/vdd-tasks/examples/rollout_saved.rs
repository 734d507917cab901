//! Rolls out a saved policy of a task (Avoiding, the default, Block-Push, Pushing or Aligning) on the
//! environment's raw observations and prints one JSON line with its success rate and task
//! entropy (and p1 on Block-Push and Pushing, the mean distance on Pushing and Aligning).
//!
//! ```text
//! cargo run --release -p vdd-tasks --example rollout_saved -- MODEL [--task TASK] [--seed S]
//!     [--rollouts N] [--contexts C] [--lockstep-batch B] [--threads T] [--hold K] [--greedy]
//!     [--temperature T]
//! ```
//!
//! `MODEL` is a mixture saved by `Moe::save`, e.g. a recipe's
//! `results/avoiding/<run>/models/vdd-beso-s0.safetensors`. One call
//! (`vdd_moe::load_policy`) loads it with everything it needs to act on raw observations: the
//! normalisers, the act mode and the deployment spec (observation features, window, chunk). The
//! evaluation is the recipe's ([`EvalProtocol`]; Block-Push's is
//! `vdd_tasks::block_push::EvalProtocol`): with the run seed `S` (default 0), `N` rollouts
//! (default: the task's, 500 on Avoiding and 200 on Block-Push; on Pushing and Aligning, D3IL's
//! `C` contexts × `N` rollouts each, default 30 × 16 and 60 × 8; `--quick` recipes use fewer)
//! and the recipe's lockstep batch (default 50) it prints the recipe's figures for that student
//! bit for bit. Threads (default: every
//! core) do not change the figures. `--hold K` replaces the saved act mode's
//! [`vdd_moe::ActMode::hold_steps`]: each episode keeps the expert it picks for `K` predictions
//! (`K` steps; `K · execute_steps` with action chunks), which changes the figures for `K > 1`.
//! `--greedy` acts with the most probable expert of `q(z|s)` instead of a sampled one
//! ([`vdd_moe::ActMode::greedy_gating`]). `--temperature T` sharpens (`T < 1`) or flattens a
//! learned gating first ([`vdd_moe::Moe::sharpen_gating`]).

use std::path::PathBuf;
use std::process::ExitCode;

use vdd_tasks::aligning::AligningEnv;
use vdd_tasks::avoiding::EvalProtocol;
use vdd_tasks::d3il::ContextEnv;
use vdd_tasks::pushing::PushingEnv;

/// The command line.
struct Args {
    model: PathBuf,
    task: String,
    seed: u64,
    rollouts: Option<usize>,
    contexts: Option<usize>,
    lockstep_batch: Option<usize>,
    threads: usize,
    hold: Option<u32>,
    greedy: bool,
    temperature: Option<f32>,
}

const USAGE: &str = "usage: rollout_saved MODEL [--task avoiding|block-push|pushing|aligning] [--seed S] [--rollouts N] [--contexts C] [--lockstep-batch B] [--threads T] \
     [--hold K] [--greedy] [--temperature T]";

fn parse() -> Result<Args, String> {
    let mut model = None;
    let mut seed = 0;
    let mut task = "avoiding".to_owned();
    let mut rollouts = None;
    let mut contexts = None;
    let mut lockstep_batch = None;
    let mut threads = std::thread::available_parallelism().map_or(1, |n| n.get());
    let mut hold = None;
    let mut greedy = false;
    let mut temperature = None;
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        let mut value = |name: &str| -> Result<u64, String> {
            let v = args.next().ok_or_else(|| format!("{name} needs a value"))?;
            v.parse().map_err(|e| format!("{name} {v}: {e}"))
        };
        match arg.as_str() {
            "--seed" => seed = value("--seed")?,
            "--task" => task = args.next().ok_or("--task needs a value")?,
            "--rollouts" => rollouts = Some(value("--rollouts")? as usize),
            "--contexts" => contexts = Some(value("--contexts")? as usize),
            "--lockstep-batch" => lockstep_batch = Some(value("--lockstep-batch")? as usize),
            "--threads" => threads = value("--threads")? as usize,
            "--hold" => hold = Some(u32::try_from(value("--hold")?).map_err(|e| e.to_string())?),
            "--greedy" => greedy = true,
            "--temperature" => {
                let v = args.next().ok_or("--temperature needs a value")?;
                temperature = Some(v.parse().map_err(|e| format!("--temperature {v}: {e}"))?);
            }
            "-h" | "--help" => return Err(USAGE.into()),
            flag if flag.starts_with('-') => return Err(format!("unknown option {flag}\n{USAGE}")),
            path if model.is_none() => model = Some(PathBuf::from(path)),
            extra => return Err(format!("unexpected argument {extra}\n{USAGE}")),
        }
    }
    let model = model.ok_or_else(|| USAGE.to_owned())?;
    Ok(Args {
        model,
        task,
        seed,
        rollouts,
        contexts,
        lockstep_batch,
        threads,
        hold,
        greedy,
        temperature,
    })
}

fn run() -> Result<(), Box<dyn std::error::Error>> {
    let args = parse()?;
    let mut policy =
        vdd_moe::load_policy(&args.model).map_err(|e| format!("{}: {e}", args.model.display()))?;
    let moe = policy.inner_mut();
    if let Some(t) = args.temperature {
        moe.sharpen_gating(t)?;
    }
    let saved = moe.act_mode();
    let hold_steps = args.hold.unwrap_or(saved.hold_steps);
    let greedy_gating = args.greedy || saved.greedy_gating;
    moe.set_act_mode(vdd_moe::ActMode { hold_steps, greedy_gating, ..saved });
    let (seed, threads) = (args.seed, args.threads);
    if args.contexts.is_some() && !matches!(args.task.as_str(), "pushing" | "aligning") {
        return Err(format!("--contexts is for --task pushing and aligning\n{USAGE}").into());
    }
    // Numbers as serde_json writes them (as in the recipe's metrics.json), keys in this order.
    let json = |x: &f64| serde_json::to_string(x);
    match args.task.as_str() {
        "avoiding" => {
            let d = EvalProtocol::default();
            let rollouts = args.rollouts.unwrap_or(d.rollouts);
            let lockstep_batch = args.lockstep_batch.unwrap_or(d.lockstep_batch);
            let protocol = EvalProtocol { rollouts, lockstep_batch };
            let m = protocol.evaluate(&policy, seed, threads, false)?.metrics;
            println!(
                r#"{{"success_rate": {}, "task_entropy": {}, "rollouts": {}}}"#,
                json(&m.success_rate)?,
                json(&m.task_entropy)?,
                m.rollouts
            );
        }
        "block-push" => {
            use vdd_tasks::block_push::EvalProtocol as BlockPush;
            let d = BlockPush::default();
            let rollouts = args.rollouts.unwrap_or(d.rollouts);
            let lockstep_batch = args.lockstep_batch.unwrap_or(d.lockstep_batch);
            let protocol = BlockPush { rollouts, lockstep_batch };
            let m = protocol.evaluate(&policy, seed, threads, false)?.metrics;
            println!(
                r#"{{"success_rate": {}, "p1_rate": {}, "task_entropy": {}, "rollouts": {}}}"#,
                json(&m.success_rate)?,
                json(&m.p1_rate)?,
                json(&m.task_entropy)?,
                m.rollouts
            );
        }
        "pushing" => println!("{}", d3il::<PushingEnv>(&args, &policy)?),
        "aligning" => println!("{}", d3il::<AligningEnv>(&args, &policy)?),
        other => return Err(format!("unknown task {other}\n{USAGE}").into()),
    }
    Ok(())
}

/// The JSON line of a D3IL task (Pushing, Aligning): success rate, p1 (Pushing), mean distance,
/// task entropy and rollouts of `args.contexts × args.rollouts` episodes (default: D3IL's).
fn d3il<E: ContextEnv>(
    args: &Args,
    policy: &vdd_moe::DeployedPolicy,
) -> Result<String, Box<dyn std::error::Error>> {
    let d = vdd_tasks::d3il::EvalProtocol::<E>::default();
    let protocol = vdd_tasks::d3il::EvalProtocol::<E>::new(
        args.contexts.unwrap_or(d.contexts),
        args.rollouts.unwrap_or(d.rollouts_per_context),
        args.lockstep_batch.unwrap_or(d.lockstep_batch),
    );
    let m = protocol.evaluate(policy, args.seed, args.threads, false)?.metrics;
    // Numbers as serde_json writes them (as in the recipe's metrics.json), keys in this order.
    let json = |x: &f64| serde_json::to_string(x);
    let p1 = match m.p1_rate {
        Some(p1) => format!(r#" "p1_rate": {},"#, json(&p1)?),
        None => String::new(),
    };
    Ok(format!(
        r#"{{"success_rate": {},{p1} "mean_distance": {}, "task_entropy": {}, "rollouts": {}}}"#,
        json(&m.success_rate)?,
        json(&m.mean_distance)?,
        json(&m.task_entropy)?,
        m.rollouts
    ))
}

fn main() -> ExitCode {
    match run() {
        Ok(()) => ExitCode::SUCCESS,
        Err(e) => {
            eprintln!("rollout_saved: {e}");
            ExitCode::FAILURE
        }
    }
}
