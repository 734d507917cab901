//! Accepting a learned teacher on a task whose true action distribution is a known Gaussian
//! mixture (the paper's 2-D toys), and measuring its samplers.
//!
//! A teacher passes ([`Thresholds::check`]) when its samples
//! * cover every mode: the share of samples nearest to each mode mean ([`mode_shares`]) is at
//!   least [`Thresholds::min_mode_share`];
//! * match the true distribution: the MMD² ([`vdd_diffusion::metrics::mmd2_rbf`]) between its samples
//!   and true samples is at most [`Thresholds::max_mmd2_ratio`] times the MMD² of two
//!   independent true samples of the same sizes (the statistic's own noise floor);
//! * come from the right score: the mean cosine between its learned score and the exact
//!   smoothed score of the mixture ([`score_cosine`]) is at least
//!   [`Thresholds::min_score_cosine`].
//!
//! `cargo xtask bench teachers` runs these checks on the circle and rotating toys and prints
//! the sampler tables ([`SamplerSetting`], [`act_batch_latency_us`]); [`report`] builds its
//! sections. The teachers and their sample-quality measures ([`vdd_diffusion::metrics`]) are
//! vdd-diffusion's; what a toy teacher must pass, and how it is measured, is the experiment
//! layer's.
//!
//! ```
//! use vdd_lab::bench::teachers::{Measures, Thresholds};
//!
//! let m = Measures { min_mode_share: 0.1, mmd2: 0.002, mmd2_baseline: 0.001, score_cosine: 0.95 };
//! assert!(Thresholds::default().check(&m, 0.1).is_empty());
//! let collapsed = Measures { min_mode_share: 0.0, ..m };
//! let failures = Thresholds::default().check(&collapsed, 0.1);
//! assert_eq!(failures[0].to_string(), "min mode share 0.000 < 0.06");
//! ```

use std::time::Instant;

pub mod report;

use faer::{Mat, MatRef};
use rand::Rng as _;
use vdd_core::gmm::{Gmm, GmmTeacher};
use vdd_core::{Policy, ScoreModel, Seeds};
use vdd_diffusion::cache::{BesoTeacherConfig, DdpmTeacherConfig, TeachersConfig};
use vdd_diffusion::metrics::{mean_cosine_similarity, mmd2_rbf, mode_shares};
use vdd_diffusion::{
    BesoConfig, DdpmConfig, DiffusionError, DiffusionTeacher, KarrasSampler, NetConfig,
    SigmaDistribution, TeacherKind, TimeSampling, TrainConfig, VpSampler,
};

use crate::Result;

/// The settings of the toy teachers that the acceptance checks accept (`cargo xtask bench
/// teachers`): a residual MLP `width` wide with `blocks` blocks, Adam at `lr` with a warm-up
/// of 200 steps (at most a tenth of the run) and a cosine decay to 2%, gradients clipped to
/// norm 1, EMA of the weights, and log-normal training noise `ln σ ~ N(noise_mean,
/// noise_std²)` for both teachers ([`ToyTeachers::toy`] has the values).
///
/// ```
/// use vdd_lab::bench::teachers::ToyTeachers;
/// let teachers = ToyTeachers::toy().config(4000);
/// assert_eq!(teachers.beso.config.sampling_steps, 24);
/// assert_eq!(teachers.ddpm.train.warmup_steps, 200);
/// ```
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ToyTeachers {
    /// Hidden width of the residual MLP.
    pub width: usize,
    /// Residual blocks.
    pub blocks: usize,
    /// Adam learning rate.
    pub lr: f32,
    /// Batch size.
    pub batch: usize,
    /// EMA decay of the weights.
    pub ema: f32,
    /// Training noise: mean of `ln σ` (DDPM: of its log-normal training times).
    pub noise_mean: f32,
    /// Training noise: std of `ln σ`.
    pub noise_std: f32,
}

impl ToyTeachers {
    /// 64 wide, 2 blocks, lr `1e-2`, batch 1024, EMA 0.995, `ln σ ~ N(−1.6, 1.2²)`.
    pub const fn toy() -> Self {
        Self {
            width: 64,
            blocks: 2,
            lr: 1e-2,
            batch: 1024,
            ema: 0.995,
            noise_mean: -1.6,
            noise_std: 1.2,
        }
    }

    /// The residual MLP of both teachers.
    pub fn net(&self) -> NetConfig {
        NetConfig { hidden_dim: self.width, num_blocks: self.blocks, ..Default::default() }
    }

    /// DDPM: the library defaults (cosine β, N = 16, ancestral sampling with `σ_t² = β_t` over
    /// all 16 steps) with log-normal training times.
    pub fn ddpm(&self) -> DdpmConfig {
        let (mean, std) = (self.noise_mean, self.noise_std);
        DdpmConfig {
            net: self.net(),
            time_sampling: TimeSampling::LogNormal { mean, std },
            ..Default::default()
        }
    }

    /// BESO: the library defaults with Heun over 24 steps (47 network evaluations);
    /// first-order samplers need many more steps for the same fidelity.
    pub fn beso(&self) -> BesoConfig {
        let (mean, std) = (self.noise_mean, self.noise_std);
        BesoConfig {
            net: self.net(),
            training_sigma: SigmaDistribution::LogNormal { mean, std },
            sampler: KarrasSampler::Heun,
            sampling_steps: 24,
            ..Default::default()
        }
    }

    /// Training of `steps` steps (four progress reports).
    pub fn train(&self, steps: u64) -> TrainConfig {
        TrainConfig {
            steps,
            batch_size: self.batch,
            adam: vdd_nn::AdamConfig { lr: self.lr, ..Default::default() },
            warmup_steps: 200.min(steps / 10),
            final_lr_factor: 0.02,
            ema_decay: self.ema,
            grad_clip: Some(1.0),
            log_every: (steps / 4).max(1),
            chunks: 1,
        }
    }

    /// Both teachers' model and training configuration for a run of `steps` steps.
    pub fn config(&self, steps: u64) -> TeachersConfig {
        let train = self.train(steps);
        TeachersConfig {
            beso: BesoTeacherConfig { config: self.beso(), train: train.clone() },
            ddpm: DdpmTeacherConfig { config: self.ddpm(), train },
        }
    }
}

impl Default for ToyTeachers {
    fn default() -> Self {
        Self::toy()
    }
}

/// What [`score_cosine`] found: the mean cosine and the noise level the teacher was queried
/// at (its own convention: `σ` for BESO, the matching time `t` for DDPM).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ScoreCosine {
    /// Mean cosine similarity of the learned and the exact score.
    pub cosine: f32,
    /// The teacher's noise level of the query.
    pub level: f32,
}

/// A Gaussian mixture by its parameters, in raw action units: the true action distribution of
/// a toy task. Unlike a [`Gmm`], it keeps its weights as given, so it can be carried into a
/// teacher's normalised space without rounding.
#[derive(Debug, Clone, PartialEq)]
pub struct MixtureParams {
    /// Positive weights (normalised by [`Gmm::new`]).
    pub weights: Vec<f32>,
    /// Component means.
    pub means: Vec<Vec<f32>>,
    /// Component covariances, row-major `d x d`.
    pub covariances: Vec<Vec<f32>>,
}

impl MixtureParams {
    /// `k` equally weighted isotropic components of standard deviation `std` on a circle of
    /// `radius`, mode `i` at angle `offset + 2πi/k` (the circle toy: `circle(8, 2.0, 0.5, 0.0)`;
    /// the rotating toy at state `s`: `circle(8, 2.0, 0.5, s)`).
    ///
    /// ```
    /// let m = vdd_lab::bench::teachers::MixtureParams::circle(4, 2.0, 0.5, 0.0);
    /// assert_eq!(m.means[0], [2.0, 0.0]);
    /// assert_eq!(m.covariances[0], [0.25, 0.0, 0.0, 0.25]);
    /// assert!(m.to_gmm().is_ok());
    /// ```
    pub fn circle(k: usize, radius: f32, std: f32, offset: f32) -> Self {
        let means = (0..k)
            .map(|i| {
                let a = offset + std::f32::consts::TAU * i as f32 / k as f32;
                vec![radius * a.cos(), radius * a.sin()]
            })
            .collect();
        let var = std * std;
        Self { weights: vec![1.0; k], means, covariances: vec![vec![var, 0.0, 0.0, var]; k] }
    }

    /// The mixture.
    pub fn to_gmm(&self) -> Result<Gmm> {
        Ok(Gmm::new(&self.weights, &self.means, &self.covariances)?)
    }

    /// The mixture of `(a − offset)/scale`: means `(μ − o)/c`, covariances `Σ_ij/(c_i c_j)`.
    pub fn normalized(&self, offset: &[f32], scale: &[f32]) -> Self {
        let d = offset.len();
        let means = self
            .means
            .iter()
            .map(|m| m.iter().enumerate().map(|(j, v)| (v - offset[j]) / scale[j]).collect())
            .collect();
        let covariances = self
            .covariances
            .iter()
            .map(|c| (0..d * d).map(|ij| c[ij] / (scale[ij / d] * scale[ij % d])).collect())
            .collect();
        Self { weights: self.weights.clone(), means, covariances }
    }
}

/// Mean cosine similarity between a learned teacher's score and the exact smoothed score of
/// `exact`, the true action distribution in raw units, at noise level `sigma` of the
/// teacher's normalised action space, on the raw `actions` at the raw `state` (every row).
///
/// The exact mixture is carried into the teacher's normalised space
/// ([`MixtureParams::normalized`]). A DDPM teacher is queried at the time whose noise level is
/// `sigma`; its `x_t = √ᾱ_t·(a + σε)`, so its score at `a` is compared with the exact score at
/// `a/√ᾱ_t` (equal up to a positive factor, which the cosine ignores).
///
/// Errors: dimensions that do not fit the teacher, or a score that fails.
pub fn score_cosine(
    teacher: &mut DiffusionTeacher,
    exact: &MixtureParams,
    state: &[f32],
    actions: MatRef<'_, f32>,
    sigma: f32,
) -> Result<ScoreCosine> {
    let (sn, an) = {
        let (s, a) = teacher.normalizers();
        (s.clone(), a.clone())
    };
    let (n, d) = (actions.nrows(), actions.ncols());
    let exact_dim = exact.means.first().map_or(0, Vec::len);
    if exact_dim != d || an.offset.len() != d || sn.offset.len() != state.len() {
        return Err(DiffusionError::Config(format!(
            "score_cosine: a {exact_dim}-D mixture, {d}-D actions and a {}-D state for a \
             teacher of {} -> {} dimensions",
            state.len(),
            sn.offset.len(),
            an.offset.len()
        ))
        .into());
    }
    let mut exact = GmmTeacher::fixed(exact.normalized(&an.offset, &an.scale).to_gmm()?, 1);
    let a = an.normalize_rows(actions)?;
    // `−(o − x)` is `x − o` (IEEE subtraction is symmetric) and keeps `−o` for `x = 0`.
    let s = Mat::from_fn(n, state.len(), |_, j| -(sn.offset[j] - state[j]) / sn.scale[j]);
    let (level, x_scale) = match teacher {
        DiffusionTeacher::Ddpm(t) => {
            let time = t.schedule().time_for_sigma(sigma);
            (time, 1.0 / t.schedule().alpha_bar(time).sqrt())
        }
        DiffusionTeacher::Beso(_) => (sigma, 1.0),
    };
    let mut learned = Mat::zeros(n, d);
    teacher.score(a.as_ref(), s.as_ref(), &vec![level; n], learned.as_mut())?;
    let y = Mat::from_fn(n, d, |i, j| a[(i, j)] * x_scale);
    let mut truth = Mat::zeros(n, d);
    exact.score(y.as_ref(), Mat::<f32>::zeros(n, 1).as_ref(), &vec![sigma; n], truth.as_mut())?;
    Ok(ScoreCosine { cosine: mean_cosine_similarity(learned.as_ref(), truth.as_ref()), level })
}

/// The circle toy's reference for the acceptance (8 modes on a circle of radius 2, std 0.5,
/// state 0): the exact mixture and two independent true sample sets of the same size (the
/// streams `"fresh-true-a"`, `"fresh-true-b"` of a seed) with their MMD² (RBF, bandwidth 1),
/// the statistic's noise floor.
#[derive(Debug, Clone)]
pub struct CircleReference {
    /// The true distribution.
    pub exact: MixtureParams,
    /// True samples, for MMD².
    pub true_a: Mat<f32>,
    /// Other true samples, for the score check.
    pub true_b: Mat<f32>,
    /// MMD² of `true_a` and `true_b`.
    pub baseline: f64,
}

/// A teacher's [`Measures`] on the circle toy ([`CircleReference::measure`]).
#[derive(Debug, Clone, PartialEq)]
pub struct CircleMeasures {
    /// The measures the thresholds check.
    pub measures: Measures,
    /// The share of samples nearest to each mode.
    pub shares: Vec<f32>,
    /// The teacher's noise level of the score check ([`ScoreCosine::level`]).
    pub level: f32,
}

impl CircleReference {
    /// `n` true samples per set from `seed`.
    pub fn new(n: usize, seed: u64) -> Result<Self> {
        let seeds = Seeds::new(seed);
        let (_, true_a) = GmmTeacher::circle_toy_data(n, &mut seeds.stream("fresh-true-a"))?;
        let (_, true_b) = GmmTeacher::circle_toy_data(n, &mut seeds.stream("fresh-true-b"))?;
        let baseline = mmd2_rbf(true_a.as_ref(), true_b.as_ref(), 1.0);
        Ok(Self { exact: MixtureParams::circle(8, 2.0, 0.5, 0.0), true_a, true_b, baseline })
    }

    /// The smallest mode share, the shares and the MMD² to `true_a` of its first rows of
    /// teacher samples `x` (as many as `true_a` has).
    pub fn compare(&self, x: MatRef<'_, f32>) -> (f32, Vec<f32>, f64) {
        let (share, shares) = mode_shares(x, &self.exact.means);
        let rows = x.nrows().min(self.true_a.nrows());
        (share, shares, mmd2_rbf(x.subrows(0, rows), self.true_a.as_ref(), 1.0))
    }

    /// The measures of `teacher` with its current sampler: `n` samples at state 0 (the policy
    /// stream seeded by `seed`, [`samples_at`]) and the score cosine at `sigma` on `true_b`.
    pub fn measure(
        &self,
        teacher: &mut DiffusionTeacher,
        n: usize,
        sigma: f32,
        seed: u64,
    ) -> Result<CircleMeasures> {
        let x = samples_at(teacher, &[0.0], n, seed)?;
        let (min_mode_share, shares, mmd2) = self.compare(x.as_ref());
        let ScoreCosine { cosine, level } =
            score_cosine(teacher, &self.exact, &[0.0], self.true_b.as_ref(), sigma)?;
        let measures =
            Measures { min_mode_share, mmd2, mmd2_baseline: self.baseline, score_cosine: cosine };
        Ok(CircleMeasures { measures, shares, level })
    }
}

/// The rotating toy of the acceptance: mode `k` at angle `s + 2πk/8` on the circle of radius
/// 2, std 0.5, for the scalar state `s`.
pub struct RotatingReference(GmmTeacher);

impl RotatingReference {
    /// The mixture.
    pub fn new() -> Result<Self> {
        Ok(Self(GmmTeacher::rotating_toy(8, 2.0, 0.5)?))
    }

    /// `n` training pairs from `seed`: states uniform in `[0, 2π)` (stream `"rot-states"`),
    /// actions from the mixture (stream `"rot-data"`).
    pub fn data(&mut self, n: usize, seed: u64) -> Result<(Mat<f32>, Mat<f32>)> {
        let mut rng = Seeds::new(seed).stream("rot-states");
        let states = Mat::from_fn(n, 1, |_, _| rng.random_range(0.0..std::f32::consts::TAU));
        let actions = self.0.sample(states.as_ref(), &mut Seeds::new(seed).stream("rot-data"))?;
        Ok((states, actions))
    }

    /// The smallest mode share of 2000 samples of `teacher` at state `s` (policy stream seeded
    /// by `seed + index`) and their first 1000 rows' MMD² to 1000 true samples (stream
    /// `"rot-true"` of `seed`, indexed by `index`).
    pub fn check_at(
        &mut self,
        teacher: &mut DiffusionTeacher,
        s: f32,
        index: u64,
        seed: u64,
    ) -> Result<(f32, f64)> {
        let obs = Mat::from_fn(1000, 1, |_, _| s);
        let mut rng = Seeds::new(seed).stream_indexed("rot-true", index);
        let truth = self.0.sample(obs.as_ref(), &mut rng)?;
        let x = samples_at(teacher, &[s], 2000, seed + index)?;
        let (share, _) = mode_shares(x.as_ref(), &MixtureParams::circle(8, 2.0, 0.5, s).means);
        Ok((share, mmd2_rbf(x.as_ref().subrows(0, 1000), truth.as_ref(), 1.0)))
    }
}

/// The measures a teacher is accepted on (see the [module docs](self)).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Measures {
    /// The smallest share of samples nearest to one mode ([`mode_shares`]).
    pub min_mode_share: f32,
    /// MMD² between teacher samples and true samples.
    pub mmd2: f64,
    /// MMD² between two independent true samples of the same sizes.
    pub mmd2_baseline: f64,
    /// Mean cosine of the learned and the exact score ([`score_cosine`]).
    pub score_cosine: f32,
}

/// The acceptance thresholds; the defaults are the toy teachers' (6% per mode of 8, 3× the
/// MMD² noise floor, cosine 0.9).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Thresholds {
    /// Least share of samples per mode.
    pub min_mode_share: f32,
    /// Largest MMD² as a multiple of the true-vs-true baseline.
    pub max_mmd2_ratio: f64,
    /// Least mean score cosine.
    pub min_score_cosine: f32,
}

impl Default for Thresholds {
    fn default() -> Self {
        Self { min_mode_share: 0.06, max_mmd2_ratio: 3.0, min_score_cosine: 0.9 }
    }
}

/// A failed acceptance check; its `Display` states the measure and the threshold.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Failure {
    /// A mode is covered by too few samples.
    ModeShare {
        /// The smallest share.
        share: f32,
        /// The threshold.
        min: f32,
    },
    /// The samples are too far from the true distribution.
    Mmd2 {
        /// The teacher's MMD².
        mmd2: f64,
        /// The allowed multiple of the baseline.
        ratio: f64,
        /// The true-vs-true MMD².
        baseline: f64,
    },
    /// The learned score points elsewhere than the exact one.
    ScoreCosine {
        /// The mean cosine.
        cosine: f32,
        /// The threshold.
        min: f32,
        /// The noise level of the check.
        sigma: f32,
    },
}

impl std::fmt::Display for Failure {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::ModeShare { share, min } => write!(f, "min mode share {share:.3} < {min}"),
            Self::Mmd2 { mmd2, ratio, baseline } => {
                write!(f, "MMD² {mmd2:.5} > {ratio} x {baseline:.5}")
            }
            Self::ScoreCosine { cosine, min, sigma } => {
                write!(f, "score cosine {cosine:.4} < {min} at σ = {sigma}")
            }
        }
    }
}

impl Thresholds {
    /// Whether a smallest mode share passes.
    pub fn covers(&self, min_mode_share: f32) -> bool {
        min_mode_share >= self.min_mode_share
    }

    /// The largest MMD² that passes against `baseline`.
    pub fn mmd2_bar(&self, baseline: f64) -> f64 {
        self.max_mmd2_ratio * baseline
    }

    /// The failed checks of `m` (empty: the teacher passes); `sigma` is the noise level of the
    /// score check, for the message.
    pub fn check(&self, m: &Measures, sigma: f32) -> Vec<Failure> {
        let mut failures = Vec::new();
        if !self.covers(m.min_mode_share) {
            failures.push(Failure::ModeShare { share: m.min_mode_share, min: self.min_mode_share });
        }
        // A NaN measure fails.
        if m.mmd2.is_nan() || m.mmd2 > self.mmd2_bar(m.mmd2_baseline) {
            failures.push(Failure::Mmd2 {
                mmd2: m.mmd2,
                ratio: self.max_mmd2_ratio,
                baseline: m.mmd2_baseline,
            });
        }
        if m.score_cosine.is_nan() || m.score_cosine < self.min_score_cosine {
            failures.push(Failure::ScoreCosine {
                cosine: m.score_cosine,
                min: self.min_score_cosine,
                sigma,
            });
        }
        failures
    }
}

/// A sampler of either learned teacher with its number of steps.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum SamplerSetting {
    /// A DDPM (variance-preserving) sampler.
    Vp(VpSampler, usize),
    /// A BESO (variance-exploding, Karras) sampler.
    Ve(KarrasSampler, usize),
}

impl SamplerSetting {
    /// The teacher's current sampler.
    pub fn of(teacher: &DiffusionTeacher) -> Self {
        match teacher {
            DiffusionTeacher::Ddpm(d) => Self::Vp(d.sampler().0, d.sampler().1),
            DiffusionTeacher::Beso(b) => Self::Ve(b.sampler().0, b.sampler().1),
        }
    }

    /// Every sampler of a teacher of `kind`, with `steps` steps.
    pub fn all(kind: TeacherKind, steps: usize) -> Vec<Self> {
        match kind {
            TeacherKind::Ddpm => [VpSampler::AncestralLarge, VpSampler::Ancestral, VpSampler::Ddim]
                .map(|v| Self::Vp(v, steps))
                .to_vec(),
            TeacherKind::Beso => [
                KarrasSampler::Euler,
                KarrasSampler::Heun,
                KarrasSampler::EulerAncestral,
                KarrasSampler::Ddim,
            ]
            .map(|v| Self::Ve(v, steps))
            .to_vec(),
        }
    }

    /// Sets this sampler on `teacher`; returns the previous one. An error for a sampler of the
    /// other kind of teacher, or steps the teacher does not support.
    pub fn apply(self, teacher: &mut DiffusionTeacher) -> Result<Self> {
        let old = Self::of(teacher);
        match (teacher, self) {
            (DiffusionTeacher::Ddpm(d), Self::Vp(v, k)) => d.set_sampler(v, k)?,
            (DiffusionTeacher::Beso(b), Self::Ve(v, k)) => b.set_sampler(v, k)?,
            _ => {
                return Err(DiffusionError::Config(format!(
                    "sampler {self:?} is of the other teacher kind"
                ))
                .into());
            }
        }
        Ok(old)
    }

    /// The sampler's name (`Heun`, `Ddim`, ...).
    pub fn name(self) -> String {
        match self {
            Self::Vp(v, _) => format!("{v:?}"),
            Self::Ve(v, _) => format!("{v:?}"),
        }
    }

    /// Name and steps (`Heun 24`).
    pub fn label(self) -> String {
        format!("{} {}", self.name(), self.steps())
    }

    /// Sampling steps.
    pub fn steps(self) -> usize {
        match self {
            Self::Vp(_, k) | Self::Ve(_, k) => k,
        }
    }

    /// The same sampler with `k` steps.
    pub fn with_steps(self, k: usize) -> Self {
        match self {
            Self::Vp(v, _) => Self::Vp(v, k),
            Self::Ve(v, _) => Self::Ve(v, k),
        }
    }

    /// Network evaluations per sample.
    pub fn nfe(self) -> usize {
        match self {
            Self::Vp(_, k) => k,
            Self::Ve(v, k) => v.evaluations(k),
        }
    }
}

/// `n` actions of `policy` at the raw observation `obs` (every row), with the policy seeded by
/// `seed` first.
pub fn samples_at<P: Policy + ?Sized>(
    policy: &mut P,
    obs: &[f32],
    n: usize,
    seed: u64,
) -> Result<Mat<f32>> {
    policy.seed(seed);
    let obs = Mat::from_fn(n, obs.len(), |_, j| obs[j]);
    let mut out = Mat::<f32>::zeros(n, policy.action_dim());
    policy.act_batch(obs.as_ref(), out.as_mut())?;
    Ok(out)
}

/// Wall-clock µs per action of `policy.act_batch` on `n` all-zero observations: three untimed
/// calls, then the best of 5 rounds of at least `min_secs / 5` (and 2 calls) each; the best
/// round is the one least disturbed by other jobs. Single-threaded.
pub fn act_batch_latency_us<P: Policy + ?Sized>(
    policy: &mut P,
    n: usize,
    min_secs: f64,
) -> Result<f64> {
    let obs = Mat::<f32>::zeros(n, policy.obs_dim());
    let mut out = Mat::<f32>::zeros(n, policy.action_dim());
    for _ in 0..3 {
        policy.act_batch(obs.as_ref(), out.as_mut())?;
    }
    let mut best = f64::INFINITY;
    for _ in 0..5 {
        let (start, mut calls) = (Instant::now(), 0u32);
        while calls < 2 || start.elapsed().as_secs_f64() < min_secs / 5.0 {
            policy.act_batch(obs.as_ref(), out.as_mut())?;
            calls += 1;
        }
        best = best.min(start.elapsed().as_secs_f64() / f64::from(calls));
    }
    Ok(best * 1e6 / n as f64)
}
