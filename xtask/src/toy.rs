//! The toy recipes (`recipes/toy-gmm.toml`, `recipes/toy-conditional.toml`).
//!
//! * `toy-gmm`: the paper's 2-D toy. VDD distils a teacher of the 8-mode circle mixture — the
//!   exact score (`vdd-exact`), or a learned DDPM / BESO teacher trained on 5000 samples
//!   (`vdd-ddpm`, `vdd-beso`; cached like every learned teacher) — into 8 diagonal experts,
//!   then measures reverse/forward KL against the exact density by Monte Carlo, modes covered
//!   and training speed.
//! * `toy-conditional`: the rotating-modes toy (mode `k` at angle `s + 2πk/K`) distilled from its
//!   exact teacher with a learned gating trained on dataset actions; coverage and KL at 8
//!   evaluation states.
//!
//! `metrics.json` has the common `methods.<method>` layout ([`crate::report`]) and, for the
//! first method, the top-level keys of the original command: `reverse_kl`, `forward_kl`,
//! `modes_covered` (the minimum over seeds), `ms_per_iter`, `train_seconds` (means over seeds)
//! for `toy-gmm`; `states_fully_covered` (minimum), `mean_reverse_kl`, `mean_forward_kl`,
//! `ms_per_iter`, `train_seconds` and the first seed's per-state results for `toy-conditional`.
//! KL and coverage are computed in the student's (teacher-normalised) action space with the
//! target transformed alike; KL is invariant under that affine map, and coverage distances are
//! measured after mapping the experts' means back to raw actions.

use std::time::Instant;

use faer::Mat;
use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use vdd::{DistillData, Vdd, VddConfig, eval};
use vdd_core::gmm::{Gmm, GmmTeacher};
use vdd_core::{Affine, ScoreModel, Seeds};
use vdd_diffusion::TeacherKind;
use vdd_moe::{GatingKind, Moe, MoeConfig};

use crate::avoiding::vdd_config_for;
use crate::context::RunContext;
use crate::methods::{self, Method};
use crate::plots::{self, DensityPanel, ExpertEllipse};
use crate::recipe::{self, Overrides};
use crate::report::{self, Row};
use crate::teachers::{self, TeachersConfig};

/// A toy recipe: the schema of the recipe files; the values not given there come from
/// `recipes/defaults/` ([`Self::defaults`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToyRecipe {
    /// Recipe name.
    pub name: String,
    /// What it shows.
    pub description: String,
    /// `toy-gmm` or `toy-conditional`.
    pub task: String,
    /// Run seeds.
    pub seeds: Vec<u64>,
    /// Methods (`vdd-exact`; `toy-gmm` also `vdd-ddpm`, `vdd-beso`).
    pub methods: Vec<String>,
    /// Data.
    pub data: ToyData,
    /// Learned teachers (trained on `data.points` samples of the mixture).
    pub teachers: TeachersConfig,
    /// The student (`state_dim` / `action_dim` come from the task).
    pub student: MoeConfig,
    /// VDD for each teacher.
    pub vdd: ToyVdd,
    /// Evaluation.
    pub eval: ToyEval,
    /// Figure 2.
    pub plots: ToyPlots,
}

/// Data of a toy recipe.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToyData {
    /// Number of states (and mixture samples) VDD distils on; learned teachers train on them.
    pub points: usize,
}

/// VDD for each teacher.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToyVdd {
    /// Exact mixture score.
    pub exact: VddConfig,
    /// Learned BESO teacher (noise levels in σ).
    pub beso: VddConfig,
    /// Learned DDPM teacher (noise levels in time `t`).
    pub ddpm: VddConfig,
}

/// Evaluation of a toy recipe.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToyEval {
    /// Monte-Carlo samples per KL estimate (and per evaluation state).
    pub kl_samples: usize,
    /// Evaluation states of `toy-conditional` (`s_i = (i + 0.5) 2π / n`).
    pub eval_states: usize,
    /// A mode is covered when an expert mean lies within this distance.
    pub coverage_radius: f32,
    /// ... and that expert's gating weight is at least this.
    pub min_weight: f32,
}

/// Figure 2 settings.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ToyPlots {
    /// Write the figure.
    pub enabled: bool,
    /// Also PNG.
    pub png: bool,
    /// Density grid cells per side.
    pub grid: usize,
    /// Score arrows per side.
    pub arrows: usize,
    /// Half-width of the plotted square.
    pub extent: f32,
    /// Panels of `toy-conditional` (states spread over `[0, 2π)`).
    pub states: usize,
}

/// `recipes/defaults/toy-gmm.toml` and the `toy-conditional` keys merged on top of it,
/// embedded so that the binary is self-contained.
const DEFAULTS: [(&str, &str); 2] = [
    ("recipes/defaults/toy-gmm.toml", include_str!("../../recipes/defaults/toy-gmm.toml")),
    (
        "recipes/defaults/toy-conditional.toml",
        include_str!("../../recipes/defaults/toy-conditional.toml"),
    ),
];

impl ToyRecipe {
    /// The defaults of `task` (`toy-gmm` or `toy-conditional`), from `recipes/defaults/`,
    /// which a recipe file overrides.
    pub fn defaults(task: &str) -> recipe::RecipeResult<Self> {
        match task {
            "toy-gmm" => recipe::defaults_from_toml(&DEFAULTS[..1]),
            "toy-conditional" => recipe::defaults_from_toml(&DEFAULTS),
            other => Err(format!("no toy task `{other}` (toy-gmm, toy-conditional)")),
        }
    }
}

/// Translates the original commands' options into recipe overrides: `toy-gmm --teacher X`
/// (methods = `vdd-X`), `--iterations N`; `toy-conditional --iterations N --experts N --lr X
/// --weighting gating|uniform`.
pub fn apply_shorthands(
    task: &str,
    shorthands: &[(String, String)],
    o: &mut Overrides,
) -> Result<(), String> {
    let mut teacher = "exact".to_owned();
    for (k, v) in shorthands {
        if k == "teacher" {
            if task != "toy-gmm" {
                return Err(format!("--teacher is a toy-gmm option; use --methods for `{task}`"));
            }
            if !["exact", "ddpm", "beso"].contains(&v.as_str()) {
                return Err(format!("unknown teacher `{v}` (exact|ddpm|beso)"));
            }
            teacher = v.clone();
            o.methods = Some(vec![format!("vdd-{v}")]);
        }
    }
    for (k, v) in shorthands {
        let sets: Vec<(String, String)> = match (task, k.as_str()) {
            (_, "teacher") => continue,
            ("toy-gmm" | "toy-conditional", "iterations") => {
                let t = if task == "toy-gmm" { teacher.as_str() } else { "exact" };
                vec![(format!("vdd.{t}.iterations"), v.clone())]
            }
            ("toy-conditional", "experts") => vec![("student.num_experts".into(), v.clone())],
            ("toy-conditional", "lr") => vec![
                ("vdd.exact.expert_optimizer.lr".into(), v.clone()),
                ("vdd.exact.gating_optimizer.lr".into(), v.clone()),
            ],
            ("toy-conditional", "weighting") => {
                if !["gating", "uniform"].contains(&v.as_str()) {
                    return Err(format!("unknown weighting `{v}` (gating|uniform)"));
                }
                vec![("vdd.exact.expert_weighting".into(), format!("\"{v}\""))]
            }
            _ => return Err(format!("option --{k} does not apply to task `{task}`")),
        };
        o.sets.extend(sets);
    }
    Ok(())
}

/// The teacher a toy method distils.
enum ToyTeacher {
    Exact(Box<GmmTeacher>),
    Learned(Box<teachers::TrainedTeacher>),
}

/// Everything the student needs to be evaluated in raw coordinates.
struct Distilled {
    student: Moe,
    /// The student's (= teacher's) normalisers.
    state_norm: Affine,
    action_norm: Affine,
    train_seconds: f64,
    teacher_seconds: Option<f64>,
    iterations: usize,
    teacher: ToyTeacher,
    noise_level: f32,
}

fn distil(
    method: Method,
    cfg: &ToyRecipe,
    seed: u64,
    ctx: &RunContext,
    label: &str,
) -> crate::XResult<Distilled> {
    let task = vdd_tasks::toy::CircleGmm::toy_conditional();
    let conditional = cfg.task == "toy-conditional";
    let n = cfg.data.points;
    if n == 0 {
        return Err("data.points must be positive".into());
    }
    // Data: the toy-gmm state is constant (0); toy-conditional samples states and actions.
    let (states, actions) = if conditional {
        task.sample(n, seed)?
    } else {
        let mut gmm = GmmTeacher::circle_toy();
        let states = Mat::<f32>::zeros(n, 1);
        let actions = gmm.sample(states.as_ref(), &mut Seeds::new(seed).stream("toy-data"))?;
        (states, actions)
    };
    let (vc, teacher) = match method {
        Method::VddExact => {
            let t = if conditional { task.teacher()? } else { GmmTeacher::circle_toy() };
            (&cfg.vdd.exact, ToyTeacher::Exact(Box::new(t)))
        }
        Method::VddBeso | Method::VddDdpm => {
            let kind = method.teacher().ok_or("no teacher")?;
            let t = teachers::train_or_load(
                kind,
                &cfg.teachers,
                states.as_ref(),
                actions.as_ref(),
                seed,
                &ctx.cache_dir,
                ctx.fresh,
                &format!("{} s{seed}", teachers::kind_name(kind)),
            )?;
            let vc = if kind == TeacherKind::Beso { &cfg.vdd.beso } else { &cfg.vdd.ddpm };
            (vc, ToyTeacher::Learned(Box::new(t)))
        }
        other => {
            return Err(format!("method `{}` is not available on toy tasks", other.name()).into());
        }
    };
    let vc: VddConfig = vdd_config_for(vc, seed);
    let (state_norm, action_norm) = match &teacher {
        ToyTeacher::Exact(_) => (Affine::identity(1), Affine::identity(2)),
        ToyTeacher::Learned(t) => {
            let (s, a) = t.teacher.normalizers();
            (s.clone(), a.clone())
        }
    };
    let norm = |m: &Mat<f32>, a: &Affine| {
        Mat::from_fn(m.nrows(), m.ncols(), |i, j| (m[(i, j)] - a.offset[j]) / a.scale[j])
    };
    let mut student_cfg = cfg.student.clone();
    student_cfg.state_dim = 1;
    student_cfg.action_dim = 2;
    let data = if student_cfg.gating == GatingKind::Learned {
        DistillData::new(norm(&states, &state_norm), Some(norm(&actions, &action_norm)))?
    } else {
        DistillData::from_states(norm(&states, &state_norm))?
    };
    let iterations = vc.iterations;
    let bar = crate::progress::bar(iterations as u64, label);
    let mut noise_sum = 0.0f64;
    let mut callback = |m: &vdd::IterationMetrics| {
        bar.inc(1);
        noise_sum += f64::from(m.expert.noise_level);
        if m.iteration % 50 == 0 {
            bar.set_message(format!(
                "|g| {:.3}, H(z|s) {:.3}",
                m.expert.corrected_score_rms, m.gating_entropy
            ));
        }
    };
    let t0 = Instant::now();
    let (student, teacher) = match teacher {
        ToyTeacher::Exact(mut t) => {
            let mut vdd = Vdd::from_config(vc, t.as_mut(), student_cfg, data)?;
            vdd.train(&mut callback)?;
            (vdd.into_student(), ToyTeacher::Exact(t))
        }
        ToyTeacher::Learned(mut t) => {
            let mut vdd = Vdd::from_config(vc, &mut t.teacher, student_cfg, data)?;
            vdd.train(&mut callback)?;
            (vdd.into_student(), ToyTeacher::Learned(t))
        }
    };
    let train_seconds = t0.elapsed().as_secs_f64();
    bar.finish_and_clear();
    let teacher_seconds = match &teacher {
        ToyTeacher::Learned(t) => Some(t.train_seconds),
        ToyTeacher::Exact(_) => None,
    };
    Ok(Distilled {
        student,
        state_norm,
        action_norm,
        train_seconds,
        teacher_seconds,
        iterations,
        teacher,
        noise_level: (noise_sum / iterations.max(1) as f64) as f32,
    })
}

/// KL both ways and coverage of the student at raw state `s` against the exact mixture `truth`.
fn evaluate_at(
    d: &mut Distilled,
    truth: &Gmm,
    s: f32,
    samples: usize,
    cfg: &ToyEval,
    seeds: &Seeds,
    index: u64,
) -> crate::XResult<(f64, f64, usize)> {
    let an = d.action_norm.clone();
    let log_det: f32 = an.scale.iter().map(|c| c.ln()).sum();
    let s_n = [(s - d.state_norm.offset[0]) / d.state_norm.scale[0]];
    // log p in the normalised space: p_n(a_n) = p(denorm(a_n)) · Π scale.
    let log_p = |a: &[f32]| {
        let raw = [a[0] * an.scale[0] + an.offset[0], a[1] * an.scale[1] + an.offset[1]];
        truth.log_density(&raw, 0.0).map(|l| l + log_det).unwrap_or(f32::NEG_INFINITY)
    };
    let reverse = eval::reverse_kl(
        &mut d.student,
        &s_n,
        log_p,
        samples,
        &mut seeds.stream_indexed("reverse", index),
    )?;
    let mut rng = seeds.stream_indexed("forward", index);
    let mut target = Mat::zeros(samples, 2);
    let mut a = [0.0f32; 2];
    for i in 0..samples {
        truth.sample_into(&mut rng, &mut a);
        for j in 0..2 {
            target[(i, j)] = (a[j] - an.offset[j]) / an.scale[j];
        }
    }
    let forward = eval::forward_kl(&mut d.student, &s_n, log_p, target.as_ref())?;
    // Coverage in raw coordinates.
    d.student.forward(faer::MatRef::from_row_major_slice(&s_n, 1, 1))?;
    let out = d.student.output();
    let lg = out.log_gating_row(0);
    let covered = (0..truth.num_components())
        .filter(|&k| {
            let m = truth.mean(k);
            (0..out.num_experts).any(|z| {
                let mu = out.mean(0, z);
                let raw = [mu[0] * an.scale[0] + an.offset[0], mu[1] * an.scale[1] + an.offset[1]];
                let dist = ((raw[0] - m[0]).powi(2) + (raw[1] - m[1]).powi(2)).sqrt();
                lg[z].exp() >= cfg.min_weight && dist <= cfg.coverage_radius
            })
        })
        .count();
    Ok((reverse, forward, covered))
}

/// One panel of Figure 2 at raw state `s`.
fn density_panel(
    d: &mut Distilled,
    s: f32,
    title: String,
    modes: Vec<(f32, f32)>,
    p: &ToyPlots,
) -> crate::XResult<DensityPanel> {
    let (sn, an) = (d.state_norm.clone(), d.action_norm.clone());
    let s_n = (s - sn.offset[0]) / sn.scale[0];
    let e = p.extent;
    let n = p.grid.max(2);
    let h = 2.0 * e / n as f32;
    let norm_point =
        |x: f32, y: f32| [(x - an.offset[0]) / an.scale[0], (y - an.offset[1]) / an.scale[1]];
    let mut pts = Mat::<f32>::zeros(n * n, 2);
    for i in 0..n {
        for j in 0..n {
            let q = norm_point(-e + (j as f32 + 0.5) * h, -e + (i as f32 + 0.5) * h);
            pts[(i * n + j, 0)] = q[0];
            pts[(i * n + j, 1)] = q[1];
        }
    }
    let log_q = eval::student_log_density(&mut d.student, &[s_n], pts.as_ref())?;
    let density: Vec<f32> = log_q.iter().map(|l| l.exp()).collect();
    // Score field of the teacher at its VDD noise level, mapped to raw coordinates.
    let k = p.arrows.max(2);
    let spacing = 2.0 * e / k as f32;
    let mut apts = Mat::<f32>::zeros(k * k, 2);
    let mut raw_pos = Vec::with_capacity(k * k);
    for i in 0..k {
        for j in 0..k {
            let (x, y) = (-e + (j as f32 + 0.5) * spacing, -e + (i as f32 + 0.5) * spacing);
            let q = norm_point(x, y);
            apts[(i * k + j, 0)] = q[0];
            apts[(i * k + j, 1)] = q[1];
            raw_pos.push((x, y));
        }
    }
    let states = Mat::from_fn(k * k, 1, |_, _| s_n);
    let levels = vec![d.noise_level; k * k];
    let mut score = Mat::<f32>::zeros(k * k, 2);
    match &mut d.teacher {
        ToyTeacher::Exact(t) => t.score(apts.as_ref(), states.as_ref(), &levels, score.as_mut())?,
        ToyTeacher::Learned(t) => {
            t.teacher.score(apts.as_ref(), states.as_ref(), &levels, score.as_mut())?
        }
    }
    let arrows = raw_pos
        .iter()
        .enumerate()
        .map(|(r, &pos)| {
            let (gx, gy) = (score[(r, 0)] / an.scale[0], score[(r, 1)] / an.scale[1]);
            let len = (gx * gx + gy * gy).sqrt().max(1e-12);
            // Direction at a fixed length, shortened where the field is weak.
            let l = 0.4 * spacing * (len / (len + 0.5));
            (pos, (gx / len * l, gy / len * l))
        })
        .collect();
    d.student.forward(faer::MatRef::from_row_major_slice(&[s_n], 1, 1))?;
    let out = d.student.output();
    let experts = (0..out.num_experts)
        .map(|z| {
            let mu = out.mean(0, z);
            let l = out.scale(0, z);
            let (l00, l10, l11) = (l[0], l[2], l[3]);
            let (c00, c01, c11) = (l00 * l00, l00 * l10, l10 * l10 + l11 * l11);
            let (s0, s1) = (an.scale[0], an.scale[1]);
            ExpertEllipse {
                mean: (mu[0] * s0 + an.offset[0], mu[1] * s1 + an.offset[1]),
                cov: (c00 * s0 * s0, c01 * s0 * s1, c11 * s1 * s1),
                weight: out.log_gating_row(0)[z].exp(),
            }
        })
        .collect();
    Ok(DensityPanel { title, extent: e, density, n, arrows, experts, modes })
}

fn circle_modes(k: usize, offset: f32) -> Vec<(f32, f32)> {
    (0..k)
        .map(|i| {
            let a = offset + std::f32::consts::TAU * i as f32 / k as f32;
            (2.0 * a.cos(), 2.0 * a.sin())
        })
        .collect()
}

/// Runs a toy recipe.
pub fn run_recipe(ctx: &RunContext, task: &str) -> crate::XResult {
    let resolved = recipe::resolve(&ToyRecipe::defaults(task)?, &ctx.file, &ctx.overrides)?;
    let base = &resolved.base;
    if base.task != task {
        return Err(format!("recipe task `{}` changed to `{task}`", base.task).into());
    }
    if base.seeds.is_empty() {
        return Err("the recipe lists no seeds".into());
    }
    let mut plan: Vec<(String, Method, &ToyRecipe)> = Vec::new();
    for (variant, cfg) in resolved.configs() {
        for m in methods::parse_methods(&cfg.methods, task)? {
            plan.push((methods::label(m, variant.map(|v| v.name.as_str())), m, cfg));
        }
    }
    let dir = ctx.run_dir(&base.seeds);
    ctx.write_resolved(&dir, &resolved.to_toml()?)?;
    let conditional = task == "toy-conditional";
    let k = 8;
    let mut rows: Vec<(String, Vec<Row>)> =
        plan.iter().map(|(l, _, _)| (l.clone(), Vec::new())).collect();
    let mut panels = Vec::new();
    let mut first_states: Option<Value> = None;
    let mut teacher_log: Vec<Value> = Vec::new();
    for (si, &seed) in base.seeds.iter().enumerate() {
        for (pi, (label, method, cfg)) in plan.iter().enumerate() {
            let tag = format!("{label} s{seed}");
            let mut d = distil(*method, cfg, seed, ctx, &tag)?;
            if let ToyTeacher::Learned(t) = &d.teacher {
                teacher_log.push(teachers::cache_entry(t.teacher.kind(), seed, t));
            }
            let seeds = Seeds::new(seed).child("toy-eval");
            let ms_per_iter = d.train_seconds * 1e3 / d.iterations.max(1) as f64;
            let mut row = Row::new();
            row.insert("seed".into(), json!(seed));
            if conditional {
                let n_states = cfg.eval.eval_states.max(1);
                let mut states = Vec::new();
                for i in 0..n_states {
                    let s = (i as f32 + 0.5) * std::f32::consts::TAU / n_states as f32;
                    let truth = Gmm::circle(k, 2.0, 0.5, s)?;
                    let (rev, fwd, cov) = evaluate_at(
                        &mut d,
                        &truth,
                        s,
                        cfg.eval.kl_samples,
                        &cfg.eval,
                        &seeds,
                        i as u64,
                    )?;
                    states.push(json!({"state": s, "modes_covered": cov, "reverse_kl": rev, "forward_kl": fwd}));
                }
                let mean = |key: &str| {
                    states.iter().filter_map(|v| v[key].as_f64()).sum::<f64>() / states.len() as f64
                };
                let full =
                    states.iter().filter(|v| v["modes_covered"].as_u64() == Some(k as u64)).count();
                row.insert("states_fully_covered".into(), json!(full));
                row.insert("eval_states".into(), json!(n_states));
                row.insert("mean_reverse_kl".into(), report::json_f64(mean("reverse_kl")));
                row.insert("mean_forward_kl".into(), report::json_f64(mean("forward_kl")));
                crate::progress::log(format!(
                    "[{tag}] all {k} modes covered at {full}/{n_states} states, mean reverse KL {:.4}, mean forward KL {:.4} nats, {:.2} s",
                    mean("reverse_kl"),
                    mean("forward_kl"),
                    d.train_seconds
                ));
                row.insert("states".into(), Value::Array(states.clone()));
                if si == 0 && pi == 0 {
                    first_states = Some(Value::Array(states));
                }
            } else {
                let truth = Gmm::circle(k, 2.0, 0.5, 0.0)?;
                let (rev, fwd, cov) =
                    evaluate_at(&mut d, &truth, 0.0, cfg.eval.kl_samples, &cfg.eval, &seeds, 0)?;
                crate::progress::log(format!(
                    "[{tag}] reverse KL {rev:.5} nats, forward KL {fwd:.5} nats, modes {cov}/{k}, {ms_per_iter:.3} ms/iter ({:.2} s)",
                    d.train_seconds
                ));
                row.insert("reverse_kl".into(), report::json_f64(rev));
                row.insert("forward_kl".into(), report::json_f64(fwd));
                row.insert("modes_covered".into(), json!(cov));
                row.insert("modes_total".into(), json!(k));
            }
            row.insert("ms_per_iter".into(), report::json_f64(ms_per_iter));
            row.insert("train_seconds".into(), report::json_f64(d.train_seconds));
            if let Some(t) = d.teacher_seconds {
                row.insert("teacher_seconds".into(), report::json_f64(t));
            }
            row.insert("iterations".into(), json!(d.iterations));
            rows[pi].1.push(row);
            if si == 0 && cfg.plots.enabled {
                if conditional {
                    let n = cfg.plots.states.max(1);
                    for i in 0..n {
                        let s = (i as f32 + 0.5) * std::f32::consts::TAU / n as f32;
                        let title = format!("{label}, s = {s:.2}");
                        panels.push(density_panel(
                            &mut d,
                            s,
                            title,
                            circle_modes(k, s),
                            &cfg.plots,
                        )?);
                    }
                } else {
                    panels.push(density_panel(
                        &mut d,
                        0.0,
                        label.clone(),
                        circle_modes(k, 0.0),
                        &cfg.plots,
                    )?);
                }
            }
        }
    }

    let mut metrics = report::metrics_json(&ctx.name, task, &base.seeds, &rows);
    // The original command's top-level keys, from the first method.
    let first = &rows[0].1;
    let mean = |key: &str| {
        report::mean_std(&first.iter().filter_map(|r| r.get(key)?.as_f64()).collect::<Vec<_>>()).0
    };
    let min = |key: &str| first.iter().filter_map(|r| r.get(key)?.as_u64()).min().unwrap_or(0);
    metrics.insert("method".into(), json!(rows[0].0));
    metrics.insert("teacher".into(), json!(rows[0].0.trim_start_matches("vdd-")));
    metrics.insert("seed".into(), json!(base.seeds[0]));
    if conditional {
        metrics.insert("modes".into(), json!(k));
        metrics.insert("states_fully_covered".into(), json!(min("states_fully_covered")));
        metrics.insert("mean_reverse_kl".into(), report::json_f64(mean("mean_reverse_kl")));
        metrics.insert("mean_forward_kl".into(), report::json_f64(mean("mean_forward_kl")));
        metrics.insert("states".into(), first_states.unwrap_or(Value::Null));
    } else {
        metrics.insert("reverse_kl".into(), report::json_f64(mean("reverse_kl")));
        metrics.insert("forward_kl".into(), report::json_f64(mean("forward_kl")));
        metrics.insert("modes_covered".into(), json!(min("modes_covered")));
        metrics.insert("modes_total".into(), json!(k));
    }
    metrics.insert("ms_per_iter".into(), report::json_f64(mean("ms_per_iter")));
    metrics.insert("train_seconds".into(), report::json_f64(mean("train_seconds")));
    let path = dir.join("metrics.json");
    vdd_nn::io::write_atomic(&path, serde_json::to_string_pretty(&metrics)?.as_bytes())?;
    let table = format!(
        "## {} ({task})\n\n{}\n\n{}\nmean ± std over seeds {:?}\n",
        ctx.name,
        base.description,
        report::markdown_table(&rows, &report::columns_for(task)),
        base.seeds
    );
    vdd_nn::io::write_atomic(&dir.join("table.md"), table.as_bytes())?;
    let mut figures = Vec::new();
    if base.plots.enabled && !panels.is_empty() {
        figures = plots::toy_density(&dir.join("density"), &panels, base.plots.png)?;
    }
    ctx.write_run_info(&dir, json!({ "figures": figures, "teachers": teacher_log }))?;
    println!("\n{table}");
    println!("wrote {}", path.display());
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn toy_recipes_resolve_and_shorthands_translate() {
        for task in ["toy-gmm", "toy-conditional"] {
            let file = recipe::read_recipe(&recipe::recipe_path(task).unwrap()).unwrap();
            let r =
                recipe::resolve(&ToyRecipe::defaults(task).unwrap(), &file, &Overrides::default())
                    .unwrap();
            methods::parse_methods(&r.base.methods, task).unwrap();
            assert_eq!(r.base.task, task);
        }
        let mut o = Overrides::default();
        apply_shorthands(
            "toy-gmm",
            &[("teacher".into(), "beso".into()), ("iterations".into(), "7".into())],
            &mut o,
        )
        .unwrap();
        assert_eq!(o.methods, Some(vec!["vdd-beso".to_owned()]));
        let file = recipe::read_recipe(&recipe::recipe_path("toy-gmm").unwrap()).unwrap();
        let r = recipe::resolve(&ToyRecipe::defaults("toy-gmm").unwrap(), &file, &o).unwrap();
        assert_eq!(r.base.vdd.beso.iterations, 7);
        assert!(
            apply_shorthands(
                "toy-gmm",
                &[("teacher".into(), "x".into())],
                &mut Overrides::default()
            )
            .is_err()
        );
        assert!(
            apply_shorthands(
                "avoiding",
                &[("teacher".into(), "beso".into())],
                &mut Overrides::default()
            )
            .is_err()
        );
        let mut o = Overrides::default();
        apply_shorthands(
            "toy-conditional",
            &[("weighting".into(), "uniform".into()), ("experts".into(), "8".into())],
            &mut o,
        )
        .unwrap();
        let file = recipe::read_recipe(&recipe::recipe_path("toy-conditional").unwrap()).unwrap();
        let r =
            recipe::resolve(&ToyRecipe::defaults("toy-conditional").unwrap(), &file, &o).unwrap();
        assert_eq!(r.base.vdd.exact.expert_weighting, vdd::ExpertWeighting::Uniform);
        assert_eq!(r.base.student.num_experts, 8);
    }

    #[test]
    fn the_defaults_files_are_complete_and_valid() {
        recipe::assert_complete_defaults::<ToyRecipe>(&DEFAULTS[..1]);
        recipe::assert_complete_defaults::<ToyRecipe>(&DEFAULTS);
    }

    #[test]
    fn toy_defaults_match_the_paper() {
        let r = ToyRecipe::defaults("toy-gmm").unwrap();
        assert_eq!(r.vdd.exact, VddConfig::toy());
        assert_eq!(r.student, MoeConfig::toy(1, 2, 8));
        assert_eq!(r.data.points, 5000);
        assert_eq!(r.eval.kl_samples, 100_000);
    }
}
