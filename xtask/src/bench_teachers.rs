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
//! Defaults (the toy teachers, [`ToyTeachers::toy`]): residual MLP 64 wide with 2 blocks, Adam
//! lr 1e-2 with 200 warm-up steps and a cosine decay to 2%, batch 1024, EMA 0.995, training
//! noise `ln σ ~ N(−1.6, 1.2²)` for both teachers, 4000 steps on the circle toy and 2000 on the
//! rotating toy. A whole run from scratch uses about 100 CPU-seconds (training runs the two
//! teachers on two threads); 2 to 4 minutes of wall clock on a busy 2-core machine.
//!
//! * Acceptance, 2-D toy (8 modes on a circle of radius 2, std 0.5, 5000 training pairs): for
//!   the DDPM and the BESO teacher, the share of 10,000 samples nearest to each mode (each must
//!   be ≥ 6%), MMD² (RBF, bandwidth 1) between 2,000 teacher samples and 2,000 fresh true
//!   samples against 3× the MMD² of two independent true sets, and the mean cosine similarity
//!   of the learned score at `σ = 0.1` (normalised units; DDPM: the matching `t`) with the
//!   exact smoothed score on true samples (≥ 0.9).
//! * Acceptance, rotating toy (mode k at angle `s + 2πk/8`, `s ~ U[0, 2π)`): both teachers,
//!   conditioned on the state, must put ≥ 6% of 2,000 samples on every mode at 8 states.
//! * Latency: µs per action of `act_batch` (single thread) at batch 1 and 256, for every
//!   sampler against 1, 2, 4, 8, 16 steps and the default.
//!
//! Trained teachers are cached under `--cache` (default `target/xtask-cache/teachers`) by the
//! recipes' teacher cache ([`crate::teachers::train_or_load`]: keyed by the cache version, the
//! model and training configuration, the seed and the training data); `--retrain` ignores the
//! cache. The command fails when a check fails.

use std::path::PathBuf;
use std::time::Instant;

use faer::Mat;
use vdd_core::Seeds;
use vdd_core::gmm::GmmTeacher;
use vdd_diffusion::acceptance::{
    CircleMeasures, CircleReference, RotatingReference, SamplerSetting, Thresholds, ToyTeachers,
    act_batch_latency_us, samples_at, score_cosine,
};
use vdd_diffusion::{DiffusionTeacher, TeacherKind};

use crate::teachers;

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

/// Everything that determines the toy teachers.
#[derive(Debug, Clone)]
struct Setup {
    seed: u64,
    steps: u64,
    rot_steps: u64,
    teachers: ToyTeachers,
}

/// Runs the command.
pub fn run(args: &Args) -> crate::XResult {
    let (noise_mean, noise_std) = (args.noise_mean, args.noise_std);
    let (width, blocks, lr, batch, ema) = (args.width, args.blocks, args.lr, args.batch, args.ema);
    let toy = ToyTeachers { width, blocks, lr, batch, ema, noise_mean, noise_std };
    let setup =
        Setup { seed: args.seed, steps: args.steps, rot_steps: args.rot_steps, teachers: toy };
    let (sigma, min_secs) = (args.sigma, args.min_secs);
    let cache = Cache { dir: args.cache.clone(), retrain: args.retrain };
    std::fs::create_dir_all(&cache.dir)?;
    let t0 = Instant::now();
    println!(
        "toy teachers: residual MLP {} wide, {} blocks; Adam lr {} (warm-up, cosine decay), \
         batch {}; {} training steps (circle), {} (rotating); seed {}",
        width, blocks, lr, batch, setup.steps, setup.rot_steps, setup.seed
    );
    println!(
        "DDPM: cosine β, N = 16, ε-prediction, log-normal training noise; BESO: EDM \
         preconditioning (σ_data 0.5), Karras σ ∈ [0.002, 80], ρ = 7, log-normal training noise"
    );
    let mut rng = Seeds::new(setup.seed).stream("toy-data");
    let (states, actions) = GmmTeacher::circle_toy_data(5000, &mut rng)?;
    let task = Task { name: "circle", steps: setup.steps, states: &states, actions: &actions };
    let mut circle = teachers(&task, &setup, &cache)?;
    let mut failures = Vec::new();
    if !args.no_acceptance {
        failures.extend(circle_acceptance(&mut circle, &setup, sigma)?);
        failures.extend(rotating_acceptance(&setup, &cache)?);
    }
    if !args.no_latency {
        latency_tables(&mut circle, min_secs)?;
    }
    println!("\nbench teachers finished in {:.1} s", t0.elapsed().as_secs_f64());
    if failures.is_empty() {
        if !args.no_acceptance {
            println!("acceptance: all checks pass");
        }
        Ok(())
    } else {
        for f in &failures {
            println!("FAILED: {f}");
        }
        Err(format!("{} acceptance check(s) failed", failures.len()).into())
    }
}

/// A toy task's training data and training length.
struct Task<'a> {
    name: &'a str,
    steps: u64,
    states: &'a Mat<f32>,
    actions: &'a Mat<f32>,
}

/// Where trained teachers are cached, and whether to ignore the cache.
struct Cache {
    dir: PathBuf,
    retrain: bool,
}

/// Trains a teacher of `kind` on `task`, or loads it from the cache (the recipes' teacher
/// cache, [`teachers::train_or_load`]); returns the training seconds (`None` when loaded).
fn train_or_load(
    kind: TeacherKind,
    task: &Task<'_>,
    setup: &Setup,
    cache: &Cache,
) -> crate::XResult<(DiffusionTeacher, Option<f64>)> {
    let t = teachers::train_or_load(
        kind,
        &setup.teachers.config(task.steps),
        task.states.as_ref(),
        task.actions.as_ref(),
        setup.seed,
        &cache.dir,
        cache.retrain,
        &format!("{} {}", teachers::kind_name(kind), task.name),
    )?;
    Ok((t.teacher, (!t.cached).then_some(t.train_seconds)))
}

/// Both teachers of one task, trained in parallel on two threads.
fn teachers(
    task: &Task<'_>,
    setup: &Setup,
    cache: &Cache,
) -> crate::XResult<[DiffusionTeacher; 2]> {
    let go = |kind| train_or_load(kind, task, setup, cache).map_err(|e| e.to_string());
    let (ddpm, beso) = std::thread::scope(|s| {
        let h = s.spawn(|| go(TeacherKind::Ddpm));
        let beso = go(TeacherKind::Beso);
        (h.join().unwrap_or_else(|_| Err("training thread panicked".into())), beso)
    });
    let (ddpm, beso) = (ddpm?, beso?);
    let secs = |s: Option<f64>| s.map_or("cached".to_owned(), |s| format!("{s:.1} s"));
    println!(
        "{}: {} training steps: DDPM {}, BESO {} (two threads in parallel)",
        task.name,
        task.steps,
        secs(ddpm.1),
        secs(beso.1)
    );
    Ok([ddpm.0, beso.0])
}

fn teacher_name(t: &DiffusionTeacher) -> &'static str {
    match t.kind() {
        TeacherKind::Ddpm => "DDPM",
        TeacherKind::Beso => "BESO",
    }
}

/// `n` teacher samples at raw state `s` with the teacher's policy stream seeded by `seed`.
fn sample_at(t: &mut DiffusionTeacher, s: f32, n: usize, seed: u64) -> crate::XResult<Mat<f32>> {
    Ok(samples_at(t, &[s], n, seed)?)
}

fn fmt_shares(shares: &[f32]) -> String {
    shares.iter().map(|s| format!("{:.3}", s)).collect::<Vec<_>>().join(" ")
}

fn pass(ok: bool) -> &'static str {
    if ok { "pass" } else { "FAIL" }
}

fn circle_acceptance(
    ts: &mut [DiffusionTeacher; 2],
    setup: &Setup,
    sigma: f32,
) -> crate::XResult<Vec<String>> {
    let seed = setup.seed;
    let thresholds = Thresholds::default();
    let reference = CircleReference::new(2000, seed)?;
    let (baseline, exact) = (reference.baseline, &reference.exact);
    let bar = thresholds.mmd2_bar(baseline);
    let mut failures = Vec::new();
    println!("\n== acceptance: 2-D toy (8 modes on a circle of radius 2, std 0.5; 5000 pairs) ==");
    println!(
        "MMD² (RBF, bandwidth 1), two independent true sets of 2000: {baseline:.5}; bar 3x = {bar:.5}"
    );
    println!(
        "{:<6} {:<18} {:>4} {:>10} {:>9} {:>8} {:>22} {:>6}",
        "",
        "sampler, steps",
        "NFE",
        "min share",
        "MMD²",
        "MMD²/true",
        "score cos (σ = 0.1)",
        "result"
    );
    for t in ts.iter_mut() {
        let name = teacher_name(t);
        let default = SamplerSetting::of(t);
        let CircleMeasures { measures, shares, level } =
            reference.measure(t, 10_000, sigma, seed)?;
        let (share, mmd, cos) = (measures.min_mode_share, measures.mmd2, measures.score_cosine);
        let at = match t.kind() {
            TeacherKind::Ddpm => format!("{cos:.4} (t = {level:.3})"),
            TeacherKind::Beso => format!("{cos:.4}"),
        };
        let failed = thresholds.check(&measures, sigma);
        println!(
            "{name:<6} {:<18} {:>4} {share:>10.3} {mmd:>9.5} {:>8.2}x {at:>22} {:>6}",
            default.label(),
            default.nfe(),
            mmd / baseline,
            pass(failed.is_empty())
        );
        failures.extend(failed.iter().map(|f| format!("{name}: {f}")));
        println!("       mode shares: {}", fmt_shares(&shares));
        let half = score_cosine(t, exact, &[0.0], reference.true_b.as_ref(), 0.5 * sigma)?.cosine;
        println!("       (info) score cosine at σ = {}: {half:.4}", 0.5 * sigma);
    }
    println!("(info) other samplers, 2000 samples each (not part of the acceptance):");
    println!(
        "{:<6} {:<18} {:>4} {:>10} {:>9} {:>9}",
        "", "sampler, steps", "NFE", "min share", "MMD²", "MMD²/true"
    );
    for t in ts.iter_mut() {
        let name = teacher_name(t);
        for steps in [16usize, 8, 1] {
            for s in SamplerSetting::all(t.kind(), steps) {
                let saved = s.apply(t)?;
                let x = sample_at(t, 0.0, 2000, seed);
                saved.apply(t)?;
                let x = x?;
                let (share, _, mmd) = reference.compare(x.as_ref());
                println!(
                    "{name:<6} {:<18} {:>4} {share:>10.3} {mmd:>9.5} {:>8.2}x",
                    s.label(),
                    s.nfe(),
                    mmd / baseline
                );
            }
        }
    }
    Ok(failures)
}

fn rotating_acceptance(setup: &Setup, cache: &Cache) -> crate::XResult<Vec<String>> {
    let seed = setup.seed;
    let n_rot = 20_000;
    let mut rot = RotatingReference::new()?;
    let (states, actions) = rot.data(n_rot, seed)?;
    println!(
        "\n== acceptance: rotating toy (mode k at angle s + 2πk/8, s ~ U[0, 2π); {n_rot} pairs) =="
    );
    let task =
        Task { name: "rotating", steps: setup.rot_steps, states: &states, actions: &actions };
    let mut ts = teachers(&task, setup, cache)?;
    println!("min share of 2000 samples over the 8 modes at state s (MMD² to 1000 true samples):");
    println!("{:>7} {:>22} {:>22}", "s", "DDPM", "BESO");
    let thresholds = Thresholds::default();
    let mut worst = [f32::INFINITY; 2];
    let mut covered = [0usize; 2];
    for i in 0..8 {
        let s = (i as f32 + 0.5) * std::f32::consts::TAU / 8.0 * 0.999;
        let mut cells = Vec::new();
        for (k, t) in ts.iter_mut().enumerate() {
            let (share, mmd) = rot.check_at(t, s, i, seed)?;
            worst[k] = worst[k].min(share);
            covered[k] += usize::from(thresholds.covers(share));
            cells.push(format!("{share:.3} ({mmd:.4})"));
        }
        println!("{s:>7.3} {:>22} {:>22}", cells[0], cells[1]);
    }
    let mut failures = Vec::new();
    for (k, name) in ["DDPM", "BESO"].iter().enumerate() {
        let ok = covered[k] == 8;
        println!(
            "{name}: all 8 modes (>= 6% each) at {}/8 states, worst share {:.3}: {}",
            covered[k],
            worst[k],
            pass(ok)
        );
        if !ok {
            failures.push(format!("{name} rotating: modes covered at {}/8 states", covered[k]));
        }
    }
    Ok(failures)
}

/// µs per action of `act_batch` at batch size `n` ([`act_batch_latency_us`]).
fn latency(t: &mut DiffusionTeacher, n: usize, min_secs: f64) -> crate::XResult<f64> {
    Ok(act_batch_latency_us(t, n, min_secs)?)
}

fn latency_tables(ts: &mut [DiffusionTeacher; 2], min_secs: f64) -> crate::XResult {
    println!(
        "\n== sampling latency: µs per action (act_batch, single thread, best of 5 rounds) =="
    );
    println!(
        "(2-D toy teachers; wall clock on a shared machine: other jobs inflate these figures)"
    );
    let steps = [1usize, 2, 4, 8, 16];
    for batch in [1usize, 256] {
        println!("\nbatch {batch}:");
        let head: String = steps.iter().map(|k| format!("{:>9}", format!("{k} st"))).collect();
        println!("{:<6} {:<16}{head} {:>16}", "", "sampler", "default");
        for t in ts.iter_mut() {
            let name = teacher_name(t);
            let default = SamplerSetting::of(t);
            for s in SamplerSetting::all(t.kind(), 1) {
                let mut row = String::new();
                for &k in &steps {
                    s.with_steps(k).apply(t)?;
                    row.push_str(&format!("{:>9.1}", latency(t, batch, min_secs)?));
                }
                let def = if s.name() == default.name() {
                    default.apply(t)?;
                    format!("{:.1} ({} st)", latency(t, batch, min_secs)?, default.steps())
                } else {
                    String::new()
                };
                println!("{name:<6} {:<16}{row} {def:>16}", s.name());
            }
            default.apply(t)?;
        }
    }
    Ok(())
}
