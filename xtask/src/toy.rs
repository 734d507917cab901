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

/// Per-state results of the rotating-modes toy.
#[derive(Debug, Serialize)]
struct StateResult {
    state: f32,
    modes_covered: usize,
    reverse_kl: f64,
    forward_kl: f64,
}

/// Everything `metrics.json` of `toy-conditional` records.
#[derive(Debug, Serialize)]
struct ConditionalMetrics {
    task: &'static str,
    seed: u64,
    modes: usize,
    states_fully_covered: usize,
    states: Vec<StateResult>,
    mean_reverse_kl: f64,
    mean_forward_kl: f64,
    ms_per_iter: f64,
    train_seconds: f64,
    config: VddConfig,
    student: MoeConfig,
}

/// `cargo xtask experiment toy-conditional [--seed N] [--out DIR] [--iterations N]`: the
/// rotating-modes toy (mode `k` at angle `s + 2πk/K`) distilled from its exact teacher with a
/// learned gating trained on dataset actions; coverage and KL at 8 evaluation states.
pub fn run_conditional(args: &[String]) -> crate::XResult {
    use vdd_moe::GatingKind;
    let opts = Opts::parse(args, &[])?;
    opts.only(&["seed", "out", "iterations", "experts", "lr", "weighting"])?;
    let seed: u64 = opts.get("seed", 0)?;
    let out: PathBuf =
        opts.get("out", PathBuf::from(format!("results/toy-conditional/seed{seed}")))?;
    let task = vdd_tasks::toy::CircleGmm::toy_conditional();
    let k = task.n_modes();
    let mut config = VddConfig::toy();
    config.seed = seed;
    config.iterations = opts.get("iterations", 3000)?;
    config.expert_optimizer.lr = opts.get("lr", 1e-2)?;
    config.gating_optimizer.lr = config.expert_optimizer.lr;
    config.expert_weighting = match opts.get("weighting", "gating".to_owned())?.as_str() {
        "gating" => vdd::ExpertWeighting::Gating,
        "uniform" => vdd::ExpertWeighting::Uniform,
        other => return Err(format!("unknown weighting `{other}` (gating|uniform)").into()),
    };
    let it = config.iterations as u64;
    config.expert_lr_schedule =
        vdd_nn::LrSchedule::LinearDecay { total_steps: it, final_factor: 0.0 };
    config.gating_lr_schedule = config.expert_lr_schedule.clone();
    // Twice as many experts as modes: with exactly K, reverse-KL training can leave an expert
    // switching modes part-way around the circle (measured: 4-7 of 8 states covered).
    let experts = opts.get("experts", 2 * k)?;
    let student_config = MoeConfig { gating: GatingKind::Learned, ..MoeConfig::toy(1, 2, experts) };

    let (states, actions) = task.sample(DATA_POINTS, seed)?;
    let data = DistillData::new(states, Some(actions))?;
    let student = Moe::from_config(student_config.clone(), seed)?;
    let mut vdd = Vdd::new(config.clone(), task.teacher()?, student, data)?;
    let bar = crate::progress::bar(it, "VDD");
    let start = Instant::now();
    vdd.train(|m| {
        bar.inc(1);
        if m.iteration % 50 == 0 {
            bar.set_message(format!("gating H {:.3}", m.gating_entropy));
        }
    })?;
    let train_seconds = start.elapsed().as_secs_f64();
    bar.finish_and_clear();

    let mut student = vdd.into_student();
    let seeds = Seeds::new(seed).child("toy-eval");
    let n_eval = 20_000;
    let mut results = Vec::new();
    for i in 0..8 {
        let s = (i as f32 + 0.5) * std::f32::consts::TAU / 8.0;
        let truth = Gmm::circle(k, 2.0, 0.5, s)?;
        let log_p = |a: &[f32]| truth.log_density(a, 0.0).unwrap_or(f32::NEG_INFINITY);
        let reverse_kl = eval::reverse_kl(
            &mut student,
            &[s],
            log_p,
            n_eval,
            &mut seeds.stream_indexed("reverse", i),
        )?;
        let mut rng = seeds.stream_indexed("forward", i);
        let mut target = Mat::zeros(n_eval, 2);
        let mut a = [0.0f32; 2];
        for r in 0..n_eval {
            truth.sample_into(&mut rng, &mut a);
            target[(r, 0)] = a[0];
            target[(r, 1)] = a[1];
        }
        let forward_kl = eval::forward_kl(&mut student, &[s], log_p, target.as_ref())?;
        let modes: Vec<Vec<f32>> = (0..k).map(|m| truth.mean(m).to_vec()).collect();
        let modes_covered = eval::modes_covered(&mut student, &[s], &modes, 0.3, 0.01)?;
        results.push(StateResult { state: s, modes_covered, reverse_kl, forward_kl });
    }
    let n = results.len() as f64;
    let metrics = ConditionalMetrics {
        task: "toy-conditional",
        seed,
        modes: k,
        states_fully_covered: results.iter().filter(|r| r.modes_covered == k).count(),
        mean_reverse_kl: results.iter().map(|r| r.reverse_kl).sum::<f64>() / n,
        mean_forward_kl: results.iter().map(|r| r.forward_kl).sum::<f64>() / n,
        states: results,
        ms_per_iter: train_seconds * 1e3 / config.iterations as f64,
        train_seconds,
        config,
        student: student_config,
    };
    std::fs::create_dir_all(&out)?;
    let path = out.join("metrics.json");
    vdd_nn::io::write_atomic(&path, serde_json::to_string_pretty(&metrics)?.as_bytes())?;
    for r in &metrics.states {
        println!(
            "  s = {:.3}: modes {}/{k}, reverse KL {:.4}, forward KL {:.4}",
            r.state, r.modes_covered, r.reverse_kl, r.forward_kl
        );
    }
    println!(
        "toy-conditional seed={seed}: all {k} modes covered at {}/8 states, mean reverse KL {:.4}, \
         mean forward KL {:.4} nats, {:.2} s",
        metrics.states_fully_covered, metrics.mean_reverse_kl, metrics.mean_forward_kl, train_seconds
    );
    println!("wrote {}", path.display());
    Ok(())
}
