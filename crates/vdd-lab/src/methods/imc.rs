//! `imc`: Information Maximizing Curriculum, the mixture of experts fitted to the
//! demonstrations with a curriculum per expert; with `with.authors = true` (row
//! `imc-authors`), IMC as in the authors' code ([`ImcVariant::Authors`]: unit-variance experts,
//! curricula normalised per data point, the gating fitted at the end), beside the
//! paper-literal `imc`. Keys: `baselines.imc`, or for the authors' `baselines.imc_authors`
//! (an [`ImcConfig`] each, the latter's `variant` must be `"authors"`; the `seed` is replaced
//! by the run seed).

use serde::Deserialize;
use vdd_mixture::{ImcConfig, ImcMetrics, ImcVariant};

use crate::method::{Capability, Info, Job, Method, MethodRecipe, Row, TeacherUse, Trained};
use crate::plots::Curves;

/// IMC.
pub struct Imc;

const INFO: Info = Info {
    name: "imc",
    teacher: TeacherUse::Never,
    needs: &[Capability::Rollouts],
    row_keys: &["authors"],
};

/// A row's settings.
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct Settings {
    /// The authors' IMC (its curves are the unit-variance log-likelihood and the effective
    /// data fraction; the paper's: the log-likelihood and the IMC objective).
    #[serde(default)]
    authors: bool,
}

/// The key of the row's [`ImcConfig`] and whether it is the authors' variant.
fn key(row: &Row) -> crate::Result<(&'static str, bool)> {
    let s: Settings = row.settings()?;
    Ok(if s.authors { ("baselines.imc_authors", true) } else { ("baselines.imc", false) })
}

fn config(recipe: &MethodRecipe<'_>) -> crate::Result<(ImcConfig, bool)> {
    let (key, authors) = key(recipe.row)?;
    let c: ImcConfig = recipe.get(key)?;
    if authors && c.variant != ImcVariant::Authors {
        return Err(format!("`{key}.variant` must be \"authors\", got {:?}", c.variant).into());
    }
    Ok((c, authors))
}

impl Method for Imc {
    fn info(&self) -> &Info {
        &INFO
    }
    fn keys(&self, row: &Row) -> Vec<String> {
        key(row).map(|(k, _)| vec![k.to_owned()]).unwrap_or_default()
    }
    fn check(&self, recipe: &MethodRecipe<'_>) -> crate::Result {
        config(recipe).map(drop)
    }
    fn train(&self, job: &Job<'_>) -> crate::Result<Trained> {
        let (config, authors) = config(&job.recipe)?;
        let config = ImcConfig { seed: job.seed, ..config };
        let (its, steps, batch) =
            (config.iterations, config.expert_steps_per_iter, config.batch_size);
        let budget = super::em::mixture_budget(job, its, steps, batch);
        let record = |curves: &mut Curves, m: &ImcMetrics| {
            let x = m.iteration as f64;
            let (ll, (other, y)) = if authors {
                let fraction = ("effective data fraction", m.effective_data_fraction);
                ("log-likelihood, unit variances (nats)", fraction)
            } else {
                ("log-likelihood (nats)", ("IMC objective", m.objective))
            };
            curves.entry(ll.into()).or_default().push((x, m.log_likelihood));
            curves.entry(other.into()).or_default().push((x, y));
        };
        let trained =
            super::em::fit(job, config.iterations, |student, data, bar, curves, probe| {
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
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_paper_imc_serialises_as_before_and_the_authors_reads_as_such() {
        let v = serde_json::to_value(ImcConfig::toy()).unwrap();
        assert!(v.get("variant").is_none(), "the paper's IMC keeps its recipes and hashes");
        let authors = ImcConfig { variant: ImcVariant::Authors, ..ImcConfig::toy() };
        let v = serde_json::to_value(&authors).unwrap();
        assert_eq!(v["variant"], "authors");
        assert_eq!(serde_json::from_value::<ImcConfig>(v).unwrap(), authors);
    }
}
