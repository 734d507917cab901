//! Recipe files and run directories: the recipes of a directory ([`recipes_in`],
//! [`find_recipe`]), the default names of run directories ([`run_name`]) and the revision a run
//! was made at ([`git_revision`]), and what a run's cells share ([`Shared`]: one dataset per
//! distinct configuration, whatever the seed and the method).

use std::path::{Path, PathBuf};

use crate::{Overrides, RecipeError, RecipeResult, fnv1a};

/// The names (file stems) of the `.toml` recipes in `dir`, sorted (none when it cannot be
/// read).
pub fn recipes_in(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .filter_map(|e| {
                    let p = e.path();
                    (p.extension()? == "toml").then(|| p.file_stem()?.to_str().map(String::from))?
                })
                .collect()
        })
        .unwrap_or_default();
    names.sort();
    names
}

/// The recipe file for `name`: an existing `.toml` path, or `<dir>/<name>.toml`; an error
/// listing the recipes of `dir` when neither exists.
pub fn find_recipe(dir: &Path, name: &str) -> RecipeResult<PathBuf> {
    let direct = Path::new(name);
    if name.ends_with(".toml") && direct.is_file() {
        return Ok(direct.to_path_buf());
    }
    let path = dir.join(format!("{name}.toml"));
    if path.is_file() {
        Ok(path)
    } else {
        let available = recipes_in(dir).join(", ");
        Err(RecipeError::NoRecipe { name: name.to_owned(), path, available })
    }
}

/// The default name of a run directory: `seed0`, `seed0-1-2`, `+ -quick` under `--quick`,
/// `+ -o<hash>` (six hex digits of [`fnv1a`] of the overrides) when methods or `--set` were
/// overridden.
pub fn run_name(seeds: &[u64], o: &Overrides) -> String {
    let list: Vec<String> = seeds.iter().map(u64::to_string).collect();
    let mut name = format!("seed{}", list.join("-"));
    if o.quick {
        name.push_str("-quick");
    }
    if o.has_config_overrides() {
        let key = format!("{:?}|{:?}", o.methods, o.sets);
        name.push_str(&format!("-o{:06x}", fnv1a(key.as_bytes()) & 0xff_ffff));
    }
    name
}

/// The first lines of a run's `resolved.toml`: the recipe, the command, and how to run the
/// file in `dir` again.
pub fn resolved_header(recipe: &str, command: &str, dir: &Path) -> String {
    format!(
        "# Resolved configuration of recipe `{recipe}`.\n# Command: {command}\n# Re-run: cargo xtask experiment {}/resolved.toml\n\n",
        dir.display()
    )
}

/// A run's `run.json`: the recipe, the command, the revision of the repository at `root`
/// ([`git_revision`]), wall and CPU seconds, the threads available and `details`.
pub fn run_info(
    recipe: &str,
    command: &str,
    root: &Path,
    (wall_seconds, cpu_seconds): (f64, Option<f64>),
    details: serde_json::Value,
) -> serde_json::Value {
    let (revision, dirty) = git_revision(root);
    serde_json::json!({
        "recipe": recipe,
        "command": command,
        "git": { "revision": revision, "dirty": dirty },
        "wall_seconds": wall_seconds,
        "cpu_seconds": cpu_seconds,
        "threads_available": std::thread::available_parallelism().map_or(1, |p| p.get()),
        "details": details,
    })
}

/// `(git rev-parse HEAD, working tree dirty)` of the repository at `root`, or
/// `("unknown", None)` without git.
pub fn git_revision(root: &Path) -> (String, Option<bool>) {
    let run = |args: &[&str]| {
        std::process::Command::new("git")
            .args(args)
            .current_dir(root)
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_owned())
    };
    match run(&["rev-parse", "HEAD"]) {
        Some(rev) if !rev.is_empty() => {
            let dirty =
                run(&["status", "--porcelain", "--untracked-files=no"]).map(|s| !s.is_empty());
            (rev, dirty)
        }
        _ => ("unknown".into(), None),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn recipes_are_found_by_name_or_path() {
        let dir = std::env::temp_dir().join(format!("vdd-recipe-find-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for f in ["b.toml", "a.toml", "notes.md"] {
            std::fs::write(dir.join(f), "").unwrap();
        }
        assert_eq!(recipes_in(&dir), ["a", "b"]);
        assert_eq!(find_recipe(&dir, "a").unwrap(), dir.join("a.toml"));
        let path = dir.join("b.toml");
        assert_eq!(find_recipe(Path::new("/nonexistent"), path.to_str().unwrap()).unwrap(), path);
        let e = find_recipe(&dir, "c").unwrap_err().to_string();
        assert!(e.contains("no recipe `c`") && e.ends_with("available: a, b"), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn run_records_name_the_recipe_command_and_revision() {
        let dir = Path::new("results/toy/seed0");
        let h = resolved_header("toy", "cargo xtask experiment toy", dir);
        assert!(h.starts_with("# Resolved configuration of recipe `toy`.\n# Command: cargo"));
        assert!(h.ends_with("experiment results/toy/seed0/resolved.toml\n\n"), "{h}");
        let root = std::env::temp_dir().join(format!("vdd-recipe-run-{}", std::process::id()));
        std::fs::create_dir_all(&root).unwrap();
        let info = run_info("toy", "c", &root, (1.5, None), serde_json::json!({"jobs": 2}));
        assert_eq!(
            (info["recipe"].as_str(), info["wall_seconds"].as_f64()),
            (Some("toy"), Some(1.5))
        );
        assert!(info["cpu_seconds"].is_null() && info["git"]["revision"].is_string());
        assert_eq!(info["details"]["jobs"], 2);
        std::fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn run_names_follow_seeds_and_overrides() {
        let mut o = Overrides::default();
        assert_eq!(run_name(&[0], &o), "seed0");
        assert_eq!(run_name(&[0, 1, 2], &o), "seed0-1-2");
        o.quick = true;
        assert_eq!(run_name(&[0], &o), "seed0-quick");
        o.sets.push(("a".into(), "1".into()));
        let n = run_name(&[0], &o);
        assert!(n.starts_with("seed0-quick-o") && n.len() == "seed0-quick-o".len() + 6, "{n}");
        o.sets[0].1 = "2".into();
        assert_ne!(run_name(&[0], &o), n);
    }
}

/// Values shared by the cells of a run's grid (seed `si` × entry `pi`): one value per distinct
/// key, built once, in the order the cells are visited (seed by seed, entry by entry).
///
/// ```
/// use vdd_recipe::run::Shared;
/// let mut built = 0;
/// // Two seeds × three entries; the data depend on the entry's parity only.
/// let key = |_si: usize, pi: usize| Ok::<_, String>(format!("data-{}", pi % 2));
/// let shared = Shared::build(2, 3, key, |_si, pi| {
///     built += 1;
///     Ok(pi % 2)
/// })?;
/// assert_eq!(built, 2);
/// assert_eq!(shared.id(1, 2), shared.id(0, 0));
/// assert_eq!(*shared.get(1, 1), 1);
/// # Ok::<(), String>(())
/// ```
#[derive(Debug, Clone)]
pub struct Shared<P> {
    values: Vec<P>,
    /// The value of each cell, `si * entries + pi`.
    index: Vec<usize>,
    entries: usize,
}

impl<P> Shared<P> {
    /// Builds the values of a grid of `seeds` × `entries` cells: cells with equal `key`s share
    /// one value, which `make` builds for the first of them.
    pub fn build<E>(
        seeds: usize,
        entries: usize,
        mut key: impl FnMut(usize, usize) -> Result<String, E>,
        mut make: impl FnMut(usize, usize) -> Result<P, E>,
    ) -> Result<Self, E> {
        let mut keys: std::collections::HashMap<String, usize> = Default::default();
        let mut out =
            Self { values: Vec::new(), index: Vec::with_capacity(seeds * entries), entries };
        for si in 0..seeds {
            for pi in 0..entries {
                let i = match keys.entry(key(si, pi)?) {
                    std::collections::hash_map::Entry::Occupied(o) => *o.get(),
                    std::collections::hash_map::Entry::Vacant(v) => {
                        out.values.push(make(si, pi)?);
                        *v.insert(out.values.len() - 1)
                    }
                };
                out.index.push(i);
            }
        }
        Ok(out)
    }

    /// The index of the value of cell (`si`, `pi`): equal indices, the same value. Panics
    /// outside the grid.
    pub fn id(&self, si: usize, pi: usize) -> usize {
        assert!(pi < self.entries, "entry {pi} outside a grid of {} entries", self.entries);
        self.index[si * self.entries + pi]
    }

    /// The value of cell (`si`, `pi`). Panics outside the grid.
    pub fn get(&self, si: usize, pi: usize) -> &P {
        &self.values[self.id(si, pi)]
    }
}
