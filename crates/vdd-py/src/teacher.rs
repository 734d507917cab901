//! `vdd.Teacher` and `vdd.load_teacher`: the diffusion teachers the crates train
//! (`vdd-diffusion`), usable from Python as a `score_fn`.

use std::path::PathBuf;

use numpy::{AllowTypeChange, PyArray2, PyArrayLike1, PyArrayLike2};
use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use vdd::TeacherSpace;
use vdd_core::{NoiseConvention, ScoreModel};
use vdd_diffusion::DiffusionTeacher;

use crate::arrays::{check_batch, mat_to_numpy, matrix, row_bytes, vector};
use crate::errors::run;

/// A learned diffusion teacher (DDPM or BESO) saved by the crates.
#[pyclass(module = "vdd", name = "Teacher")]
pub struct PyTeacher {
    pub(crate) inner: DiffusionTeacher,
}

impl PyTeacher {
    /// The space the teacher's score model works in (its own normalisers).
    pub fn space(&self) -> TeacherSpace {
        let (s, a) = self.inner.normalizers();
        TeacherSpace::normalized(s.clone(), a.clone())
    }
}

/// Loads a teacher saved by `vdd-diffusion` (`cargo xtask experiment`'s teacher cache).
#[pyfunction]
#[pyo3(signature = (path, seed = 0))]
pub fn load_teacher(py: Python<'_>, path: PathBuf, seed: u64) -> PyResult<PyTeacher> {
    let inner = run(py, || DiffusionTeacher::load(&path, seed))?;
    Ok(PyTeacher { inner })
}

#[pymethods]
impl PyTeacher {
    /// The score `∇_a log p_level(a | s)` `(n, action_dim)` of raw actions `(n, action_dim)`
    /// at raw states `(n, state_dim)` and noise levels `(n,)` in the teacher's own space and
    /// convention (`noise_convention`: VE `sigma` for BESO, VP `time` for DDPM).
    fn __call__<'py>(
        &mut self,
        py: Python<'py>,
        actions: PyArrayLike2<'py, f32, AllowTypeChange>,
        states: PyArrayLike2<'py, f32, AllowTypeChange>,
        levels: PyArrayLike1<'py, f32, AllowTypeChange>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let (ds, da) = (self.inner.state_dim(), self.inner.action_dim());
        // Inputs, output and the teacher's working copies: a few rows' worth of each, far
        // below its network's activations, which the row limit bounds.
        let rows = actions.as_array().nrows();
        check_batch("a teacher's score", rows, row_bytes(rows, (ds + 2 * da).saturating_mul(4)))?;
        let mut actions = matrix(actions.as_array(), da, "actions")?;
        let mut states = matrix(states.as_array(), ds, "states")?;
        let n = actions.nrows();
        if states.nrows() != n {
            return Err(PyValueError::new_err(format!(
                "actions has {n} rows but states has {}",
                states.nrows()
            )));
        }
        let levels = vector(levels.as_array(), n, "levels")?;
        let (s_map, a_map) = self.inner.normalizers();
        let (s_map, a_map) = (s_map.clone(), a_map.clone());
        for i in 0..n {
            for j in 0..da {
                actions[(i, j)] = (actions[(i, j)] - a_map.offset[j]) / a_map.scale[j];
            }
            for j in 0..ds {
                states[(i, j)] = (states[(i, j)] - s_map.offset[j]) / s_map.scale[j];
            }
        }
        let mut out = faer::Mat::<f32>::zeros(n, da);
        let inner = &mut self.inner;
        run(py, || inner.score(actions.as_ref(), states.as_ref(), &levels, out.as_mut()))?;
        // The chain rule of the normaliser: ∇_raw = ∇_normalised / scale.
        for i in 0..n {
            for j in 0..da {
                out[(i, j)] /= a_map.scale[j];
            }
        }
        Ok(mat_to_numpy(py, out.as_ref()))
    }

    /// Dimension of one action.
    #[getter]
    fn action_dim(&self) -> usize {
        self.inner.action_dim()
    }

    /// Dimension of one state.
    #[getter]
    fn state_dim(&self) -> usize {
        self.inner.state_dim()
    }

    /// `"ddpm"` or `"beso"`.
    #[getter]
    fn kind(&self) -> &'static str {
        match self.inner.kind() {
            vdd_diffusion::TeacherKind::Ddpm => "ddpm",
            vdd_diffusion::TeacherKind::Beso => "beso",
        }
    }

    /// `"sigma"` (VE noise level) or `"time"` (VP diffusion time).
    #[getter]
    fn noise_convention(&self) -> &'static str {
        match self.inner.noise_convention() {
            NoiseConvention::Sigma => "sigma",
            NoiseConvention::Time => "time",
        }
    }

    fn __repr__(&self) -> String {
        format!(
            "vdd.Teacher(kind='{}', state_dim={}, action_dim={})",
            self.kind(),
            self.state_dim(),
            self.action_dim()
        )
    }
}
