//! [`ImportedTeacher`]: any teacher a teacher file holds, as one `ScoreModel` and `Policy`.

use faer::{MatMut, MatRef};
use vdd_core::{DenoiserForm, NoiseConvention, NoiseSchedule, Policy, ScoreModel};

use crate::options::Sampler;
use crate::unet_teacher::UnetTeacher;

/// A teacher loaded from a teacher file ([`crate::load_teacher`]). As a [`Policy`] it acts on
/// the raw observation window and returns the executed chunk (see each kind's docs; wrap it
/// with its `deploy_spec` in a [`vdd_data::Windowed`] to act step by step).
#[derive(Debug, Clone)]
pub enum ImportedTeacher {
    /// A LeRobot / diffusion_policy 1-D U-Net.
    Unet1d(Box<UnetTeacher>),
}

impl ImportedTeacher {
    /// How the teacher's package acts with it.
    pub fn deploy_spec(&self) -> vdd_data::DeploySpec {
        match self {
            Self::Unet1d(t) => t.deploy_spec(),
        }
    }

    /// The teacher acting step by step on raw observations.
    pub fn into_policy(self) -> Result<vdd_data::Windowed<Self>, crate::ImportError> {
        let spec = self.deploy_spec();
        vdd_data::Windowed::new(self, spec)
            .map_err(|e| crate::ImportError::bad("teacher", "deploy spec", e))
    }

    /// The sampler the teacher acts with.
    pub fn sampler(&self) -> Sampler {
        match self {
            Self::Unet1d(t) => t.spec().sampler(),
        }
    }

    /// Acts with `sampler` from now on ([`UnetTeacher::set_sampler`]): chosen when running,
    /// not by editing the package's files.
    ///
    /// ```no_run
    /// use vdd_import::Sampler;
    /// let mut teacher = vdd_import::load_teacher("teacher.safetensors".as_ref())?;
    /// teacher.set_sampler(Sampler::Ddim { steps: 10 })?; // rollouts
    /// teacher.set_sampler(Sampler::Ddpm { steps: None })?; // the trained schedule
    /// # Ok::<(), vdd_import::ImportError>(())
    /// ```
    pub fn set_sampler(&mut self, sampler: Sampler) -> Result<(), crate::ImportError> {
        match self {
            Self::Unet1d(t) => t.set_sampler(sampler),
        }
    }

    fn score_model(&mut self) -> &mut dyn ScoreModel {
        match self {
            Self::Unet1d(t) => t.as_mut(),
        }
    }

    fn score_model_ref(&self) -> &dyn ScoreModel {
        match self {
            Self::Unet1d(t) => t.as_ref(),
        }
    }

    fn policy(&mut self) -> &mut dyn Policy {
        match self {
            Self::Unet1d(t) => t.as_mut(),
        }
    }

    fn policy_ref(&self) -> &dyn Policy {
        match self {
            Self::Unet1d(t) => t.as_ref(),
        }
    }
}

impl ScoreModel for ImportedTeacher {
    fn action_dim(&self) -> usize {
        self.score_model_ref().action_dim()
    }
    fn state_dim(&self) -> usize {
        self.score_model_ref().state_dim()
    }
    fn noise_process(&self) -> Option<&dyn vdd_core::NoiseProcess> {
        self.score_model_ref().noise_process()
    }
    fn noise_convention(&self) -> NoiseConvention {
        self.score_model_ref().noise_convention()
    }
    fn score(
        &mut self,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        noise_levels: &[f32],
        out: MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        self.score_model().score(actions, states, noise_levels, out)
    }
    fn sample_actions(
        &mut self,
        states: MatRef<'_, f32>,
        rng: &mut dyn rand::RngCore,
        out: MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        self.score_model().sample_actions(states, rng, out)
    }
    fn draw_noise_levels(
        &self,
        schedule: &NoiseSchedule,
        progress: f32,
        rng: &mut dyn rand::RngCore,
        out: &mut [f32],
    ) {
        self.score_model_ref().draw_noise_levels(schedule, progress, rng, out)
    }
    fn denoiser_form(&self, level: f32) -> Option<DenoiserForm> {
        self.score_model_ref().denoiser_form(level)
    }
    fn noise_range(&self) -> Option<(f32, f32)> {
        self.score_model_ref().noise_range()
    }
    fn fork(&self) -> Option<Box<dyn ScoreModel + Send>> {
        self.score_model_ref().fork()
    }
}

impl Policy for ImportedTeacher {
    fn obs_dim(&self) -> usize {
        self.policy_ref().obs_dim()
    }
    fn action_dim(&self) -> usize {
        self.policy_ref().action_dim()
    }
    fn reset(&mut self) {
        self.policy().reset()
    }
    fn seed(&mut self, seed: u64) {
        self.policy().seed(seed)
    }
    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
        self.policy().act_into(obs, action)
    }
    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        actions: MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        self.policy().act_batch(obs, actions)
    }
}
