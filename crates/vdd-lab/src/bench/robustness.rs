//! The robustness benchmark: VDD with library defaults only ([`Vdd::auto`]) on the seeded
//! family of exact-mixture teachers ([`vdd_core::gmm::family`]), each student evaluated by
//! [`evaluate_against_mixture`] (the trainer's evaluation, `vdd::eval`) ([`robustness`]).
//!
//! Every problem is distilled once with as many experts as it has components and once with
//! twice as many, on 8 problems and seed 0 ([`RobustnessOptions::quick`]) or 24 problems and
//! seeds 0–2. Independent runs go to [`RobustnessOptions::threads`] workers; every run is
//! seeded, so the records do not depend on the scheduling. The paper's 2-D toy
//! ([`paper_toy`]) runs first, one run at a time (its ms/iteration is a single-threaded
//! figure). `cargo xtask bench robustness` writes the document this returns.

use std::convert::Infallible;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use faer::Mat;
use serde_json::{Value, json};
use vdd_core::gmm::GmmTeacher;
use vdd_core::gmm::family::{MixtureProblem, ProblemInfo, robustness_family};
use vdd_core::parallel::parallel_map;
use vdd_core::{Seeds, Trainer as _};
use vdd_moe::{ExpertKind, GatingKind, MoeConfig};

use vdd::eval::evaluate_against_mixture;
use vdd::{AutoOptions, DistillData, InitKind, Vdd, VddConfig};

/// What runs instead of the library defaults, for comparisons.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Variant {
    /// [`Vdd::auto`] with [`AutoOptions::new`].
    #[default]
    Default,
    /// [`VddConfig::toy`] and [`MoeConfig::toy`] with full-covariance experts, raw units.
    Toy,
    /// The defaults with a uniform gating.
    UniformGating,
    /// The defaults with the official initialisation ([`InitKind::Official`]).
    OfficialInit,
    /// The defaults without noise annealing.
    NoAnneal,
}

impl Variant {
    /// Every variant.
    pub const ALL: [Variant; 5] =
        [Self::Default, Self::Toy, Self::UniformGating, Self::OfficialInit, Self::NoAnneal];

    /// `default`, `toy`, `uniform-gating`, `official-init` or `no-anneal`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Default => "default",
            Self::Toy => "toy",
            Self::UniformGating => "uniform-gating",
            Self::OfficialInit => "official-init",
            Self::NoAnneal => "no-anneal",
        }
    }
}

impl std::str::FromStr for Variant {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        Self::ALL.into_iter().find(|v| v.name() == s).ok_or_else(|| {
            let names: Vec<&str> = Self::ALL.iter().map(|v| v.name()).collect();
            format!("unknown variant `{s}` ({})", names.join(", "))
        })
    }
}

/// The settings of [`robustness`].
#[derive(Debug, Clone, PartialEq)]
pub struct RobustnessOptions {
    /// 8 problems and one seed instead of 24 problems and three.
    pub quick: bool,
    /// Parallel runs.
    pub threads: usize,
    /// Skip the paper's toy.
    pub no_toy: bool,
    /// Monte-Carlo samples per state for each KL estimate.
    pub samples: usize,
    /// What to run.
    pub variant: Variant,
    /// Only these problem indices (all when empty).
    pub only: Vec<usize>,
}

/// The paper's 2-D toy (8 modes on a circle of radius 2, std 0.5, 5000 zero states) as a
/// problem of the family.
pub fn paper_toy() -> MixtureProblem {
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

/// Distils problem `p` with `experts` experts and `seed`, and evaluates the student with
/// `samples` samples per state: the run's record (`problem`, `seed`, `experts`, `reverse_kl`,
/// `forward_kl`, `components`, `components_covered`, `ms_per_iter`, `setup_ms`).
pub fn run_one(
    p: &MixtureProblem,
    seed: u64,
    experts: usize,
    samples: usize,
    variant: Variant,
) -> crate::Result<Value> {
    let data = DistillData::from_states(p.train_states.clone())?;
    let mut options = AutoOptions::new(experts, seed);
    match variant {
        Variant::Default | Variant::Toy => {}
        Variant::UniformGating => options.gating = GatingKind::Uniform,
        Variant::OfficialInit => options.init = InitKind::Official,
        Variant::NoAnneal => options.start_noise_factor = 0.0,
    }
    let t0 = Instant::now();
    let mut vdd = if variant == Variant::Toy {
        let (ds, d) = (p.train_states.ncols(), p.info.action_dim);
        let mc = MoeConfig { expert_kind: ExpertKind::Full, ..MoeConfig::toy(ds, d, experts) };
        Vdd::from_config(VddConfig { seed, ..VddConfig::toy() }, p.teacher.clone(), mc, data)?
    } else {
        Vdd::auto(p.teacher.clone(), data, &options)?
    };
    let t1 = Instant::now();
    vdd.train(|_| {})?;
    let ms_per_iter = t1.elapsed().as_secs_f64() * 1e3 / vdd.iterations().max(1) as f64;
    let setup_ms = (t1 - t0).as_secs_f64() * 1e3;
    let mut student = vdd.finish()?;
    let mut rng = Seeds::new(seed).stream("robustness-eval");
    let mut teacher = p.teacher.clone();
    let states = p.eval_states.as_ref();
    let e = evaluate_against_mixture(&mut student, &mut teacher, states, samples, 0.01, &mut rng)?;
    Ok(json!({
        "problem": p.info.name, "seed": seed, "experts": experts,
        "reverse_kl": e.reverse_kl, "forward_kl": e.forward_kl,
        "components": e.components, "components_covered": e.components_covered,
        "ms_per_iter": ms_per_iter, "setup_ms": setup_ms,
    }))
}

/// Nearest-rank quantile `q` of `v` (`None` when empty).
pub fn quantile(mut v: Vec<f64>, q: f64) -> Option<f64> {
    v.sort_by(f64::total_cmp);
    let i = ((q * v.len() as f64).ceil() as usize).clamp(1, v.len().max(1)) - 1;
    v.get(i).copied()
}

/// `/proc/loadavg` (empty where there is none): the machine load beside the timings.
fn load() -> String {
    std::fs::read_to_string("/proc/loadavg").unwrap_or_default().trim().to_owned()
}

/// Runs the benchmark, reporting progress lines to `log`: `{"summary", "problems", "runs",
/// "paper_toy"}`. A run that fails is a record with an `error` and counts as not covered; the
/// summary has the coverage rate (runs covering every component), the median and 90th
/// percentile reverse KL with as many experts as components and with twice as many, the wall
/// time, the threads, the load before and after, `quick` and the variant.
pub fn robustness(o: &RobustnessOptions, log: impl Fn(String) + Sync) -> crate::Result<Value> {
    let (n, seeds): (usize, &[u64]) = if o.quick { (8, &[0]) } else { (24, &[0, 1, 2]) };
    let problems = robustness_family(n, 0)?;
    let jobs: Vec<(usize, u64, usize)> = (0..n)
        .filter(|p| o.only.is_empty() || o.only.contains(p))
        .flat_map(|p| seeds.iter().flat_map(move |&s| [1, 2].map(|m| (p, s, m))))
        .map(|(p, s, m)| (p, s, m * problems[p].info.components))
        .collect();
    let load_start = load();
    log(format!("{} runs on {} threads; load {load_start}", jobs.len(), o.threads));
    let t0 = Instant::now();
    let toy_problem = paper_toy();
    let mut toy_runs = Vec::new();
    for seed in 0..if o.no_toy { 0 } else { 3 } {
        let r = run_one(&toy_problem, seed, 8, o.samples, o.variant)?;
        log(format!("[toy] {r}"));
        toy_runs.push(r);
    }
    let done = AtomicUsize::new(0);
    let runs = parallel_map(&jobs, o.threads.max(1), |&(p, seed, experts)| {
        let name = &problems[p].info.name;
        let r = run_one(&problems[p], seed, experts, o.samples, o.variant).unwrap_or_else(
            |e| json!({"problem": name, "seed": seed, "experts": experts, "error": e.to_string()}),
        );
        let k = done.fetch_add(1, Ordering::SeqCst) + 1;
        let f = |key: &str| r[key].as_f64().unwrap_or(f64::NAN);
        log(format!(
            "[{k}/{}] {name} seed {seed} experts {experts}: reverse KL {:.4} forward KL {:.4} covered {}/{} {:.1} ms/iter {}",
            jobs.len(),
            f("reverse_kl"),
            f("forward_kl"),
            r["components_covered"],
            r["components"],
            f("ms_per_iter"),
            r.get("error").map_or(String::new(), |e| e.to_string()),
        ));
        Ok::<_, Infallible>(r)
    });
    let runs: Vec<Value> = match runs {
        Ok(runs) => runs,
        Err(never) => match never {},
    };
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
        "wall_seconds": t0.elapsed().as_secs_f64(), "threads": o.threads,
        "load_start": load_start, "load_end": load(), "quick": o.quick,
        "variant": o.variant.name(),
    });
    let problems_info: Vec<_> = problems.iter().map(|p| &p.info).collect();
    Ok(json!({"summary": summary, "problems": problems_info, "runs": runs, "paper_toy": toy_runs}))
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn quantiles_are_nearest_rank_and_variants_round_trip() {
        let v: Vec<f64> = (1..=10).map(f64::from).collect();
        assert_eq!(quantile(v.clone(), 0.5), Some(5.0));
        assert_eq!(quantile(v.clone(), 0.9), Some(9.0));
        assert_eq!(quantile(v, 0.0), Some(1.0));
        assert_eq!(quantile(Vec::new(), 0.5), None);
        for v in Variant::ALL {
            assert_eq!(v.name().parse::<Variant>(), Ok(v));
        }
        assert!("bogus".parse::<Variant>().unwrap_err().contains("uniform-gating"));
    }

    #[test]
    fn one_run_on_the_paper_toy_gives_a_complete_record() {
        let mut p = paper_toy();
        p.train_states = Mat::zeros(64, 1);
        let r = run_one(&p, 0, 2, 200, Variant::Toy).unwrap();
        for key in ["reverse_kl", "forward_kl", "ms_per_iter", "setup_ms"] {
            assert!(r[key].as_f64().is_some_and(f64::is_finite), "{key}: {r}");
        }
        assert_eq!((r["components"].as_u64(), r["experts"].as_u64()), (Some(8), Some(2)));
        assert!(r["components_covered"].as_u64().is_some_and(|c| c <= 8), "{r}");
    }
}
