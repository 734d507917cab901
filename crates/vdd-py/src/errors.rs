//! Rust errors as Python exceptions.
//!
//! Invalid arguments (shapes, non-finite values, configuration values) raise `ValueError`;
//! everything else raises `vdd.VddError`, with the whole source chain in its message. A Python
//! exception raised inside a `score_fn` travels through the trainer as the source of a
//! [`vdd_core::CoreError::Implementor`] and is raised again as itself, traceback included.

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use vdd_core::CoreError;

pyo3::create_exception!(
    vdd,
    VddError,
    pyo3::exceptions::PyException,
    "A failure of the Rust side of `vdd` (file I/O, a malformed model, a failed training step)."
);

/// The error and its sources, joined by `": "`.
pub fn chain_message(e: &(dyn std::error::Error + 'static)) -> String {
    let mut msg = e.to_string();
    let mut source = e.source();
    while let Some(s) = source {
        let text = s.to_string();
        if !msg.ends_with(&text) {
            msg.push_str(": ");
            msg.push_str(&text);
        }
        source = s.source();
    }
    msg
}

/// The Python exception for a Rust error: the original Python exception if one is in the
/// source chain (raised inside a `score_fn`), `ValueError` for invalid arguments, otherwise
/// `vdd.VddError`.
pub fn to_py(py: Python<'_>, e: &(dyn std::error::Error + 'static)) -> PyErr {
    let mut cur: Option<&(dyn std::error::Error + 'static)> = Some(e);
    let mut invalid = false;
    while let Some(err) = cur {
        if let Some(py_err) = err.downcast_ref::<PyErr>() {
            return py_err.clone_ref(py);
        }
        if let Some(core) = err.downcast_ref::<CoreError>() {
            invalid |= matches!(
                core,
                CoreError::Shape { .. } | CoreError::NonFinite { .. } | CoreError::Config(_)
            );
        }
        cur = err.source();
    }
    if invalid {
        PyValueError::new_err(chain_message(e))
    } else {
        VddError::new_err(chain_message(e))
    }
}

/// `Result<T, E>` to `PyResult<T>` through [`to_py`].
pub trait IntoPy<T> {
    /// Converts the error, if any.
    fn py_err(self, py: Python<'_>) -> PyResult<T>;
}

impl<T, E: std::error::Error + 'static> IntoPy<T> for Result<T, E> {
    fn py_err(self, py: Python<'_>) -> PyResult<T> {
        self.map_err(|e| to_py(py, &e))
    }
}
