//! # vdd-py
//!
//! The Python package `vdd`, built from the workspace with [pyo3] and `maturin`: load, run and
//! export distilled policies ([`policy::PyPolicy`], `vdd.Policy`), distil a teacher that lives
//! in Python (`vdd.distill`, whose `score_fn` is any Python callable), load the teachers the
//! crates train (`vdd.load_teacher`) and import LeRobot diffusion policies
//! (`vdd.import_lerobot`), which `vdd.distill` distils in Rust through the wiring of the Rust
//! experiment path (the `imported` module). NumPy `float32` arrays go in and out; the GIL is released
//! while Rust computes, and reacquired only to call a Python `score_fn`.
//!
//! The Python API and its documentation are in `vdd.pyi` beside this crate's `Cargo.toml`;
//! the tests are Python's (`tests/`, run by pytest against the built wheel, see `.ci/run`).
#![warn(missing_docs)]

pub mod arrays;
pub mod distill;
pub mod errors;
mod imported;
pub mod policy;
mod settings;
pub mod teacher;

use pyo3::prelude::*;

/// The Python module `vdd`.
#[pymodule]
#[pyo3(name = "vdd")]
fn vdd_module(m: &Bound<'_, PyModule>) -> PyResult<()> {
    m.add("__version__", env!("CARGO_PKG_VERSION"))?;
    m.add("VddError", m.py().get_type::<errors::VddError>())?;
    m.add_class::<policy::PyPolicy>()?;
    m.add_class::<teacher::PyTeacher>()?;
    m.add_function(wrap_pyfunction!(distill::distill, m)?)?;
    m.add_function(wrap_pyfunction!(teacher::load_teacher, m)?)?;
    m.add_function(wrap_pyfunction!(teacher::import_lerobot, m)?)?;
    Ok(())
}
