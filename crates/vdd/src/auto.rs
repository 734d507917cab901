//! Robust defaults: a distillation set up from the teacher itself ([`AutoPlan`],
//! [`VddConfig::for_teacher`], [`Vdd::auto`]).
//!
//! [`VddConfig::toy`] and [`MoeConfig::toy`] are the paper's toy settings: they assume actions
//! of unit scale near the origin and a handful of well-separated modes. [`AutoPlan::inspect`]
//! looks at the teacher instead and picks:
//!
//! * **What it learns from.** Actions of the teacher: its own samples
//!   ([`ScoreModel::sample_actions`]) at up to 256 of the data's states; the dataset's actions
//!   when it cannot sample; otherwise samples of an annealed reverse diffusion driven by its
//!   score (VE teachers only, [`score_sampling`]). A teacher seen through its score alone
//!   cannot give the gating step fresh actions, so the gating then trains on all of those
//!   score-sampled (state, action) pairs ([`AutoPlan::gating_pairs`], 8192 by default) rather
//!   than on one action per data state, whose weights could only be multiples of one over the
//!   number of states; [`AutoPlan::notes`] says so.
//! * **The run's length.** [`BASE_ITERATIONS`] (600) for a teacher whose components and
//!   weights do not depend on the state beyond a shared linear motion, growing linearly with
//!   [`AutoPlan::state_dependence`] (the share of the variance of the fitted components'
//!   responsibilities that the state explains) up to [`MAX_AUTO_ITERATIONS`] (2400) at
//!   [`FULL_STATE_DEPENDENCE`]: a student whose gating and experts must learn how the state
//!   moves and reweights the modes needs more steps than one that starts on them
//!   ([`auto_iterations`]; [`AutoOptions::iterations`] overrides it).
//! * **The student's space.** Observation and action normalisers (mean and standard deviation
//!   per dimension of the data's states and of those actions), so the networks see unit-scale
//!   inputs and outputs whatever the units and offsets of the problem.
//! * **Noise levels.** The level is annealed geometrically from a tenth of the actions' spread
//!   (RMS standard deviation, in the teacher's space; half of it with the official
//!   initialisation, [`START_NOISE_FROM_TEACHER`], [`START_NOISE_OFFICIAL`]) down to the
//!   smallest level the teacher reports as trustworthy ([`ScoreModel::noise_range`]; 0 for
//!   an exact score, where the end is 10⁻³ of the spread), over the first
//!   [`ANNEAL_ITERATIONS`] (420) iterations or 70 % of a shorter run, then held. Large levels
//!   smooth the teacher so that experts slide into the basins they start in rather than onto
//!   the nearest bump; small ones give the exact target at the end; too large ones merge the
//!   teacher's modes, and experts that follow them there can end between modes. The anneal
//!   does not stretch with the run: a longer run spends its extra iterations at the end
//!   level, where it refines, rather than longer at large levels. Teachers that count noise
//!   in diffusion time ([`NoiseConvention::Time`]) keep a fixed level, the smallest they
//!   report (or 0).
//! * **Initialisation from the teacher** ([`InitKind::FromTeacher`]). The actions are
//!   regressed linearly on the states (the part of the modes' motion all modes share), and a
//!   mixture of as many full-covariance Gaussians as there are experts is fitted to the
//!   residuals in the student's space (k-means++, then EM; empty components re-seeded at the
//!   worst-explained sample; the most likely of 4 such fits). Each expert starts as one
//!   fitted component: its mean head outputs the component's mean plus the shared linear
//!   motion (a ridge fit of the output layer on the trunk's features), its scale head the
//!   component's Cholesky factor; the learned gating starts at the fitted weights.
//!   [`InitKind::Official`] keeps the official initialisation instead.
//! * **Experts and gating that keep components.** Full-covariance experts and a learned
//!   gating: a uniform gating cannot give a 5 % mode 5 % of the actions, and with twice as many
//!   experts as modes it must split them evenly. The gating is trained on the teacher's
//!   samples' responsibilities (the trainer's gating step) and starts from the fitted weights,
//!   so no expert starts without mass; EM re-seeds components that lose their samples before
//!   training starts.
//! * **The rest.** Objectives weighted by the gating (official), 32 states and 32 samples per
//!   expert per iteration, Adam `10⁻³` decaying linearly to 0 over the run (every schedule
//!   follows `iterations`), gating Adam `10⁻³`.
//!
//! Whether the run then converged is the trainer's verdict ([`Vdd::convergence`], and
//! [`crate::IterationMetrics::converged`] on the last iteration), from the student's score
//! mismatch with the teacher measured at eighths of the run.
//!
//! ```
//! use vdd::faer::Mat;
//! use vdd::gmm::GmmTeacher;
//! use vdd::{AutoOptions, DistillData, Trainer, Vdd};
//!
//! // Eight modes on a circle of radius 200 around (1000, −50), std 50: far from unit scale.
//! let gmm = vdd::gmm::Gmm::circle(8, 200.0, 50.0, 0.0)?;
//! let means: Vec<Vec<f32>> = (0..8).map(|k| gmm.mean(k).iter().zip([1000.0, -50.0]).map(|(m, o)| m + o).collect()).collect();
//! let teacher = GmmTeacher::isotropic(&[1.0; 8], &means, 50.0)?;
//! let data = DistillData::from_states(Mat::zeros(64, 1))?;
//! let options = AutoOptions { iterations: Some(100), ..AutoOptions::new(8, 0) };
//! let mut vdd = Vdd::auto(teacher, data, &options)?;
//! vdd.train(|_| {})?;
//! let verdict = vdd.convergence().expect("the run is finished");
//! println!("score mismatch {:.4}, converged {}", verdict.mismatch, verdict.converged);
//! let student = vdd.finish()?;
//! assert_eq!(student.num_experts(), 8);
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

mod fit;

use faer::{Mat, MatRef};
use serde::{Deserialize, Serialize};
use vdd_core::{
    Affine, CoreError, NoiseConvention, NoiseSchedule, ScoreModel, Seeds, check_finite,
};
use vdd_moe::{ExpertFamily, ExpertKind, GatingKind, Moe, MoeConfig};
use vdd_nn::init::Init;
use vdd_nn::{AdamConfig, LrSchedule};

use crate::config::{ExpertWeighting, VddConfig};
use crate::error::VddError;
use crate::trainer::{DistillData, Vdd};
use fit::Fitted;

/// Iterations [`AutoPlan::inspect`] picks for a teacher that ignores the state (the paper's
/// toy run).
pub const BASE_ITERATIONS: usize = 600;

/// Most iterations [`AutoPlan::inspect`] picks: for a teacher whose state decides the
/// component ([`AutoPlan::state_dependence`] at or above [`FULL_STATE_DEPENDENCE`]).
pub const MAX_AUTO_ITERATIONS: usize = 2400;

/// The state dependence at which [`AutoPlan::inspect`] picks [`MAX_AUTO_ITERATIONS`].
pub const FULL_STATE_DEPENDENCE: f32 = 0.15;

/// Iterations over which the noise level is annealed (or 70 % of a shorter run); the rest of
/// the run trains at the end level.
pub const ANNEAL_ITERATIONS: usize = 420;

/// The start of the noise anneal, as a fraction of the actions' spread, for experts started
/// on the teacher's modes ([`InitKind::FromTeacher`]): enough to smooth the teacher's
/// small-scale bumps, not enough to merge its modes.
pub const START_NOISE_FROM_TEACHER: f32 = 0.1;

/// The start of the noise anneal for the official initialisation ([`InitKind::Official`]),
/// whose experts all start near the centre: half the spread, which smooths the teacher
/// into one basin that the experts then follow apart as the level falls.
pub const START_NOISE_OFFICIAL: f32 = 0.5;

/// Fewest dataset actions below which [`AutoPlan::notes`] warns that the learned gating
/// trains on too few actions.
pub const MIN_GATING_ACTIONS: usize = 1024;

/// The run length [`AutoPlan::inspect`] picks for a teacher of state dependence `dependence`
/// (see [`AutoPlan::state_dependence`]): from [`BASE_ITERATIONS`] at 0, linearly, to
/// [`MAX_AUTO_ITERATIONS`] at [`FULL_STATE_DEPENDENCE`] and above, rounded to hundreds.
///
/// ```
/// use vdd::auto::{BASE_ITERATIONS, MAX_AUTO_ITERATIONS, auto_iterations};
/// assert_eq!(auto_iterations(0.0), BASE_ITERATIONS);
/// assert_eq!(auto_iterations(1.0), MAX_AUTO_ITERATIONS);
/// assert_eq!(auto_iterations(0.05), 1200);
/// ```
pub fn auto_iterations(dependence: f32) -> usize {
    let f = f64::from(dependence / FULL_STATE_DEPENDENCE).clamp(0.0, 1.0);
    let span = (MAX_AUTO_ITERATIONS - BASE_ITERATIONS) as f64;
    BASE_ITERATIONS + ((f * span / 100.0).round() as usize) * 100
}

/// Re-initialises a fresh `student` as the official VDD code does ([`InitKind::Official`]):
/// every linear layer orthogonal with gain 0.01, the mean head's output weights zero (so each
/// expert's mean starts at its bias, `U[−w, w]` from [`MoeConfig::mean_bias_init`]), the scale
/// outputs' biases zero. Draws from `Seeds::new(seed).stream("auto-init")`.
///
/// ```
/// use vdd::{Moe, MoeConfig, init_official};
/// let mut student = Moe::from_config(MoeConfig::toy(1, 2, 4), 0)?;
/// init_official(&mut student, 0)?;
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
pub fn init_official(student: &mut Moe, seed: u64) -> Result<(), VddError> {
    let mut rng = Seeds::new(seed).stream("auto-init");
    let family = *student.expert();
    let d = student.config().action_dim;
    let r = vdd_core::Expert::raw_dim(&family);
    for (net, experts) in student.expert_trunks_mut() {
        net.init_weights(Init::Orthogonal { gain: 0.01 }, &mut rng)?;
        let out = net.output_layer_mut();
        let cols = out.weight.value.len() / out.bias.value.len();
        for e in 0..experts.len() {
            for j in 0..d {
                let row = e * r + j;
                out.weight.value[row * cols..(row + 1) * cols].fill(0.0);
            }
            for k in d..r {
                out.bias.value[e * r + k] = 0.0;
            }
        }
    }
    if let Some(g) = student.gating_network_mut() {
        g.init_weights(Init::Orthogonal { gain: 0.01 }, &mut rng)?;
    }
    Ok(())
}

/// How the student's networks are initialised.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum InitKind {
    /// Each expert starts as one component of a mixture fitted to the teacher's actions (see
    /// the module docs).
    #[default]
    FromTeacher,
    /// Every linear layer orthogonal with gain 0.01, the mean head's output weights zero, mean
    /// biases `U[−w, w]` ([`MoeConfig::mean_bias_init`]), scales at `init_std`.
    Official,
}

/// Where the actions that [`AutoPlan`] learned from came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum SampleSource {
    /// The teacher's own sampler.
    Teacher,
    /// The dataset's actions.
    Dataset,
    /// Annealed reverse diffusion with the teacher's score.
    ScoreSampling,
}

/// What a user chooses for [`AutoPlan::inspect`]; everything else is derived from the teacher.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct AutoOptions {
    /// Number of experts (as many as the teacher has modes, or more).
    pub num_experts: usize,
    /// Run length; every schedule follows it. `None` (the default): the plan picks it from
    /// the teacher's state dependence ([`AutoPlan::state_dependence`]), from
    /// [`BASE_ITERATIONS`] for a teacher that ignores the state up to [`MAX_AUTO_ITERATIONS`].
    pub iterations: Option<usize>,
    /// Root seed of the run (student initialisation included).
    pub seed: u64,
    /// How the networks start.
    pub init: InitKind,
    /// Expert family (full covariance by default).
    pub expert_kind: ExpertKind,
    /// Gating (learned by default).
    pub gating: GatingKind,
    /// Teacher actions to inspect.
    pub samples: usize,
    /// Annealing starts at this fraction of the actions' spread. `None` (the default): picked
    /// by the initialisation, [`START_NOISE_FROM_TEACHER`] for experts started on the teacher's
    /// modes, [`START_NOISE_OFFICIAL`] for the official start, which the noise must first carry
    /// to the modes.
    pub start_noise_factor: Option<f32>,
}

impl AutoOptions {
    /// The defaults for `num_experts` experts and seed `seed`: the run length picked from the
    /// teacher, initialisation from the teacher, full-covariance experts, learned gating, 8192
    /// teacher actions, annealing from the initialisation's start level.
    ///
    /// ```
    /// use vdd::AutoOptions;
    /// let options = AutoOptions::new(8, 0);
    /// assert_eq!(options.iterations, None); // picked by the plan
    /// let fixed = AutoOptions { iterations: Some(300), ..AutoOptions::new(8, 0) };
    /// assert_eq!(fixed.num_experts, 8);
    /// ```
    pub fn new(num_experts: usize, seed: u64) -> Self {
        Self {
            num_experts,
            iterations: None,
            seed,
            init: InitKind::FromTeacher,
            expert_kind: ExpertKind::Full,
            gating: GatingKind::Learned,
            samples: 8192,
            start_noise_factor: None,
        }
    }
}

/// What [`AutoPlan::inspect`] found and picked: the trainer's and the student's
/// configurations, the student's normalisers and its initial experts.
#[derive(Debug, Clone)]
pub struct AutoPlan {
    /// The trainer's configuration.
    pub vdd: VddConfig,
    /// The student's architecture.
    pub student: MoeConfig,
    /// The student's observation normaliser.
    pub state_normalizer: Affine,
    /// The student's action normaliser.
    pub action_normalizer: Affine,
    /// Where the inspected actions came from.
    pub source: SampleSource,
    /// RMS standard deviation of the actions in the teacher's space.
    pub spread: f32,
    /// The teacher's reported noise range.
    pub noise_range: Option<(f32, f32)>,
    /// How much the state decides which component an action belongs to, in `[0, 1]`: the
    /// share of the variance of the fitted mixture's responsibilities that the state explains
    /// (the covariance of the responsibilities of two actions at one state over their
    /// variance). 0: neither the components nor their weights depend on the state beyond the
    /// shared linear motion; 1: the state decides the component. The run length grows with
    /// it ([`auto_iterations`]).
    pub state_dependence: f32,
    /// (State, action) pairs for the gating step when the teacher cannot sample and the data
    /// has no actions (raw): every score-sampled action at its state, so that the gating
    /// learns the weights from as many actions as the plan inspected, not from one per data
    /// state ([`DistillData::with_gating_pairs`]).
    pub gating_pairs: Option<(Mat<f32>, Mat<f32>)>,
    /// What a user should know about this plan (each a sentence), e.g. that the teacher was
    /// sampled through its score.
    pub notes: Vec<String>,
    init: InitKind,
    fitted: Fitted,
    /// Shared linear motion `a ≈ c + W s` in the student's space (`d x d_s`, row-major).
    motion: Vec<f64>,
    /// The inspected states in the student's space (for the output-layer fit).
    states_n: Mat<f32>,
}

impl VddConfig {
    /// The trainer's configuration [`AutoPlan::inspect`] picks for `teacher` on raw `states`
    /// with [`AutoOptions::new`]`(num_experts, seed)`. Use [`Vdd::auto`] to get the student's
    /// normalisers and initialisation too.
    pub fn for_teacher<S: ScoreModel>(
        teacher: &mut S,
        states: MatRef<'_, f32>,
        num_experts: usize,
        seed: u64,
    ) -> Result<Self, VddError> {
        let data = DistillData::from_states(states.to_owned())?;
        Ok(AutoPlan::inspect(teacher, &data, &AutoOptions::new(num_experts, seed))?.vdd)
    }
}

impl<S: ScoreModel> Vdd<S, ExpertFamily> {
    /// A run set up from the teacher ([`AutoPlan::inspect`] with `options`), its student
    /// built, normalised and initialised accordingly ([`AutoPlan::build_student`]).
    pub fn auto(
        mut teacher: S,
        data: DistillData,
        options: &AutoOptions,
    ) -> Result<Self, VddError> {
        let plan = AutoPlan::inspect(&mut teacher, &data, options)?;
        Self::from_plan(&plan, teacher, data)
    }

    /// A run of `plan`. When the teacher cannot sample and the data has neither actions nor
    /// gating pairs, the gating step learns from the plan's score-sampled pairs
    /// ([`AutoPlan::gating_pairs`]).
    pub fn from_plan(plan: &AutoPlan, teacher: S, mut data: DistillData) -> Result<Self, VddError> {
        let student = plan.build_student()?;
        if data.actions.is_none() && data.gating.is_none() {
            if let Some((states, actions)) = &plan.gating_pairs {
                data = data.with_gating_pairs(states.clone(), actions.clone())?;
            }
        }
        Self::new(plan.vdd.clone(), teacher, student, data)
    }
}

fn stats(m: MatRef<'_, f32>) -> (Vec<f32>, Vec<f32>) {
    let n = m.nrows().max(1) as f64;
    (0..m.ncols())
        .map(|j| {
            let mean = (0..m.nrows()).map(|i| f64::from(m[(i, j)])).sum::<f64>() / n;
            let var =
                (0..m.nrows()).map(|i| (f64::from(m[(i, j)]) - mean).powi(2)).sum::<f64>() / n;
            (mean as f32, var.sqrt() as f32)
        })
        .unzip()
}

/// Mean and standard deviation per column as a normaliser (a constant column keeps scale 1
/// and the offset).
fn normalizer(m: MatRef<'_, f32>) -> Result<Affine, CoreError> {
    let (mean, std) = stats(m);
    let scale = std
        .iter()
        .zip(&mean)
        .map(|(s, mu)| if *s > 1e-6 * mu.abs().max(1e-12) && *s > 0.0 { *s } else { 1.0 })
        .collect();
    Affine::new(mean, scale)
}

fn map_rows(m: MatRef<'_, f32>, a: &Affine, forward: bool) -> Mat<f32> {
    Mat::from_fn(m.nrows(), m.ncols(), |i, j| {
        if forward {
            (m[(i, j)] - a.offset[j]) / a.scale[j]
        } else {
            m[(i, j)] * a.scale[j] + a.offset[j]
        }
    })
}

impl AutoPlan {
    /// Inspects `teacher` on `data` and picks everything (see the module docs).
    pub fn inspect<S: ScoreModel>(
        teacher: &mut S,
        data: &DistillData,
        options: &AutoOptions,
    ) -> Result<Self, VddError> {
        let (ds, d) = (teacher.state_dim(), teacher.action_dim());
        vdd_core::check_len("data state columns", data.states.ncols(), ds)?;
        if options.num_experts == 0 || options.iterations == Some(0) || options.samples == 0 {
            return Err(CoreError::Config(
                "num_experts, iterations and samples must be positive".into(),
            )
            .into());
        }
        let seeds = Seeds::new(options.seed).child("auto");
        let space = data.teacher_space.clone();
        // Up to 256 of the data's states, evenly spaced, each repeated.
        let n_data = data.states.nrows();
        let n_states = n_data.min(256);
        let per = options.samples.div_ceil(n_states);
        let idx: Vec<usize> = (0..n_states * per).map(|r| (r / per) * n_data / n_states).collect();
        let states = Mat::from_fn(idx.len(), ds, |r, j| data.states[(idx[r], j)]);
        let to_teacher_states = |m: MatRef<'_, f32>| match &space.states {
            Some(a) => map_rows(m, a, true),
            None => m.to_owned(),
        };
        let from_teacher_actions = |m: Mat<f32>| match &space.actions {
            Some(a) => map_rows(m.as_ref(), a, false),
            None => m,
        };
        let t_states = to_teacher_states(states.as_ref());
        let mut rng = seeds.stream("samples");
        let mut out = Mat::zeros(idx.len(), d);
        let noise_range = teacher.noise_range();
        let (source, states, actions) =
            match teacher.sample_actions(t_states.as_ref(), &mut rng, out.as_mut()) {
                Ok(()) => (SampleSource::Teacher, states, from_teacher_actions(out)),
                Err(CoreError::Unsupported(_)) => match &data.actions {
                    Some(a) => (SampleSource::Dataset, data.states.clone(), a.clone()),
                    None => {
                        let sampled =
                            score_sampling(teacher, t_states.as_ref(), noise_range, &mut rng)?;
                        (SampleSource::ScoreSampling, states, from_teacher_actions(sampled))
                    }
                },
                Err(e) => return Err(e.into()),
            };
        check_finite("teacher actions", actions.as_ref())?;
        let mut notes = Vec::new();
        let gating_pairs = match source {
            SampleSource::ScoreSampling => {
                notes.push(format!(
                    "the teacher cannot sample (ScoreModel::sample_actions) and the data has no \
                     actions: {} actions at {n_states} states were drawn by annealed reverse \
                     diffusion through its score, and the learned gating trains on them; a \
                     sampler, if the teacher has one, gives the gating fresh actions at every step",
                    actions.nrows()
                ));
                Some((states.clone(), actions.clone()))
            }
            SampleSource::Dataset if n_data < MIN_GATING_ACTIONS => {
                notes.push(format!(
                    "the learned gating trains on the dataset's {n_data} actions, one per state: \
                     with so few, its weights can only be near multiples of 1/{n_data}; give more \
                     states or a teacher that samples"
                ));
                None
            }
            _ => None,
        };

        // The student's space.
        let state_normalizer = normalizer(data.states.as_ref())?;
        let action_normalizer = normalizer(actions.as_ref())?;
        let states_n = map_rows(states.as_ref(), &state_normalizer, true);
        let actions_n = map_rows(actions.as_ref(), &action_normalizer, true);

        // The spread in the teacher's space.
        let t_actions = match &space.actions {
            Some(a) => map_rows(actions.as_ref(), a, true),
            None => actions.clone(),
        };
        let (_, std) = stats(t_actions.as_ref());
        let spread = (std.iter().map(|s| s * s).sum::<f32>() / d as f32).sqrt().max(1e-12);
        // The shared linear motion and the mixture of the residuals.
        let n = actions_n.nrows();
        let x: Vec<f64> = (0..n)
            .flat_map(|i| {
                std::iter::once(1.0)
                    .chain((0..ds).map(|j| f64::from(states_n[(i, j)])))
                    .collect::<Vec<_>>()
            })
            .collect();
        let y: Vec<f64> = (0..n)
            .flat_map(|i| (0..d).map(|j| f64::from(actions_n[(i, j)])).collect::<Vec<_>>())
            .collect();
        let beta = fit::least_squares(&x, &y, n, ds + 1, d, 1e-6 * n as f64)
            .unwrap_or_else(|| vec![0.0; (ds + 1) * d]);
        // motion[j * ds + t] = ∂a_j/∂s_t.
        let motion: Vec<f64> = (0..d * ds).map(|k| beta[(1 + k % ds) * d + k / ds]).collect();
        let residuals: Vec<f64> = (0..n)
            .flat_map(|i| {
                (0..d)
                    .map(|j| {
                        y[i * d + j]
                            - (0..ds)
                                .map(|t| motion[j * ds + t] * x[i * (ds + 1) + 1 + t])
                                .sum::<f64>()
                    })
                    .collect::<Vec<_>>()
            })
            .collect();
        let mut fit_rng = seeds.stream("fit");
        let fitted =
            fit::fit_best(&residuals, n, d, options.num_experts, 30, 1e-6, 4, &mut fit_rng);
        let resp = fit::responsibilities(&residuals, n, d, &fitted);
        let state_dependence =
            fit::state_dependence(&resp, options.num_experts, states_n.as_ref()) as f32;
        let iterations = options.iterations.unwrap_or_else(|| auto_iterations(state_dependence));
        // The noise schedule: annealed over the first ANNEAL_ITERATIONS (at most 70 % of the
        // run), so that a longer run refines at the end level rather than drifting longer at
        // large ones.
        let (noise, anneal) = match teacher.noise_convention() {
            NoiseConvention::Time => {
                (NoiseSchedule::Fixed { level: noise_range.map_or(0.0, |r| r.0) }, None)
            }
            NoiseConvention::Sigma => {
                let end = noise_range.map_or(0.0, |r| r.0).max(1e-3 * spread);
                let factor = options.start_noise_factor.unwrap_or(match options.init {
                    InitKind::FromTeacher => START_NOISE_FROM_TEACHER,
                    InitKind::Official => START_NOISE_OFFICIAL,
                });
                let start = (factor * spread).max(end);
                let until = (ANNEAL_ITERATIONS as f32 / iterations as f32).min(0.7);
                (NoiseSchedule::Annealed { start, end }, Some(until))
            }
        };

        let student = MoeConfig {
            expert_kind: options.expert_kind,
            gating: options.gating,
            ..MoeConfig::toy(ds, d, options.num_experts)
        };
        let adam = AdamConfig { lr: 1e-3, ..AdamConfig::default() };
        let vdd = VddConfig {
            iterations,
            batch_size: 32,
            vi_samples: 32,
            noise,
            noise_anneal_until: anneal,
            expert_weighting: ExpertWeighting::Gating,
            expert_optimizer: adam,
            expert_lr_schedule: LrSchedule::LinearDecay { final_factor: 0.0 },
            gating_optimizer: adam,
            gating_lr_schedule: LrSchedule::LinearDecay { final_factor: 0.0 },
            seed: options.seed,
            ..VddConfig::toy()
        };
        Ok(Self {
            vdd,
            student,
            state_normalizer,
            action_normalizer,
            source,
            spread,
            noise_range,
            state_dependence,
            gating_pairs,
            notes,
            init: options.init,
            fitted,
            motion,
            states_n: thin(states_n, per),
        })
    }

    /// What was picked and why, on one line, then the plan's [`AutoPlan::notes`] one a line.
    pub fn summary(&self) -> String {
        let mut out = format!(
            "actions from {:?}; spread {:.4e} (teacher space); state dependence {:.3}, {} \
             iterations; noise {:?} until {:?} of the run (teacher range {:?}); {} {:?} experts, \
             {:?} gating, init {:?}; fitted weights {:?}",
            self.source,
            self.spread,
            self.state_dependence,
            self.vdd.iterations,
            self.vdd.noise,
            self.vdd.noise_anneal_until,
            self.noise_range,
            self.student.num_experts,
            self.student.expert_kind,
            self.student.gating,
            self.init,
            self.fitted.weights.iter().map(|w| (w * 1000.0).round() / 1000.0).collect::<Vec<_>>()
        );
        for note in &self.notes {
            out.push_str("\nnote: ");
            out.push_str(note);
        }
        out
    }

    /// The student: built from the run's seed, normalisers attached, networks initialised as
    /// the plan says.
    pub fn build_student(&self) -> Result<Moe, VddError> {
        let mut student = Moe::from_config(self.student.clone(), self.vdd.seed)?;
        student.set_normalizers(
            Some(self.state_normalizer.clone()),
            Some(self.action_normalizer.clone()),
        )?;
        let family = *student.expert();
        let (d, ds) = (self.student.action_dim, self.student.state_dim);
        let r = vdd_core::Expert::raw_dim(&family);
        match self.init {
            InitKind::Official => init_official(&mut student, self.vdd.seed)?,
            InitKind::FromTeacher => {
                let f = &self.fitted;
                let mut raw = vec![0.0f32; r];
                for (net, experts) in student.expert_trunks_mut() {
                    // The output layer's mean rows reproduce the shared motion W s.
                    let (h, _) = net.forward_hidden(self.states_n.as_ref());
                    let (n, hd) = (h.nrows(), h.ncols());
                    let feats: Vec<f64> = (0..n)
                        .flat_map(|i| {
                            std::iter::once(1.0)
                                .chain((0..hd).map(move |k| f64::from(h[(i, k)])))
                                .collect::<Vec<_>>()
                        })
                        .collect();
                    let targets: Vec<f64> = (0..n)
                        .flat_map(|i| {
                            (0..d)
                                .map(|j| {
                                    (0..ds)
                                        .map(|t| {
                                            self.motion[j * ds + t]
                                                * f64::from(self.states_n[(i, t)])
                                        })
                                        .sum::<f64>()
                                })
                                .collect::<Vec<_>>()
                        })
                        .collect();
                    let moving = targets.iter().any(|t| t.abs() > 1e-3);
                    let beta = if moving {
                        fit::least_squares(&feats, &targets, n, hd + 1, d, 1e-3 * n as f64)
                    } else {
                        None
                    };
                    let out = net.output_layer_mut();
                    let cols = out.weight.value.len() / out.bias.value.len();
                    for (e, z) in experts.enumerate() {
                        let mean: Vec<f32> = f.means[z].iter().map(|&m| m as f32).collect();
                        let chol: Vec<f32> = f.chols[z].iter().map(|&m| m as f32).collect();
                        family.encode(&mean, &chol, &mut raw);
                        for k in 0..r {
                            let row = e * r + k;
                            let w = &mut out.weight.value[row * cols..(row + 1) * cols];
                            match (&beta, k < d) {
                                (Some(b), true) => {
                                    for (c, wc) in w.iter_mut().enumerate() {
                                        *wc = b[(c + 1) * d + k] as f32;
                                    }
                                    out.bias.value[row] = raw[k] + b[k] as f32;
                                }
                                _ => {
                                    w.fill(0.0);
                                    out.bias.value[row] = raw[k];
                                }
                            }
                        }
                    }
                }
                if let Some(g) = student.gating_network_mut() {
                    let out = g.output_layer_mut();
                    out.weight.value.fill(0.0);
                    for (b, w) in out.bias.value.iter_mut().zip(&f.weights) {
                        *b = w.max(1e-6).ln() as f32;
                    }
                }
            }
        }
        Ok(student)
    }
}

/// Every `per`-th row (one per distinct state).
fn thin(m: Mat<f32>, per: usize) -> Mat<f32> {
    let n = m.nrows().div_ceil(per.max(1));
    Mat::from_fn(n, m.ncols(), |i, j| m[(i * per, j)])
}

/// Annealed reverse diffusion with the score of a VE teacher, one sample per row of
/// `states` (teacher space): 200 geometric levels from `σ_max` (the teacher's `range`, at most
/// 10³) down to its `σ_min` (at least `10⁻⁶ σ_max`), ancestral steps, then one denoising step.
/// What [`AutoPlan::inspect`] samples a teacher without a sampler with; a teacher of another
/// noise convention is an error.
pub fn score_sampling<S: ScoreModel>(
    teacher: &mut S,
    states: MatRef<'_, f32>,
    range: Option<(f32, f32)>,
    rng: &mut vdd_core::Rng,
) -> Result<Mat<f32>, VddError> {
    if teacher.noise_convention() != NoiseConvention::Sigma {
        return Err(CoreError::Unsupported(
            "automatic set-up of a teacher that neither samples nor counts noise in σ: give \
             dataset actions",
        )
        .into());
    }
    let (n, d) = (states.nrows(), teacher.action_dim());
    let hi = range.map_or(1e3, |r| r.1.min(1e3));
    let lo = range.map_or(0.0, |r| r.0).max(1e-6 * hi);
    let levels = 200;
    let sigma = |k: usize| hi * (lo / hi).powf(k as f32 / (levels - 1) as f32);
    let mut x = Mat::from_fn(n, d, |_, _| hi * vdd_core::standard_normal(rng));
    let mut score = Mat::zeros(n, d);
    for k in 0..levels {
        let s = sigma(k);
        teacher.score(x.as_ref(), states, &vec![s; n], score.as_mut())?;
        if k + 1 == levels {
            for i in 0..n {
                for j in 0..d {
                    x[(i, j)] += s * s * score[(i, j)];
                }
            }
            break;
        }
        let next = sigma(k + 1);
        let var = s * s - next * next;
        let noise = (var * next * next / (s * s)).sqrt();
        for i in 0..n {
            for j in 0..d {
                x[(i, j)] += var * score[(i, j)] + noise * vdd_core::standard_normal(rng);
            }
        }
    }
    check_finite("score-sampled actions", x.as_ref())?;
    Ok(x)
}

#[cfg(test)]
mod tests;
