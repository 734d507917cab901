//! Scripted Avoiding demonstrations written as an `.npz` dataset, checked to load back
//! bit-identically, with the demonstrator's metrics and rollout throughput
//! ([`write_demonstrations`]; `cargo xtask demos avoiding`).
//!
//! Writes `<out>/avoiding_demos.npz` (`observations_seq` `N x T x 4`, `actions_seq` `N x T x
//! 2`, `existence_mask` `N x T`, episodes padded to the longest) and
//! `<out>/avoiding_demos.json` (settings, per-episode lengths and modes, demonstrator metrics,
//! throughput). The evaluation rollouts use a seed derived from the demonstrations' seed
//! (`Seeds::new(seed).child("demonstrator-eval")`), so they are not the demonstrations
//! themselves.

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::time::Instant;

use vdd_core::Seeds;
use vdd_data::{DataError, Episodes};

use super::rollout::{EvalConfig, Evaluation, Stepping, evaluate, evaluate_cloned};
use super::{FarLeft, N_MODES};
use crate::{
    AvoidingDemonstrator, DemonstratorConfig, TaskError, generate_demonstrations,
    normalized_entropy,
};

/// The settings of [`write_demonstrations`].
#[derive(Debug, Clone, PartialEq)]
pub struct DemosOptions {
    /// Successful demonstrations to generate.
    pub n: usize,
    /// Seed of the demonstrations (the evaluation derives its own from it).
    pub seed: u64,
    /// Evaluation rollouts of the demonstrator.
    pub eval: usize,
    /// Evaluation threads of the parallel throughput runs.
    pub threads: usize,
}

/// Errors of [`write_demonstrations`].
#[derive(Debug, thiserror::Error)]
pub enum DemosError {
    /// Zero demonstrations, rollouts or threads.
    #[error("the demonstrations, evaluation rollouts and threads must be positive")]
    Settings,
    /// Generating or evaluating failed.
    #[error(transparent)]
    Task(#[from] TaskError),
    /// Writing or reading the dataset failed.
    #[error(transparent)]
    Data(#[from] DataError),
    /// Writing a file or directory failed.
    #[error("{}: {source}", .path.display())]
    Io {
        /// The file or directory.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// The metadata did not serialise.
    #[error("avoiding_demos.json: {0}")]
    Json(#[from] serde_json::Error),
    /// A check failed: the dataset does not load back bit-identically, or the parallel
    /// evaluation differs from the sequential one.
    #[error("{0}")]
    Check(String),
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> DemosError + '_ {
    move |source| DemosError::Io { path: path.to_owned(), source }
}

/// Generates `o.n` demonstrations into `out` (see the [module docs](self)), evaluates the
/// demonstrator over `o.eval` rollouts and measures rollout throughput; `log` receives the
/// summary lines.
pub fn write_demonstrations(
    o: &DemosOptions,
    out: &Path,
    mut log: impl FnMut(String),
) -> Result<(), DemosError> {
    let (n, seed, n_eval, threads) = (o.n, o.seed, o.eval, o.threads);
    if n == 0 || n_eval == 0 || threads == 0 {
        return Err(DemosError::Settings);
    }
    let config = DemonstratorConfig::default();

    // 1. Demonstrations.
    let t0 = Instant::now();
    let demos = generate_demonstrations(n, seed, &config)?;
    let gen_secs = t0.elapsed().as_secs_f64();
    let lengths = demos.lengths();
    let total_steps: usize = lengths.iter().sum();
    let mode_counts = demos.mode_counts();
    log(format!(
        "generated {n} Avoiding demonstrations (seed {seed}) from {} episodes in {:.1} ms",
        demos.episodes_run,
        gen_secs * 1e3
    ));
    log(format!(
        "  lengths: min {} / mean {:.1} / max {} steps ({total_steps} steps in total)",
        lengths.iter().min().copied().unwrap_or(0),
        total_steps as f64 / n as f64,
        lengths.iter().max().copied().unwrap_or(0)
    ));
    log(format!(
        "  modes in the dataset: {} of {N_MODES}, entropy {:.4}",
        mode_counts.iter().filter(|&&c| c > 0).count(),
        normalized_entropy(&mode_counts)
    ));

    // 2. Write, load back, compare.
    std::fs::create_dir_all(out).map_err(io(out))?;
    let npz = out.join("avoiding_demos.npz");
    let episodes = demos.to_episodes()?;
    episodes.save_npz(&npz)?;
    check_round_trip(&episodes, &npz)?;
    log(format!("wrote {} and loaded it back bit-identically", npz.display()));

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
    log(format!(
        "demonstrator over {n_eval} rollouts (seed {eval_seed}): success rate {:.4} ({} collisions, \
         {} timeouts), task entropy {:.4}, {} of {N_MODES} modes, mean length {:.1}",
        m.success_rate,
        m.collisions,
        m.timeouts,
        m.task_entropy,
        m.modes_reached,
        m.mean_success_steps
    ));
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
            let e = "parallel per-episode evaluation differs from the sequential one";
            return Err(DemosError::Check(e.into()));
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
    log("rollout throughput (demonstrator policy + environment):".into());
    for (name, rate) in &throughput {
        log(format!("  {name:<28} {:>8.2} M steps/s", rate / 1e6));
    }
    log(format!(
        "environment alone (trivial policy, 1 thread): {:.2} M steps/s per-episode, \
         {:.2} M steps/s lockstep 64",
        env_rate / 1e6,
        env_lockstep_rate / 1e6
    ));
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
        "throughput_steps_per_sec": throughput.into_iter().collect::<BTreeMap<_, _>>(),
    });
    let meta = out.join("avoiding_demos.json");
    std::fs::write(&meta, serde_json::to_string_pretty(&json)?).map_err(io(&meta))?;
    log(format!("wrote {}", meta.display()));
    Ok(())
}

/// Loads `path` back and checks it equals `episodes`, bit for bit: `PartialEq` compares the
/// values, and saving the loaded set again must reproduce the file byte for byte (the writer is
/// deterministic and stores raw `f32` bits, so this also catches `-0.0` vs `0.0`).
pub fn check_round_trip(episodes: &Episodes, path: &Path) -> Result<(), DemosError> {
    let loaded = Episodes::load_npz(path)?;
    if &loaded != episodes {
        let e = format!("{} does not load back to the saved episodes", path.display());
        return Err(DemosError::Check(e));
    }
    let again = path.with_extension("roundtrip.npz");
    loaded.save_npz(&again)?;
    let same =
        std::fs::read(path).map_err(io(path))? == std::fs::read(&again).map_err(io(&again))?;
    std::fs::remove_file(&again).map_err(io(&again))?;
    if !same {
        let e = format!("re-saving the loaded {} changes its bytes", path.display());
        return Err(DemosError::Check(e));
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

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn demonstrations_are_written_checked_and_described() {
        let dir = std::env::temp_dir().join(format!("vdd-tasks-demos-{}", std::process::id()));
        let o = DemosOptions { n: 3, seed: 1, eval: 4, threads: 2 };
        let mut lines = Vec::new();
        write_demonstrations(&o, &dir, |l| lines.push(l)).unwrap();
        assert!(lines[0].starts_with("generated 3 Avoiding demonstrations (seed 1)"), "{lines:?}");
        let episodes = Episodes::load_npz(&dir.join("avoiding_demos.npz")).unwrap();
        check_round_trip(&episodes, &dir.join("avoiding_demos.npz")).unwrap();
        let meta: serde_json::Value =
            serde_json::from_slice(&std::fs::read(dir.join("avoiding_demos.json")).unwrap())
                .unwrap();
        assert_eq!(meta["lengths"].as_array().map(Vec::len), Some(3));
        assert_eq!(meta["throughput_steps_per_sec"].as_object().map(|m| m.len()), Some(6));
        let zero = DemosOptions { n: 0, ..o };
        assert!(matches!(write_demonstrations(&zero, &dir, |_| {}), Err(DemosError::Settings)));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
