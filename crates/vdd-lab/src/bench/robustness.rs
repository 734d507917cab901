//! The robustness benchmark: VDD with library defaults only ([`Vdd::auto`]) on the seeded
//! family of exact-mixture teachers ([`vdd_core::gmm::family`]) and its extra problems
//! ([`robustness_extras`]: state-conditioned weights, teachers served through their score
//! alone, a curved target), each student evaluated by [`evaluate_against_mixture_in_regions`]
//! (the trainer's evaluation, `vdd::eval`) ([`robustness`]).
//!
//! Every problem is distilled once with its number of experts (as many as it has components,
//! or the extra problem's own) and once with twice as many, on 8 random problems and the
//! extras with seed 0 ([`RobustnessOptions::quick`]) or 24 random problems and the extras with
//! seeds 0–2 ([`RobustnessOptions::seeds`] overrides them). A problem served score-only
//! reaches the trainer through [`ScoreOnly`]. Independent runs go to
//! [`RobustnessOptions::threads`] workers; every run is seeded, so the records do not depend on
//! the scheduling. The paper's 2-D toy ([`paper_toy`]) runs first, one run at a time (its
//! ms/iteration is a single-threaded figure). `cargo xtask bench robustness` writes the
//! document this returns.

use std::convert::Infallible;
use std::sync::atomic::{AtomicUsize, Ordering};
use std::time::Instant;

use faer::{Mat, MatMut, MatRef};
use rand::RngCore;
use serde_json::{Value, json};
use vdd_core::gmm::GmmTeacher;
use vdd_core::gmm::family::{MixtureProblem, ProblemInfo, robustness_extras, robustness_family};
use vdd_core::parallel::parallel_map;
use vdd_core::{
    CoreError, DenoiserForm, NoiseConvention, NoiseSchedule, ScoreModel, Seeds, Trainer as _,
};
use vdd_moe::{ExpertKind, GatingKind, Moe, MoeConfig};

use vdd::eval::evaluate_against_mixture_in_regions;
use vdd::{AutoOptions, Convergence, DistillData, InitKind, Vdd, VddConfig};

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
    /// The defaults run four times as long as the paper's toy run ([`LONG_ITERATIONS`]).
    Long,
}

/// Iterations of [`Variant::Long`].
pub const LONG_ITERATIONS: usize = 2400;

impl Variant {
    /// Every variant.
    pub const ALL: [Variant; 6] = [
        Self::Default,
        Self::Toy,
        Self::UniformGating,
        Self::OfficialInit,
        Self::NoAnneal,
        Self::Long,
    ];

    /// `default`, `toy`, `uniform-gating`, `official-init`, `no-anneal` or `long`.
    pub fn name(self) -> &'static str {
        match self {
            Self::Default => "default",
            Self::Toy => "toy",
            Self::UniformGating => "uniform-gating",
            Self::OfficialInit => "official-init",
            Self::NoAnneal => "no-anneal",
            Self::Long => "long",
        }
    }
}

/// A teacher seen through its score alone: every [`ScoreModel`] method is forwarded except
/// [`ScoreModel::sample_actions`], which keeps the trait's default (unsupported), as for a
/// teacher behind a score function. The benchmark serves the problems marked
/// [`ProblemInfo::score_only`] through it.
///
/// ```
/// use faer::Mat;
/// use vdd_core::ScoreModel;
/// use vdd_core::gmm::GmmTeacher;
/// use vdd_lab::bench::robustness::ScoreOnly;
/// let mut t = ScoreOnly(GmmTeacher::circle_toy());
/// let (s, mut out) = (Mat::<f32>::zeros(1, 1), Mat::<f32>::zeros(1, 2));
/// let mut rng = vdd_core::Seeds::new(0).stream("x");
/// assert!(t.sample_actions(s.as_ref(), &mut rng, out.as_mut()).is_err());
/// assert!(t.score(Mat::zeros(1, 2).as_ref(), s.as_ref(), &[0.1], out.as_mut()).is_ok());
/// ```
#[derive(Debug, Clone)]
pub struct ScoreOnly<S>(pub S);

impl<S: ScoreModel> ScoreModel for ScoreOnly<S> {
    fn action_dim(&self) -> usize {
        self.0.action_dim()
    }
    fn state_dim(&self) -> usize {
        self.0.state_dim()
    }
    fn noise_process(&self) -> Option<&dyn vdd_core::NoiseProcess> {
        self.0.noise_process()
    }
    fn noise_convention(&self) -> NoiseConvention {
        self.0.noise_convention()
    }
    fn score(
        &mut self,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        noise_levels: &[f32],
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        self.0.score(actions, states, noise_levels, out)
    }
    fn draw_noise_levels(
        &self,
        schedule: &NoiseSchedule,
        progress: f32,
        rng: &mut dyn RngCore,
        out: &mut [f32],
    ) {
        self.0.draw_noise_levels(schedule, progress, rng, out)
    }
    fn denoiser_form(&self, level: f32) -> Option<DenoiserForm> {
        self.0.denoiser_form(level)
    }
    fn noise_range(&self) -> Option<(f32, f32)> {
        self.0.noise_range()
    }
    fn fork(&self) -> Option<Box<dyn ScoreModel + Send>> {
        None
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
    /// 8 random problems (and the extras) and one seed instead of 24 and three.
    pub quick: bool,
    /// Parallel runs.
    pub threads: usize,
    /// Skip the paper's toy.
    pub no_toy: bool,
    /// Monte-Carlo samples per state for each KL estimate.
    pub samples: usize,
    /// What to run.
    pub variant: Variant,
    /// Only these problem indices ([`ProblemInfo::index`]; all when empty).
    pub only: Vec<usize>,
    /// These seeds instead of `quick`'s (0) or the full run's (0, 1, 2), when not empty.
    pub seeds: Vec<u64>,
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
        score_only: false,
        experts: 8,
        regions: 8,
    };
    let (train_states, eval_states) = (Mat::zeros(5000, 1), Mat::zeros(1, 1));
    MixtureProblem { info, teacher, train_states, eval_states, regions: (0..8).collect() }
}

/// What [`train`] returns: the student, its iterations, and the training's and the set-up's
/// milliseconds.
struct Trained {
    student: Moe,
    convergence: Option<Convergence>,
    iterations: usize,
    ms_per_iter: f64,
    setup_ms: f64,
}

/// Sets up and trains the run of `variant` on `teacher`.
fn train<S: ScoreModel>(
    p: &MixtureProblem,
    teacher: S,
    seed: u64,
    experts: usize,
    variant: Variant,
) -> crate::Result<Trained> {
    let data = DistillData::from_states(p.train_states.clone())?;
    let mut options = AutoOptions::new(experts, seed);
    match variant {
        Variant::Default | Variant::Toy => {}
        Variant::UniformGating => options.gating = GatingKind::Uniform,
        Variant::OfficialInit => options.init = InitKind::Official,
        Variant::NoAnneal => options.start_noise_factor = Some(0.0),
        Variant::Long => options.iterations = Some(LONG_ITERATIONS),
    }
    let t0 = Instant::now();
    let mut vdd = if variant == Variant::Toy {
        let (ds, d) = (p.train_states.ncols(), p.info.action_dim);
        let mc = MoeConfig { expert_kind: ExpertKind::Full, ..MoeConfig::toy(ds, d, experts) };
        Vdd::from_config(VddConfig { seed, ..VddConfig::toy() }, teacher, mc, data)?
    } else {
        Vdd::auto(teacher, data, &options)?
    };
    let t1 = Instant::now();
    vdd.train(|_| {})?;
    let iterations = vdd.iterations();
    let ms_per_iter = t1.elapsed().as_secs_f64() * 1e3 / iterations.max(1) as f64;
    let setup_ms = (t1 - t0).as_secs_f64() * 1e3;
    let convergence = vdd.convergence();
    Ok(Trained { student: vdd.finish()?, convergence, iterations, ms_per_iter, setup_ms })
}

/// Distils problem `p` with `experts` experts and `seed` (through [`ScoreOnly`] when the
/// problem is served score-only), and evaluates the student with `samples` samples per state:
/// the run's record (`problem`, `seed`, `experts`, `iterations`, `reverse_kl`, `forward_kl`,
/// `components`, `components_covered` (regions, for a problem that groups its components),
/// `converged`, `score_mismatch` and the measurements it came from, `score_mismatches`
/// ([`Vdd::convergence`]), `ms_per_iter`, `setup_ms`).
pub fn run_one(
    p: &MixtureProblem,
    seed: u64,
    experts: usize,
    samples: usize,
    variant: Variant,
) -> crate::Result<Value> {
    let t = match p.info.score_only {
        true => train(p, ScoreOnly(p.teacher.clone()), seed, experts, variant)?,
        false => train(p, p.teacher.clone(), seed, experts, variant)?,
    };
    let mut student = t.student;
    let mut rng = Seeds::new(seed).stream("robustness-eval");
    let mut teacher = p.teacher.clone();
    let (states, regions) = (p.eval_states.as_ref(), Some(&p.regions[..]));
    let e = evaluate_against_mixture_in_regions(
        &mut student,
        &mut teacher,
        states,
        samples,
        0.01,
        regions,
        &mut rng,
    )?;
    Ok(json!({
        "problem": p.info.name, "seed": seed, "experts": experts, "iterations": t.iterations,
        "reverse_kl": e.reverse_kl, "forward_kl": e.forward_kl,
        "components": e.components, "components_covered": e.components_covered,
        "converged": t.convergence.as_ref().map(|c| c.converged),
        "score_mismatch": t.convergence.as_ref().map(|c| c.mismatch),
        "score_mismatches": t.convergence.as_ref().map(|c| &c.mismatches),
        "ms_per_iter": t.ms_per_iter, "setup_ms": t.setup_ms,
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
/// summary has the coverage rate (runs covering every component, or every region), the runs
/// that did not converge ([`Vdd::convergence`]), the median and 90th percentile reverse KL with
/// each problem's number of experts and with twice as many, the wall time, the threads, the
/// load before and after, `quick`, the variant, and per extra problem its runs, how many
/// covered everything and its median reverse KL with each number of experts.
pub fn robustness(o: &RobustnessOptions, log: impl Fn(String) + Sync) -> crate::Result<Value> {
    let (n, mut seeds): (usize, &[u64]) = if o.quick { (8, &[0]) } else { (24, &[0, 1, 2]) };
    if !o.seeds.is_empty() {
        seeds = &o.seeds;
    }
    let mut problems = robustness_family(n, 0)?;
    problems.extend(robustness_extras(0)?);
    let jobs: Vec<(usize, u64, usize)> = (0..problems.len())
        .filter(|&p| o.only.is_empty() || o.only.contains(&problems[p].info.index))
        .flat_map(|p| seeds.iter().flat_map(move |&s| [1, 2].map(|m| (p, s, m))))
        .map(|(p, s, m)| (p, s, m * problems[p].info.experts))
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
            "[{k}/{}] {name} seed {seed} experts {experts}: reverse KL {:.4} forward KL {:.4} covered {}/{} {} iterations, converged {} {:.1} ms/iter {}",
            jobs.len(),
            f("reverse_kl"),
            f("forward_kl"),
            r["components_covered"],
            r["components"],
            r["iterations"],
            r["converged"],
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
            .filter(|(_, j)| j.2 == mult * problems[j.0].info.experts)
            .map(|(r, _)| r["reverse_kl"].as_f64().unwrap_or(f64::INFINITY))
            .collect()
    };
    // Per extra problem: its runs' median reverse KL (each expert count) and coverage.
    let extras: Vec<Value> = problems
        .iter()
        .enumerate()
        .filter(|(_, p)| p.info.index >= vdd_core::gmm::family::FIRST_EXTRA)
        .filter_map(|(k, p)| {
            let mine: Vec<(&Value, &(usize, u64, usize))> =
                runs.iter().zip(&jobs).filter(|(_, j)| j.0 == k).collect();
            let median = |mult: usize| {
                let v = mine
                    .iter()
                    .filter(|(_, j)| j.2 == mult * p.info.experts)
                    .map(|(r, _)| r["reverse_kl"].as_f64().unwrap_or(f64::INFINITY))
                    .collect();
                quantile(v, 0.5)
            };
            let covered = mine.iter().filter(|(r, _)| full(r)).count();
            (!mine.is_empty()).then(|| {
                json!({"problem": p.info.name, "runs": mine.len(), "covered": covered,
                       "median_reverse_kl": median(1), "median_reverse_kl_2x": median(2)})
            })
        })
        .collect();
    let summary = json!({
        "runs": runs.len(),
        "coverage_rate": runs.iter().filter(full).count() as f64 / runs.len().max(1) as f64,
        "not_converged": runs.iter().filter(|r| r["converged"] == false).count(),
        "median_reverse_kl": quantile(kl(1), 0.5), "p90_reverse_kl": quantile(kl(1), 0.9),
        "median_reverse_kl_2x": quantile(kl(2), 0.5), "p90_reverse_kl_2x": quantile(kl(2), 0.9),
        "wall_seconds": t0.elapsed().as_secs_f64(), "threads": o.threads,
        "load_start": load_start, "load_end": load(), "quick": o.quick,
        "variant": o.variant.name(), "extras": extras,
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
