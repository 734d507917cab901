//! The settings of a consistency distillation ([`ConsistencyConfig`], with its optimisation
//! [`ConsistencyTrainConfig`]) and its reports ([`ConsistencyStep`] per step,
//! [`ConsistencyProgress`] every `log_every` steps).

use serde::{Deserialize, Serialize};
use vdd_core::CoreError;
use vdd_diffusion::{BesoConfig, NetConfig};
use vdd_nn::AdamConfig;

use crate::error::ConsistencyError;
use crate::network::BoundaryPreconditioning;
use crate::teacher::ConsistencyTeacher;

/// The settings of Consistency Distillation ([`crate::cd::CdConfig`] is this type), which the
/// Consistency Trajectory Model shares ([`crate::ctm::CtmConfig::base`]): the student network,
/// the noise levels, sampling and optimisation.
///
/// ```
/// use vdd_consistency::ConsistencyConfig;
/// use vdd_diffusion::BesoConfig;
/// let beso = BesoConfig::default();
/// let config = ConsistencyConfig::for_beso(&beso).with_seed(3);
/// assert!(config.init_from_teacher && config.sigma_max == beso.sigma_max);
/// assert_eq!(config.train.seed, 3);
/// config.validate().unwrap();
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ConsistencyConfig {
    /// The student network `F_θ` (the teacher's architecture to start from its weights).
    pub net: NetConfig,
    /// Start the student from the teacher's network (it must have one of the same
    /// architecture; the paper's choice); otherwise fresh weights from the seed's `"init"`
    /// stream.
    pub init_from_teacher: bool,
    /// `σ_data` of the preconditioning (normalised action space).
    pub sigma_data: f32,
    /// The boundary level `σ_min`, the end of the grid and of sampling.
    pub sigma_min: f32,
    /// The largest level `σ_max`, where sampling starts.
    pub sigma_max: f32,
    /// The Karras grid's `ρ`.
    pub rho: f32,
    /// Number of grid levels `N` (Song et al. use 18 for their EDM teacher).
    pub num_scales: usize,
    /// Sampling steps of the returned policy (1: one-step sampling).
    pub sampling_steps: usize,
    /// Optimisation.
    pub train: ConsistencyTrainConfig,
}

impl Default for ConsistencyConfig {
    /// BESO's default levels (`σ_data = 0.5`, `σ ∈ [0.002, 80]`, `ρ = 7`), `N = 18`, a fresh
    /// student of the default [`NetConfig`], one-step sampling, the default optimisation.
    fn default() -> Self {
        Self {
            net: NetConfig::default(),
            init_from_teacher: false,
            sigma_data: 0.5,
            sigma_min: 0.002,
            sigma_max: 80.0,
            rho: 7.0,
            num_scales: 18,
            sampling_steps: 1,
            train: ConsistencyTrainConfig::default(),
        }
    }
}

impl ConsistencyConfig {
    /// The configuration for distilling a BESO teacher built with `beso`: its network
    /// architecture (the student starts from its weights), `σ_data`, `σ_min`, `σ_max`, `ρ`.
    pub fn for_beso(beso: &BesoConfig) -> Self {
        Self {
            net: beso.net.clone(),
            init_from_teacher: true,
            sigma_data: beso.sigma_data,
            sigma_min: beso.sigma_min,
            sigma_max: beso.sigma_max,
            rho: beso.rho,
            ..Self::default()
        }
    }

    /// [`ConsistencyConfig::for_beso`] for a teacher that is a BESO teacher (starting from its
    /// network when it exposes one), the defaults otherwise.
    pub fn for_teacher<T: ConsistencyTeacher + ?Sized>(teacher: &T) -> Self {
        match teacher.beso_config() {
            Some(beso) => {
                Self { init_from_teacher: teacher.network().is_some(), ..Self::for_beso(beso) }
            }
            None => Self::default(),
        }
    }

    /// The same settings with the root seed of every random draw set to `seed`.
    pub fn with_seed(mut self, seed: u64) -> Self {
        self.train.seed = seed;
        self
    }

    /// When the student starts from the teacher ([`Self::init_from_teacher`]), the same
    /// settings with the teacher's network architecture and levels (`net`, `sigma_data`,
    /// `sigma_min`, `sigma_max`, `rho` of [`Self::for_beso`]), so that a changed teacher needs
    /// no matching change here; otherwise unchanged.
    ///
    /// ```
    /// use vdd_consistency::ConsistencyConfig;
    /// use vdd_diffusion::BesoConfig;
    /// let beso = BesoConfig { sigma_max: 40.0, ..Default::default() };
    /// let c = ConsistencyConfig { init_from_teacher: true, ..Default::default() };
    /// assert_eq!(c.following_teacher(&beso).sigma_max, 40.0);
    /// ```
    pub fn following_teacher(mut self, beso: &BesoConfig) -> Self {
        if self.init_from_teacher {
            let t = Self::for_beso(beso);
            self.net = t.net;
            self.sigma_data = t.sigma_data;
            self.sigma_min = t.sigma_min;
            self.sigma_max = t.sigma_max;
            self.rho = t.rho;
        }
        self
    }

    /// Checks the numbers.
    pub fn validate(&self) -> Result<(), ConsistencyError> {
        self.net.validate()?;
        BoundaryPreconditioning::new(self.sigma_data, self.sigma_min)?;
        if !(self.sigma_max.is_finite() && self.sigma_max > self.sigma_min) {
            return Err(CoreError::Config(format!(
                "need sigma_max > sigma_min, got {} <= {}",
                self.sigma_max, self.sigma_min
            ))
            .into());
        }
        if !(self.rho.is_finite() && self.rho > 0.0) {
            return Err(CoreError::Config(format!("rho must be positive, got {}", self.rho)).into());
        }
        if self.num_scales < 2 {
            return Err(CoreError::Config(format!(
                "num_scales must be >= 2, got {}",
                self.num_scales
            ))
            .into());
        }
        if self.sampling_steps == 0 {
            return Err(CoreError::Config("sampling_steps must be >= 1".into()).into());
        }
        Ok(self.train.validate()?)
    }
}

/// Optimisation settings of a consistency training run.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ConsistencyTrainConfig {
    /// Optimisation steps.
    pub steps: u64,
    /// Minibatch size (rows drawn uniformly with replacement from the data).
    pub batch_size: usize,
    /// Adam's hyper-parameters (`lr` is the initial learning rate).
    pub adam: AdamConfig,
    /// The learning rate decays from `adam.lr` to `final_lr_factor · adam.lr` along a cosine
    /// over the `steps`.
    pub final_lr_factor: f32,
    /// Global gradient-norm clipping threshold (`None`: no clipping).
    pub grad_clip: Option<f32>,
    /// Decay `μ` of the target network `θ⁻ ← μ θ⁻ + (1 − μ) θ` (updated after every step).
    pub target_ema_decay: f32,
    /// Decay of the separate average of the online weights that the returned model samples
    /// with (0: the final online weights).
    pub ema_decay: f32,
    /// Report progress every this many steps (and after the last).
    pub log_every: u64,
    /// Root seed of every random draw of the run (initialisation, minibatches, noise, and the
    /// returned policy's stream).
    pub seed: u64,
}

impl Default for ConsistencyTrainConfig {
    /// 3000 steps of 256 pairs, Adam `2e-4` with a cosine decay to 10%, clipping at norm 1,
    /// target decay 0.95 (Song et al.'s CD setting), evaluation average 0.995 (a half-life of
    /// about 140 steps, so nothing of the initial weights remains after 3000).
    fn default() -> Self {
        Self {
            steps: 3000,
            batch_size: 256,
            adam: AdamConfig { lr: 2e-4, ..AdamConfig::default() },
            final_lr_factor: 0.1,
            grad_clip: Some(1.0),
            target_ema_decay: 0.95,
            ema_decay: 0.995,
            log_every: 500,
            seed: 0,
        }
    }
}

impl ConsistencyTrainConfig {
    /// Checks the numbers.
    pub fn validate(&self) -> Result<(), CoreError> {
        let a = &self.adam;
        let ok = self.steps > 0
            && self.batch_size > 0
            && self.log_every > 0
            && a.lr.is_finite()
            && a.lr > 0.0
            && (0.0..1.0).contains(&a.beta1)
            && (0.0..1.0).contains(&a.beta2)
            && a.eps > 0.0
            && a.weight_decay.is_finite()
            && a.weight_decay >= 0.0
            && (0.0..=1.0).contains(&self.final_lr_factor)
            && (0.0..1.0).contains(&self.target_ema_decay)
            && (0.0..1.0).contains(&self.ema_decay)
            && self.grad_clip.is_none_or(|g| g.is_finite() && g > 0.0);
        if ok {
            Ok(())
        } else {
            Err(CoreError::Config(format!("invalid training configuration {self:?}")))
        }
    }
}

/// A progress report of a consistency training run.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ConsistencyProgress {
    /// Steps done so far.
    pub step: u64,
    /// Total steps.
    pub total_steps: u64,
    /// Mean total loss over the steps since the previous report.
    pub loss: f32,
    /// Mean consistency term (CD's loss, CTM's soft consistency matching).
    pub consistency_loss: f32,
    /// Mean denoising-score-matching term (CTM; 0 for CD).
    pub dsm_loss: f32,
    /// Learning rate of the last step.
    pub lr: f32,
    /// Wall-clock seconds since training started.
    pub elapsed_secs: f64,
}

/// What one optimisation step of a consistency training run did: the report of
/// [`vdd_core::Trainer::step`] for [`crate::CdTrainer`] and [`crate::CtmTrainer`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct ConsistencyStep {
    /// 0-based index of the step.
    pub step: u64,
    /// Total loss before the update.
    pub loss: f32,
    /// Consistency term (CD's loss, CTM's soft consistency matching).
    pub consistency_loss: f32,
    /// Denoising-score-matching term (CTM; 0 for CD).
    pub dsm_loss: f32,
    /// Learning rate of the step.
    pub lr: f32,
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::teacher::ScoreTeacher;
    use vdd_core::Affine;
    use vdd_diffusion::{Beso, DiffusionTeacher, GmmTeacher};

    #[test]
    fn configs_follow_the_teacher_and_reject_bad_numbers() {
        let beso =
            Beso::new(&BesoConfig::default(), Affine::identity(3), Affine::identity(2), 0).unwrap();
        let c = ConsistencyConfig::for_teacher(&beso);
        assert!(c.init_from_teacher);
        assert_eq!(c.net, beso.config().net);
        let wrapped = DiffusionTeacher::from(beso);
        assert_eq!(ConsistencyConfig::for_teacher(&wrapped), c);
        assert!(wrapped.validate().is_ok());
        let gmm = ScoreTeacher::identity(GmmTeacher::circle_toy()).unwrap();
        assert_eq!(ConsistencyConfig::for_teacher(&gmm), ConsistencyConfig::default());
        let ddpm = vdd_diffusion::Ddpm::new(
            &vdd_diffusion::DdpmConfig::default(),
            Affine::identity(1),
            Affine::identity(2),
            0,
        )
        .unwrap();
        assert!(DiffusionTeacher::from(ddpm).validate().is_err());
        let ok = ConsistencyConfig::default();
        for bad in [
            ConsistencyConfig { num_scales: 1, ..ok.clone() },
            ConsistencyConfig { sigma_min: 0.0, ..ok.clone() },
            ConsistencyConfig { sigma_max: 0.001, ..ok.clone() },
            ConsistencyConfig { rho: -1.0, ..ok.clone() },
            ConsistencyConfig { sampling_steps: 0, ..ok.clone() },
        ] {
            assert!(bad.validate().is_err(), "{bad:?}");
        }
        let mut bad = ok.clone();
        bad.train.target_ema_decay = 1.0;
        assert!(bad.validate().is_err());
        let mut bad = ok;
        bad.train.final_lr_factor = 2.0;
        assert!(bad.validate().is_err());
    }
}
