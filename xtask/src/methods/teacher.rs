//! The learned teachers as rows of the table: `ddpm` and `beso` with their default sampling
//! steps, `ddpm-1` and `beso-1` with one step. Their training is the teacher's (shared with
//! every method distilled from it).

use vdd_diffusion::TeacherKind;

use crate::method::{Job, Method, MethodRecipe, Trained};
use crate::plots::Curves;
use crate::policy::TrainedPolicy;
use crate::teachers;

/// A learned teacher sampling with its default steps, or with one.
pub struct TeacherRow {
    name: &'static str,
    kind: TeacherKind,
    one_step: bool,
}

/// `ddpm`.
pub const DDPM: TeacherRow = TeacherRow { name: "ddpm", kind: TeacherKind::Ddpm, one_step: false };
/// `beso`.
pub const BESO: TeacherRow = TeacherRow { name: "beso", kind: TeacherKind::Beso, one_step: false };
/// `ddpm-1`.
pub const DDPM_1: TeacherRow =
    TeacherRow { name: "ddpm-1", kind: TeacherKind::Ddpm, one_step: true };
/// `beso-1`.
pub const BESO_1: TeacherRow =
    TeacherRow { name: "beso-1", kind: TeacherKind::Beso, one_step: true };

impl Method for TeacherRow {
    fn name(&self) -> &'static str {
        self.name
    }
    fn teacher(&self) -> Option<TeacherKind> {
        Some(self.kind)
    }
    fn tasks(&self) -> &'static [&'static str] {
        &["avoiding"]
    }
    fn keys(&self) -> &'static [&'static str] {
        &[]
    }
    fn check(&self, _: &MethodRecipe<'_>) -> crate::XResult {
        Ok(())
    }
    fn train(&self, job: &Job<'_>) -> crate::XResult<Trained> {
        let t = job.teacher()?;
        let mut teacher = t.teacher.clone();
        if self.one_step {
            teacher.set_steps(1)?;
        }
        let mut curves = Curves::default();
        curves.insert(
            format!("{} teacher loss", teachers::kind_name(self.kind)),
            t.losses.iter().map(|&(s, l)| (s as f64, f64::from(l))).collect(),
        );
        let steps = teacher.steps();
        let policy = TrainedPolicy::Teacher(Box::new(teacher));
        Ok(Trained { sampling_steps: Some(steps), ..Trained::new(policy, t.train_seconds, curves) })
    }
}
