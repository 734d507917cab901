//! Consistency Distillation and the Consistency Trajectory Model on the paper's 2-D toy
//! (8 modes on a circle of radius 2, std 0.5, 5000 samples, one constant state), each with
//! its one default configuration (`CdConfig::for_teacher`, `CtmConfig::for_teacher`; nothing
//! tuned per seed), distilled from two teachers (`--teacher beso|exact|both`, default both):
//!
//! * `beso`: a BESO / EDM teacher trained on the 5000 points first (residual MLP 128 wide,
//!   2 blocks, EDM log-normal σ, Adam 1e-2, 8000 steps); the students start from its weights.
//!   A DDPM teacher with the same network and training (cosine β, N = 16, ancestral sampling)
//!   is evaluated too, with its 16 steps and as DDPM-1 (one step), like BESO-1;
//! * `exact`: the exact denoiser of the mixture (Tweedie's formula on
//!   `vdd_diffusion::GmmTeacher`'s closed-form score) in the same normalised space, so the
//!   teacher ODE is the true one; the students (same architecture) start from scratch.
//!
//! Metrics against the exact density (the same as `toy_em_imc`, which has exact student
//! densities; these samplers have none):
//!
//! * reverse KL `E_q[ln q − ln p]` = `−H(q) − E_q[ln p]` and forward KL `E_p[ln p − ln q]`, with
//!   the exact `ln p` and k-nearest-neighbour estimates (k = 5) of the student's entropy and of
//!   the cross-entropy `−E_p[ln q]` from 10,000 student and 10,000 true samples. The row "true
//!   samples" runs the estimators on fresh true samples: its figures (≈ 0) are the
//!   estimators' noise floor;
//! * modes covered: a mode is covered when at least 1/16 of the samples (half its share) are
//!   nearest to it; the nearest-mode histogram's entropy in base 8 (1 = uniform);
//! * spread: mean distance to the nearest mode (true samples ≈ 0.63; smaller = sharper than
//!   the data, lost within-mode diversity);
//! * µs per action (`Policy::act_into`, one observation at a time) and training seconds.
//!
//! ```sh
//! cargo run --release -p vdd-consistency --example toy_cd_ctm -- [--seed N] [--teacher beso|exact|both]
//! ```

use std::time::Instant;

use faer::{Mat, MatRef};
use vdd_consistency::{
    CdConfig, CdTrainer, ConsistencyProgress, ConsistencyTeacher, CtmConfig, CtmTrainer,
    ScoreTeacher,
};
use vdd_core::{Affine, Policy, Seeds};
use vdd_diffusion::{
    Beso, BesoConfig, Ddpm, DdpmConfig, Gmm, GmmTeacher, KarrasSampler, NetConfig, NormalizerKind,
    SamplerBuffers, SigmaDistribution, TimeSampling, TrainConfig, TrainProgress, fit_normalizer,
};
use vdd_nn::AdamConfig;

mod toy_common;
use toy_common::{
    DATA_POINTS, MODES, RADIUS, STD, arg, knn_kl, mean_nearest_mode_distance, mode, mode_histogram,
    sample_target,
};

const EVAL_SAMPLES: usize = 10_000;
const TIMED_ACTIONS: usize = 2000;

struct Row {
    name: String,
    reverse_kl: f64,
    forward_kl: f64,
    covered: usize,
    entropy: f64,
    spread: f64,
    us_per_action: Option<f64>,
    train_secs: Option<f64>,
}

fn row(name: &str, samples: MatRef<'_, f32>, truth: MatRef<'_, f32>) -> Row {
    let (reverse_kl, forward_kl) = knn_kl(samples, truth);
    let hist = mode_histogram(samples);
    Row {
        name: name.into(),
        reverse_kl,
        forward_kl,
        covered: hist.iter().filter(|&&p| p >= 1.0 / (2 * MODES) as f64).count(),
        entropy: -hist.iter().filter(|&&p| p > 0.0).map(|p| p * p.ln()).sum::<f64>()
            / (MODES as f64).ln(),
        spread: mean_nearest_mode_distance(samples),
        us_per_action: None,
        train_secs: None,
    }
}

fn evaluate(
    name: &str,
    policy: &mut dyn Policy,
    truth: MatRef<'_, f32>,
    seed: u64,
    train_secs: Option<f64>,
) -> Result<Row, Box<dyn std::error::Error>> {
    policy.seed(seed);
    let obs = Mat::<f32>::zeros(EVAL_SAMPLES, 1);
    let mut samples = Mat::zeros(EVAL_SAMPLES, 2);
    policy.act_batch(obs.as_ref(), samples.as_mut())?;
    let mut a = [0.0f32; 2];
    let start = Instant::now();
    for _ in 0..TIMED_ACTIONS {
        policy.act_into(&[0.0], &mut a)?;
    }
    let us = start.elapsed().as_secs_f64() * 1e6 / TIMED_ACTIONS as f64;
    Ok(Row { us_per_action: Some(us), train_secs, ..row(name, samples.as_ref(), truth) })
}

/// The exact teacher in the space normalised by `(sn, an)`: the mixture with means
/// `(μ − offset) / scale` and covariances `diag(std² / scale²)`, seen through Tweedie's formula.
fn exact_teacher(
    sn: Affine,
    an: Affine,
) -> Result<ScoreTeacher<GmmTeacher>, Box<dyn std::error::Error>> {
    let means: Vec<Vec<f32>> = (0..MODES)
        .map(|k| (0..2).map(|j| (mode(k)[j] - an.offset[j]) / an.scale[j]).collect())
        .collect();
    let (v0, v1) = ((STD / an.scale[0]).powi(2), (STD / an.scale[1]).powi(2));
    let cov = vec![vec![v0, 0.0, 0.0, v1]; MODES];
    let gmm = Gmm::new(&[1.0; MODES], &means, &cov)?;
    Ok(ScoreTeacher::new(GmmTeacher::fixed(gmm, 1), sn, an)?)
}

/// Samples of the exact teacher's own probability-flow ODE (Heun, 24 Karras steps), raw.
fn exact_ode_samples(
    teacher: &mut ScoreTeacher<GmmTeacher>,
    config: &CdConfig,
    seed: u64,
) -> Result<Mat<f32>, Box<dyn std::error::Error>> {
    let n = EVAL_SAMPLES;
    let mut rng = Seeds::new(seed).stream("exact-ode");
    let mut x = Mat::from_fn(n, 2, |_, _| config.sigma_max * vdd_core::standard_normal(&mut rng));
    let sigmas = vdd_diffusion::karras_sigmas(24, config.sigma_min, config.sigma_max, config.rho)?;
    let states = Mat::<f32>::zeros(n, 1);
    let mut denoise = |x: MatRef<'_, f32>, s: &[f32], out: faer::MatMut<'_, f32>| {
        teacher.denoise(x, s, states.as_ref(), out).map_err(vdd_diffusion::DiffusionError::from)
    };
    let mut buf = SamplerBuffers::default();
    vdd_diffusion::sample_karras(
        &mut denoise,
        KarrasSampler::Heun,
        &sigmas,
        x.as_mut(),
        &mut rng,
        &mut buf,
    )?;
    let (_, an) = teacher.normalizers();
    Ok(Mat::from_fn(n, 2, |i, j| x[(i, j)] * an.scale[j] + an.offset[j]))
}

/// Runs `train` (a teacher's training, given a progress callback), printing its name, steps
/// and progress; returns the teacher and the training seconds.
fn train_teacher<T>(
    name: &str,
    steps: u64,
    train: impl FnOnce(&mut dyn FnMut(TrainProgress)) -> vdd_diffusion::Result<T>,
) -> Result<(T, f64), Box<dyn std::error::Error>> {
    println!("training the {name} teacher ({steps} steps)...");
    let start = Instant::now();
    let teacher = train(&mut |p| {
        println!("  teacher step {:>5}/{}: loss {:.4}", p.step, p.total_steps, p.loss)
    })?;
    Ok((teacher, start.elapsed().as_secs_f64()))
}

fn log(label: &'static str) -> impl FnMut(&ConsistencyProgress) {
    move |p| {
        println!(
            "  {label} step {:>5}/{}: loss {:.5} (consistency {:.5}, dsm {:.4}) lr {:.1e} {:.1}s",
            p.step, p.total_steps, p.loss, p.consistency_loss, p.dsm_loss, p.lr, p.elapsed_secs
        )
    }
}

/// Trains CD and CTM students of `teacher` with their default configurations; rows for one and
/// two sampling steps each.
fn distil<T: ConsistencyTeacher>(
    teacher: &mut T,
    states: MatRef<'_, f32>,
    actions: MatRef<'_, f32>,
    truth: MatRef<'_, f32>,
    seed: u64,
) -> Result<Vec<Row>, Box<dyn std::error::Error>> {
    let mut rows = Vec::new();
    let cd = CdConfig::for_teacher(teacher).with_seed(seed);
    println!(
        "CD ({} steps, from the teacher's weights: {})...",
        cd.train.steps, cd.init_from_teacher
    );
    let start = Instant::now();
    let mut model = CdTrainer::new(cd, &mut *teacher, states, actions)?.train(&mut log("CD"))?;
    let secs = start.elapsed().as_secs_f64();
    rows.push(evaluate("CD-1", &mut model, truth, seed, Some(secs))?);
    model.set_sampling_steps(2)?;
    rows.push(evaluate("CD-2", &mut model, truth, seed, None)?);

    let ctm = CtmConfig::for_teacher(teacher).with_seed(seed);
    println!("CTM ({} steps)...", ctm.base.train.steps);
    let start = Instant::now();
    let mut model = CtmTrainer::new(ctm, &mut *teacher, states, actions)?.train(&mut log("CTM"))?;
    let secs = start.elapsed().as_secs_f64();
    rows.push(evaluate("CTM-1", &mut model, truth, seed, Some(secs))?);
    model.set_sampling_steps(2)?;
    rows.push(evaluate("CTM-2", &mut model, truth, seed, None)?);
    Ok(rows)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let seed: u64 = arg(&args, "--seed", 0);
    let which: String = arg(&args, "--teacher", String::from("both"));
    let teacher_steps: u64 = arg(&args, "--teacher-steps", 8000);
    if !matches!(which.as_str(), "beso" | "exact" | "both") {
        return Err(format!("--teacher must be beso, exact or both, got {which}").into());
    }

    let seeds = Seeds::new(seed);
    let actions = sample_target(DATA_POINTS, &mut seeds.stream("toy-data"));
    let states = Mat::<f32>::zeros(DATA_POINTS, 1);
    let truth = sample_target(EVAL_SAMPLES, &mut seeds.stream("truth"));
    let true_row = row(
        "true samples",
        sample_target(EVAL_SAMPLES, &mut seeds.stream("truth-2")).as_ref(),
        truth.as_ref(),
    );
    let mut tables: Vec<(String, Vec<Row>)> = Vec::new();

    if which != "exact" {
        let beso_config = BesoConfig {
            net: NetConfig { hidden_dim: 128, num_blocks: 2, ..Default::default() },
            training_sigma: SigmaDistribution::LogNormal { mean: -1.2, std: 1.2 },
            sampler: KarrasSampler::Heun,
            sampling_steps: 24,
            ..Default::default()
        };
        let teacher_train = TrainConfig {
            steps: teacher_steps,
            batch_size: 256,
            adam: AdamConfig { lr: 1e-2, ..Default::default() },
            warmup_steps: 200,
            final_lr_factor: 0.02,
            ema_decay: 0.999,
            grad_clip: Some(1.0),
            log_every: teacher_steps.div_ceil(4),
            chunks: 1,
        };
        let (mut beso, secs) = train_teacher("BESO", teacher_steps, |progress| {
            Beso::train(
                &beso_config,
                &teacher_train,
                states.as_ref(),
                actions.as_ref(),
                seed,
                progress,
            )
        })?;
        let mut rows =
            vec![evaluate("BESO (Heun 24)", &mut beso, truth.as_ref(), seed, Some(secs))?];
        beso.set_sampler(KarrasSampler::Euler, 1)?;
        rows.push(evaluate("BESO-1", &mut beso, truth.as_ref(), seed, None)?);
        beso.set_sampler(KarrasSampler::Heun, 24)?;
        rows.extend(distil(&mut beso, states.as_ref(), actions.as_ref(), truth.as_ref(), seed)?);

        // The DDPM teacher (library defaults: cosine β, N = 16, ancestral sampling) with the
        // same network and training, and its one-step version DDPM-1.
        let ddpm_config = DdpmConfig {
            net: beso_config.net.clone(),
            time_sampling: TimeSampling::LogNormal { mean: -1.2, std: 1.2 },
            ..Default::default()
        };
        let (mut ddpm, secs) = train_teacher("DDPM", teacher_steps, |progress| {
            Ddpm::train(
                &ddpm_config,
                &teacher_train,
                states.as_ref(),
                actions.as_ref(),
                seed,
                progress,
            )
        })?;
        let (sampler, steps) = ddpm.sampler();
        rows.push(evaluate(
            &format!("DDPM ({steps} steps)"),
            &mut ddpm,
            truth.as_ref(),
            seed,
            Some(secs),
        )?);
        ddpm.set_sampler(sampler, 1)?;
        rows.push(evaluate("DDPM-1", &mut ddpm, truth.as_ref(), seed, None)?);
        tables.push((
            "learned BESO teacher (students start from its weights) and DDPM teacher".into(),
            rows,
        ));
    }

    if which != "beso" {
        // The normalisers a BESO teacher fits (per-dimension standardisation).
        let sn = fit_normalizer(states.as_ref(), NormalizerKind::Standard);
        let an = fit_normalizer(actions.as_ref(), NormalizerKind::Standard);
        let mut teacher = exact_teacher(sn, an)?;
        let levels = CdConfig::for_teacher(&teacher);
        let ode = exact_ode_samples(&mut teacher, &levels, seed)?;
        let mut rows = vec![row("exact ODE (Heun 24)", ode.as_ref(), truth.as_ref())];
        rows.extend(distil(&mut teacher, states.as_ref(), actions.as_ref(), truth.as_ref(), seed)?);
        tables.push(("exact GMM denoiser as the teacher ODE (students from scratch)".into(), rows));
    }

    println!(
        "\ntoy-gmm (8 modes, radius {RADIUS}, std {STD}, {DATA_POINTS} points), seed {seed}; \
         {EVAL_SAMPLES} samples per row, k-NN (k = 5) KL estimates"
    );
    for (title, rows) in &tables {
        println!("\n{title}:");
        println!(
            "method               rev KL  fwd KL  modes  mode entropy  spread  µs/action  train s"
        );
        for r in std::iter::once(&true_row).chain(rows.iter()) {
            let opt = |v: Option<f64>, p: usize| v.map_or("-".to_string(), |v| format!("{v:.p$}"));
            println!(
                "{:<19} {:>7.3} {:>7.3}  {:>2}/{MODES}  {:>12.3}  {:>6.3}  {:>9}  {:>7}",
                r.name,
                r.reverse_kl,
                r.forward_kl,
                r.covered,
                r.entropy,
                r.spread,
                opt(r.us_per_action, 1),
                opt(r.train_secs, 1),
            );
        }
    }
    Ok(())
}
