//! The Avoiding pipeline: scripted demonstrations → dataset → teachers (cached) → VDD and
//! baselines → rollouts (success rate, task entropy) and µs per action → `metrics.json`,
//! `table.md`, `curves.json`, plots.
//!
//! Seeds: the demonstrations come from `data.seed` (one fixed dataset for every run seed);
//! the run seed drives teacher training, student initialisation and training, and the
//! evaluation rollouts (`vdd_tasks::avoiding::EvalProtocol`: the same episode seeds for every
//! method of a seed, so methods are compared on the same episodes). Every `seed` field inside the
//! component configurations is replaced by the run seed.

use std::collections::HashMap;
use std::time::Instant;

use faer::Mat;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use vdd::{DistillData, Vdd, VddConfig};
use vdd_consistency::{CdConfig, CdTrainer, ConsistencyProgress, CtmConfig, CtmTrainer};
use vdd_core::{Affine, ClampedDenoiser, Policy};
use vdd_data::{
    DeploySpec, Episodes, Normalization, NormalizationKind, SequenceDataset, WindowConfig, Windowed,
};
use vdd_diffusion::{BesoConfig, DiffusionTeacher, TeacherKind};
use vdd_mixture::{Dataset, Em, EmConfig, Imc, ImcConfig};
use vdd_moe::{ActMode, GatingKind, Moe, MoeConfig};
use vdd_tasks::avoiding::rollout::Evaluation;
use vdd_tasks::avoiding::{EvalProtocol, ObsFeatures};
use vdd_tasks::timing::{Timing, us_per_action};
use vdd_tasks::{DemonstratorConfig, generate_demonstrations};

use crate::context::{RunContext, StageTimes};
use crate::methods::{self, Method};
use crate::plots::{self, Curves, TrajectoryPanel};
use crate::policy::TrainedPolicy;
use crate::recipe;
use crate::report::{self, Row};
use crate::student_cache::{CachedStudent, StudentCache};
use crate::teachers::{self, TeachersConfig, TrainedTeacher};

/// A recipe of the Avoiding task (see `recipes/avoiding.toml`): the schema of the recipe files;
/// the values not given there come from `recipes/defaults/avoiding.toml` ([`Self::defaults`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AvoidingRecipe {
    /// Recipe name (results go to `results/<name>/`).
    pub name: String,
    /// One line on what the recipe shows.
    pub description: String,
    /// Always `avoiding`.
    pub task: String,
    /// Run seeds.
    pub seeds: Vec<u64>,
    /// Methods to run (`beso`, `vdd-beso`, ...; `all`).
    pub methods: Vec<String>,
    /// Trainings run concurrently, each on one thread (0: one per core). Results do not
    /// depend on it.
    pub jobs: usize,
    /// Demonstrations and windowing.
    pub data: AvoidingData,
    /// The learned teachers.
    pub teachers: TeachersConfig,
    /// The mixture of experts of VDD, EM and IMC (`state_dim` / `action_dim` come from the data).
    pub student: MoeConfig,
    /// VDD's trainer for each teacher.
    pub vdd: VddMethods,
    /// EM and IMC.
    pub baselines: Baselines,
    /// Rollouts and timing.
    pub eval: AvoidingEval,
    /// Figures.
    pub plots: PlotSettings,
}

/// Demonstrations and windowing.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AvoidingData {
    /// Number of successful scripted demonstrations.
    pub demonstrations: usize,
    /// Seed of the demonstrations and of the train/validation split (fixed across run seeds).
    pub seed: u64,
    /// Share of episodes held out (0: train on all; the normalisation is fitted on the rest).
    pub validation_fraction: f64,
    /// Observation window `W` (steps).
    pub obs_window: usize,
    /// Action chunk `C` (steps).
    pub action_chunk: usize,
    /// Actions of each predicted chunk executed before predicting again (`1..=C`).
    pub execute_steps: usize,
    /// Also train on the first `W − 1` steps with the window padded by the first observation.
    pub pad_start: bool,
    /// What the models see of each observation ([`ObsFeatures`], a registered feature map
    /// saved with the models in their deployment spec).
    pub features: ObsFeatures,
    /// The scripted demonstrator.
    pub demonstrator: DemonstratorConfig,
}

/// VDD's trainer for each teacher, and how the student acts.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct VddMethods {
    /// VDD-BESO (noise levels are BESO's `σ`).
    pub beso: VddConfig,
    /// VDD-DDPM (noise levels are DDPM's time `t`).
    pub ddpm: VddConfig,
    /// Clamp the teacher's denoised estimate to the training actions' bounding box (normalised
    /// units) widened by this margin before forming the score VDD distils
    /// ([`vdd_core::ClampedDenoiser`]); `None`: the raw score. Without it the learned teachers'
    /// scores far from the data (where they extrapolate) make experts' variances run away.
    pub clip_margin: Option<f32>,
    /// VDD-BESO's student gating when it differs from `student.gating` (the mixture EM, IMC
    /// and, unless `ddpm_gating` says otherwise, VDD-DDPM use).
    pub beso_gating: Option<GatingKind>,
    /// VDD-DDPM's student gating when it differs from `student.gating`.
    pub ddpm_gating: Option<GatingKind>,
    /// Acting: greedy gating instead of sampling `z ~ q(z|s)`.
    pub greedy_gating: bool,
    /// Acting: sample `a ~ N(μ_z, Σ_z)` instead of returning `μ_z` (the paper uses `μ_z`).
    pub sample_action: bool,
}

/// The baselines: EM and IMC on the same mixture of experts, CD and CTM distilled from the
/// BESO teacher.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Baselines {
    /// EM.
    pub em: EmConfig,
    /// IMC.
    pub imc: ImcConfig,
    /// Consistency distillation of the BESO teacher.
    pub cd: CdConfig,
    /// Consistency trajectory model distilled from the BESO teacher.
    pub ctm: CtmConfig,
    /// For CD and CTM students started from the teacher (`init_from_teacher`): take the
    /// network architecture and the levels (`σ_data`, `σ_min`, `σ_max`, `ρ`) from the BESO
    /// teacher's configuration, so `--set teachers.beso...` changes need no matching change here.
    pub consistency_follows_teacher: bool,
}

/// Evaluation.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct AvoidingEval {
    /// Rollouts per method and seed.
    pub rollouts: usize,
    /// Environments stepped together with one batched `act_batch` (0: one episode at a time).
    pub lockstep_batch: usize,
    /// Evaluation threads (0: all cores).
    pub threads: usize,
    /// Timed single-observation `Policy::act` calls for µs per action (single thread).
    pub timing_calls: usize,
    /// Untimed calls before timing.
    pub timing_warmup: usize,
    /// The shortest timing round in milliseconds: a fast policy makes more than
    /// `timing_calls / 5` calls a round (see `vdd_tasks::timing::us_per_action`).
    pub timing_min_round_ms: f64,
}

impl AvoidingEval {
    /// The rollouts' protocol (episodes and lockstep batch; the seed comes from the run seed).
    fn protocol(&self) -> EvalProtocol {
        EvalProtocol { rollouts: self.rollouts, lockstep_batch: self.lockstep_batch }
    }

    /// The settings of `us_per_action`.
    fn timing(&self) -> Timing {
        Timing {
            calls: self.timing_calls,
            warmup: self.timing_warmup,
            min_round_ms: self.timing_min_round_ms,
        }
    }
}

/// Figures.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PlotSettings {
    /// Write plots at all.
    pub enabled: bool,
    /// Rollouts drawn per method in the trajectory figure.
    pub trajectories: usize,
    /// Also write PNGs (SVG always).
    pub png: bool,
}

/// `recipes/defaults/avoiding.toml`, embedded so that the binary is self-contained.
const DEFAULTS: &str = include_str!("../../recipes/defaults/avoiding.toml");

impl AvoidingRecipe {
    /// The task's defaults, `recipes/defaults/avoiding.toml`, which a recipe file overrides.
    pub fn defaults() -> recipe::RecipeResult<Self> {
        recipe::defaults_from_toml(&[("recipes/defaults/avoiding.toml", DEFAULTS)])
    }
}

/// A CD / CTM configuration for `seed`: the seed and (with `follow_teacher` and
/// `init_from_teacher`) the teacher's architecture and levels. (Their learning rate decays over
/// their `train.steps` by construction.)
pub fn consistency_config_for(
    c: &CdConfig,
    beso: &BesoConfig,
    seed: u64,
    follow_teacher: bool,
) -> CdConfig {
    let mut c = c.clone().with_seed(seed);
    if follow_teacher && c.init_from_teacher {
        let t = CdConfig::for_beso(beso);
        c.net = t.net;
        c.sigma_data = t.sigma_data;
        c.sigma_min = t.sigma_min;
        c.sigma_max = t.sigma_max;
        c.rho = t.rho;
    }
    c
}

/// The VDD config for a run: the run's seed (learning-rate schedules follow the run's length
/// by construction).
pub fn vdd_config_for(c: &VddConfig, seed: u64) -> VddConfig {
    VddConfig { seed, ..c.clone() }
}

/// How the models of a recipe act on raw observations: saved with the mixtures, applied to
/// every method's rollouts.
fn deploy_spec(data: &AvoidingData) -> DeploySpec {
    DeploySpec {
        obs_window: data.obs_window,
        action_chunk: data.action_chunk,
        execute_steps: data.execute_steps,
        ..DeploySpec::identity()
    }
    .with_features(data.features.feature_map())
}

/// Demonstrations turned into training matrices.
struct Prepared {
    /// Raw windows of the training split (`n x W·4`, `n x C·2`).
    states: Mat<f32>,
    actions: Mat<f32>,
    /// `vdd_data` standard normalisation fitted on the training split (EM, IMC).
    norm: Normalization,
    /// Normalised windows of the training split (EM, IMC).
    states_n: Mat<f32>,
    actions_n: Mat<f32>,
    /// Raw observations of the training episodes (µs-per-action timing).
    episodes_obs: Vec<Mat<f32>>,
    summary: Value,
    /// [`teachers::data_hash`] of the raw training matrices.
    data_hash: String,
}

fn prepare(data: &AvoidingData) -> crate::XResult<Prepared> {
    let t0 = Instant::now();
    let demos = generate_demonstrations(data.demonstrations, data.seed, &data.demonstrator)?;
    let episodes = Episodes::from_episodes(demos.observations, demos.actions)?;
    let train = if data.validation_fraction > 0.0 {
        episodes.split(data.validation_fraction, data.seed)?.train
    } else {
        episodes
    };
    // Raw observations of the training episodes (timing feeds them through the policy, which
    // applies the features itself); the models train on the features.
    let (episodes_obs, episode_actions) = train.to_episode_matrices();
    let features = data.features.feature_map();
    let train = if features.is_identity() {
        train
    } else {
        let obs: Result<Vec<_>, _> =
            episodes_obs.iter().map(|o| features.apply_rows(o.as_ref())).collect();
        Episodes::from_episodes(obs?, episode_actions)?
    };
    let window =
        WindowConfig::new(data.obs_window, data.action_chunk).with_pad_start(data.pad_start);
    let raw = SequenceDataset::new(train.clone(), window)?;
    let (states, actions) = raw.to_matrices();
    let norm = Normalization::fit(&train, NormalizationKind::standard())?;
    let (states_n, actions_n) =
        SequenceDataset::new(train.normalized(&norm)?, window)?.to_matrices();
    let mut counts = vec![0usize; vdd_tasks::avoiding::N_MODES];
    for m in &demos.modes {
        counts[m.index()] += 1;
    }
    let summary = json!({
        "demonstrations": data.demonstrations,
        "train_episodes": train.num_episodes(),
        "train_samples": states.nrows(),
        "state_dim": states.ncols(),
        "action_dim": actions.ncols(),
        "dataset_modes": counts.iter().filter(|&&c| c > 0).count(),
        "dataset_entropy": vdd_tasks::normalized_entropy(&counts),
    });
    crate::progress::log(format!(
        "data: {} demonstrations ({} train episodes, {} samples, {} of 24 modes, entropy {:.3}) in {:.2} s",
        data.demonstrations,
        train.num_episodes(),
        states.nrows(),
        summary["dataset_modes"],
        summary["dataset_entropy"].as_f64().unwrap_or(0.0),
        t0.elapsed().as_secs_f64()
    ));
    let data_hash = teachers::data_hash(states.as_ref(), actions.as_ref());
    Ok(Prepared { states, actions, norm, states_n, actions_n, episodes_obs, summary, data_hash })
}

/// Repeats a per-step normaliser over a window of `k` steps.
fn tile(a: &Affine, k: usize) -> Affine {
    Affine { offset: a.offset.repeat(k), scale: a.scale.repeat(k) }
}

fn normalize_rows(m: &Mat<f32>, a: &Affine) -> Mat<f32> {
    Mat::from_fn(m.nrows(), m.ncols(), |i, j| (m[(i, j)] - a.offset[j]) / a.scale[j])
}

/// A trained method before evaluation.
struct Trained {
    policy: TrainedPolicy,
    train_seconds: f64,
    teacher_seconds: Option<f64>,
    sampling_steps: Option<usize>,
    curves: Curves,
}

/// The key of the teacher of `kind` for a recipe, data and seed (teachers with equal keys are
/// trained once per run and shared by every method and variant that needs them).
fn teacher_key(
    kind: TeacherKind,
    cfg: &AvoidingRecipe,
    prep: &Prepared,
    seed: u64,
) -> crate::XResult<String> {
    let sub = match kind {
        TeacherKind::Beso => recipe::config_hash(&cfg.teachers.beso)?,
        TeacherKind::Ddpm => recipe::config_hash(&cfg.teachers.ddpm)?,
    };
    Ok(format!("{}-{sub}-{seed}-{}", teachers::kind_name(kind), prep.data_hash))
}

/// The teachers of this run, by [`teacher_key`].
#[derive(Default)]
struct TeacherStore {
    teachers: HashMap<String, TrainedTeacher>,
}

impl TeacherStore {
    fn get(
        &self,
        kind: TeacherKind,
        cfg: &AvoidingRecipe,
        prep: &Prepared,
        seed: u64,
    ) -> crate::XResult<&TrainedTeacher> {
        let key = teacher_key(kind, cfg, prep, seed)?;
        self.teachers.get(&key).ok_or_else(|| {
            format!("internal: the {} teacher of seed {seed} was not trained", kind_label(kind))
                .into()
        })
    }
}

fn kind_label(kind: TeacherKind) -> &'static str {
    teachers::kind_name(kind)
}

fn train_method(
    method: Method,
    cfg: &AvoidingRecipe,
    prep: &Prepared,
    seed: u64,
    store: &TeacherStore,
    students: StudentCache<'_>,
    label: &str,
) -> crate::XResult<Trained> {
    let mut curves = Curves::default();
    match method {
        Method::Beso | Method::Ddpm | Method::Beso1 | Method::Ddpm1 => {
            let kind = method.teacher().ok_or("teacher method without a teacher")?;
            let t = store.get(kind, cfg, prep, seed)?;
            let mut teacher = t.teacher.clone();
            if matches!(method, Method::Beso1 | Method::Ddpm1) {
                teacher.set_steps(1)?;
            }
            curves.insert(
                format!("{} teacher loss", teachers::kind_name(kind)),
                t.losses.iter().map(|&(s, l)| (s as f64, f64::from(l))).collect(),
            );
            Ok(Trained {
                sampling_steps: Some(teacher.steps()),
                policy: TrainedPolicy::Teacher(Box::new(teacher)),
                train_seconds: t.train_seconds,
                teacher_seconds: None,
                curves,
            })
        }
        Method::VddBeso | Method::VddDdpm => {
            let kind = method.teacher().ok_or("VDD without a teacher")?;
            let vc = match kind {
                TeacherKind::Beso => &cfg.vdd.beso,
                TeacherKind::Ddpm => &cfg.vdd.ddpm,
            };
            let vc = vdd_config_for(vc, seed);
            let t = store.get(kind, cfg, prep, seed)?;
            let teacher = t.teacher.clone();
            let teacher_seconds = t.train_seconds;
            let (sn, an) = {
                let (s, a) = teacher.normalizers();
                (s.clone(), a.clone())
            };
            let states = normalize_rows(&prep.states, &sn);
            let actions = normalize_rows(&prep.actions, &an);
            let mut mc = cfg.student.clone();
            mc.state_dim = states.ncols();
            mc.action_dim = actions.ncols();
            let gating = match kind {
                TeacherKind::Beso => cfg.vdd.beso_gating,
                TeacherKind::Ddpm => cfg.vdd.ddpm_gating,
            };
            mc.gating = gating.unwrap_or(mc.gating);
            let teacher_config = match kind {
                TeacherKind::Beso => serde_json::to_value(&cfg.teachers.beso)?,
                TeacherKind::Ddpm => serde_json::to_value(&cfg.teachers.ddpm)?,
            };
            let key = json!({
                "version": 1,
                "teacher": teacher_config,
                "teacher_hash": t.hash,
                "student": mc,
                "vdd": vc,
                "clip_margin": cfg.vdd.clip_margin,
            });
            let hash = recipe::config_hash(&key)?;
            let name = method.name();
            let trained = match students.load(name, &hash)? {
                Some(c) => {
                    crate::progress::log(format!("[{label}] student loaded from the cache"));
                    c
                }
                None => {
                    let c = distill(vc, teacher, mc, states, actions, cfg.vdd.clip_margin, label)?;
                    let path = students.store(name, &hash, &c)?;
                    crate::progress::log(format!(
                        "[{label}] trained in {:.1} s; cached as {}",
                        c.train_seconds,
                        teachers::rel(&path)
                    ));
                    c
                }
            };
            let CachedStudent { mut student, train_seconds, curves } = trained;
            student.set_normalizers(Some(sn), Some(an))?;
            student.set_act_mode(ActMode {
                greedy_gating: cfg.vdd.greedy_gating,
                sample_action: cfg.vdd.sample_action,
            });
            Ok(Trained {
                policy: TrainedPolicy::Moe(Box::new(student)),
                train_seconds,
                teacher_seconds: Some(teacher_seconds),
                sampling_steps: None,
                curves,
            })
        }
        Method::Em | Method::Imc => {
            let (w, c) = (cfg.data.obs_window, cfg.data.action_chunk);
            let (sn, an) = (tile(&prep.norm.observations, w), tile(&prep.norm.actions, c));
            let data = Dataset::new(prep.states_n.clone(), prep.actions_n.clone())?;
            let mut mc = cfg.student.clone();
            mc.state_dim = prep.states_n.ncols();
            mc.action_dim = prep.actions_n.ncols();
            let student = Moe::from_config(mc, seed)?;
            let t0 = Instant::now();
            let mut student = if method == Method::Em {
                let mut ec = cfg.baselines.em.clone();
                ec.seed = seed;
                let bar = crate::progress::bar(ec.iterations as u64, label);
                let mut em = Em::new(ec, student, data)?;
                em.train(|m| {
                    bar.inc(1);
                    bar.set_message(format!("log-lik {:.3}", m.log_likelihood));
                    curves
                        .entry("log-likelihood (nats)".into())
                        .or_default()
                        .push((m.iteration as f64, m.log_likelihood));
                })?;
                bar.finish_and_clear();
                em.into_student()
            } else {
                let mut ic = cfg.baselines.imc.clone();
                ic.seed = seed;
                let bar = crate::progress::bar(ic.iterations as u64, label);
                let mut imc = Imc::new(ic, student, data)?;
                imc.train(|m| {
                    bar.inc(1);
                    bar.set_message(format!("log-lik {:.3}", m.log_likelihood));
                    curves
                        .entry("log-likelihood (nats)".into())
                        .or_default()
                        .push((m.iteration as f64, m.log_likelihood));
                    curves
                        .entry("IMC objective".into())
                        .or_default()
                        .push((m.iteration as f64, m.objective));
                })?;
                bar.finish_and_clear();
                imc.into_student()
            };
            let train_seconds = t0.elapsed().as_secs_f64();
            student.set_normalizers(Some(sn), Some(an))?;
            Ok(Trained {
                policy: TrainedPolicy::Moe(Box::new(student)),
                train_seconds,
                teacher_seconds: None,
                sampling_steps: None,
                curves,
            })
        }
        Method::Cd | Method::Ctm => {
            let t = store.get(TeacherKind::Beso, cfg, prep, seed)?;
            let teacher_seconds = t.train_seconds;
            let DiffusionTeacher::Beso(beso) = t.teacher.clone() else {
                return Err("CD and CTM need the BESO teacher".into());
            };
            let b = &cfg.baselines;
            let follow = b.consistency_follows_teacher;
            let (states, actions) = (prep.states.as_ref(), prep.actions.as_ref());
            let t0 = Instant::now();
            let mut progress_curves = |bar: &indicatif::ProgressBar, p: &ConsistencyProgress| {
                bar.set_position(p.step);
                bar.set_message(format!("loss {:.4}", p.loss));
                let x = p.step as f64;
                curves
                    .entry("consistency loss".into())
                    .or_default()
                    .push((x, f64::from(p.consistency_loss)));
                if p.dsm_loss != 0.0 {
                    curves.entry("DSM loss".into()).or_default().push((x, f64::from(p.dsm_loss)));
                }
            };
            let (policy, steps) = if method == Method::Cd {
                let c = consistency_config_for(&b.cd, beso.config(), seed, follow);
                let steps = c.sampling_steps;
                let bar = crate::progress::bar(c.train.steps, label);
                let mut trainer = CdTrainer::new(c, beso, states, actions)?;
                let model = trainer.train(&mut |p| progress_curves(&bar, p))?;
                bar.finish_and_clear();
                (TrainedPolicy::Consistency(Box::new(model)), steps)
            } else {
                let mut c = b.ctm.clone();
                c.base = consistency_config_for(&c.base, beso.config(), seed, follow);
                let steps = c.base.sampling_steps;
                let bar = crate::progress::bar(c.base.train.steps, label);
                let mut trainer = CtmTrainer::new(c, beso, states, actions)?;
                let model = trainer.train(&mut |p| progress_curves(&bar, p))?;
                bar.finish_and_clear();
                (TrainedPolicy::Trajectory(Box::new(model)), steps)
            };
            Ok(Trained {
                policy,
                train_seconds: t0.elapsed().as_secs_f64(),
                teacher_seconds: Some(teacher_seconds),
                sampling_steps: Some(steps),
                curves,
            })
        }
        Method::VddExact => Err(method
            .check_available("avoiding")
            .err()
            .unwrap_or_else(|| "unavailable".into())
            .into()),
    }
}

/// Distils `teacher` into a new mixture of configuration `mc` with VDD (the states and actions
/// normalised by the teacher's normalisers; the student initialised from the run seed
/// `vc.seed`), with a progress bar and learning curves.
#[allow(clippy::too_many_arguments)]
fn distill(
    vc: VddConfig,
    teacher: DiffusionTeacher,
    mc: MoeConfig,
    states: Mat<f32>,
    actions: Mat<f32>,
    clip_margin: Option<f32>,
    label: &str,
) -> crate::XResult<CachedStudent> {
    let mut curves = Curves::default();
    let teacher = match clip_margin {
        Some(m) => ClampedDenoiser::around_data(teacher, actions.as_ref(), m)?,
        None => ClampedDenoiser::unclamped(teacher),
    };
    let data = DistillData::new(states, Some(actions))?;
    let iterations = vc.iterations;
    let mut vdd = Vdd::from_config(vc, teacher, mc, data)?;
    let bar = crate::progress::bar(iterations as u64, label);
    let every = (iterations / 200).max(1);
    let t0 = Instant::now();
    vdd.train(|m| {
        bar.inc(1);
        if m.iteration % every == 0 || m.iteration + 1 == iterations {
            let x = m.iteration as f64;
            let mut push = |k: &str, v: f64| curves.entry(k.to_owned()).or_default().push((x, v));
            push("expert entropy (nats)", f64::from(m.expert.expert_entropy));
            push("corrected score rms", f64::from(m.expert.corrected_score_rms));
            push("log responsibility", f64::from(m.expert.log_responsibility));
            push("gating entropy (nats)", f64::from(m.gating_entropy));
            if let Some(g) = m.gating_loss {
                push("gating loss", f64::from(g));
            }
            bar.set_message(format!("H(z|s) {:.2}", m.gating_entropy));
        }
    })?;
    let train_seconds = t0.elapsed().as_secs_f64();
    bar.finish_and_clear();
    Ok(CachedStudent { student: vdd.into_student(), train_seconds, curves })
}

/// For each step of each of the first `n` recorded rollouts of `eval`, the expert the mixture
/// inside `policy` acted with ([`vdd_moe::Moe::last_experts`]): the evaluation units holding
/// those rollouts run again on this thread with a copy of the policy (the same seeds, so the
/// same rollouts, which is checked). Needs a mixture asked at every step for every row
/// (observation window and action chunk 1).
fn chosen_experts(
    policy: &Windowed<TrainedPolicy>,
    protocol: EvalProtocol,
    seed: u64,
    eval: &Evaluation,
    n: usize,
) -> crate::XResult<Vec<Vec<usize>>> {
    let unit = protocol.lockstep_batch.max(1);
    let rollouts = n.div_ceil(unit).saturating_mul(unit).min(protocol.rollouts);
    let cfg = EvalProtocol { rollouts, ..protocol }.config(seed, true);
    let mut log = ExpertLog { policy: policy.clone(), units: Vec::new() };
    let again = vdd_tasks::evaluate(&mut log, &cfg)?;
    if eval.rollouts.get(..rollouts) != Some(&again.rollouts[..]) {
        return Err("internal: the rollouts did not replay for expert attribution".into());
    }
    let mut out = Vec::with_capacity(n);
    for (i, r) in again.rollouts.iter().take(n).enumerate() {
        let steps = log.units.get(i / unit).map_or(&[][..], |u| &u[..]);
        let ids: Option<Vec<usize>> =
            (0..r.steps).map(|t| steps.get(t)?.get(i % unit).copied()).collect();
        out.push(ids.ok_or("internal: the mixture did not act for every row and step")?);
    }
    Ok(out)
}

/// A policy that logs, for each evaluation unit (from one `reset` to the next) and each call,
/// the expert of each row ([`vdd_moe::Moe::last_experts`]; nothing for other policies).
struct ExpertLog {
    policy: Windowed<TrainedPolicy>,
    units: Vec<Vec<Vec<usize>>>,
}

impl ExpertLog {
    fn log(&mut self) {
        let experts = match self.policy.inner() {
            TrainedPolicy::Moe(moe) => moe.last_experts().to_vec(),
            _ => Vec::new(),
        };
        if let Some(unit) = self.units.last_mut() {
            unit.push(experts);
        }
    }
}

impl Policy for ExpertLog {
    fn obs_dim(&self) -> usize {
        self.policy.obs_dim()
    }
    fn action_dim(&self) -> usize {
        self.policy.action_dim()
    }
    fn reset(&mut self) {
        self.policy.reset();
        self.units.push(Vec::new());
    }
    fn seed(&mut self, seed: u64) {
        self.policy.seed(seed);
    }
    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
        self.policy.act_into(obs, action)?;
        self.log();
        Ok(())
    }
    fn act_batch(
        &mut self,
        obs: faer::MatRef<'_, f32>,
        actions: faer::MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        self.policy.act_batch(obs, actions)?;
        self.log();
        Ok(())
    }
}

/// Runs the recipe.
pub fn run(ctx: &RunContext) -> crate::XResult {
    let resolved = recipe::resolve(&AvoidingRecipe::defaults()?, &ctx.file, &ctx.overrides)?;
    let base = &resolved.base;
    if base.task != "avoiding" {
        return Err(format!("task `{}` is not avoiding", base.task).into());
    }
    if base.seeds.is_empty() {
        return Err("the recipe lists no seeds".into());
    }
    let configs = resolved.configs();
    let mut plan: Vec<(String, Method, &AvoidingRecipe)> = Vec::new();
    for (variant, cfg) in &configs {
        for m in methods::parse_methods(&cfg.methods, "avoiding")? {
            plan.push((methods::label(m, variant.map(|v| v.name.as_str())), m, cfg));
        }
        // Before any training: a bad timing setting would otherwise fail after it.
        cfg.eval.timing().check().map_err(|e| format!("eval: {e}"))?;
        deploy_spec(&cfg.data).validate().map_err(|e| format!("data: {e}"))?;
    }
    let dir = ctx.run_dir(&base.seeds);
    ctx.write_resolved(&dir, &resolved.to_toml()?)?;
    crate::progress::log(format!(
        "recipe `{}`: {} method run(s) x {} seed(s) -> {}",
        ctx.name,
        plan.len(),
        base.seeds.len(),
        teachers::rel(&dir)
    ));

    let mut stages = StageTimes::default();
    let cores = std::thread::available_parallelism().map_or(1, |p| p.get());
    let threads = if base.eval.threads == 0 { cores } else { base.eval.threads };
    let jobs = if base.jobs == 0 { cores } else { base.jobs };

    // Data: one dataset per distinct `data` table (usually one).
    let mut prepared: HashMap<String, Prepared> = HashMap::new();
    let mut dkeys = Vec::with_capacity(plan.len());
    for (_, _, cfg) in &plan {
        let dkey = recipe::config_hash(&cfg.data)?;
        if !prepared.contains_key(&dkey) {
            let p = stages.time("data", || prepare(&cfg.data))?;
            prepared.insert(dkey.clone(), p);
        }
        dkeys.push(dkey);
    }
    let data_summary = dkeys.first().map_or(Value::Null, |k| prepared[k].summary.clone());

    // Training, in two parallel phases of single-threaded jobs (`jobs` at a time): the teachers
    // with the methods that need none (EM, IMC), then the students of the teachers (VDD, CD,
    // CTM). The teachers' own rows (`beso`, `beso-1`, ...) just clone them. Every job is seeded
    // on its own, so the results do not depend on the number of jobs.
    let mut teacher_jobs: Vec<(String, TeacherKind, usize, u64)> = Vec::new();
    for &seed in &base.seeds {
        for (pi, (_, method, cfg)) in plan.iter().enumerate() {
            if let Some(kind) = method.teacher() {
                let key = teacher_key(kind, cfg, &prepared[&dkeys[pi]], seed)?;
                if !teacher_jobs.iter().any(|j| j.0 == key) {
                    teacher_jobs.push((key, kind, pi, seed));
                }
            }
        }
    }
    let student_jobs: Vec<(usize, u64, usize)> = base
        .seeds
        .iter()
        .enumerate()
        .flat_map(|(si, &seed)| (0..plan.len()).map(move |pi| (si, seed, pi)))
        .collect();
    let (free, dependent): (Vec<_>, Vec<_>) = student_jobs
        .into_iter()
        .filter(|&(_, _, pi)| !plan[pi].1.is_teacher())
        .partition(|&(_, _, pi)| plan[pi].1.teacher().is_none());
    enum Work<'a> {
        Teacher(&'a (String, TeacherKind, usize, u64)),
        Student((usize, u64, usize)),
    }
    enum Done {
        Teacher(String, Box<TrainedTeacher>),
        Student((usize, usize), Box<Trained>),
    }
    let mut store = TeacherStore::default();
    let students = StudentCache { dir: &ctx.student_cache_dir, fresh: ctx.fresh };
    let mut trained: HashMap<(usize, usize), Trained> = HashMap::new();
    let run_job = |w: &Work, store: &TeacherStore| -> Result<Done, String> {
        match w {
            Work::Teacher((key, kind, pi, seed)) => {
                let cfg = plan[*pi].2;
                let prep = &prepared[&dkeys[*pi]];
                let t = teachers::train_or_load(
                    *kind,
                    &cfg.teachers,
                    prep.states.as_ref(),
                    prep.actions.as_ref(),
                    *seed,
                    &ctx.cache_dir,
                    ctx.fresh,
                    &format!("{} s{seed}", teachers::kind_name(*kind)),
                )
                .map_err(|e| e.to_string())?;
                Ok(Done::Teacher(key.clone(), Box::new(t)))
            }
            Work::Student((si, seed, pi)) => {
                let (label, method, cfg) = &plan[*pi];
                let prep = &prepared[&dkeys[*pi]];
                let tag = format!("{label} s{seed}");
                let t = train_method(*method, cfg, prep, *seed, store, students, &tag)
                    .map_err(|e| format!("{tag}: {e}"))?;
                Ok(Done::Student((*si, *pi), Box::new(t)))
            }
        }
    };
    let mut collect = |done: Vec<Done>, store: &mut TeacherStore| {
        for d in done {
            match d {
                Done::Teacher(key, t) => {
                    store.teachers.insert(key, *t);
                }
                Done::Student(k, t) => {
                    trained.insert(k, *t);
                }
            }
        }
    };
    let phase1: Vec<Work> = teacher_jobs
        .iter()
        .map(Work::Teacher)
        .chain(free.iter().map(|&j| Work::Student(j)))
        .collect();
    let t0 = Instant::now();
    let empty = TeacherStore::default();
    let done = crate::context::parallel_map(&phase1, jobs, |w| run_job(w, &empty))?;
    collect(done, &mut store);
    stages.add("teachers_em_imc", t0.elapsed().as_secs_f64());
    let phase2: Vec<Work> = dependent.iter().map(|&j| Work::Student(j)).collect();
    let t0 = Instant::now();
    let done = crate::context::parallel_map(&phase2, jobs, |w| run_job(w, &store))?;
    collect(done, &mut store);
    stages.add("distillation", t0.elapsed().as_secs_f64());
    let teacher_log: Vec<Value> = teacher_jobs
        .iter()
        .filter_map(|(key, kind, _, seed)| {
            store.teachers.get(key).map(|t| teachers::cache_entry(*kind, *seed, t))
        })
        .collect();

    // Evaluation, one method at a time (rollouts on every core, then the single-threaded
    // timing with nothing else running).
    let mut rows: Vec<(String, Vec<Row>)> =
        plan.iter().map(|(l, _, _)| (l.clone(), Vec::new())).collect();
    let mut all_curves: serde_json::Map<String, Value> = serde_json::Map::new();
    let mut panels: Vec<TrajectoryPanel> = Vec::new();
    let mut curve_panels: Vec<(String, Curves)> = Vec::new();
    for (si, &seed) in base.seeds.iter().enumerate() {
        // Rollouts and timing use the same seed for every method of a run seed.
        let eval_seed = EvalProtocol::seed(seed);
        let mut timed: Vec<(usize, Windowed<TrainedPolicy>)> = Vec::with_capacity(plan.len());
        for (pi, (label, method, cfg)) in plan.iter().enumerate() {
            let prep = &prepared[&dkeys[pi]];
            let tag = format!("{label} s{seed}");
            let mut trained = match trained.remove(&(si, pi)) {
                Some(t) => t,
                None => train_method(*method, cfg, prep, seed, &store, students, &tag)?,
            };

            // Rollouts, on raw observations through the recipe's features and windows.
            let d = &cfg.data;
            let spec = deploy_spec(d);
            if let TrainedPolicy::Moe(moe) = &mut trained.policy {
                moe.set_deploy_spec(spec.clone())?;
            }
            let wrapped = Windowed::new(trained.policy.clone(), spec)?;
            let protocol = cfg.eval.protocol();
            let record = si == 0 && cfg.plots.enabled;
            let spin = crate::progress::spinner(&tag, &format!("{} rollouts", cfg.eval.rollouts));
            let t0 = Instant::now();
            let ev = protocol.evaluate(&wrapped, seed, threads, record)?;
            let eval_seconds = t0.elapsed().as_secs_f64();
            stages.add("rollouts", eval_seconds);
            spin.finish_and_clear();

            // The distilled / fitted mixtures are saved for deployment with their spec
            // (`vdd_moe::load_policy` gives a policy on raw observations).
            if let TrainedPolicy::Moe(moe) = &trained.policy {
                let models = dir.join("models");
                std::fs::create_dir_all(&models)?;
                moe.save(&models.join(format!("{label}-s{seed}.safetensors")))?;
            }

            let m = &ev.metrics;
            crate::progress::log(format!(
                "[{tag}] success {:.3}, entropy {:.3} ({} modes), trained in {:.1} s{}, evaluated in {:.1} s",
                m.success_rate,
                m.task_entropy,
                m.modes_reached,
                trained.train_seconds,
                trained.teacher_seconds.map_or(String::new(), |t| format!(" (+ teacher {t:.1} s)")),
                eval_seconds
            ));
            let mut row = Row::new();
            row.insert("seed".into(), json!(seed));
            row.insert("success_rate".into(), json!(m.success_rate));
            row.insert("task_entropy".into(), json!(m.task_entropy));
            row.insert("train_seconds".into(), report::json_f64(trained.train_seconds));
            if let Some(t) = trained.teacher_seconds {
                row.insert("teacher_seconds".into(), report::json_f64(t));
            }
            if let Some(s) = trained.sampling_steps {
                row.insert("sampling_steps".into(), json!(s));
            }
            row.insert("rollouts".into(), json!(m.rollouts));
            row.insert("modes_reached".into(), json!(m.modes_reached));
            row.insert("collisions".into(), json!(m.collisions));
            row.insert("timeouts".into(), json!(m.timeouts));
            row.insert("mean_success_steps".into(), report::json_f64(m.mean_success_steps));
            row.insert("mode_counts".into(), json!(m.mode_counts));
            rows[pi].1.push(row);
            all_curves
                .insert(format!("{label}/seed{seed}"), serde_json::to_value(&trained.curves)?);

            if si == 0 && cfg.plots.enabled {
                let t0 = Instant::now();
                let n = cfg.plots.trajectories;
                let experts = match &trained.policy {
                    TrainedPolicy::Moe(moe) if d.obs_window == 1 && d.action_chunk == 1 => {
                        Some((chosen_experts(&wrapped, protocol, seed, &ev, n)?, moe.num_experts()))
                    }
                    _ => None,
                };
                panels.push(TrajectoryPanel::from_rollouts(
                    label,
                    &ev.rollouts,
                    n,
                    experts,
                    m.success_rate,
                    m.task_entropy,
                ));
                curve_panels.push((label.clone(), trained.curves));
                stages.add("plots", t0.elapsed().as_secs_f64());
            }

            // Timed below, with the seed's other methods.
            timed.push((pi, wrapped));
        }

        // Inference time, single-threaded, one observation per call, with nothing else running:
        // the seed's methods take their timing rounds in turn (see `us_per_action`), in groups
        // that share the observations and the timing settings (one group unless variants change
        // them).
        let t0 = Instant::now();
        while let Some((first, _)) = timed.first() {
            let (timing, dkey) = (plan[*first].2.eval.timing(), &dkeys[*first]);
            let same = |pi: usize| dkeys[pi] == *dkey && plan[pi].2.eval.timing() == timing;
            let (group, rest): (Vec<_>, Vec<_>) = timed.drain(..).partition(|(pi, _)| same(*pi));
            timed = rest;
            let (pis, mut policies): (Vec<usize>, Vec<_>) = group.into_iter().unzip();
            let episodes = &prepared[dkey].episodes_obs;
            let us = us_per_action(&mut policies, episodes, timing, eval_seed)?;
            let mut line = Vec::with_capacity(pis.len());
            for (pi, us) in pis.into_iter().zip(us) {
                rows[pi].1[si].insert("us_per_action".into(), report::json_f64(us));
                line.push(format!("{} {us:.1}", plan[pi].0));
            }
            crate::progress::log(format!("[s{seed}] µs per action: {}", line.join(", ")));
        }
        stages.add("timing", t0.elapsed().as_secs_f64());
    }

    // Outputs.
    let mut metrics = report::metrics_json(&ctx.name, "avoiding", &base.seeds, &rows);
    metrics.insert("data".into(), data_summary.clone());
    vdd_nn::io::write_atomic(
        &dir.join("metrics.json"),
        serde_json::to_string_pretty(&metrics)?.as_bytes(),
    )?;
    vdd_nn::io::write_atomic(
        &dir.join("curves.json"),
        serde_json::to_string(&all_curves)?.as_bytes(),
    )?;
    let table = format!(
        "## {} (Avoiding)\n\n{}\n\n{}\nmean ± std over seeds {:?}; {} rollouts per method and seed; µs per action: single-threaded `Policy::act` on one observation.\n",
        ctx.name,
        base.description,
        report::markdown_table(&rows, &report::columns_for("avoiding")),
        base.seeds,
        base.eval.rollouts
    );
    vdd_nn::io::write_atomic(&dir.join("table.md"), table.as_bytes())?;
    let mut figures = Vec::new();
    if base.plots.enabled && !panels.is_empty() {
        let t0 = Instant::now();
        figures.extend(plots::avoiding_trajectories(
            &dir.join("trajectories"),
            &panels,
            base.plots.png,
        )?);
        figures.extend(plots::learning_curves(&dir.join("curves"), &curve_panels, base.plots.png)?);
        stages.add("plots", t0.elapsed().as_secs_f64());
    }
    ctx.write_run_info(
        &dir,
        json!({
            "figures": figures,
            "data": data_summary,
            "teachers": teacher_log,
            "jobs": jobs,
            "stage_seconds": stages.to_json(),
        }),
    )?;
    println!("\n{table}");
    print_acceptance(&rows);
    println!("stages: {}", stages.summary());
    let cpu = crate::context::cpu_seconds().map_or(String::new(), |c| format!(", {c:.0} s CPU"));
    println!(
        "results in {} ({:.1} s wall{cpu})",
        teachers::rel(&dir),
        ctx.started.elapsed().as_secs_f64()
    );
    Ok(())
}

/// Prints VDD vs teacher comparisons (issue 7's acceptance) when both are in the run.
fn print_acceptance(rows: &[(String, Vec<Row>)]) {
    let mean = |label: &str, key: &str| -> Option<f64> {
        let (_, r) = rows.iter().find(|(l, _)| l == label)?;
        let xs: Vec<f64> = r.iter().filter_map(|x| x.get(key)?.as_f64()).collect();
        (!xs.is_empty()).then(|| report::mean_std(&xs).0)
    };
    for (vdd, teacher) in [("vdd-beso", "beso"), ("vdd-ddpm", "ddpm")] {
        let (Some(vs), Some(ve), Some(vu)) =
            (mean(vdd, "success_rate"), mean(vdd, "task_entropy"), mean(vdd, "us_per_action"))
        else {
            continue;
        };
        let mut line = format!(
            "{vdd}: success {vs:.3} (>= 0.90: {}), entropy {ve:.3} (>= 0.70: {})",
            yes(vs >= 0.90),
            yes(ve >= 0.70)
        );
        if let (Some(ts), Some(tu)) =
            (mean(teacher, "success_rate"), mean(teacher, "us_per_action"))
        {
            line.push_str(&format!(
                "; {teacher} success {ts:.3} (within 0.05: {}); speed-up {:.1}x (>= 10x: {})",
                yes(vs >= ts - 0.05),
                tu / vu,
                yes(tu / vu >= 10.0)
            ));
        }
        println!("{line}");
    }
}

fn yes(b: bool) -> &'static str {
    if b { "yes" } else { "NO" }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_defaults_file_is_complete_and_valid() {
        recipe::assert_complete_defaults::<AvoidingRecipe>(&[(
            "recipes/defaults/avoiding.toml",
            DEFAULTS,
        )]);
    }

    #[test]
    fn recipes_in_the_repository_resolve() {
        for name in [
            "avoiding",
            "avoiding-ablation-experts",
            "avoiding-ablation-gating",
            "avoiding-ablation-noise",
        ] {
            let path = recipe::recipe_path(name).unwrap();
            let file = recipe::read_recipe(&path).unwrap();
            for quick in [false, true] {
                let o = recipe::Overrides { quick, ..Default::default() };
                let r = recipe::resolve(&AvoidingRecipe::defaults().unwrap(), &file, &o)
                    .unwrap_or_else(|e| panic!("{name}: {e}"));
                for (_, c) in r.configs() {
                    methods::parse_methods(&c.methods, "avoiding").unwrap();
                }
            }
        }
    }
}
