//! Runs the scripted Pushing demonstrator for N episodes and prints success, p1, mean distance,
//! the mode histogram, episode lengths and µs per environment step (demonstrator + physics).
//!
//! ```text
//! cargo run --release -p vdd-tasks --example pushing_oracle -- 200 [seed=0] [threads=1]
//!     [substeps=10] [noise-free]
//! ```

use std::time::Instant;

use vdd_tasks::pushing::EnvConfig;
use vdd_tasks::pushing::oracle::{OracleConfig, PushingOracle};
use vdd_tasks::pushing::rollout::{EvalConfig, Stepping, evaluate_parallel_with};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let (mut n, mut seed, mut threads) = (200usize, 0u64, 1usize);
    let mut env = EnvConfig::default();
    let mut config = OracleConfig::default();
    for (i, arg) in std::env::args().skip(1).enumerate() {
        match arg.split_once('=') {
            None if i == 0 => n = arg.parse()?,
            None if arg == "noise-free" => config = OracleConfig::noise_free(),
            Some(("seed", v)) => seed = v.parse()?,
            Some(("threads", v)) => threads = v.parse()?,
            Some(("substeps", v)) => env.physics.substeps = v.parse()?,
            _ => return Err(format!("unknown argument {arg:?}").into()),
        }
    }
    let oracle = PushingOracle::new(config)?;
    let mut policies = vec![oracle; threads.max(1)];
    let cfg = EvalConfig { n_rollouts: n, seed, stepping: Stepping::PerEpisode, record: false };
    let t0 = Instant::now();
    let eval = evaluate_parallel_with(&mut policies, &cfg, &env)?;
    let secs = t0.elapsed().as_secs_f64();
    let m = &eval.metrics;
    println!(
        "Pushing demonstrator: {n} episodes, seed {seed}, {} thread(s), {} substeps",
        policies.len(),
        env.physics.substeps
    );
    println!(
        "success {:.3}, p1 {:.3}, mean distance {:.4}, mode entropy {:.3}, modes {:?}, \
         timeouts {}, faults {}",
        m.success_rate,
        m.p1_rate.unwrap_or_default(),
        m.mean_distance,
        m.mode_entropy,
        m.mode_counts,
        m.timeouts,
        m.faults
    );
    println!(
        "steps of successes: mean {:.1} / max {}; {:.1} µs per env step and thread",
        m.mean_success_steps,
        m.max_success_steps,
        secs * 1e6 * policies.len() as f64 / m.total_steps.max(1) as f64
    );
    for (i, r) in eval.rollouts.iter().enumerate().filter(|(_, r)| !r.success()) {
        println!("  episode {i}: {:?} after {} steps, mode {:?}", r.status, r.steps, r.info.mode);
    }
    Ok(())
}
