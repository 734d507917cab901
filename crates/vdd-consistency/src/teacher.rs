//! The teacher seen through its denoiser: [`ConsistencyTeacher`], implemented for the BESO
//! teacher ([`vdd_diffusion::Beso`]), a [`vdd_diffusion::DiffusionTeacher`] holding one, any
//! variance-exploding [`ScoreModel`] through [`ScoreTeacher`] (e.g. the exact
//! [`vdd_diffusion::GmmTeacher`]) and closures ([`DenoiserFn`]).

use faer::reborrow::Reborrow;
use faer::{MatMut, MatRef};
use vdd_core::{Affine, CoreError, NoiseConvention, ScoreModel, check_len, check_shape};
use vdd_diffusion::{Beso, BesoConfig, DenoiserNet, DiffusionTeacher};

/// A variance-exploding diffusion teacher seen through its denoiser `D(x; σ, s)` in its
/// normalised space: what consistency distillation needs (the probability-flow ODE
/// `dx/dσ = (x − D)/σ` is integrated with Heun steps of it).
///
/// Implemented for the BESO teacher ([`vdd_diffusion::Beso`]), for a
/// [`vdd_diffusion::DiffusionTeacher`] holding one (a DDPM one is rejected by
/// [`ConsistencyTeacher::validate`]), for any variance-exploding [`ScoreModel`] through
/// [`ScoreTeacher`] (e.g. the exact [`vdd_diffusion::GmmTeacher`]), for closures
/// ([`DenoiserFn`]) and for `&mut` references to any of these.
pub trait ConsistencyTeacher {
    /// Dimension of one (normalised) state; by default the state normaliser's.
    fn state_dim(&self) -> usize {
        self.normalizers().0.dim()
    }

    /// Dimension of one (normalised, flattened) action; by default the action normaliser's.
    fn action_dim(&self) -> usize {
        self.normalizers().1.dim()
    }

    /// The `(state, action)` normalisers mapping raw data into the space the denoiser works in
    /// (their dimensions are the teacher's).
    fn normalizers(&self) -> (&Affine, &Affine);

    /// Writes `D(x; σ_i, s_i)` of each row into `out`: `x` is `n x action_dim`, `sigma` has `n`
    /// positive levels, `states` is `n x state_dim`, `out` is `n x action_dim`.
    fn denoise(
        &mut self,
        x: MatRef<'_, f32>,
        sigma: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError>;

    /// Checks that the teacher can be distilled (trainers call it first). `Ok` by default.
    fn validate(&self) -> Result<(), CoreError> {
        Ok(())
    }

    /// The teacher's preconditioned denoiser network, when it has one (students of the same
    /// architecture start from its weights). `None` by default.
    fn network(&self) -> Option<&DenoiserNet> {
        None
    }

    /// The BESO configuration the teacher was built with, when it is one (its levels and
    /// architecture are the students' defaults, see [`crate::ConsistencyConfig::for_teacher`]).
    /// `None` by default.
    fn beso_config(&self) -> Option<&BesoConfig> {
        None
    }
}

impl<T: ConsistencyTeacher + ?Sized> ConsistencyTeacher for &mut T {
    fn state_dim(&self) -> usize {
        (**self).state_dim()
    }
    fn action_dim(&self) -> usize {
        (**self).action_dim()
    }
    fn normalizers(&self) -> (&Affine, &Affine) {
        (**self).normalizers()
    }
    fn denoise(
        &mut self,
        x: MatRef<'_, f32>,
        sigma: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        (**self).denoise(x, sigma, states, out)
    }
    fn validate(&self) -> Result<(), CoreError> {
        (**self).validate()
    }
    fn network(&self) -> Option<&DenoiserNet> {
        (**self).network()
    }
    fn beso_config(&self) -> Option<&BesoConfig> {
        (**self).beso_config()
    }
}

impl ConsistencyTeacher for Beso {
    fn normalizers(&self) -> (&Affine, &Affine) {
        Beso::normalizers(self)
    }
    fn denoise(
        &mut self,
        x: MatRef<'_, f32>,
        sigma: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        Beso::denoise(self, x, sigma, states, out)
    }
    /// The EMA denoiser network the teacher samples with.
    fn network(&self) -> Option<&DenoiserNet> {
        Some(self.net())
    }
    fn beso_config(&self) -> Option<&BesoConfig> {
        Some(self.config())
    }
}

/// A learned teacher of either kind: a BESO one is distilled as [`Beso`]; a DDPM one is
/// rejected by [`ConsistencyTeacher::validate`] (consistency distillation here integrates the
/// variance-exploding probability-flow ODE).
impl ConsistencyTeacher for DiffusionTeacher {
    fn normalizers(&self) -> (&Affine, &Affine) {
        DiffusionTeacher::normalizers(self)
    }
    fn denoise(
        &mut self,
        x: MatRef<'_, f32>,
        sigma: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        match self {
            DiffusionTeacher::Beso(b) => Beso::denoise(b, x, sigma, states, out),
            DiffusionTeacher::Ddpm(_) => Err(not_variance_exploding()),
        }
    }
    fn validate(&self) -> Result<(), CoreError> {
        beso_of(self).map(|_| ())
    }
    fn network(&self) -> Option<&DenoiserNet> {
        beso_of(self).ok().map(Beso::net)
    }
    fn beso_config(&self) -> Option<&BesoConfig> {
        beso_of(self).ok().map(Beso::config)
    }
}

/// The BESO teacher a learned teacher holds, or the error for a DDPM one.
fn beso_of(teacher: &DiffusionTeacher) -> Result<&Beso, CoreError> {
    match teacher {
        DiffusionTeacher::Beso(b) => Ok(b),
        DiffusionTeacher::Ddpm(_) => Err(not_variance_exploding()),
    }
}

fn not_variance_exploding() -> CoreError {
    CoreError::Config(
        "consistency distillation needs a variance-exploding (BESO / EDM) teacher, got DDPM".into(),
    )
}

/// A teacher given as a closure `denoise(x, σ, states, out)` in the normalised space of the
/// given normalisers.
///
/// ```
/// use faer::{MatMut, MatRef};
/// use vdd_consistency::{ConsistencyTeacher, DenoiserFn};
/// use vdd_core::{Affine, CoreError};
/// // Data N(0, 0.5²) per dimension: D(x; σ) = 0.25 / (0.25 + σ²) · x.
/// let mut teacher = DenoiserFn::new(
///     Affine::identity(1),
///     Affine::identity(2),
///     |x: MatRef<'_, f32>, s: &[f32], _st: MatRef<'_, f32>, mut out: MatMut<'_, f32>| {
///         for j in 0..x.ncols() {
///             for i in 0..x.nrows() {
///                 out[(i, j)] = 0.25 / (0.25 + s[i] * s[i]) * x[(i, j)];
///             }
///         }
///         Ok::<(), CoreError>(())
///     },
/// );
/// let x = faer::mat![[1.0f32, -1.0]];
/// let mut out = faer::Mat::zeros(1, 2);
/// teacher.denoise(x.as_ref(), &[0.5], faer::Mat::zeros(1, 1).as_ref(), out.as_mut()).unwrap();
/// assert_eq!(out[(0, 0)], 0.5);
/// ```
pub struct DenoiserFn<F> {
    state_norm: Affine,
    action_norm: Affine,
    f: F,
}

impl<F> std::fmt::Debug for DenoiserFn<F> {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("DenoiserFn")
            .field("state_norm", &self.state_norm)
            .field("action_norm", &self.action_norm)
            .finish_non_exhaustive()
    }
}

impl<F> DenoiserFn<F>
where
    F: FnMut(MatRef<'_, f32>, &[f32], MatRef<'_, f32>, MatMut<'_, f32>) -> Result<(), CoreError>,
{
    /// A teacher whose denoiser is `f(x, σ, states, out)`, working in the space normalised by
    /// `state_norm` and `action_norm` (whose dimensions are the teacher's).
    pub fn new(state_norm: Affine, action_norm: Affine, f: F) -> Self {
        Self { state_norm, action_norm, f }
    }
}

/// Checks a denoiser call: `x` `n x d_a`, `states` `n x d_s`, `n` levels, `out` `n x d_a`.
fn check_denoise_args<T: ConsistencyTeacher + ?Sized>(
    teacher: &T,
    x: MatRef<'_, f32>,
    sigma: &[f32],
    states: MatRef<'_, f32>,
    out: MatRef<'_, f32>,
) -> Result<(), CoreError> {
    let n = x.nrows();
    check_shape("x", x, n, teacher.action_dim())?;
    check_shape("states", states, n, teacher.state_dim())?;
    check_len("sigma", sigma.len(), n)?;
    check_shape("denoiser output", out, n, teacher.action_dim())
}

impl<F> ConsistencyTeacher for DenoiserFn<F>
where
    F: FnMut(MatRef<'_, f32>, &[f32], MatRef<'_, f32>, MatMut<'_, f32>) -> Result<(), CoreError>,
{
    fn normalizers(&self) -> (&Affine, &Affine) {
        (&self.state_norm, &self.action_norm)
    }
    fn denoise(
        &mut self,
        x: MatRef<'_, f32>,
        sigma: &[f32],
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        check_denoise_args(self, x, sigma, states, out.rb())?;
        (self.f)(x, sigma, states, out)
    }
}

/// A variance-exploding [`ScoreModel`] (noise levels are `σ`) seen as a denoiser through
/// Tweedie's formula, `D(x; σ, s) = x + σ² ∇_x log π_σ(x|s)` — e.g. the exact
/// [`vdd_diffusion::GmmTeacher`], whose smoothed score is known in closed form, so its
/// probability-flow ODE is the exact one.
///
/// ```
/// use faer::Mat;
/// use vdd_consistency::{ConsistencyTeacher, ScoreTeacher};
/// use vdd_diffusion::GmmTeacher;
/// // One mode N((1, 0), 0.1² I): D(x; σ) = μ + 0.01 / (0.01 + σ²) (x − μ).
/// let gmm = GmmTeacher::isotropic(&[1.0], &[vec![1.0, 0.0]], 0.1).unwrap();
/// let mut teacher = ScoreTeacher::identity(gmm).unwrap();
/// let mut out = Mat::zeros(1, 2);
/// let x = faer::mat![[3.0f32, 0.0]];
/// teacher.denoise(x.as_ref(), &[0.1], Mat::zeros(1, 1).as_ref(), out.as_mut()).unwrap();
/// assert!((out[(0, 0)] - 2.0).abs() < 1e-5);
/// ```
#[derive(Debug, Clone)]
pub struct ScoreTeacher<S> {
    model: S,
    state_norm: Affine,
    action_norm: Affine,
}

impl<S: ScoreModel> ScoreTeacher<S> {
    /// The teacher `model`, whose score works in the space normalised by `state_norm` and
    /// `action_norm`. Errors unless the model is variance-exploding and the dimensions match.
    pub fn new(model: S, state_norm: Affine, action_norm: Affine) -> Result<Self, CoreError> {
        if model.noise_convention() != NoiseConvention::Sigma {
            return Err(CoreError::Config(
                "a score teacher must be variance-exploding (noise levels σ)".into(),
            ));
        }
        check_len("state normaliser vs model state_dim", state_norm.dim(), model.state_dim())?;
        check_len("action normaliser vs model action_dim", action_norm.dim(), model.action_dim())?;
        Ok(Self { model, state_norm, action_norm })
    }

    /// The teacher `model` on raw data (identity normalisers).
    pub fn identity(model: S) -> Result<Self, CoreError> {
        let (ds, da) = (model.state_dim(), model.action_dim());
        Self::new(model, Affine::identity(ds), Affine::identity(da))
    }

    /// The score model.
    pub fn model(&self) -> &S {
        &self.model
    }
}

impl<S: ScoreModel> ConsistencyTeacher for ScoreTeacher<S> {
    fn normalizers(&self) -> (&Affine, &Affine) {
        (&self.state_norm, &self.action_norm)
    }
    fn denoise(
        &mut self,
        x: MatRef<'_, f32>,
        sigma: &[f32],
        states: MatRef<'_, f32>,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        check_denoise_args(self, x, sigma, states, out.rb())?;
        self.model.score(x, states, sigma, out.as_mut())?;
        for j in 0..x.ncols() {
            for i in 0..x.nrows() {
                out[(i, j)] = x[(i, j)] + sigma[i] * sigma[i] * out[(i, j)];
            }
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::Mat;
    use vdd_diffusion::GmmTeacher;

    /// Tweedie's denoiser of a mixture's exact score equals the closed form
    /// `D = Σ_k r_k (μ_k + s²/(s² + σ²) (x − μ_k))` with posterior responsibilities `r_k`.
    #[test]
    fn score_teacher_is_the_exact_gmm_denoiser() {
        let means = [vec![1.0f32, 0.0], vec![-1.0, 0.5]];
        let std = 0.3f32;
        let gmm = GmmTeacher::isotropic(&[1.0, 3.0], &means, std).unwrap();
        let mut t = ScoreTeacher::identity(gmm).unwrap();
        let x = Mat::from_fn(4, 2, |i, j| 0.7 * i as f32 - 1.0 + 0.2 * j as f32);
        let sigma = [0.05f32, 0.3, 1.0, 4.0];
        let mut out = Mat::zeros(4, 2);
        t.denoise(x.as_ref(), &sigma, Mat::zeros(4, 1).as_ref(), out.as_mut()).unwrap();
        for i in 0..4 {
            let v = std * std + sigma[i] * sigma[i];
            let logits: Vec<f32> = means
                .iter()
                .zip([0.25f32, 0.75])
                .map(|(m, w)| {
                    w.ln() - ((x[(i, 0)] - m[0]).powi(2) + (x[(i, 1)] - m[1]).powi(2)) / (2.0 * v)
                })
                .collect();
            let max = logits[0].max(logits[1]);
            let r: Vec<f32> = logits.iter().map(|l| (l - max).exp()).collect();
            let total = r[0] + r[1];
            for j in 0..2 {
                let want: f32 = (0..2)
                    .map(|k| {
                        r[k] / total * (means[k][j] + std * std / v * (x[(i, j)] - means[k][j]))
                    })
                    .sum();
                assert!((out[(i, j)] - want).abs() < 1e-4, "row {i}: {} vs {want}", out[(i, j)]);
            }
        }
        // Shapes are checked.
        let mut bad = Mat::zeros(3, 2);
        assert!(t.denoise(x.as_ref(), &sigma, Mat::zeros(4, 1).as_ref(), bad.as_mut()).is_err());
        assert!(
            ScoreTeacher::new(GmmTeacher::circle_toy(), Affine::identity(2), Affine::identity(2))
                .is_err()
        );
    }
}
