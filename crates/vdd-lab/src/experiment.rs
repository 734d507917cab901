//! Running a recipe: [`Request`] (what `cargo xtask experiment` was asked) → the recipe file →
//! its task ([`crate::tasks`], found by the recipe's `task` key) → the shared stages
//! ([`crate::driver`]) → the methods ([`crate::methods`]).
//!
//! Results go to `out`, by default `results/<recipe>/<run>/` (see
//! [`crate::context::run_name`]). A run directory holds `resolved.toml` (the full
//! configuration, enough to re-run it as a recipe), `run.json` (command, git revision and dirty
//! flag, wall time), `metrics.json`, `table.md` and the plots.

use std::path::PathBuf;
use std::time::Instant;

use crate::Registry;
use crate::context::RunContext;
use crate::recipe::{self, Overrides};

/// One `experiment` request.
#[derive(Debug, Clone, Default)]
pub struct Request {
    /// A recipe name (a file in `recipes/`) or a path to a `.toml` recipe.
    pub recipe: String,
    /// `--quick`, `--seeds`, `--methods`, `--set`.
    pub overrides: Overrides,
    /// The task's shorthands (`--teacher`, `--iterations`, ...) as `(option, value)`.
    pub shorthands: Vec<(String, String)>,
    /// The run directory (default: `results/<recipe>/<run>`).
    pub out: Option<PathBuf>,
    /// Retrain cached teachers and students.
    pub fresh: bool,
    /// Continue a killed run in the same directory from its checkpoints.
    pub resume: bool,
    /// The command line, for `resolved.toml` and `run.json`.
    pub command: String,
    /// The project root: `recipes/` (recipe names), `results/` (default run directories and
    /// the caches), `docs/` (tuning logs); `None`: this workspace
    /// ([`crate::recipe::repo_root`]).
    pub root: Option<PathBuf>,
}

/// Resolves the request's recipe and runs its task with the workspace's methods and tasks
/// ([`Registry::builtin`]); a failed run leaves no run directory it created behind.
pub fn run(request: &Request) -> crate::Result {
    run_with(&Registry::builtin(), request)
}

/// The `[quick]` table of the task's own recipe (`recipes/<task>.toml`), for a recipe of the task
/// that has none: `--quick` on a tuning or table recipe runs the task's smoke settings instead of
/// its full budget. The error says why there is none.
fn task_quick(root: &std::path::Path, task: &str) -> Result<toml::Value, String> {
    let path = root.join("recipes").join(format!("{task}.toml"));
    if !path.is_file() {
        return Err(format!("the task has no recipe {} to take one from", path.display()));
    }
    match recipe::read_recipe(&path).map_err(|e| e.to_string())?.remove("quick") {
        Some(quick) => Ok(quick),
        None => Err(format!("neither has {}", path.display())),
    }
}

/// [`run`] with the methods and tasks of `registry` (a program's own added to the workspace's).
pub fn run_with(registry: &Registry, request: &Request) -> crate::Result {
    let started = Instant::now();
    let root = request.root.clone().unwrap_or_else(recipe::repo_root);
    let path = recipe::run::find_recipe(&root.join("recipes"), &request.recipe)?;
    let mut file = recipe::read_recipe(&path)?;
    let name = file
        .get("name")
        .and_then(|v| v.as_str())
        .map(String::from)
        .or_else(|| path.file_stem().and_then(|s| s.to_str()).map(String::from))
        .unwrap_or_else(|| request.recipe.clone());
    let names = || registry.tasks().iter().map(|t| t.name()).collect::<Vec<_>>().join(", ");
    let task = file
        .get("task")
        .and_then(|v| v.as_str())
        .ok_or_else(|| format!("{} has no `task` key ({})", path.display(), names()))?;
    let task = registry.task(task).map_err(|e| format!("{e} in {}", path.display()))?;
    if request.overrides.quick && !file.contains_key("quick") {
        let quick = task_quick(&root, task.name())
            .map_err(|e| format!("--quick: {} has no [quick] table, and {e}", path.display()))?;
        file.insert("quick".into(), quick);
    }
    let mut overrides = request.overrides.clone();
    task.apply_shorthands(&request.shorthands, &mut overrides)?;
    // Before anything is written: `--out` is new, empty or a previous run of this recipe.
    if let Some(out) = &request.out {
        crate::context::check_run_dir(out, &name)?;
    }
    let cache = root.join("results").join("cache");
    let ctx = RunContext {
        name,
        file,
        overrides,
        out: request.out.clone(),
        fresh: request.fresh,
        resume: request.resume,
        cache_dir: cache.join("teachers"),
        student_cache_dir: cache.join("students"),
        command: request.command.clone(),
        started,
        registry: registry.clone(),
        root,
        created: Default::default(),
    };
    let result = task.run(&ctx);
    if result.is_err() {
        ctx.remove_created_run_dir();
    }
    result
}
