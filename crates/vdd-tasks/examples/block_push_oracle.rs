//! Runs the scripted Block-Push oracle for N episodes (first argument, default 200) and prints
//! success (p2), p1, task entropy, the mode histogram, episode lengths and µs per env step.
//!
//! `cargo run --release -p vdd-tasks --example block_push_oracle -- 200 [seed] [threads] [noise-free]`

use std::time::Instant;

use vdd_tasks::block_push::oracle::{BlockPushOracle, OracleConfig};
use vdd_tasks::block_push::rollout::{EvalConfig, Stepping, evaluate, evaluate_cloned};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let n: usize = args.first().map(|a| a.parse()).transpose()?.unwrap_or(200);
    let seed: u64 = args.get(1).map(|a| a.parse()).transpose()?.unwrap_or(0);
    let threads: usize = args.get(2).map(|a| a.parse()).transpose()?.unwrap_or(1);
    let config = if args.get(3).is_some_and(|a| a == "noise-free") {
        OracleConfig::noise_free()
    } else {
        OracleConfig::default()
    };
    let mut oracle = BlockPushOracle::new(config)?;
    let cfg = EvalConfig { n_rollouts: n, seed, stepping: Stepping::PerEpisode, record: false };
    let t0 = Instant::now();
    let eval = if threads > 1 {
        evaluate_cloned(&oracle, threads, &cfg)?
    } else {
        evaluate(&mut oracle, &cfg)?
    };
    let secs = t0.elapsed().as_secs_f64();
    let m = &eval.metrics;
    println!("Block-Push oracle, {n} episodes, seed {seed}, {threads} thread(s)");
    println!(
        "  success (p2)  {:.3} ({} of {n}), timeouts {}",
        m.success_rate, m.successes, m.timeouts
    );
    println!("  p1            {:.3}", m.p1_rate);
    println!("  task entropy  {:.3} over {} modes reached", m.task_entropy, m.modes_reached);
    println!("  mode counts   {:?} (b0→t0, b0→t1, b1→t0, b1→t1)", m.mode_counts);
    println!(
        "  episode steps mean {:.1} (successes), max {} (successes), all episodes {:.1}",
        m.mean_success_steps,
        m.max_success_steps,
        m.total_steps as f64 / n as f64
    );
    println!(
        "  {:.1} µs per env step (oracle + physics, {} steps in {:.2} s)",
        secs * 1e6 / m.total_steps.max(1) as f64 * threads as f64,
        m.total_steps,
        secs
    );
    Ok(())
}
