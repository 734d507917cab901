//! NumPy arrays ↔ `faer` matrices and flat vectors (copies: the GIL is released while Rust
//! computes, so Rust never holds on to memory that Python may change).

use faer::{Mat, MatRef};
use numpy::ndarray::{Array, ArrayView1, ArrayView2, Dimension, IxDyn};
use numpy::{IntoPyArray, PyArray1, PyArray2, PyArrayDyn};
use pyo3::exceptions::{PyMemoryError, PyValueError};
use pyo3::prelude::*;

/// A vector of `len` entries (`what` names the argument in errors).
pub fn vector(a: ArrayView1<'_, f32>, len: usize, what: &str) -> PyResult<Vec<f32>> {
    if a.len() != len {
        return Err(PyValueError::new_err(format!(
            "{what}: expected shape ({len},), got ({},)",
            a.len()
        )));
    }
    Ok(a.iter().copied().collect())
}

/// An `n x cols` matrix (`what` names the argument in errors).
pub fn matrix(a: ArrayView2<'_, f32>, cols: usize, what: &str) -> PyResult<Mat<f32>> {
    let (n, c) = a.dim();
    if c != cols {
        return Err(PyValueError::new_err(format!(
            "{what}: expected shape (n, {cols}), got ({n}, {c})"
        )));
    }
    Ok(Mat::from_fn(n, c, |i, j| a[(i, j)]))
}

/// A matrix as a new NumPy array.
pub fn mat_to_numpy<'py>(py: Python<'py>, m: MatRef<'_, f32>) -> Bound<'py, PyArray2<f32>> {
    Array::from_shape_fn((m.nrows(), m.ncols()), |(i, j)| m[(i, j)]).into_pyarray(py)
}

/// A flat vector as a new 1-D NumPy array.
pub fn vec_to_numpy(py: Python<'_>, v: Vec<f32>) -> Bound<'_, PyArray1<f32>> {
    PyArray1::from_vec(py, v)
}

/// A row-major flat vector as a new NumPy array of `shape`.
pub fn shaped<'py>(
    py: Python<'py>,
    v: Vec<f32>,
    shape: &[usize],
) -> PyResult<Bound<'py, PyArrayDyn<f32>>> {
    let a = Array::from_shape_vec(IxDyn(shape), v)
        .map_err(|e| PyValueError::new_err(format!("internal shape error: {e}")))?;
    debug_assert_eq!(a.raw_dim().size(), a.len());
    Ok(a.into_pyarray(py))
}

/// Largest number of rows of one call (`act_batch`, `log_likelihood`, `components`, a teacher's
/// score): 2^20, far above any number of environments stepped together. A larger batch is a
/// `ValueError` raised before anything is allocated; split it into several calls.
pub const MAX_BATCH_ROWS: usize = 1 << 20;

/// Checks a batch of `rows` rows (`what` names the call) against [`MAX_BATCH_ROWS`]
/// (`ValueError`) and its estimated memory `bytes` against the memory available
/// ([`vdd_core::memory::check_fits`], `MemoryError`), before anything is allocated.
pub fn check_batch(what: &str, rows: usize, bytes: u64) -> PyResult<()> {
    if rows > MAX_BATCH_ROWS {
        return Err(PyValueError::new_err(format!(
            "{what}: {rows} rows, more than the limit of {MAX_BATCH_ROWS} rows per call; \
             split the batch"
        )));
    }
    vdd_core::memory::check_fits(&format!("{what} on {rows} rows"), bytes)
        .map_err(|e| PyMemoryError::new_err(e.to_string()))
}

/// Bytes of `rows` rows of `floats` `f32` values each (saturating).
pub fn row_bytes(rows: usize, floats: usize) -> u64 {
    vdd_core::memory::product(&[rows, floats, 4])
}
