//! Expert attribution for the Avoiding trajectory figure: which expert of a mixture acted at
//! each step of the recorded rollouts.

use vdd_core::Policy;
use vdd_data::Windowed;
use vdd_tasks::avoiding::EvalProtocol;
use vdd_tasks::avoiding::rollout::Evaluation;

use crate::policy::TrainedPolicy;

/// For each step of each of the first `n` recorded rollouts of `eval`, the expert the mixture
/// inside `policy` acted with ([`vdd_moe::Moe::last_experts`]): the evaluation units holding
/// those rollouts run again on this thread with a copy of the policy (the same seeds, so the
/// same rollouts, which is checked). Needs a mixture asked at every step for every row
/// (observation window and action chunk 1).
pub fn chosen_experts(
    policy: &Windowed<TrainedPolicy>,
    protocol: EvalProtocol,
    seed: u64,
    eval: &Evaluation,
    n: usize,
) -> crate::XResult<Vec<Vec<usize>>> {
    let unit = protocol.lockstep_batch.max(1);
    let rollouts = n.div_ceil(unit).saturating_mul(unit).min(protocol.rollouts);
    let cfg = EvalProtocol { rollouts, ..protocol }.config(seed, true);
    let mut log = ExpertLog { policy: policy.clone(), units: Vec::new() };
    let again = vdd_tasks::evaluate(&mut log, &cfg)?;
    if eval.rollouts.get(..rollouts) != Some(&again.rollouts[..]) {
        return Err("internal: the rollouts did not replay for expert attribution".into());
    }
    let mut out = Vec::with_capacity(n);
    for (i, r) in again.rollouts.iter().take(n).enumerate() {
        let steps = log.units.get(i / unit).map_or(&[][..], |u| &u[..]);
        let ids: Option<Vec<usize>> =
            (0..r.steps).map(|t| steps.get(t)?.get(i % unit).copied()).collect();
        out.push(ids.ok_or("internal: the mixture did not act for every row and step")?);
    }
    Ok(out)
}

/// A policy that logs, for each evaluation unit (from one `reset` to the next) and each call,
/// the expert of each row ([`vdd_moe::Moe::last_experts`]; nothing for other policies).
struct ExpertLog {
    policy: Windowed<TrainedPolicy>,
    units: Vec<Vec<Vec<usize>>>,
}

impl ExpertLog {
    fn log(&mut self) {
        let experts = match self.policy.inner() {
            TrainedPolicy::Moe(moe) => moe.last_experts().to_vec(),
            _ => Vec::new(),
        };
        if let Some(unit) = self.units.last_mut() {
            unit.push(experts);
        }
    }
}

impl Policy for ExpertLog {
    fn obs_dim(&self) -> usize {
        self.policy.obs_dim()
    }
    fn action_dim(&self) -> usize {
        self.policy.action_dim()
    }
    fn reset(&mut self) {
        self.policy.reset();
        self.units.push(Vec::new());
    }
    fn seed(&mut self, seed: u64) {
        self.policy.seed(seed);
    }
    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> vdd_core::Result<()> {
        self.policy.act_into(obs, action)?;
        self.log();
        Ok(())
    }
    fn act_batch(
        &mut self,
        obs: faer::MatRef<'_, f32>,
        actions: faer::MatMut<'_, f32>,
    ) -> vdd_core::Result<()> {
        self.policy.act_batch(obs, actions)?;
        self.log();
        Ok(())
    }
}
