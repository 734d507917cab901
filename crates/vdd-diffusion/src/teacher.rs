//! [`DiffusionTeacher`]: either learned teacher behind one type, e.g. for recipes that pick the
//! teacher by name or load whichever a checkpoint holds.

use std::path::Path;

use faer::{MatMut, MatRef};
use rand::RngCore;
use serde::{Deserialize, Serialize};
use vdd_core::{
    Affine, CoreError, DenoiserForm, NoiseConvention, NoiseSchedule, Policy, ScoreModel,
};

use crate::beso::Beso;
use crate::common::{KIND_KEY, format_err};
use crate::ddpm::Ddpm;
use crate::error::Result;

/// Which learned teacher.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum TeacherKind {
    /// [`Ddpm`] (VP).
    Ddpm,
    /// [`Beso`] (VE / EDM).
    Beso,
}

impl std::str::FromStr for TeacherKind {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "ddpm" => Ok(TeacherKind::Ddpm),
            "beso" => Ok(TeacherKind::Beso),
            other => Err(format!("unknown teacher `{other}` (expected ddpm or beso)")),
        }
    }
}

/// A learned diffusion teacher of either kind; implements [`ScoreModel`] and [`Policy`] by
/// delegation.
///
/// ```
/// use faer::Mat;
/// use vdd_core::{Affine, ScoreModel};
/// use vdd_diffusion::{Beso, BesoConfig, DiffusionTeacher, TeacherKind};
/// let beso = Beso::new(&BesoConfig::default(), Affine::identity(1), Affine::identity(2), 0).unwrap();
/// let dir = std::env::temp_dir().join(format!("vdd-diffusion-doc-{}", std::process::id()));
/// std::fs::create_dir_all(&dir).unwrap();
/// let path = dir.join("teacher.safetensors");
/// beso.save(&path).unwrap();
/// let loaded = DiffusionTeacher::load(&path, 0).unwrap();
/// assert_eq!(loaded.kind(), TeacherKind::Beso);
/// assert_eq!(loaded.action_dim(), 2);
/// # std::fs::remove_dir_all(&dir).unwrap();
/// ```
#[derive(Debug, Clone)]
pub enum DiffusionTeacher {
    /// A DDPM teacher.
    Ddpm(Ddpm),
    /// A BESO teacher.
    Beso(Beso),
}

macro_rules! delegate {
    ($self:expr, $t:ident => $e:expr) => {
        match $self {
            DiffusionTeacher::Ddpm($t) => $e,
            DiffusionTeacher::Beso($t) => $e,
        }
    };
}

impl DiffusionTeacher {
    /// Loads whichever teacher the checkpoint holds.
    pub fn load(path: &Path, seed: u64) -> Result<Self> {
        let meta = vdd_nn::io::read_metadata(path)?;
        match meta.get(KIND_KEY).map(String::as_str) {
            Some(k) if k == Ddpm::kind() => Ok(Self::Ddpm(Ddpm::load(path, seed)?)),
            Some(k) if k == Beso::kind() => Ok(Self::Beso(Beso::load(path, seed)?)),
            Some(k) => Err(format_err(path, format!("unknown teacher kind `{k}`"))),
            None => Err(format_err(path, "not a vdd-diffusion teacher (no kind metadata)")),
        }
    }

    /// Dimension of one (flattened) action.
    pub fn action_dim(&self) -> usize {
        delegate!(self, t => t.action_dim())
    }

    /// Dimension of one state / observation.
    pub fn state_dim(&self) -> usize {
        delegate!(self, t => t.state_dim())
    }

    /// Which teacher this is.
    pub fn kind(&self) -> TeacherKind {
        match self {
            DiffusionTeacher::Ddpm(_) => TeacherKind::Ddpm,
            DiffusionTeacher::Beso(_) => TeacherKind::Beso,
        }
    }

    /// Saves the teacher (see [`Ddpm::save`], [`Beso::save`]).
    pub fn save(&self, path: &Path) -> Result<()> {
        delegate!(self, t => t.save(path))
    }

    /// The `(state, action)` normalisers of the score model's space.
    pub fn normalizers(&self) -> (&Affine, &Affine) {
        delegate!(self, t => t.normalizers())
    }

    /// Sets the number of sampling steps, keeping the sampler (`1 ≤ steps`, and `≤ N` for DDPM).
    pub fn set_steps(&mut self, steps: usize) -> Result<()> {
        delegate!(self, t => t.set_sampler(t.sampler().0, steps))
    }

    /// The current number of sampling steps.
    pub fn steps(&self) -> usize {
        delegate!(self, t => t.sampler().1)
    }

    /// How the teacher acts on raw observations (see [`Ddpm::deploy_spec`]): saved with it.
    pub fn deploy_spec(&self) -> &vdd_data::DeploySpec {
        delegate!(self, t => t.deploy_spec())
    }

    /// Sets the deployment spec, checked against the teacher's dimensions (see
    /// [`Ddpm::set_deploy_spec`]).
    pub fn set_deploy_spec(&mut self, spec: vdd_data::DeploySpec) -> Result<()> {
        delegate!(self, t => t.set_deploy_spec(spec))
    }

    /// The teacher as a policy on raw observations, by its [`DiffusionTeacher::deploy_spec`].
    pub fn into_policy(self) -> Result<vdd_data::Windowed<Self>> {
        let spec = self.deploy_spec().clone();
        Ok(vdd_data::Windowed::new(self, spec)?)
    }

    /// A saved teacher (any kind) as a policy on raw observations, through the deployment
    /// spec saved with it; its sampling stream is seeded with `seed`.
    ///
    /// ```no_run
    /// use vdd_core::Policy;
    /// let mut policy = vdd_diffusion::DiffusionTeacher::load_policy("beso-s0.safetensors".as_ref(), 0)?;
    /// let action = policy.act(&[0.5, 0.1, 0.5, 0.1])?;
    /// # Ok::<(), Box<dyn std::error::Error>>(())
    /// ```
    pub fn load_policy(path: &Path, seed: u64) -> Result<vdd_data::Windowed<Self>> {
        Self::load(path, seed)?.into_policy()
    }
}

impl From<Ddpm> for DiffusionTeacher {
    fn from(t: Ddpm) -> Self {
        Self::Ddpm(t)
    }
}

impl From<Beso> for DiffusionTeacher {
    fn from(t: Beso) -> Self {
        Self::Beso(t)
    }
}

impl ScoreModel for DiffusionTeacher {
    fn action_dim(&self) -> usize {
        delegate!(self, t => ScoreModel::action_dim(t))
    }
    fn state_dim(&self) -> usize {
        delegate!(self, t => t.state_dim())
    }
    fn noise_process(&self) -> Option<&dyn vdd_core::NoiseProcess> {
        delegate!(self, t => t.noise_process())
    }
    fn noise_convention(&self) -> NoiseConvention {
        delegate!(self, t => t.noise_convention())
    }
    fn score(
        &mut self,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        noise_levels: &[f32],
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        delegate!(self, t => t.score(actions, states, noise_levels, out))
    }
    fn sample_actions(
        &mut self,
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        delegate!(self, t => t.sample_actions(states, rng, out))
    }
    fn draw_noise_levels(
        &self,
        schedule: &NoiseSchedule,
        progress: f32,
        rng: &mut dyn RngCore,
        out: &mut [f32],
    ) {
        delegate!(self, t => t.draw_noise_levels(schedule, progress, rng, out))
    }
    fn denoiser_form(&self, level: f32) -> Option<DenoiserForm> {
        delegate!(self, t => t.denoiser_form(level))
    }
    fn fork(&self) -> Option<Box<dyn ScoreModel + Send>> {
        delegate!(self, t => t.fork())
    }
    fn noise_range(&self) -> Option<(f32, f32)> {
        delegate!(self, t => t.noise_range())
    }
}

impl Policy for DiffusionTeacher {
    fn obs_dim(&self) -> usize {
        delegate!(self, t => t.obs_dim())
    }
    fn action_dim(&self) -> usize {
        delegate!(self, t => Policy::action_dim(t))
    }
    fn seed(&mut self, seed: u64) {
        delegate!(self, t => t.seed(seed))
    }
    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> Result<(), CoreError> {
        delegate!(self, t => t.act_into(obs, action))
    }
    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        actions: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        delegate!(self, t => t.act_batch(obs, actions))
    }
}
