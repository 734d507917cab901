//! `vdd-beso-oracle`, a diagnostic row: `vdd-beso`'s student (the same training, so the
//! cached student when there is one) acting with its gating replaced by the responsibilities
//! of a BESO sample at each step ([`OracleGating`]). Beside `vdd-beso` it tells whether the
//! experts or the weights lose success: if the oracle reaches the teacher's success, the
//! experts hold the teacher's good actions and only the weights are wrong. It reads no key of
//! its own; its keys are `vdd-beso`'s.

use vdd_diffusion::TeacherKind;

use super::vdd::VDD_BESO;
use crate::method::{Info, Job, Method, MethodRecipe, Trained};
use crate::policy::{OracleGating, TrainedPolicy};

/// `vdd-beso-oracle`.
pub struct VddBesoOracle;

const INFO: Info = Info {
    name: "vdd-beso-oracle",
    teacher: Some(TeacherKind::Beso),
    tasks: &["avoiding"],
    keys: VDD_BESO.0.keys,
};

impl Method for VddBesoOracle {
    fn info(&self) -> &Info {
        &INFO
    }
    fn shadowed_keys(&self) -> Vec<(&'static str, Option<String>)> {
        VDD_BESO.shadowed_keys()
    }
    fn check(&self, recipe: &MethodRecipe<'_>) -> crate::Result {
        VDD_BESO.check(recipe)
    }
    fn train(&self, job: &Job<'_>) -> crate::Result<Trained> {
        let mut trained = VDD_BESO.train(job)?;
        let TrainedPolicy::Moe(student) = trained.policy else {
            return Err("vdd-beso did not train a mixture".into());
        };
        let teacher = job.teacher()?.teacher.clone();
        trained.policy =
            TrainedPolicy::OracleGated(Box::new(OracleGating::new(*student, teacher)?));
        Ok(trained)
    }
}
