//! Consistency Distillation and the Consistency Trajectory Model on the paper's 2-D toy:
//! 8 modes on a circle of radius 2, isotropic std 0.5, equal weights, 5000 samples, one constant
//! state `s = 0` (1-D).
//!
//! Teachers (`--teacher beso|exact|both`, default both):
//!
//! * `beso`: a BESO / EDM teacher trained on the 5000 points (the xtask toy recipe's network and
//!   training: residual MLP 128 wide, 2 blocks, Adam 1e-2, 8000 steps), distilled by CD and CTM
//!   students that start from its weights;
//! * `exact`: the exact denoiser of the mixture, `D(x; σ) = E[a | a + σ z = x]`, in the same
//!   normalised space, distilled by students of the same architecture trained from scratch.
//!
//! For each teacher it reports, for the teacher's own sampler (Heun, 24 steps), its one-step
//! version (BESO-1, learned teacher only), CD and CTM with one and two steps:
//!
//! * modes covered: nearest-mode histogram of 10,000 samples, a mode covered at ≥ 6% (uniform
//!   is 12.5%), and the histogram's entropy in base 8 (1 = uniform over the modes);
//! * mean distance to the nearest mode (true samples: ≈ 0.63) — smaller means the samples are
//!   sharper than the data, i.e. lost within-mode diversity;
//! * MMD² (RBF, bandwidth 1) of 2000 samples against 2000 true samples (the row "true" is two
//!   independent true samples, the noise floor);
//! * µs per action (`Policy::act_into`, one observation at a time, 2000 calls).
//!
//! ```sh
//! cargo run --release -p vdd-baselines --example toy_cd_ctm -- [--seed N] [--teacher beso|exact|both]
//!     [--teacher-steps N] [--cd-steps N] [--ctm-steps N]
//! ```

use std::time::Instant;

use faer::{Mat, MatRef};
use rand::Rng as _;
use vdd_baselines::consistency::{ConsistencyTeacher, DenoiserFn};
use vdd_baselines::{CdConfig, CdTrainer, ConsistencyProgress, CtmConfig, CtmTrainer};
use vdd_core::{Affine, Policy, Rng, Seeds};
use vdd_diffusion::metrics::{mmd2_rbf, nearest_mode_counts};
use vdd_diffusion::{
    Beso, BesoConfig, KarrasSampler, NetConfig, NormalizerKind, SigmaDistribution, TrainConfig,
    fit_normalizer,
};
use vdd_nn::AdamConfig;

const MODES: usize = 8;
const RADIUS: f32 = 2.0;
const STD: f32 = 0.5;
const DATA_POINTS: usize = 5000;
const EVAL_SAMPLES: usize = 10_000;
const MMD_SAMPLES: usize = 2000;
const TIMED_ACTIONS: usize = 2000;

fn mode(k: usize) -> [f32; 2] {
    let t = std::f32::consts::TAU * k as f32 / MODES as f32;
    [RADIUS * t.cos(), RADIUS * t.sin()]
}

fn sample_target(n: usize, rng: &mut Rng) -> Mat<f32> {
    let mut out = Mat::zeros(n, 2);
    for i in 0..n {
        let m = mode(rng.random_range(0..MODES));
        for j in 0..2 {
            out[(i, j)] = m[j] + STD * vdd_core::standard_normal(rng);
        }
    }
    out
}

/// The exact denoiser of the mixture in the space normalised by `norm` (per-dimension affine):
/// in raw units the noise of normalised level `σ` has std `σ scale_j` in dimension `j`, so with
/// `v_j = s² + σ² scale_j²`, responsibilities `w_k ∝ exp(−Σ_j (x_j − μ_kj)² / 2v_j)` and
/// `D_j = (s²/v_j) x_j + (σ² scale_j² / v_j) Σ_k w_k μ_kj` (raw), normalised back.
fn exact_teacher(state_norm: Affine, action_norm: Affine) -> impl ConsistencyTeacher {
    let (off, sc) = (action_norm.offset.clone(), action_norm.scale.clone());
    let means: Vec<[f32; 2]> = (0..MODES).map(mode).collect();
    DenoiserFn::new(state_norm, action_norm, move |x, sigma, _states, mut out| {
        let s2 = STD * STD;
        let mut logits = [0.0f32; MODES];
        for i in 0..x.nrows() {
            let raw = [x[(i, 0)] * sc[0] + off[0], x[(i, 1)] * sc[1] + off[1]];
            let noise = [sigma[i] * sc[0], sigma[i] * sc[1]];
            let v = [s2 + noise[0] * noise[0], s2 + noise[1] * noise[1]];
            for (k, m) in means.iter().enumerate() {
                logits[k] = -(raw[0] - m[0]).powi(2) / (2.0 * v[0])
                    - (raw[1] - m[1]).powi(2) / (2.0 * v[1]);
            }
            let max = logits.iter().copied().fold(f32::NEG_INFINITY, f32::max);
            let (mut total, mut mean) = (0.0f32, [0.0f32; 2]);
            for (k, m) in means.iter().enumerate() {
                let w = (logits[k] - max).exp();
                total += w;
                mean[0] += w * m[0];
                mean[1] += w * m[1];
            }
            for j in 0..2 {
                let d = s2 / v[j] * raw[j] + noise[j] * noise[j] / v[j] * mean[j] / total;
                out[(i, j)] = (d - off[j]) / sc[j];
            }
        }
        Ok(())
    })
}

#[derive(Debug)]
struct Row {
    name: String,
    covered: usize,
    entropy: f64,
    histogram: Vec<f64>,
    nearest: f64,
    mmd: f64,
    us_per_action: f64,
}

/// Mode histogram, covered modes, base-8 entropy and mean nearest-mode distance of samples.
fn sample_stats(samples: MatRef<'_, f32>) -> (usize, f64, Vec<f64>, f64) {
    let n = samples.nrows();
    let means: Vec<Vec<f32>> = (0..MODES).map(|k| mode(k).to_vec()).collect();
    let counts = nearest_mode_counts(samples, &means);
    let histogram: Vec<f64> = counts.iter().map(|&c| c as f64 / n as f64).collect();
    let covered = histogram.iter().filter(|&&p| p >= 0.06).count();
    let entropy = -histogram.iter().filter(|&&p| p > 0.0).map(|p| p * p.ln()).sum::<f64>()
        / (MODES as f64).ln();
    let nearest = (0..n)
        .map(|i| {
            means
                .iter()
                .map(|m| {
                    let d2 = (samples[(i, 0)] - m[0]).powi(2) + (samples[(i, 1)] - m[1]).powi(2);
                    f64::from(d2.sqrt())
                })
                .fold(f64::INFINITY, f64::min)
        })
        .sum::<f64>()
        / n as f64;
    (covered, entropy, histogram, nearest)
}

fn evaluate(name: &str, policy: &mut dyn Policy, truth: MatRef<'_, f32>, seed: u64) -> Row {
    policy.seed(seed);
    let obs = Mat::<f32>::zeros(EVAL_SAMPLES, 1);
    let mut samples = Mat::zeros(EVAL_SAMPLES, 2);
    policy.act_batch(obs.as_ref(), samples.as_mut()).expect("sampling");
    let (covered, entropy, histogram, nearest) = sample_stats(samples.as_ref());
    let mmd = mmd2_rbf(samples.as_ref().subrows(0, MMD_SAMPLES), truth, 1.0);
    let mut a = [0.0f32; 2];
    let start = Instant::now();
    for _ in 0..TIMED_ACTIONS {
        policy.act_into(&[0.0], &mut a).expect("act");
    }
    let us_per_action = start.elapsed().as_secs_f64() * 1e6 / TIMED_ACTIONS as f64;
    Row { name: name.into(), covered, entropy, histogram, nearest, mmd, us_per_action }
}

fn arg<T: std::str::FromStr>(args: &[String], name: &str, default: T) -> T {
    args.iter()
        .position(|a| a == name)
        .and_then(|i| args.get(i + 1))
        .map(|v| v.parse().unwrap_or_else(|_| panic!("bad value for {name}")))
        .unwrap_or(default)
}

fn log(label: &'static str) -> impl FnMut(&ConsistencyProgress) {
    move |p| {
        println!(
            "  {label} step {:>5}/{}: loss {:.5} (consistency {:.5}, dsm {:.4}) lr {:.1e} {:.1}s",
            p.step, p.total_steps, p.loss, p.consistency_loss, p.dsm_loss, p.lr, p.elapsed_secs
        )
    }
}

/// The one default configuration of the students (both teachers).
fn student_configs(
    beso: &BesoConfig,
    from_teacher: bool,
    cd_steps: u64,
    ctm_steps: u64,
    seed: u64,
) -> (CdConfig, CtmConfig) {
    let mut cd = CdConfig::for_beso(beso);
    cd.init_from_teacher = from_teacher;
    cd.train.steps = cd_steps;
    cd.train.lr_schedule = vdd_nn::LrSchedule::Cosine { total_steps: cd_steps, final_factor: 0.1 };
    cd.train.seed = seed;
    let mut ctm = CtmConfig::for_beso(beso);
    ctm.init_from_teacher = from_teacher;
    ctm.train.steps = ctm_steps;
    ctm.train.lr_schedule =
        vdd_nn::LrSchedule::Cosine { total_steps: ctm_steps, final_factor: 0.1 };
    ctm.train.seed = seed;
    (cd, ctm)
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let seed: u64 = arg(&args, "--seed", 0);
    let which: String = arg(&args, "--teacher", String::from("both"));
    let teacher_steps: u64 = arg(&args, "--teacher-steps", 8000);
    let cd_steps: u64 = arg(&args, "--cd-steps", 4000);
    let ctm_steps: u64 = arg(&args, "--ctm-steps", 4000);
    let lr: f32 = arg(&args, "--lr", 2e-4);
    let target_decay: f32 = arg(&args, "--target-decay", 0.95);

    let seeds = Seeds::new(seed);
    let actions = sample_target(DATA_POINTS, &mut seeds.stream("toy-data"));
    let states = Mat::<f32>::zeros(DATA_POINTS, 1);
    let truth = sample_target(MMD_SAMPLES, &mut seeds.stream("truth"));
    let truth2 = sample_target(MMD_SAMPLES, &mut seeds.stream("truth-2"));

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
    };

    let mut tables: Vec<(String, Vec<Row>)> = Vec::new();
    let true_row = {
        let big = sample_target(EVAL_SAMPLES, &mut seeds.stream("truth-stats"));
        let (covered, entropy, histogram, nearest) = sample_stats(big.as_ref());
        let mmd = mmd2_rbf(truth2.as_ref(), truth.as_ref(), 1.0);
        Row {
            name: "true".into(),
            covered,
            entropy,
            histogram,
            nearest,
            mmd,
            us_per_action: f64::NAN,
        }
    };

    let run_beso = which == "beso" || which == "both";
    let run_exact = which == "exact" || which == "both";
    let mut timings = Vec::new();

    if run_beso {
        println!("training the BESO teacher ({teacher_steps} steps)...");
        let start = Instant::now();
        let mut beso = Beso::train(
            &beso_config,
            &teacher_train,
            states.as_ref(),
            actions.as_ref(),
            seed,
            &mut |p| println!("  teacher step {:>5}/{}: loss {:.4}", p.step, p.total_steps, p.loss),
        )?;
        timings.push(("BESO teacher", start.elapsed().as_secs_f64()));
        let mut rows = vec![evaluate("BESO (Heun 24)", &mut beso, truth.as_ref(), seed)];
        beso.set_sampler(KarrasSampler::Euler, 1)?;
        rows.push(evaluate("BESO-1", &mut beso, truth.as_ref(), seed));
        beso.set_sampler(KarrasSampler::Heun, 24)?;

        let (mut cd, mut ctm) = student_configs(&beso_config, true, cd_steps, ctm_steps, seed);
        cd.train.adam.lr = lr;
        ctm.train.adam.lr = lr;
        cd.train.target_ema_decay = target_decay;
        ctm.train.target_ema_decay = target_decay;
        println!("CD of the BESO teacher ({cd_steps} steps)...");
        let start = Instant::now();
        let mut trainer = CdTrainer::new(cd, &mut beso, states.as_ref(), actions.as_ref())?;
        let mut model = trainer.train(&mut log("CD"))?;
        timings.push(("CD (BESO teacher)", start.elapsed().as_secs_f64()));
        rows.push(evaluate("CD-1", &mut model, truth.as_ref(), seed));
        model.set_sampling_steps(2)?;
        rows.push(evaluate("CD-2", &mut model, truth.as_ref(), seed));

        println!("CTM of the BESO teacher ({ctm_steps} steps)...");
        let start = Instant::now();
        let mut trainer = CtmTrainer::new(ctm, &mut beso, states.as_ref(), actions.as_ref())?;
        let mut model = trainer.train(&mut log("CTM"))?;
        timings.push(("CTM (BESO teacher)", start.elapsed().as_secs_f64()));
        rows.push(evaluate("CTM-1", &mut model, truth.as_ref(), seed));
        model.set_sampling_steps(2)?;
        rows.push(evaluate("CTM-2", &mut model, truth.as_ref(), seed));
        tables.push(("learned BESO teacher (students start from its weights)".into(), rows));
    }

    if run_exact {
        // The same normalisers a BESO teacher would fit (per-dimension standardisation).
        let sn = fit_normalizer(states.as_ref(), NormalizerKind::Standard);
        let an = fit_normalizer(actions.as_ref(), NormalizerKind::Standard);
        let (mut cd, mut ctm) = student_configs(&beso_config, false, cd_steps, ctm_steps, seed);
        cd.train.adam.lr = lr;
        ctm.train.adam.lr = lr;
        cd.train.target_ema_decay = target_decay;
        ctm.train.target_ema_decay = target_decay;
        let mut rows = Vec::new();
        println!("CD of the exact teacher ({cd_steps} steps, fresh student)...");
        let start = Instant::now();
        let mut trainer = CdTrainer::new(
            cd,
            exact_teacher(sn.clone(), an.clone()),
            states.as_ref(),
            actions.as_ref(),
        )?;
        let mut model = trainer.train(&mut log("CD"))?;
        timings.push(("CD (exact teacher)", start.elapsed().as_secs_f64()));
        rows.push(evaluate("CD-1", &mut model, truth.as_ref(), seed));
        model.set_sampling_steps(2)?;
        rows.push(evaluate("CD-2", &mut model, truth.as_ref(), seed));
        println!("CTM of the exact teacher ({ctm_steps} steps, fresh student)...");
        let start = Instant::now();
        let mut trainer =
            CtmTrainer::new(ctm, exact_teacher(sn, an), states.as_ref(), actions.as_ref())?;
        let mut model = trainer.train(&mut log("CTM"))?;
        timings.push(("CTM (exact teacher)", start.elapsed().as_secs_f64()));
        rows.push(evaluate("CTM-1", &mut model, truth.as_ref(), seed));
        model.set_sampling_steps(2)?;
        rows.push(evaluate("CTM-2", &mut model, truth.as_ref(), seed));
        tables.push(("exact GMM denoiser teacher (students from scratch)".into(), rows));
    }

    println!(
        "\ntoy-gmm (8 modes, radius {RADIUS}, std {STD}, {DATA_POINTS} points), seed {seed}; \
         {EVAL_SAMPLES} samples for modes, {MMD_SAMPLES} for MMD² (RBF h = 1)"
    );
    for (title, rows) in &tables {
        println!("\n{title}:");
        println!(
            "method           modes  entropy  nearest-mode dist   MMD²      µs/action  histogram (%)"
        );
        for r in std::iter::once(&true_row).chain(rows.iter()) {
            let hist: Vec<String> =
                r.histogram.iter().map(|p| format!("{:.1}", 100.0 * p)).collect();
            println!(
                "{:<16} {:>2}/{MODES}   {:>6.3}   {:>17.3}   {:>8.5}  {:>9.1}  [{}]",
                r.name,
                r.covered,
                r.entropy,
                r.nearest,
                r.mmd,
                r.us_per_action,
                hist.join(" ")
            );
        }
    }
    println!();
    for (what, secs) in timings {
        println!("{what}: trained in {secs:.1} s");
    }
    Ok(())
}
