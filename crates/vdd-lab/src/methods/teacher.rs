//! The learned teachers as rows of the table: `ddpm` and `beso` with their default sampling
//! steps, `ddpm-1` and `beso-1` with one step. Their training is the teacher's (shared with
//! every method distilled from it).

use vdd_diffusion::TeacherKind;

use crate::method::{Budget, BudgetRole, Info, Job, Method, MethodRecipe, Trained};
use crate::plots::Curves;
use crate::policy::TrainedPolicy;
use crate::teachers;

/// A learned teacher sampling with its default steps, or with one.
pub struct TeacherRow(pub(super) Info, pub(super) bool);

const fn row(name: &'static str, kind: TeacherKind, one_step: bool) -> TeacherRow {
    TeacherRow(
        Info { name, teacher: Some(kind), tasks: &["avoiding", "block-push"], keys: &[] },
        one_step,
    )
}

/// `ddpm`, `beso`, `ddpm-1`, `beso-1`.
pub const DDPM: TeacherRow = row("ddpm", TeacherKind::Ddpm, false);
#[allow(missing_docs)]
pub const BESO: TeacherRow = row("beso", TeacherKind::Beso, false);
#[allow(missing_docs)]
pub const DDPM_1: TeacherRow = row("ddpm-1", TeacherKind::Ddpm, true);
#[allow(missing_docs)]
pub const BESO_1: TeacherRow = row("beso-1", TeacherKind::Beso, true);

impl Method for TeacherRow {
    fn info(&self) -> &Info {
        &self.0
    }
    fn check(&self, _: &MethodRecipe<'_>) -> crate::Result {
        Ok(())
    }
    fn train(&self, job: &Job<'_>) -> crate::Result<Trained> {
        let t = job.teacher()?;
        let mut teacher = t.teacher.clone();
        if self.1 {
            teacher.set_steps(1)?;
        }
        let loss = t.losses.iter().map(|&(s, l)| (s as f64, f64::from(l))).collect();
        let kind = teachers::kind_name(teacher.kind());
        let curves = Curves::from([(format!("{kind} teacher loss"), loss)]);
        let steps = teacher.steps();
        let train = match teacher.kind() {
            TeacherKind::Beso => &job.recipe.teachers.beso.train,
            TeacherKind::Ddpm => &job.recipe.teachers.ddpm.train,
        };
        let budget =
            Budget { steps: train.steps, batch: train.batch_size, role: BudgetRole::Teacher };
        let policy = TrainedPolicy::Teacher(Box::new(teacher));
        Ok(Trained {
            sampling_steps: Some(steps),
            budget: Some(budget),
            ..Trained::new(policy, t.train_seconds, curves)
        })
    }
}
