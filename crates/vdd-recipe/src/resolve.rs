//! Resolution of a recipe file against defaults, overrides and variants.

use std::path::Path;

use serde::Serialize;
use serde::de::DeserializeOwned;
use toml::{Table, Value};

use crate::tree::{changed_keys, expand_dotted, from_tree, merge, parse_value, set_path, to_tree};
use crate::{RecipeError, RecipeResult, unknown_keys};

/// Command-line overrides of a recipe.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Overrides {
    /// `--quick`: merge the recipe's `[quick]` table.
    pub quick: bool,
    /// `--seeds 0,1,2` or `--seed N`: replaces the `seeds` key.
    pub seeds: Option<Vec<u64>>,
    /// `--methods a,b`: replaces the `methods` key.
    pub methods: Option<Vec<String>>,
    /// `--set key.path=value`, in order (values are parsed with
    /// [`parse_value`](crate::parse_value)).
    pub sets: Vec<(String, String)>,
}

impl Overrides {
    /// Whether anything beyond seeds and `--quick` was overridden (then the default run name
    /// carries a hash of the overrides).
    pub fn has_config_overrides(&self) -> bool {
        self.methods.is_some() || !self.sets.is_empty()
    }
}

/// One `[[variants]]` entry: a named set of overrides on top of the resolved recipe.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Variant {
    /// Short lower-case name, appended to method names (`vdd-beso-z4`).
    pub name: String,
    /// What the variant changes, for tables and plots.
    #[serde(default)]
    pub description: String,
    /// `"key.path" = value` overrides.
    #[serde(default)]
    pub set: Table,
}

/// A resolved recipe: the base configuration and one configuration per variant.
#[derive(Debug, Clone)]
pub struct Resolved<R> {
    /// The base configuration (defaults, file, `--quick`, CLI overrides).
    pub base: R,
    /// The base configuration as a TOML tree (what `resolved.toml` holds).
    pub tree: Table,
    /// `(variant, configuration)` pairs; empty when the recipe has no variants.
    pub variants: Vec<(Variant, R)>,
}

impl<R> Resolved<R> {
    /// The configurations to run: `(variant, config)`; the base alone (without a variant) when
    /// there are no variants.
    pub fn configs(&self) -> Vec<(Option<&Variant>, &R)> {
        if self.variants.is_empty() {
            vec![(None, &self.base)]
        } else {
            self.variants.iter().map(|(v, r)| (Some(v), r)).collect()
        }
    }

    /// The resolved configuration as TOML text, variants appended as `[[variants]]`.
    pub fn to_toml(&self) -> RecipeResult<String> {
        let mut t = self.tree.clone();
        if !self.variants.is_empty() {
            let vs: Vec<Value> = self
                .variants
                .iter()
                .map(|(v, _)| Value::try_from(v).map_err(RecipeError::Serialize))
                .collect::<RecipeResult<_>>()?;
            t.insert("variants".into(), Value::Array(vs));
        }
        toml::to_string_pretty(&t).map_err(RecipeError::Serialize)
    }
}

/// Resolves a recipe `file` against `defaults` and the command-line `overrides` (see the
/// [crate docs](crate) for the order of the layers).
///
/// ```
/// use serde::{Deserialize, Serialize};
/// use vdd_recipe::{Overrides, resolve};
///
/// #[derive(Debug, Serialize, Deserialize)]
/// struct Train {
///     lr: f32,
///     iterations: usize,
/// }
///
/// #[derive(Debug, Serialize, Deserialize)]
/// struct Recipe {
///     seeds: Vec<u64>,
///     train: Train,
/// }
///
/// let defaults = Recipe { seeds: vec![0], train: Train { lr: 1e-3, iterations: 1000 } };
/// let file: toml::Table = r#"
///     [train]
///     lr = 5e-4
///     [quick]
///     "train.iterations" = 10
/// "#
/// .parse()?;
/// let overrides = Overrides {
///     quick: true,
///     seeds: Some(vec![1, 2]),
///     sets: vec![("train.lr".into(), "2e-3".into())],
///     ..Overrides::default()
/// };
/// let resolved = resolve(&defaults, &file, &overrides)?;
/// assert_eq!(resolved.base.train.iterations, 10);
/// assert_eq!(resolved.base.train.lr, 2e-3);
/// assert_eq!(resolved.base.seeds, [1, 2]);
/// assert!(resolved.to_toml()?.contains("lr = 0.002"));
///
/// // A key the recipe type does not know is an error that names it.
/// let typo: toml::Table = "[train]\nlearning_rate = 1.0".parse()?;
/// let err = resolve(&defaults, &typo, &Overrides::default()).unwrap_err();
/// assert!(err.to_string().contains("train.learning_rate"));
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
pub fn resolve<R: Serialize + DeserializeOwned>(
    defaults: &R,
    file: &Table,
    overrides: &Overrides,
) -> RecipeResult<Resolved<R>> {
    let mut file = file.clone();
    let quick = match file.remove("quick") {
        None => Table::new(),
        Some(Value::Table(t)) => t,
        Some(_) => return Err(RecipeError::QuickNotATable),
    };
    let variants: Vec<Variant> = match file.remove("variants") {
        None => Vec::new(),
        Some(v) => v.try_into().map_err(RecipeError::InvalidVariants)?,
    };
    let mut tree = to_tree(defaults)?;
    merge(&mut tree, &expand_dotted(&file)?);
    if overrides.quick {
        merge(&mut tree, &expand_dotted(&quick)?);
    }
    if let Some(seeds) = &overrides.seeds {
        let v = seeds.iter().map(|&s| Value::Integer(s as i64)).collect();
        tree.insert("seeds".into(), Value::Array(v));
    }
    if let Some(methods) = &overrides.methods {
        let v = methods.iter().map(|m| Value::String(m.clone())).collect();
        tree.insert("methods".into(), Value::Array(v));
    }
    for (path, value) in &overrides.sets {
        set_path(&mut tree, path, parse_value(value))?;
    }
    let base: R = from_tree(&tree)?;
    let tree = to_tree(&base)?;
    let mut names = std::collections::BTreeSet::new();
    let mut resolved_variants = Vec::with_capacity(variants.len());
    for v in variants {
        if v.name.is_empty() || !names.insert(v.name.clone()) {
            return Err(RecipeError::VariantName(v.name));
        }
        let mut t = tree.clone();
        merge(&mut t, &expand_dotted(&v.set)?);
        let r: R = from_tree(&t)
            .map_err(|e| RecipeError::Variant { name: v.name.clone(), source: Box::new(e) })?;
        resolved_variants.push((v, r));
    }
    Ok(Resolved { base, tree, variants: resolved_variants })
}

/// A task's defaults: the TOML `files` (`(name, text)`, the first complete, each next merged on
/// top of it as in [`merge`]) deserialised into the recipe type. Every field must be given
/// (the recipe types have no defaults of their own) and every key known.
pub fn defaults_from_toml<R: Serialize + DeserializeOwned>(
    files: &[(&str, &str)],
) -> RecipeResult<R> {
    let names: Vec<&str> = files.iter().map(|(n, _)| *n).collect();
    from_tree(&defaults_tree(files)?)
        .map_err(|e| RecipeError::Defaults { files: names.join(" + "), source: Box::new(e) })
}

/// The merged tree of [`defaults_from_toml`], as written in the files.
pub fn defaults_tree(files: &[(&str, &str)]) -> RecipeResult<Table> {
    let mut tree = Table::new();
    for (name, text) in files {
        let t: Table =
            text.parse().map_err(|e| RecipeError::Parse { name: (*name).to_owned(), source: e })?;
        merge(&mut tree, &expand_dotted(&t)?);
    }
    Ok(tree)
}

/// Checks that the defaults `files` deserialise into `R` and state every key that `R`
/// serialises (none is left to a serde default), with values that read back unchanged.
pub fn check_complete_defaults<R: Serialize + DeserializeOwned>(
    files: &[(&str, &str)],
) -> RecipeResult<()> {
    let tree = defaults_tree(files)?;
    let r: R = defaults_from_toml(files)?;
    let back = to_tree(&r)?;
    let missing = unknown_keys(&back, &tree, "");
    let changed = changed_keys(&back, &tree, "");
    if missing.is_empty() && changed.is_empty() && back == tree {
        Ok(())
    } else {
        Err(RecipeError::IncompleteDefaults { missing, changed })
    }
}

/// Largest recipe file read (a real one has a few KB).
pub const MAX_RECIPE_BYTES: u64 = 1 << 20;

/// Reads and parses a recipe file: only a regular file (not a FIFO or a device), at most
/// [`MAX_RECIPE_BYTES`].
pub fn read_recipe(path: &Path) -> RecipeResult<Table> {
    let text = vdd_core::files::read_bounded_string(path, MAX_RECIPE_BYTES)
        .map_err(|e| RecipeError::Io { path: path.to_path_buf(), source: e })?;
    text.parse::<Table>()
        .map_err(|e| RecipeError::Parse { name: path.display().to_string(), source: e })
}
