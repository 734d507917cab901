//! FNV-1a 64, the one stable hash of the workspace: the purposes of [`crate::Seeds`]' streams,
//! the keys of the teacher and student caches and the recipes' configuration hashes all use it.
//! Seeds, cache files and pinned hashes depend on its values, so it must never change.
//!
//! ```
//! use vdd_core::hash::{Fnv1a, fnv1a};
//! assert_eq!(fnv1a(b""), 0xcbf2_9ce4_8422_2325);
//! // Fed in pieces, it hashes the concatenation.
//! let mut h = Fnv1a::new();
//! h.write(b"v").write(b"dd");
//! assert_eq!(h.finish(), fnv1a(b"vdd"));
//! assert_eq!(h.hex(), "691520194edfde09");
//! ```

/// An FNV-1a 64 hash fed incrementally ([`Fnv1a::write`]); [`fnv1a`] hashes one slice.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct Fnv1a(u64);

impl Fnv1a {
    const OFFSET_BASIS: u64 = 0xcbf2_9ce4_8422_2325;
    const PRIME: u64 = 0x0100_0000_01b3;

    /// The hash of no bytes.
    pub const fn new() -> Self {
        Self(Self::OFFSET_BASIS)
    }

    /// Feeds `bytes`.
    pub fn write(&mut self, bytes: &[u8]) -> &mut Self {
        for &b in bytes {
            self.0 ^= u64::from(b);
            self.0 = self.0.wrapping_mul(Self::PRIME);
        }
        self
    }

    /// The hash of everything fed so far.
    pub fn finish(&self) -> u64 {
        self.0
    }

    /// [`Fnv1a::finish`] as 16 lower-case hex digits (the form of cache keys).
    pub fn hex(&self) -> String {
        format!("{:016x}", self.0)
    }
}

impl Default for Fnv1a {
    fn default() -> Self {
        Self::new()
    }
}

/// FNV-1a 64 of `bytes`.
pub fn fnv1a(bytes: &[u8]) -> u64 {
    Fnv1a::new().write(bytes).finish()
}

/// A 16-hex-digit FNV-1a hash of the shapes and bits of `states` and `actions` (the data
/// part of the teacher and student caches' keys).
///
/// ```
/// use faer::Mat;
/// let (s, a) = (Mat::<f32>::zeros(2, 1), Mat::<f32>::zeros(2, 1));
/// assert_eq!(vdd_core::hash::data_hash(s.as_ref(), a.as_ref()).len(), 16);
/// ```
pub fn data_hash(states: faer::MatRef<'_, f32>, actions: faer::MatRef<'_, f32>) -> String {
    let mut h = Fnv1a::new();
    for m in [states, actions] {
        h.write(&(m.nrows() as u64).to_le_bytes()).write(&(m.ncols() as u64).to_le_bytes());
        for j in 0..m.ncols() {
            for i in 0..m.nrows() {
                h.write(&m[(i, j)].to_bits().to_le_bytes());
            }
        }
    }
    h.hex()
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn known_values_of_fnv1a_64() {
        // Reference values of FNV-1a 64 (Fowler, Noll, Vo).
        assert_eq!(fnv1a(b"a"), 0xaf63_dc4c_8601_ec8c);
        assert_eq!(fnv1a(b"foobar"), 0x8594_4171_f739_67e8);
        assert_eq!(Fnv1a::new().write(b"foo").write(b"bar").hex(), "85944171f73967e8");
    }
}
