//! The tasks a recipe can name (its `task` key), one file each, and their list [`BUILTIN`]
//! (what [`crate::registry::Registry::builtin`] holds).
//!
//! Adding a task: a new file here implementing [`crate::task::Task`] (usually: a recipe type
//! implementing [`crate::task::TaskRecipe`], its defaults in `recipes/defaults/<task>.toml`,
//! data preparation, evaluation) and one line in [`BUILTIN`]; the methods whose needs it offers
//! ([`crate::task::Task::offers`], [`crate::method::Info::needs`]) run on it (docs/recipes.md,
//! "Adding a task"). A task outside this crate is added with
//! [`crate::registry::Registry::with_task`]. The D3IL contact tasks (Pushing, Aligning) share
//! one pipeline, [`D3ilRecipe`] over a [`D3ilTask`]: each of their files says only what is its
//! own.

use crate::task::Task;

mod aligning;
mod avoiding;
mod block_push;
mod d3il;
mod pushing;
mod rollouts;
mod toy;
mod toy_eval;

pub use aligning::{Aligning, AligningRecipe, COLUMNS as ALIGNING_COLUMNS};
pub use avoiding::{AvoidingRecipe, COLUMNS as AVOIDING_COLUMNS};
pub use block_push::{BlockPushRecipe, COLUMNS as BLOCK_PUSH_COLUMNS};
pub use d3il::{D3il, D3ilEval, D3ilPlots, D3ilRecipe, D3ilTask, FigureFn, PanelFn};
pub use pushing::{COLUMNS as PUSHING_COLUMNS, Pushing, PushingRecipe};
pub use toy::check_toy_gmm;

/// The workspace's tasks.
pub static BUILTIN: &[&dyn Task] = &[
    &avoiding::Avoiding,
    &toy::TOY_GMM,
    &toy::TOY_CONDITIONAL,
    &block_push::BlockPush,
    &D3il::<Pushing>::TASK,
    &D3il::<Aligning>::TASK,
];
