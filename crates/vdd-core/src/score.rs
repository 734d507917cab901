//! The teacher seen through its score: [`ScoreModel`], noise-level conventions and schedules.

use faer::{MatMut, MatRef};
use rand::{Rng as _, RngCore};
use serde::{Deserialize, Serialize};

use crate::error::{CoreError, Result, check_len, check_shape};
use crate::noise::{DenoiserForm, NoiseConvention, NoiseProcess};

/// How the expert step picks the teacher's noise level for each sample.
///
/// Levels are in the teacher's own [`NoiseConvention`].
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum NoiseSchedule {
    /// Always the same level.
    Fixed {
        /// The level.
        level: f32,
    },
    /// Uniform in `[min, max]`, drawn independently per sample.
    Uniform {
        /// Lower end.
        min: f32,
        /// Upper end.
        max: f32,
    },
    /// Annealed from `start` (at the beginning of training) to `end` (at its end),
    /// geometrically when both are positive and linearly otherwise.
    Annealed {
        /// Level at progress 0.
        start: f32,
        /// Level at progress 1.
        end: f32,
    },
}

impl NoiseSchedule {
    /// Checks that the levels are finite, non-negative and ordered.
    pub fn validate(&self) -> Result<()> {
        let ok = match *self {
            NoiseSchedule::Fixed { level } => level.is_finite() && level >= 0.0,
            NoiseSchedule::Uniform { min, max } => {
                min.is_finite() && max.is_finite() && min >= 0.0 && min <= max
            }
            NoiseSchedule::Annealed { start, end } => {
                start.is_finite() && end.is_finite() && start >= 0.0 && end >= 0.0
            }
        };
        if ok { Ok(()) } else { Err(CoreError::Config(format!("invalid noise schedule {self:?}"))) }
    }

    /// The lowest and highest level the schedule can draw.
    ///
    /// ```
    /// use vdd_core::NoiseSchedule;
    /// assert_eq!(NoiseSchedule::Annealed { start: 1.0, end: 0.01 }.bounds(), (0.01, 1.0));
    /// assert_eq!(NoiseSchedule::Uniform { min: 0.1, max: 1.0 }.bounds(), (0.1, 1.0));
    /// ```
    pub fn bounds(&self) -> (f32, f32) {
        match *self {
            NoiseSchedule::Fixed { level } => (level, level),
            NoiseSchedule::Uniform { min, max } => (min, max),
            NoiseSchedule::Annealed { start, end } => (start.min(end), start.max(end)),
        }
    }

    /// Checks that every level of the schedule is in `unit` and inside `range` (both
    /// inclusive), as the teacher reports them ([`ScoreModel::noise_convention`] and
    /// [`ScoreModel::noise_range`]); `None` skips a check. The errors name the settings
    /// `noise` and `noise_unit`.
    ///
    /// ```
    /// use vdd_core::{NoiseConvention, NoiseSchedule};
    /// let s = NoiseSchedule::Uniform { min: 0.1, max: 1.0 };
    /// let ve = Some((0.002, 80.0));
    /// assert!(s.check_teacher(Some(NoiseConvention::Sigma), NoiseConvention::Sigma, ve).is_ok());
    /// assert!(s.check_teacher(None, NoiseConvention::Time, Some((1.0, 100.0))).is_err());
    /// assert!(s.check_teacher(Some(NoiseConvention::Sigma), NoiseConvention::Time, None).is_err());
    /// ```
    pub fn check_teacher(
        &self,
        unit: Option<NoiseConvention>,
        teacher_unit: NoiseConvention,
        range: Option<(f32, f32)>,
    ) -> Result<()> {
        let name = |u: NoiseConvention| match u {
            NoiseConvention::Sigma => "sigma (a VE noise level σ)",
            NoiseConvention::Time => "time (a VP diffusion time t)",
        };
        if let Some(u) = unit.filter(|&u| u != teacher_unit) {
            return Err(CoreError::Config(format!(
                "noise_unit is {} but the teacher's levels are in {}",
                name(u),
                name(teacher_unit)
            )));
        }
        let (lo, hi) = self.bounds();
        if let Some((min, max)) = range.filter(|&(min, max)| lo < min || hi > max) {
            return Err(CoreError::Config(format!(
                "noise levels {lo}..={hi} are outside the teacher's range {min}..={max} \
                 (its levels are in {})",
                name(teacher_unit)
            )));
        }
        Ok(())
    }

    /// Draws one level at training progress `progress ∈ [0, 1]`.
    ///
    /// ```
    /// use vdd_core::{NoiseSchedule, Seeds};
    /// let mut rng = Seeds::new(0).stream("noise");
    /// let s = NoiseSchedule::Annealed { start: 1.0, end: 0.01 };
    /// assert!((s.draw(0.5, &mut rng) - 0.1).abs() < 1e-5);
    /// ```
    pub fn draw(&self, progress: f32, rng: &mut dyn RngCore) -> f32 {
        match *self {
            NoiseSchedule::Fixed { level } => level,
            NoiseSchedule::Uniform { min, max } => {
                if max > min {
                    rng.random_range(min..=max)
                } else {
                    min
                }
            }
            NoiseSchedule::Annealed { start, end } => {
                let p = progress.clamp(0.0, 1.0);
                if start > 0.0 && end > 0.0 {
                    (start.ln() + p * (end.ln() - start.ln())).exp()
                } else {
                    start + p * (end - start)
                }
            }
        }
    }
}

/// A teacher policy `π(a|s)` seen only through its score `∇_a log π_σ(a|s)`, where `π_σ` is
/// `π` convolved with Gaussian noise of level `σ` (or diffusion time `t`).
///
/// This is all VDD needs from a teacher. Implement it for your own model in a few lines; the
/// example is an analytic state-independent Gaussian `N(m, s² I)`, whose smoothed density is
/// `N(m, (s² + σ²) I)`:
///
/// ```
/// use faer::{MatMut, MatRef, reborrow::Reborrow};
/// use vdd_core::{check_score_args, CoreError, ScoreModel};
///
/// struct IsoGaussian { mean: Vec<f32>, std: f32 }
///
/// impl ScoreModel for IsoGaussian {
///     fn action_dim(&self) -> usize { self.mean.len() }
///     fn state_dim(&self) -> usize { 1 }
///     fn score(&mut self, a: MatRef<'_, f32>, s: MatRef<'_, f32>, sigma: &[f32],
///              mut out: MatMut<'_, f32>) -> Result<(), CoreError> {
///         check_score_args(self, a, s, sigma, out.rb())?;
///         for i in 0..a.nrows() {
///             let var = self.std * self.std + sigma[i] * sigma[i];
///             for j in 0..a.ncols() {
///                 out[(i, j)] = -(a[(i, j)] - self.mean[j]) / var;
///             }
///         }
///         Ok(())
///     }
/// }
///
/// let mut teacher = IsoGaussian { mean: vec![1.0, -1.0], std: 0.5 };
/// let a = faer::mat![[1.5f32, -1.0]];
/// let s = faer::Mat::<f32>::zeros(1, 1);
/// let mut out = faer::Mat::<f32>::zeros(1, 2);
/// teacher.score(a.as_ref(), s.as_ref(), &[0.0], out.as_mut()).unwrap();
/// assert!((out[(0, 0)] + 2.0).abs() < 1e-6);
/// ```
pub trait ScoreModel {
    /// Dimension of one (flattened) action.
    fn action_dim(&self) -> usize;

    /// Dimension of one (flattened) state / observation.
    fn state_dim(&self) -> usize;

    /// The teacher's noise process ([`NoiseProcess`]): its levels' unit, trained range, valid
    /// levels, denoiser form and `σ` conversion, stated once. [`ScoreModel::noise_convention`],
    /// [`ScoreModel::noise_range`], [`ScoreModel::denoiser_form`] and
    /// [`ScoreModel::draw_noise_levels`] follow from it unless a teacher overrides them. The
    /// default is `None` (a teacher of VE levels that states nothing else).
    fn noise_process(&self) -> Option<&dyn NoiseProcess> {
        None
    }

    /// Whether noise levels are VE `σ` or VP `t`: the [`ScoreModel::noise_process`]'s, else
    /// [`NoiseConvention::Sigma`].
    fn noise_convention(&self) -> NoiseConvention {
        self.noise_process().map_or(NoiseConvention::Sigma, |p| p.convention())
    }

    /// Writes `∇_a log π_level(a|s)` for each row into `out`.
    ///
    /// `actions` is `n x action_dim`, `states` is `n x state_dim`, `noise_levels` has length
    /// `n` and `out` is `n x action_dim`.
    fn score(
        &mut self,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        noise_levels: &[f32],
        out: MatMut<'_, f32>,
    ) -> Result<()>;

    /// Draws one action per state from the teacher's (clean) distribution into `out`
    /// (`n x action_dim`), for teachers that can sample.
    ///
    /// VDD's gating step uses it when no dataset actions are given. The default returns
    /// [`CoreError::Unsupported`].
    fn sample_actions(
        &mut self,
        _states: MatRef<'_, f32>,
        _rng: &mut dyn RngCore,
        _out: MatMut<'_, f32>,
    ) -> Result<()> {
        Err(CoreError::Unsupported("sampling actions from this teacher"))
    }

    /// Fills `out` with noise levels drawn from `schedule` at training progress `progress`.
    ///
    /// The default draws each level independently with [`NoiseSchedule::draw`] and maps it
    /// through the [`ScoreModel::noise_process`]'s [`NoiseProcess::valid_level`] (a teacher
    /// with discrete levels rounds onto its grid), if it states one.
    fn draw_noise_levels(
        &self,
        schedule: &NoiseSchedule,
        progress: f32,
        rng: &mut dyn RngCore,
        out: &mut [f32],
    ) {
        let process = self.noise_process();
        for x in out {
            let level = schedule.draw(progress, rng);
            *x = process.map_or(level, |p| p.valid_level(level));
        }
    }

    /// How the score at `level` relates to the teacher's denoised estimate of the clean action
    /// (VE: `D = a + σ² s`; VP: `x̂₀ = (a + (1 − ᾱ) s)/√ᾱ`), for teachers that have one.
    ///
    /// [`crate::ClampedDenoiser`] needs it. The default is the
    /// [`ScoreModel::noise_process`]'s, or `None`.
    fn denoiser_form(&self, level: f32) -> Option<DenoiserForm> {
        self.noise_process().map(|p| p.denoiser_form(level))
    }

    /// The range `(min, max)` of noise levels (in the teacher's [`NoiseConvention`]) at which
    /// the score is trustworthy: the levels a learned teacher was trained at, or `(0, ∞)` for
    /// an exact score. Automatic schedules (`vdd::VddConfig::for_teacher`) end at `min`.
    /// The default is the [`ScoreModel::noise_process`]'s, or `None` (unknown).
    fn noise_range(&self) -> Option<(f32, f32)> {
        self.noise_process().map(|p| p.range())
    }

    /// An independent copy of this teacher that computes the same scores, bit for bit, so
    /// that a trainer can query chunks of a batch from several threads at once. The default
    /// is `None` (the teacher cannot be copied): trainers then query this one for every chunk
    /// in turn, with the same results.
    fn fork(&self) -> Option<Box<dyn ScoreModel + Send>> {
        None
    }
}

/// `ScoreModel` for a pointer to a score model: every method forwarded to the pointee.
macro_rules! forward_score_model {
    ($($pointer:tt)*) => {
        impl<T: ScoreModel + ?Sized> ScoreModel for $($pointer)* {
            fn action_dim(&self) -> usize {
                (**self).action_dim()
            }
            fn state_dim(&self) -> usize {
                (**self).state_dim()
            }
            fn noise_process(&self) -> Option<&dyn NoiseProcess> {
                (**self).noise_process()
            }
            fn noise_convention(&self) -> NoiseConvention {
                (**self).noise_convention()
            }
            fn score(
                &mut self,
                actions: MatRef<'_, f32>,
                states: MatRef<'_, f32>,
                noise_levels: &[f32],
                out: MatMut<'_, f32>,
            ) -> Result<()> {
                (**self).score(actions, states, noise_levels, out)
            }
            fn draw_noise_levels(
                &self,
                schedule: &NoiseSchedule,
                progress: f32,
                rng: &mut dyn RngCore,
                out: &mut [f32],
            ) {
                (**self).draw_noise_levels(schedule, progress, rng, out)
            }
            fn sample_actions(
                &mut self,
                states: MatRef<'_, f32>,
                rng: &mut dyn RngCore,
                out: MatMut<'_, f32>,
            ) -> Result<()> {
                (**self).sample_actions(states, rng, out)
            }
            fn denoiser_form(&self, level: f32) -> Option<DenoiserForm> {
                (**self).denoiser_form(level)
            }
            fn noise_range(&self) -> Option<(f32, f32)> {
                (**self).noise_range()
            }
            fn fork(&self) -> Option<Box<dyn ScoreModel + Send>> {
                (**self).fork()
            }
        }
    };
}

forward_score_model!(Box<T>);
forward_score_model!(&mut T);

/// Validates the arguments of [`ScoreModel::score`]: shapes agree with the model's dimensions.
pub fn check_score_args<S: ScoreModel + ?Sized>(
    model: &S,
    actions: MatRef<'_, f32>,
    states: MatRef<'_, f32>,
    noise_levels: &[f32],
    out: MatRef<'_, f32>,
) -> Result<()> {
    let n = actions.nrows();
    check_shape("actions", actions, n, model.action_dim())?;
    check_shape("states", states, n, model.state_dim())?;
    check_len("noise_levels", noise_levels.len(), n)?;
    check_shape("score output", out, n, model.action_dim())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::Seeds;

    #[test]
    fn uniform_schedule_stays_in_range() {
        let mut rng = Seeds::new(1).stream("n");
        let s = NoiseSchedule::Uniform { min: 0.1, max: 0.5 };
        let draws: Vec<f32> = (0..1000).map(|_| s.draw(0.0, &mut rng)).collect();
        assert!(draws.iter().all(|&x| (0.1..=0.5).contains(&x)));
        let mean = draws.iter().sum::<f32>() / 1000.0;
        assert!((mean - 0.3).abs() < 0.02);
    }

    #[test]
    fn invalid_schedules_are_rejected() {
        assert!(NoiseSchedule::Uniform { min: 0.5, max: 0.1 }.validate().is_err());
        assert!(NoiseSchedule::Fixed { level: f32::NAN }.validate().is_err());
        assert!(NoiseSchedule::Fixed { level: 0.1 }.validate().is_ok());
    }
}
