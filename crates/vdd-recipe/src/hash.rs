//! Stable hashes of configurations (cache keys).

use serde::Serialize;
use vdd_core::hash::Fnv1a;
pub use vdd_core::hash::fnv1a;

use crate::{RecipeError, RecipeResult};

/// A stable 16-hex-digit hash of `value`'s JSON form (struct fields in declaration order):
/// [`fnv1a`] (`vdd_core::hash`) of `serde_json::to_string(value)`.
///
/// Caches key their entries by it, so the hash of a configuration must never change: neither
/// the serialisation nor the hash function may be altered.
pub fn config_hash<T: Serialize + ?Sized>(value: &T) -> RecipeResult<String> {
    let json = serde_json::to_string(value).map_err(RecipeError::Json)?;
    Ok(Fnv1a::new().write(json.as_bytes()).hex())
}
