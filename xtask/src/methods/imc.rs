//! `imc`: Information Maximizing Curriculum, the mixture of experts fitted to the
//! demonstrations with a curriculum per expert. Keys: `baselines.imc` (the [`ImcConfig`]; its
//! `seed` is replaced by the run seed).

use vdd_mixture::{ImcConfig, ImcMetrics};

use crate::method::{Info, Job, Method, MethodRecipe, Trained};
use crate::plots::Curves;

/// IMC.
pub struct Imc;

const INFO: Info =
    Info { name: "imc", teacher: None, tasks: &["avoiding"], keys: &["baselines.imc"] };

impl Method for Imc {
    fn info(&self) -> &Info {
        &INFO
    }
    fn check(&self, recipe: &MethodRecipe<'_>) -> crate::XResult {
        recipe.get::<ImcConfig>("baselines.imc").map(drop)
    }
    fn train(&self, job: &Job<'_>) -> crate::XResult<Trained> {
        let config = ImcConfig { seed: job.seed, ..job.recipe.get("baselines.imc")? };
        train(job, config, |curves, m| {
            let x = m.iteration as f64;
            curves.entry("log-likelihood (nats)".into()).or_default().push((x, m.log_likelihood));
            curves.entry("IMC objective".into()).or_default().push((x, m.objective));
        })
    }
}

/// Trains IMC of `config` (either variant) on `job` with its budget, the curves over training
/// and the learning curves `record` keeps of each iteration.
pub fn train(
    job: &Job<'_>,
    config: ImcConfig,
    record: impl Fn(&mut Curves, &ImcMetrics),
) -> crate::XResult<Trained> {
    let (its, steps, batch) = (config.iterations, config.expert_steps_per_iter, config.batch_size);
    let budget = super::em::mixture_budget(job, its, steps, batch);
    let trained = super::em::fit(job, config.iterations, |student, data, bar, curves, probe| {
        let mut imc = vdd_mixture::Imc::from_config(config, student, data)?;
        let report = |m: &ImcMetrics| {
            bar.inc(1);
            bar.set_message(format!("log-lik {:.3}", m.log_likelihood));
            record(curves, m);
        };
        probe.run(&mut imc, report, |s| super::em::snapshot_policy(job, s))?;
        Ok(imc.into_student())
    })?;
    Ok(Trained { budget: Some(budget), ..trained })
}
