//! `vdd-beso-learned`: the paper's VDD-BESO, with a learned gating, beside the headline
//! `vdd-beso` (uniform gating). Everything else is `vdd-beso`'s (`vdd.beso` and the shared VDD
//! keys); only `vdd.beso_gating` is replaced by `"learned"`, so a `--set vdd.beso...` changes
//! both rows alike. It reads no key of its own; its keys are `vdd-beso`'s, so that its
//! tuning-log configuration hash covers them.

use toml::Value;
use vdd_diffusion::TeacherKind;

use super::vdd::VDD_BESO;
use crate::method::{Capability, Info, Job, Method, MethodRecipe, Trained};

/// `vdd-beso-learned`.
pub struct VddBesoLearned;

const INFO: Info = Info {
    name: "vdd-beso-learned",
    teacher: Some(TeacherKind::Beso),
    needs: &[Capability::Rollouts, Capability::LearnedTeachers],
    only_on: &[],
    keys: VDD_BESO.0.keys,
};

/// `tree` with `vdd.beso_gating = "learned"`.
fn learned(tree: &toml::Table) -> crate::Result<toml::Table> {
    let mut tree = tree.clone();
    let vdd = tree.entry("vdd").or_insert_with(|| Value::Table(Default::default()));
    let vdd = vdd.as_table_mut().ok_or("the recipe's `vdd` is not a table")?;
    vdd.insert("beso_gating".into(), Value::String("learned".into()));
    Ok(tree)
}

impl Method for VddBesoLearned {
    fn info(&self) -> &Info {
        &INFO
    }
    fn shadowed_keys(&self) -> Vec<(&'static str, Option<String>)> {
        let mut keys = VDD_BESO.shadowed_keys();
        keys.retain(|(shared, _)| *shared != "student.gating");
        keys.push(("student.gating", None));
        keys.push(("vdd.beso_gating", None));
        keys
    }
    fn check(&self, recipe: &MethodRecipe<'_>) -> crate::Result {
        let tree = learned(recipe.tree)?;
        VDD_BESO.check(&MethodRecipe { tree: &tree, ..*recipe })
    }
    fn train(&self, job: &Job<'_>) -> crate::Result<Trained> {
        let tree = learned(job.recipe.tree)?;
        let recipe = MethodRecipe { tree: &tree, ..job.recipe };
        VDD_BESO.train(&Job { recipe, ..*job })
    }
}
