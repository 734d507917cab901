//! The core crate's error type and small validation helpers shared by every crate.

use faer::MatRef;

/// Errors raised by the core traits and their implementations.
#[derive(Debug, Clone, PartialEq, thiserror::Error)]
pub enum CoreError {
    /// A matrix or slice does not have the shape the operation needs.
    #[error("shape mismatch for {what}: expected {expected}, got {got}")]
    Shape {
        /// Which argument was wrong.
        what: &'static str,
        /// The shape that was expected, e.g. `"32 x 2"`.
        expected: String,
        /// The shape that was given.
        got: String,
    },
    /// A NaN or infinite value was found where finite numbers are required.
    #[error("non-finite value in {what}")]
    NonFinite {
        /// Which quantity held the value.
        what: &'static str,
    },
    /// A configuration value is out of its valid range.
    #[error("invalid configuration: {0}")]
    Config(String),
    /// The implementation does not support this operation (e.g. a likelihood for a diffusion policy).
    #[error("unsupported operation: {0}")]
    Unsupported(&'static str),
}

/// Result alias for the core crate.
pub type Result<T, E = CoreError> = std::result::Result<T, E>;

/// Checks that `m` is `rows x cols`.
///
/// ```
/// use vdd_core::{check_shape, CoreError};
/// let m = faer::Mat::<f32>::zeros(3, 2);
/// assert!(check_shape("states", m.as_ref(), 3, 2).is_ok());
/// assert!(matches!(check_shape("states", m.as_ref(), 3, 4), Err(CoreError::Shape { .. })));
/// ```
pub fn check_shape(what: &'static str, m: MatRef<'_, f32>, rows: usize, cols: usize) -> Result<()> {
    if m.nrows() != rows || m.ncols() != cols {
        return Err(CoreError::Shape {
            what,
            expected: format!("{rows} x {cols}"),
            got: format!("{} x {}", m.nrows(), m.ncols()),
        });
    }
    Ok(())
}

/// Checks that a slice has length `len`.
pub fn check_len(what: &'static str, len_got: usize, len: usize) -> Result<()> {
    if len_got != len {
        return Err(CoreError::Shape {
            what,
            expected: format!("length {len}"),
            got: format!("length {len_got}"),
        });
    }
    Ok(())
}

/// Checks that every entry of `m` is finite.
pub fn check_finite(what: &'static str, m: MatRef<'_, f32>) -> Result<()> {
    for j in 0..m.ncols() {
        for i in 0..m.nrows() {
            if !m[(i, j)].is_finite() {
                return Err(CoreError::NonFinite { what });
            }
        }
    }
    Ok(())
}

/// Checks that every entry of a slice is finite.
pub fn check_finite_slice(what: &'static str, xs: &[f32]) -> Result<()> {
    if xs.iter().all(|x| x.is_finite()) { Ok(()) } else { Err(CoreError::NonFinite { what }) }
}
