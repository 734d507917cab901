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
}

macro_rules! each {
    ($self:expr, $p:ident => $e:expr) => {
        match $self {
            TrainedPolicy::Teacher($p) => $e,
            TrainedPolicy::Moe($p) => $e,
            TrainedPolicy::Consistency($p) => $e,
            TrainedPolicy::Trajectory($p) => $e,
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
