//! A BESO/D3IL teacher: the imported score network inside BESO's Karras (EDM)
//! preconditioning (`GCDenoiser`), as a [`ScoreModel`] at any σ and (see [`crate::BesoPolicy`])
//! as a [`vdd_core::Policy`] with BESO's own sampler.

use std::collections::{BTreeMap, BTreeSet};
use std::path::Path;

use faer::{Mat, MatMut, MatRef};
use serde::{Deserialize, Serialize};
use vdd_core::{Affine, NoiseProcess, ScoreModel, VeProcess, check_score_args};
use vdd_diffusion::{KarrasSampler, Preconditioning};
use vdd_nn::{Param, Parameters};
use vdd_torch::{
    DiffusionGpt, DiffusionGptConfig, ResMlpScore, ResMlpScoreConfig, diffusion_gpt_buffer_suffixes,
};

use crate::beso_error::BesoError;
use crate::karras::SigmaSchedule;

/// The inner score network of a BESO teacher.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "arch", rename_all = "snake_case")]
pub enum BesoNetworkConfig {
    /// `score_gpts.DiffusionGPT`.
    DiffusionGpt(DiffusionGptConfig),
    /// `GCTimeScoreNetwork` over a `ResidualMLPNetwork`.
    ResMlp(ResMlpScoreConfig),
}

/// D3IL's `Scaler` as the teacher needs it: observations and actions standardised
/// (`(x − mean) / (std + 1e-12)`), and the action box (in the scaled space) that
/// `BesoAgent.predict` clamps the sampled action to.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BesoScaler {
    /// Observation scaling (identity when `scale_data` is false).
    pub obs: Affine,
    /// Action scaling (identity when `scale_data` is false).
    pub action: Affine,
    /// `y_bounds[0]`: per-dimension lower clamp of the (scaled) action (`f32::MIN` when the
    /// run exported no scaler).
    pub action_min: Vec<f32>,
    /// `y_bounds[1]`: per-dimension upper clamp.
    pub action_max: Vec<f32>,
}

/// Everything besides the weights that defines an imported BESO/D3IL teacher.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct BesoTeacherConfig {
    /// The inner network.
    pub network: BesoNetworkConfig,
    /// `GCDenoiser.sigma_data`.
    pub sigma_data: f32,
    /// `sigma_min` of the sampler's schedule.
    pub sigma_min: f32,
    /// `sigma_max`: the sampler starts from `σ_max · z`.
    pub sigma_max: f32,
    /// `num_sampling_steps`.
    pub steps: usize,
    /// `sampler_type`.
    pub sampler: KarrasSampler,
    /// The agent's noise schedule (D3IL's agent: linear; BESO's: exponential).
    pub schedule: SigmaSchedule,
    /// `window_size`: observations (and actions) the network sees.
    pub window: usize,
    /// Goal tokens (`goal_window_size` when goal-conditioned, else 0); a goal has the
    /// observation's width and follows the observation window in a state row.
    pub goal_window: usize,
    /// The data scaler.
    pub scaler: BesoScaler,
}

impl BesoTeacherConfig {
    /// One observation's width.
    pub fn obs_dim(&self) -> usize {
        match &self.network {
            BesoNetworkConfig::DiffusionGpt(c) => c.state_dim,
            BesoNetworkConfig::ResMlp(c) => c.obs_dim,
        }
    }

    /// One action's width.
    pub fn action_dim(&self) -> usize {
        match &self.network {
            BesoNetworkConfig::DiffusionGpt(c) => c.action_dim,
            BesoNetworkConfig::ResMlp(c) => c.action_dim,
        }
    }

    /// Checks ranges and that the scaler, window and network agree.
    pub fn validate(&self) -> Result<(), BesoError> {
        let bad = |what: String| Err(BesoError::Core(vdd_core::CoreError::Config(what)));
        let sizes = match &self.network {
            BesoNetworkConfig::DiffusionGpt(c) => crate::limits::check_gpt(c).map(drop),
            BesoNetworkConfig::ResMlp(c) => crate::limits::check_resmlp(c).map(drop),
        };
        if let Err(r) = sizes {
            return bad(format!("network `{}` = {}: {}", r.key, r.value, r.reason));
        }
        // The bounds of the preconditioning and of the noise range keep σ², σ_d² and 1/σ²
        // finite in f32: a σ_d of 1.8e19 would make every score NaN.
        let noise = Preconditioning::new(self.sigma_data)
            .and_then(|_| vdd_diffusion::check_sigma_range(self.sigma_min, self.sigma_max));
        if let Err(e) = noise {
            return bad(format!(
                "sigma_data {}, sigma_min {}, sigma_max {}: {e}",
                self.sigma_data, self.sigma_min, self.sigma_max
            ));
        }
        if self.steps == 0 || self.steps > 10_000 || self.window == 0 || self.window > 4096 {
            return bad(format!("steps {} / window {} out of range", self.steps, self.window));
        }
        if let BesoNetworkConfig::DiffusionGpt(c) = &self.network {
            if self.window > c.obs_seq_len || self.goal_window != c.goal_tokens() {
                return bad(format!(
                    "window {} / goal window {} do not fit DiffusionGPT's obs_seq_len {} / goal tokens {}",
                    self.window,
                    self.goal_window,
                    c.obs_seq_len,
                    c.goal_tokens()
                ));
            }
        } else if self.goal_window != 0 {
            return bad("the ResNet-MLP teacher is imported without goals".into());
        }
        let (od, ad, s) = (self.obs_dim(), self.action_dim(), &self.scaler);
        if s.obs.dim() != od
            || s.action.dim() != ad
            || s.action_min.len() != ad
            || s.action_max.len() != ad
        {
            return bad(format!("scaler dimensions do not match obs {od} / action {ad}"));
        }
        // Statistics of 1e300 become ±inf in f32 and every score NaN: refused here, as a
        // normaliser anywhere else is.
        for (what, a) in [("observation", &s.obs), ("action", &s.action)] {
            if let Err(e) = a.validate() {
                return bad(format!("scaler {what} statistics: {e}"));
            }
        }
        if s.action_min
            .iter()
            .zip(&s.action_max)
            .any(|(a, b)| !(a.is_finite() && b.is_finite() && a <= b))
        {
            return bad("scaler action bounds must be finite and ordered".into());
        }
        Ok(())
    }
}

/// The network of a teacher.
#[derive(Debug, Clone)]
pub(crate) enum Net {
    Gpt(Box<DiffusionGpt>),
    Mlp(Box<ResMlpScore>),
}

impl Net {
    pub(crate) fn new(cfg: &BesoNetworkConfig) -> Result<Self, BesoError> {
        Ok(match cfg {
            BesoNetworkConfig::DiffusionGpt(c) => Net::Gpt(Box::new(DiffusionGpt::new(c.clone())?)),
            BesoNetworkConfig::ResMlp(c) => Net::Mlp(Box::new(ResMlpScore::new(c.clone())?)),
        })
    }

    fn params(&self) -> &dyn Parameters {
        match self {
            Net::Gpt(n) => n.as_ref(),
            Net::Mlp(n) => n.as_ref(),
        }
    }

    fn params_mut(&mut self) -> &mut dyn Parameters {
        match self {
            Net::Gpt(n) => n.as_mut(),
            Net::Mlp(n) => n.as_mut(),
        }
    }

    /// The inner network's forward pass (`inner_model(state, action, goal, sigma)`).
    pub(crate) fn forward(
        &mut self,
        states: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
        goals: Option<MatRef<'_, f32>>,
        sigma: &[f32],
        out: MatMut<'_, f32>,
    ) -> Result<(), BesoError> {
        match self {
            Net::Gpt(n) => n.forward(states, actions, goals, sigma, out)?,
            Net::Mlp(n) => n.forward(states, actions, goals, sigma, out)?,
        }
        Ok(())
    }
}

/// A [`Parameters`] view that puts `prefix` before every name (PyTorch's `inner_model.`).
struct Prefixed<'a>(&'a mut dyn Parameters, &'a str);

impl Parameters for Prefixed<'_> {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        self.0.visit_params(&vdd_nn::join_name(prefix, self.1), f)
    }
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        self.0.visit_params_mut(&vdd_nn::join_name(prefix, self.1), f)
    }
}

/// The metadata key of the teacher file holding [`BesoTeacherConfig`] as JSON.
pub const BESO_CONFIG_KEY: &str = "vdd_import.beso";

/// An imported BESO/D3IL teacher. As a [`ScoreModel`] it works in the scaler's space on whole
/// windows: an action row is the window's `window · action_dim` actions (oldest first), a
/// state row the window's `window · obs_dim` observations followed by the goals, and
/// `score = (D(a; σ) − a) / σ²` with `D = c_skip a + c_out F(c_in a, σ)` (`GCDenoiser`).
#[derive(Debug, Clone)]
pub struct BesoTeacher {
    pub(crate) config: BesoTeacherConfig,
    pub(crate) net: Net,
    precond: Preconditioning,
    scaled: Mat<f32>,
    inner: Mat<f32>,
    coef: Vec<[f32; 3]>,
    /// The VE levels `[σ_min, σ_max]` of `config`.
    process: VeProcess,
}

impl BesoTeacher {
    /// A teacher with zero weights (fill them with [`BesoTeacher::load_state_dict`]).
    pub fn new(config: BesoTeacherConfig) -> Result<Self, BesoError> {
        config.validate()?;
        Ok(Self {
            net: Net::new(&config.network)?,
            precond: Preconditioning::new(config.sigma_data)?,
            process: VeProcess { min: config.sigma_min, max: config.sigma_max },
            config,
            scaled: Mat::zeros(0, 0),
            inner: Mat::zeros(0, 0),
            coef: Vec::new(),
        })
    }

    /// The configuration.
    pub fn config(&self) -> &BesoTeacherConfig {
        &self.config
    }

    /// Replaces the data scaler (for example D3IL statistics exported after the import); on
    /// error (dimensions that do not match the network) the teacher is unchanged.
    pub fn set_scaler(&mut self, scaler: BesoScaler) -> Result<(), BesoError> {
        let mut config = self.config.clone();
        config.scaler = scaler;
        config.validate()?;
        self.config = config;
        Ok(())
    }

    /// Loads the weights from a safetensors file of the PyTorch state dict (`GCDenoiser`'s
    /// keys, `inner_model.` first). A tensor the network needs but the file lacks is an error
    /// naming it, and so is a tensor the configured network does not have (apart from the
    /// causal-mask buffers the forward pass rebuilds).
    pub fn load_state_dict(&mut self, path: &Path) -> Result<(), BesoError> {
        let bytes = vdd_core::files::read_bounded(path, vdd_nn::io::MAX_FILE_BYTES)
            .map_err(|source| BesoError::Io { path: path.to_owned(), source })?;
        self.load_state_dict_bytes(path, &bytes)
    }

    /// [`BesoTeacher::load_state_dict`] from bytes; `path` names the source in errors.
    pub fn load_state_dict_bytes(&mut self, path: &Path, bytes: &[u8]) -> Result<(), BesoError> {
        let (_, meta) = safetensors::SafeTensors::read_metadata(bytes)
            .map_err(|source| vdd_nn::NnError::Malformed { path: path.to_owned(), source })?;
        let mut known = BTreeSet::new();
        let mut view = Prefixed(self.net.params_mut(), "inner_model");
        view.visit_params("", &mut |name, _| {
            known.insert(name.to_owned());
        });
        let buffers = diffusion_gpt_buffer_suffixes();
        for name in meta.tensors().keys() {
            let is_buffer = buffers.iter().any(|b| name.ends_with(b));
            if !known.contains(name) && !is_buffer {
                return Err(BesoError::UnexpectedTensor {
                    path: path.to_owned(),
                    name: name.clone(),
                });
            }
        }
        vdd_nn::io::load_safetensors_bytes(path, bytes, &mut view)?;
        Ok(())
    }

    /// Writes the teacher file: weights (without the `inner_model.` prefix) and the
    /// configuration as JSON under [`BESO_CONFIG_KEY`].
    pub fn save(&self, path: &Path) -> Result<(), BesoError> {
        let json = serde_json::to_string(&self.config)
            .map_err(|source| BesoError::Json { what: "teacher config".into(), source })?;
        let meta = BTreeMap::from([(BESO_CONFIG_KEY.to_owned(), json)]);
        vdd_nn::io::save_safetensors(path, self.net.params(), &meta)?;
        Ok(())
    }

    /// Loads a teacher file written by [`BesoTeacher::save`] (`cargo xtask import beso`).
    pub fn load(path: &Path) -> Result<Self, BesoError> {
        let bytes = vdd_core::files::read_bounded(path, vdd_nn::io::MAX_FILE_BYTES)
            .map_err(|source| BesoError::Io { path: path.to_owned(), source })?;
        let (_, meta) = safetensors::SafeTensors::read_metadata(&bytes)
            .map_err(|source| vdd_nn::NnError::Malformed { path: path.to_owned(), source })?;
        let json =
            meta.metadata().as_ref().and_then(|m| m.get(BESO_CONFIG_KEY)).ok_or_else(|| {
                BesoError::MissingKey { path: path.to_owned(), key: BESO_CONFIG_KEY.into() }
            })?;
        let config: BesoTeacherConfig =
            serde_json::from_str(json).map_err(|source| BesoError::Json {
                what: format!("{} metadata `{BESO_CONFIG_KEY}`", path.display()),
                source,
            })?;
        let mut teacher = Self::new(config)?;
        vdd_nn::io::load_safetensors_bytes(path, &bytes, teacher.net.params_mut())?;
        let mut finite = true;
        teacher.net.params().visit_params("", &mut |_, p| {
            finite &= p.value.iter().all(|v| v.is_finite());
        });
        if !finite {
            return Err(BesoError::Core(vdd_core::CoreError::NonFinite {
                what: "teacher weights",
            }));
        }
        Ok(teacher)
    }

    /// Width of a state row: the observation window, then the goals.
    fn state_width(&self) -> usize {
        (self.config.window + self.config.goal_window) * self.config.obs_dim()
    }

    /// The inner network's output `F(x, σ)` on raw inputs (`inner_model(state, x, goal, σ)`),
    /// for windows of any length `t ≤ window`: `states` is `n x (t · obs_dim + goals)`,
    /// `actions` and `out` are `n x (t · action_dim)`.
    pub fn inner(
        &mut self,
        states: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
        sigma: &[f32],
        out: MatMut<'_, f32>,
    ) -> Result<(), BesoError> {
        inner_forward(&mut self.net, &self.config, states, actions, sigma, out)
    }

    /// `GCDenoiser.forward`: `D(a; σ) = c_skip a + c_out F(c_in a, σ)` for each row, on
    /// windows of any length `t ≤ window` (shapes as [`BesoTeacher::inner`]).
    pub fn denoise(
        &mut self,
        states: MatRef<'_, f32>,
        actions: MatRef<'_, f32>,
        sigma: &[f32],
        mut out: MatMut<'_, f32>,
    ) -> Result<(), BesoError> {
        let (n, w) = (actions.nrows(), actions.ncols());
        if sigma.len() != n || sigma.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(BesoError::Core(vdd_core::CoreError::Config(
                "BESO noise levels must be positive and finite, one per row".into(),
            )));
        }
        let p = self.precond;
        self.coef.clear();
        self.coef.extend(sigma.iter().map(|&s| [p.c_skip(s), p.c_out(s), p.c_in(s)]));
        if self.scaled.nrows() != n || self.scaled.ncols() != w {
            self.scaled = Mat::zeros(n, w);
            self.inner = Mat::zeros(n, w);
        }
        for j in 0..w {
            for i in 0..n {
                self.scaled[(i, j)] = actions[(i, j)] * self.coef[i][2];
            }
        }
        let (scaled, inner) = (self.scaled.as_ref(), self.inner.as_mut());
        inner_forward(&mut self.net, &self.config, states, scaled, sigma, inner)?;
        for j in 0..w {
            for i in 0..n {
                let [c_skip, c_out, _] = self.coef[i];
                out[(i, j)] = self.inner[(i, j)] * c_out + actions[(i, j)] * c_skip;
            }
        }
        Ok(())
    }
}

/// The inner network on a state row split into observation window and goals.
fn inner_forward(
    net: &mut Net,
    config: &BesoTeacherConfig,
    states: MatRef<'_, f32>,
    actions: MatRef<'_, f32>,
    sigma: &[f32],
    out: MatMut<'_, f32>,
) -> Result<(), BesoError> {
    let gw = config.goal_window * config.obs_dim();
    let sw = states.ncols().checked_sub(gw).ok_or(vdd_core::CoreError::Shape {
        what: "states",
        expected: format!("at least {gw} columns"),
        got: states.ncols().to_string(),
    })?;
    let goals = (gw > 0).then(|| states.subcols(sw, gw));
    net.forward(states.subcols(0, sw), actions, goals, sigma, out)
}

impl ScoreModel for BesoTeacher {
    fn action_dim(&self) -> usize {
        self.config.window * self.config.action_dim()
    }

    fn state_dim(&self) -> usize {
        self.state_width()
    }

    fn score(
        &mut self,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        noise_levels: &[f32],
        mut out: MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        check_score_args(self, actions, states, noise_levels, out.as_ref())?;
        self.denoise(states, actions, noise_levels, out.as_mut())?;
        for j in 0..actions.ncols() {
            for i in 0..actions.nrows() {
                let s2 = noise_levels[i] * noise_levels[i];
                out[(i, j)] = (out[(i, j)] - actions[(i, j)]) / s2;
            }
        }
        Ok(())
    }

    fn sample_actions(
        &mut self,
        states: MatRef<'_, f32>,
        rng: &mut dyn rand::RngCore,
        mut out: MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        let n = states.nrows();
        vdd_core::check_shape("states", states, n, self.state_width())?;
        vdd_core::check_shape("actions", out.as_ref(), n, ScoreModel::action_dim(self))?;
        let sigmas = self.config.schedule.sigmas(
            self.config.steps,
            self.config.sigma_min,
            self.config.sigma_max,
        )?;
        let smax = self.config.sigma_max;
        let mut x = Mat::from_fn(n, out.ncols(), |_, _| vdd_core::standard_normal(rng) * smax);
        let mut buf = crate::karras::KarrasBuffers::default();
        let sampler = self.config.sampler;
        let mut den =
            |a: MatRef<'_, f32>, s: &[f32], o: MatMut<'_, f32>| self.denoise(states, a, s, o);
        let mut noise = |b: &mut [f32]| vdd_core::fill_standard_normal(rng, b);
        crate::karras::sample(&mut den, sampler, &sigmas, x.as_mut(), &mut noise, &mut buf)?;
        out.copy_from(&x);
        Ok(())
    }

    /// VE levels on `[σ_min, σ_max]`, the range BESO and D3IL draw their training levels from
    /// (unless the agent's `sigma_sample_density` config sets its own `min_value`/`max_value`);
    /// drawn levels are kept as drawn.
    fn noise_process(&self) -> Option<&dyn NoiseProcess> {
        Some(&self.process)
    }

    /// A copy: the score keeps no state between calls beyond scratch buffers.
    fn fork(&self) -> Option<Box<dyn ScoreModel + Send>> {
        Some(Box::new(self.clone()))
    }
}
