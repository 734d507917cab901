//! Stable hashes of configurations (cache keys).

use serde::Serialize;

use crate::{RecipeError, RecipeResult};

/// FNV-1a 64 of `bytes`.
///
/// ```
/// assert_eq!(vdd_recipe::fnv1a(b""), 0xcbf2_9ce4_8422_2325);
/// ```
pub fn fnv1a(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    h
}

/// A stable 16-hex-digit hash of `value`'s JSON form (struct fields in declaration order):
/// [`fnv1a`] of `serde_json::to_string(value)`.
///
/// Caches key their entries by it, so the hash of a configuration must never change: neither
/// the serialisation nor the hash function may be altered.
pub fn config_hash<T: Serialize + ?Sized>(value: &T) -> RecipeResult<String> {
    let json = serde_json::to_string(value).map_err(RecipeError::Json)?;
    Ok(format!("{:016x}", fnv1a(json.as_bytes())))
}
