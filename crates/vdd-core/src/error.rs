//! The core crate's error type and small validation helpers shared by every crate.

use std::sync::Arc;

use faer::MatRef;

/// Errors raised by the core traits and their implementations.
///
/// An implementor of [`crate::Policy`], [`crate::ScoreModel`] or [`crate::Expert`] whose own
/// failure is none of these (a file it reads, a simulator it calls, a network of its own)
/// returns it as [`CoreError::Implementor`], which keeps it as the error's source:
///
/// ```
/// use std::error::Error as _;
/// use vdd_core::CoreError;
///
/// #[derive(Debug, thiserror::Error)]
/// #[error("my teacher's server is down")]
/// struct Down;
///
/// let e = CoreError::implementor(Down);
/// assert!(e.source().unwrap().downcast_ref::<Down>().is_some());
/// ```
///
/// Errors compare equal when they are the same variant with equal fields; two implementor
/// errors are equal when they share the same error value.
#[derive(Debug, Clone)]
pub enum CoreError {
    /// A matrix or slice does not have the shape the operation needs.
    Shape {
        /// Which argument was wrong.
        what: &'static str,
        /// The shape that was expected, e.g. `"32 x 2"`.
        expected: String,
        /// The shape that was given.
        got: String,
    },
    /// A NaN or infinite value was found where finite numbers are required.
    NonFinite {
        /// Which quantity held the value.
        what: &'static str,
    },
    /// A configuration value is out of its valid range.
    Config(String),
    /// The implementation does not support this operation (e.g. a likelihood for a diffusion policy).
    Unsupported(&'static str),
    /// The implementation of a core trait failed in its own way; the error is the source
    /// (shared, so the core error stays `Clone`).
    Implementor(Arc<dyn std::error::Error + Send + Sync + 'static>),
}

impl CoreError {
    /// Wraps an implementor's own error, keeping it (and its sources) as the source.
    pub fn implementor(e: impl Into<Box<dyn std::error::Error + Send + Sync + 'static>>) -> Self {
        Self::Implementor(Arc::from(e.into()))
    }
}

impl std::fmt::Display for CoreError {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Self::Shape { what, expected, got } => {
                write!(f, "shape mismatch for {what}: expected {expected}, got {got}")
            }
            Self::NonFinite { what } => write!(f, "non-finite value in {what}"),
            Self::Config(m) => write!(f, "invalid configuration: {m}"),
            Self::Unsupported(m) => write!(f, "unsupported operation: {m}"),
            Self::Implementor(e) => write!(f, "{e}"),
        }
    }
}

impl std::error::Error for CoreError {
    /// The implementor's own error for [`CoreError::Implementor`] (downcast it to its type).
    fn source(&self) -> Option<&(dyn std::error::Error + 'static)> {
        match self {
            Self::Implementor(e) => Some(&**e),
            _ => None,
        }
    }
}

impl PartialEq for CoreError {
    fn eq(&self, other: &Self) -> bool {
        use CoreError::*;
        match (self, other) {
            (Shape { what, expected, got }, Shape { what: w2, expected: e2, got: g2 }) => {
                what == w2 && expected == e2 && got == g2
            }
            (NonFinite { what }, NonFinite { what: w2 }) => what == w2,
            (Config(a), Config(b)) => a == b,
            (Unsupported(a), Unsupported(b)) => a == b,
            (Implementor(a), Implementor(b)) => Arc::ptr_eq(a, b),
            _ => false,
        }
    }
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
