//! `cargo xtask bench robustness [--quick] --out DIR`: the robustness benchmark of
//! [`vdd_lab::bench::robustness`] (VDD with library defaults only on the seeded family of exact-mixture
//! teachers and its extra problems). Writes `DIR/robustness.json`: one record per run and the
//! summary, which it also prints.

use std::path::PathBuf;

use vdd_lab::bench::robustness::{RobustnessOptions, Variant, robustness};

/// The command line of `bench robustness`.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// 8 random problems (and the extra ones) and one seed instead of 24 and three.
    #[arg(long)]
    pub quick: bool,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Parallel runs.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Skip the paper's toy.
    #[arg(long)]
    pub no_toy: bool,
    /// Monte-Carlo samples per state for each KL estimate.
    #[arg(long, default_value_t = 20_000)]
    pub samples: usize,
    /// What to run instead of the library defaults, for comparisons: `toy` (VddConfig::toy and
    /// MoeConfig::toy with full-covariance experts, raw units), `uniform-gating`,
    /// `official-init`, `no-anneal`, `long` (2,400 iterations).
    #[arg(long, default_value = "default", value_parser = |s: &str| s.parse::<Variant>())]
    pub variant: Variant,
    /// Only these problem indices (comma-separated; 0-23 the random family, 100-104 the extra
    /// problems; for investigating one problem).
    #[arg(long, value_delimiter = ',')]
    pub only: Vec<usize>,
    /// These seeds (comma-separated) instead of 0 (`--quick`) or 0, 1, 2.
    #[arg(long, value_delimiter = ',')]
    pub seeds: Vec<u64>,
}

/// Runs the benchmark.
pub fn run(a: &Args) -> crate::XResult {
    let (quick, threads, no_toy, samples) = (a.quick, a.threads, a.no_toy, a.samples);
    let o = RobustnessOptions {
        quick,
        threads,
        no_toy,
        samples,
        variant: a.variant,
        only: a.only.clone(),
        seeds: a.seeds.clone(),
    };
    std::fs::create_dir_all(&a.out)?;
    let doc = robustness(&o, |line: String| crate::progress::log(line))?;
    std::fs::write(a.out.join("robustness.json"), serde_json::to_string_pretty(&doc)?)?;
    println!("{}", serde_json::to_string_pretty(&doc["summary"])?);
    Ok(())
}
