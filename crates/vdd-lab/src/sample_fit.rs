//! A student fitted to its teacher's own samples before VDD refines it through the score
//! (`[imported.fit]` of the Avoiding recipes).
//!
//! For a teacher whose actions are whole chunks (an imported U-Net: 16 steps × 2 dimensions),
//! the paper's start (every expert at the origin with unit scale, queried at small noise)
//! leaves each expert to find a 32-D route through the score alone, and they all land on one.
//! The teacher can sample, so the student starts where its samples are: at a subset of the data
//! states the teacher draws `samples_per_state` chunks each (in fixed blocks of states, each on a
//! copy of the teacher with a random stream of its own, so both cores work and the draws do not
//! depend on the thread count), and EM fits the mixture to those pairs by maximum likelihood.
//! VDD then continues from that mixture.

use faer::{Mat, MatRef};
use serde::{Deserialize, Serialize};
use vdd_core::{ScoreModel, Seeds};
use vdd_mixture::{Dataset, Em, EmConfig};
use vdd_moe::Moe;
use vdd_nn::parallel::{Workers, chunk_range};

/// How the student is fitted to the teacher's samples.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct SampleFit {
    /// Data states the teacher samples at (evenly spaced over the data; 0 or more than the data
    /// has: all of them).
    pub states: usize,
    /// Teacher samples per state.
    pub samples_per_state: usize,
    /// The states in this many blocks, each sampled on its own copy of the teacher with its
    /// own random stream: the samples depend on it, never on the number of threads.
    pub blocks: usize,
    /// EM on the (state, sample) pairs; its `seed` is replaced by the run seed.
    pub em: EmConfig,
}

impl SampleFit {
    /// Checks ranges.
    pub fn validate(&self) -> crate::Result {
        if self.samples_per_state == 0 || self.blocks == 0 || self.blocks > 4096 {
            return Err(format!(
                "imported.fit: samples_per_state must be ≥ 1 and blocks in 1..=4096 (got {} and {})",
                self.samples_per_state, self.blocks
            )
            .into());
        }
        self.em.validate()?;
        Ok(())
    }

    /// Draws the teacher's samples at `states` (the teacher's space, one row per state) and
    /// returns the pairs: every selected state repeated `samples_per_state` times, beside one
    /// sample each. `progress` is called once per block.
    pub fn draw<T: ScoreModel + Clone + Send>(
        &self,
        teacher: &T,
        states: MatRef<'_, f32>,
        seed: u64,
        progress: &(dyn Fn() + Sync),
    ) -> crate::Result<(Mat<f32>, Mat<f32>)> {
        let n = states.nrows();
        let m = if self.states == 0 { n } else { self.states.min(n) };
        if m == 0 {
            return Err("imported.fit: no states to sample the teacher at".into());
        }
        let rows = m * self.samples_per_state;
        let picked = Mat::from_fn(rows, states.ncols(), |r, j| {
            states[((r / self.samples_per_state) * n / m, j)]
        });
        let d = teacher.action_dim();
        let blocks = self.blocks.min(rows);
        let seeds = Seeds::new(seed).child("sample-fit");
        let mut outs: Vec<(T, Mat<f32>, Option<vdd_core::CoreError>)> = (0..blocks)
            .map(|b| (teacher.clone(), Mat::zeros(chunk_range(rows, blocks, b).len(), d), None))
            .collect();
        Workers::new(0)?.for_each_mut(&mut outs, |b, (t, out, err)| {
            let range = chunk_range(rows, blocks, b);
            let mut rng = seeds.stream_indexed("block", b as u64);
            let cond = picked.as_ref().subrows(range.start, range.len());
            if let Err(e) = t.sample_actions(cond, &mut rng, out.as_mut()) {
                *err = Some(e);
            }
            progress();
        });
        let mut actions = Mat::zeros(rows, d);
        for (b, (_, out, err)) in outs.into_iter().enumerate() {
            if let Some(e) = err {
                return Err(e.into());
            }
            let range = chunk_range(rows, blocks, b);
            actions.as_mut().subrows_mut(range.start, range.len()).copy_from(out.as_ref());
        }
        if actions.col_iter().any(|c| c.iter().any(|v| !v.is_finite())) {
            return Err("imported.fit: the teacher's samples are not finite".into());
        }
        Ok((picked, actions))
    }

    /// Fits `student` (already in the space of `states` and `actions`) to the pairs by EM with
    /// the run's `seed`; `report` sees each iteration's log-likelihood.
    pub fn fit(
        &self,
        student: Moe,
        states: Mat<f32>,
        actions: Mat<f32>,
        seed: u64,
        mut report: impl FnMut(f64),
    ) -> crate::Result<Moe> {
        let config = EmConfig { seed, ..self.em.clone() };
        let mut em = Em::new(config, student, Dataset::new(states, actions)?)?;
        em.train(|m| report(m.log_likelihood))?;
        Ok(em.into_student())
    }
}
