//! Runs the scripted Block-Push oracle for N episodes and prints success (p2), p1, task entropy,
//! the mode histogram, episode lengths and µs per environment step (oracle + physics).
//!
//! ```text
//! cargo run --release -p vdd-tasks --example block_push_oracle -- 200 [seed=0] [threads=1]
//!     [substeps=24] [noise-free]
//! ```

use std::time::Instant;

use vdd_tasks::block_push::EnvConfig;
use vdd_tasks::block_push::oracle::{BlockPushOracle, OracleConfig};
use vdd_tasks::block_push::rollout::{EvalConfig, Stepping, evaluate_parallel_with};

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
    let oracle = BlockPushOracle::new(config)?;
    let mut policies = vec![oracle; threads.max(1)];
    let cfg = EvalConfig { n_rollouts: n, seed, stepping: Stepping::PerEpisode, record: false };
    let t0 = Instant::now();
    let eval = evaluate_parallel_with(&mut policies, &cfg, &env)?;
    let secs = t0.elapsed().as_secs_f64();
    let m = &eval.metrics;
    println!(
        "Block-Push oracle: {n} episodes, seed {seed}, {} thread(s), {} substeps",
        policies.len(),
        env.physics.substeps
    );
    println!(
        "  success (p2)  {:.3} ({} of {n}; {} timeouts)",
        m.success_rate, m.successes, m.timeouts
    );
    println!("  p1            {:.3}", m.p1_rate);
    println!("  task entropy  {:.3} ({} of 4 modes reached)", m.task_entropy, m.modes_reached);
    println!("  mode counts   {:?} (b0→t0, b0→t1, b1→t0, b1→t1)", m.mode_counts);
    println!(
        "  steps         mean {:.1} / max {} over successes; mean {:.1} over all episodes",
        m.mean_success_steps,
        m.max_success_steps,
        m.total_steps as f64 / n.max(1) as f64
    );
    println!(
        "  time          {:.1} µs per env step and thread ({} steps in {:.2} s)",
        secs * 1e6 * policies.len() as f64 / m.total_steps.max(1) as f64,
        m.total_steps,
        secs
    );
    Ok(())
}
