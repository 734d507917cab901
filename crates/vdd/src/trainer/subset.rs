//! The experts each state of an expert step trains ([`VddConfig::experts_per_state`]).

use rand::Rng;
use vdd_core::{Expert, ScoreModel};

use super::Vdd;
#[cfg(doc)]
use crate::config::VddConfig;
use crate::expert_step::ExpertSubset;

impl<S: ScoreModel, E: Expert> Vdd<S, E> {
    /// Experts trained per state in an expert step: [`VddConfig::experts_per_state`] when it
    /// is below the number of experts, else all of them.
    pub(super) fn slots(&self) -> usize {
        let z_n = self.student.num_experts();
        self.config.experts_per_state.map_or(z_n, |k| k.min(z_n))
    }

    /// Draws the experts of expert step `stream` into `self.subset` (left empty when every
    /// state trains every expert): a permutation of the experts from the step's own stream,
    /// dealt out `k` at a time to the states in batch order, wrapping around.
    pub(super) fn draw_subset(&mut self, stream: u64) {
        let (z_n, k) = (self.student.num_experts(), self.slots());
        self.subset.clear();
        if k == z_n {
            return;
        }
        let mut rng = self.seeds.stream_indexed("expert-subset", stream);
        // The permutation in the first Z entries, then dealt out after them.
        self.subset.extend(0..z_n as u32);
        for i in (1..z_n).rev() {
            self.subset.swap(i, rng.random_range(0..=i));
        }
        let n = self.config.batch_size * k;
        for i in 0..n {
            self.subset.push(self.subset[i % z_n]);
        }
        self.subset.drain(..z_n);
    }
}

/// The [`ExpertSubset`] of `k` experts per state drawn into `subset`
/// ([`Vdd::draw_subset`]), `None` when it is empty (every state trains every expert).
pub(super) fn expert_subset(subset: &[u32], k: usize) -> Option<ExpertSubset<'_>> {
    (!subset.is_empty()).then_some(ExpertSubset { experts: subset, per_state: k })
}
