//! The mixture's per-expert parameters in raw action space ([`Components`]): what a caller
//! outside Rust (Python, an ONNX graph) needs to pick an expert and sample an action itself.

use faer::{Mat, MatRef};
use vdd_core::{Expert, Policy, check_shape};

use super::Moe;
use super::deploy::DeployedPolicy;
use crate::error::MoeError;

/// The mixture at `n` states, in raw action space: `log q(z|s)` (`n·Z`), means `μ_z(s)`
/// (`n·Z·d`) and lower-triangular scales `L_z(s)` (`n·Z·d·d`, row-major), all row-major in
/// that order of indices, so that `q(a|s) = Σ_z q(z|s) N(a; μ_z, L_z L_zᵀ)` is the density
/// [`Policy::act`] samples from (with the action normaliser folded in:
/// `μ = offset + scale ⊙ μ̃`, `L = diag(scale) L̃`).
///
/// Acting by hand: pick `z` with probability `exp(log_gating[z])` (or the largest for greedy
/// gating), then `a = μ_z` (the mean; what the recipes evaluate) or `a = μ_z + L_z ε` with
/// `ε ~ N(0, I)`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Components {
    /// Number of states `n`.
    pub n: usize,
    /// Number of experts `Z`.
    pub num_experts: usize,
    /// Action dimension `d` (a whole chunk for chunked policies).
    pub action_dim: usize,
    /// `log q(z|s)`, `n·Z`.
    pub log_gating: Vec<f32>,
    /// Means, `n·Z·d`.
    pub means: Vec<f32>,
    /// Lower-triangular scale factors, `n·Z·d·d`.
    pub scale_tril: Vec<f32>,
}

impl<E: Expert> Moe<E> {
    /// The mixture's components at `n x obs_dim` observations (the mixture's own observations:
    /// normalised here by its observation normaliser), in raw action space (see
    /// [`Components`]).
    ///
    /// ```
    /// use vdd_core::Policy;
    /// use vdd_moe::{ActMode, Moe, MoeConfig};
    ///
    /// let mut moe = Moe::from_config(MoeConfig::toy(2, 1, 3), 0)?;
    /// moe.set_act_mode(ActMode { greedy_gating: true, sample_action: false, hold_steps: 0 });
    /// let obs = faer::mat![[0.1f32, 0.2]];
    /// let c = moe.components(obs.as_ref())?;
    /// assert_eq!((c.means.len(), c.scale_tril.len(), c.log_gating.len()), (3, 3, 3));
    /// // Uniform gating: the greedy pick is expert 0, and acting returns its mean.
    /// assert_eq!(moe.act(&[0.1, 0.2])?, vec![c.means[0]]);
    /// # Ok::<(), vdd_moe::MoeError>(())
    /// ```
    pub fn components(&mut self, obs: MatRef<'_, f32>) -> Result<Components, MoeError> {
        self.forward_observations(obs)?;
        let (n, z, d) = (obs.nrows(), self.config.num_experts, self.config.action_dim);
        let mut c = Components {
            n,
            num_experts: z,
            action_dim: d,
            log_gating: self.out.log_gating[..n * z].to_vec(),
            means: self.out.means[..n * z * d].to_vec(),
            scale_tril: self.out.scales[..n * z * d * d].to_vec(),
        };
        if let Some(norm) = &self.action_normalizer {
            for mean in c.means.chunks_exact_mut(d) {
                norm.denormalize(mean);
            }
            for l in c.scale_tril.chunks_exact_mut(d * d) {
                for (i, row) in l.chunks_exact_mut(d).enumerate() {
                    for v in row {
                        *v *= norm.scale[i];
                    }
                }
            }
        }
        Ok(c)
    }
}

/// The raw observation windows `n x (obs_window · obs_dim)` of a deployed policy (oldest
/// observation first, each `obs_dim` raw entries, as [`DeployedPolicy::act`] would have
/// stacked them) as the mixture's observations: the spec's feature map applied to each.
/// With the identity spec (window 1, identity features) the rows are unchanged.
pub fn mixture_observations(
    policy: &DeployedPolicy,
    windows: MatRef<'_, f32>,
) -> Result<Mat<f32>, MoeError> {
    let spec = policy.spec();
    let (k, w) = (policy.obs_dim(), spec.obs_window);
    check_shape("observation windows", windows, windows.nrows(), w * k)?;
    let map = spec.validate()?;
    let mut out = windows.to_owned();
    if !map.is_identity() {
        let mut row = vec![0.0f32; k];
        for i in 0..out.nrows() {
            for slot in 0..w {
                for (j, x) in row.iter_mut().enumerate() {
                    *x = out[(i, slot * k + j)];
                }
                map.apply(&mut row);
                for (j, x) in row.iter().enumerate() {
                    out[(i, slot * k + j)] = *x;
                }
            }
        }
    }
    Ok(out)
}

/// [`Moe::components`] of a deployed policy at raw observation windows (see
/// [`mixture_observations`]); the actions are whole chunks (`action_chunk · action_dim`).
pub fn deployed_components(
    policy: &mut DeployedPolicy,
    windows: MatRef<'_, f32>,
) -> Result<Components, MoeError> {
    let obs = mixture_observations(policy, windows)?;
    policy.inner_mut().components(obs.as_ref())
}

/// The exact `log q(chunk | window)` of a deployed policy for raw observation windows
/// `n x (obs_window · obs_dim)` (see [`mixture_observations`]) and raw action chunks
/// `n x (action_chunk · action_dim)`, into `out` (length `n`).
pub fn deployed_log_likelihood(
    policy: &mut DeployedPolicy,
    windows: MatRef<'_, f32>,
    chunks: MatRef<'_, f32>,
    out: &mut [f32],
) -> Result<(), MoeError> {
    let obs = mixture_observations(policy, windows)?;
    Ok(policy.inner_mut().log_likelihood(obs.as_ref(), chunks, out)?)
}
