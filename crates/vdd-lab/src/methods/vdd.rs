//! `vdd`: VDD distilling a row's teacher: rows `vdd-ddpm` and `vdd-beso` distil the learned
//! teachers, `vdd-exact` the task's exact mixture (toys). With `with.select_checkpoint = true`
//! (row `vdd-beso-selected`) the row's policy is the snapshot with the highest value of the
//! curve series `vdd.select_by` (default: the held-out task entropy, as the official code
//! selects) among the curves' checkpoints instead of the final iterate, from the same training
//! (and cache key); the chosen iteration and its value are the `selected checkpoint` series of
//! its curves. A training without selection keeps the default selection's snapshot as well
//! (when the task takes curves and no rounds on visited states change the training), so the
//! selecting row of the same training loads it rather than training again.
//!
//! Keys (below `vdd`, `<teacher>` the row's teacher with `-` as `_`): `<teacher>` (the
//! [`VddConfig`]; its `seed` is replaced by the run seed),
//! optional `<teacher>_gating` and `<teacher>_experts` (the student's gating and number of
//! experts when they differ from `student.gating` and `student.num_experts`),
//! `clip_margin` (clamp the teacher's denoised estimate to the training actions' bounding box,
//! in the student's normalised units, widened by this margin: [`ClampedDenoiser`]),
//! `clamp_denoiser` (`false`: the raw score whatever `clip_margin` says), `official_init`
//! (initialise the student as the official code does: [`vdd::init_official`]),
//! `greedy_gating` and `sample_action` (how the student acts); `<teacher>_expert_visits`
//! (continue distilling on the states the student visits: [`ExpertVisits`]) and
//! `<teacher>_gating_fit` / `<teacher>_gating_visits` (a learned gating fitted afterwards);
//! `<teacher>_init = "samples"` (start from a mixture fitted by EM to the teacher's samples,
//! with the fit `<teacher>_init_fit`: [`SampleFit`]; `"paper"`, the default: a new mixture)
//! and `<teacher>_gating_temperature` (a learned gating sharpened after training:
//! [`Moe::sharpen_gating`]).
//!
//! The student works in the teacher's normalised space (the exact teacher's is the raw one; a
//! file teacher's data come in its space, [`crate::teachers::LoadedTeacher::training_data`],
//! and its student acts through the teacher's windows and chunk). Students of learned and
//! file teachers are cached when the task gives a [`StudentCache`] ([`vdd_moe::cache`]).

use faer::MatRef;
use rand::Rng as _;
use serde::{Deserialize, Serialize};
use serde_json::json;
use vdd::{DistillData, Resumable, ResumableOutcome, VddConfig};
use vdd_core::{Affine, ClampedDenoiser, NoiseConvention, ScoreModel};
use vdd_diffusion::TeacherKind;
use vdd_mixture::gating::{GatingFitConfig, GatingFitProgress, fit_gating_to_policy_with_progress};
use vdd_moe::{ActMode, GatingKind, Moe, MoeConfig, NetworkConfig};

use crate::method::{Budget, Info, Job, Method, MethodRecipe, TeacherUse, Trained};
use crate::policy::TrainedPolicy;
use crate::recipe;
use crate::sample_fit::SampleFit;
use crate::teachers;
use vdd_moe::cache::{CachedStudent, STUDENT_CACHE_VERSION, StudentCache};
use visits::{
    ExpertVisits, GatingVisits, MAX_VISIT_EPISODES, MAX_VISIT_ITERATIONS, MAX_VISIT_ROUNDS,
    distill_on_visits, stacked,
};

mod visits;

/// VDD.
pub struct Vdd;

const INFO: Info =
    Info { name: "vdd", teacher: TeacherUse::Any, needs: &[], row_keys: &["select_checkpoint"] };

/// The key naming the curve series of checkpoint selection.
const SELECT_BY: &str = "vdd.select_by";

/// The recipe keys of VDD with its settings at `vdd.<t>`.
fn vdd_keys(t: &str) -> Vec<String> {
    let own = [
        "",
        "_gating",
        "_experts",
        "_gating_fit",
        "_gating_visits",
        "_expert_visits",
        "_init",
        "_init_fit",
        "_gating_temperature",
    ];
    let mut keys: Vec<String> = own.iter().map(|k| format!("vdd.{t}{k}")).collect();
    keys.extend([CLIP, CLAMP, INIT, GREEDY, SAMPLE].map(String::from));
    keys
}

/// A row's settings.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct RowSettings {
    /// Report the snapshot chosen by `vdd.select_by` (the paper's checkpoint selection).
    #[serde(default)]
    select_checkpoint: bool,
}

/// The curve series `row` selects its checkpoint by, if it does.
fn select_by(recipe: &MethodRecipe<'_>) -> crate::Result<Option<String>> {
    let s: RowSettings = recipe.row.settings()?;
    if !s.select_checkpoint {
        return Ok(None);
    }
    Ok(Some(recipe.get_opt::<String>(SELECT_BY)?.unwrap_or_else(|| DEFAULT_SELECTION.to_owned())))
}

/// Whether the row's teacher is a learned one (not the task's exact mixture).
fn learned(row: &crate::row::Row) -> bool {
    row.teacher_kind().is_some()
}

/// The name students of `row` are cached under: `vdd-<teacher>` (whatever the row is called).
fn cache_name(row: &crate::row::Row) -> String {
    format!("vdd-{}", row.teacher_name().unwrap_or("none"))
}

pub(super) const CLIP: &str = "vdd.clip_margin";
pub(super) const CLAMP: &str = "vdd.clamp_denoiser";
pub(super) const INIT: &str = "vdd.official_init";
pub(super) const GREEDY: &str = "vdd.greedy_gating";
pub(super) const SAMPLE: &str = "vdd.sample_action";

/// The settings of one VDD method.
struct Settings {
    vdd: VddConfig,
    /// `student` with the method's gating and number of experts.
    student: MoeConfig,
    clip_margin: Option<f32>,
    official_init: bool,
    act: ActMode,
    /// `vdd.<teacher>_gating_fit`: after distillation, a gating fitted to teacher samples.
    gating_fit: Option<GatingFitConfig>,
    /// `vdd.<teacher>_gating_visits`: that fit also on the states the student visits.
    gating_visits: Option<GatingVisits>,
    /// `vdd.<teacher>_expert_visits`: distillation continued on the states the student visits.
    expert_visits: Option<ExpertVisits>,
    /// `vdd.<teacher>_init` = `samples`: the student starts from a mixture fitted to teacher
    /// samples by `vdd.<teacher>_init_fit`.
    init_fit: Option<SampleFit>,
    /// `vdd.<teacher>_gating_temperature`: a learned gating sharpened after training.
    gating_temperature: Option<f32>,
}

/// An optional settings table that `false` switches off: a recipe cannot remove a table its
/// defaults set (`vdd.beso_expert_visits = false` trains without the rounds).
fn switchable<T: Serialize + serde::de::DeserializeOwned>(
    r: &MethodRecipe<'_>,
    key: &str,
) -> crate::Result<Option<T>> {
    match r.get_opt::<toml::Value>(key)? {
        None | Some(toml::Value::Boolean(false)) => Ok(None),
        Some(_) => r.get_opt(key),
    }
}

/// `vdd.<teacher>_init`: how the student starts.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum Init {
    /// The paper's start: a new mixture of the student's configuration, seeded by the run.
    Paper,
    /// The whole mixture fitted by EM to the teacher's samples (`vdd.<teacher>_init_fit`,
    /// [`SampleFit`]), then VDD from there.
    Samples,
}

impl Vdd {
    fn settings(&self, r: &MethodRecipe<'_>) -> crate::Result<Settings> {
        let t = r.row.teacher_key()?;
        let flag = |k: &str| r.get_opt::<bool>(k).map(|b| b.unwrap_or(false));
        let clamp = r.get_opt::<bool>(CLAMP)?.unwrap_or(true);
        Ok(Settings {
            vdd: r.get(&format!("vdd.{t}"))?,
            student: MoeConfig {
                gating: r.get_opt(&format!("vdd.{t}_gating"))?.unwrap_or(r.student.gating),
                num_experts: r
                    .get_opt(&format!("vdd.{t}_experts"))?
                    .unwrap_or(r.student.num_experts),
                ..r.student.clone()
            },
            clip_margin: if clamp { r.get_opt(CLIP)? } else { None },
            official_init: flag(INIT)?,
            act: ActMode {
                greedy_gating: flag(GREEDY)?,
                sample_action: flag(SAMPLE)?,
                hold_steps: 0,
            },
            gating_fit: r.get_opt(&format!("vdd.{t}_gating_fit"))?,
            gating_visits: r.get_opt(&format!("vdd.{t}_gating_visits"))?,
            expert_visits: switchable(r, &format!("vdd.{t}_expert_visits"))?,
            init_fit: match r.get_opt(&format!("vdd.{t}_init"))?.unwrap_or(Init::Paper) {
                Init::Paper => None,
                Init::Samples => {
                    Some(r.get_opt(&format!("vdd.{t}_init_fit"))?.ok_or_else(|| {
                        format!("vdd.{t}_init = \"samples\" needs its fit, vdd.{t}_init_fit")
                    })?)
                }
            },
            gating_temperature: r.get_opt(&format!("vdd.{t}_gating_temperature"))?,
        })
    }
}

impl Method for Vdd {
    fn info(&self) -> &Info {
        &INFO
    }
    fn keys(&self, row: &crate::row::Row) -> Vec<String> {
        let Ok(t) = row.teacher_key() else { return Vec::new() };
        let select = row.settings::<RowSettings>().is_ok_and(|s| s.select_checkpoint);
        let mut keys = if select { vec![SELECT_BY.to_owned()] } else { Vec::new() };
        keys.extend(vdd_keys(&t));
        keys
    }
    fn shadowed_keys(&self, row: &crate::row::Row) -> Vec<(String, Option<String>)> {
        let Ok(t) = row.teacher_key() else { return Vec::new() };
        vec![
            ("student.num_experts".into(), Some(format!("vdd.{t}_experts"))),
            ("student.gating".into(), Some(format!("vdd.{t}_gating"))),
        ]
    }
    fn check(&self, recipe: &MethodRecipe<'_>) -> crate::Result {
        let s = self.settings(recipe)?;
        let (t, learned) = (recipe.row.teacher_key()?, learned(recipe.row));
        let acts = learned || recipe.row.teacher.is_some_and(|t| t.loads_file());
        select_by(recipe)?;
        if s.gating_fit.is_some() && !learned {
            return Err(
                format!("vdd.{t}_gating_fit needs a learned teacher; {t} is not one").into()
            );
        }
        if let Some(fit) = &s.init_fit {
            if !acts {
                return Err(
                    format!("vdd.{t}_init = \"samples\" needs a teacher that samples").into()
                );
            }
            fit.validate().map_err(|e| format!("vdd.{t}_init_fit: {e}"))?;
        }
        if let Some(temp) = s.gating_temperature {
            // Checked before any training: `Moe::sharpen_gating` would refuse it only after.
            let learned_gating = s.student.gating == GatingKind::Learned;
            if !(temp.is_finite() && temp > 0.0) || (temp != 1.0 && !learned_gating) {
                return Err(format!(
                    "vdd.{t}_gating_temperature = {temp}: a finite positive temperature of a \
                     learned gating (vdd.{t}_gating = \"learned\"), or 1"
                )
                .into());
            }
        }
        if let Some(v) = s.gating_visits {
            if s.gating_fit.is_none() {
                return Err(format!(
                    "vdd.{t}_gating_visits needs vdd.{t}_gating_fit (the fit it feeds)"
                )
                .into());
            }
            if !(1..=MAX_VISIT_ROUNDS).contains(&v.rounds)
                || !(1..=MAX_VISIT_EPISODES).contains(&v.episodes)
            {
                return Err(format!(
                    "vdd.{t}_gating_visits: rounds must be in 1..={MAX_VISIT_ROUNDS} and \
                     episodes in 1..={MAX_VISIT_EPISODES}, got {} and {}",
                    v.rounds, v.episodes
                )
                .into());
            }
        }
        if let Some(v) = s.expert_visits {
            if !(1..=MAX_VISIT_ROUNDS).contains(&v.rounds)
                || !(1..=MAX_VISIT_EPISODES).contains(&v.episodes)
                || !(1..=MAX_VISIT_ITERATIONS).contains(&v.iterations)
            {
                return Err(format!(
                    "vdd.{t}_expert_visits: rounds must be in 1..={MAX_VISIT_ROUNDS}, episodes \
                     in 1..={MAX_VISIT_EPISODES} and iterations in 1..={MAX_VISIT_ITERATIONS}, \
                     got {}, {} and {}",
                    v.rounds, v.episodes, v.iterations
                )
                .into());
            }
            if !learned {
                return Err(format!("vdd.{t}_expert_visits needs a learned teacher").into());
            }
        }
        // The schedule's unit against the teacher's, before any training (its range is
        // checked against the trained teacher's when VDD starts).
        let unit = recipe.row.teacher.map_or(NoiseConvention::Sigma, |t| t.noise_unit());
        s.vdd
            .noise
            .check_teacher(s.vdd.noise_unit, unit, None)
            .and_then(|()| s.vdd.check(&s.student))
            .map_err(|e| format!("vdd.{t}: {e}"))?;
        Ok(())
    }

    fn check_loaded(&self, _row: &crate::row::Row, t: &teachers::LoadedTeacher) -> crate::Result {
        match t.obs_map() {
            // The student's deployment spec cannot carry the map yet: it would act on the
            // mapped observation and refuse the task's raw one.
            Some(m) => Err(format!(
                "{}: the teacher was imported with the observation map `{m}`, which a VDD \
                 student cannot carry yet; roll the teacher out alone with --methods teacher",
                t.file
            )
            .into()),
            None => Ok(()),
        }
    }

    fn train(&self, job: &Job<'_>) -> crate::Result<Trained> {
        let series = select_by(&job.recipe)?;
        self.train_selecting(job, series.as_deref())
    }
}

/// The name under which the snapshot kept by checkpoint selection is cached, beside the
/// final student cached as `name`.
fn selected_name(name: &str) -> String {
    format!("{name}-selected")
}

/// The series checkpoint selection maximises unless told otherwise (`vdd.select_by`): the
/// held-out task entropy, as the official code selects.
const DEFAULT_SELECTION: &str = vdd_tasks::avoiding::CURVE_ENTROPY;

/// The cache key of the snapshot selected by `series` from the training of key `hash`: the
/// training's own for the default series, one derived from both otherwise.
fn selected_key(hash: &str, series: &str) -> crate::Result<String> {
    if series == DEFAULT_SELECTION {
        return Ok(hash.to_owned());
    }
    Ok(recipe::config_hash(&json!({ "training": hash, "select_by": series }))?)
}

/// The curve series holding the selected checkpoint: `(iteration, value)`.
pub(super) const SELECTED_SERIES: &str = "selected checkpoint";

impl Vdd {
    /// Trains (or loads) the student; with `select_by`, the row's policy is the snapshot with
    /// the highest value of that curve series among the curves' checkpoints (the paper's
    /// checkpoint selection, [`vdd::Resumable::select_by`]) instead of the final iterate, and
    /// its curves gain [`SELECTED_SERIES`]. A training stores both in the student cache.
    fn train_selecting(&self, job: &Job<'_>, select_by: Option<&str>) -> crate::Result<Trained> {
        let (mut s, d, label) = (self.settings(&job.recipe)?, job.data, job.label);
        let row = job.recipe.row;
        let (t, name) = (row.teacher_key()?, cache_name(row));
        if let (Some(_), Some(v)) = (select_by, s.expert_visits) {
            // The rounds on visited states take no checkpoints: the same budget, all of it on
            // the demonstrations' states.
            s.expert_visits = None;
            s.vdd.iterations += v.rounds * v.iterations;
            crate::progress::log(format!(
                "[{label}] checkpoint selection: vdd.{t}_expert_visits's rounds take no \
                 checkpoints, so all {} iterations run on the demonstrations' states",
                s.vdd.iterations
            ));
        }
        if select_by.is_some() && job.curves.is_none() {
            return Err("checkpoint selection needs curves over training, and this run takes \
                        none (eval.curve_points = 0, or the task has no curves)"
                .into());
        }
        let vc = VddConfig { seed: job.seed, ..s.vdd.clone() };
        let teacher = if learned(row) { Some(job.teacher()?) } else { None };
        let (sn, an) = match (teacher, job.loaded) {
            (Some(t), _) => (t.teacher.normalizers().0.clone(), t.teacher.normalizers().1.clone()),
            // A file teacher's data come with its space.
            (None, Some(_)) => (d.state_normalizer.clone(), d.action_normalizer.clone()),
            (None, None) => {
                (Affine::identity(d.states.ncols()), Affine::identity(d.actions.ncols()))
            }
        };
        let states = sn.normalize_rows(d.states.as_ref())?;
        let actions = an.normalize_rows(d.actions.as_ref())?;
        let mut mc = s.student.clone();
        mc.state_dim = states.ncols();
        mc.action_dim = actions.ncols();
        let extra = s.expert_visits.map_or(0, |v| v.rounds * v.iterations);
        let iterations = vc.iterations + extra;
        let budget = Budget::student(
            vc.expert_steps() + (extra * vc.expert_steps_per_iter) as u64,
            vc.batch_size * vc.vi_samples,
        )
        .with_prefit(s.init_fit.as_ref().map_or(0, |f| f.budget_samples(states.nrows())));
        let teacher_id = match (teacher, job.loaded) {
            (Some(t), _) => {
                let teachers = &job.recipe.teachers;
                let teacher_config = match t.teacher.kind() {
                    TeacherKind::Beso => serde_json::to_value(&teachers.beso)?,
                    TeacherKind::Ddpm => serde_json::to_value(&teachers.ddpm)?,
                };
                Some((teacher_config, t.hash.clone()))
            }
            // The file's bytes determine the teacher, wherever it lies.
            (None, Some(l)) => Some((json!("file"), l.hash.clone())),
            (None, None) => None,
        };
        let cache = match (job.students, teacher_id) {
            (Some(cache), Some((teacher_config, teacher_hash))) => {
                let mut key = json!({
                    "version": STUDENT_CACHE_VERSION,
                    "teacher": teacher_config,
                    "teacher_hash": teacher_hash,
                    "student": keyed_student(&mc),
                    // The unit only checks the schedule; it never changes a student.
                    "vdd": VddConfig { noise_unit: None, ..vc.clone() },
                    "clip_margin": s.clip_margin,
                });
                if let Some(c) = job.curves {
                    // Cached students carry their curves over training.
                    key["curves"] = c.key();
                }
                if s.official_init {
                    key["official_init"] = json!(true);
                }
                if let Some(v) = s.expert_visits {
                    key["expert_visits"] = json!(v);
                }
                if let Some(fit) = &s.init_fit {
                    key["init_fit"] = json!(fit);
                }
                Some((cache, recipe::config_hash(&key)?))
            }
            _ => None,
        };
        // A training without selection keeps the default selection's snapshot as well, so a
        // selecting row of the same training (the same cache key) loads it instead of
        // training again. Rounds on visited states would make that training another one.
        let keep = select_by.or_else(|| {
            let curves =
                job.curves.is_some_and(|c| c.series().iter().any(|x| x == DEFAULT_SELECTION));
            (curves && cache.is_some() && s.expert_visits.is_none()).then_some(DEFAULT_SELECTION)
        });
        let selected = selected_name(&name);
        let lookup = |c: &StudentCache<'_>, hash: &str| -> crate::Result<_> {
            Ok(match select_by {
                Some(series) => c.load(&selected, &selected_key(hash, series)?)?,
                None => c.load(&name, hash)?,
            })
        };
        // Another job of this run training the same student: wait for it, then load.
        let claim = cache.as_ref().map(|(c, hash)| c.claim(&name, hash));
        let hit = cache.as_ref().map(|(c, hash)| lookup(c, hash)).transpose()?.flatten();
        let (trained, noise_level, curve_seconds) = match hit {
            Some(c) => {
                crate::progress::log(format!("[{label}] student loaded from the cache"));
                (c, None, 0.0)
            }
            None => {
                let clip = s.clip_margin;
                let (psn, pan, act) = (sn.clone(), an.clone(), s.act);
                let policy = move |mut student: Moe| -> crate::Result<TrainedPolicy> {
                    student.set_normalizers(Some(psn.clone()), Some(pan.clone()))?;
                    student.set_act_mode(act);
                    Ok(TrainedPolicy::Moe(Box::new(student)))
                };
                // The demonstrations again for the rounds on visited states.
                let demos = s.expert_visits.map(|_| (states.clone(), actions.clone()));
                let data = DistillData::new(states, Some(actions))?;
                let mut student = Moe::from_config(mc, vc.seed)?;
                if s.official_init {
                    vdd::init_official(&mut student, vc.seed)?;
                }
                let key = format!("vdd.{t}");
                let fit = s.init_fit.as_ref().map(|f| (f, data.states(), job));
                let run = DistillRun { clip_margin: clip, job, policy: &policy, select_by: keep };
                let mut fit_seconds = 0.0;
                let (mut c, mut chosen, noise, curve_seconds) = match (teacher, job.loaded) {
                    (Some(tt), _) => {
                        let student = fitted(fit, &tt.teacher, student, &t, &mut fit_seconds)?;
                        distill(vc.clone(), tt.teacher.clone(), student, data, run)
                            .map_err(|e| e.context(key.clone()))?
                    }
                    (None, Some(l)) => {
                        let student = fitted(fit, &l.teacher, student, &t, &mut fit_seconds)?;
                        distill(vc.clone(), l.teacher.clone(), student, data, run)
                            .map_err(|e| e.context(key.clone()))?
                    }
                    (None, None) => {
                        let exact = d.exact.clone().ok_or("the task has no exact teacher")?;
                        distill(vc.clone(), exact, student, data, run)
                            .map_err(|e| e.context(key.clone()))?
                    }
                };
                // The fit to the teacher's samples is part of the training.
                c.train_seconds += fit_seconds;
                chosen.iter_mut().for_each(|x| x.train_seconds += fit_seconds);
                if let (Some(v), Some(t), Some(demos)) = (s.expert_visits, teacher, demos) {
                    let run =
                        DistillRun { clip_margin: clip, job, policy: &policy, select_by: None };
                    c = distill_on_visits(c, (v, &vc, &sn), t, demos, run)
                        .map_err(|e| e.context(format!("{key}_expert_visits")))?;
                }
                if let Some((cache, hash)) = &cache {
                    let path = cache.store(&name, hash, &c)?;
                    let (secs, path) = (c.train_seconds, teachers::rel(&path));
                    crate::progress::log(format!(
                        "[{label}] trained in {secs:.1} s; cached as {path}"
                    ));
                    if let (Some(chosen), Some(series)) = (&chosen, keep) {
                        cache.store(&selected, &selected_key(hash, series)?, chosen)?;
                    }
                }
                let c = match (select_by, chosen) {
                    (None, _) => c,
                    (Some(_), Some(chosen)) => chosen,
                    (Some(series), None) => {
                        return Err(format!(
                            "checkpoint selection by `{series}`: the run took no checkpoint"
                        )
                        .into());
                    }
                };
                (c, Some(noise), curve_seconds)
            }
        };
        drop(claim);
        let CachedStudent { mut student, mut train_seconds, curves } = trained;
        student.set_normalizers(Some(sn), Some(an))?;
        if let (Some(fit), Some(trained_teacher)) = (&s.gating_fit, teacher) {
            let t0 = std::time::Instant::now();
            student = fit_gating(student, (&t, &s), fit, trained_teacher, job)?;
            train_seconds += t0.elapsed().as_secs_f64();
        }
        if let Some(temp) = s.gating_temperature.filter(|&temp| temp != 1.0) {
            student
                .sharpen_gating(temp)
                .map_err(|e| format!("vdd.{t}_gating_temperature = {temp}: {e}"))?;
        }
        student.set_act_mode(s.act);
        Ok(Trained {
            teacher_seconds: teacher.map(|t| t.train_seconds),
            iterations: Some(iterations),
            noise_level,
            budget: Some(budget),
            curve_seconds,
            deploy: job.loaded.map(|l| l.chunk_deploy_spec()),
            ..Trained::new(TrainedPolicy::Moe(Box::new(student)), train_seconds, curves)
        })
    }
}

/// `student` fitted by EM to samples of `teacher` at the distillation's states (normalised;
/// `fit`: `vdd.<key>_init_fit`, the states and the job), or `student` as it is without a fit;
/// the fit's wall-clock seconds in `seconds`.
fn fitted<T: ScoreModel + Clone + Send>(
    fit: Option<(&SampleFit, MatRef<'_, f32>, &Job<'_>)>,
    teacher: &T,
    student: Moe,
    key: &str,
    seconds: &mut f64,
) -> crate::Result<Moe> {
    let Some((fit, states, job)) = fit else { return Ok(student) };
    let t0 = std::time::Instant::now();
    let context = |e: crate::LabError| e.context(format!("vdd.{key}_init_fit"));
    let (label, seed) = (job.label, job.seed);
    let bar = crate::progress::bar(fit.blocks as u64, &format!("{label}: teacher samples"));
    let workers = vdd_nn::parallel::Workers::new(0)?;
    let (s, a) = fit.draw(teacher, states, seed, &workers, &|| bar.inc(1)).map_err(context)?;
    bar.finish_and_clear();
    let bar = crate::progress::bar(fit.em.iterations as u64, &format!("{label}: EM fit"));
    let student = fit
        .fit(student, s, a, seed, |ll| {
            bar.inc(1);
            bar.set_message(format!("log-lik {ll:.3}"));
        })
        .map_err(context)?;
    bar.finish_and_clear();
    *seconds = t0.elapsed().as_secs_f64();
    Ok(student)
}

/// `student` as it enters a student's cache key: a uniform gating has no network, so its
/// architecture (which only a later gating fit uses) does not change the student and is left
/// out; varying the fit then reuses the cached distillation.
fn keyed_student(student: &MoeConfig) -> MoeConfig {
    let mut keyed = student.clone();
    if keyed.gating == GatingKind::Uniform {
        keyed.gating_network = NetworkConfig::default();
    }
    keyed
}

/// Fits a learned gating of `student` (experts frozen) to samples of `t` at the demonstration
/// states, and at the states the student visits when `s.gating_visits` asks for them.
fn fit_gating(
    mut student: Moe,
    (key, s): (&str, &Settings),
    fit: &GatingFitConfig,
    t: &teachers::TrainedTeacher,
    job: &Job<'_>,
) -> crate::Result<Moe> {
    let (label, d) = (job.label, job.data);
    let network = s.student.gating_network.clone();
    let mut states = d.states.clone();
    let rounds = s.gating_visits.map_or(1, |v| v.rounds);
    for round in 0..rounds {
        let t0 = std::time::Instant::now();
        let mut seed = job.seed;
        if let Some(v) = s.gating_visits {
            let visits = job.visits.ok_or_else(|| {
                format!("vdd.{key}_gating_visits: the task has no rollouts to visit states")
            })?;
            let mut acting = student.clone();
            acting.set_act_mode(s.act);
            let policy = TrainedPolicy::Moe(Box::new(acting));
            let root = vdd_core::Seeds::new(job.seed).child("gating-visits");
            let visit_seed: u64 = root.stream_indexed("episodes", round as u64).random();
            let visited = visits.visit(&policy, visit_seed, v.episodes)?;
            crate::progress::log(format!(
                "[{label}] round {}: the student visited {} states in {} episodes",
                round + 1,
                visited.nrows(),
                v.episodes
            ));
            states = stacked(&states, &visited)?;
            seed = root.stream_indexed("fit", round as u64).random();
        }
        let fit = GatingFitConfig { seed, ..fit.clone() };
        let bar = crate::progress::bar(fit.iterations as u64, &format!("{label}: gating fit"));
        let progress = |p| match p {
            GatingFitProgress::Sampling { pairs } => bar.set_message(format!("{pairs} samples")),
            GatingFitProgress::Iteration { log_likelihood: ll, .. } => {
                bar.inc(1);
                bar.set_message(format!("log-lik {ll:.3}"));
            }
            _ => {}
        };
        let report;
        (student, report) = fit_gating_to_policy_with_progress(
            student,
            network.clone(),
            &mut t.teacher.clone(),
            states.as_ref(),
            &fit,
            progress,
        )?;
        bar.finish_and_clear();
        let secs = t0.elapsed().as_secs_f64();
        crate::progress::log(format!(
            "[{label}] gating fitted to {} teacher samples in {secs:.1} s: their \
             log-likelihood {:.3} -> {:.3} nats",
            report.pairs, report.log_likelihood_before, report.log_likelihood_after
        ));
    }
    Ok(student)
}

/// How [`distill`] runs, besides what it distils.
struct DistillRun<'a> {
    /// [`ClampedDenoiser::around_data`]'s margin (`None`: the raw score).
    clip_margin: Option<f32>,
    /// The job (checkpoints, curves, label).
    job: &'a Job<'a>,
    /// A snapshot of the student as a policy on raw states, for the curves over training.
    policy: &'a dyn Fn(Moe) -> crate::Result<TrainedPolicy>,
    /// [`vdd::Resumable::select_by`].
    select_by: Option<&'a str>,
}

/// Seconds of VDD training between checkpoints.
const CHECKPOINT_SECONDS: u64 = 10;

/// Distils `teacher` into `student`, freshly initialised, with VDD (states and actions in
/// the student's normalised space; the student initialised from the run seed `vc.seed`), with a
/// progress bar and learning curves; also returns the snapshot `select_by` chose (with its
/// point in [`SELECTED_SERIES`] of its curves), the mean noise level of the teacher queries
/// and the seconds the curves over training took.
///
/// The run is a [`Resumable`] one: it commits a checkpoint every [`CHECKPOINT_SECONDS`] of
/// training to `<run>/checkpoints/<label>/`, resumes from there under `--resume` and removes it
/// when done; `policy` makes a snapshot of the student a policy on raw states for the curves
/// over training ([`crate::method::CurveProbe`]).
fn distill<S: ScoreModel>(
    vc: VddConfig,
    teacher: S,
    student: Moe,
    data: DistillData,
    run: DistillRun<'_>,
) -> crate::Result<(CachedStudent, Option<CachedStudent>, f32, f64)> {
    let DistillRun { clip_margin, job, policy, select_by } = run;
    // The demonstrations' actions: the data's own, or the gating step's pairs'.
    let actions = data.actions().or(data.gating_pairs().map(|p| p.1));
    let teacher = match (clip_margin, actions) {
        (Some(m), Some(a)) => ClampedDenoiser::around_data(teacher, a, m)?,
        (Some(_), None) => {
            return Err("internal: clamping needs the demonstrations' actions".into());
        }
        (None, _) => ClampedDenoiser::unclamped(teacher),
    };
    let root = job.checkpoints.0.join(job.label.replace(' ', "-"));
    let run = Resumable {
        dir: &root,
        resume: job.checkpoints.1,
        every_seconds: CHECKPOINT_SECONDS,
        select_by,
    };
    let bar = crate::progress::bar(vc.iterations as u64, job.label);
    let report = |m: &vdd::IterationMetrics| {
        bar.set_position(m.iteration as u64 + 1);
        if m.iteration % 100 == 0 {
            bar.set_message(format!("H(z|s) {:.2}", m.gating_entropy));
        }
    };
    let mut probe = job.probe();
    let out = run.run((vc, teacher, student, data), &mut probe, policy, report)?;
    bar.finish_and_clear();
    let _ = std::fs::remove_dir(job.checkpoints.0); // when empty
    let ResumableOutcome { student, train_seconds, curves, mean_noise_level, selected } = out;
    let chosen = selected.map(|c| {
        let mut curves = curves.clone();
        curves.insert(SELECTED_SERIES.to_owned(), vec![(c.iteration as f64, c.value)]);
        CachedStudent { student: c.student, train_seconds, curves }
    });
    let last = CachedStudent { student, train_seconds, curves };
    Ok((last, chosen, mean_noise_level, probe.seconds))
}

#[cfg(test)]
mod tests;
