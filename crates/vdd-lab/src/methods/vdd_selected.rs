//! `vdd-beso-selected`: the paper's checkpoint selection as a labelled row. The official VDD
//! code reports the best of its training's snapshots by an entropy estimate from a few
//! held-out rollouts, not the final iterate. This row is `vdd-beso`'s training (the same
//! settings and cache key) whose policy is the snapshot with the highest held-out task entropy
//! among the curves' checkpoints (`eval.curve_points` of them, each scored on the curves' own
//! held-out episodes, never on the evaluation's); `vdd-beso` beside it is the final iterate.
//! The chosen iteration and its value are the `selected checkpoint` series of its curves.
//!
//! Key: `vdd.select_by`, the curve series to maximise (default `held-out task entropy`, as
//! the official code selects); every other key is `vdd-beso`'s.

use vdd_diffusion::TeacherKind;

use super::vdd::VDD_BESO;
use crate::method::{Capability, Info, Job, Method, MethodRecipe, Trained};

/// `vdd-beso-selected`.
pub struct VddBesoSelected;

/// The key naming the selection's curve series.
const SELECT_BY: &str = "vdd.select_by";

const INFO: Info = Info {
    name: "vdd-beso-selected",
    teacher: Some(TeacherKind::Beso),
    needs: &[Capability::Rollouts, Capability::LearnedTeachers],
    only_on: &[],
    keys: super::vdd::vdd_keys!("beso", SELECT_BY),
};

fn series(recipe: &MethodRecipe<'_>) -> crate::Result<String> {
    Ok(recipe
        .get_opt::<String>(SELECT_BY)?
        .unwrap_or_else(|| super::vdd::DEFAULT_SELECTION.to_owned()))
}

impl Method for VddBesoSelected {
    fn info(&self) -> &Info {
        &INFO
    }
    fn shadowed_keys(&self) -> Vec<(&'static str, Option<String>)> {
        VDD_BESO.shadowed_keys()
    }
    fn check(&self, recipe: &MethodRecipe<'_>) -> crate::Result {
        series(recipe)?;
        VDD_BESO.check(recipe)
    }
    fn train(&self, job: &Job<'_>) -> crate::Result<Trained> {
        let series = series(&job.recipe)?;
        VDD_BESO.train_selecting(job, Some(&series))
    }
}
