//! The rounds on the states the student itself visits: `vdd.<teacher>_expert_visits` (the
//! distillation continued there) and `vdd.<teacher>_gating_visits` (the gating fit there).

use faer::Mat;
use rand::Rng as _;
use serde::{Deserialize, Serialize};
use vdd::{DistillData, VddConfig};
use vdd_core::Affine;
use vdd_moe::cache::CachedStudent;

use super::{DistillRun, distill};
use crate::method::Job;
use crate::teachers;

/// `vdd.<teacher>_expert_visits`: after the distillation of `vdd.<teacher>`, continue it on
/// the states the student itself visits (DAgger for the experts; issue 33, "states beyond
/// the demonstrations"). Each round rolls the current student out for `episodes` episodes
/// (a seed stream of its own, apart from every evaluation), adds the states it acted on to
/// the states distilled on, and runs `iterations` more VDD iterations from the current
/// student on all of them (`vdd.<teacher>` with its iterations replaced: a learning-rate
/// schedule of its own). The teacher labels the new states through its score, as any other.
/// The budget counts every round: `vdd.<teacher>.iterations + rounds × iterations`.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct ExpertVisits {
    /// Student episodes per round.
    pub episodes: usize,
    /// Rounds of roll-out-and-distil (at least 1).
    pub rounds: usize,
    /// VDD iterations per round (at least 1).
    pub iterations: usize,
}

/// `vdd.<teacher>_gating_visits`: fit the gating of `vdd.<teacher>_gating_fit` on the states
/// the student itself visits as well as on the demonstrations' (DAgger-style aggregation; the
/// teacher labels every state through its samples). Each round rolls the student out (with
/// the gating of the round before, uniform in the first), adds the states it acted on to the
/// fit's states and fits again from the current gating.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct GatingVisits {
    /// Student episodes per round (their own seed stream, apart from every evaluation).
    pub episodes: usize,
    /// Rounds of roll-out-and-fit (at least 1).
    pub rounds: usize,
}

/// Most rounds and episodes per round of [`GatingVisits`].
pub(super) const MAX_VISIT_ROUNDS: usize = 16;
pub(super) const MAX_VISIT_EPISODES: usize = 100_000;
/// Most VDD iterations per round of [`ExpertVisits`].
pub(super) const MAX_VISIT_ITERATIONS: usize = 10_000_000;

/// `states` with the `visited` states below them (the same columns, or an internal error).
pub(super) fn stacked(states: &Mat<f32>, visited: &Mat<f32>) -> crate::Result<Mat<f32>> {
    if visited.ncols() != states.ncols() {
        return Err(format!(
            "internal: visited states have {} columns, the data {}",
            visited.ncols(),
            states.ncols()
        )
        .into());
    }
    let n = states.nrows();
    Ok(Mat::from_fn(n + visited.nrows(), states.ncols(), |i, j| {
        if i < n { states[(i, j)] } else { visited[(i - n, j)] }
    }))
}

/// Continues the distillation of `c` on the states the student visits ([`ExpertVisits`]):
/// each round adds the states of `v.episodes` student episodes (raw, normalised by `sn`) to
/// the demonstrations' `(states, actions)` and runs `v.iterations` more iterations of `vc`
/// from the current student (the demonstrations stay the gating step's pairs). No curves or
/// checkpoint selection; each round checkpoints under a directory of its own.
pub(super) fn distill_on_visits(
    mut c: CachedStudent,
    (v, vc, sn): (ExpertVisits, &VddConfig, &Affine),
    t: &teachers::TrainedTeacher,
    (mut states, actions): (Mat<f32>, Mat<f32>),
    run: DistillRun<'_>,
) -> crate::Result<CachedStudent> {
    let DistillRun { clip_margin, job, policy, .. } = run;
    let visits = job.visits.ok_or("the task has no rollouts to visit states")?;
    let root = vdd_core::Seeds::new(job.seed).child("expert-visits");
    for round in 0..v.rounds {
        let t0 = std::time::Instant::now();
        let visit_seed: u64 = root.stream_indexed("episodes", round as u64).random();
        let visited = visits.visit(&policy(c.student.clone())?, visit_seed, v.episodes)?;
        let visited = sn.normalize_rows(visited.as_ref())?;
        states = stacked(&states, &visited)?;
        crate::progress::log(format!(
            "[{}] expert round {}: the student visited {} states in {} episodes; distilling on \
             {} states",
            job.label,
            round + 1,
            visited.nrows(),
            v.episodes,
            states.nrows()
        ));
        let label = format!("{} visits {}", job.label, round + 1);
        let stage = Job { label: &label, students: None, curves: None, ..*job };
        let vc = VddConfig {
            iterations: v.iterations,
            seed: root.stream_indexed("vdd", round as u64).random(),
            ..vc.clone()
        };
        let data = DistillData::new(states.clone(), None)?
            .with_gating_pairs(states.subrows(0, actions.nrows()).to_owned(), actions.clone())?;
        let run = DistillRun { clip_margin, job: &stage, policy, select_by: None };
        let (next, _, _, _) = distill(vc, t.teacher.clone(), c.student, data, run)?;
        c = CachedStudent {
            student: next.student,
            train_seconds: c.train_seconds + t0.elapsed().as_secs_f64(),
            curves: c.curves,
        };
    }
    Ok(c)
}
