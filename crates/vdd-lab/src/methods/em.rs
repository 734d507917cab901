//! `em`: the mixture of experts fitted to the demonstrations by expectation maximisation.
//! Keys: `baselines.em` (the [`EmConfig`]; its `seed` is replaced by the run seed).

use std::time::Instant;

use crate::progress::Bar;
use vdd_mixture::{Dataset, EmConfig};
use vdd_moe::{Moe, MoeConfig};

use crate::method::{
    Budget, Capability, CurveProbe, Info, Job, Method, MethodRecipe, Row, TeacherUse, Trained,
};
use crate::plots::Curves;
use crate::policy::TrainedPolicy;

/// EM.
pub struct Em;

const INFO: Info =
    Info { name: "em", teacher: TeacherUse::Never, needs: &[Capability::Rollouts], row_keys: &[] };

impl Method for Em {
    fn info(&self) -> &Info {
        &INFO
    }
    fn keys(&self, _: &Row) -> Vec<String> {
        vec!["baselines.em".into()]
    }
    fn check(&self, recipe: &MethodRecipe<'_>) -> crate::Result {
        recipe.get::<EmConfig>("baselines.em").map(drop)
    }
    fn train(&self, job: &Job<'_>) -> crate::Result<Trained> {
        let config = EmConfig { seed: job.seed, ..job.recipe.get("baselines.em")? };
        let budget =
            mixture_budget(job, config.iterations, config.expert_steps_per_iter, config.batch_size);
        let trained = fit(job, config.iterations, |student, data, bar, curves, probe| {
            let mut em = vdd_mixture::Em::from_config(config, student, data)?;
            let report = |m: &vdd_mixture::EmMetrics| {
                bar.inc(1);
                bar.set_message(format!("log-lik {:.3}", m.log_likelihood));
                let ll = curves.entry("log-likelihood (nats)".into()).or_default();
                ll.push((m.iteration as f64, m.log_likelihood));
            };
            probe.run(&mut em, report, |s| snapshot_policy(job, s))?;
            Ok(em.into_student())
        })?;
        Ok(Trained { budget: Some(budget), ..trained })
    }
}

/// The budget of EM / IMC: `iterations · steps` expert steps of `batch` pairs (the whole
/// dataset when `None` or larger).
pub fn mixture_budget(
    job: &Job<'_>,
    iterations: usize,
    steps: usize,
    batch: Option<usize>,
) -> Budget {
    let rows = job.data.states_normalized.nrows();
    Budget::student((iterations * steps) as u64, batch.unwrap_or(rows).min(rows))
}

/// A snapshot of a mixture trained on the task's normalised data, acting on raw states.
pub fn snapshot_policy(job: &Job<'_>, mut student: Moe) -> crate::Result<TrainedPolicy> {
    let (sn, an) = (&job.data.state_normalizer, &job.data.action_normalizer);
    student.set_normalizers(Some(sn.clone()), Some(an.clone()))?;
    Ok(TrainedPolicy::Moe(Box::new(student)))
}

/// Fits a new mixture (`student`'s configuration with the data's dimensions; the trainer
/// initialises it from the run seed) to the task's normalised data with `train` (given the
/// mixture's configuration, the data, a progress bar of `iterations`, the curves to fill and
/// the probe of the curves over training) and sets the data's normalisers on it: EM and IMC.
pub fn fit(
    job: &Job<'_>,
    iterations: usize,
    train: impl FnOnce(
        MoeConfig,
        Dataset,
        &dyn Bar,
        &mut Curves,
        &mut CurveProbe<'_>,
    ) -> crate::Result<Moe>,
) -> crate::Result<Trained> {
    let d = job.data;
    let data = Dataset::new(d.states_normalized.clone(), d.actions_normalized.clone())?;
    let mut mc = job.recipe.student.clone();
    mc.state_dim = d.states_normalized.ncols();
    mc.action_dim = d.actions_normalized.ncols();
    let t0 = Instant::now();
    let bar = crate::progress::bar(iterations as u64, job.label);
    let mut curves = Curves::default();
    let mut probe = job.probe();
    let student = train(mc, data, bar.as_ref(), &mut curves, &mut probe)?;
    bar.finish_and_clear();
    let curve_seconds = probe.take_into(&mut curves);
    let train_seconds = t0.elapsed().as_secs_f64() - curve_seconds;
    let policy = snapshot_policy(job, student)?;
    Ok(Trained { curve_seconds, ..Trained::new(policy, train_seconds, curves) })
}
