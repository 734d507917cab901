//! Trained policies of every method as one evaluable type. (Observation windows and action
//! chunks at rollout time are `vdd_data::Windowed`; the µs-per-action measurement is
//! `vdd_tasks::timing`.)

use faer::{MatMut, MatRef};
use vdd_consistency::{ConsistencyModel, TrajectoryModel};
use vdd_core::Policy;
use vdd_diffusion::DiffusionTeacher;
use vdd_moe::Moe;

/// A trained policy of any method.
#[derive(Debug, Clone)]
pub enum TrainedPolicy {
    /// A diffusion teacher (DDPM, BESO, and their one-step versions).
    Teacher(Box<DiffusionTeacher>),
    /// A mixture of experts (VDD, EM, IMC).
    Moe(Box<Moe>),
    /// A consistency model (CD).
    Consistency(Box<ConsistencyModel>),
    /// A consistency trajectory model (CTM).
    Trajectory(Box<TrajectoryModel>),
    /// Any other policy: a method of its own (in this crate or outside it) returns its policy
    /// type here without a new variant ([`AnyPolicy`]).
    Other(Box<dyn AnyPolicy>),
}

/// A policy that [`TrainedPolicy::Other`] can hold: every [`Policy`] that is `Clone`,
/// `Debug`, `Send` and `'static` is one.
///
/// ```
/// use vdd_lab::policy::TrainedPolicy;
/// use vdd_core::Policy;
///
/// #[derive(Debug, Clone)]
/// struct Still;
/// impl Policy for Still {
///     fn obs_dim(&self) -> usize { 2 }
///     fn action_dim(&self) -> usize { 2 }
///     fn act_into(&mut self, _obs: &[f32], a: &mut [f32]) -> vdd_core::Result<()> {
///         a.fill(0.0);
///         Ok(())
///     }
/// }
/// let mut p = TrainedPolicy::Other(Box::new(Still));
/// assert_eq!(p.clone().act(&[0.5, 0.5])?, vec![0.0, 0.0]);
/// # Ok::<(), vdd_core::CoreError>(())
/// ```
pub trait AnyPolicy: Policy + std::fmt::Debug + Send {
    /// A boxed copy.
    fn clone_box(&self) -> Box<dyn AnyPolicy>;
}

impl<T: Policy + std::fmt::Debug + Clone + Send + 'static> AnyPolicy for T {
    fn clone_box(&self) -> Box<dyn AnyPolicy> {
        Box::new(self.clone())
    }
}

impl Clone for Box<dyn AnyPolicy> {
    fn clone(&self) -> Self {
        // On the policy inside: the box is itself an `AnyPolicy`.
        (**self).clone_box()
    }
}

impl TrainedPolicy {
    /// Saves the policy to one `safetensors` file with its deployment: a mixture, a diffusion
    /// teacher or a consistency or trajectory model (each type's own `save`, read back by its
    /// `load`); `Ok(false)` for a policy of another type ([`TrainedPolicy::Other`]), which is
    /// not saved.
    pub fn save(&self, path: &std::path::Path) -> crate::Result<bool> {
        match self {
            TrainedPolicy::Moe(moe) => moe.save(path)?,
            TrainedPolicy::Teacher(t) => t.save(path)?,
            TrainedPolicy::Consistency(m) => m.save(path)?,
            TrainedPolicy::Trajectory(m) => m.save(path)?,
            TrainedPolicy::Other(_) => return Ok(false),
        }
        Ok(true)
    }
}

macro_rules! each {
    ($self:expr, $p:ident => $e:expr) => {
        match $self {
            TrainedPolicy::Teacher($p) => $e,
            TrainedPolicy::Moe($p) => $e,
            TrainedPolicy::Consistency($p) => $e,
            TrainedPolicy::Trajectory($p) => $e,
            TrainedPolicy::Other($p) => $e,
        }
    };
}

impl Policy for TrainedPolicy {
    fn obs_dim(&self) -> usize {
        each!(self, p => Policy::obs_dim(p))
    }
    fn action_dim(&self) -> usize {
        each!(self, p => Policy::action_dim(p))
    }
    fn reset(&mut self) {
        each!(self, p => p.reset())
    }
    fn seed(&mut self, seed: u64) {
        each!(self, p => p.seed(seed))
    }
    fn last_experts(&self) -> &[usize] {
        each!(self, p => p.last_experts())
    }
    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
        each!(self, p => p.act_into(obs, action))
    }
    fn act_batch(
        &mut self,
        obs: MatRef<'_, f32>,
        actions: MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        each!(self, p => p.act_batch(obs, actions))
    }
}
