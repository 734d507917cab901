//! `cargo xtask demos avoiding`: generates scripted Avoiding demonstrations, writes them as an
//! `.npz` dataset, checks that it loads back bit-identically, and measures the demonstrator
//! (success rate, task entropy, rollout throughput).
//!
//! ```text
//! cargo xtask demos avoiding [--n 200] [--seed 0] [--out results/demos/avoiding]
//!                            [--eval 500] [--threads N]
//! ```
//!
//! The files and checks are [`vdd_tasks::avoiding::demos`]'s. `--export FILE` instead writes
//! the recipe's training episodes (`recipes/defaults/avoiding.toml`'s `[data]`;
//! `DatasetConfig::train_episodes`) to `FILE` (`.npz`), for models trained elsewhere
//! (`scripts/import/train_lerobot_avoiding.py`).

use std::path::PathBuf;

use vdd_tasks::avoiding::demos::{DemosOptions, write_demonstrations};

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
        let data = vdd_lab::tasks::AvoidingRecipe::defaults()?.data;
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
    let default_threads = std::thread::available_parallelism().map_or(1, |p| p.get());
    let threads = args.threads.unwrap_or(default_threads);
    let o = DemosOptions { n: args.n, seed: args.seed, eval: args.eval, threads };
    Ok(write_demonstrations(&o, &args.out, |line| println!("{line}"))?)
}
