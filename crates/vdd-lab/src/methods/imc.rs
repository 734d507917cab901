//! `imc`: Information Maximizing Curriculum, the mixture of experts fitted to the
//! demonstrations with a curriculum per expert, and `imc-authors`: IMC as in the authors' code
//! ([`ImcVariant::Authors`]: unit-variance experts, curricula normalised per data point, the
//! gating fitted at the end), beside the paper-literal `imc`. Keys: `baselines.imc` and
//! `baselines.imc_authors` (an [`ImcConfig`] each, the latter's `variant` must be
//! `"authors"`; the `seed` is replaced by the run seed).

use vdd_mixture::{ImcConfig, ImcMetrics, ImcVariant};

use crate::method::{Info, Job, Method, MethodRecipe, Trained};
use crate::plots::Curves;

/// An IMC row: the method's info, the key of its [`ImcConfig`] and the variant it requires
/// (the authors' row: its curves are the unit-variance log-likelihood and the effective data
/// fraction; the paper's: the log-likelihood and the IMC objective).
pub struct Imc {
    info: Info,
    key: &'static str,
    variant: Option<ImcVariant>,
}

/// The paper's IMC.
pub const IMC: Imc = Imc {
    info: Info {
        name: "imc",
        teacher: None,
        tasks: &["avoiding", "block-push"],
        keys: &["baselines.imc"],
    },
    key: "baselines.imc",
    variant: None,
};

/// The authors' IMC.
pub const IMC_AUTHORS: Imc = Imc {
    info: Info {
        name: "imc-authors",
        teacher: None,
        tasks: &["avoiding"],
        keys: &["baselines.imc_authors"],
    },
    key: "baselines.imc_authors",
    variant: Some(ImcVariant::Authors),
};

impl Imc {
    fn config(&self, recipe: &MethodRecipe<'_>) -> crate::Result<ImcConfig> {
        let c: ImcConfig = recipe.get(self.key)?;
        match self.variant {
            Some(v) if c.variant != v => {
                Err(format!("`{}.variant` must be \"authors\", got {:?}", self.key, c.variant)
                    .into())
            }
            _ => Ok(c),
        }
    }
}

impl Method for Imc {
    fn info(&self) -> &Info {
        &self.info
    }
    fn check(&self, recipe: &MethodRecipe<'_>) -> crate::Result {
        self.config(recipe).map(drop)
    }
    fn train(&self, job: &Job<'_>) -> crate::Result<Trained> {
        let config = ImcConfig { seed: job.seed, ..self.config(&job.recipe)? };
        let (its, steps, batch) =
            (config.iterations, config.expert_steps_per_iter, config.batch_size);
        let budget = super::em::mixture_budget(job, its, steps, batch);
        let authors = self.variant.is_some();
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
