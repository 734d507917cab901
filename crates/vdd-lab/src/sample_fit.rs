//! A student fitted to its teacher's own samples before VDD refines it through the score
//! (`vdd.<teacher>_init_fit` of the recipes: the default of the imported
//! teacher's rows).
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

/// Most samples per state a fit draws.
pub const MAX_SAMPLES_PER_STATE: usize = 1024;
/// Most (state, sample) pairs a fit holds.
pub const MAX_PAIRS: usize = vdd_mixture::gating::MAX_PAIRS;

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
        let per = self.samples_per_state;
        if !(1..=MAX_SAMPLES_PER_STATE).contains(&per) || !(1..=4096).contains(&self.blocks) {
            return Err(format!(
                "samples_per_state must be in 1..={MAX_SAMPLES_PER_STATE} and blocks \
                 in 1..=4096 (got {per} and {})",
                self.blocks
            )
            .into());
        }
        self.em.validate()?;
        Ok(())
    }

    /// The states sampled at out of `n` data states (`states`; 0 or more than `n`: all).
    fn states_used(&self, n: usize) -> usize {
        if self.states == 0 { n } else { self.states.min(n) }
    }

    /// The rows the fit's expert steps process on a dataset of `data_states` states
    /// (`em.iterations × em.expert_steps_per_iter ×` the batch, the pairs when the batch is
    /// unset or larger): what it adds to the student's budget.
    ///
    /// ```
    /// # use vdd_lab::sample_fit::SampleFit;
    /// # use vdd_mixture::EmConfig;
    /// let em = EmConfig {
    ///     iterations: 500,
    ///     expert_steps_per_iter: 30,
    ///     batch_size: Some(256),
    ///     ..EmConfig::default()
    /// };
    /// let fit = SampleFit { states: 8192, samples_per_state: 2, blocks: 16, em };
    /// assert_eq!(fit.budget_samples(24_266), 500 * 30 * 256);
    /// // Four states, eight pairs: a batch of 256 is the whole set.
    /// assert_eq!(fit.budget_samples(4), 500 * 30 * 8);
    /// ```
    pub fn budget_samples(&self, data_states: usize) -> u64 {
        let m = self.states_used(data_states);
        let pairs = m.saturating_mul(self.samples_per_state);
        let batch = self.em.batch_size.unwrap_or(pairs).min(pairs) as u64;
        (self.em.iterations as u64)
            .saturating_mul(self.em.expert_steps_per_iter as u64)
            .saturating_mul(batch)
    }

    /// Draws the teacher's samples at `states` (the teacher's space, one row per state) and
    /// returns the pairs: every selected state repeated `samples_per_state` times, beside one
    /// sample each. The blocks run on `workers` (the same pairs for any number of threads);
    /// `progress` is called once per block.
    pub fn draw<T: ScoreModel + Clone + Send>(
        &self,
        teacher: &T,
        states: MatRef<'_, f32>,
        seed: u64,
        workers: &Workers,
        progress: &(dyn Fn() + Sync),
    ) -> crate::Result<(Mat<f32>, Mat<f32>)> {
        let n = states.nrows();
        let m = self.states_used(n);
        if m == 0 {
            return Err("no states to sample the teacher at".into());
        }
        self.validate()?;
        let rows =
            m.checked_mul(self.samples_per_state).filter(|&r| r <= MAX_PAIRS).ok_or_else(|| {
                format!("{m} states × {} samples is over {MAX_PAIRS} pairs", self.samples_per_state)
            })?;
        let picked = Mat::from_fn(rows, states.ncols(), |r, j| {
            states[((r / self.samples_per_state) * n / m, j)]
        });
        let d = teacher.action_dim();
        let blocks = self.blocks.min(rows);
        let seeds = Seeds::new(seed).child("sample-fit");
        let mut outs: Vec<(T, Mat<f32>, Option<vdd_core::CoreError>)> = (0..blocks)
            .map(|b| (teacher.clone(), Mat::zeros(chunk_range(rows, blocks, b).len(), d), None))
            .collect();
        workers.for_each_mut(&mut outs, |b, (t, out, err)| {
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
            return Err("the teacher's samples are not finite".into());
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

#[cfg(test)]
mod tests {
    use super::*;
    use faer::MatMut;
    use rand::RngCore;
    use vdd_core::CoreError;

    /// Samples `state + N(0, 1)` per dimension.
    #[derive(Clone)]
    struct Shifted;
    impl ScoreModel for Shifted {
        fn action_dim(&self) -> usize {
            2
        }
        fn state_dim(&self) -> usize {
            2
        }
        fn score(
            &mut self,
            a: MatRef<'_, f32>,
            s: MatRef<'_, f32>,
            _: &[f32],
            mut out: MatMut<'_, f32>,
        ) -> Result<(), CoreError> {
            for i in 0..a.nrows() {
                for j in 0..2 {
                    out[(i, j)] = s[(i, j)] - a[(i, j)];
                }
            }
            Ok(())
        }
        fn sample_actions(
            &mut self,
            s: MatRef<'_, f32>,
            rng: &mut dyn RngCore,
            mut out: MatMut<'_, f32>,
        ) -> Result<(), CoreError> {
            for i in 0..s.nrows() {
                for j in 0..2 {
                    out[(i, j)] = s[(i, j)] + vdd_core::standard_normal(rng);
                }
            }
            Ok(())
        }
    }

    fn fit(states: usize, blocks: usize) -> SampleFit {
        SampleFit { states, samples_per_state: 3, blocks, em: EmConfig::toy() }
    }

    #[test]
    fn the_samples_depend_on_the_blocks_and_the_seed_never_on_the_threads() {
        let states = Mat::from_fn(10, 2, |i, j| (i * 2 + j) as f32);
        let draw = |f: &SampleFit, seed, threads| {
            let workers = Workers::new(threads).unwrap();
            f.draw(&Shifted, states.as_ref(), seed, &workers, &|| {}).unwrap()
        };
        let (s, a) = draw(&fit(5, 4), 1, 1);
        // States 0, 2, 4, 6, 8, each three times.
        assert_eq!((s.nrows(), a.nrows()), (15, 15));
        assert!((0..15).all(|r| s[(r, 0)] == ((r / 3) * 4) as f32), "{s:?}");
        assert_eq!(draw(&fit(5, 4), 1, 3), (s.clone(), a.clone()));
        assert_ne!(draw(&fit(5, 2), 1, 1).1, a, "the blocks decide the streams");
        assert_ne!(draw(&fit(5, 4), 2, 1).1, a, "the seed decides the streams");
        assert_eq!(draw(&fit(0, 4), 1, 1).0.nrows(), 30, "0: every state");
    }

    #[test]
    fn bad_settings_and_teachers_that_cannot_sample_are_refused() {
        assert!(SampleFit { samples_per_state: 0, ..fit(5, 4) }.validate().is_err());
        assert!(fit(5, 0).validate().is_err());
        let huge = SampleFit { samples_per_state: MAX_SAMPLES_PER_STATE, ..fit(0, 4) };
        assert!(huge.validate().is_ok());
        let states = Mat::zeros(MAX_PAIRS / MAX_SAMPLES_PER_STATE + 1, 2);
        let e = huge.draw(&Shifted, states.as_ref(), 0, &Workers::inline(), &|| {}).unwrap_err();
        assert!(e.to_string().contains("pairs"), "{e}");
        assert!(fit(5, 4).validate().is_ok());
        /// A teacher without a sampler.
        #[derive(Clone)]
        struct ScoreOnly;
        impl ScoreModel for ScoreOnly {
            fn action_dim(&self) -> usize {
                1
            }
            fn state_dim(&self) -> usize {
                1
            }
            fn score(
                &mut self,
                _: MatRef<'_, f32>,
                _: MatRef<'_, f32>,
                _: &[f32],
                _: MatMut<'_, f32>,
            ) -> Result<(), CoreError> {
                Ok(())
            }
        }
        let states = Mat::zeros(4, 1);
        let w = Workers::inline();
        let e = fit(4, 2).draw(&ScoreOnly, states.as_ref(), 0, &w, &|| {}).unwrap_err();
        assert!(e.to_string().to_lowercase().contains("sampl"), "{e}");
    }
}
