//! `vdd.distill`: the Rust VDD trainer driven from Python, with a teacher that is any Python
//! callable (or a `vdd.Teacher`).

use faer::{Mat, MatMut, MatRef};
use numpy::{AllowTypeChange, PyArrayLike2};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyTuple};
use serde_json::{Map, Value};
use vdd::{
    Affine, AutoOptions, AutoPlan, DistillData, Moe, MoeConfig, ScoreModel, Vdd, VddConfig,
    VddError,
};
use vdd_core::{CoreError, check_score_args};

use crate::arrays::{mat_to_numpy, matrix, row_bytes};
use crate::errors::{IntoPy as _, to_py};
use crate::policy::PyPolicy;
use crate::teacher::PyTeacher;

/// A teacher whose score is a Python callable `score_fn(actions, states, sigma)`: called with
/// the GIL held, the rest of training runs without it. A Python exception raised by the
/// callable (or a wrong result) becomes [`CoreError::Implementor`] with the `PyErr` as its
/// source, which `distill` raises again.
pub struct PyScore {
    score_fn: Py<PyAny>,
    sample_fn: Option<Py<PyAny>>,
    state_dim: usize,
    action_dim: usize,
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

/// Keys of `vdd.distill`'s own arguments, which `**settings` must not repeat.
const RESERVED: &[(&str, &str)] = &[
    ("seed", "seed="),
    ("iterations", "iterations="),
    ("num_experts", "experts="),
    ("action_dim", "action_dim="),
    ("state_dim", "the columns of `states`"),
];

/// Applies `settings` to the trainer's and the student's configurations (each key is a field of
/// `VddConfig` or `MoeConfig`); an unknown key is an error naming it.
pub fn apply_settings(
    vdd: &mut VddConfig,
    moe: &mut MoeConfig,
    settings: &[(String, Value)],
) -> Result<(), String> {
    let mut v = serde_json::to_value(&*vdd).map_err(|e| e.to_string())?;
    let mut m = serde_json::to_value(&*moe).map_err(|e| e.to_string())?;
    // Every trainer field, those left out of the serialised form when unset included.
    let probe = VddConfig {
        noise_anneal_until: Some(0.0),
        score_at: vdd::ScoreAt::NoisedSample,
        state_noise: Some(vdd::StateNoise { share: 1.0, std: 1.0 }),
        ..vdd.clone()
    };
    let trainer_fields = serde_json::to_value(&probe).map_err(|e| e.to_string())?;
    for (key, value) in settings {
        if let Some((_, instead)) = RESERVED.iter().find(|(k, _)| k == key) {
            return Err(format!("setting `{key}`: give it as {instead}"));
        }
        let target = if trainer_fields.get(key).is_some() {
            &mut v
        } else if m.get(key).is_some() {
            &mut m
        } else {
            let names = |x: &Value| {
                let own = |k: &String| !RESERVED.iter().any(|(r, _)| r == k);
                x.as_object()
                    .map(|o| o.keys().filter(|k| own(k)).cloned().collect::<Vec<_>>().join(", "))
            };
            return Err(format!(
                "unknown setting `{key}` (trainer settings: {}; student settings: {})",
                names(&trainer_fields).unwrap_or_default(),
                names(&m).unwrap_or_default()
            ));
        };
        target[key.as_str()] = value.clone();
    }
    *vdd = serde_json::from_value(v).map_err(|e| format!("invalid trainer setting: {e}"))?;
    *moe = serde_json::from_value(m).map_err(|e| format!("invalid student setting: {e}"))?;
    Ok(())
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

/// Which defaults `distill` starts from (the setting `defaults`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Defaults {
    /// [`Vdd::auto`]: picked from the teacher ([`AutoPlan::inspect`]).
    Auto,
    /// The paper's toy settings ([`VddConfig::toy`], [`MoeConfig::toy`]) with [`Vdd::new`].
    Toy,
}

/// A failed run: a training error, or a setting the plan's configurations refuse.
enum RunError {
    Vdd(VddError),
    Setting(String),
}

impl From<VddError> for RunError {
    fn from(e: VddError) -> Self {
        Self::Vdd(e)
    }
}

impl From<CoreError> for RunError {
    fn from(e: CoreError) -> Self {
        Self::Vdd(e.into())
    }
}

impl From<vdd::MoeError> for RunError {
    fn from(e: vdd::MoeError) -> Self {
        Self::Vdd(e.into())
    }
}

/// What `distill` was asked for, besides the teacher and the data.
struct Request {
    defaults: Defaults,
    experts: usize,
    iterations: Option<usize>,
    seed: u64,
    state_dim: usize,
    action_dim: usize,
    settings: Vec<(String, Value)>,
}

impl Request {
    /// The toy configurations with `iterations`, `seed` and the settings applied.
    fn toy_configs(&self) -> Result<(VddConfig, MoeConfig), String> {
        let mut config = VddConfig { seed: self.seed, ..VddConfig::toy() };
        if let Some(it) = self.iterations {
            config.iterations = it;
        }
        let mut moe = MoeConfig::toy(self.state_dim, self.action_dim, self.experts);
        apply_settings(&mut config, &mut moe, &self.settings)?;
        Ok((config, moe))
    }
}

fn train<S: ScoreModel>(
    request: &Request,
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
            let options = AutoOptions {
                iterations: request.iterations,
                ..AutoOptions::new(request.experts, request.seed)
            };
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
#[pyo3(signature = (score_fn, states, *, action_dim, experts = 8, iterations = None, seed = 0, actions = None, sample_fn = None, **settings))]
#[allow(clippy::too_many_arguments)]
pub fn distill(
    py: Python<'_>,
    score_fn: Bound<'_, PyAny>,
    states: PyArrayLike2<'_, f32, AllowTypeChange>,
    action_dim: usize,
    experts: usize,
    iterations: Option<usize>,
    seed: u64,
    actions: Option<PyArrayLike2<'_, f32, AllowTypeChange>>,
    sample_fn: Option<Bound<'_, PyAny>>,
    settings: Option<Bound<'_, PyDict>>,
) -> PyResult<PyPolicy> {
    let state_dim = states.as_array().ncols();
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
            let value = to_json(&v, &k)?;
            pairs.push((k, value));
        }
    }
    let request =
        Request { defaults, experts, iterations, seed, state_dim, action_dim, settings: pairs };
    // Settings are checked before the teacher is inspected (which may take many calls).
    request.toy_configs().map_err(PyValueError::new_err)?;
    let data = DistillData::new(states, actions.clone()).py_err(py)?;
    let trained = if let Ok(teacher) = score_fn.cast::<PyTeacher>() {
        if sample_fn.is_some() {
            return Err(PyValueError::new_err(
                "sample_fn is for a Python score_fn; a vdd.Teacher samples itself",
            ));
        }
        let teacher = teacher.borrow();
        let data = data.with_teacher_space(teacher.space());
        let inner = teacher.inner.clone();
        if (inner.state_dim(), inner.action_dim()) != (state_dim, action_dim) {
            return Err(PyValueError::new_err(format!(
                "the teacher is {} -> {}, the data {state_dim} -> {action_dim}",
                inner.state_dim(),
                inner.action_dim()
            )));
        }
        run_train(py, || train(&request, inner, data, actions.as_ref()))
    } else {
        if !score_fn.is_callable() {
            return Err(PyTypeError::new_err("score_fn must be callable"));
        }
        if sample_fn.as_ref().is_some_and(|f| !f.is_callable()) {
            return Err(PyTypeError::new_err("sample_fn must be callable (or None)"));
        }
        let teacher = PyScore {
            score_fn: score_fn.unbind(),
            sample_fn: sample_fn.map(Bound::unbind),
            state_dim,
            action_dim,
        };
        run_train(py, || train(&request, teacher, data, actions.as_ref()))
    };
    match trained? {
        Ok(student) => Ok(PyPolicy::new(student.into_policy().py_err(py)?)),
        Err(RunError::Vdd(e)) => Err(to_py(py, &e)),
        Err(RunError::Setting(msg)) => Err(PyValueError::new_err(msg)),
    }
}

/// Runs a training closure with the GIL released; a panic becomes `RuntimeError`
/// ([`crate::errors::panic_error`]), the training error is kept for [`to_py`].
fn run_train<T: Send, E: Send>(
    py: Python<'_>,
    f: impl FnOnce() -> Result<T, E> + Send,
) -> PyResult<Result<T, E>> {
    py.detach(|| std::panic::catch_unwind(std::panic::AssertUnwindSafe(f)))
        .map_err(|payload| crate::errors::panic_error(payload.as_ref()))
}
