//! `teacher`: a learned teacher as a row of the table (`ddpm`, `beso`), sampling with its
//! default steps, or with `with.steps` of them (`ddpm-1`, `beso-1`: one step). Its training is
//! the teacher's (shared with every row distilled from it). A teacher loaded from a file
//! (`imported`) acts as its package does, through its own window, chunk and features (its
//! sampler's steps as imported; `with.steps` is refused). Keys: none of its own.

use serde::Deserialize;

use crate::method::{
    Budget, Capability, Info, Job, Method, MethodRecipe, Row, TeacherUse, Trained,
};
use crate::plots::Curves;
use crate::policy::TrainedPolicy;
use crate::teachers;

/// The teacher itself as a policy.
pub struct TeacherRow;

const INFO: Info = Info {
    name: "teacher",
    teacher: TeacherUse::Acting,
    needs: &[Capability::Rollouts],
    row_keys: &["steps"],
};

/// A row's settings: the sampling steps (default: the teacher's own).
#[derive(Debug, Default, Deserialize)]
#[serde(deny_unknown_fields)]
struct Settings {
    steps: Option<usize>,
}

fn settings(row: &Row) -> crate::Result<Settings> {
    let s: Settings = row.settings()?;
    if s.steps == Some(0) {
        return Err(format!("row `{}`: `with.steps` must be at least 1", row.name).into());
    }
    Ok(s)
}

impl Method for TeacherRow {
    fn info(&self) -> &Info {
        &INFO
    }
    fn keys(&self, _: &Row) -> Vec<String> {
        Vec::new()
    }
    fn check(&self, recipe: &MethodRecipe<'_>) -> crate::Result {
        settings(recipe.row).map(drop)
    }
    fn train(&self, job: &Job<'_>) -> crate::Result<Trained> {
        let steps = settings(job.recipe.row)?.steps;
        if let Some(loaded) = job.loaded {
            if steps.is_some() {
                return Err(format!(
                    "row `{}`: `with.steps` of a teacher from a file (it samples as imported)",
                    job.recipe.row.name
                )
                .into());
            }
            let policy = TrainedPolicy::Other(Box::new(loaded.teacher.clone()));
            // Trained elsewhere: no training time here (`null` in the results).
            return Ok(Trained {
                deploy: Some(loaded.deploy_spec()),
                ..Trained::new(policy, f64::NAN, Curves::new())
            });
        }
        let t = job.teacher()?;
        let mut teacher = t.teacher.clone();
        if let Some(steps) = steps {
            teacher.set_steps(steps)?;
        }
        let loss = t.losses.iter().map(|&(s, l)| (s as f64, f64::from(l))).collect();
        let kind = teacher.kind();
        let curves = Curves::from([(format!("{} teacher loss", teachers::kind_name(kind)), loss)]);
        let steps = teacher.steps();
        let train = match kind {
            vdd_diffusion::TeacherKind::Beso => &job.recipe.teachers.beso.train,
            vdd_diffusion::TeacherKind::Ddpm => &job.recipe.teachers.ddpm.train,
        };
        let budget = Budget::teacher(train.steps, train.batch_size);
        let policy = TrainedPolicy::Teacher(Box::new(teacher));
        Ok(Trained {
            sampling_steps: Some(steps),
            budget: Some(budget),
            ..Trained::new(policy, t.train_seconds, curves)
        })
    }
}
