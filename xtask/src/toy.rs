//! `cargo xtask experiment toy-gmm`: the paper's 2-D toy. VDD distils a teacher of the 8-mode
//! circle mixture (exact score, or a learned DDPM / BESO teacher) into 8 diagonal experts, then
//! measures reverse/forward KL against the exact density by Monte Carlo, modes covered and
//! training speed, and writes `DIR/metrics.json`.

use std::path::PathBuf;
use std::time::Instant;

use faer::Mat;
use serde::Serialize;
use vdd::{eval, DistillData, Vdd, VddConfig};
use vdd_core::{ScoreModel, Seeds};
use vdd_diffusion::{Gmm, GmmTeacher};
use vdd_moe::{Moe, MoeConfig};

use crate::cli::Opts;

/// Monte-Carlo sample count for each KL estimate.
const KL_SAMPLES: usize = 100_000;
/// Number of data states (the toy has one fixed state; the paper uses 5000 data points).
const DATA_POINTS: usize = 5000;

/// Everything `metrics.json` records.
#[derive(Debug, Serialize)]
struct Metrics {
    task: &'static str,
    teacher: String,
    seed: u64,
    reverse_kl: f64,
    forward_kl: f64,
    modes_covered: usize,
    modes_total: usize,
    ms_per_iter: f64,
    train_seconds: f64,
    iterations: usize,
    config: VddConfig,
    student: MoeConfig,
}

/// Runs the command.
pub fn run(args: &[String]) -> crate::XResult {
    let opts = Opts::parse(args, &[])?;
    opts.only(&["teacher", "seed", "out", "iterations"])?;
    let teacher_kind: String = opts.get("teacher", "exact".to_owned())?;
    let seed: u64 = opts.get("seed", 0)?;
    let out: PathBuf =
        opts.get("out", PathBuf::from(format!("results/toy-gmm/{teacher_kind}-seed{seed}")))?;
    let mut config = VddConfig::toy();
    config.seed = seed;
    config.iterations = opts.get("iterations", config.iterations)?;
    let it = config.iterations as u64;
    config.expert_lr_schedule =
        vdd_nn::LrSchedule::LinearDecay { total_steps: it, final_factor: 0.0 };
    config.gating_lr_schedule = config.expert_lr_schedule.clone();

    let truth = Gmm::circle(8, 2.0, 0.5, 0.0)?;
    let metrics = match teacher_kind.as_str() {
        "exact" => distil(GmmTeacher::circle_toy(), &truth, config, seed, "exact")?,
        "ddpm" | "beso" => {
            return Err(
                format!("the learned `{teacher_kind}` toy teacher is not wired in yet").into()
            )
        }
        other => return Err(format!("unknown teacher `{other}` (exact|ddpm|beso)").into()),
    };
    std::fs::create_dir_all(&out)?;
    let path = out.join("metrics.json");
    vdd_nn::io::write_atomic(&path, serde_json::to_string_pretty(&metrics)?.as_bytes())?;
    println!(
        "toy-gmm teacher={} seed={}: reverse KL {:.5} nats, forward KL {:.5} nats, modes {}/{}, \
         {:.3} ms/iter ({:.2} s)",
        metrics.teacher,
        seed,
        metrics.reverse_kl,
        metrics.forward_kl,
        metrics.modes_covered,
        metrics.modes_total,
        metrics.ms_per_iter,
        metrics.train_seconds
    );
    println!("wrote {}", path.display());
    Ok(())
}

fn distil<S: ScoreModel>(
    teacher: S,
    truth: &Gmm,
    config: VddConfig,
    seed: u64,
    name: &str,
) -> crate::XResult<Metrics> {
    let student_config = MoeConfig::toy(1, 2, 8);
    let student = Moe::from_config(student_config.clone(), seed)?;
    let data = DistillData::from_states(Mat::zeros(DATA_POINTS, 1))?;
    let iterations = config.iterations;
    let mut vdd = Vdd::new(config.clone(), teacher, student, data)?;
    let bar = crate::progress::bar(iterations as u64, "VDD");
    let start = Instant::now();
    vdd.train(|m| {
        bar.inc(1);
        if m.iteration % 50 == 0 {
            bar.set_message(format!("|g| {:.3}", m.expert.corrected_score_rms));
        }
    })?;
    let train_seconds = start.elapsed().as_secs_f64();
    bar.finish_and_clear();

    let mut student = vdd.into_student();
    let seeds = Seeds::new(seed).child("toy-eval");
    let log_p = |a: &[f32]| truth.log_density(a, 0.0).unwrap_or(f32::NEG_INFINITY);
    let reverse_kl =
        eval::reverse_kl(&mut student, &[0.0], log_p, KL_SAMPLES, &mut seeds.stream("reverse"))?;
    let mut target = Mat::zeros(KL_SAMPLES, 2);
    let mut rng = seeds.stream("forward");
    let mut a = [0.0f32; 2];
    for i in 0..KL_SAMPLES {
        truth.sample_into(&mut rng, &mut a);
        target[(i, 0)] = a[0];
        target[(i, 1)] = a[1];
    }
    let forward_kl = eval::forward_kl(&mut student, &[0.0], log_p, target.as_ref())?;
    let modes: Vec<Vec<f32>> = (0..8).map(|k| truth.mean(k).to_vec()).collect();
    let modes_covered = eval::modes_covered(&mut student, &[0.0], &modes, 0.3, 0.01)?;
    Ok(Metrics {
        task: "toy-gmm",
        teacher: name.to_owned(),
        seed,
        reverse_kl,
        forward_kl,
        modes_covered,
        modes_total: 8,
        ms_per_iter: train_seconds * 1e3 / iterations as f64,
        train_seconds,
        iterations,
        config,
        student: student_config,
    })
}
