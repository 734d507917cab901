//! Rust errors as Python exceptions.
//!
//! Invalid arguments (shapes, non-finite values, configuration values) raise `ValueError`;
//! everything else raises `vdd.VddError`, with the whole source chain in its message. A Python
//! exception raised inside a `score_fn` travels through the trainer as the source of a
//! [`vdd_core::CoreError::Implementor`] and is raised again as itself, traceback included.
//!
//! No panic crosses into Python: batch sizes are checked before anything is allocated
//! ([`crate::arrays::check_batch`]: `ValueError` over the documented row limit, `MemoryError`
//! over the memory available), and every call into the crates runs through [`run`], which turns
//! a panic, as a last resort, into `RuntimeError` instead of pyo3's `PanicException`.

use pyo3::exceptions::{PyRuntimeError, PyValueError};
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

/// Runs `f` with the GIL released ([`Python::detach`]) and converts its error ([`to_py`]); a
/// panic inside it becomes a Python `RuntimeError` naming it, never a `PanicException`.
pub fn run<T, E, F>(py: Python<'_>, f: F) -> PyResult<T>
where
    T: Send,
    E: std::error::Error + Send + 'static,
    F: FnOnce() -> Result<T, E> + Send,
{
    let caught = py.detach(|| std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)));
    match caught {
        Ok(result) => result.py_err(py),
        Err(payload) => Err(panic_error(payload.as_ref())),
    }
}

/// A caught panic as `RuntimeError`, with its message.
pub fn panic_error(payload: &(dyn std::any::Any + Send)) -> PyErr {
    let msg = payload
        .downcast_ref::<&str>()
        .map(|s| (*s).to_owned())
        .or_else(|| payload.downcast_ref::<String>().cloned())
        .unwrap_or_else(|| "(no message)".to_owned());
    PyRuntimeError::new_err(format!(
        "internal error in vdd (a Rust panic, please report it): {msg}"
    ))
}

/// Runs a training closure with the GIL released; a panic becomes `RuntimeError`
/// ([`crate::errors::panic_error`]), the training error is kept for [`to_py`].
pub fn run_train<T: Send, E: Send>(
    py: Python<'_>,
    f: impl FnOnce() -> Result<T, E> + Send,
) -> PyResult<Result<T, E>> {
    py.detach(|| std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)))
        .map_err(|payload| panic_error(payload.as_ref()))
}
