//! **A gating fitted to a teacher's samples**: after a mixture's experts are trained (by VDD,
//! say, with a uniform gating), draw actions of a teacher policy at the training states and fit
//! a learned gating to them by maximum likelihood with the experts frozen ([`Em`] with
//! `expert_steps_per_iter = 0`).
//!
//! The gating that maximises `Σ log Σ_z q(z|s) N(a; μ_z(s), Σ_z(s))` over teacher samples
//! `a ~ π(·|s)` weighs each expert by how much of the teacher's action distribution it explains
//! at `s`. It starts from the uniform gating ([`Moe::add_learned_gating`]) when the mixture's
//! gating is uniform, from the current one otherwise.

use faer::{Mat, MatRef};
use rand::Rng as _;
use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Expert, Policy, Seeds, check_finite};
use vdd_moe::{Moe, NetworkConfig};
use vdd_nn::{AdamConfig, LrSchedule};

use crate::{Dataset, Em, EmConfig, MixtureError};

/// Most teacher samples per state [`fit_gating_to_policy`] accepts.
pub const MAX_SAMPLES_PER_STATE: usize = 1024;
/// Most state–sample pairs [`fit_gating_to_policy`] holds in memory.
pub const MAX_PAIRS: usize = 1 << 24;

/// Settings of [`fit_gating_to_policy`]; [`GatingFitConfig::default`] is what the Avoiding
/// lever measured.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(default, deny_unknown_fields)]
pub struct GatingFitConfig {
    /// Teacher samples drawn at each state.
    pub samples_per_state: usize,
    /// EM iterations: an E-step on every pair, then `steps_per_iter` gating steps.
    pub iterations: usize,
    /// Gating steps per iteration.
    pub steps_per_iter: usize,
    /// Pairs per gating step.
    pub batch_size: usize,
    /// Adam's learning rate of the gating, decaying linearly to 0 over the fit.
    pub lr: f32,
    /// Root seed of the teacher's draws and of the fit's minibatches.
    pub seed: u64,
    /// States beyond the given ones: this share of the pairs takes its state moved by Gaussian
    /// noise of standard deviation [`Self::state_noise_std`] in the student's normalised state
    /// space (the raw state plus `std · scale · ε`), drawn from a stream of its own, so that
    /// the gating also learns the teacher's weights a little off the training states, where a
    /// policy's rollouts drift. 0 (the default): every pair at a given state.
    pub state_noise_share: f32,
    /// The standard deviation of those moves (normalised units); 0: none.
    pub state_noise_std: f32,
}

impl Default for GatingFitConfig {
    /// 4 samples per state; 50 iterations of 30 steps of 256 pairs at learning rate `1e-3`.
    fn default() -> Self {
        Self {
            samples_per_state: 4,
            iterations: 50,
            steps_per_iter: 30,
            batch_size: 256,
            lr: 1e-3,
            seed: 0,
            state_noise_share: 0.0,
            state_noise_std: 0.0,
        }
    }
}

/// How far [`fit_gating_to_policy_with_progress`] has got.
#[derive(Debug, Clone, Copy, PartialEq)]
#[non_exhaustive]
pub enum GatingFitProgress {
    /// The teacher's samples are about to be drawn, `pairs` of them in one batch (a long call
    /// with a slow teacher; nothing is reported until it returns).
    Sampling {
        /// State–sample pairs drawn.
        pairs: usize,
    },
    /// An EM iteration of the fit is done.
    Iteration {
        /// 0-based index of the iteration.
        iteration: usize,
        /// Iterations of the fit ([`GatingFitConfig::iterations`]).
        iterations: usize,
        /// Mean log-likelihood of the teacher's samples at the iteration's E-step (nats).
        log_likelihood: f64,
    },
}

/// What [`fit_gating_to_policy`] did.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GatingFitReport {
    /// State–sample pairs fitted.
    pub pairs: usize,
    /// Mean log-likelihood of the teacher's samples under the mixture before the fit (nats,
    /// in the networks' normalised space).
    pub log_likelihood_before: f64,
    /// The same after the fit.
    pub log_likelihood_after: f64,
}

/// Draws `config.samples_per_state` actions of `teacher` at every row of `states` (raw
/// observations, as the teacher's [`Policy::act_batch`] takes them) and fits the gating of
/// `student` to them with the experts frozen. A uniform gating is first replaced by a learned
/// one of architecture `network` ([`Moe::add_learned_gating`]). The student's own normalisers
/// ([`Moe::normalizers`]) map the raw states and actions into its networks' space, so set them
/// first. The teacher is re-seeded from the stream `gating-fit-teacher` of `config.seed`.
///
/// ```
/// use faer::Mat;
/// use vdd_core::{CoreError, Policy};
/// use vdd_mixture::gating::{GatingFitConfig, fit_gating_to_policy};
/// use vdd_moe::{Moe, MoeConfig, NetworkConfig};
///
/// /// A teacher that always answers 1.0.
/// struct One;
/// impl Policy for One {
///     fn obs_dim(&self) -> usize { 1 }
///     fn action_dim(&self) -> usize { 1 }
///     fn act_into(&mut self, _: &[f32], a: &mut [f32]) -> Result<(), CoreError> {
///         a[0] = 1.0;
///         Ok(())
///     }
/// }
///
/// let mut config = MoeConfig::toy(1, 1, 2); // uniform gating
/// config.mean_bias_init = 1.0;
/// let student = Moe::from_config(config, 0)?;
/// let states = Mat::from_fn(64, 1, |i, _| i as f32 / 64.0);
/// let fit = GatingFitConfig { iterations: 10, batch_size: 64, lr: 1e-2, ..Default::default() };
/// let (student, report) =
///     fit_gating_to_policy(student, NetworkConfig::default(), &mut One, states.as_ref(), &fit)?;
/// assert!(student.has_learned_gating());
/// assert_eq!(report.pairs, 256);
/// assert!(report.log_likelihood_after > report.log_likelihood_before);
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
pub fn fit_gating_to_policy<E: Expert, P: Policy + ?Sized>(
    student: Moe<E>,
    network: NetworkConfig,
    teacher: &mut P,
    states: MatRef<'_, f32>,
    config: &GatingFitConfig,
) -> Result<(Moe<E>, GatingFitReport), MixtureError> {
    fit_gating_to_policy_with_progress(student, network, teacher, states, config, |_| {})
}

/// [`fit_gating_to_policy`], telling `progress` where it is: once before the teacher's samples
/// are drawn, then after every EM iteration. The fit is the same, bit for bit.
///
/// ```
/// use faer::Mat;
/// use vdd_core::{CoreError, Policy};
/// use vdd_mixture::gating::{GatingFitConfig, GatingFitProgress, fit_gating_to_policy_with_progress};
/// use vdd_moe::{Moe, MoeConfig, NetworkConfig};
///
/// struct One;
/// impl Policy for One {
///     fn obs_dim(&self) -> usize { 1 }
///     fn action_dim(&self) -> usize { 1 }
///     fn act_into(&mut self, _: &[f32], a: &mut [f32]) -> Result<(), CoreError> {
///         a[0] = 1.0;
///         Ok(())
///     }
/// }
///
/// let student = Moe::from_config(MoeConfig::toy(1, 1, 2), 0)?;
/// let states = Mat::from_fn(16, 1, |i, _| i as f32 / 16.0);
/// let fit = GatingFitConfig { iterations: 3, batch_size: 16, ..Default::default() };
/// let mut seen = Vec::new();
/// fit_gating_to_policy_with_progress(
///     student, NetworkConfig::default(), &mut One, states.as_ref(), &fit, |p| seen.push(p),
/// )?;
/// assert_eq!(seen.len(), 4);
/// assert!(matches!(seen[0], GatingFitProgress::Sampling { pairs: 64 }));
/// assert!(matches!(seen[3], GatingFitProgress::Iteration { iteration: 2, iterations: 3, .. }));
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
pub fn fit_gating_to_policy_with_progress<E: Expert, P: Policy + ?Sized>(
    mut student: Moe<E>,
    network: NetworkConfig,
    teacher: &mut P,
    states: MatRef<'_, f32>,
    config: &GatingFitConfig,
    mut progress: impl FnMut(GatingFitProgress),
) -> Result<(Moe<E>, GatingFitReport), MixtureError> {
    let k = config.samples_per_state;
    if !(1..=MAX_SAMPLES_PER_STATE).contains(&k) {
        return Err(config_error(format!(
            "samples_per_state must be in 1..={MAX_SAMPLES_PER_STATE}, got {k}"
        )));
    }
    if config.steps_per_iter == 0 {
        return Err(config_error("steps_per_iter must be positive".into()));
    }
    let n = states.nrows();
    let pairs = n.checked_mul(k).filter(|&p| p > 0 && p <= MAX_PAIRS).ok_or_else(|| {
        config_error(format!("{n} states x {k} samples: between 1 and {MAX_PAIRS} pairs needed"))
    })?;
    check_finite("gating-fit states", states)?;
    let (ds, da) = (student.config().state_dim, student.config().action_dim);
    vdd_core::check_len("gating-fit state columns", states.ncols(), ds)?;
    vdd_core::check_len("teacher action dimension", teacher.action_dim(), da)?;

    let (share, std) = (config.state_noise_share, config.state_noise_std);
    if !(0.0..=1.0).contains(&share) || !(0.0..=1e3).contains(&std) {
        return Err(config_error(format!(
            "state_noise_share must be in [0, 1] and state_noise_std in [0, 1000], got {share} \
             and {std}"
        )));
    }
    let mut raw_states = Mat::from_fn(pairs, ds, |i, j| states[(i % n, j)]);
    if share > 0.0 && std > 0.0 {
        let mut rng = Seeds::new(config.seed).stream("gating-fit-states");
        let scale = student.normalizers().0.map(|a| a.scale.clone());
        for i in 0..pairs {
            // One draw decides whether the pair moves, then one per dimension: the stream's
            // use does not depend on the outcome.
            let moves = rng.random::<f32>() < share;
            for j in 0..ds {
                let e: f32 = vdd_core::standard_normal(&mut rng);
                if moves {
                    raw_states[(i, j)] += std * e * scale.as_ref().map_or(1.0, |s| s[j]);
                }
            }
        }
    }
    let mut actions = Mat::zeros(pairs, da);
    progress(GatingFitProgress::Sampling { pairs });
    teacher.seed(Seeds::new(config.seed).stream("gating-fit-teacher").random());
    teacher.act_batch(raw_states.as_ref(), actions.as_mut())?;
    let (sn, an) = student.normalizers();
    let states = match sn {
        Some(sn) => sn.normalize_rows(raw_states.as_ref())?,
        None => raw_states,
    };
    let actions = match an {
        Some(an) => an.normalize_rows(actions.as_ref())?,
        None => actions,
    };
    let data = Dataset::new(states, actions)?;

    if !student.has_learned_gating() {
        student.add_learned_gating(network, config.seed)?;
    }
    let schedule = LrSchedule::LinearDecay { final_factor: 0.0 };
    let adam = AdamConfig { lr: config.lr, ..AdamConfig::default() };
    let em = EmConfig {
        iterations: config.iterations,
        expert_steps_per_iter: 0,
        gating_steps_per_iter: config.steps_per_iter,
        batch_size: Some(config.batch_size),
        gating_batch_size: Some(config.batch_size),
        expert_optimizer: adam,
        expert_lr_schedule: schedule.clone(),
        gating_optimizer: adam,
        gating_lr_schedule: schedule,
        max_grad_norm: None,
        seed: config.seed,
        e_step_rows: None,
    };
    let mut em = Em::new(em, student, data)?;
    let log_likelihood_before = em.log_likelihood()?;
    let iterations = config.iterations;
    em.train(|m| {
        progress(GatingFitProgress::Iteration {
            iteration: m.iteration,
            iterations,
            log_likelihood: m.log_likelihood,
        })
    })?;
    let log_likelihood_after = em.log_likelihood()?;
    let report = GatingFitReport { pairs, log_likelihood_before, log_likelihood_after };
    Ok((em.into_student(), report))
}

fn config_error(message: String) -> MixtureError {
    CoreError::Config(format!("gating fit: {message}")).into()
}

#[cfg(test)]
mod tests;
