//! Learned diffusion teachers: `beso` and `ddpm` (the recipe's `teachers.beso` and
//! `teachers.ddpm`), and `beso-d3il`, the VDD paper's teacher, D3IL's BESO agent
//! (`baselines.beso_d3il`: a [`BesoTeacherConfig`], [`vdd_diffusion::BesoConfig::d3il`] in
//! Avoiding's defaults, trained as the recipe's BESO is). A source with its own key takes the
//! place of its family's recipe teacher for its rows only, so it is trained once per seed,
//! cached under its own key and shared by those rows.

use vdd_diffusion::TeacherKind;
use vdd_diffusion::cache::{BesoTeacherConfig, DdpmTeacherConfig};

use super::{TeacherSource, TeachersConfig};
use crate::capability::Capability;
use crate::recipe;

/// A learned teacher of family `kind`, configured by the recipe's `teachers.<kind>` or, with
/// a `key`, by that recipe key (a configuration of the same family).
pub struct Learned {
    /// The source's name.
    pub name: &'static str,
    /// Its family.
    pub kind: TeacherKind,
    /// The recipe key of its own configuration, in place of `teachers.<kind>` (none, or one).
    pub key: &'static [&'static str],
}

/// The recipe's BESO teacher.
pub const BESO: Learned = Learned { name: "beso", kind: TeacherKind::Beso, key: &[] };
/// The recipe's DDPM teacher.
pub const DDPM: Learned = Learned { name: "ddpm", kind: TeacherKind::Ddpm, key: &[] };
/// D3IL's BESO agent (`baselines.beso_d3il`).
pub const BESO_D3IL: Learned =
    Learned { name: "beso-d3il", kind: TeacherKind::Beso, key: &["baselines.beso_d3il"] };

impl TeacherSource for Learned {
    fn name(&self) -> &'static str {
        self.name
    }
    fn kind(&self) -> Option<TeacherKind> {
        Some(self.kind)
    }
    fn needs(&self) -> &'static [Capability] {
        &[Capability::LearnedTeachers]
    }
    fn keys(&self) -> &'static [&'static str] {
        self.key
    }
    fn teachers(
        &self,
        shared: &TeachersConfig,
        tree: &toml::Table,
    ) -> crate::Result<TeachersConfig> {
        let Some(&key) = self.key.first() else { return Ok(shared.clone()) };
        let missing = || format!("the recipe has no `{key}`");
        Ok(match self.kind {
            TeacherKind::Beso => {
                let beso: BesoTeacherConfig = recipe::get_path(tree, key)?.ok_or_else(missing)?;
                beso.config.validate().map_err(|e| format!("`{key}`: {e}"))?;
                TeachersConfig { beso, ..shared.clone() }
            }
            TeacherKind::Ddpm => {
                let ddpm: DdpmTeacherConfig = recipe::get_path(tree, key)?.ok_or_else(missing)?;
                ddpm.config.validate().map_err(|e| format!("`{key}`: {e}"))?;
                TeachersConfig { ddpm, ..shared.clone() }
            }
        })
    }
}
