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
//! The data (and so the learned teachers) depend on the run seed. `metrics.json` has the common
//! `methods.<method>` layout ([`crate::report`]) and, for the first method, the top-level keys
//! of the original command: `reverse_kl`, `forward_kl`, `modes_covered` (the minimum over
//! seeds), `ms_per_iter`, `train_seconds` (means over seeds) for `toy-gmm`;
//! `states_fully_covered` (minimum), `mean_reverse_kl`, `mean_forward_kl`, `ms_per_iter`,
//! `train_seconds` and the first seed's per-state results for `toy-conditional`.

use serde::{Deserialize, Serialize};
use serde_json::{Value, json};
use toml::Table;
use vdd::eval::{GmmEval, against_circle, circle_states};
use vdd_core::gmm::GmmTeacher;
use vdd_core::{Affine, ScoreModel, Seeds};
use vdd_moe::MoeConfig;
use vdd_tasks::toy::ToyData;

use super::toy_eval::{ToyPlots, ToyStudent, circle_modes, density_panel};
use crate::Registry;
use crate::context::{RunContext, StageTimes};
use crate::driver::{self, Datasets, Entry, Probes, Task, TaskRecipe, Trainings};
use crate::method::{Trained, TrainingData};
use crate::plots;
use crate::policy::TrainedPolicy;
use crate::recipe::{self, Header, Overrides};
use crate::report::{self, Row};
use crate::task::Capability;
use crate::teachers::TeachersConfig;

/// A toy recipe: the schema of the recipe files; the values not given there come from
/// `recipes/defaults/` ([`Self::defaults`]). Unknown keys are errors ([`recipe::from_tree`]).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ToyRecipe {
    /// Name, description, task (`toy-gmm` or `toy-conditional`), seeds and methods
    /// (`vdd-exact`; `toy-gmm` also `vdd-ddpm`, `vdd-beso`).
    #[serde(flatten)]
    pub header: Header,
    /// Data.
    pub data: ToyData,
    /// Learned teachers (trained on `data.points` samples of the mixture).
    pub teachers: TeachersConfig,
    /// The student (`state_dim` / `action_dim` come from the task).
    pub student: MoeConfig,
    /// VDD's settings for each teacher, read by the VDD methods ([`crate::methods`]).
    pub vdd: Table,
    /// Evaluation.
    pub eval: GmmEval,
    /// Figure 2.
    pub plots: ToyPlots,
}

/// `recipes/defaults/toy-gmm.toml` and the `toy-conditional` keys merged on top of it,
/// embedded so that the binary is self-contained.
const DEFAULTS: [(&str, &str); 2] = [
    ("recipes/defaults/toy-gmm.toml", include_str!("../../../../recipes/defaults/toy-gmm.toml")),
    (
        "recipes/defaults/toy-conditional.toml",
        include_str!("../../../../recipes/defaults/toy-conditional.toml"),
    ),
];

impl ToyRecipe {
    /// The defaults of `task` (`toy-gmm` or `toy-conditional`), from `recipes/defaults/`,
    /// which a recipe file overrides.
    pub fn defaults(task: &str) -> crate::Result<Self> {
        Ok(match task {
            "toy-gmm" => recipe::defaults_from_toml(&DEFAULTS[..1])?,
            "toy-conditional" => recipe::defaults_from_toml(&DEFAULTS)?,
            other => return Err(format!("no toy task `{other}` (toy-gmm, toy-conditional)").into()),
        })
    }
}

/// Resolves a `toy-gmm` recipe file and checks it without doing any work (the fuzzer's
/// `recipe` target): the plan and the methods' settings as `experiment` checks them, the
/// ranges of the student, the teachers and every VDD section, and the student's size.
pub fn check_toy_gmm(file: &Table) -> crate::Result {
    let resolved = recipe::resolve(&ToyRecipe::defaults("toy-gmm")?, file, &Overrides::default())?;
    driver::plan(&Registry::builtin(), &resolved, "toy-gmm", &[])?;
    for (_, cfg) in resolved.configs() {
        let s = &cfg.student;
        s.validate()?;
        let family =
            vdd_moe::ExpertFamily::new(s.expert_kind, s.action_dim, s.init_std, s.min_std)?;
        vdd_nn::limits::check_params(
            "the student",
            s.num_params(vdd_core::Expert::raw_dim(&family)),
        )?;
        cfg.teachers.beso.config.validate()?;
        cfg.teachers.ddpm.config.validate()?;
        for (name, section) in &cfg.vdd {
            if let Ok(v) = section.clone().try_into::<vdd::VddConfig>() {
                v.validate().map_err(|e| format!("vdd.{name}: {e}"))?;
            }
        }
    }
    Ok(())
}

impl TaskRecipe for ToyRecipe {
    const METHOD_SECTIONS: &'static [&'static str] = &["vdd"];
    fn header(&self) -> &Header {
        &self.header
    }
    fn teachers(&self) -> &TeachersConfig {
        &self.teachers
    }
    fn student(&self) -> &MoeConfig {
        &self.student
    }
}

/// A toy task.
pub struct Toy {
    name: &'static str,
    conditional: bool,
}

/// `toy-gmm`.
pub const TOY_GMM: Toy = Toy { name: "toy-gmm", conditional: false };
/// `toy-conditional`.
pub const TOY_CONDITIONAL: Toy = Toy { name: "toy-conditional", conditional: true };

/// Modes of the toys' mixtures.
const MODES: usize = 8;

impl Task for Toy {
    fn name(&self) -> &'static str {
        self.name
    }

    /// The exact mixture; `toy-gmm` also trains the learned teachers on its samples.
    fn offers(&self) -> &'static [Capability] {
        if self.conditional {
            &[Capability::ExactMixture]
        } else {
            &[Capability::LearnedTeachers, Capability::ExactMixture]
        }
    }

    fn columns(&self) -> Vec<report::Column> {
        use report::Column as C;
        let first: &[C] = if self.conditional {
            &[
                C::new("states_fully_covered", "states fully covered", 2),
                C::new("mean_reverse_kl", "reverse KL (nats)", 4),
                C::new("mean_forward_kl", "forward KL (nats)", 4),
            ]
        } else {
            &[
                C::new("reverse_kl", "reverse KL (nats)", 4),
                C::new("forward_kl", "forward KL (nats)", 4),
                C::new("modes_covered", "modes covered", 2),
            ]
        };
        let last = [C::new("ms_per_iter", "ms / iter", 3), C::new("train_seconds", "train s", 1)];
        first.iter().copied().chain(last).collect()
    }

    /// Translates the original commands' options into recipe overrides: `toy-gmm --teacher X`
    /// (methods = `vdd-X`), `--iterations N`; `toy-conditional --iterations N --experts N
    /// --lr X --weighting gating|uniform`.
    fn apply_shorthands(
        &self,
        shorthands: &[(String, String)],
        o: &mut Overrides,
    ) -> Result<(), String> {
        let task = self.name;
        let mut teacher = "exact".to_owned();
        for (k, v) in shorthands.iter().filter(|(k, _)| k == "teacher") {
            if self.conditional {
                return Err(format!("--{k} is a toy-gmm option; use --methods for `{task}`"));
            }
            if !["exact", "ddpm", "beso"].contains(&v.as_str()) {
                return Err(format!("unknown teacher `{v}` (exact|ddpm|beso)"));
            }
            teacher = v.clone();
            o.methods = Some(vec![format!("vdd-{v}")]);
        }
        for (k, v) in shorthands {
            let sets: Vec<(String, String)> = match (self.conditional, k.as_str()) {
                (_, "teacher") => continue,
                (_, "iterations") => vec![(format!("vdd.{teacher}.iterations"), v.clone())],
                (true, "experts") => vec![("student.num_experts".into(), v.clone())],
                (true, "lr") => vec![
                    ("vdd.exact.expert_optimizer.lr".into(), v.clone()),
                    ("vdd.exact.gating_optimizer.lr".into(), v.clone()),
                ],
                (true, "weighting") => {
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

    fn run(&self, ctx: &RunContext) -> crate::Result {
        let task = self.name;
        let resolved = recipe::resolve(&ToyRecipe::defaults(task)?, &ctx.file, &ctx.overrides)?;
        let base = &resolved.base;
        let plan = driver::plan(&ctx.registry, &resolved, task, &ctx.overrides.sets)?;
        for (_, cfg) in resolved.configs() {
            cfg.data.validate()?;
            cfg.eval.validate()?;
            cfg.plots.validate()?;
        }
        let dir = ctx.run_dir(&base.header.seeds);
        ctx.write_resolved(&dir, &resolved.to_toml()?)?;
        let mut stages = StageTimes::default();
        let seeds = &base.header.seeds;
        let key = |si, pi: usize| -> crate::Result<String> {
            Ok(format!("{}-{}", recipe::config_hash(&plan[pi].cfg.data)?, seeds[si]))
        };
        let prepare = |si, pi: usize| stages.time("data", || self.prepare(plan[pi].cfg, seeds[si]));
        let data = Datasets::build(seeds.len(), plan.len(), key, prepare)?;
        let mut trainings = driver::train_all(
            ctx,
            &plan,
            &base.header.seeds,
            &data,
            1,
            (None, &|_| Probes::default()),
            &mut stages,
        )?;

        let mut rows = driver::empty_rows(&plan);
        let mut panels = Vec::new();
        for (si, &seed) in base.header.seeds.iter().enumerate() {
            for (pi, e) in plan.iter().enumerate() {
                let trained = trainings.trained.remove(&(si, pi)).ok_or("internal: not trained")?;
                let mut s = student(e, &trained, data.get(si, pi), &trainings, seed)?;
                let row = self.evaluate(e, &trained, &mut s, seed)?;
                rows[pi].1.push(row);
                if si == 0 && e.cfg.plots.enabled {
                    let n = if self.conditional { e.cfg.plots.states.max(1) } else { 1 };
                    for i in 0..n {
                        let (state, title) = if self.conditional {
                            let s = (i as f32 + 0.5) * std::f32::consts::TAU / n as f32;
                            (s, format!("{}, s = {s:.2}", e.label))
                        } else {
                            (0.0, e.label.clone())
                        };
                        let modes = circle_modes(MODES, state)?;
                        panels.push(density_panel(&mut s, state, title, modes, &e.cfg.plots)?);
                    }
                }
            }
        }
        self.write_outputs(ctx, &dir, base, &rows, &panels, trainings.teachers.log)
    }
}

impl Toy {
    /// The row of one trained method: KL and coverage against the exact mixture, training time.
    fn evaluate(
        &self,
        e: &Entry<'_, ToyRecipe>,
        trained: &Trained,
        s: &mut ToyStudent,
        seed: u64,
    ) -> crate::Result<Row> {
        let (cfg, train_seconds) = (e.cfg, trained.train_seconds);
        let iterations = trained.iterations.unwrap_or(0);
        let tag = format!("{} s{seed}", e.label);
        let seeds = Seeds::new(seed).child("toy-eval");
        let ms_per_iter = train_seconds * 1e3 / iterations.max(1) as f64;
        let mut row = Row::new();
        row.insert("seed".into(), json!(seed));
        let n = if self.conditional { cfg.eval.eval_states.max(1) } else { 1 };
        let states = if self.conditional { circle_states(n) } else { vec![0.0] };
        let scores = against_circle(&mut s.student, MODES, &states, &cfg.eval, &seeds)?;
        let at = |(&st, g): (&f32, &vdd::eval::GmmScores)| {
            (st, g.reverse_kl, g.forward_kl, g.modes_covered)
        };
        let scores: Vec<_> = states.iter().zip(&scores).map(at).collect();
        let fields = report::toy_fields(&scores, MODES, self.conditional);
        crate::progress::log(format!(
            "[{tag}] {}, {ms_per_iter:.3} ms/iter ({train_seconds:.2} s)",
            report::toy_line(&fields, MODES)
        ));
        row.extend(fields);
        row.insert("ms_per_iter".into(), report::json_f64(ms_per_iter));
        row.insert("train_seconds".into(), report::json_f64(train_seconds));
        if let Some(t) = trained.teacher_seconds {
            row.insert("teacher_seconds".into(), report::json_f64(t));
        }
        row.insert("iterations".into(), json!(iterations));
        Ok(row)
    }

    /// The run seed's samples of the toy's mixture and its exact teacher.
    fn prepare(&self, cfg: &ToyRecipe, seed: u64) -> crate::Result<TrainingData> {
        let n = cfg.data.points;
        let task = vdd_tasks::toy::CircleGmm::toy_conditional();
        // The toy-gmm state is constant (0); toy-conditional samples states and actions.
        if self.conditional {
            let (states, actions) = task.sample(n, seed)?;
            Ok(TrainingData::raw(states, actions, Some(task.teacher()?)))
        } else {
            let mut rng = Seeds::new(seed).stream("toy-data");
            let (states, actions) = GmmTeacher::circle_toy_data(n, &mut rng)?;
            Ok(TrainingData::raw(states, actions, Some(GmmTeacher::circle_toy())))
        }
    }

    #[allow(clippy::too_many_arguments)]
    fn write_outputs(
        &self,
        ctx: &RunContext,
        dir: &std::path::Path,
        base: &ToyRecipe,
        rows: &[(String, Vec<Row>)],
        panels: &[plots::DensityPanel],
        teacher_log: Vec<Value>,
    ) -> crate::Result {
        let task = self.name;
        let mut metrics = report::metrics_json(&ctx.name, task, &base.header.seeds, rows);
        report::toy_summary(&mut metrics, rows, base.header.seeds[0], self.conditional, MODES);
        let table = format!(
            "## {} ({task})\n\n{}\n\n{}\nmean ± std over seeds {:?}\n",
            ctx.name,
            base.header.description,
            report::markdown_table(rows, &self.columns()),
            base.header.seeds
        );
        let mut figures = Vec::new();
        if base.plots.enabled && !panels.is_empty() {
            figures = plots::toy_density(&dir.join("density"), panels, base.plots.png)?;
        }
        let details = json!({ "figures": figures, "teachers": teacher_log });
        driver::write_results(ctx, dir, &metrics, &table, details)?;
        crate::progress::print(format!("wrote {}", dir.join("metrics.json").display()));
        Ok(())
    }
}

/// The distilled mixture of `trained` with its normalisers and teacher.
fn student(
    e: &Entry<'_, ToyRecipe>,
    trained: &Trained,
    d: &TrainingData,
    trainings: &Trainings,
    seed: u64,
) -> crate::Result<ToyStudent> {
    let TrainedPolicy::Moe(student) = &trained.policy else {
        return Err(format!("{}: the toys evaluate mixtures of experts", e.label).into());
    };
    let (sn, an) = student.normalizers();
    let state_norm = sn.cloned().unwrap_or_else(|| Affine::identity(1));
    let action_norm = an.cloned().unwrap_or_else(|| Affine::identity(2));
    let teacher: Box<dyn ScoreModel> = match e.teacher_kind() {
        Some(kind) => {
            Box::new(trainings.teachers.get(kind, e.cfg.teachers(), d, seed)?.teacher.clone())
        }
        None => Box::new(d.exact.clone().ok_or("the toy has no exact teacher")?),
    };
    let noise_level = trained.noise_level.ok_or("internal: no distillation noise level")?;
    let student = student.as_ref().clone();
    Ok(ToyStudent { student, state_norm, action_norm, teacher, noise_level })
}

#[cfg(test)]
mod tests {
    use super::*;

    fn resolve(task: &str, o: &Overrides) -> recipe::Resolved<ToyRecipe> {
        let file = recipe::read_recipe(&recipe::recipe_path(task).unwrap()).unwrap();
        recipe::resolve(&ToyRecipe::defaults(task).unwrap(), &file, o).unwrap()
    }

    #[test]
    fn toy_recipes_resolve_and_shorthands_translate() {
        for task in [&TOY_GMM, &TOY_CONDITIONAL] {
            let r = resolve(task.name, &Overrides::default());
            driver::plan(&Registry::builtin(), &r, task.name, &[]).unwrap();
            assert_eq!(r.base.header.task, task.name);
        }
        let mut o = Overrides::default();
        let sh = [("teacher".into(), "beso".into()), ("iterations".into(), "7".into())];
        TOY_GMM.apply_shorthands(&sh, &mut o).unwrap();
        assert_eq!(o.methods, Some(vec!["vdd-beso".to_owned()]));
        let r = resolve("toy-gmm", &o);
        assert_eq!(r.base.vdd["beso"]["iterations"].as_integer(), Some(7));
        let bad = [("teacher".into(), "x".into())];
        assert!(TOY_GMM.apply_shorthands(&bad, &mut Overrides::default()).is_err());
        let teacher = [("teacher".into(), "beso".into())];
        assert!(TOY_CONDITIONAL.apply_shorthands(&teacher, &mut Overrides::default()).is_err());
        let avoiding = Registry::builtin().task("avoiding").unwrap();
        let toy_only = [("iterations".into(), "7".into())];
        assert!(avoiding.apply_shorthands(&toy_only, &mut Overrides::default()).is_err());
        let mut o = Overrides::default();
        let sh = [("weighting".into(), "uniform".into()), ("experts".into(), "8".into())];
        TOY_CONDITIONAL.apply_shorthands(&sh, &mut o).unwrap();
        let r = resolve("toy-conditional", &o);
        assert_eq!(r.base.vdd["exact"]["expert_weighting"].as_str(), Some("uniform"));
        assert_eq!(r.base.student.num_experts, 8);
    }

    #[test]
    fn unknown_keys_are_named_at_the_top_and_inside_and_the_header_comes_first() {
        let defaults = ToyRecipe::defaults("toy-gmm").unwrap();
        for (text, key) in [("nmae = \"x\"", "nmae"), ("[eval]\nradius = 2", "radius")] {
            let file = text.parse().unwrap();
            let err = recipe::resolve(&defaults, &file, &Overrides::default()).unwrap_err();
            assert!(err.to_string().contains(key), "{err}");
        }
        let text = resolve("toy-gmm", &Overrides::default()).to_toml().unwrap();
        assert!(text.find("methods = ").unwrap() < text.find("[data]").unwrap(), "{text}");
    }

    #[test]
    fn the_defaults_files_are_complete_and_valid() {
        recipe::check_complete_defaults::<ToyRecipe>(&DEFAULTS[..1])
            .unwrap_or_else(|e| panic!("{e}"));
        recipe::check_complete_defaults::<ToyRecipe>(&DEFAULTS).unwrap_or_else(|e| panic!("{e}"));
    }
}
