//! `cargo xtask experiment avoiding --teacher FILE [--methods teacher,vdd]`: a diffusion policy
//! imported from PyTorch (a `vdd_import` teacher file, `cargo xtask import`) rolled out in
//! Avoiding (row `<source>`, e.g. `lerobot`) and distilled with VDD into a mixture that emits its
//! whole chunk (row `vdd-<source>`), on the recipe's demonstrations (`data`; the window, chunk
//! and feature map are the teacher's), student (`student`, gating `imported.gating`), VDD
//! settings (`imported.vdd`) and evaluation (`eval`). This file only wires the crates: the
//! teacher's samples, space and deployment are `vdd_import`'s, the trainer `vdd`'s, rollouts
//! and timing `vdd_tasks`'.

use std::path::Path;
use std::time::Instant;

use serde::{Deserialize, Serialize};
use serde_json::json;
use vdd::{Vdd, VddConfig};
use vdd_core::Policy;
use vdd_data::Episodes;
use vdd_import::ImportedTeacher;
use vdd_moe::{GatingKind, MoeConfig};
use vdd_tasks::avoiding::EvalProtocol;
use vdd_tasks::timing::us_per_action;

use super::AvoidingRecipe;
use crate::context::RunContext;
use crate::recipe::Resolved;
use crate::report::{self, Row};
use crate::sample_fit::SampleFit;

/// The `[imported]` table of the Avoiding recipes.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ImportedSettings {
    /// The teacher file (`--teacher FILE`); empty: the recipe's own teachers and methods.
    pub teacher: String,
    /// VDD's settings (noise levels in the teacher's convention; `seed` is the run seed).
    pub vdd: VddConfig,
    /// The student's gating.
    pub gating: GatingKind,
    /// Clamp the teacher's denoised chunk to the training chunks' box (teacher's normalised
    /// units) widened by `clip_margin`, as `vdd.clamp_denoiser` does for the recipe's own
    /// teachers; `false` (or no `clip_margin`): the raw score.
    pub clamp_denoiser: bool,
    /// The clamp's margin.
    #[serde(default)]
    pub clip_margin: Option<f32>,
    /// How the student starts.
    pub init: ImportedInit,
    /// The fit to the teacher's samples of `init = "samples"`.
    pub fit: SampleFit,
    /// The learned gating's temperature after training (`Moe::sharpen_gating`):
    /// `q(z|s) ∝ q(z|s)^(1/T)`; below 1 it moves weight to each state's most probable experts,
    /// trading task entropy for success; 1 leaves the student as trained.
    pub gating_temperature: f32,
}

/// How the student of an imported teacher starts (`imported.init`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum ImportedInit {
    /// The paper's start: a new mixture of `student`, seeded by the run seed.
    Paper,
    /// Experts started from a mixture fitted to 2,048 teacher samples, with the noise level
    /// and normalisers `vdd::AutoPlan` picks (`imported.vdd` then gives only the iterations,
    /// the batch and the samples per state).
    Auto,
    /// The whole student fitted by EM to the teacher's samples (`imported.fit`, module
    /// [`crate::sample_fit`]), then VDD with `imported.vdd` from there.
    Samples,
}

/// A new mixture of `mc` (seeded by `seed`) fitted by EM to the teacher's samples at the data's
/// `states` (raw; `sn` maps them into the teacher's normalised space, where the mixture works).
fn fit_to_samples<T: vdd_core::ScoreModel + Clone + Send>(
    fit: &SampleFit,
    teacher: &T,
    mc: &MoeConfig,
    sn: &vdd_core::Affine,
    states: &faer::Mat<f32>,
    seed: u64,
) -> crate::Result<vdd_moe::Moe> {
    fit.validate()?;
    let states_n = sn.normalize_rows(states.as_ref())?;
    let blocks = fit.blocks as u64;
    let bar = crate::progress::bar(blocks, &format!("teacher samples s{seed}"));
    let workers = vdd_nn::parallel::Workers::new(0)?;
    let (s, a) = fit.draw(teacher, states_n.as_ref(), seed, &workers, &|| bar.inc(1))?;
    bar.finish_and_clear();
    let bar = crate::progress::bar(fit.em.iterations as u64, &format!("EM fit s{seed}"));
    let student = vdd_moe::Moe::from_config(mc.clone(), seed)?;
    let student = fit.fit(student, s, a, seed, |ll| {
        bar.inc(1);
        bar.set_message(format!("log-lik {ll:.3}"));
    })?;
    bar.finish_and_clear();
    Ok(student)
}

/// Appends one entry per row of a tuning run to the Avoiding tuning log: the configuration
/// hash covers the data, the teacher file, the student and the whole `[imported]` table.
fn log_tuning(
    ctx: &RunContext,
    cfg: &AvoidingRecipe,
    dir: &Path,
    rows: &[(String, Vec<Row>)],
) -> crate::Result {
    use crate::tuning;
    let revision = ctx.revision_label();
    let mut keys = serde_json::Map::new();
    keys.insert("imported".into(), serde_json::to_value(&cfg.imported)?);
    let mut entries = Vec::new();
    for (label, rows) in rows {
        let teacher = Some(&cfg.imported.teacher);
        let config = tuning::config_hash(label, &cfg.data, teacher, &cfg.student, keys.clone())?;
        let id = tuning::RunId {
            method: label.clone(),
            config,
            recipe: ctx.name.clone(),
            command: ctx.command.clone(),
            revision: revision.clone(),
            run: crate::teachers::rel(dir),
        };
        entries.push(tuning::LogEntry::from_rows(id, rows));
    }
    let path = tuning::log_path(&ctx.root, "avoiding");
    let n = entries.len();
    tuning::append_log(&path, entries)?;
    crate::progress::print(format!(
        "tuning log: {n} entries appended to {}",
        crate::teachers::rel(&path)
    ));
    Ok(())
}

/// Runs the imported teacher's methods of `resolved` (see the module docs).
pub fn run(ctx: &RunContext, resolved: &Resolved<AvoidingRecipe>) -> crate::Result {
    if !resolved.variants.is_empty() {
        return Err("--teacher runs take no recipe variants".into());
    }
    let cfg = &resolved.base;
    let (seeds, methods) = (&cfg.header.seeds, &cfg.header.methods);
    if let Some(m) = methods.iter().find(|m| !["teacher", "vdd"].contains(&m.as_str())) {
        return Err(format!("method `{m}` with --teacher (teacher, vdd)").into());
    }
    let t = cfg.imported.gating_temperature;
    if !(t.is_finite() && t > 0.0) || (t != 1.0 && cfg.imported.gating != GatingKind::Learned) {
        // Checked before any training: `Moe::sharpen_gating` would refuse it only after.
        return Err(format!(
            "imported.gating_temperature = {t}: a finite positive temperature of a learned gating \
             (imported.gating = \"learned\"), or 1"
        )
        .into());
    }
    let ImportedTeacher::Unet1d(teacher) =
        vdd_import::load_teacher(Path::new(&cfg.imported.teacher))?;
    let src = teacher.spec().source.clone();
    if let (Some(m), true) = (&teacher.spec().obs_map, methods.iter().any(|m| m == "vdd")) {
        // The student's deployment spec cannot carry the map yet: it would act on the mapped
        // observation and refuse the task's raw one.
        return Err(format!(
            "{}: the teacher was imported with the observation map `{m}`, which a VDD student \
             cannot carry yet; roll the teacher out alone with --methods teacher",
            cfg.imported.teacher
        )
        .into());
    }
    let map = teacher.spec().features.resolve()?;
    let (train, raw_obs) = cfg.data.train_episodes()?;
    let featured: Result<Vec<_>, _> = raw_obs.iter().map(|o| map.apply_rows(o.as_ref())).collect();
    let episodes = Episodes::from_episodes(featured?, train.to_episode_matrices().1)?;
    let (states, chunks) = teacher.training_windows(&episodes)?;
    let (sn, an) = teacher.teacher_space()?;

    let dir = ctx.run_dir(seeds);
    ctx.write_resolved(&dir, &resolved.to_toml()?)?;
    let threads = cfg.eval.eval_threads();
    let protocol = cfg.eval.protocol();
    let mut rows: Vec<(String, Vec<Row>)> = Vec::new();
    for &seed in seeds {
        let mut timed: Vec<Box<dyn Policy + Send>> = Vec::new();
        let mut results = Vec::new();
        if methods.iter().any(|m| m == "teacher") {
            let policy = ImportedTeacher::Unet1d(teacher.clone()).into_policy()?;
            results.push((src.clone(), protocol.evaluate(&policy, seed, threads, false)?, None));
            timed.push(Box::new(policy));
        }
        if methods.iter().any(|m| m == "vdd") {
            let label = format!("vdd-{src}");
            let mc = MoeConfig {
                state_dim: states.ncols(),
                action_dim: chunks.ncols(),
                gating: cfg.imported.gating,
                ..cfg.student.clone()
            };
            let vc = VddConfig { seed, ..cfg.imported.vdd.clone() };
            let clip = cfg.imported.clip_margin.filter(|_| cfg.imported.clamp_denoiser);
            let space = (sn.clone(), an.clone());
            let data = (states.clone(), chunks.clone());
            let inner = teacher.as_ref().clone();
            let t0 = Instant::now();
            let mut vdd = match cfg.imported.init {
                ImportedInit::Samples => {
                    let start = fit_to_samples(&cfg.imported.fit, &inner, &mc, &sn, &states, seed)?;
                    Vdd::continue_in_teacher_space(inner, data, space, start, &vc, clip)?
                }
                init => {
                    let setup = (clip, init == ImportedInit::Auto);
                    Vdd::in_teacher_space(inner, data, space, (&mc, &vc), setup)?
                }
            };
            let bar = crate::progress::bar(vc.iterations as u64, &format!("{label} s{seed}"));
            vdd.train(|_| bar.inc(1))?;
            let secs = t0.elapsed().as_secs_f64();
            bar.finish_and_clear();
            let mut student = vdd.into_student();
            if cfg.imported.gating_temperature != 1.0 {
                student.sharpen_gating(cfg.imported.gating_temperature).map_err(|e| {
                    format!(
                        "imported.gating_temperature = {}: {e}",
                        cfg.imported.gating_temperature
                    )
                })?;
            }
            student.set_deploy_spec(teacher.chunk_deploy_spec())?;
            std::fs::create_dir_all(dir.join("models"))?;
            student.save(&dir.join("models").join(format!("{label}-s{seed}.safetensors")))?;
            let policy = student.into_policy()?;
            results.push((
                label.clone(),
                protocol.evaluate(&policy, seed, threads, false)?,
                Some(secs),
            ));
            timed.push(Box::new(policy));
        }
        let us = us_per_action(&mut timed, &raw_obs, cfg.eval.timing(), EvalProtocol::seed(seed))?;
        for ((label, ev, secs), us) in results.into_iter().zip(us) {
            let m = &ev.metrics;
            crate::progress::log(format!(
                "[{label} s{seed}] success {:.3}, entropy {:.3} ({} modes), {us:.1} µs per action",
                m.success_rate, m.task_entropy, m.modes_reached
            ));
            let mut row = m.row_fields();
            row.insert("seed".into(), json!(seed));
            row.insert("us_per_action".into(), report::json_f64(us));
            let secs = secs.map_or(serde_json::Value::Null, report::json_f64);
            row.insert("train_seconds".into(), secs);
            match rows.iter_mut().find(|(l, _)| *l == label) {
                Some((_, r)) => r.push(row),
                None => rows.push((label, vec![row])),
            }
        }
    }
    if crate::tuning::is_tuning_run(seeds, cfg.data.seed)? {
        log_tuning(ctx, cfg, &dir, &rows)?;
    }
    let metrics = report::metrics_json(&ctx.name, "avoiding", seeds, &rows);
    let table = format!(
        "## {} (Avoiding, imported teacher {})\n\n{}\n\nmean ± std over seeds {seeds:?}; {} rollouts per method and seed; µs per action: single-threaded `Policy::act` on one observation.\n",
        ctx.name,
        cfg.imported.teacher,
        report::markdown_table(&rows, &super::COLUMNS),
        cfg.eval.rollouts
    );
    crate::driver::write_results(
        ctx,
        &dir,
        &metrics,
        &table,
        json!({ "teacher": cfg.imported.teacher }),
    )
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::recipe::{self, Overrides};
    use crate::task::Task;

    fn resolved(shorthands: &[(String, String)], mut o: Overrides) -> AvoidingRecipe {
        super::super::Avoiding.apply_shorthands(shorthands, &mut o).unwrap();
        let file = recipe::read_recipe(&recipe::recipe_path("avoiding").unwrap()).unwrap();
        recipe::resolve(&AvoidingRecipe::defaults().unwrap(), &file, &o).unwrap().base
    }

    #[test]
    fn the_teacher_option_selects_the_imported_run_and_its_methods() {
        let plain = resolved(&[], Overrides::default());
        assert!(plain.imported.teacher.is_empty(), "no teacher file by default");
        let given = [("teacher".to_owned(), r"dir with space/t\1.safetensors".to_owned())];
        let r = resolved(&given, Overrides::default());
        assert_eq!(r.imported.teacher, r"dir with space/t\1.safetensors");
        assert_eq!(r.header.methods, ["teacher", "vdd"]);
        let only = Overrides { methods: Some(vec!["vdd".into()]), ..Default::default() };
        assert_eq!(resolved(&given, only).header.methods, ["vdd"]);
        assert!(r.imported.vdd.validate().is_ok() && r.imported.clip_margin == Some(0.5));
        assert!(r.imported.fit.validate().is_ok());
    }
}
