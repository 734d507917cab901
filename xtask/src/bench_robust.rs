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
use vdd::faer::Mat;
use vdd::gmm::GmmTeacher;
use vdd::gmm::family::{MixtureProblem, ProblemInfo, robustness_family};
use vdd::{
    AutoOptions, DistillData, ExpertKind, GatingKind, InitKind, MoeConfig, Seeds, Trainer, Vdd,
    VddConfig,
};

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
    /// Skip the paper's toy.
    #[arg(long)]
    pub no_toy: bool,
    /// Monte-Carlo samples per state for each KL estimate.
    #[arg(long, default_value_t = 20_000)]
    pub samples: usize,
    /// What to run instead of the library defaults, for comparisons: `toy` (VddConfig::toy and
    /// MoeConfig::toy with full-covariance experts, raw units), `uniform-gating`,
    /// `official-init`, `no-anneal`.
    #[arg(long, default_value = "default")]
    pub variant: String,
    /// Only these problem indices (comma-separated; for investigating one problem).
    #[arg(long, value_delimiter = ',')]
    pub only: Vec<usize>,
}

/// The paper's 2-D toy (8 modes on a circle of radius 2, std 0.5, 5000 zero states) through
/// the same defaults.
fn toy() -> MixtureProblem {
    let teacher = GmmTeacher::circle_toy();
    let info = ProblemInfo {
        name: "paper-toy".into(),
        index: usize::MAX,
        action_dim: 2,
        components: 8,
        conditional: false,
        scale: 1.0,
        offset_norm: 0.0,
        condition: 1.0,
        min_weight: 0.125,
    };
    let (train_states, eval_states) = (Mat::zeros(5000, 1), Mat::zeros(1, 1));
    MixtureProblem { info, teacher, train_states, eval_states }
}

fn run_one(p: &MixtureProblem, seed: u64, experts: usize, args: &Args) -> crate::XResult<Value> {
    let samples = args.samples;
    let data = DistillData::from_states(p.train_states.clone())?;
    let mut options = AutoOptions::new(experts, seed);
    match args.variant.as_str() {
        "default" | "toy" => {}
        "uniform-gating" => options.gating = GatingKind::Uniform,
        "official-init" => options.init = InitKind::Official,
        "no-anneal" => options.start_noise_factor = 0.0,
        other => return Err(format!("unknown --variant {other}").into()),
    }
    let t0 = Instant::now();
    let mut vdd = if args.variant == "toy" {
        let (ds, d) = (p.train_states.ncols(), p.info.action_dim);
        let mc = MoeConfig { expert_kind: ExpertKind::Full, ..MoeConfig::toy(ds, d, experts) };
        Vdd::from_config(VddConfig { seed, ..VddConfig::toy() }, p.teacher.clone(), mc, data)?
    } else {
        Vdd::auto(p.teacher.clone(), data, &options)?
    };
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
        .filter(|p| args.only.is_empty() || args.only.contains(p))
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
    // The paper's toy first, one run at a time (its ms/iter is a single-threaded figure).
    let toy_problem = toy();
    let mut toy_runs = Vec::new();
    for seed in 0..if args.no_toy { 0 } else { 3 } {
        let r = run_one(&toy_problem, seed, 8, args)?;
        crate::progress::log(format!("[toy] {r}"));
        toy_runs.push(r);
    }
    let next = AtomicUsize::new(0);
    let results: Mutex<Vec<Option<Value>>> = Mutex::new(vec![None; jobs.len()]);
    let done = AtomicUsize::new(0);
    std::thread::scope(|scope| {
        for _ in 0..args.threads.max(1) {
            scope.spawn(|| loop {
                let i = next.fetch_add(1, Ordering::SeqCst);
                let Some(&(p, seed, experts)) = jobs.get(i) else { break };
                let r = run_one(&problems[p], seed, experts, args)
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
        "variant": args.variant,
    });
    let problems_info: Vec<_> = problems.iter().map(|p| &p.info).collect();
    let doc =
        json!({"summary": summary, "problems": problems_info, "runs": runs, "paper_toy": toy_runs});
    std::fs::write(args.out.join("robustness.json"), serde_json::to_string_pretty(&doc)?)?;
    println!("{}", serde_json::to_string_pretty(&summary)?);
    Ok(())
}
