//! The keys every recipe starts with.

use serde::{Deserialize, Serialize};

/// The keys every recipe starts with: its name, what it shows, its task, run seeds and methods
/// (what `--seeds` and `--methods` of [`crate::Overrides`] replace).
///
/// A recipe type embeds it with `#[serde(flatten)]`, first, so that the keys stay at the top
/// level of the file and of `resolved.toml`. Such a type cannot use
/// `#[serde(deny_unknown_fields)]` (serde refuses it next to `flatten`) and needs not: unknown
/// keys are found by [`crate::from_tree`] (which [`crate::resolve`] and
/// [`crate::defaults_from_toml`] use), and named in the error.
///
/// ```
/// use serde::{Deserialize, Serialize};
/// use vdd_recipe::{Header, Overrides, resolve};
///
/// #[derive(Debug, Serialize, Deserialize)]
/// struct Recipe {
///     #[serde(flatten)]
///     header: Header,
///     iterations: usize,
/// }
///
/// let defaults: Recipe = vdd_recipe::from_tree(&toml::from_str(
///     "name = \"r\"\ndescription = \"d\"\ntask = \"t\"\nseeds = [0]\nmethods = [\"m\"]\niterations = 1",
/// )?)?;
/// let resolved = resolve(&defaults, &"iterations = 5".parse()?, &Overrides::default())?;
/// assert_eq!((resolved.base.header.seeds.as_slice(), resolved.base.iterations), (&[0][..], 5));
/// // A key the recipe type does not know is an error that names it.
/// let err = resolve(&defaults, &"iteration = 5".parse()?, &Overrides::default()).unwrap_err();
/// assert!(err.to_string().contains("iteration"), "{err}");
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Header {
    /// Recipe name (results go to `results/<name>/`).
    pub name: String,
    /// One line on what the recipe shows.
    pub description: String,
    /// The task it runs.
    pub task: String,
    /// Run seeds.
    pub seeds: Vec<u64>,
    /// The rows to run: names of rows (each a method run from a teacher; `vdd_lab`'s built-in
    /// rows or this recipe's own `runs`).
    pub methods: Vec<String>,
    /// The recipe's own rows, `[runs.<name>]` tables (their fields are the experiment layer's,
    /// `vdd_lab::row::RowSpec`), beside the built-in ones; absent when the recipe adds none.
    #[serde(default, skip_serializing_if = "toml::Table::is_empty")]
    pub runs: toml::Table,
}
