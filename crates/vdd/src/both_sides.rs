//! **Noise on both sides**: the expert step's objective between the noised student and the
//! noised teacher (vdd-method.md, "Beyond the paper"; derivation in docs/noise-both-sides.md).
//!
//! The paper's expert step queries the teacher's score at the student's *clean* sample, so its
//! fixed point is the blurred teacher `π_σ`. With [`crate::config::ScoreAt::NoisedSample`] the
//! student's sample is noised the way the teacher's process noises actions at the level `t`,
//!
//! `x = k_t a + √v_t η`, `a = μ_z + L_z ε`, `ε, η ~ N(0, I)`,
//!
//! (`k_t = 1`, `v_t = σ²` for a VE teacher; `k_t = √ᾱ_t`, `v_t = 1 − ᾱ_t` for VP), and expert `z`
//! maximises, per state,
//!
//! `J_z^t = E[log π_t(x) + log q̃_t(z|x)] + H[N(k_t μ_z, k_t² Σ_z + v_t I)]`,
//!
//! where `q̃_t` is the frozen snapshot noised the same way (its experts
//! `N(k_t μ̃_k, k_t² Σ̃_k + v_t I)`, exact for a Gaussian mixture). Summed over the experts with
//! the gating weights this is the upper bound of `KL(q_t ‖ π_t)` that the paper's bound is at
//! `t = 0`, so its minimiser over a range of levels is `π` itself, not its blur.
//!
//! With the corrected score `g = score_π(x, t) + ∇_x log q̃_t(z|x)` (the kernel of
//! [`crate::expert_step`], run on `x` with the noised snapshot), the gradients are
//!
//! * `∂J/∂μ = k E[g]`,
//! * `∂J/∂L = k tril(E[g εᵀ]) + tril(k² (k² L Lᵀ + v I)⁻¹ L)`.
//!
//! [`BothSides`] holds the per-state `k`, the shift and the noise scale of `x` in the
//! student's coordinates (an affine map between the student's and the teacher's action spaces
//! turns `√v` into a per-dimension scale and adds a shift), and the `η`; the expert step folds
//! the factor `k` and the entropy term into `E[g]` and `E[g εᵀ]` so that
//! [`vdd_core::Expert::expert_step_grad`] applies unchanged to every expert family.

use std::ops::Range;

use rand::RngCore;
use vdd_core::{CoreError, NoiseConvention, ScoreModel, gaussian};

use crate::spaces::ActionMap;

/// The noising of one expert step's samples (see the [module docs](self)): per state `b`, the
/// student's sample `a` becomes `x = k_b a + β_b + γ_b ⊙ η` in the student's coordinates.
#[derive(Debug, Default, Clone, PartialEq)]
pub struct BothSides {
    /// `k_b`, one per state.
    pub scale: Vec<f32>,
    /// `β_b`, row-major `B x d` (zero without an action map).
    pub shift: Vec<f32>,
    /// `γ_b`, row-major `B x d`: `√v` over the map's per-dimension scale.
    pub std: Vec<f32>,
    /// `η ~ N(0, I)` per sample, row-major `B·Z·V x d`, in the order of the step's `ε`.
    pub eta: Vec<f32>,
}

/// The part of a [`BothSides`] that belongs to some consecutive states of the step (a chunk).
#[derive(Debug, Clone, Copy)]
pub struct BothSidesView<'a> {
    /// `k_b` of these states.
    pub scale: &'a [f32],
    /// `β_b`, `len x d`.
    pub shift: &'a [f32],
    /// `γ_b`, `len x d`.
    pub std: &'a [f32],
    /// `η` of these states' samples.
    pub eta: &'a [f32],
}

impl BothSides {
    /// Prepares the noising of an expert step of `levels.len() / per_state` states with
    /// `per_state` samples each (`Z·V`) of dimension `d`: every sample of a state takes the
    /// level drawn for the state's first sample (so the noised snapshot is one mixture per
    /// state), `k` and `v` come from the teacher's [`ScoreModel::denoiser_form`] at that level
    /// (for a teacher without one, a [`NoiseConvention::Sigma`] level is read as VE: `k = 1`,
    /// `v = σ²`), and `η` is drawn from `rng`.
    ///
    /// `teacher` is the teacher in its own space; `map` the student-to-teacher action map.
    /// Fails when the teacher's levels are diffusion times and it states no denoiser form, or
    /// when a form is not finite.
    pub(crate) fn prepare(
        &mut self,
        teacher: &dyn ScoreModel,
        map: Option<&ActionMap>,
        levels: &mut [f32],
        per_state: usize,
        d: usize,
        rng: &mut dyn RngCore,
    ) -> Result<(), CoreError> {
        let states = levels.len() / per_state.max(1);
        self.scale.resize(states, 0.0);
        self.shift.resize(states * d, 0.0);
        self.std.resize(states * d, 0.0);
        for b in 0..states {
            let level = levels[b * per_state];
            levels[b * per_state..(b + 1) * per_state].fill(level);
            let form = match (teacher.denoiser_form(level), teacher.noise_convention()) {
                (Some(f), _) => f,
                (None, NoiseConvention::Sigma) => vdd_core::DenoiserForm::ve(level),
                (None, NoiseConvention::Time) => {
                    return Err(CoreError::Config(
                        "score_at = noised_sample needs the teacher's denoiser form \
                         (ScoreModel::denoiser_form) for diffusion-time levels"
                            .into(),
                    ));
                }
            };
            let (k, v) = (form.scale, form.variance);
            if !(k.is_finite() && k > 0.0 && v.is_finite() && v >= 0.0) {
                return Err(CoreError::NonFinite { what: "teacher's denoiser form" });
            }
            self.scale[b] = k;
            for j in 0..d {
                // x_T = k (o + s a) + √v η = o + s x  ⇒  x = k a + (k − 1) o / s + (√v / s) η.
                let (s, o) = map.map_or((1.0, 0.0), |m| m.coefficients(j));
                self.shift[b * d + j] = (k - 1.0) * o / s;
                self.std[b * d + j] = v.sqrt() / s;
            }
        }
        self.eta.resize(levels.len() * d, 0.0);
        vdd_core::fill_standard_normal(rng, &mut self.eta);
        Ok(())
    }

    /// The part of the states `states` (of `per_state` samples each, dimension `d`).
    pub fn view(&self, states: Range<usize>, per_state: usize, d: usize) -> BothSidesView<'_> {
        let (s, e) = (states.start, states.end);
        BothSidesView {
            scale: &self.scale[s..e],
            shift: &self.shift[s * d..e * d],
            std: &self.std[s * d..e * d],
            eta: &self.eta[s * per_state * d..e * per_state * d],
        }
    }
}

/// `chol(k² L Lᵀ + diag(γ²))` into `out` (row-major `d x d`); `false` when it is not positive
/// definite.
pub(crate) fn noised_cholesky(l: &[f32], k: f32, gamma: &[f32], d: usize, out: &mut [f32]) -> bool {
    for r in 0..d {
        for c in 0..=r {
            let lr = &l[r * d..r * d + c + 1];
            let lc = &l[c * d..c * d + c + 1];
            let s: f32 = lr.iter().zip(lc).map(|(a, b)| a * b).sum();
            out[r * d + c] = k * k * s + if r == c { gamma[r] * gamma[r] } else { 0.0 };
            out[c * d + r] = out[r * d + c];
        }
    }
    gaussian::cholesky_in_place(out, d)
}

/// Turns one (state, expert)'s `E[g]` and `E[g εᵀ]` at the noised samples into what
/// [`vdd_core::Expert::expert_step_grad`] expects for `J^t` (see the [module docs](self)):
/// `mean_g ← k E[g]`, `mean_g_eps ← k E[g εᵀ] + tril(k² C⁻¹ L) − diag(1/L_ii)` with
/// `C = k² L Lᵀ + diag(γ²)`. `chol` and `col` are scratch (`d·d`, `d`).
#[allow(clippy::too_many_arguments)]
pub(crate) fn fold_into_moments(
    l: &[f32],
    k: f32,
    gamma: &[f32],
    d: usize,
    mean_g: &mut [f32],
    mean_g_eps: &mut [f32],
    chol: &mut [f32],
    col: &mut [f32],
) -> Result<(), CoreError> {
    if !noised_cholesky(l, k, gamma, d, chol) {
        return Err(CoreError::NonFinite { what: "noised expert covariance" });
    }
    mean_g.iter_mut().for_each(|g| *g *= k);
    mean_g_eps.iter_mut().for_each(|g| *g *= k);
    for c in 0..d {
        // Column c of C⁻¹ (k² L); only its entries on and below the diagonal are parameters.
        for r in 0..d {
            col[r] = k * k * l[r * d + c];
        }
        gaussian::solve_lower_in_place(chol, col);
        gaussian::solve_upper_t_in_place(chol, col);
        for r in c..d {
            mean_g_eps[r * d + c] += col[r];
        }
        mean_g_eps[c * d + c] -= 1.0 / l[c * d + c];
    }
    Ok(())
}
