//! Oracle Block-Push demonstrations written as an `.npz` dataset, checked to load back
//! bit-identically, with the oracle's metrics ([`write_demonstrations`]), as Avoiding's
//! [`crate::avoiding::demos`] does.
//!
//! Writes `<out>/block_push_demos.npz` (`observations_seq` `N x T x 16`, `actions_seq`
//! `N x T x 2`, `existence_mask` `N x T`, episodes padded to the longest) and
//! `<out>/block_push_demos.json` (settings, per-episode lengths and modes, the demonstrations'
//! success rate and mode histogram, the oracle's metrics over separate evaluation rollouts
//! and the µs per environment step). The evaluation uses a seed derived from the
//! demonstrations' seed (`Seeds::new(seed).child("oracle-eval")`).

use std::path::Path;
use std::time::Instant;

use vdd_core::Seeds;

use super::oracle::{BlockPushOracle, OracleConfig, generate_demonstrations};
use super::rollout::{EvalConfig, Stepping, evaluate_cloned};
pub use crate::avoiding::demos::{DemosError, DemosOptions, check_round_trip};
use crate::normalized_entropy;

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> DemosError + '_ {
    move |source| DemosError::Io { path: path.to_owned(), source }
}

/// Generates `o.n` successful oracle demonstrations into `out` (see the
/// [module docs](self)), evaluates the oracle over `o.eval` rollouts on `o.threads` threads;
/// `log` receives the summary lines.
pub fn write_demonstrations(
    o: &DemosOptions,
    out: &Path,
    mut log: impl FnMut(String),
) -> Result<(), DemosError> {
    let (n, seed, n_eval, threads) = (o.n, o.seed, o.eval, o.threads);
    if n == 0 || n_eval == 0 || threads == 0 {
        return Err(DemosError::Settings);
    }
    let config = OracleConfig::default();
    let t0 = Instant::now();
    let demos = generate_demonstrations(n, seed, &config)?;
    let gen_secs = t0.elapsed().as_secs_f64();
    let lengths = demos.lengths();
    let total_steps: usize = lengths.iter().sum();
    let mode_counts = demos.mode_counts();
    log(format!(
        "generated {n} Block-Push demonstrations (seed {seed}) from {} episodes \
         (success rate {:.3}) in {:.1} s",
        demos.episodes_run,
        demos.success_rate(),
        gen_secs
    ));
    log(format!(
        "  lengths: min {} / mean {:.1} / max {} steps; modes {mode_counts:?}, entropy {:.4}",
        lengths.iter().min().copied().unwrap_or(0),
        total_steps as f64 / n as f64,
        lengths.iter().max().copied().unwrap_or(0),
        normalized_entropy(&mode_counts)
    ));

    std::fs::create_dir_all(out).map_err(io(out))?;
    let npz = out.join("block_push_demos.npz");
    let episodes = demos.to_episodes()?;
    episodes.save_npz(&npz)?;
    check_round_trip(&episodes, &npz)?;
    log(format!("wrote {} and loaded it back bit-identically", npz.display()));

    let eval_seed = Seeds::new(seed).child("oracle-eval").root();
    let oracle = BlockPushOracle::new(config.clone())?;
    let cfg = EvalConfig {
        n_rollouts: n_eval,
        seed: eval_seed,
        stepping: Stepping::PerEpisode,
        record: false,
    };
    let t0 = Instant::now();
    let eval = evaluate_cloned(&oracle, threads, &cfg)?;
    let secs = t0.elapsed().as_secs_f64();
    let m = &eval.metrics;
    let us_per_step = secs * 1e6 * threads.min(n_eval) as f64 / m.total_steps.max(1) as f64;
    log(format!(
        "oracle over {n_eval} rollouts (seed {eval_seed}): success {:.4}, p1 {:.4}, task entropy \
         {:.4}, modes {:?}, mean length {:.1}; {us_per_step:.1} µs per env step and thread",
        m.success_rate, m.p1_rate, m.task_entropy, m.mode_counts, m.mean_success_steps
    ));

    let json = serde_json::json!({
        "task": "block_push",
        "n": n,
        "seed": seed,
        "episodes_run": demos.episodes_run,
        "success_rate": demos.success_rate(),
        "oracle": config,
        "lengths": lengths,
        "modes": demos.modes.iter().map(|m| m.index()).collect::<Vec<_>>(),
        "dataset_mode_counts": mode_counts,
        "evaluation": { "seed": eval_seed, "metrics": eval.metrics },
        "us_per_env_step": us_per_step,
    });
    let meta = out.join("block_push_demos.json");
    std::fs::write(&meta, serde_json::to_string_pretty(&json)?).map_err(io(&meta))?;
    log(format!("wrote {}", meta.display()));
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use vdd_data::Episodes;

    #[test]
    fn demonstrations_are_written_checked_and_described() {
        let dir = std::env::temp_dir().join(format!("vdd-tasks-bp-demos-{}", std::process::id()));
        let o = DemosOptions { n: 3, seed: 1, eval: 2, threads: 2 };
        let mut lines = Vec::new();
        write_demonstrations(&o, &dir, |l| lines.push(l)).unwrap();
        assert!(lines[0].starts_with("generated 3 Block-Push demonstrations"), "{lines:?}");
        let npz = dir.join("block_push_demos.npz");
        let episodes = Episodes::load_npz(&npz).unwrap();
        assert_eq!(episodes.num_episodes(), 3);
        check_round_trip(&episodes, &npz).unwrap();
        let meta: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.join("block_push_demos.json")).unwrap())
                .unwrap();
        assert_eq!(meta["lengths"].as_array().map(Vec::len), Some(3));
        assert_eq!(meta["dataset_mode_counts"].as_array().map(Vec::len), Some(4));
        let zero = DemosOptions { n: 0, ..o };
        assert!(matches!(write_demonstrations(&zero, &dir, |_| {}), Err(DemosError::Settings)));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
