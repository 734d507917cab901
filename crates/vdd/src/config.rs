//! Configuration of a VDD run.

use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, NoiseConvention, NoiseSchedule};
use vdd_moe::MoeConfig;
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

/// Where the expert step takes the teacher's score (vdd-method.md, "Beyond the paper").
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum ScoreAt {
    /// At the student's clean sample, at the drawn noise level (the paper). The expert step's
    /// fixed point is the teacher blurred at that level, `π_σ`.
    #[default]
    CleanSample,
    /// Noise on both sides: at the student's sample noised as the teacher's process noises
    /// actions at that level, against the student's exact noised density
    /// ([`crate::both_sides`]). The fixed point is the teacher itself, whatever the levels.
    NoisedSample,
}

/// States beyond the data for the expert step: a share of each state batch perturbed by
/// Gaussian noise, where the teacher's score labels the student as anywhere else (issue 33,
/// "states beyond the demonstrations"). The gating step keeps the data's states.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct StateNoise {
    /// Fraction of the batch's states perturbed, in `[0, 1]`; each state independently. `0`
    /// turns the perturbation off: the same training, bit for bit, as no `state_noise` (what
    /// `--set vdd.<teacher>.state_noise.share=0` gives a recipe whose default perturbs).
    pub share: f32,
    /// Standard deviation of the perturbation in the student's (normalised) state units,
    /// finite and positive.
    pub std: f32,
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
    /// The unit `noise` is written in, checked against the teacher's
    /// ([`vdd_core::ScoreModel::noise_convention`]) when the run starts: `sigma` (VE σ) or
    /// `time` (VP diffusion time t). `None`: the teacher's, unchecked.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_unit: Option<NoiseConvention>,
    /// With an [`NoiseSchedule::Annealed`] schedule: the fraction of the run over which the
    /// level goes from `start` to `end`; it then stays at `end`. `None`: the whole run.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub noise_anneal_until: Option<f32>,
    /// Where the expert step takes the teacher's score: at the clean sample (the paper, the
    /// default) or with noise on both sides.
    #[serde(default)]
    pub score_at: ScoreAt,
    /// Perturbed states in the expert step's batches (`None`, the default: the data's states
    /// only).
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub state_noise: Option<StateNoise>,
    /// Experts trained at each state of an expert step, `k` (`None`, the default: all `Z`).
    /// With `k < Z` every expert step draws, for each state, `k` distinct experts (a random
    /// permutation of the experts dealt out to the batch's states in turn, so each expert
    /// gets `B·k/Z` states, up to rounding), samples and scores only those `B·k·V` pairs, and
    /// weights their gradients by `Z/k`: an unbiased estimate of the full step at `k/Z` of its
    /// teacher evaluations. `k >= Z` is the full step, bit for bit.
    #[serde(default, skip_serializing_if = "Option::is_none")]
    pub experts_per_state: Option<usize>,
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
    /// Chunks the state batch of an expert step is split into (at most [`MAX_CHUNKS`]; more
    /// than `batch_size` count as `batch_size`): each chunk's forward pass, teacher queries
    /// and backward pass run on their own replica of the student and fork of the teacher
    /// ([`vdd_core::ScoreModel::fork`]), possibly on another thread, and the chunks'
    /// gradients are summed in chunk order. The student depends on the number of chunks,
    /// never on the number of threads ([`crate::Vdd::set_threads`]); with one chunk (the
    /// default) the whole batch runs in the calling thread.
    #[serde(default = "one_chunk")]
    pub chunks: usize,
}

fn one_chunk() -> usize {
    1
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
            noise_unit: None,
            score_at: ScoreAt::CleanSample,
            state_noise: None,
            experts_per_state: None,
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
            chunks: 1,
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

    /// Checks the documented ranges: every count positive and at most its limit
    /// ([`MAX_ITERATIONS`], [`MAX_BATCH_SIZE`], [`MAX_VI_SAMPLES`], [`MAX_STEPS_PER_ITER`],
    /// [`MAX_SAMPLES_PER_EXPERT`]), both optimisers' [`AdamConfig::validate`] (finite
    /// `lr >= 0`, betas in `[0, 1)`, finite `eps > 0`, finite `weight_decay >= 0`),
    /// `max_grad_norm` finite and positive, `student_ema` in `[0, 1)`, and the noise schedule's
    /// own ranges. Non-finite values (NaN, or `1e39` read as an `f32` infinity) fail.
    pub fn validate(&self) -> Result<(), CoreError> {
        let positive = [
            ("iterations", self.iterations),
            ("batch_size", self.batch_size),
            ("vi_samples", self.vi_samples),
            ("expert_steps_per_iter", self.expert_steps_per_iter),
            ("gating_batch_size", self.gating_batch_size),
            ("chunks", self.chunks),
        ];
        for (name, v) in positive {
            if v == 0 {
                return Err(CoreError::Config(format!("{name} must be positive")));
            }
        }
        let bounded = [
            ("iterations", self.iterations, MAX_ITERATIONS),
            ("batch_size", self.batch_size, MAX_BATCH_SIZE),
            ("gating_batch_size", self.gating_batch_size, MAX_BATCH_SIZE),
            ("vi_samples", self.vi_samples, MAX_VI_SAMPLES),
            ("expert_steps_per_iter", self.expert_steps_per_iter, MAX_STEPS_PER_ITER),
            ("gating_steps_per_iter", self.gating_steps_per_iter, MAX_STEPS_PER_ITER),
            ("chunks", self.chunks, MAX_CHUNKS),
        ];
        for (name, v, max) in bounded {
            if v > max {
                return Err(CoreError::Config(format!("{name} must be <= {max}, got {v}")));
            }
        }
        if self.experts_per_state == Some(0) {
            return Err(CoreError::Config("experts_per_state must be positive".into()));
        }
        if self.batch_size * self.vi_samples > MAX_SAMPLES_PER_EXPERT {
            return Err(CoreError::Config(format!(
                "batch_size · vi_samples must be <= {MAX_SAMPLES_PER_EXPERT}, got {} · {}",
                self.batch_size, self.vi_samples
            )));
        }
        for (name, opt) in [("expert", &self.expert_optimizer), ("gating", &self.gating_optimizer)]
        {
            opt.validate().map_err(|e| CoreError::Config(format!("{name}_optimizer: {e}")))?;
        }
        for (name, s) in
            [("expert", &self.expert_lr_schedule), ("gating", &self.gating_lr_schedule)]
        {
            s.validate().map_err(|e| CoreError::Config(format!("{name}_lr_schedule: {e}")))?;
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
        if let Some(n) = self.state_noise {
            if !((0.0..=1.0).contains(&n.share) && n.std.is_finite() && n.std > 0.0) {
                return Err(CoreError::Config(format!(
                    "state_noise needs share in [0, 1] and a finite std > 0, got share {} and \
                     std {}",
                    n.share, n.std
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

impl VddConfig {
    /// What a run checks before any work: [`VddConfig::validate`], the student's ranges, and
    /// the estimated memory of training `student` with these settings (the student's
    /// [`MoeConfig::training_bytes`] plus the expert step's `batch_size · num_experts ·
    /// vi_samples` sample buffers) against the memory available.
    ///
    /// ```
    /// use vdd::{MoeConfig, VddConfig};
    /// let student = MoeConfig::toy(1, 2, 8);
    /// assert!(VddConfig::toy().check(&student).is_ok());
    /// let wide = MoeConfig { num_experts: 4000, ..student.clone() };
    /// let wide = VddConfig { batch_size: 4096, vi_samples: 256, ..VddConfig::toy() }.check(&wide);
    /// assert!(wide.unwrap_err().to_string().contains("memory"));
    /// ```
    pub fn check(&self, student: &MoeConfig) -> Result<(), CoreError> {
        use vdd_core::memory::{check_fits, product};
        self.validate()?;
        student.check(self.batch_size.max(self.gating_batch_size))?;
        let rows = self.batch_size.max(self.gating_batch_size);
        let samples = product(&[8, self.batch_size, student.num_experts, self.vi_samples])
            .saturating_mul(product(&[student.action_dim + 1, 4]));
        let bytes = student.training_bytes(rows).saturating_add(samples);
        let what = format!(
            "VDD with batch_size {}, vi_samples {} and {} experts",
            self.batch_size, self.vi_samples, student.num_experts
        );
        check_fits(&what, bytes)
    }
}

/// Largest number of iterations of a run.
pub const MAX_ITERATIONS: usize = 1 << 30;
/// Largest `batch_size` and `gating_batch_size`.
pub const MAX_BATCH_SIZE: usize = 1 << 16;
/// Largest [`VddConfig::chunks`].
pub const MAX_CHUNKS: usize = 256;
/// Largest `vi_samples`.
pub const MAX_VI_SAMPLES: usize = 1 << 12;
/// Largest `expert_steps_per_iter` and `gating_steps_per_iter`.
pub const MAX_STEPS_PER_ITER: usize = 10_000;
/// Largest `batch_size · vi_samples`: the samples of one expert in one expert step (all experts
/// together hold `num_experts` times as many, see [`MAX_SAMPLES_PER_STEP`]).
pub const MAX_SAMPLES_PER_EXPERT: usize = 1 << 20;
/// Largest `batch_size · vi_samples · num_experts`: the teacher's score rows of one expert
/// step, checked by [`crate::Vdd::new`].
pub const MAX_SAMPLES_PER_STEP: usize = 1 << 22;

impl Default for VddConfig {
    fn default() -> Self {
        Self::toy()
    }
}
