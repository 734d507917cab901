//! `vdd.Policy`: a saved policy acting on raw observations ([`vdd_moe::load_policy`]).

use std::path::PathBuf;

use numpy::{AllowTypeChange, PyArray1, PyArray2, PyArrayDyn, PyArrayLike1, PyArrayLike2};
use pyo3::prelude::*;
use pyo3::types::PyTuple;
use vdd_core::Policy as _;
use vdd_moe::DeployedPolicy;

use crate::arrays::{check_batch, mat_to_numpy, matrix, row_bytes, shaped, vec_to_numpy, vector};
use crate::errors::run;

/// A distilled mixture-of-experts policy acting on raw environment observations.
#[pyclass(module = "vdd", name = "Policy")]
pub struct PyPolicy {
    inner: DeployedPolicy,
}

impl PyPolicy {
    /// Wraps a deployed policy.
    pub fn new(inner: DeployedPolicy) -> Self {
        Self { inner }
    }

    /// The raw observation window width (`obs_window · obs_dim`) and action chunk width.
    fn window_dims(&self) -> (usize, usize) {
        let spec = self.inner.spec();
        (spec.obs_window * self.inner.obs_dim(), spec.action_chunk * self.inner.action_dim())
    }

    /// Checks a call on `rows` rows with `io_floats` input and output values per row
    /// ([`check_batch`]): the mixture's activations on the batch
    /// ([`vdd_moe::MoeConfig::training_bytes`], an upper bound for inference) plus the inputs
    /// and outputs, twice (the Rust and the NumPy copies).
    fn check_rows(&self, what: &str, rows: usize, io_floats: usize) -> PyResult<()> {
        let model = self.inner.inner().config().training_bytes(rows);
        check_batch(what, rows, model.saturating_add(row_bytes(rows, io_floats).saturating_mul(2)))
    }
}

#[pymethods]
impl PyPolicy {
    /// Loads a policy saved by the crates (`Moe::save`, `cargo xtask experiment`) or by
    /// `Policy.save`.
    #[staticmethod]
    fn load(py: Python<'_>, path: PathBuf) -> PyResult<Self> {
        let inner = run(py, || vdd_moe::load_policy(&path))?;
        Ok(Self::new(inner))
    }

    /// One action `(action_dim,)` for one raw observation `(obs_dim,)`.
    fn act<'py>(
        &mut self,
        py: Python<'py>,
        obs: PyArrayLike1<'py, f32, AllowTypeChange>,
    ) -> PyResult<Bound<'py, PyArray1<f32>>> {
        let obs = vector(obs.as_array(), self.inner.obs_dim(), "obs")?;
        let mut action = vec![0.0f32; self.inner.action_dim()];
        let inner = &mut self.inner;
        run(py, || inner.act_into(&obs, &mut action))?;
        Ok(vec_to_numpy(py, action))
    }

    /// Actions `(n, action_dim)` for `n` raw observations `(n, obs_dim)`, one per
    /// environment (row `i` keeps its own observation history and action chunk).
    fn act_batch<'py>(
        &mut self,
        py: Python<'py>,
        obs: PyArrayLike2<'py, f32, AllowTypeChange>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let (rows, io) = (obs.as_array().nrows(), self.inner.obs_dim() + self.inner.action_dim());
        self.check_rows("act_batch", rows, io)?;
        let obs = matrix(obs.as_array(), self.inner.obs_dim(), "obs")?;
        let mut actions = faer::Mat::<f32>::zeros(obs.nrows(), self.inner.action_dim());
        let inner = &mut self.inner;
        run(py, || inner.act_batch(obs.as_ref(), actions.as_mut()))?;
        Ok(mat_to_numpy(py, actions.as_ref()))
    }

    /// The exact `log q(action | obs)` `(n,)` of raw actions `(n, action_chunk · action_dim)`
    /// at raw observation windows `(n, obs_window · obs_dim)`.
    fn log_likelihood<'py>(
        &mut self,
        py: Python<'py>,
        obs: PyArrayLike2<'py, f32, AllowTypeChange>,
        actions: PyArrayLike2<'py, f32, AllowTypeChange>,
    ) -> PyResult<Bound<'py, PyArray1<f32>>> {
        let (w, c) = self.window_dims();
        self.check_rows("log_likelihood", obs.as_array().nrows(), w + c + 1)?;
        let obs = matrix(obs.as_array(), w, "obs")?;
        let actions = matrix(actions.as_array(), c, "actions")?;
        if actions.nrows() != obs.nrows() {
            return Err(pyo3::exceptions::PyValueError::new_err(format!(
                "obs has {} rows but actions has {}",
                obs.nrows(),
                actions.nrows()
            )));
        }
        let mut out = vec![0.0f32; obs.nrows()];
        let inner = &mut self.inner;
        run(py, || {
            vdd_moe::deployed_log_likelihood(inner, obs.as_ref(), actions.as_ref(), &mut out)
        })?;
        Ok(vec_to_numpy(py, out))
    }

    /// The mixture at raw observation windows `(n, obs_window · obs_dim)`, in raw action
    /// space: `(log_gating (n, Z), means (n, Z, A), scale_tril (n, Z, A, A))` with
    /// `A = action_chunk · action_dim`.
    fn components<'py>(
        &mut self,
        py: Python<'py>,
        obs: PyArrayLike2<'py, f32, AllowTypeChange>,
    ) -> PyResult<Bound<'py, PyTuple>> {
        let (w, c) = self.window_dims();
        let z = self.inner.inner().num_experts();
        // log_gating, means and scale factors: Z·(1 + A + A²) per row.
        let out = z.saturating_mul(c.saturating_mul(c).saturating_add(c).saturating_add(1));
        self.check_rows("components", obs.as_array().nrows(), w.saturating_add(out))?;
        let obs = matrix(obs.as_array(), w, "obs")?;
        let inner = &mut self.inner;
        let c = run(py, || vdd_moe::deployed_components(inner, obs.as_ref()))?;
        let (n, z, a) = (c.n, c.num_experts, c.action_dim);
        let parts: [Bound<'py, PyArrayDyn<f32>>; 3] = [
            shaped(py, c.log_gating, &[n, z])?,
            shaped(py, c.means, &[n, z, a])?,
            shaped(py, c.scale_tril, &[n, z, a, a])?,
        ];
        PyTuple::new(py, parts)
    }

    /// Forgets the observation histories, action chunks and held experts (call at an
    /// episode's start).
    fn reset(&mut self) {
        self.inner.reset();
    }

    /// Reseeds the random draws of acting (expert picks and sampled actions).
    fn seed(&mut self, seed: u64) {
        self.inner.seed(seed);
    }

    /// Saves the policy (weights, normalisers, act mode, deployment spec) to one file.
    fn save(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        let moe = self.inner.inner();
        run(py, || moe.save(&path))
    }

    /// Writes the policy as a LeRobot policy directory (`--policy.type=vdd`) through the
    /// `lerobot_policy_vdd` plugin's converter (`lerobot-vdd-convert`): `teacher_dir` is the
    /// LeRobot `DiffusionPolicy` directory the student was distilled from. `ImportError` when
    /// the plugin (and with it LeRobot and PyTorch) is not installed.
    #[pyo3(signature = (out, teacher_dir, seed = 0))]
    fn save_pretrained(
        &self,
        py: Python<'_>,
        out: PathBuf,
        teacher_dir: PathBuf,
        seed: u64,
    ) -> PyResult<()> {
        let convert = match py.import("lerobot_policy_vdd.convert") {
            Ok(m) => m,
            Err(e) if e.is_instance_of::<pyo3::exceptions::PyImportError>(py) => {
                let err = pyo3::exceptions::PyImportError::new_err(
                    "save_pretrained needs the LeRobot plugin package lerobot_policy_vdd \
                     (crates/vdd-py/lerobot_policy_vdd: `pip install \
                     crates/vdd-py/lerobot_policy_vdd`, with lerobot 0.6.1 and torch); \
                     without it, save the student with Policy.save and convert it later with \
                     `lerobot-vdd-convert --student FILE --teacher DIR --out DIR`",
                );
                err.set_cause(py, Some(e));
                return Err(err);
            }
            Err(e) => return Err(e),
        };
        let nanos = std::time::SystemTime::now()
            .duration_since(std::time::UNIX_EPOCH)
            .map_or(0, |d| d.as_nanos());
        let tmp = std::env::temp_dir()
            .join(format!("vdd-student-{}-{nanos}.safetensors", std::process::id()));
        let moe = self.inner.inner();
        run(py, || moe.save(&tmp))?;
        let kwargs = pyo3::types::PyDict::new(py);
        kwargs.set_item("seed", seed)?;
        let result = convert.getattr("convert")?.call((&tmp, teacher_dir, out), Some(&kwargs));
        // The temporary file goes whatever the converter did; failing to remove it is harmless.
        let _ = std::fs::remove_file(&tmp);
        result.map(|_| ())
    }

    /// Writes the policy as an ONNX graph (`vdd_onnx`): input `obs`
    /// `(n, obs_window · obs_dim)`, outputs `log_gating`, `means`, `scale_tril` equal to
    /// `components(obs)`.
    fn export_onnx(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        let moe = self.inner.inner();
        run(py, || {
            let bytes = vdd_onnx::export(moe)?;
            std::fs::write(&path, bytes)
                .map_err(|source| vdd_onnx::OnnxError::Io { path: path.clone(), source })
        })
    }

    /// Rust's own µs per `act` call for this policy (`vdd_tasks::timing::us_per_action`, the
    /// recipes' measurement: the median of 5 timed rounds of single-observation calls over
    /// the episode `obs` `(T, obs_dim)`, again and again), on a copy of the policy.
    #[pyo3(signature = (obs, calls = 2000, warmup = 100, min_round_ms = 20.0))]
    fn rust_us_per_act(
        &self,
        py: Python<'_>,
        obs: PyArrayLike2<'_, f32, AllowTypeChange>,
        calls: usize,
        warmup: usize,
        min_round_ms: f64,
    ) -> PyResult<f64> {
        let episode = matrix(obs.as_array(), self.inner.obs_dim(), "obs")?;
        let timing = vdd_tasks::timing::Timing { calls, warmup, min_round_ms };
        let mut copies = [self.inner.clone()];
        let us = run(py, || vdd_tasks::timing::us_per_action(&mut copies, &[episode], timing, 0))?;
        Ok(us[0])
    }

    /// Dimension of one raw observation.
    #[getter]
    fn obs_dim(&self) -> usize {
        self.inner.obs_dim()
    }

    /// Dimension of one action.
    #[getter]
    fn action_dim(&self) -> usize {
        self.inner.action_dim()
    }

    /// Number of experts `Z`.
    #[getter]
    fn num_experts(&self) -> usize {
        self.inner.inner().num_experts()
    }

    /// Raw observations per model input (`components`, `log_likelihood` and the ONNX graph
    /// take windows of this many observations, oldest first).
    #[getter]
    fn obs_window(&self) -> usize {
        self.inner.spec().obs_window
    }

    /// Actions per predicted chunk (`components` and `log_likelihood` work on whole chunks).
    #[getter]
    fn action_chunk(&self) -> usize {
        self.inner.spec().action_chunk
    }

    /// The observation feature map the policy applies, as `"name vVERSION"`.
    #[getter]
    fn features(&self) -> String {
        self.inner.spec().features.to_string()
    }

    fn __repr__(&self) -> String {
        format!(
            "vdd.Policy(obs_dim={}, action_dim={}, num_experts={}, obs_window={}, action_chunk={}, features='{}')",
            self.obs_dim(),
            self.action_dim(),
            self.num_experts(),
            self.obs_window(),
            self.action_chunk(),
            self.features()
        )
    }
}
