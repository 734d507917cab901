//! The VDD paper's teacher, D3IL's BESO agent, beside the recipe's BESO: `beso-d3il` (its
//! default sampling steps), `beso-d3il-1` (one step) and `vdd-beso-d3il` (VDD distilled from
//! it). Keys: `baselines.beso_d3il` (a [`BesoTeacherConfig`]: the model, [`BesoConfig::d3il`]
//! in the defaults, and its training, the recipe BESO's), and for `vdd-beso-d3il`
//! `vdd.beso_d3il` (the `VddConfig`) and `vdd.beso_d3il_gating`, with the shared VDD keys.
//!
//! The D3IL teacher takes the place of the BESO teacher for these rows only
//! ([`Method::teachers`]), so it is trained once per seed, cached under its own key and shared
//! by the three rows.
//!
//! [`BesoConfig::d3il`]: vdd_diffusion::BesoConfig::d3il

use vdd_diffusion::TeacherKind;

use super::teacher::TeacherRow;
use super::vdd::{VddMethod, vdd_keys};
use crate::method::{Capability, Info, Job, Method, MethodRecipe, Trained};
use crate::teachers::TeachersConfig;
use vdd_diffusion::cache::BesoTeacherConfig;

/// The recipe key of the D3IL teacher.
pub const KEY: &str = "baselines.beso_d3il";

/// A method run with the D3IL teacher in place of the recipe's BESO.
pub struct D3il<M>(M);

/// `beso-d3il`, `beso-d3il-1`, `vdd-beso-d3il`.
pub const BESO_D3IL: D3il<TeacherRow> = D3il(TeacherRow(teacher_info("beso-d3il"), false));
#[allow(missing_docs)]
pub const BESO_D3IL_1: D3il<TeacherRow> = D3il(TeacherRow(teacher_info("beso-d3il-1"), true));

/// The D3IL configurations are Avoiding's settings.
const AVOIDING: &[&str] = &["avoiding"];

const fn teacher_info(name: &'static str) -> Info {
    Info {
        name,
        teacher: Some(TeacherKind::Beso),
        needs: &[Capability::Rollouts, Capability::LearnedTeachers],
        only_on: AVOIDING,
        keys: &[KEY],
    }
}
#[allow(missing_docs)]
pub const VDD_BESO_D3IL: D3il<VddMethod> = D3il(VddMethod(
    Info {
        name: "vdd-beso-d3il",
        teacher: Some(TeacherKind::Beso),
        needs: &[Capability::LearnedTeachers],
        only_on: AVOIDING,
        keys: vdd_keys!("beso_d3il", KEY),
    },
    "beso_d3il",
));

impl<M: Method> Method for D3il<M> {
    fn info(&self) -> &Info {
        self.0.info()
    }
    fn check(&self, recipe: &MethodRecipe<'_>) -> crate::Result {
        let teachers = self.teachers(recipe)?;
        self.0.check(&MethodRecipe { teachers: &teachers, ..*recipe })
    }
    fn train(&self, job: &Job<'_>) -> crate::Result<Trained> {
        self.0.train(job)
    }
    fn teachers(&self, recipe: &MethodRecipe<'_>) -> crate::Result<TeachersConfig> {
        let beso: BesoTeacherConfig = recipe.get(KEY)?;
        beso.config.validate().map_err(|e| format!("`{KEY}`: {e}"))?;
        Ok(TeachersConfig { beso, ..recipe.teachers.clone() })
    }
}
