//! The crate's error type.

use std::path::PathBuf;

use crate::MAX_SEEDS;

/// Everything that can go wrong when reading, resolving, serialising or hashing a recipe.
///
/// Messages name the offending key path, file or value; the TOML, JSON and i/o errors they come
/// from stay reachable through [`std::error::Error::source`].
#[derive(Debug, thiserror::Error)]
#[non_exhaustive]
pub enum RecipeError {
    /// A recipe file could not be read.
    #[error("reading {}: {source}", .path.display())]
    Io {
        /// The file.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// A TOML text is not valid TOML.
    #[error("parsing {name}: {source}")]
    Parse {
        /// The file (or other name) the text came from.
        name: String,
        /// The parser's error.
        #[source]
        source: toml::de::Error,
    },
    /// A configuration tree does not deserialise into the recipe type (a value of the wrong
    /// type, a missing key, an unknown enum variant).
    #[error("invalid recipe: {}", .0.to_string().trim())]
    Invalid(#[source] toml::de::Error),
    /// Keys that the recipe type does not know (typos), as dotted paths.
    #[error("unknown recipe key(s): {}", .0.join(", "))]
    UnknownKeys(Vec<String>),
    /// A `--set` path goes through a table that does not exist.
    #[error("unknown recipe key `{0}`")]
    UnknownKey(String),
    /// A `--set` path goes through a value that is not a table.
    #[error("`{0}` is not a table")]
    NotATable(String),
    /// A dotted key with an empty part (`"a..b"`) in an overlay.
    #[error("invalid key `{0}`")]
    InvalidKey(String),
    /// An empty `--set` key path or one with an empty part.
    #[error("invalid key path `{0}`")]
    InvalidKeyPath(String),
    /// A recipe's `quick` entry is not a table.
    #[error("`quick` must be a table")]
    QuickNotATable,
    /// A recipe's `[[variants]]` list is malformed.
    #[error("invalid [[variants]]: {0}")]
    InvalidVariants(#[source] toml::de::Error),
    /// Two variants share a name, or a name is empty.
    #[error("variant names must be non-empty and unique (`{0}`)")]
    VariantName(String),
    /// A variant's configuration does not resolve.
    #[error("variant `{name}`: {source}")]
    Variant {
        /// The variant's name.
        name: String,
        /// Why it does not resolve.
        #[source]
        source: Box<RecipeError>,
    },
    /// A task's defaults do not resolve.
    #[error("{files}: {source}")]
    Defaults {
        /// The defaults' file names, joined by ` + `.
        files: String,
        /// Why they do not resolve.
        #[source]
        source: Box<RecipeError>,
    },
    /// Defaults that leave keys to serde defaults or whose values do not read back unchanged
    /// (see [`check_complete_defaults`](crate::check_complete_defaults)).
    #[error(
        "incomplete defaults: keys missing {missing:?}, values that do not read back unchanged {changed:?}"
    )]
    IncompleteDefaults {
        /// Keys the recipe type serialises but the defaults do not state.
        missing: Vec<String>,
        /// Keys whose value differs after a round trip through the recipe type.
        changed: Vec<String>,
    },
    /// A value does not serialise to a TOML table.
    #[error("a recipe must serialise to a table")]
    NotATableValue,
    /// A value could not be serialised as TOML.
    #[error("{0}")]
    Serialize(#[source] toml::ser::Error),
    /// A value could not be serialised as JSON (for its hash).
    #[error("{0}")]
    Json(#[source] serde_json::Error),
    /// A seed list that does not parse.
    #[error("invalid seed list `{0}` (expected e.g. 0, 0,1,2 or 0..3)")]
    InvalidSeeds(String),
    /// A seed above `i64::MAX` (not a TOML integer).
    #[error("seed {0} is too large (at most {max})", max = i64::MAX)]
    SeedTooLarge(u64),
    /// No recipe of that name ([`find_recipe`](crate::run::find_recipe)).
    #[error("no recipe `{name}` ({} does not exist); available: {available}", .path.display())]
    NoRecipe {
        /// The name asked for.
        name: String,
        /// The file looked for.
        path: PathBuf,
        /// The recipes there are, comma-separated.
        available: String,
    },
    /// The value at a key path does not read as the type asked for
    /// ([`get_path`](crate::get_path)).
    #[error("`{path}`: {source}")]
    AtPath {
        /// The dotted key path.
        path: String,
        /// Why it does not read.
        #[source]
        source: Box<RecipeError>,
    },
    /// A seed list longer than [`MAX_SEEDS`].
    #[error("`{0}` gives more than {MAX_SEEDS} seeds")]
    TooManySeeds(String),
}

/// Result alias of the crate.
pub type RecipeResult<T> = Result<T, RecipeError>;
