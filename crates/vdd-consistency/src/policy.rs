//! A distilled network as a [`vdd_core::Policy`] ([`DistilledPolicy`]): raw observations in,
//! the method's sampler ([`Sampling`]) in the teacher's normalised space, raw actions out.

use faer::reborrow::{Reborrow, ReborrowMut};
use faer::{Mat, MatMut, MatRef};
use rand::RngCore;
use vdd_core::{
    Affine, CoreError, Policy, Seeds, check_act_args, check_finite, check_len, check_shape,
};
use vdd_diffusion::{DenoiserNet, DiffusionError, RowCoefficients};

use crate::config::ConsistencyConfig;
use crate::error::ConsistencyError;
use crate::network::{ensure, fill_normal};

mod io;
pub use io::SavedKind;

/// The `n ≥ 1` Karras levels from `σ_max` down to `σ_min` (without the trailing 0).
pub(crate) fn karras_levels(
    n: usize,
    sigma_min: f32,
    sigma_max: f32,
    rho: f32,
) -> Result<Vec<f32>, DiffusionError> {
    let mut v = vdd_diffusion::karras_sigmas(n, sigma_min, sigma_max, rho)?;
    v.pop();
    Ok(v)
}

/// How a distilled network samples: from noise `x = σ_max z` at `levels[0] = σ_max` down to
/// `levels[k] = σ_min` with `k` network evaluations, in the normalised space; step `i`
/// evaluates the network on `x` from `levels[i]` towards `levels[i + 1]` (`sample_along`).
pub trait Sampling: Copy {
    /// Number of noise conditions of the network.
    const LEVELS: usize;

    /// Writes into `coef` (cleared first) the coefficients of the evaluation taking each row
    /// from its level `t` towards its level `u`.
    fn coefficients(&self, coef: &mut RowCoefficients, t: &[f32], u: &[f32]);

    /// Every step but the first starts from the previous step's output plus fresh noise of
    /// this standard deviation at the step's `level`, or (`None`) from the output itself,
    /// without drawing.
    fn fresh_noise_std(&self, level: f32) -> Option<f32>;
}

/// Writes one sample per row of `states` into `out` along `levels` with `pre`'s steps.
fn sample_along<P: Sampling>(
    pre: &P,
    net: &mut DenoiserNet,
    levels: &[f32],
    scratch: &mut SampleScratch,
    states: MatRef<'_, f32>,
    rng: &mut dyn RngCore,
    mut out: MatMut<'_, f32>,
) {
    let (n, d) = (out.nrows(), out.ncols());
    scratch.start(n, d, levels[0], rng);
    for (k, w) in levels.windows(2).enumerate() {
        if k > 0 {
            match pre.fresh_noise_std(w[0]) {
                Some(std) => {
                    scratch.start(n, d, std, rng);
                    for j in 0..d {
                        let x = scratch.x.col_as_slice_mut(j);
                        for i in 0..n {
                            x[i] += out[(i, j)];
                        }
                    }
                }
                None => scratch.x.copy_from(out.rb()),
            }
        }
        scratch.set_levels(n, w[0], w[1]);
        pre.coefficients(&mut scratch.coef, &scratch.t, &scratch.u);
        net.forward_preconditioned_inference(
            scratch.x.as_ref(),
            states,
            &scratch.coef,
            out.rb_mut(),
        );
    }
}

/// Reused buffers of sampling.
#[derive(Debug, Clone)]
pub struct SampleScratch {
    pub(crate) x: Mat<f32>,
    pub(crate) t: Vec<f32>,
    pub(crate) u: Vec<f32>,
    pub(crate) coef: RowCoefficients,
}

impl Default for SampleScratch {
    fn default() -> Self {
        Self { x: Mat::zeros(0, 0), t: Vec::new(), u: Vec::new(), coef: RowCoefficients::default() }
    }
}

impl SampleScratch {
    /// `x = σ z` for an `n x d` batch.
    pub(crate) fn start(&mut self, n: usize, d: usize, sigma: f32, rng: &mut dyn RngCore) {
        ensure(&mut self.x, n, d);
        fill_normal(&mut self.x, rng);
        for j in 0..d {
            for v in self.x.col_as_slice_mut(j) {
                *v *= sigma;
            }
        }
    }

    /// Sets the per-row levels `t` and `u` to constants for `n` rows.
    pub(crate) fn set_levels(&mut self, n: usize, t: f32, u: f32) {
        self.t.clear();
        self.t.resize(n, t);
        self.u.clear();
        self.u.resize(n, u);
    }
}

/// A distilled network as a [`Policy`]: the teacher's normalisers around the method's
/// sampler — raw observations in, raw actions out, one network evaluation per sampling step.
/// Used as [`crate::ConsistencyModel`] and [`crate::TrajectoryModel`], which add the
/// method's own functions (the consistency function; the jump and the denoiser); see
/// [`crate::CdTrainer`] for an example.
#[derive(Debug, Clone)]
pub struct DistilledPolicy<P> {
    pub(crate) net: DenoiserNet,
    pub(crate) pre: P,
    sigma_min: f32,
    sigma_max: f32,
    rho: f32,
    /// `σ_max = l_0 > … > l_k = σ_min`.
    levels: Vec<f32>,
    state_norm: Affine,
    action_norm: Affine,
    rng: vdd_core::Rng,
    stream: &'static str,
    obs: Mat<f32>,
    act: Mat<f32>,
    pub(crate) scratch: SampleScratch,
    deploy_spec: vdd_data::DeploySpec,
}

impl<P: Sampling> DistilledPolicy<P> {
    /// Assembles a policy; `config` gives the levels and the sampling steps.
    pub(crate) fn new(
        net: DenoiserNet,
        pre: P,
        config: &ConsistencyConfig,
        (state_norm, action_norm): (Affine, Affine),
        seed: u64,
        stream: &'static str,
    ) -> Result<Self, ConsistencyError> {
        check_len("network noise conditions", net.levels(), P::LEVELS)?;
        check_len("state normaliser", state_norm.dim(), net.state_dim())?;
        check_len("action normaliser", action_norm.dim(), net.action_dim())?;
        let mut policy = Self {
            net,
            pre,
            sigma_min: config.sigma_min,
            sigma_max: config.sigma_max,
            rho: config.rho,
            levels: Vec::new(),
            state_norm,
            action_norm,
            rng: Seeds::new(seed).stream(stream),
            stream,
            obs: Mat::zeros(0, 0),
            act: Mat::zeros(0, 0),
            scratch: SampleScratch::default(),
            deploy_spec: vdd_data::DeploySpec::identity(),
        };
        policy.set_sampling_steps(config.sampling_steps)?;
        Ok(policy)
    }

    /// How the policy acts on raw observations (features, observation window, action chunk):
    /// saved with it ([`DistilledPolicy::save`]); the identity unless set.
    pub fn deploy_spec(&self) -> &vdd_data::DeploySpec {
        &self.deploy_spec
    }

    /// Sets [`DistilledPolicy::deploy_spec`], checked against the policy's state and action
    /// dimensions.
    pub fn set_deploy_spec(&mut self, spec: vdd_data::DeploySpec) -> Result<(), ConsistencyError> {
        spec.check_policy_dims(self.net.state_dim(), self.net.action_dim())?;
        self.deploy_spec = spec;
        Ok(())
    }

    /// The network `F`.
    pub fn net(&self) -> &DenoiserNet {
        &self.net
    }

    /// The preconditioning.
    pub fn preconditioning(&self) -> P {
        self.pre
    }

    /// The `(state, action)` normalisers (the teacher's).
    pub fn normalizers(&self) -> (&Affine, &Affine) {
        (&self.state_norm, &self.action_norm)
    }

    /// The sampling levels `σ_max = l_0 > … > l_k = σ_min` (`k` network evaluations per
    /// action).
    pub fn sampling_levels(&self) -> &[f32] {
        &self.levels
    }

    /// Sets `k ≥ 1` sampling steps along a `(k + 1)`-level Karras grid from `σ_max` to
    /// `σ_min`.
    pub fn set_sampling_steps(&mut self, steps: usize) -> Result<(), ConsistencyError> {
        if steps == 0 {
            return Err(CoreError::Config("sampling steps must be >= 1".into()).into());
        }
        self.levels = karras_levels(steps + 1, self.sigma_min, self.sigma_max, self.rho)?;
        Ok(())
    }

    /// Sets explicit sampling levels: strictly decreasing, all above `σ_min` (which is
    /// appended as the last level).
    pub fn set_sampling_levels(&mut self, levels: &[f32]) -> Result<(), ConsistencyError> {
        let ok = !levels.is_empty()
            && levels.iter().all(|s| s.is_finite() && *s > self.sigma_min)
            && levels.windows(2).all(|w| w[1] < w[0]);
        if !ok {
            return Err(CoreError::Config(format!(
                "sampling levels must be finite, above sigma_min = {} and strictly decreasing, \
                 got {levels:?}",
                self.sigma_min
            ))
            .into());
        }
        self.levels.clear();
        self.levels.extend_from_slice(levels);
        self.levels.push(self.sigma_min);
        Ok(())
    }

    /// Checks normalised model inputs: `x` `n x d_a` and `states` `n x d_s` finite, `out`
    /// `n x d_a`, and positive finite levels of length `n`.
    pub(crate) fn check_model_batch(
        &self,
        x: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        levels: &[&[f32]],
        out: MatRef<'_, f32>,
    ) -> Result<(), CoreError> {
        let n = x.nrows();
        check_shape("x", x, n, self.net.action_dim())?;
        check_shape("states", states, n, self.net.state_dim())?;
        check_shape("output", out, n, self.net.action_dim())?;
        check_finite("x", x)?;
        check_finite("states", states)?;
        for l in levels {
            check_len("noise levels", l.len(), n)?;
            if !l.iter().all(|s| s.is_finite() && *s > 0.0) {
                return Err(CoreError::Config("noise levels must be positive and finite".into()));
            }
        }
        Ok(())
    }

    /// Samples one action per row of normalised `states` into `out` (normalised space) with
    /// the configured steps, drawing noise from `rng`.
    pub fn sample(
        &mut self,
        states: MatRef<'_, f32>,
        rng: &mut dyn RngCore,
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let n = states.nrows();
        check_shape("states", states, n, self.net.state_dim())?;
        check_finite("states", states)?;
        check_shape("sampled actions", out.rb(), n, self.net.action_dim())?;
        let Self { net, pre, levels, scratch, .. } = self;
        sample_along(pre, net, levels, scratch, states, rng, out.rb_mut());
        Ok(())
    }

    /// `out = skip · x + out · F(c_in · x, states, …)` with the coefficients that
    /// `coefficients(pre, coef)` writes, for inputs that [`DistilledPolicy::check_model_batch`]
    /// accepted.
    pub(crate) fn forward_with(
        &mut self,
        x: MatRef<'_, f32>,
        states: MatRef<'_, f32>,
        out: MatMut<'_, f32>,
        coefficients: impl FnOnce(&P, &mut RowCoefficients),
    ) {
        let Self { net, pre, scratch, .. } = self;
        coefficients(pre, &mut scratch.coef);
        net.forward_preconditioned_inference(x, states, &scratch.coef, out);
    }
}

impl<P: Sampling> Policy for DistilledPolicy<P> {
    fn obs_dim(&self) -> usize {
        self.state_norm.dim()
    }

    fn action_dim(&self) -> usize {
        self.action_norm.dim()
    }

    fn seed(&mut self, seed: u64) {
        self.rng = Seeds::new(seed).stream(self.stream);
    }

    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> Result<(), CoreError> {
        check_act_args(self, obs, action)?;
        let (ds, da) = (self.obs_dim(), self.action_dim());
        self.act_batch(
            MatRef::from_row_major_slice(obs, 1, ds),
            MatMut::from_row_major_slice_mut(action, 1, da),
        )
    }

    /// Normalises the observations, samples, denormalises the actions.
    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        mut actions: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        let (n, ds, da) = (obs.nrows(), self.obs_dim(), self.action_dim());
        check_shape("observations", obs, n, ds)?;
        check_finite("observations", obs)?;
        check_shape("actions", actions.rb(), n, da)?;
        ensure(&mut self.obs, n, ds);
        ensure(&mut self.act, n, da);
        for j in 0..ds {
            let (o, s) = (self.state_norm.offset[j], self.state_norm.scale[j]);
            let dst = self.obs.col_as_slice_mut(j);
            for i in 0..n {
                dst[i] = (obs[(i, j)] - o) / s;
            }
        }
        let Self { net, pre, levels, scratch, rng, obs, act, .. } = self;
        sample_along(pre, net, levels, scratch, obs.as_ref(), rng, act.as_mut());
        for j in 0..da {
            let (o, s) = (self.action_norm.offset[j], self.action_norm.scale[j]);
            let src = self.act.col_as_slice(j);
            for i in 0..n {
                actions[(i, j)] = src[i] * s + o;
            }
        }
        Ok(())
    }
}
