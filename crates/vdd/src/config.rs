//! Configuration of a VDD run.

use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, NoiseSchedule};
use vdd_nn::{AdamConfig, LrSchedule};

/// How the per-expert objectives are weighted in the experts' loss
/// `L = −mean_s Σ_z w_z(s) J_z(s)`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum ExpertWeighting {
    /// `w_z(s) = q(z|s)`, detached (the official code's choice).
    #[default]
    Gating,
    /// `w_z(s) = 1/Z`.
    Uniform,
}

/// Hyper-parameters of [`crate::Vdd`]. [`VddConfig::toy`] gives the paper's toy defaults.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct VddConfig {
    /// Number of EM iterations.
    pub iterations: usize,
    /// States per expert step.
    pub batch_size: usize,
    /// Reparameterised samples per (state, expert), `V`.
    pub vi_samples: usize,
    /// Teacher noise levels used in the expert step (in the teacher's convention).
    pub noise: NoiseSchedule,
    /// With an [`NoiseSchedule::Annealed`] schedule: the fraction of the run over which the
    /// level goes from `start` to `end`; it then stays at `end`. `None`: the whole run.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_anneal_until: Option<f32>,
    /// Weighting of the experts' objectives.
    pub expert_weighting: ExpertWeighting,
    /// Expert updates per iteration (all against the same E-step snapshot).
    pub expert_steps_per_iter: usize,
    /// Gating updates per iteration (ignored for uniform gating).
    pub gating_steps_per_iter: usize,
    /// (state, action) pairs per gating step.
    pub gating_batch_size: usize,
    /// Stop updating the gating from this iteration on.
    pub freeze_gating_after: Option<usize>,
    /// Adam for the experts.
    pub expert_optimizer: AdamConfig,
    /// Learning-rate schedule for the experts, over the run's expert steps
    /// (`iterations · expert_steps_per_iter`).
    pub expert_lr_schedule: LrSchedule,
    /// Adam for the gating.
    pub gating_optimizer: AdamConfig,
    /// Learning-rate schedule for the gating, over the run's gating steps
    /// (`gating_steps_per_iter` per iteration until `freeze_gating_after`, or `iterations`).
    pub gating_lr_schedule: LrSchedule,
    /// Clip each network's gradient to this global norm.
    pub max_grad_norm: Option<f32>,
    /// Decay of an exponential moving average of the student's parameters, updated after
    /// every iteration; [`crate::Vdd::into_student`] then returns the averaged student.
    /// `None` (the default) returns the last iterate.
    #[serde(default)]
    pub student_ema: Option<f32>,
    /// Root seed of every random draw of the run, including the student's initialisation
    /// when the trainer builds the student ([`crate::Vdd::from_config`]).
    pub seed: u64,
}

impl VddConfig {
    /// The paper's toy defaults: 600 iterations, 32 states, 64 samples per expert, Adam
    /// `5e-4` decaying linearly to 0 over the run (whatever its length), exact score
    /// (`σ = 0`), gating-weighted objectives.
    pub fn toy() -> Self {
        Self {
            iterations: 600,
            batch_size: 32,
            vi_samples: 64,
            noise: NoiseSchedule::Fixed { level: 0.0 },
            noise_anneal_until: None,
            expert_weighting: ExpertWeighting::Gating,
            expert_steps_per_iter: 1,
            gating_steps_per_iter: 1,
            gating_batch_size: 256,
            freeze_gating_after: None,
            expert_optimizer: AdamConfig { lr: 5e-4, ..AdamConfig::default() },
            expert_lr_schedule: LrSchedule::LinearDecay { final_factor: 0.0 },
            gating_optimizer: AdamConfig { lr: 5e-4, ..AdamConfig::default() },
            gating_lr_schedule: LrSchedule::LinearDecay { final_factor: 0.0 },
            max_grad_norm: None,
            student_ema: None,
            seed: 0,
        }
    }

    /// Training progress in `[0, 1]` at which the noise schedule is read at `progress`
    /// (the run's progress, rescaled by [`VddConfig::noise_anneal_until`]).
    pub fn noise_progress(&self, progress: f32) -> f32 {
        match self.noise_anneal_until {
            Some(f) => (progress / f).min(1.0),
            None => progress,
        }
    }

    /// Expert optimiser steps of the whole run, the length of `expert_lr_schedule`.
    pub fn expert_steps(&self) -> u64 {
        (self.iterations * self.expert_steps_per_iter) as u64
    }

    /// Gating optimiser steps of the whole run (until `freeze_gating_after`), the length of
    /// `gating_lr_schedule`.
    pub fn gating_steps(&self) -> u64 {
        let it = self.iterations as u64;
        let g_it = self.freeze_gating_after.map_or(it, |f| (f as u64).min(it));
        g_it * self.gating_steps_per_iter as u64
    }

    /// Checks ranges.
    pub fn validate(&self) -> Result<(), CoreError> {
        let positive = [
            ("iterations", self.iterations),
            ("batch_size", self.batch_size),
            ("vi_samples", self.vi_samples),
            ("expert_steps_per_iter", self.expert_steps_per_iter),
            ("gating_batch_size", self.gating_batch_size),
        ];
        for (name, v) in positive {
            if v == 0 {
                return Err(CoreError::Config(format!("{name} must be positive")));
            }
        }
        for (name, opt) in [("expert", &self.expert_optimizer), ("gating", &self.gating_optimizer)]
        {
            if !(opt.lr.is_finite() && opt.lr >= 0.0) {
                return Err(CoreError::Config(format!("{name} learning rate must be >= 0")));
            }
        }
        if let Some(m) = self.max_grad_norm {
            if !(m.is_finite() && m > 0.0) {
                return Err(CoreError::Config("max_grad_norm must be positive".into()));
            }
        }
        if let Some(f) = self.noise_anneal_until {
            if !(f > 0.0 && f <= 1.0) {
                return Err(CoreError::Config(format!(
                    "noise_anneal_until must be in (0, 1], got {f}"
                )));
            }
        }
        if let Some(d) = self.student_ema {
            if !(0.0..1.0).contains(&d) {
                return Err(CoreError::Config(format!("student_ema must be in [0, 1), got {d}")));
            }
        }
        self.noise.validate()
    }
}

impl Default for VddConfig {
    fn default() -> Self {
        Self::toy()
    }
}
