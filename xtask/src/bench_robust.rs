//! `cargo xtask bench robustness [--quick] --out DIR`: VDD with library defaults only
//! ([`vdd::Vdd::auto`]) on the seeded family of exact-mixture teachers
//! ([`vdd::gmm::family`]), evaluated by [`vdd::eval::evaluate_against_mixture`]. Writes
//! `DIR/robustness.json`: one record per run and the summary. Independent runs go to
//! `--threads` workers; every run is seeded, so the records do not depend on the scheduling.

use std::path::PathBuf;
use std::sync::Mutex;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use serde_json::{Value, json};
use vdd::eval::evaluate_against_mixture;
use vdd::gmm::family::{MixtureProblem, robustness_family};
use vdd::{AutoOptions, DistillData, Seeds, Trainer, Vdd};

/// The command line of `bench robustness`.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// 8 problems and one seed instead of 24 problems and three.
    #[arg(long)]
    pub quick: bool,
    /// Output directory.
    #[arg(long)]
    pub out: PathBuf,
    /// Parallel runs.
    #[arg(long, default_value_t = 2)]
    pub threads: usize,
    /// Monte-Carlo samples per state for each KL estimate.
    #[arg(long, default_value_t = 20_000)]
    pub samples: usize,
}

fn run_one(p: &MixtureProblem, seed: u64, experts: usize, samples: usize) -> crate::XResult<Value> {
    let data = DistillData::from_states(p.train_states.clone())?;
    let options = AutoOptions::new(experts, seed);
    let t0 = Instant::now();
    let mut vdd = Vdd::auto(p.teacher.clone(), data, &options)?;
    let t1 = Instant::now();
    vdd.train(|_| {})?;
    let ms_per_iter = t1.elapsed().as_secs_f64() * 1e3 / options.iterations as f64;
    let setup_ms = (t1 - t0).as_secs_f64() * 1e3;
    let mut student = vdd.finish()?;
    let mut rng = Seeds::new(seed).stream("robustness-eval");
    let mut teacher = p.teacher.clone();
    let e = evaluate_against_mixture(
        &mut student,
        &mut teacher,
        p.eval_states.as_ref(),
        samples,
        0.01,
        &mut rng,
    )?;
    Ok(json!({
        "problem": p.info.name, "seed": seed, "experts": experts,
        "reverse_kl": e.reverse_kl, "forward_kl": e.forward_kl,
        "components": e.components, "components_covered": e.components_covered,
        "ms_per_iter": ms_per_iter, "setup_ms": setup_ms,
    }))
}

/// Nearest-rank quantile `q` of `v`.
fn quantile(mut v: Vec<f64>, q: f64) -> Option<f64> {
    v.sort_by(f64::total_cmp);
    let i = ((q * v.len() as f64).ceil() as usize).clamp(1, v.len().max(1)) - 1;
    v.get(i).copied()
}

fn load() -> String {
    std::fs::read_to_string("/proc/loadavg").unwrap_or_default().trim().to_owned()
}

/// Runs the benchmark.
pub fn run(args: &Args) -> crate::XResult {
    let (n, seeds): (usize, &[u64]) = if args.quick { (8, &[0]) } else { (24, &[0, 1, 2]) };
    let problems = robustness_family(n, 0)?;
    let jobs: Vec<(usize, u64, usize)> = (0..n)
        .flat_map(|p| seeds.iter().flat_map(move |&s| [1, 2].map(|m| (p, s, m))))
        .map(|(p, s, m)| (p, s, m * problems[p].info.components))
        .collect();
    std::fs::create_dir_all(&args.out)?;
    let load_start = load();
    crate::progress::log(format!(
        "{} runs on {} threads; load {load_start}",
        jobs.len(),
        args.threads
    ));
    let t0 = Instant::now();
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<Option<Value>>> = Mutex::new(vec![None; jobs.len()]);
    let done = AtomicUsize::new(0);
    std::thread::scope(|scope| {
        for _ in 0..args.threads.max(1) {
            scope.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::SeqCst);
                let Some(&(p, seed, experts)) = jobs.get(i) else { break };
                let r = run_one(&problems[p], seed, experts, args.samples)
                    .unwrap_or_else(|e| json!({"problem": problems[p].info.name, "seed": seed, "experts": experts, "error": e.to_string()}));
                let k = done.fetch_add(1, Ordering::SeqCst) + 1;
                crate::progress::log(format!(
                    "[{k}/{}] {} seed {seed} experts {experts}: reverse KL {:.4} forward KL {:.4} covered {}/{} {:.1} ms/iter {}",
                    jobs.len(), problems[p].info.name, r["reverse_kl"].as_f64().unwrap_or(f64::NAN),
                    r["forward_kl"].as_f64().unwrap_or(f64::NAN), r["components_covered"], r["components"],
                    r["ms_per_iter"].as_f64().unwrap_or(f64::NAN), r.get("error").map_or(String::new(), |e| e.to_string()),
                ));
                results.lock().expect("no worker panics holding the lock")[i] = Some(r);
            });
        }
    });
    let runs: Vec<Value> = results.into_inner()?.into_iter().flatten().collect();
    let full = |r: &&Value| r["components_covered"] == r["components"] && r.get("error").is_none();
    let kl = |mult: usize| -> Vec<f64> {
        runs.iter()
            .zip(&jobs)
            .filter(|(_, j)| j.2 == mult * problems[j.0].info.components)
            .map(|(r, _)| r["reverse_kl"].as_f64().unwrap_or(f64::INFINITY))
            .collect()
    };
    let summary = json!({
        "runs": runs.len(),
        "coverage_rate": runs.iter().filter(full).count() as f64 / runs.len().max(1) as f64,
        "median_reverse_kl": quantile(kl(1), 0.5), "p90_reverse_kl": quantile(kl(1), 0.9),
        "median_reverse_kl_2x": quantile(kl(2), 0.5), "p90_reverse_kl_2x": quantile(kl(2), 0.9),
        "wall_seconds": t0.elapsed().as_secs_f64(), "threads": args.threads,
        "load_start": load_start, "load_end": load(), "quick": args.quick,
    });
    let problems_info: Vec<_> = problems.iter().map(|p| &p.info).collect();
    let doc = json!({"summary": summary, "problems": problems_info, "runs": runs});
    std::fs::write(args.out.join("robustness.json"), serde_json::to_string_pretty(&doc)?)?;
    println!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(())
}
