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

/// The command line of `demos block-push`.
#[derive(Debug, Clone, clap::Args)]
pub struct BlockPushArgs {
    /// Successful demonstrations to generate.
    #[arg(long, default_value_t = 200)]
    pub n: usize,
    /// Seed of the demonstrations (the evaluation derives its own from it).
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Output directory.
    #[arg(long, value_name = "DIR", default_value = "results/demos/block-push")]
    pub out: PathBuf,
    /// Evaluation rollouts of the oracle.
    #[arg(long, default_value_t = 500)]
    pub eval: usize,
    /// Evaluation threads (default: all cores).
    #[arg(long)]
    pub threads: Option<usize>,
    /// Demonstrations drawn per panel of the figure (one panel per target layout; colour =
    /// mode).
    #[arg(long, default_value_t = 12)]
    pub figure: usize,
}

/// `cargo xtask demos block-push`: the oracle's demonstrations as `.npz` with their metadata
/// ([`vdd_tasks::block_push::demos`]), their mode histogram and a trajectory figure coloured by
/// mode (`trajectories-*.svg`, `modes.svg`).
pub fn block_push(args: &BlockPushArgs) -> crate::XResult {
    use vdd_tasks::block_push::demos::write_demonstrations;
    let default_threads = std::thread::available_parallelism().map_or(1, |p| p.get());
    let threads = args.threads.unwrap_or(default_threads);
    let o = DemosOptions { n: args.n, seed: args.seed, eval: args.eval, threads };
    write_demonstrations(&o, &args.out, |line| println!("{line}"))?;
    let episodes = vdd_data::Episodes::load_npz(&args.out.join("block_push_demos.npz"))?;
    let meta: serde_json::Value =
        serde_json::from_slice(&std::fs::read(args.out.join("block_push_demos.json"))?)?;
    let modes: Vec<usize> = meta["modes"]
        .as_array()
        .map(|m| m.iter().filter_map(|v| v.as_u64()).map(|v| v as usize).collect())
        .unwrap_or_default();
    let (observations, _) = episodes.to_episode_matrices();
    let stem = args.out.join("trajectories");
    let mut files =
        vdd_lab::plots::block_push_demonstrations(&stem, &observations, &modes, args.figure, true)?;
    let n_modes = vdd_tasks::block_push::N_MODES;
    let shares: Vec<f64> = (0..n_modes)
        .map(|m| modes.iter().filter(|&&x| x == m).count() as f64 / modes.len().max(1) as f64)
        .collect();
    let panel = [("oracle demonstrations (b0→t0, b0→t1, b1→t0, b1→t1)".to_owned(), shares)];
    files.extend(vdd_lab::plots::mode_histograms(&args.out.join("modes"), &panel, true)?);
    println!("wrote {}", files.join(", "));
    Ok(())
}
