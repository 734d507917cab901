//! The tasks a recipe can name (its `task` key), one file each, and their [`REGISTRY`].
//!
//! Adding a task: a new file here implementing [`crate::pipeline::Task`] (usually: a recipe type
//! implementing [`crate::pipeline::TaskRecipe`], its defaults in `recipes/defaults/<task>.toml`,
//! data preparation, evaluation), one line in [`REGISTRY`], and the task's name in the
//! [`crate::method::Method::tasks`] of the methods that run on it (docs/recipes.md, "Adding a
//! task").

use crate::pipeline::Task;

mod avoiding;
mod avoiding_imported;
mod toy;
mod toy_eval;

pub use avoiding::AvoidingRecipe;
pub use toy::check_toy_gmm;

/// Every task.
pub static REGISTRY: &[&dyn Task] = &[&avoiding::Avoiding, &toy::TOY_GMM, &toy::TOY_CONDITIONAL];

/// The task called `name`.
pub fn find(name: &str) -> Result<&'static dyn Task, String> {
    REGISTRY.iter().copied().find(|t| t.name() == name).ok_or_else(|| {
        let names: Vec<&str> = REGISTRY.iter().map(|t| t.name()).collect();
        format!("unknown task `{name}` ({})", names.join(", "))
    })
}
