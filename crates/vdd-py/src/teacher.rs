//! `vdd.Teacher`, `vdd.load_teacher` and `vdd.import_lerobot`: the diffusion teachers the
//! crates train (`vdd-diffusion`) and the diffusion policies imported from PyTorch
//! (`vdd-import`: LeRobot's and diffusion_policy's 1-D U-Nets), usable from Python as a
//! `score_fn` of `vdd.distill` (they then run in Rust).
//!
//! Both kinds take and return **raw** values in `__call__`: raw actions (for an imported
//! teacher the raw action chunk, step-major), raw states (for an imported teacher the
//! observation window after its feature and observation maps, oldest first, as
//! `training_windows` builds them), noise levels in the teacher's own convention; the score is
//! with respect to the raw actions (the chain rule of the teacher's normaliser).

use std::path::{Path, PathBuf};

use faer::Mat;
use numpy::{AllowTypeChange, PyArray2, PyArrayLike1, PyArrayLike2};
use pyo3::exceptions::{PyTypeError, PyValueError};
use pyo3::prelude::*;
use pyo3::types::{PyDict, PyList, PyTuple};
use vdd::TeacherSpace;
use vdd_core::{Affine, NoiseConvention, ScoreModel};
use vdd_diffusion::DiffusionTeacher;
use vdd_import::{ImportedTeacher, LerobotOptions, ObsMap, Sampler, UnetTeacher};

use crate::arrays::{check_batch, mat_to_numpy, matrix, row_bytes, vector};
use crate::errors::{IntoPy as _, run};

/// Two NumPy matrices (states and action chunks).
type ArrayPair<'py> = (Bound<'py, PyArray2<f32>>, Bound<'py, PyArray2<f32>>);

/// The teacher a `vdd.Teacher` holds.
#[derive(Debug, Clone)]
pub enum TeacherModel {
    /// A DDPM or BESO teacher of `vdd-diffusion`.
    Diffusion(Box<DiffusionTeacher>),
    /// A 1-D U-Net diffusion policy imported from PyTorch (`vdd-import`).
    Unet(Box<UnetTeacher>),
}

/// A learned diffusion teacher: trained by the crates, or imported from PyTorch.
#[pyclass(module = "vdd", name = "Teacher")]
pub struct PyTeacher {
    pub(crate) inner: TeacherModel,
}

impl PyTeacher {
    /// The space the teacher's score model works in (its own normalisers).
    pub fn space(&self) -> Result<TeacherSpace, vdd_import::ImportError> {
        let (s, a) = self.normalizers()?;
        Ok(TeacherSpace::normalized(s, a))
    }

    /// The teacher's state and action normalisers (of its whole state and action).
    fn normalizers(&self) -> Result<(Affine, Affine), vdd_import::ImportError> {
        match &self.inner {
            TeacherModel::Diffusion(t) => {
                let (s, a) = t.normalizers();
                Ok((s.clone(), a.clone()))
            }
            TeacherModel::Unet(t) => t.teacher_space(),
        }
    }

    /// The teacher as a score model.
    fn score_model(&mut self) -> &mut (dyn ScoreModel + Send) {
        match &mut self.inner {
            TeacherModel::Diffusion(t) => t.as_mut(),
            TeacherModel::Unet(t) => t.as_mut(),
        }
    }

    fn score_model_ref(&self) -> &dyn ScoreModel {
        match &self.inner {
            TeacherModel::Diffusion(t) => t.as_ref(),
            TeacherModel::Unet(t) => t.as_ref(),
        }
    }

    /// The imported U-Net, or a `TypeError` naming what needs one.
    fn unet(&self, what: &str) -> PyResult<&UnetTeacher> {
        match &self.inner {
            TeacherModel::Unet(t) => Ok(t),
            TeacherModel::Diffusion(_) => Err(PyTypeError::new_err(format!(
                "{what} is for a teacher imported from PyTorch (vdd.import_lerobot); this one is \
                 a vdd-diffusion teacher, whose states and actions are single steps"
            ))),
        }
    }
}

/// An observation map given as `"key=INDICES;..."` or `{key: [indices]}`.
fn parse_obs_map(v: &Bound<'_, PyAny>) -> PyResult<ObsMap> {
    let bad = |e: vdd_import::ImportError| PyValueError::new_err(format!("obs_map: {e}"));
    if let Ok(s) = v.extract::<String>() {
        return s.parse().map_err(bad);
    }
    let Ok(d) = v.cast::<PyDict>() else {
        return Err(PyTypeError::new_err(
            "obs_map must be a string 'observation.state=0..4;observation.environment_state=4..7' \
             or a dict {'observation.state': [0, 1, 2, 3], ...}",
        ));
    };
    let mut features = Vec::new();
    let mut raw_dim = None;
    for (k, x) in d.iter() {
        let k: String = k.extract()?;
        if k == "raw_dim" {
            raw_dim = Some(x.extract::<usize>()?);
            continue;
        }
        let idx: Vec<usize> = if x.cast::<PyList>().is_ok() || x.cast::<PyTuple>().is_ok() {
            x.extract()?
        } else {
            // A `range`, or any iterable of indices.
            x.try_iter()?.map(|i| i?.extract::<usize>()).collect::<PyResult<_>>()?
        };
        features.push((k, idx));
    }
    let widest = features.iter().flat_map(|(_, i)| i.iter()).max().map_or(0, |&m| m + 1);
    ObsMap::new(raw_dim.unwrap_or(widest), features).map_err(bad)
}

fn parse_sampler(s: &str) -> PyResult<Sampler> {
    s.parse().map_err(sampler_error)
}

/// A sampler the caller named that does not parse or does not fit the teacher's schedule.
fn sampler_error(e: vdd_import::ImportError) -> PyErr {
    PyValueError::new_err(format!("sampler: {e}"))
}

/// Imports a LeRobot `DiffusionPolicy` directory (`save_pretrained`'s files; state inputs
/// only) as a teacher that runs in Rust.
#[pyfunction]
#[pyo3(signature = (path, obs_map = None, sampler = None, seed = 0))]
pub fn import_lerobot(
    py: Python<'_>,
    path: PathBuf,
    obs_map: Option<Bound<'_, PyAny>>,
    sampler: Option<String>,
    seed: u64,
) -> PyResult<PyTeacher> {
    if !path.is_dir() {
        return Err(PyValueError::new_err(format!(
            "import_lerobot: {} is not a directory (a LeRobot policy's save_pretrained folder \
             with config.json and model.safetensors)",
            path.display()
        )));
    }
    let options = LerobotOptions {
        obs_map: obs_map.as_ref().map(parse_obs_map).transpose()?,
        sampler: sampler.as_deref().map(parse_sampler).transpose()?,
    };
    let imported =
        crate::errors::run_train(py, || vdd_import::import_lerobot_with(&path, &options))?;
    let mut teacher = match imported {
        Ok(t) => t,
        // A map that does not fit the policy's features is the caller's argument.
        Err(e @ vdd_import::ImportError::BadValue { .. })
            if e.to_string().contains("obs_map") || e.to_string().starts_with("sampler") =>
        {
            return Err(PyValueError::new_err(e.to_string()));
        }
        Err(e) => return Err(crate::errors::to_py(py, &e)),
    };
    vdd_core::Policy::seed(&mut teacher, seed);
    Ok(PyTeacher { inner: TeacherModel::Unet(Box::new(teacher)) })
}

/// Whether `path` is a safetensors file written by `vdd-import` (`cargo xtask import`).
fn is_import_file(path: &Path) -> bool {
    use std::io::Read;
    // The header's first bytes: its length, then JSON whose metadata names the kind. Reading a
    // bounded prefix is enough to find the key; the loader checks everything again.
    let Ok(mut f) = std::fs::File::open(path) else { return false };
    let mut len = [0u8; 8];
    if f.read_exact(&mut len).is_err() {
        return false;
    }
    let n = u64::from_le_bytes(len).min(1 << 24);
    let mut header = Vec::new();
    if f.take(n).read_to_end(&mut header).is_err() {
        return false;
    }
    String::from_utf8_lossy(&header).contains(vdd_import::KIND_KEY)
}

/// Loads a teacher: a LeRobot policy directory ([`import_lerobot`]), a teacher file written by
/// `cargo xtask import`, or a teacher saved by `vdd-diffusion`.
#[pyfunction]
#[pyo3(signature = (path, seed = 0, obs_map = None, sampler = None))]
pub fn load_teacher(
    py: Python<'_>,
    path: PathBuf,
    seed: u64,
    obs_map: Option<Bound<'_, PyAny>>,
    sampler: Option<String>,
) -> PyResult<PyTeacher> {
    if path.is_dir() {
        return import_lerobot(py, path, obs_map, sampler, seed);
    }
    if !path.exists() {
        return Err(PyValueError::new_err(format!(
            "load_teacher: {} does not exist",
            path.display()
        )));
    }
    if obs_map.is_some() {
        return Err(PyValueError::new_err(
            "obs_map is stated when importing a LeRobot directory; a teacher file carries its own",
        ));
    }
    if is_import_file(&path) {
        let ImportedTeacher::Unet1d(mut t) = run(py, || vdd_import::load_teacher(&path))?;
        if let Some(s) = sampler {
            t.set_sampler(parse_sampler(&s)?).map_err(sampler_error)?;
        }
        vdd_core::Policy::seed(t.as_mut(), seed);
        return Ok(PyTeacher { inner: TeacherModel::Unet(t) });
    }
    if sampler.is_some() {
        return Err(PyValueError::new_err(
            "sampler applies to teachers imported from PyTorch; this is a vdd-diffusion teacher",
        ));
    }
    let inner = run(py, || DiffusionTeacher::load(&path, seed))?;
    Ok(PyTeacher { inner: TeacherModel::Diffusion(Box::new(inner)) })
}

#[pymethods]
impl PyTeacher {
    /// The score `∇_a log p_level(a | s)` `(n, action_dim)` of raw actions `(n, action_dim)`
    /// at raw states `(n, state_dim)` and noise levels `(n,)` in the teacher's own convention
    /// (`noise_convention`: VE `sigma` for BESO, VP `time` for DDPM and imported U-Nets).
    fn __call__<'py>(
        &mut self,
        py: Python<'py>,
        actions: PyArrayLike2<'py, f32, AllowTypeChange>,
        states: PyArrayLike2<'py, f32, AllowTypeChange>,
        levels: PyArrayLike1<'py, f32, AllowTypeChange>,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let (ds, da) = (self.state_dim(), self.action_dim());
        // Inputs, output and the teacher's working copies: a few rows' worth of each, far
        // below its network's activations, which the row limit bounds.
        let rows = actions.as_array().nrows();
        check_batch("a teacher's score", rows, row_bytes(rows, (ds + 2 * da).saturating_mul(4)))?;
        let actions = matrix(actions.as_array(), da, "actions")?;
        let states = matrix(states.as_array(), ds, "states")?;
        let n = actions.nrows();
        if states.nrows() != n {
            return Err(PyValueError::new_err(format!(
                "actions has {n} rows but states has {}",
                states.nrows()
            )));
        }
        let levels = vector(levels.as_array(), n, "levels")?;
        let (s_map, a_map) = self.normalizers().py_err(py)?;
        let actions = a_map.normalize_rows(actions.as_ref()).py_err(py)?;
        let states = s_map.normalize_rows(states.as_ref()).py_err(py)?;
        let mut out = Mat::<f32>::zeros(n, da);
        let inner = self.score_model();
        run(py, || inner.score(actions.as_ref(), states.as_ref(), &levels, out.as_mut()))?;
        // The chain rule of the normaliser: ∇_raw = ∇_normalised / scale.
        for i in 0..n {
            for j in 0..da {
                out[(i, j)] /= a_map.scale[j];
            }
        }
        Ok(mat_to_numpy(py, out.as_ref()))
    }

    /// Actions `(n, action_dim)` the teacher samples with its own sampler at raw states
    /// `(n, state_dim)` (an imported teacher: raw chunks at observation windows), in raw units;
    /// `seed` seeds the draws (the same seed, the same actions).
    #[pyo3(signature = (states, seed = 0))]
    fn sample<'py>(
        &mut self,
        py: Python<'py>,
        states: PyArrayLike2<'py, f32, AllowTypeChange>,
        seed: u64,
    ) -> PyResult<Bound<'py, PyArray2<f32>>> {
        let (ds, da) = (self.state_dim(), self.action_dim());
        let rows = states.as_array().nrows();
        check_batch("a teacher's samples", rows, row_bytes(rows, (ds + 2 * da).saturating_mul(4)))?;
        let states = matrix(states.as_array(), ds, "states")?;
        let (s_map, a_map) = self.normalizers().py_err(py)?;
        let states = s_map.normalize_rows(states.as_ref()).py_err(py)?;
        let mut out = Mat::<f32>::zeros(rows, da);
        let inner = self.score_model();
        run(py, || {
            let mut rng = vdd_core::Seeds::new(seed).stream("vdd.Teacher.sample");
            inner.sample_actions(states.as_ref(), &mut rng, out.as_mut())
        })?;
        let mut row = vec![0.0f32; da];
        for i in 0..rows {
            for (j, x) in row.iter_mut().enumerate() {
                *x = out[(i, j)];
            }
            a_map.denormalize(&mut row);
            for (j, x) in row.iter().enumerate() {
                out[(i, j)] = *x;
            }
        }
        Ok(mat_to_numpy(py, out.as_ref()))
    }

    /// The teacher's training samples of episodes (imported teachers): per episode, raw
    /// observations `(T, obs_dim)` and actions `(T, step_action_dim)`; returns the raw states
    /// `(N, state_dim)` and action chunks `(N, action_dim)`, one per step of every episode.
    fn training_windows<'py>(
        &self,
        py: Python<'py>,
        observations: Vec<PyArrayLike2<'py, f32, AllowTypeChange>>,
        actions: Vec<PyArrayLike2<'py, f32, AllowTypeChange>>,
    ) -> PyResult<ArrayPair<'py>> {
        let t = self.unet("training_windows")?;
        let spec = t.spec();
        let (d_raw, d_act) = (spec.raw_obs_dim(), spec.unet.input_dim);
        if observations.len() != actions.len() {
            return Err(PyValueError::new_err(format!(
                "training_windows: {} observation arrays but {} action arrays (one of each per \
                 episode)",
                observations.len(),
                actions.len()
            )));
        }
        if observations.is_empty() {
            return Err(PyValueError::new_err("training_windows: no episodes"));
        }
        let map = spec.features.resolve().py_err(py)?;
        let (mut obs, mut act) = (Vec::new(), Vec::new());
        for (e, (o, a)) in observations.iter().zip(&actions).enumerate() {
            let o = matrix(o.as_array(), d_raw, &format!("observations[{e}]"))?;
            let a = matrix(a.as_array(), d_act, &format!("actions[{e}]"))?;
            if o.nrows() != a.nrows() || o.nrows() == 0 {
                return Err(PyValueError::new_err(format!(
                    "episode {e}: {} observations and {} actions (equal and at least one)",
                    o.nrows(),
                    a.nrows()
                )));
            }
            obs.push(map.apply_rows(o.as_ref()).py_err(py)?);
            act.push(a);
        }
        let episodes = vdd_data::Episodes::from_episodes(obs, act).py_err(py)?;
        let (states, chunks) = t.training_windows(&episodes).py_err(py)?;
        Ok((mat_to_numpy(py, states.as_ref()), mat_to_numpy(py, chunks.as_ref())))
    }

    /// Saves an imported teacher as a teacher file (as `cargo xtask import` writes it; its
    /// observation map and sampler included), which `load_teacher` reads back.
    fn save(&self, py: Python<'_>, path: PathBuf) -> PyResult<()> {
        let t = self.unet("save")?;
        run(py, || vdd_import::save_unet_teacher(&path, t))
    }

    /// Acts with `sampler` (`'ddpm'`, `'ddpm:N'`, `'ddim:N'`) from now on (imported teachers).
    fn set_sampler(&mut self, sampler: &str) -> PyResult<()> {
        let s = parse_sampler(sampler)?;
        match &mut self.inner {
            TeacherModel::Unet(t) => t.set_sampler(s).map_err(sampler_error),
            TeacherModel::Diffusion(_) => self.unet("set_sampler").map(|_| ()),
        }
    }

    /// Width of the teacher's action: a whole chunk (`action_chunk · step_action_dim`) for
    /// an imported teacher.
    #[getter]
    fn action_dim(&self) -> usize {
        self.score_model_ref().action_dim()
    }

    /// Width of the teacher's state: a whole observation window (`obs_window · obs_dim`
    /// after the maps) for an imported teacher.
    #[getter]
    fn state_dim(&self) -> usize {
        self.score_model_ref().state_dim()
    }

    /// Width of one raw per-step observation the teacher reads.
    #[getter]
    fn obs_dim(&self) -> usize {
        match &self.inner {
            TeacherModel::Diffusion(t) => t.state_dim(),
            TeacherModel::Unet(t) => t.spec().raw_obs_dim(),
        }
    }

    /// Width of one per-step action.
    #[getter]
    fn step_action_dim(&self) -> usize {
        match &self.inner {
            TeacherModel::Diffusion(t) => t.action_dim(),
            TeacherModel::Unet(t) => t.spec().unet.input_dim,
        }
    }

    /// Observations per teacher state (1 for `vdd-diffusion` teachers).
    #[getter]
    fn obs_window(&self) -> usize {
        match &self.inner {
            TeacherModel::Diffusion(_) => 1,
            TeacherModel::Unet(t) => t.spec().n_obs_steps,
        }
    }

    /// Actions per teacher chunk (its horizon; 1 for `vdd-diffusion` teachers).
    #[getter]
    fn action_chunk(&self) -> usize {
        match &self.inner {
            TeacherModel::Diffusion(_) => 1,
            TeacherModel::Unet(t) => t.spec().horizon,
        }
    }

    /// Actions of a chunk executed before the next prediction (imported teachers; 1 else).
    #[getter]
    fn execute_steps(&self) -> usize {
        match &self.inner {
            TeacherModel::Diffusion(_) => 1,
            TeacherModel::Unet(t) => t.spec().n_action_steps,
        }
    }

    /// Index of the chunk's first executed action (imported teachers; 0 else).
    #[getter]
    fn chunk_start(&self) -> usize {
        match &self.inner {
            TeacherModel::Diffusion(_) => 0,
            TeacherModel::Unet(t) => t.spec().action_start,
        }
    }

    /// The sampler an imported teacher acts with (`'ddpm'`, `'ddpm:N'`, `'ddim:N'`), `None`
    /// for a `vdd-diffusion` teacher.
    #[getter]
    fn sampler(&self) -> Option<String> {
        match &self.inner {
            TeacherModel::Diffusion(_) => None,
            TeacherModel::Unet(t) => Some(t.spec().sampler().to_string()),
        }
    }

    /// The observation map an imported teacher was given (`'key=i,j;...'`), or `None`.
    #[getter]
    fn obs_map(&self) -> Option<String> {
        match &self.inner {
            TeacherModel::Diffusion(_) => None,
            TeacherModel::Unet(t) => t.spec().obs_map.as_ref().map(ToString::to_string),
        }
    }

    /// The observation feature map (`"name vVERSION"`) of an imported teacher, or `None`.
    #[getter]
    fn features(&self) -> Option<String> {
        match &self.inner {
            TeacherModel::Diffusion(_) => None,
            TeacherModel::Unet(t) => Some(t.spec().features.to_string()),
        }
    }

    /// The noise levels the teacher was trained on, `(low, high)`, if it states them.
    #[getter]
    fn noise_range(&self) -> Option<(f32, f32)> {
        self.score_model_ref().noise_range()
    }

    /// `"ddpm"` or `"beso"` (`vdd-diffusion`), `"unet1d"` (imported).
    #[getter]
    fn kind(&self) -> &'static str {
        match &self.inner {
            TeacherModel::Diffusion(t) => match t.kind() {
                vdd_diffusion::TeacherKind::Ddpm => "ddpm",
                vdd_diffusion::TeacherKind::Beso => "beso",
            },
            TeacherModel::Unet(_) => "unet1d",
        }
    }

    /// Where an imported teacher came from (`"lerobot"`, `"diffusion_policy"`), else `None`.
    #[getter]
    fn source(&self) -> Option<String> {
        match &self.inner {
            TeacherModel::Diffusion(_) => None,
            TeacherModel::Unet(t) => Some(t.spec().source.clone()),
        }
    }

    /// `"sigma"` (VE noise level) or `"time"` (VP diffusion time).
    #[getter]
    fn noise_convention(&self) -> &'static str {
        match self.score_model_ref().noise_convention() {
            NoiseConvention::Sigma => "sigma",
            NoiseConvention::Time => "time",
        }
    }

    fn __repr__(&self) -> String {
        match &self.inner {
            TeacherModel::Diffusion(_) => format!(
                "vdd.Teacher(kind='{}', state_dim={}, action_dim={})",
                self.kind(),
                self.state_dim(),
                self.action_dim()
            ),
            TeacherModel::Unet(t) => format!(
                "vdd.Teacher(kind='unet1d', source='{}', obs_dim={}, obs_window={}, \
                 step_action_dim={}, action_chunk={}, sampler='{}')",
                t.spec().source,
                self.obs_dim(),
                self.obs_window(),
                self.step_action_dim(),
                self.action_chunk(),
                t.spec().sampler()
            ),
        }
    }
}
