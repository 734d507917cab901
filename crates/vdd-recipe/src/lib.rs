//! Layered TOML configurations ("recipes"): a typed configuration resolved from defaults, a
//! recipe file, a quick profile, command-line overrides and named variants, written back as
//! TOML and hashed stably for cache keys.
//!
//! The crate knows no task, model or trainer: a recipe type is any `Serialize +
//! DeserializeOwned` struct, usually starting with the common keys of [`Header`] (name,
//! description, task, seeds, methods). It never prints.
//!
//! # Resolution
//!
//! A recipe file only states what differs from the defaults (typically TOML files embedded in
//! the binary and read with [`defaults_from_toml`]; they state every key of the recipe type,
//! which has no defaults of its own — [`check_complete_defaults`] tests that). [`resolve`]
//! builds one TOML tree and deserialises it once:
//!
//! 1. the defaults (deserialised, which validates them, and serialised again);
//! 2. the recipe file merged on top (tables merge key by key; see [`merge`]), except its
//!    `[quick]` table and `[[variants]]` list;
//! 3. with [`Overrides::quick`], the recipe's `[quick]` table merged on top;
//! 4. the command-line overrides in order: [`Overrides::seeds`] (the `seeds` key),
//!    [`Overrides::methods`] (the `methods` key) and every `--set key.path=value` of
//!    [`Overrides::sets`] (the value is parsed as TOML, and taken as a string when it does not
//!    parse: `--set teachers.beso.config.sampler=heun`; see [`parse_value`]);
//! 5. each `[[variants]]` entry (`name`, optional `description`, a `set` table of
//!    `"key.path" = value`) merged on top of that, giving one configuration per [`Variant`].
//!
//! Keys may be dotted paths anywhere an overlay is given (`"vdd.beso.iterations" = 100` in
//! `[quick]` or in a variant's `set`). A key the resolved configuration does not know (a typo)
//! is an error that names it, as is a value of the wrong type. Tables whose `kind` differs, and
//! one-key tables naming another variant of an externally tagged enum (`{ cosine = { ... } }`
//! over `{ linear_decay = { ... } }`), replace the default instead of merging into it.
//!
//! Floats that came from `f32` fields are written back in their shortest `f32` form (`0.1`, not
//! `0.10000000149011612`; see [`to_tree`]), so [`Resolved::to_toml`] reads like a hand-written
//! recipe and resolves to the same configuration again.
//!
//! # Runs
//!
//! [`run`] names run directories after their seeds and overrides and records the revision they
//! ran at.
//!
//! # Hashes
//!
//! [`config_hash`] is FNV-1a 64 ([`fnv1a`]) of a value's JSON form: a stable key for caches of
//! anything a configuration determines.
//!
//! ```
//! use serde::{Deserialize, Serialize};
//!
//! #[derive(Serialize, Deserialize)]
//! struct Recipe {
//!     seeds: Vec<u64>,
//!     lr: f32,
//! }
//!
//! let defaults: Recipe = vdd_recipe::defaults_from_toml(&[("defaults", "seeds = [0]\nlr = 0.1")])?;
//! let overrides = vdd_recipe::Overrides {
//!     seeds: Some(vdd_recipe::parse_seeds("0..3")?),
//!     ..Default::default()
//! };
//! let resolved = vdd_recipe::resolve(&defaults, &toml::Table::new(), &overrides)?;
//! assert_eq!(resolved.base.seeds, [0, 1, 2]);
//! assert_eq!(vdd_recipe::config_hash(&resolved.base)?.len(), 16);
//! # Ok::<(), vdd_recipe::RecipeError>(())
//! ```

#![warn(missing_docs)]

mod error;
mod hash;
mod header;
mod resolve;
pub mod run;
mod seeds;
mod tree;

pub use error::{RecipeError, RecipeResult};
pub use hash::{config_hash, fnv1a};
pub use header::Header;
pub use resolve::{
    MAX_RECIPE_BYTES, Overrides, Resolved, Variant, check_complete_defaults, defaults_from_toml,
    defaults_tree, read_recipe, resolve,
};
pub use seeds::{MAX_SEEDS, parse_seeds};
pub use tree::{
    expand_dotted, from_tree, get_path, merge, parse_value, set_path, to_tree, unknown_keys,
};

#[cfg(test)]
mod tests;
