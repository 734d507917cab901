//! `vdd.distill`: the Rust VDD trainer driven from Python, with a teacher that is any Python
//! callable (or a `vdd.Teacher`).

use faer::{Mat, MatMut, MatRef};
use numpy::{AllowTypeChange, PyArrayLike2};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyTuple};
use serde_json::{Map, Value};
use vdd::{Affine, AutoOptions, AutoPlan, DistillData, Moe, ScoreModel, Vdd};
use vdd_core::{CoreError, check_score_args};

use crate::arrays::{mat_to_numpy, matrix, row_bytes};
use crate::errors::{IntoPy as _, run_train, to_py};
use crate::policy::PyPolicy;
use crate::settings::{Defaults, Extra, Request, RunError, apply_settings};
use crate::teacher::{PyTeacher, TeacherModel};

/// A teacher whose score is a Python callable `score_fn(actions, states, sigma)`: called with
/// the GIL held, the rest of training runs without it. A Python exception raised by the
/// callable (or a wrong result) becomes [`CoreError::Implementor`] with the `PyErr` as its
/// source, which `distill` raises again.
pub struct PyScore {
    score_fn: Py<PyAny>,
    sample_fn: Option<Py<PyAny>>,
    state_dim: usize,
    action_dim: usize,
    /// `noise_range=(min, max)`, if given: VE levels trusted on `[min, max]`.
    process: Option<vdd_core::VeProcess>,
}

impl PyScore {
    fn call(
        &self,
        py: Python<'_>,
        a: MatRef<'_, f32>,
        s: MatRef<'_, f32>,
        sigma: &[f32],
        mut out: MatMut<'_, f32>,
    ) -> PyResult<()> {
        py.check_signals()?;
        let args =
            (mat_to_numpy(py, a), mat_to_numpy(py, s), numpy::PyArray1::from_slice(py, sigma));
        let result = self.score_fn.bind(py).call1(args)?;
        let score: PyArrayLike2<'_, f32, AllowTypeChange> = result.extract().map_err(|e| {
            PyTypeError::new_err(format!(
                "score_fn must return a float array of shape ({}, {}): {e}",
                a.nrows(),
                self.action_dim
            ))
        })?;
        let score = score.as_array();
        let (rows, cols) = score.dim();
        if (rows, cols) != (a.nrows(), self.action_dim) {
            return Err(PyValueError::new_err(format!(
                "score_fn returned shape ({rows}, {cols}), expected ({}, {})",
                a.nrows(),
                self.action_dim
            )));
        }
        for i in 0..a.nrows() {
            for j in 0..self.action_dim {
                out[(i, j)] = score[(i, j)];
            }
        }
        Ok(())
    }

    /// Calls `sample_fn(states)` and checks its result: `(n, action_dim)`, finite.
    fn sample(
        &self,
        py: Python<'_>,
        sample_fn: &Py<PyAny>,
        s: MatRef<'_, f32>,
        mut out: MatMut<'_, f32>,
    ) -> PyResult<()> {
        py.check_signals()?;
        let n = s.nrows();
        let result = sample_fn.bind(py).call1((mat_to_numpy(py, s),))?;
        let actions: PyArrayLike2<'_, f32, AllowTypeChange> = result.extract().map_err(|e| {
            PyTypeError::new_err(format!(
                "sample_fn must return a float array of shape ({n}, {}): {e}",
                self.action_dim
            ))
        })?;
        let actions = actions.as_array();
        let (rows, cols) = actions.dim();
        if (rows, cols) != (n, self.action_dim) {
            return Err(PyValueError::new_err(format!(
                "sample_fn returned shape ({rows}, {cols}), expected ({n}, {})",
                self.action_dim
            )));
        }
        for i in 0..n {
            for j in 0..self.action_dim {
                let x = actions[(i, j)];
                if !x.is_finite() {
                    return Err(PyValueError::new_err(format!(
                        "sample_fn returned a non-finite action ({x} at row {i}, column {j})"
                    )));
                }
                out[(i, j)] = x;
            }
        }
        Ok(())
    }
}

impl ScoreModel for PyScore {
    fn action_dim(&self) -> usize {
        self.action_dim
    }
    /// VE levels; trusted on `noise_range` when it was given (then `Vdd::auto` anneals down to
    /// its `min`, and a noise setting outside it is refused).
    fn noise_process(&self) -> Option<&dyn vdd_core::NoiseProcess> {
        self.process.as_ref().map(|p| p as &dyn vdd_core::NoiseProcess)
    }
    fn state_dim(&self) -> usize {
        self.state_dim
    }
    fn score(
        &mut self,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        noise_levels: &[f32],
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        check_score_args(self, actions, states, noise_levels, out.as_ref())?;
        Python::attach(|py| self.call(py, actions, states, noise_levels, out))
            .map_err(CoreError::implementor)
    }
    /// The Python teacher's `sample_fn(states)`, if it was given (unsupported otherwise).
    fn sample_actions(
        &mut self,
        states: MatRef<'_, f32>,
        _rng: &mut dyn vdd::rand::RngCore,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let Some(sample_fn) = &self.sample_fn else {
            return Err(CoreError::Unsupported("sampling actions from a score_fn (no sample_fn)"));
        };
        vdd_core::check_shape("states", states, states.nrows(), self.state_dim)?;
        vdd_core::check_shape("sampled actions", out.as_ref(), states.nrows(), self.action_dim)?;
        Python::attach(|py| self.sample(py, sample_fn, states, out)).map_err(CoreError::implementor)
    }
}

/// A Python value as JSON (what the configurations deserialise from).
fn to_json(v: &Bound<'_, PyAny>, key: &str) -> PyResult<Value> {
    if v.is_none() {
        Ok(Value::Null)
    } else if let Ok(b) = v.cast::<pyo3::types::PyBool>() {
        Ok(Value::Bool(b.is_true()))
    } else if let Ok(i) = v.extract::<i64>() {
        Ok(Value::from(i))
    } else if let Ok(f) = v.extract::<f64>() {
        serde_json::Number::from_f64(f).map(Value::Number).ok_or_else(|| {
            PyValueError::new_err(format!("setting `{key}`: {f} is not a finite number"))
        })
    } else if let Ok(s) = v.extract::<String>() {
        Ok(Value::String(s))
    } else if let Ok(d) = v.cast::<PyDict>() {
        let mut m = Map::new();
        for (k, x) in d.iter() {
            let k: String = k.extract()?;
            let inner = to_json(&x, &format!("{key}.{k}"))?;
            m.insert(k, inner);
        }
        Ok(Value::Object(m))
    } else if v.cast::<PyList>().is_ok() || v.cast::<PyTuple>().is_ok() {
        let items: Vec<Bound<'_, PyAny>> = v.extract()?;
        items.iter().map(|x| to_json(x, key)).collect::<PyResult<_>>().map(Value::Array)
    } else {
        Err(PyTypeError::new_err(format!(
            "setting `{key}`: cannot use a value of type {}",
            v.get_type().name()?
        )))
    }
}

/// Per-column mean and standard deviation of `m` as a normaliser (a constant column gets
/// scale 1).
fn column_normalizer(m: MatRef<'_, f32>) -> Result<Affine, CoreError> {
    let n = m.nrows() as f64;
    let (mut offset, mut scale) = (Vec::new(), Vec::new());
    for j in 0..m.ncols() {
        let mean = (0..m.nrows()).map(|i| f64::from(m[(i, j)])).sum::<f64>() / n;
        let var = (0..m.nrows()).map(|i| (f64::from(m[(i, j)]) - mean).powi(2)).sum::<f64>() / n;
        offset.push(mean as f32);
        scale.push(if var.sqrt() > 1e-6 { var.sqrt() as f32 } else { 1.0 });
    }
    Affine::new(offset, scale)
}

fn train<S: ScoreModel>(
    request: &Request,
    extra: &Extra,
    mut teacher: S,
    data: DistillData,
    actions: Option<&Mat<f32>>,
) -> Result<Moe, RunError> {
    let mut vdd = match request.defaults {
        Defaults::Toy => {
            let (config, moe) = request.toy_configs().map_err(RunError::Setting)?;
            let mut student = Moe::from_config(moe, config.seed)?;
            let obs = column_normalizer(data.states())?;
            let act = actions.map(|a| column_normalizer(a.as_ref())).transpose()?;
            student.set_normalizers(Some(obs), act)?;
            Vdd::new(config, teacher, student, data)?
        }
        Defaults::Auto => {
            let mut options = AutoOptions {
                iterations: request.iterations,
                ..AutoOptions::new(request.experts, request.seed)
            };
            if let Some(n) = extra.teacher_samples {
                options.samples = n;
            }
            let mut plan = AutoPlan::inspect(&mut teacher, &data, &options)?;
            apply_settings(&mut plan.vdd, &mut plan.student, &request.settings)
                .map_err(RunError::Setting)?;
            Vdd::from_plan(&plan, teacher, data)?
        }
    };
    vdd.train(|_| {})?;
    Ok(vdd.into_student())
}

/// Distils a teacher into a mixture of experts with the Rust VDD trainer; returns the
/// student as a `vdd.Policy` (acting on raw states).
#[pyfunction]
#[pyo3(signature = (score_fn, states, *, action_dim = None, experts = 8, iterations = None, seed = 0, actions = None, sample_fn = None, **settings))]
#[allow(clippy::too_many_arguments)]
pub fn distill(
    py: Python<'_>,
    score_fn: Bound<'_, PyAny>,
    states: PyArrayLike2<'_, f32, AllowTypeChange>,
    action_dim: Option<usize>,
    experts: usize,
    iterations: Option<usize>,
    seed: u64,
    actions: Option<PyArrayLike2<'_, f32, AllowTypeChange>>,
    sample_fn: Option<Bound<'_, PyAny>>,
    settings: Option<Bound<'_, PyDict>>,
) -> PyResult<PyPolicy> {
    let teacher = score_fn.cast::<PyTeacher>().ok().map(|t| t.borrow().inner.clone());
    let state_dim = states.as_array().ncols();
    let action_dim = match (&teacher, action_dim) {
        (Some(t), given) => {
            let (ts, ta) = teacher_dims(t);
            if given.is_some_and(|a| a != ta) {
                return Err(PyValueError::new_err(format!(
                    "action_dim={} but the teacher's actions are {ta} wide",
                    given.unwrap_or_default()
                )));
            }
            if state_dim != ts {
                return Err(PyValueError::new_err(wrong_state_width(t, state_dim)));
            }
            ta
        }
        (None, Some(a)) => a,
        (None, None) => {
            return Err(PyTypeError::new_err(
                "distill: action_dim= is required for a Python score_fn",
            ));
        }
    };
    // The dataset is copied once or twice (states, their normalised copy): bounded by memory,
    // not by the batch limit (a dataset may hold many more states than one batch).
    let rows = states.as_array().nrows();
    let bytes = row_bytes(rows, state_dim.saturating_add(action_dim).saturating_mul(3));
    vdd_core::memory::check_fits(&format!("the {rows} states of `distill`"), bytes)
        .map_err(|e| pyo3::exceptions::PyMemoryError::new_err(e.to_string()))?;
    let states = matrix(states.as_array(), state_dim, "states")?;
    let actions = actions.map(|a| matrix(a.as_array(), action_dim, "actions")).transpose()?;
    if experts == 0 {
        return Err(PyValueError::new_err("experts must be at least 1"));
    }
    if iterations == Some(0) {
        return Err(PyValueError::new_err("iterations must be at least 1"));
    }
    let mut defaults = Defaults::Auto;
    let mut pairs = Vec::new();
    let mut extra = Extra::default();
    if let Some(s) = &settings {
        for (k, v) in s.iter() {
            let k: String = k.extract()?;
            if k == "defaults" {
                defaults = match v.extract::<String>().as_deref() {
                    Ok("auto") => Defaults::Auto,
                    Ok("toy") => Defaults::Toy,
                    _ => {
                        return Err(PyValueError::new_err(format!(
                            "setting `defaults`: expected 'auto' or 'toy', got {}",
                            v.repr()?
                        )));
                    }
                };
                continue;
            }
            if extra.take(&k, &v)? {
                continue;
            }
            let value = to_json(&v, &k)?;
            pairs.push((k, value));
        }
    }
    let request =
        Request { defaults, experts, iterations, seed, state_dim, action_dim, settings: pairs };
    // Settings are checked before the teacher is inspected (which may take many calls).
    request.toy_configs().map_err(PyValueError::new_err)?;
    let trained = match teacher {
        Some(teacher) => {
            if sample_fn.is_some() {
                return Err(PyValueError::new_err(
                    "sample_fn is for a Python score_fn; a vdd.Teacher samples itself",
                ));
            }
            extra.refuse_score_fn_only()?;
            match teacher {
                TeacherModel::Diffusion(inner) => {
                    extra.refuse_imported_only()?;
                    let (s, a) = inner.normalizers();
                    let space = vdd::TeacherSpace::normalized(s.clone(), a.clone());
                    let data = DistillData::new(states, actions.clone()).py_err(py)?;
                    let data = data.with_teacher_space(space);
                    run_train(py, || train(&request, &extra, *inner, data, actions.as_ref()))
                }
                TeacherModel::Unet(inner) => {
                    if let Some(m) = &inner.spec().obs_map {
                        return Err(PyValueError::new_err(format!(
                            "the teacher was imported with the observation map `{m}`, which a \
                             distilled student cannot carry yet (it would act on mapped \
                             observations); import it without obs_map, its observation being \
                             the features in the policy's order"
                        )));
                    }
                    if request.defaults == Defaults::Toy {
                        return Err(PyValueError::new_err(
                            "defaults='toy' does not apply to an imported teacher",
                        ));
                    }
                    run_train(py, || {
                        crate::imported::train(&request, &extra, *inner, states, actions)
                    })
                }
            }
        }
        None => {
            extra.refuse_imported_only()?;
            if !score_fn.is_callable() {
                return Err(PyTypeError::new_err("score_fn must be callable"));
            }
            if sample_fn.as_ref().is_some_and(|f| !f.is_callable()) {
                return Err(PyTypeError::new_err("sample_fn must be callable (or None)"));
            }
            let data = DistillData::new(states, actions.clone()).py_err(py)?;
            let teacher = PyScore {
                score_fn: score_fn.unbind(),
                sample_fn: sample_fn.map(Bound::unbind),
                state_dim,
                action_dim,
                process: extra.noise_range,
            };
            run_train(py, || train(&request, &extra, teacher, data, actions.as_ref()))
        }
    };
    match trained? {
        Ok(student) => Ok(PyPolicy::new(student.into_policy().py_err(py)?)),
        Err(RunError::Vdd(e)) => Err(to_py(py, &e)),
        Err(RunError::Setting(msg)) => Err(PyValueError::new_err(msg)),
    }
}

/// The teacher's (state, action) widths.
fn teacher_dims(t: &TeacherModel) -> (usize, usize) {
    match t {
        TeacherModel::Diffusion(t) => (t.state_dim(), t.action_dim()),
        TeacherModel::Unet(t) => (t.state_dim(), t.action_dim()),
    }
}

/// The error for states of the wrong width, saying what the teacher's states are.
fn wrong_state_width(t: &TeacherModel, got: usize) -> String {
    match t {
        TeacherModel::Diffusion(t) => {
            format!("states: {got} columns, but the teacher's states are {} wide", t.state_dim())
        }
        TeacherModel::Unet(t) => {
            let s = t.spec();
            format!(
                "states: {got} columns, but the teacher's states are observation windows of \
                 {} steps × {} features = {} wide (build them with \
                 teacher.training_windows(observations, actions))",
                s.n_obs_steps,
                s.obs_dim(),
                t.state_dim()
            )
        }
    }
}
