//! `cargo xtask bench teachers`: the acceptance checks of the learned diffusion teachers on the
//! paper's 2-D toys, and their sampling latency per action (our version of the paper's
//! inference-time table).
//!
//! ```text
//! cargo xtask bench teachers [--seed S] [--steps N] [--rot-steps N] [--width W] [--blocks B]
//!                            [--lr X] [--batch B] [--ema D] [--noise-mean M] [--noise-std S]
//!                            [--sigma X] [--min-secs T] [--cache DIR]
//!                            [--retrain] [--no-acceptance] [--no-latency]
//! ```
//!
//! Defaults: the accepted toy teachers ([`ToyTeachers::toy`]), 4000 training steps on the
//! circle toy and 2000 on the rotating toy; a whole run from scratch uses about 100
//! CPU-seconds (the two teachers train on two threads). The checks, their thresholds and the
//! latency tables are [`vdd_lab::bench::teachers::report`]'s.
//!
//! Trained teachers are cached under `--cache` (default `target/xtask-cache/teachers`) by the
//! recipes' teacher cache ([`vdd_lab::teachers::train_or_load`]: keyed by the cache version, the
//! model and training configuration, the seed and the training data); `--retrain` ignores the
//! cache. The command fails when a check fails.

use std::path::PathBuf;
use std::time::Instant;

use faer::Mat;
use vdd_diffusion::{DiffusionTeacher, TeacherKind};
use vdd_lab::bench::teachers::ToyTeachers;
use vdd_lab::bench::teachers::report::{self, BenchOptions};
use vdd_lab::teachers;

/// The command line of `bench teachers`.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// Seed of the data, the training and the checks.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Training steps on the circle toy.
    #[arg(long, default_value_t = 4000)]
    pub steps: u64,
    /// Training steps on the rotating toy.
    #[arg(long, default_value_t = 2000)]
    pub rot_steps: u64,
    /// Hidden width of the residual MLP.
    #[arg(long, default_value_t = TOY.width)]
    pub width: usize,
    /// Residual blocks.
    #[arg(long, default_value_t = TOY.blocks)]
    pub blocks: usize,
    /// Adam learning rate.
    #[arg(long, default_value_t = TOY.lr)]
    pub lr: f32,
    /// Batch size.
    #[arg(long, default_value_t = TOY.batch)]
    pub batch: usize,
    /// EMA decay of the weights.
    #[arg(long, default_value_t = TOY.ema)]
    pub ema: f32,
    /// Training noise: mean of ln σ.
    #[arg(long, default_value_t = TOY.noise_mean, allow_negative_numbers = true)]
    pub noise_mean: f32,
    /// Training noise: std of ln σ.
    #[arg(long, default_value_t = TOY.noise_std)]
    pub noise_std: f32,
    /// Noise level of the score check (normalised units).
    #[arg(long, default_value_t = 0.1)]
    pub sigma: f32,
    /// Minimum seconds per latency measurement.
    #[arg(long, default_value_t = 0.3)]
    pub min_secs: f64,
    /// Cache directory of the trained teachers.
    #[arg(long, value_name = "DIR", default_value = "target/xtask-cache/teachers")]
    pub cache: PathBuf,
    /// Retrain even when cached.
    #[arg(long)]
    pub retrain: bool,
    /// Skip the acceptance checks.
    #[arg(long)]
    pub no_acceptance: bool,
    /// Skip the latency tables.
    #[arg(long)]
    pub no_latency: bool,
}

/// The defaults of the command line: the accepted toy teachers.
const TOY: ToyTeachers = ToyTeachers::toy();

/// Runs the command: trains (or loads) the teachers and prints [`report::run`]'s sections.
pub fn run(args: &Args) -> crate::XResult {
    let (noise_mean, noise_std) = (args.noise_mean, args.noise_std);
    let (width, blocks, lr, batch, ema) = (args.width, args.blocks, args.lr, args.batch, args.ema);
    let toy = ToyTeachers { width, blocks, lr, batch, ema, noise_mean, noise_std };
    std::fs::create_dir_all(&args.cache)?;
    let t0 = Instant::now();
    let (seed, steps, rot_steps, sigma, min_secs) =
        (args.seed, args.steps, args.rot_steps, args.sigma, args.min_secs);
    let (acceptance, latency) = (!args.no_acceptance, !args.no_latency);
    let options =
        BenchOptions { seed, steps, rot_steps, sigma, min_secs, acceptance, latency, toy };
    let train =
        |task: &str, steps, s: &Mat<f32>, a: &Mat<f32>| teachers(args, &toy, task, steps, s, a);
    let failures = report::run(&options, train, |text| print!("{text}"))?;
    println!("\nbench teachers finished in {:.1} s", t0.elapsed().as_secs_f64());
    if failures.is_empty() {
        if acceptance {
            println!("acceptance: all checks pass");
        }
        return Ok(());
    }
    failures.iter().for_each(|f| println!("FAILED: {f}"));
    Err(format!("{} acceptance check(s) failed", failures.len()).into())
}

/// Both teachers of one task, trained in parallel on two threads
/// ([`vdd_core::parallel::parallel_map`]) or loaded from the cache (the
/// recipes' teacher cache, [`teachers::train_or_load`]).
fn teachers(
    args: &Args,
    toy: &ToyTeachers,
    task: &str,
    steps: u64,
    states: &Mat<f32>,
    actions: &Mat<f32>,
) -> crate::XResult<[DiffusionTeacher; 2]> {
    let config = toy.config(steps);
    let go = |kind| {
        let label = format!("{} {task}", teachers::kind_name(kind));
        let (s, a) = (states.as_ref(), actions.as_ref());
        teachers::train_or_load(kind, &config, s, a, args.seed, &args.cache, args.retrain, &label)
            .map_err(|e| e.to_string())
    };
    let kinds = [TeacherKind::Ddpm, TeacherKind::Beso];
    let [ddpm, beso]: [teachers::TrainedTeacher; 2] =
        vdd_core::parallel::parallel_map(&kinds, 2, |&kind| go(kind))?
            .try_into()
            .map_err(|_| "internal: two teachers expected")?;
    let secs = |t: &teachers::TrainedTeacher| {
        if t.cached { "cached".to_owned() } else { format!("{:.1} s", t.train_seconds) }
    };
    println!(
        "{task}: {steps} training steps: DDPM {}, BESO {} (two threads in parallel)",
        secs(&ddpm),
        secs(&beso)
    );
    Ok([ddpm.teacher, beso.teacher])
}
