//! What a task is to the driver: the [`Task`] trait (the `task` key of a recipe) and the
//! [`TaskRecipe`] its recipe type implements. The tasks themselves, one file each, are in
//! [`crate::tasks`]; the stages they share in [`crate::driver`].

use serde::Serialize;
use serde::de::DeserializeOwned;
use vdd_moe::MoeConfig;

use crate::context::RunContext;
use crate::recipe::{Header, Overrides};
use crate::teachers::TeachersConfig;

pub use crate::capability::Capability;

/// A task of `cargo xtask experiment` (the `task` key of a recipe).
pub trait Task: Sync {
    /// `avoiding`, `toy-gmm`, ...
    fn name(&self) -> &'static str;
    /// What it offers its methods. By default a control task's: rollouts and learned teachers.
    fn offers(&self) -> &'static [Capability] {
        &[Capability::Rollouts, Capability::LearnedTeachers]
    }
    /// The columns of its results tables (after `method` and `seeds`).
    fn columns(&self) -> Vec<crate::report::Column>;
    /// Runs a recipe of this task.
    fn run(&self, ctx: &RunContext) -> crate::Result;
    /// Translates the task's command-line shorthands (`--teacher`, `--iterations`, ...; as
    /// `(option, value)`) into recipe overrides. By default the task has none.
    fn apply_shorthands(
        &self,
        shorthands: &[(String, String)],
        _: &mut Overrides,
    ) -> Result<(), String> {
        match shorthands.first() {
            Some((k, _)) => Err(format!("option --{k} does not apply to task `{}`", self.name())),
            None => Ok(()),
        }
    }
}

/// What the shared stages need of a task's recipe type.
pub trait TaskRecipe: Serialize + DeserializeOwned + Sync {
    /// The top-level tables read by the methods ([`crate::method::Method::keys`] lists their
    /// keys); a row's `set` may only touch these.
    const METHOD_SECTIONS: &'static [&'static str];
    /// Name, description, task, seeds and methods.
    fn header(&self) -> &Header;
    /// The learned teachers.
    fn teachers(&self) -> &TeachersConfig;
    /// The students' mixture.
    fn student(&self) -> &MoeConfig;
}
