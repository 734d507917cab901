//! `imc-authors`: IMC as in the authors' code ([`ImcVariant::Authors`]: unit-variance experts,
//! curricula normalised per data point, the gating fitted at the end), beside the
//! paper-literal `imc`. Keys: `baselines.imc_authors` (an [`ImcConfig`] whose `variant` must
//! be `"authors"`; its `seed` is replaced by the run seed).

use vdd_mixture::{ImcConfig, ImcVariant};

use crate::method::{Info, Job, Method, MethodRecipe, Trained};

/// The authors' IMC.
pub struct ImcAuthors;

const KEY: &str = "baselines.imc_authors";

const INFO: Info = Info { name: "imc-authors", teacher: None, tasks: &["avoiding"], keys: &[KEY] };

fn config(recipe: &MethodRecipe<'_>) -> crate::XResult<ImcConfig> {
    let c: ImcConfig = recipe.get(KEY)?;
    if c.variant != ImcVariant::Authors {
        return Err(format!("`{KEY}.variant` must be \"authors\", got {:?}", c.variant).into());
    }
    Ok(c)
}

impl Method for ImcAuthors {
    fn info(&self) -> &Info {
        &INFO
    }
    fn check(&self, recipe: &MethodRecipe<'_>) -> crate::XResult {
        config(recipe).map(drop)
    }
    fn train(&self, job: &Job<'_>) -> crate::XResult<Trained> {
        let config = ImcConfig { seed: job.seed, ..config(&job.recipe)? };
        super::imc::train(job, config, |curves, m| {
            let x = m.iteration as f64;
            let ll = curves.entry("log-likelihood, unit variances (nats)".into()).or_default();
            ll.push((x, m.log_likelihood));
            let cover = curves.entry("effective data fraction".into()).or_default();
            cover.push((x, m.effective_data_fraction));
        })
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
