//! The teacher's denoised estimate behind its score, and [`ClampedDenoiser`]: a teacher whose
//! denoised estimate is clamped to a box before the score is formed.
//!
//! **A deviation from the paper.** VDD as published distils the teacher's score as it is. A
//! learned diffusion teacher is trained at the data; far from it (where a distilled expert's
//! samples wander early in training) its network extrapolates, and its score there can point
//! away from the data. An expert whose samples see such scores widens instead of contracting,
//! and its variance runs away. [`ClampedDenoiser`] forms the score from the teacher's denoised
//! estimate clamped to a box around the data (in practice the data's bounding box widened by a
//! margin, [`data_box`]): the posterior mean `E[a₀ | a]` of clean actions lies in the data's
//! bounding box, so clamping the estimate there can only move it closer, and far points get a
//! score that points back into the box. Inside the box the score is the teacher's, bit for bit.
//! (DDPM's samplers clip their `x̂₀` the same way.)

use faer::reborrow::ReborrowMut;
use faer::{MatMut, MatRef};
use rand::RngCore;

use crate::error::{CoreError, Result, check_len};
use crate::noise::{DenoiserForm, NoiseConvention};
use crate::score::{NoiseSchedule, ScoreModel};

/// The bounding box of the rows of `actions` widened by `margin` on each side, as per-column
/// `(lower, upper)` bounds.
///
/// ```
/// let a = faer::mat![[0.0f32, 5.0], [2.0, -1.0]];
/// assert_eq!(vdd_core::data_box(a.as_ref(), 0.5), (vec![-0.5, -1.5], vec![2.5, 5.5]));
/// ```
pub fn data_box(actions: MatRef<'_, f32>, margin: f32) -> (Vec<f32>, Vec<f32>) {
    (0..actions.ncols())
        .map(|j| {
            let (mut lo, mut hi) = (f32::INFINITY, f32::NEG_INFINITY);
            for i in 0..actions.nrows() {
                lo = lo.min(actions[(i, j)]);
                hi = hi.max(actions[(i, j)]);
            }
            (lo - margin, hi + margin)
        })
        .unzip()
}

/// A teacher whose score is formed from its denoised estimate clamped to a box (a deviation
/// from the paper: far from its data a learned teacher extrapolates, and its score there can
/// point away from the data and make a distilled expert's variance run away).
///
/// It wraps any [`ScoreModel`] that states its [`DenoiserForm`] through
/// [`ScoreModel::denoiser_form`]; for each coordinate it computes `D = (a + v s) / k`, clamps it
/// to `[lo, hi]` and, when the clamp moved it, replaces the score by `(k D_c − a) / v`. Levels
/// whose form is not [proper](DenoiserForm::is_proper) keep the teacher's score. Actions and
/// bounds are in the teacher's own action space. Sampling and noise levels are the teacher's.
///
/// ```
/// use faer::{Mat, MatMut, MatRef};
/// use vdd_core::{check_score_args, ClampedDenoiser, CoreError, DenoiserForm, ScoreModel};
///
/// /// `N(0, I)` in 1-D, smoothed by `N(0, σ²)`: score `−a / (1 + σ²)`.
/// struct Unit;
/// impl ScoreModel for Unit {
///     fn action_dim(&self) -> usize { 1 }
///     fn state_dim(&self) -> usize { 1 }
///     fn score(&mut self, a: MatRef<'_, f32>, s: MatRef<'_, f32>, sigma: &[f32],
///              mut out: MatMut<'_, f32>) -> Result<(), CoreError> {
///         check_score_args(self, a, s, sigma, out.as_ref())?;
///         for i in 0..a.nrows() { out[(i, 0)] = -a[(i, 0)] / (1.0 + sigma[i] * sigma[i]); }
///         Ok(())
///     }
///     fn denoiser_form(&self, sigma: f32) -> Option<DenoiserForm> { Some(DenoiserForm::ve(sigma)) }
/// }
///
/// let mut clamped = ClampedDenoiser::new(Unit, vec![-0.1], vec![0.1]).unwrap();
/// let a = faer::mat![[0.05f32], [100.0]];
/// let mut out = Mat::zeros(2, 1);
/// clamped.score(a.as_ref(), Mat::zeros(2, 1).as_ref(), &[1.0, 1.0], out.as_mut()).unwrap();
/// assert_eq!(out[(0, 0)], -0.025);            // D = 0.025 is inside the box: unchanged
/// assert!((out[(1, 0)] - (0.1 - 100.0)).abs() < 1e-3); // D clamped to 0.1
/// ```
#[derive(Debug, Clone)]
pub struct ClampedDenoiser<S> {
    inner: S,
    /// Per-dimension lower and upper bounds of the denoised estimate; `None`: no clamping.
    bounds: Option<(Vec<f32>, Vec<f32>)>,
}

impl<S: ScoreModel> ClampedDenoiser<S> {
    /// Clamps `inner`'s denoised estimate to `[lo, hi]` per action dimension (teacher's space).
    pub fn new(inner: S, lo: Vec<f32>, hi: Vec<f32>) -> Result<Self> {
        let d = inner.action_dim();
        check_len("clamp lower bounds", lo.len(), d)?;
        check_len("clamp upper bounds", hi.len(), d)?;
        if lo.iter().zip(&hi).any(|(l, h)| l.partial_cmp(h).is_none_or(|o| o.is_gt())) {
            return Err(CoreError::Config("clamp bounds must be ordered pairs lo <= hi".into()));
        }
        Ok(Self { inner, bounds: Some((lo, hi)) })
    }

    /// Clamps to the bounding box of the rows of `actions` (teacher's space) widened by
    /// `margin` ([`data_box`]), which must be finite and non-negative.
    pub fn around_data(inner: S, actions: MatRef<'_, f32>, margin: f32) -> Result<Self> {
        if !(margin.is_finite() && margin >= 0.0) {
            let what = format!("clip margin {margin}: must be finite and non-negative");
            return Err(CoreError::Config(what));
        }
        let (lo, hi) = data_box(actions, margin);
        Self::new(inner, lo, hi)
    }

    /// No clamping: the teacher's score unchanged (for settings where clamping is off, so one
    /// type serves both).
    pub fn unclamped(inner: S) -> Self {
        Self { inner, bounds: None }
    }

    /// The `(lower, upper)` bounds, `None` when not clamping.
    pub fn bounds(&self) -> Option<(&[f32], &[f32])> {
        self.bounds.as_ref().map(|(l, h)| (l.as_slice(), h.as_slice()))
    }

    /// The wrapped teacher.
    pub fn inner(&self) -> &S {
        &self.inner
    }

    /// The wrapped teacher, mutably.
    pub fn inner_mut(&mut self) -> &mut S {
        &mut self.inner
    }

    /// Unwraps the teacher.
    pub fn into_inner(self) -> S {
        self.inner
    }
}

impl<S: ScoreModel> ScoreModel for ClampedDenoiser<S> {
    fn action_dim(&self) -> usize {
        self.inner.action_dim()
    }
    fn state_dim(&self) -> usize {
        self.inner.state_dim()
    }
    fn noise_process(&self) -> Option<&dyn crate::NoiseProcess> {
        self.inner.noise_process()
    }
    fn noise_convention(&self) -> NoiseConvention {
        self.inner.noise_convention()
    }
    /// The teacher's score with the denoised estimate clamped (see the type's docs). Errors
    /// with [`CoreError::Unsupported`] when clamping and the teacher states no denoiser form.
    fn score(
        &mut self,
        actions: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        noise_levels: &[f32],
        mut out: MatMut<'_, f32>,
    ) -> Result<()> {
        self.inner.score(actions, states, noise_levels, out.rb_mut())?;
        let Some((lo, hi)) = &self.bounds else { return Ok(()) };
        for (i, &level) in noise_levels.iter().enumerate() {
            let form = self.inner.denoiser_form(level).ok_or(CoreError::Unsupported(
                "clamping the denoised estimate of a teacher that states no denoiser form",
            ))?;
            if !form.is_proper() {
                continue;
            }
            for j in 0..actions.ncols() {
                let a = actions[(i, j)];
                let d = form.denoise(a, out[(i, j)]);
                let dc = d.clamp(lo[j], hi[j]);
                if dc != d {
                    out[(i, j)] = form.score(a, dc);
                }
            }
        }
        Ok(())
    }
    fn sample_actions(
        &mut self,
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        out: MatMut<'_, f32>,
    ) -> Result<()> {
        self.inner.sample_actions(states, rng, out)
    }
    fn draw_noise_levels(
        &self,
        schedule: &NoiseSchedule,
        progress: f32,
        rng: &mut dyn RngCore,
        out: &mut [f32],
    ) {
        self.inner.draw_noise_levels(schedule, progress, rng, out)
    }
    fn denoiser_form(&self, level: f32) -> Option<DenoiserForm> {
        self.inner.denoiser_form(level)
    }
    fn noise_range(&self) -> Option<(f32, f32)> {
        self.inner.noise_range()
    }
    /// A clamped fork of the wrapped teacher (with the same bounds), when it forks.
    fn fork(&self) -> Option<Box<dyn ScoreModel + Send>> {
        let inner = self.inner.fork()?;
        Some(Box::new(ClampedDenoiser { inner, bounds: self.bounds.clone() }))
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::check_score_args;
    use faer::Mat;

    /// `N(m, I)` per dimension, VE (σ) or VP (`t` with `ᾱ(t) = exp(−t)`), state ignored.
    #[derive(Clone)]
    struct Gauss {
        mean: Vec<f32>,
        vp: bool,
    }

    impl ScoreModel for Gauss {
        fn action_dim(&self) -> usize {
            self.mean.len()
        }
        fn state_dim(&self) -> usize {
            1
        }
        fn score(
            &mut self,
            a: MatRef<'_, f32>,
            s: MatRef<'_, f32>,
            levels: &[f32],
            mut out: MatMut<'_, f32>,
        ) -> Result<()> {
            check_score_args(self, a, s, levels, out.as_ref())?;
            for i in 0..a.nrows() {
                for j in 0..a.ncols() {
                    out[(i, j)] = if self.vp {
                        // x_t = √ᾱ a₀ + √(1−ᾱ) ε with a₀ ~ N(m, 1): N(√ᾱ m, 1).
                        let ab = (-levels[i]).exp();
                        -(a[(i, j)] - ab.sqrt() * self.mean[j])
                    } else {
                        -(a[(i, j)] - self.mean[j]) / (1.0 + levels[i] * levels[i])
                    };
                }
            }
            Ok(())
        }
        fn denoiser_form(&self, level: f32) -> Option<DenoiserForm> {
            Some(if self.vp { DenoiserForm::vp((-level).exp()) } else { DenoiserForm::ve(level) })
        }
    }

    #[test]
    fn clamped_scores_equal_the_teachers_inside_the_box_and_point_back_outside() {
        for vp in [false, true] {
            let teacher = Gauss { mean: vec![0.3, -0.2], vp };
            let level = if vp { 2.0 } else { 0.3 };
            let actions = faer::mat![[0.1f32, -0.2], [30.0, -40.0], [0.0, 0.0]];
            let states = Mat::<f32>::zeros(3, 1);
            let levels = [level; 3];
            let mut raw = Mat::<f32>::zeros(3, 2);
            let mut plain = ClampedDenoiser::unclamped(teacher.clone());
            plain.score(actions.as_ref(), states.as_ref(), &levels, raw.as_mut()).unwrap();
            // A box wide enough never clamps: the score is the teacher's, bit for bit.
            let mut wide =
                ClampedDenoiser::new(teacher.clone(), vec![-1e6; 2], vec![1e6; 2]).unwrap();
            let mut out = Mat::<f32>::zeros(3, 2);
            wide.score(actions.as_ref(), states.as_ref(), &levels, out.as_mut()).unwrap();
            assert_eq!(out, raw);
            // A unit box: every denoised estimate lands in it, and far points are pulled back.
            let mut unit = ClampedDenoiser::new(teacher, vec![-1.0; 2], vec![1.0; 2]).unwrap();
            unit.score(actions.as_ref(), states.as_ref(), &levels, out.as_mut()).unwrap();
            let form = unit.denoiser_form(level).unwrap();
            for i in 0..3 {
                for j in 0..2 {
                    let d = form.denoise(actions[(i, j)], out[(i, j)]);
                    assert!((-1.0 - 1e-3..=1.0 + 1e-3).contains(&d), "row {i}: D = {d}");
                    let rd = form.denoise(actions[(i, j)], raw[(i, j)]);
                    if (-1.0..=1.0).contains(&rd) {
                        assert_eq!(out[(i, j)], raw[(i, j)], "unclamped entries are unchanged");
                    }
                }
            }
            assert!(out[(1, 0)] < 0.0 && out[(1, 1)] > 0.0, "far points are pulled back: {out:?}");
        }
    }

    #[test]
    fn bounds_are_checked_and_a_teacher_without_a_form_is_an_error_when_clamping() {
        let t = Gauss { mean: vec![0.0, 0.0], vp: false };
        assert!(ClampedDenoiser::new(t.clone(), vec![1.0, 0.0], vec![0.0, 1.0]).is_err());
        assert!(ClampedDenoiser::new(t.clone(), vec![0.0], vec![1.0]).is_err());
        assert!(ClampedDenoiser::new(t.clone(), vec![f32::NAN, 0.0], vec![1.0, 1.0]).is_err());
        // A margin that would shrink the box or lose it is refused, naming the margin.
        let a = faer::mat![[0.0f32, 0.0], [1.0, 1.0]];
        assert!(ClampedDenoiser::around_data(t.clone(), a.as_ref(), 0.0).is_ok());
        for bad in [-0.1, f32::NAN, f32::INFINITY] {
            let e = ClampedDenoiser::around_data(t.clone(), a.as_ref(), bad).err().unwrap();
            assert!(e.to_string().contains("clip margin"), "{e}");
        }

        struct NoForm;
        impl ScoreModel for NoForm {
            fn action_dim(&self) -> usize {
                1
            }
            fn state_dim(&self) -> usize {
                1
            }
            fn score(
                &mut self,
                _: MatRef<'_, f32>,
                _: MatRef<'_, f32>,
                _: &[f32],
                _: MatMut<'_, f32>,
            ) -> Result<()> {
                Ok(())
            }
        }
        let mut c = ClampedDenoiser::new(NoForm, vec![0.0], vec![1.0]).unwrap();
        let m = Mat::<f32>::zeros(1, 1);
        let err = c.score(m.as_ref(), m.as_ref(), &[0.1], Mat::zeros(1, 1).as_mut());
        assert!(matches!(err, Err(CoreError::Unsupported(_))));
    }
}
