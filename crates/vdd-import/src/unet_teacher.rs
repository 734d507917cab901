//! An imported 1-D U-Net diffusion policy (LeRobot or diffusion_policy) as a
//! [`vdd_core::ScoreModel`] and a [`vdd_core::Policy`].

use faer::{Mat, MatMut, MatRef};
use rand::SeedableRng as _;
use rand_chacha::ChaCha8Rng;
use rand_distr::{Distribution as _, StandardNormal};
use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, NoiseProcess, Policy, ScoreModel, check_score_args};
use vdd_data::features::FeatureMapId;
use vdd_data::{DeploySpec, Windowed};
use vdd_nn::{Param, Parameters, join_name};
use vdd_torch::{ConditionalUnet1d, Unet1dConfig};

use crate::diffusers::{Prediction, Scheduler, SchedulerConfig};
use crate::error::ImportError;
use crate::normalize::{FeatureNorm, FeatureNormSpec};
use crate::options::{ObsMap, Sampler};

/// Rows per U-Net call: bounds the im2col buffers of wide networks.
const ROWS_PER_CALL: usize = 256;

/// Everything about an imported U-Net teacher except its tensors (saved as JSON in the teacher
/// file).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct UnetTeacherSpec {
    /// The package it came from (`lerobot`, `diffusion_policy`).
    pub source: String,
    /// The network.
    pub unet: Unet1dConfig,
    /// The noise process and sampler.
    pub scheduler: SchedulerConfig,
    /// Steps of each predicted action chunk.
    pub horizon: usize,
    /// Observations the policy sees (`n_obs_steps`), oldest first.
    pub n_obs_steps: usize,
    /// Actions of each chunk executed before predicting again.
    pub n_action_steps: usize,
    /// Index in the chunk of the first executed action (LeRobot: `n_obs_steps − 1`;
    /// diffusion_policy: the same with `oa_step_convention`, else `n_obs_steps`).
    pub action_start: usize,
    /// Per-step observation features, concatenated in this order.
    pub obs_features: Vec<FeatureNormSpec>,
    /// The action's normaliser.
    pub action: FeatureNormSpec,
    /// The registered feature map ([`vdd_data::features`]) that turns the environment's raw
    /// observation into the per-step observation the policy was trained on (the identity
    /// unless the training run recorded one; see [`crate::FEATURES_FILE`]).
    #[serde(default = "identity_features")]
    pub features: FeatureMapId,
    /// Where each observation feature comes from in the raw per-step observation (after
    /// [`UnetTeacherSpec::features`]), as the user stated it at import; `None`: the raw
    /// observation is the features concatenated in order.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub obs_map: Option<ObsMap>,
}

fn identity_features() -> FeatureMapId {
    vdd_data::features::IDENTITY.id()
}

impl UnetTeacherSpec {
    /// Checks that the sizes fit together (`file` names the source in errors).
    pub fn validate(&self, file: &str) -> Result<(), ImportError> {
        crate::limits::check_unet(&self.unet, self.horizon, self.n_obs_steps)
            .map_err(|r| r.import(file))?;
        self.unet.validate()?;
        self.scheduler.validate(file)?;
        let obs_dim: usize = self.obs_features.iter().map(|f| f.dim).sum();
        let bad = |k: &str, v: String| Err(ImportError::bad(file, k, v));
        if self.action.dim != self.unet.input_dim {
            return bad(
                "action dim",
                format!("{} (the U-Net has {})", self.action.dim, self.unet.input_dim),
            );
        }
        if self.n_obs_steps == 0 || obs_dim * self.n_obs_steps != self.unet.global_cond_dim {
            return bad(
                "n_obs_steps",
                format!(
                    "{} x obs dim {obs_dim} != global_cond_dim {}",
                    self.n_obs_steps, self.unet.global_cond_dim
                ),
            );
        }
        if self.horizon == 0
            || self.horizon % self.unet.horizon_multiple() != 0
            || self.horizon > 4096
        {
            return bad("horizon", self.horizon.to_string());
        }
        if let Some(m) = &self.obs_map {
            m.check_features(&self.obs_features, file)?;
        }
        let map = self.features.resolve().map_err(|e| ImportError::bad(file, "features", e))?;
        map.check_dim(self.raw_obs_dim()).map_err(|e| ImportError::bad(file, "features", e))?;
        if self.n_action_steps == 0 || self.action_start + self.n_action_steps > self.horizon {
            return bad(
                "n_action_steps",
                format!(
                    "{} from {} exceeds horizon {}",
                    self.n_action_steps, self.action_start, self.horizon
                ),
            );
        }
        Ok(())
    }

    /// Width of one step's observation features (the policy's per-step input, all features
    /// of one step concatenated).
    pub fn obs_dim(&self) -> usize {
        self.obs_features.iter().map(|f| f.dim).sum()
    }

    /// Width of one raw observation the teacher acts on: the [`ObsMap`]'s raw width, or
    /// [`UnetTeacherSpec::obs_dim`] without a map.
    pub fn raw_obs_dim(&self) -> usize {
        self.obs_map.as_ref().map_or_else(|| self.obs_dim(), ObsMap::raw_dim)
    }

    /// The sampler the policy acts with.
    pub fn sampler(&self) -> Sampler {
        Sampler::of(&self.scheduler)
    }
}

/// An imported 1-D U-Net diffusion policy.
///
/// * As a [`ScoreModel`] (noise convention `t`, VP), it works in the teacher's **normalised**
///   space: the action is the whole chunk (`horizon × action_dim`, step-major), the state the
///   normalised observation window (`n_obs_steps × obs_dim`, oldest first) — exactly the
///   U-Net's global conditioning. Level `t ∈ [1, N]` is diffusers' timestep `t − 1`
///   (fractional `t` feeds the step embedding a fractional step and interpolates `ᾱ`
///   log-linearly); the score is `−ε̂/√(1 − ᾱ)` for ε-prediction and `(√ᾱ x̂₀ − a)/(1 − ᾱ)` for
///   sample prediction. [`UnetTeacher::scheduler`]`.time_for_sigma` maps a VE `σ` to `t`.
/// * As a [`Policy`], it takes the raw observation window and returns the executed raw actions
///   (`n_action_steps × action_dim`) of one chunk sampled with the package's own sampler;
///   [`UnetTeacher::into_policy`] wraps it to act step by step on raw observations, as the
///   package's `select_action` does.
#[derive(Debug, Clone)]
pub struct UnetTeacher {
    spec: UnetTeacherSpec,
    unet: ConditionalUnet1d,
    scheduler: Scheduler,
    obs_norms: Vec<FeatureNorm>,
    action_norm: FeatureNorm,
    rng: ChaCha8Rng,
    x: Mat<f32>,
    steps: Vec<f32>,
    sample: Vec<f32>,
    model_out: Vec<f32>,
    scratch: Vec<f32>,
}

impl UnetTeacher {
    /// A teacher of this spec with zero weights and identity-shaped normalisers (load its
    /// tensors with [`vdd_nn::io::load_safetensors`]).
    pub fn new(spec: UnetTeacherSpec) -> Result<Self, ImportError> {
        spec.validate("teacher spec")?;
        let unet = ConditionalUnet1d::new(spec.unet.clone())?;
        let scheduler = Scheduler::new(spec.scheduler.clone())?;
        Ok(Self {
            obs_norms: spec.obs_features.iter().map(FeatureNorm::from_spec).collect(),
            action_norm: FeatureNorm::from_spec(&spec.action),
            unet,
            scheduler,
            spec,
            rng: ChaCha8Rng::seed_from_u64(0),
            x: Mat::new(),
            steps: Vec::new(),
            sample: Vec::new(),
            model_out: Vec::new(),
            scratch: Vec::new(),
        })
    }

    /// Replaces the normalisers (checked against the spec's features).
    pub fn set_normalizers(
        &mut self,
        obs: Vec<FeatureNorm>,
        action: FeatureNorm,
    ) -> Result<(), ImportError> {
        let specs: Vec<_> = obs.iter().map(FeatureNorm::spec).collect();
        if specs != self.spec.obs_features || action.spec() != self.spec.action {
            return Err(ImportError::bad(
                "teacher",
                "normalizers",
                "features differ from the spec",
            ));
        }
        self.obs_norms = obs;
        self.action_norm = action;
        Ok(())
    }

    /// Re-checks the normalisers' statistics after loading them from `file`.
    pub fn check_normalizers(&self, file: &str) -> Result<(), ImportError> {
        for n in self.obs_norms.iter().chain(std::iter::once(&self.action_norm)) {
            FeatureNorm::new(&n.name, n.kind, n.a.value.clone(), n.b.value.clone(), n.eps)
                .map_err(|e| ImportError::bad(file, format!("normalizer {}", n.name), e))?;
        }
        Ok(())
    }

    /// Acts with `sampler` from now on (the noise process and the score are unchanged; saving
    /// the teacher records it). Errors naming the sampler for a step count outside
    /// `1..=num_train_timesteps`.
    ///
    /// ```
    /// # let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/import/lerobot_unet_ddpm");
    /// use vdd_import::Sampler;
    /// let teacher = vdd_import::import_lerobot(&dir)?.with_sampler(Sampler::Ddim { steps: 10 })?;
    /// assert_eq!(teacher.spec().sampler(), Sampler::Ddim { steps: 10 });
    /// assert_eq!(teacher.scheduler().timesteps().len(), 10);
    /// # Ok::<(), vdd_import::ImportError>(())
    /// ```
    pub fn set_sampler(&mut self, sampler: Sampler) -> Result<(), ImportError> {
        let config = sampler.apply(&self.spec.scheduler)?;
        self.scheduler = Scheduler::new(config.clone())?;
        self.spec.scheduler = config;
        Ok(())
    }

    /// [`UnetTeacher::set_sampler`], by value.
    pub fn with_sampler(mut self, sampler: Sampler) -> Result<Self, ImportError> {
        self.set_sampler(sampler)?;
        Ok(self)
    }

    /// The spec.
    pub fn spec(&self) -> &UnetTeacherSpec {
        &self.spec
    }

    /// The observation features' normalisers, in the spec's order.
    pub fn obs_normalizers(&self) -> &[FeatureNorm] {
        &self.obs_norms
    }

    /// The action's normaliser.
    pub fn action_normalizer(&self) -> &FeatureNorm {
        &self.action_norm
    }

    /// The noise process.
    pub fn scheduler(&self) -> &Scheduler {
        &self.scheduler
    }

    /// The network.
    pub fn unet_mut(&mut self) -> &mut ConditionalUnet1d {
        &mut self.unet
    }

    /// How the package acts with it: the spec's feature map, a window of `n_obs_steps`, chunks
    /// of the `n_action_steps` executed actions (the [`Policy`] returns only those).
    pub fn deploy_spec(&self) -> DeploySpec {
        DeploySpec {
            features: self.spec.features.clone(),
            obs_window: self.spec.n_obs_steps,
            action_chunk: self.spec.n_action_steps,
            execute_steps: self.spec.n_action_steps,
            ..DeploySpec::identity()
        }
    }

    /// The teacher acting step by step on raw observations (history and chunk execution as the
    /// package's `select_action`).
    pub fn into_policy(self) -> Result<Windowed<Self>, ImportError> {
        let spec = self.deploy_spec();
        Windowed::new(self, spec).map_err(|e| ImportError::bad("teacher", "deploy spec", e))
    }

    /// The policy's observation window (`n_obs_steps × obs_dim`) of a raw window
    /// (`n_obs_steps × raw_obs_dim`) through the spec's [`ObsMap`] (a copy without one).
    pub fn map_obs_window(&self, raw: &[f32], out: &mut Vec<f32>) {
        match &self.spec.obs_map {
            None => {
                out.clear();
                out.extend_from_slice(raw);
            }
            Some(m) => {
                out.clear();
                let mut step = Vec::with_capacity(m.mapped_dim());
                for chunk in raw.chunks_exact(m.raw_dim()) {
                    m.gather(chunk, &mut step);
                    out.extend_from_slice(&step);
                }
            }
        }
    }

    /// Normalises an observation window (`n_obs_steps × obs_dim`, one row, features in the
    /// spec's order) in place.
    pub fn normalize_obs_window(&self, window: &mut [f32]) {
        let d = self.spec.obs_dim();
        for step in window.chunks_exact_mut(d) {
            let mut at = 0;
            for f in &self.obs_norms {
                f.normalize(&mut step[at..at + f.dim()]);
                at += f.dim();
            }
        }
    }

    /// The U-Net's raw output (ε̂ or x̂₀, normalised) for `actions` (`n × horizon·action_dim`)
    /// at diffusers timesteps `timesteps` with normalised global conditioning `cond`
    /// (`n × global_cond_dim`), into `out`.
    pub fn predict(
        &mut self,
        actions: MatRef<'_, f32>,
        timesteps: &[f32],
        cond: MatRef<'_, f32>,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), ImportError> {
        let (h, a) = (self.spec.horizon, self.spec.unet.input_dim);
        let n = actions.nrows();
        if actions.ncols() != h * a || timesteps.len() != n || cond.nrows() != n || out.nrows() != n
        {
            return Err(ImportError::bad("predict", "shapes", format!("{n} rows")));
        }
        let mut start = 0;
        while start < n {
            let m = ROWS_PER_CALL.min(n - start);
            ensure(&mut self.x, m * h, a);
            for r in 0..m {
                for t in 0..h {
                    for d in 0..a {
                        self.x[(r * h + t, d)] = actions[(start + r, t * a + d)];
                    }
                }
            }
            let y = self.unet.forward(
                self.x.as_ref(),
                &timesteps[start..start + m],
                cond.subrows(start, m),
            )?;
            for r in 0..m {
                for t in 0..h {
                    for d in 0..a {
                        out[(start + r, t * a + d)] = y[(r * h + t, d)];
                    }
                }
            }
            start += m;
        }
        Ok(())
    }

    /// Runs the package's sampler from `initial` noise (`n × horizon·action_dim`, rows
    /// step-major) with normalised conditioning `cond`, drawing each DDPM step's variance noise
    /// (`n · horizon · action_dim` values, row-major, as `torch.randn(n, horizon, action_dim)`)
    /// from `noise`. Writes the normalised chunks into `out`.
    pub fn sample_with_noise(
        &mut self,
        cond: MatRef<'_, f32>,
        initial: MatRef<'_, f32>,
        noise: &mut dyn FnMut(&mut [f32]),
        mut out: MatMut<'_, f32>,
    ) -> Result<(), ImportError> {
        let n = initial.nrows();
        let w = self.spec.horizon * self.spec.unet.input_dim;
        if initial.ncols() != w || out.nrows() != n || out.ncols() != w || cond.nrows() != n {
            return Err(ImportError::bad("sample", "shapes", format!("{n} rows")));
        }
        self.sample.clear();
        for r in 0..n {
            self.sample.extend((0..w).map(|j| initial[(r, j)]));
        }
        self.model_out.resize(n * w, 0.0);
        let timesteps = self.scheduler.timesteps().to_vec();
        let mut pred = Mat::<f32>::zeros(n, w);
        for &t in &timesteps {
            self.steps.clear();
            self.steps.resize(n, t as f32);
            let x = MatRef::from_row_major_slice(&self.sample, n, w).to_owned();
            let steps = std::mem::take(&mut self.steps);
            let res = self.predict(x.as_ref(), &steps, cond, pred.as_mut());
            self.steps = steps;
            res?;
            for r in 0..n {
                for j in 0..w {
                    self.model_out[r * w + j] = pred[(r, j)];
                }
            }
            self.scheduler.step(&self.model_out, t, &mut self.sample, noise, &mut self.scratch);
        }
        for r in 0..n {
            for j in 0..w {
                out[(r, j)] = self.sample[r * w + j];
            }
        }
        Ok(())
    }

    /// The [`Policy`] step with given noise: maps (with the spec's [`ObsMap`], if any) and
    /// normalises the raw observation windows `obs` (`n × n_obs_steps·raw_obs_dim`), samples from `initial` with `noise` as
    /// [`UnetTeacher::sample_with_noise`], and writes the executed raw actions
    /// (`n × n_action_steps·action_dim`).
    pub fn act_batch_with_noise(
        &mut self,
        obs: MatRef<'_, f32>,
        initial: MatRef<'_, f32>,
        noise: &mut dyn FnMut(&mut [f32]),
        mut actions: MatMut<'_, f32>,
    ) -> Result<(), ImportError> {
        let n = obs.nrows();
        vdd_core::check_shape("observations", obs, n, Policy::obs_dim(self))?;
        vdd_core::check_shape("actions", actions.as_mut().as_ref(), n, Policy::action_dim(self))?;
        let mut cond = Mat::<f32>::zeros(n, self.spec.unet.global_cond_dim);
        let mut raw = vec![0.0f32; obs.ncols()];
        let mut row = Vec::with_capacity(cond.ncols());
        for r in 0..n {
            for (j, v) in raw.iter_mut().enumerate() {
                *v = obs[(r, j)];
            }
            if raw.iter().any(|v| !v.is_finite()) {
                return Err(CoreError::NonFinite { what: "observation" }.into());
            }
            self.map_obs_window(&raw, &mut row);
            self.normalize_obs_window(&mut row);
            for (j, v) in row.iter().enumerate() {
                cond[(r, j)] = *v;
            }
        }
        let a = self.spec.unet.input_dim;
        let mut chunk = Mat::<f32>::zeros(n, self.spec.horizon * a);
        self.sample_with_noise(cond.as_ref(), initial, noise, chunk.as_mut())?;
        let mut step = vec![0.0f32; a];
        for r in 0..n {
            for k in 0..self.spec.n_action_steps {
                let t = self.spec.action_start + k;
                for d in 0..a {
                    step[d] = chunk[(r, t * a + d)];
                }
                self.action_norm.unnormalize(&mut step);
                for d in 0..a {
                    actions[(r, k * a + d)] = step[d];
                }
            }
        }
        Ok(())
    }

    /// Samples normalised chunks for normalised conditioning rows, noise from `rng`.
    fn sample_rng(
        &mut self,
        cond: MatRef<'_, f32>,
        rng: &mut dyn rand::RngCore,
        out: MatMut<'_, f32>,
    ) -> Result<(), ImportError> {
        let w = self.spec.horizon * self.spec.unet.input_dim;
        let n = cond.nrows();
        let initial = Mat::from_fn(n, w, |_, _| StandardNormal.sample(&mut *rng));
        let mut draw =
            |buf: &mut [f32]| buf.iter_mut().for_each(|v| *v = StandardNormal.sample(&mut *rng));
        self.sample_with_noise(cond, initial.as_ref(), &mut draw, out)
    }
}

fn ensure(m: &mut Mat<f32>, r: usize, c: usize) {
    if m.nrows() != r || m.ncols() != c {
        *m = Mat::zeros(r, c);
    }
}

impl ScoreModel for UnetTeacher {
    fn action_dim(&self) -> usize {
        self.spec.horizon * self.spec.unet.input_dim
    }

    fn state_dim(&self) -> usize {
        self.spec.unet.global_cond_dim
    }

    /// diffusers' timesteps ([`Scheduler`]'s [`NoiseProcess`]): time `t ∈ [1, N]`, drawn
    /// levels rounded onto the trained grid, queries outside it clamped.
    fn noise_process(&self) -> Option<&dyn NoiseProcess> {
        Some(&self.scheduler)
    }

    fn score(
        &mut self,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        noise_levels: &[f32],
        mut out: MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        check_score_args(self, actions, states, noise_levels, out.as_mut().as_ref())?;
        let n_train = self.spec.scheduler.num_train_timesteps as f32;
        if noise_levels.iter().any(|t| !t.is_finite()) {
            return Err(CoreError::NonFinite { what: "noise levels" });
        }
        let times: Vec<f32> = noise_levels.iter().map(|t| t.clamp(1.0, n_train)).collect();
        let steps: Vec<f32> = times.iter().map(|t| t - 1.0).collect();
        self.predict(actions, &steps, states, out.as_mut())?;
        let eps = self.spec.scheduler.prediction == Prediction::Epsilon;
        for (i, &t) in times.iter().enumerate() {
            let form = NoiseProcess::denoiser_form(&self.scheduler, t);
            let sd = form.variance.sqrt();
            for j in 0..out.ncols() {
                let p = out[(i, j)];
                out[(i, j)] = if eps { -p / sd } else { form.score(actions[(i, j)], p) };
            }
        }
        Ok(())
    }

    fn sample_actions(
        &mut self,
        states: MatRef<'_, f32>,
        rng: &mut dyn rand::RngCore,
        out: MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        Ok(self.sample_rng(states, rng, out)?)
    }

    /// A copy: the score uses neither the policy's random stream nor state kept between calls.
    fn fork(&self) -> Option<Box<dyn ScoreModel + Send>> {
        Some(Box::new(self.clone()))
    }
}

impl Policy for UnetTeacher {
    fn obs_dim(&self) -> usize {
        self.spec.n_obs_steps * self.spec.raw_obs_dim()
    }

    fn action_dim(&self) -> usize {
        self.spec.n_action_steps * self.spec.unet.input_dim
    }

    fn seed(&mut self, seed: u64) {
        self.rng = ChaCha8Rng::seed_from_u64(seed);
    }

    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
        let o = MatRef::from_row_major_slice(obs, 1, obs.len());
        let a = MatMut::from_row_major_slice_mut(action, 1, action.len());
        self.act_batch(o, a)
    }

    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        actions: MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        let w = self.spec.horizon * self.spec.unet.input_dim;
        let mut rng = self.rng.clone();
        let initial = Mat::from_fn(obs.nrows(), w, |_, _| StandardNormal.sample(&mut rng));
        let mut draw =
            |buf: &mut [f32]| buf.iter_mut().for_each(|v| *v = StandardNormal.sample(&mut rng));
        let res = self.act_batch_with_noise(obs, initial.as_ref(), &mut draw, actions);
        self.rng = rng;
        Ok(res?)
    }
}

/// The teacher's tensors under their teacher-file names: `unet.*`, `norm.obs.<i>.{a,b}`,
/// `norm.action.{a,b}`.
impl Parameters for UnetTeacher {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        self.unet.visit_params(&join_name(prefix, "unet"), f);
        for (i, n) in self.obs_norms.iter().enumerate() {
            n.visit_params(&join_name(prefix, &format!("norm.obs.{i}")), f);
        }
        self.action_norm.visit_params(&join_name(prefix, "norm.action"), f);
    }

    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        self.unet.visit_params_mut(&join_name(prefix, "unet"), f);
        for (i, n) in self.obs_norms.iter_mut().enumerate() {
            n.visit_params_mut(&join_name(prefix, &format!("norm.obs.{i}")), f);
        }
        self.action_norm.visit_params_mut(&join_name(prefix, "norm.action"), f);
    }
}
