//! `cargo xtask demos avoiding`: generates scripted Avoiding demonstrations, writes them as an
//! `.npz` dataset, checks that it loads back bit-identically, and measures the demonstrator
//! (success rate, task entropy, rollout throughput).
//!
//! ```text
//! cargo xtask demos avoiding [--n 200] [--seed 0] [--out results/demos/avoiding]
//!                            [--eval 500] [--threads N]
//! ```
//!
//! Writes `DIR/avoiding_demos.npz` (`observations_seq` `N x T x 4`, `actions_seq` `N x T x 2`,
//! `existence_mask` `N x T`, episodes padded to the longest) and `DIR/avoiding_demos.json`
//! (settings, per-episode lengths and modes, demonstrator metrics). The evaluation rollouts use
//! a seed derived from `--seed` (`Seeds::new(seed).child("demonstrator-eval")`), so they are
//! not the demonstrations themselves.
//!
//! `--export FILE` instead writes the recipe's training episodes (`recipes/defaults/avoiding.toml`'s
//! `[data]`: its demonstrations, data seed, train/validation split and feature map;
//! `vdd_tasks::avoiding::dataset::DatasetConfig::train_episodes`) to `FILE` (`.npz`, as above),
//! for models trained elsewhere (`scripts/import/train_lerobot_avoiding.py`).

use std::path::{Path, PathBuf};
use std::time::Instant;

use vdd_core::Seeds;
use vdd_data::Episodes;
use vdd_tasks::avoiding::FarLeft;
use vdd_tasks::avoiding::N_MODES;
use vdd_tasks::avoiding::rollout::{EvalConfig, Evaluation, Stepping, evaluate, evaluate_cloned};
use vdd_tasks::{
    AvoidingDemonstrator, DemonstratorConfig, generate_demonstrations, normalized_entropy,
};

/// The command line of `demos avoiding`.
#[derive(Debug, Clone, clap::Args)]
pub struct AvoidingArgs {
    /// Successful demonstrations to generate.
    #[arg(long, default_value_t = 200)]
    pub n: usize,
    /// Seed of the demonstrations (the evaluation derives its own from it).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Output directory.
    #[arg(long, value_name = "DIR", default_value = "results/demos/avoiding")]
    pub out: PathBuf,
    /// Evaluation rollouts of the demonstrator.
    #[arg(long, default_value_t = 500)]
    pub eval: usize,
    /// Evaluation threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Only write the recipe's featured training episodes to this `.npz` (see the module docs).
    #[arg(long, value_name = "FILE")]
    pub export: Option<PathBuf>,
}

/// `cargo xtask demos avoiding`.
pub fn avoiding(args: &AvoidingArgs) -> crate::XResult {
    if let Some(path) = &args.export {
        let data = crate::tasks::AvoidingRecipe::defaults()?.data;
        let (train, _) = data.train_episodes()?;
        train.save_npz(path)?;
        let f = data.features.feature_map();
        println!(
            "wrote {} ({} training episodes of data seed {}, {} steps, features {})",
            path.display(),
            train.num_episodes(),
            data.seed,
            train.num_steps(),
            f.id()
        );
        return Ok(());
    }
    let (n, seed, out, n_eval) = (args.n, args.seed, args.out.clone(), args.eval);
    let default_threads = std::thread::available_parallelism().map_or(1, |p| p.get());
    let threads = args.threads.unwrap_or(default_threads);
    if n == 0 || n_eval == 0 || threads == 0 {
        return Err("--n, --eval and --threads must be positive".into());
    }
    let config = DemonstratorConfig::default();

    // 1. Demonstrations.
    let t0 = Instant::now();
    let demos = generate_demonstrations(n, seed, &config)?;
    let gen_secs = t0.elapsed().as_secs_f64();
    let lengths = demos.lengths();
    let total_steps: usize = lengths.iter().sum();
    let mode_counts = demos.mode_counts();
    println!(
        "generated {n} Avoiding demonstrations (seed {seed}) from {} episodes in {:.1} ms",
        demos.episodes_run,
        gen_secs * 1e3
    );
    println!(
        "  lengths: min {} / mean {:.1} / max {} steps ({total_steps} steps in total)",
        lengths.iter().min().copied().unwrap_or(0),
        total_steps as f64 / n as f64,
        lengths.iter().max().copied().unwrap_or(0)
    );
    println!(
        "  modes in the dataset: {} of {N_MODES}, entropy {:.4}",
        mode_counts.iter().filter(|&&c| c > 0).count(),
        normalized_entropy(&mode_counts)
    );

    // 2. Write, load back, compare.
    std::fs::create_dir_all(&out).map_err(|e| format!("creating {}: {e}", out.display()))?;
    let npz = out.join("avoiding_demos.npz");
    let episodes = demos.to_episodes()?;
    episodes.save_npz(&npz)?;
    check_round_trip(&episodes, &npz)?;
    println!("wrote {} and loaded it back bit-identically", npz.display());

    // 3. Demonstrator metrics over `n_eval` rollouts, and rollout throughput.
    let eval_seed = Seeds::new(seed).child("demonstrator-eval").root();
    let mut demo = AvoidingDemonstrator::new(config.clone())?;
    let cfg = EvalConfig {
        n_rollouts: n_eval,
        seed: eval_seed,
        stepping: Stepping::PerEpisode,
        record: false,
    };
    let (eval, secs) = timed(|| evaluate(&mut demo, &cfg))?;
    let m = &eval.metrics;
    println!(
        "demonstrator over {n_eval} rollouts (seed {eval_seed}): success rate {:.4} ({} collisions, \
         {} timeouts), task entropy {:.4}, {} of {N_MODES} modes, mean length {:.1}",
        m.success_rate,
        m.collisions,
        m.timeouts,
        m.task_entropy,
        m.modes_reached,
        m.mean_success_steps
    );
    let mut throughput = vec![("per-episode, 1 thread".to_owned(), steps_per_sec(&eval, secs))];
    let lockstep = Stepping::Lockstep { batch_size: 64 };
    let runs = [
        (format!("per-episode, {threads} threads"), Stepping::PerEpisode, threads),
        ("lockstep 64, 1 thread".to_owned(), lockstep, 1),
        (format!("lockstep 64, {threads} threads"), lockstep, threads),
    ];
    for (name, stepping, t) in runs {
        let cfg = EvalConfig { stepping, ..cfg.clone() };
        let (e, secs) = timed(|| evaluate_cloned(&demo, t, &cfg))?;
        if stepping == Stepping::PerEpisode && e != eval {
            return Err("parallel per-episode evaluation differs from the sequential one".into());
        }
        throughput.push((name, steps_per_sec(&e, secs)));
    }
    // The environment's own cost, under a trivial memoryless policy.
    let env_cfg = EvalConfig { n_rollouts: n_eval.max(2000), ..cfg.clone() };
    let (e, secs) = timed(|| evaluate(&mut FarLeft, &env_cfg))?;
    let env_rate = steps_per_sec(&e, secs);
    let (e, secs) =
        timed(|| evaluate(&mut FarLeft, &EvalConfig { stepping: lockstep, ..env_cfg.clone() }))?;
    let env_lockstep_rate = steps_per_sec(&e, secs);
    println!("rollout throughput (demonstrator policy + environment):");
    for (name, rate) in &throughput {
        println!("  {name:<28} {:>8.2} M steps/s", rate / 1e6);
    }
    println!(
        "environment alone (trivial policy, 1 thread): {:.2} M steps/s per-episode, \
         {:.2} M steps/s lockstep 64",
        env_rate / 1e6,
        env_lockstep_rate / 1e6
    );
    throughput.push(("environment, per-episode, 1 thread".to_owned(), env_rate));
    throughput.push(("environment, lockstep 64, 1 thread".to_owned(), env_lockstep_rate));

    // 4. Metadata.
    let json = serde_json::json!({
        "task": "avoiding",
        "n": n,
        "seed": seed,
        "episodes_run": demos.episodes_run,
        "demonstrator": config,
        "lengths": lengths,
        "modes": demos.modes.iter().map(|m| m.index()).collect::<Vec<_>>(),
        "dataset_mode_counts": mode_counts,
        "evaluation": { "seed": eval_seed, "metrics": eval.metrics },
        "throughput_steps_per_sec": throughput.iter().map(|(k, v)| (k.clone(), *v)).collect::<std::collections::BTreeMap<_, _>>(),
    });
    let meta = out.join("avoiding_demos.json");
    std::fs::write(&meta, serde_json::to_string_pretty(&json)?)
        .map_err(|e| format!("writing {}: {e}", meta.display()))?;
    println!("wrote {}", meta.display());
    Ok(())
}

/// Loads `path` back and checks it equals `episodes`, bit for bit: `PartialEq` compares the
/// values, and saving the loaded set again must reproduce the file byte for byte (the writer is
/// deterministic and stores raw `f32` bits, so this also catches `-0.0` vs `0.0`).
fn check_round_trip(episodes: &Episodes, path: &Path) -> crate::XResult {
    let loaded = Episodes::load_npz(path)?;
    if &loaded != episodes {
        return Err(format!("{} does not load back to the saved episodes", path.display()).into());
    }
    let again = path.with_extension("roundtrip.npz");
    loaded.save_npz(&again)?;
    let same = std::fs::read(path)? == std::fs::read(&again)?;
    std::fs::remove_file(&again)?;
    if !same {
        return Err(format!("re-saving the loaded {} changes its bytes", path.display()).into());
    }
    Ok(())
}

fn timed<T, E>(f: impl FnOnce() -> Result<T, E>) -> Result<(T, f64), E> {
    let t0 = Instant::now();
    let v = f()?;
    Ok((v, t0.elapsed().as_secs_f64()))
}

fn steps_per_sec(e: &Evaluation, secs: f64) -> f64 {
    e.metrics.total_steps as f64 / secs.max(1e-9)
}
