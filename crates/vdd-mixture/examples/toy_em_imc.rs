//! EM and IMC on the paper's 2-D toy: 8 modes on a circle of radius 2, isotropic std 0.5,
//! equal weights, 5000 samples, one constant state `s = 0` (1-D). Both fit 8 diagonal experts
//! with a learned gating (the same `MoeConfig::toy` networks VDD uses) with their one default
//! configuration, then are measured against the exact density:
//!
//! * reverse KL `E_q[log q − log p]` by Monte Carlo with student samples,
//! * forward KL `E_p[log p − log q]` by Monte Carlo with fresh target samples,
//! * modes covered (some expert of gating weight ≥ 0.01 has its mean within 0.3 of the mode),
//! * experts "between modes" (weight ≥ 0.01, mean farther than 0.3 from every mode).
//!
//! ```sh
//! cargo run --release -p vdd-mixture --example toy_em_imc -- [--seed N] [--eta X] [--mc N]
//!     [--only em|imc] [--iters N (N iterations of 3000/N steps instead of the default)]
//! ```

use std::time::Instant;

use faer::{Mat, MatRef};
use rand::Rng as _;
use vdd_core::{Seeds, gaussian};
use vdd_mixture::{Dataset, Em, EmConfig, Imc, ImcConfig};
use vdd_moe::{GatingKind, Moe, MoeConfig};

mod toy_common;
use toy_common::{DATA_POINTS, MODES, RADIUS, STD, arg, log_p, mode, sample_target};

#[derive(Debug)]
struct Report {
    reverse_kl: f64,
    forward_kl: f64,
    modes_covered: usize,
    between_modes: usize,
    data_log_likelihood: f64,
    train_seconds: f64,
}

/// `log q(a|s=0)` of each row.
fn log_q(student: &mut Moe, actions: MatRef<'_, f32>) -> Vec<f32> {
    student.forward(Mat::<f32>::zeros(1, 1).as_ref()).expect("forward");
    let out = student.output();
    let (mut a, mut resp, mut work) = ([0.0f32; 2], vec![0.0f32; out.num_experts], [0.0f32; 2]);
    (0..actions.nrows())
        .map(|i| {
            a = [actions[(i, 0)], actions[(i, 1)]];
            out.log_density_and_responsibilities(0, &a, &mut resp, &mut work)
        })
        .collect()
}

fn evaluate(student: &mut Moe, mc: usize, seeds: &Seeds) -> (f64, f64, usize, usize) {
    // Reverse KL with student samples z ~ q(z|s), a = μ_z + L_z ε.
    student.forward(Mat::<f32>::zeros(1, 1).as_ref()).expect("forward");
    let out = student.output().clone();
    let probs: Vec<f32> = out.log_gating_row(0).iter().map(|l| l.exp()).collect();
    let mut rng = seeds.stream("reverse");
    let mut samples = Mat::zeros(mc, 2);
    let (mut eps, mut a) = ([0.0f32; 2], [0.0f32; 2]);
    for i in 0..mc {
        let u: f32 = rng.random();
        let (mut acc, mut z) = (0.0, probs.len() - 1);
        for (k, p) in probs.iter().enumerate() {
            acc += p;
            if u < acc {
                z = k;
                break;
            }
        }
        vdd_core::fill_standard_normal(&mut rng, &mut eps);
        gaussian::sample_into(out.mean(0, z), out.scale(0, z), &eps, &mut a);
        samples[(i, 0)] = a[0];
        samples[(i, 1)] = a[1];
    }
    let lq = log_q(student, samples.as_ref());
    let reverse = (0..mc)
        .map(|i| f64::from(lq[i]) - f64::from(log_p(&[samples[(i, 0)], samples[(i, 1)]])))
        .sum::<f64>()
        / mc as f64;

    // Forward KL with fresh target samples.
    let target = sample_target(mc, &mut seeds.stream("forward"));
    let lq = log_q(student, target.as_ref());
    let forward = (0..mc)
        .map(|i| f64::from(log_p(&[target[(i, 0)], target[(i, 1)]])) - f64::from(lq[i]))
        .sum::<f64>()
        / mc as f64;

    // Modes covered and experts sitting between modes.
    let dist = |m: &[f32], k: usize| {
        let t = mode(k);
        ((m[0] - t[0]).powi(2) + (m[1] - t[1]).powi(2)).sqrt()
    };
    let active: Vec<usize> = (0..probs.len()).filter(|&z| probs[z] >= 0.01).collect();
    let covered =
        (0..MODES).filter(|&k| active.iter().any(|&z| dist(out.mean(0, z), k) <= 0.3)).count();
    let between =
        active.iter().filter(|&&z| (0..MODES).all(|k| dist(out.mean(0, z), k) > 0.3)).count();
    (reverse, forward, covered, between)
}

fn describe(student: &mut Moe) {
    student.forward(Mat::<f32>::zeros(1, 1).as_ref()).expect("forward");
    let out = student.output();
    for z in 0..out.num_experts {
        let (m, l) = (out.mean(0, z), out.scale(0, z));
        let nearest = (0..MODES)
            .map(|k| {
                let t = mode(k);
                ((m[0] - t[0]).powi(2) + (m[1] - t[1]).powi(2)).sqrt()
            })
            .fold(f32::INFINITY, f32::min);
        println!(
            "    expert {z}: weight {:.3}  mean ({:+.2}, {:+.2})  std ({:.2}, {:.2})  nearest mode {:.2}",
            out.log_gating_row(0)[z].exp(),
            m[0],
            m[1],
            l[0],
            l[3],
            nearest
        );
    }
}

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let args: Vec<String> = std::env::args().collect();
    let seed: u64 = arg(&args, "--seed", 0);
    let mc: usize = arg(&args, "--mc", 100_000);
    let eta: f64 = arg(&args, "--eta", ImcConfig::toy().eta);
    let only: String = arg(&args, "--only", String::from("both"));
    let iters: usize = arg(&args, "--iters", 0);

    let seeds = Seeds::new(seed);
    let actions = sample_target(DATA_POINTS, &mut seeds.stream("toy-data"));
    let data = Dataset::new(Mat::zeros(DATA_POINTS, 1), actions)?;
    let mut mc_config = MoeConfig::toy(1, 2, MODES);
    mc_config.gating = GatingKind::Learned;

    let mut reports = Vec::new();
    let methods: Vec<&str> = match only.as_str() {
        "em" => vec!["EM"],
        "imc" => vec!["IMC"],
        _ => vec!["EM", "IMC"],
    };
    for method in methods {
        let start = Instant::now();
        let mut student = match method {
            "EM" => {
                let mut config = EmConfig { seed, ..EmConfig::toy() };
                if let Some(steps) = 3000usize.checked_div(iters) {
                    config.iterations = iters;
                    config.expert_steps_per_iter = steps;
                    config.gating_steps_per_iter = steps;
                }
                let mut em = Em::from_config(config, mc_config.clone(), data.clone())?;
                em.train(|m| {
                    if m.iteration % 100 == 0 {
                        println!("  EM  it {:>3}: log-lik {:.4}", m.iteration, m.log_likelihood);
                    }
                })?;
                em.into_student()
            }
            _ => {
                let mut config = ImcConfig { seed, eta, ..ImcConfig::toy() };
                if let Some(steps) = 3000usize.checked_div(iters) {
                    config.iterations = iters;
                    config.expert_steps_per_iter = steps;
                    config.gating_steps_per_iter = steps;
                }
                let mut imc = Imc::from_config(config, mc_config.clone(), data.clone())?;
                imc.train(|m| {
                    if m.iteration % 100 == 0 {
                        println!(
                            "  IMC it {:>3}: J {:.4}  log-lik {:.4}  effective data {:.3}  active experts {}",
                            m.iteration,
                            m.objective,
                            m.log_likelihood,
                            m.effective_data_fraction,
                            m.active_experts
                        );
                    }
                })?;
                imc.into_student()
            }
        };
        let train_seconds = start.elapsed().as_secs_f64();
        let mut ll = vec![0.0f32; DATA_POINTS];
        vdd_core::Policy::log_likelihood(&mut student, data.states(), data.actions(), &mut ll)?;
        let data_log_likelihood =
            ll.iter().map(|&x| f64::from(x)).sum::<f64>() / DATA_POINTS as f64;
        let (reverse_kl, forward_kl, modes_covered, between_modes) =
            evaluate(&mut student, mc, &seeds.child("toy-eval"));
        println!("{method} experts:");
        describe(&mut student);
        reports.push((
            method,
            Report {
                reverse_kl,
                forward_kl,
                modes_covered,
                between_modes,
                data_log_likelihood,
                train_seconds,
            },
        ));
    }

    println!(
        "\ntoy-gmm (8 modes, radius {RADIUS}, std {STD}, {DATA_POINTS} points), seed {seed}, \
         IMC eta {eta}, {mc} Monte-Carlo samples"
    );
    println!("method  reverse KL  forward KL  modes  between-modes  data log-lik  train s");
    for (method, r) in &reports {
        println!(
            "{method:<6}  {:>10.4}  {:>10.4}  {:>3}/{MODES}  {:>13}  {:>12.4}  {:>7.1}",
            r.reverse_kl,
            r.forward_kl,
            r.modes_covered,
            r.between_modes,
            r.data_log_likelihood,
            r.train_seconds
        );
    }
    // The exact density's own data log-likelihood, for scale.
    let exact: f64 = (0..DATA_POINTS)
        .map(|i| f64::from(log_p(&[data.actions()[(i, 0)], data.actions()[(i, 1)]])))
        .sum::<f64>()
        / DATA_POINTS as f64;
    println!("(exact density's data log-lik: {exact:.4})");
    Ok(())
}
