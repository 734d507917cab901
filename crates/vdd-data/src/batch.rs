//! Seeded, shuffling minibatches that reuse two buffers instead of allocating per batch.

use faer::{Mat, MatMut, MatRef};
use rand::seq::SliceRandom;
use vdd_core::{Rng, Seeds};

use crate::error::{DataError, Result};

/// Anything a [`Batcher`] can draw `(state, action)` rows from.
pub trait BatchSource {
    /// Number of samples.
    fn num_samples(&self) -> usize;
    /// Length of one state row.
    fn state_dim(&self) -> usize;
    /// Length of one action row.
    fn action_dim(&self) -> usize;
    /// Writes sample `sample` into row `row` of `states` (`_ x state_dim()`) and `actions`
    /// (`_ x action_dim()`), touching no other row.
    ///
    /// # Panics
    /// If `sample >= num_samples()` or `row` or the column counts are out of range.
    fn write_row(
        &self,
        sample: usize,
        row: usize,
        states: MatMut<'_, f32>,
        actions: MatMut<'_, f32>,
    );
}

/// Plain `(state, action)` pairs held as two matrices with one row per sample, for training
/// teachers and baselines on single-step data (e.g. from [`crate::Episodes::to_matrices`]).
///
/// ```
/// use faer::Mat;
/// use vdd_data::{Batcher, MatrixDataset};
/// let states = Mat::from_fn(10, 2, |i, j| (i * 2 + j) as f32);
/// let actions = Mat::from_fn(10, 1, |i, _| i as f32);
/// let data = MatrixDataset::new(states, actions).unwrap();
/// let mut batches = Batcher::new(&data, 4, 0).unwrap();
/// let (s, a) = batches.next_batch();
/// assert_eq!((s.nrows(), s.ncols(), a.ncols()), (4, 2, 1));
/// assert_eq!(s[(0, 0)], 2.0 * a[(0, 0)]);
/// ```
#[derive(Debug, Clone, PartialEq)]
pub struct MatrixDataset {
    states: Mat<f32>,
    actions: Mat<f32>,
}

impl MatrixDataset {
    /// Wraps `states` (`n x d_s`) and `actions` (`n x d_a`).
    ///
    /// Errors: [`DataError::Empty`] for `n = 0`, [`DataError::Shape`] for differing row counts
    /// or a zero dimension, [`DataError::NonFinite`] for NaN or infinite entries (reported with
    /// the row as `step`, episode 0).
    pub fn new(states: Mat<f32>, actions: Mat<f32>) -> Result<Self> {
        if states.nrows() != actions.nrows() {
            return Err(DataError::Shape {
                what: "action rows".into(),
                expected: format!("{} (one per state)", states.nrows()),
                got: actions.nrows().to_string(),
            });
        }
        if states.nrows() == 0 {
            return Err(DataError::Empty("no (state, action) pairs".into()));
        }
        if states.ncols() == 0 || actions.ncols() == 0 {
            return Err(DataError::Shape {
                what: "state and action dimensions".into(),
                expected: "at least 1 each".into(),
                got: format!("{} and {}", states.ncols(), actions.ncols()),
            });
        }
        for (what, m) in [("observations", &states), ("actions", &actions)] {
            for j in 0..m.ncols() {
                if let Some(step) = m.col_as_slice(j).iter().position(|x| !x.is_finite()) {
                    return Err(DataError::NonFinite { what, episode: 0, step });
                }
            }
        }
        Ok(Self { states, actions })
    }

    /// The states, one row per sample.
    pub fn states(&self) -> MatRef<'_, f32> {
        self.states.as_ref()
    }

    /// The actions, one row per sample.
    pub fn actions(&self) -> MatRef<'_, f32> {
        self.actions.as_ref()
    }

    /// The two matrices back.
    pub fn into_parts(self) -> (Mat<f32>, Mat<f32>) {
        (self.states, self.actions)
    }
}

impl BatchSource for MatrixDataset {
    fn num_samples(&self) -> usize {
        self.states.nrows()
    }

    fn state_dim(&self) -> usize {
        self.states.ncols()
    }

    fn action_dim(&self) -> usize {
        self.actions.ncols()
    }

    fn write_row(
        &self,
        sample: usize,
        row: usize,
        mut states: MatMut<'_, f32>,
        mut actions: MatMut<'_, f32>,
    ) {
        for j in 0..self.states.ncols() {
            states[(row, j)] = self.states[(sample, j)];
        }
        for j in 0..self.actions.ncols() {
            actions[(row, j)] = self.actions[(sample, j)];
        }
    }
}

/// An endless, seeded, shuffling minibatch iterator over a [`BatchSource`].
///
/// Every epoch visits each sample exactly once, in a fresh uniformly random order (Fisher-Yates
/// with `Seeds::new(seed).stream("minibatch")`, so the same seed gives the same sequence of
/// batches). Batches are written into two buffers owned by the batcher and returned as views;
/// nothing is allocated per batch. The last batch of an epoch is smaller when the batch size
/// does not divide the sample count, unless [`Batcher::with_drop_last`] is set.
///
/// ```
/// use faer::Mat;
/// use vdd_data::{Batcher, Episodes, SequenceDataset, WindowConfig};
/// let obs = (0..4).map(|i| Mat::from_fn(6, 2, |t, j| (i * 100 + t * 10 + j) as f32)).collect();
/// let act = (0..4).map(|_| Mat::from_fn(6, 1, |t, _| t as f32)).collect();
/// let data =
///     SequenceDataset::new(Episodes::from_episodes(obs, act).unwrap(), WindowConfig::new(2, 2))
///         .unwrap();
/// assert_eq!(data.len(), 16); // 4 anchors per episode
/// let mut batches = Batcher::new(&data, 5, 42).unwrap();
/// assert_eq!(batches.batches_per_epoch(), 4); // 5 + 5 + 5 + 1
/// for _ in 0..4 {
///     let (states, actions) = batches.next_batch();
///     assert_eq!((states.ncols(), actions.ncols()), (4, 2));
/// }
/// assert_eq!(batches.epoch(), 0);
/// batches.next_batch();
/// assert_eq!(batches.epoch(), 1);
/// ```
#[derive(Debug)]
pub struct Batcher<'a, S: BatchSource + ?Sized> {
    source: &'a S,
    batch_size: usize,
    drop_last: bool,
    rng: Rng,
    order: Vec<usize>,
    cursor: usize,
    epoch: usize,
    last: std::ops::Range<usize>,
    states: Mat<f32>,
    actions: Mat<f32>,
}

impl<'a, S: BatchSource + ?Sized> Batcher<'a, S> {
    /// A batcher over `source` drawing `batch_size` samples per batch, shuffled with `seed`.
    ///
    /// Errors: [`DataError::Config`] for `batch_size = 0`, [`DataError::Empty`] for an empty
    /// source.
    pub fn new(source: &'a S, batch_size: usize, seed: u64) -> Result<Self> {
        if batch_size == 0 {
            return Err(DataError::Config("batch size must be at least 1".into()));
        }
        let n = source.num_samples();
        if n == 0 {
            return Err(DataError::Empty("batch source has no samples".into()));
        }
        let mut rng = Seeds::new(seed).stream("minibatch");
        let mut order: Vec<usize> = (0..n).collect();
        order.shuffle(&mut rng);
        let rows = batch_size.min(n);
        Ok(Self {
            source,
            batch_size,
            drop_last: false,
            rng,
            order,
            cursor: 0,
            epoch: 0,
            last: 0..0,
            states: Mat::zeros(rows, source.state_dim()),
            actions: Mat::zeros(rows, source.action_dim()),
        })
    }

    /// Whether to drop the incomplete last batch of each epoch (then every batch has exactly
    /// `batch_size` rows and the dropped samples differ from epoch to epoch).
    ///
    /// Errors: [`DataError::Config`] when dropping would leave no batch at all
    /// (`batch_size > num_samples()`).
    pub fn with_drop_last(mut self, drop_last: bool) -> Result<Self> {
        if drop_last && self.batch_size > self.source.num_samples() {
            return Err(DataError::Config(format!(
                "batch size {} exceeds the {} samples, so dropping the last incomplete batch \
                 leaves none",
                self.batch_size,
                self.source.num_samples()
            )));
        }
        self.drop_last = drop_last;
        Ok(self)
    }

    /// The next batch `(states, actions)`, one row per sample, starting a new (reshuffled)
    /// epoch when the current one is exhausted. The views borrow the batcher's buffers and are
    /// overwritten by the next call.
    pub fn next_batch(&mut self) -> (MatRef<'_, f32>, MatRef<'_, f32>) {
        let n = self.order.len();
        let remaining = n - self.cursor;
        if remaining == 0 || (self.drop_last && remaining < self.batch_size) {
            self.order.shuffle(&mut self.rng);
            self.cursor = 0;
            self.epoch += 1;
        }
        let m = self.batch_size.min(n - self.cursor);
        self.last = self.cursor..self.cursor + m;
        self.cursor += m;
        for (row, &sample) in self.order[self.last.clone()].iter().enumerate() {
            self.source.write_row(sample, row, self.states.as_mut(), self.actions.as_mut());
        }
        (self.states.as_ref().subrows(0, m), self.actions.as_ref().subrows(0, m))
    }

    /// Sample indices of the rows of the last batch returned (empty before the first).
    pub fn last_indices(&self) -> &[usize] {
        &self.order[self.last.clone()]
    }

    /// Index of the epoch the last batch belongs to (0 for the first).
    pub fn epoch(&self) -> usize {
        self.epoch
    }

    /// Batches per epoch: `ceil(n / batch_size)`, or `floor` with `drop_last`.
    pub fn batches_per_epoch(&self) -> usize {
        let n = self.order.len();
        if self.drop_last { n / self.batch_size } else { n.div_ceil(self.batch_size) }
    }

    /// The configured batch size (the last batch of an epoch may be smaller).
    pub fn batch_size(&self) -> usize {
        self.batch_size
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// `n` samples whose state row is `[k, 2k]` and action row `[-k]` for sample `k`.
    fn numbered(n: usize) -> MatrixDataset {
        MatrixDataset::new(
            Mat::from_fn(n, 2, |i, j| ((j + 1) * i) as f32),
            Mat::from_fn(n, 1, |i, _| -(i as f32)),
        )
        .unwrap()
    }

    fn epoch_orders(
        data: &MatrixDataset,
        batch: usize,
        seed: u64,
        epochs: usize,
    ) -> Vec<Vec<usize>> {
        let mut b = Batcher::new(data, batch, seed).unwrap();
        let mut out = vec![Vec::new(); epochs];
        for _ in 0..epochs * b.batches_per_epoch() {
            let (s, _) = b.next_batch();
            let rows: Vec<usize> = (0..s.nrows()).map(|r| s[(r, 0)] as usize).collect();
            out[b.epoch()].extend(rows);
        }
        out
    }

    #[test]
    fn every_sample_once_per_epoch_and_rows_match_indices() {
        let data = numbered(23);
        let mut b = Batcher::new(&data, 5, 3).unwrap();
        assert_eq!(b.batches_per_epoch(), 5);
        assert!(b.last_indices().is_empty());
        for epoch in 0..4 {
            let mut seen = Vec::new();
            for k in 0..5 {
                let (s, a) = b.next_batch();
                assert_eq!(s.nrows(), if k < 4 { 5 } else { 3 });
                for r in 0..s.nrows() {
                    assert_eq!(s[(r, 1)], 2.0 * s[(r, 0)]);
                    assert_eq!(a[(r, 0)], -s[(r, 0)]);
                }
                let rows: Vec<usize> = (0..s.nrows()).map(|r| s[(r, 0)] as usize).collect();
                assert_eq!(rows, b.last_indices());
                seen.extend(rows);
                assert_eq!(b.epoch(), epoch);
            }
            seen.sort_unstable();
            assert_eq!(seen, (0..23).collect::<Vec<_>>());
        }
    }

    #[test]
    fn same_seed_same_order_different_seed_different_order() {
        let data = numbered(50);
        let a = epoch_orders(&data, 7, 11, 3);
        assert_eq!(a, epoch_orders(&data, 7, 11, 3));
        // Epochs are reshuffled, not repeated.
        assert_ne!(a[0], a[1]);
        assert_ne!(a[1], a[2]);
        // Ten seeds give ten different first epochs (50! orders: a collision means a bug).
        let firsts: std::collections::BTreeSet<Vec<usize>> =
            (0..10).map(|s| epoch_orders(&data, 7, s, 1).remove(0)).collect();
        assert_eq!(firsts.len(), 10);
        // The order does not depend on the batch size, only on the seed.
        assert_eq!(epoch_orders(&data, 50, 11, 3), a);
    }

    #[test]
    fn shuffling_is_uniform_over_positions() {
        // Over many epochs each of 8 samples appears at each of 8 positions equally often.
        let n = 8;
        let epochs = 4000;
        let data = numbered(n);
        let orders = epoch_orders(&data, n, 5, epochs);
        let mut counts = vec![[0usize; 8]; n];
        for order in &orders {
            for (pos, &k) in order.iter().enumerate() {
                counts[k][pos] += 1;
            }
        }
        let expected = epochs as f64 / n as f64;
        let chi2: f64 = counts
            .iter()
            .flat_map(|row| row.iter())
            .map(|&c| (c as f64 - expected).powi(2) / expected)
            .sum();
        // (n - 1)^2 = 49 degrees of freedom: the 0.999 quantile is 85.4.
        assert!(chi2 < 85.4, "chi2 {chi2}");
        // A broken shuffle that never moves sample 0 from the front would fail the above; so
        // would one that only rotates. Also check consecutive epochs are independent enough:
        // the same first element in consecutive epochs happens about 1/8 of the time.
        let same_first = orders.windows(2).filter(|w| w[0][0] == w[1][0]).count() as f64;
        let p = same_first / (epochs - 1) as f64;
        assert!((p - 0.125).abs() < 0.03, "p {p}");
    }

    #[test]
    fn buffers_are_reused_not_reallocated() {
        let data = numbered(30);
        let mut b = Batcher::new(&data, 8, 0).unwrap();
        let (s, a) = b.next_batch();
        let (ps, pa) = (s.as_ptr(), a.as_ptr());
        for _ in 0..20 {
            let (s, a) = b.next_batch();
            assert_eq!((s.as_ptr(), a.as_ptr()), (ps, pa));
        }
    }

    #[test]
    fn drop_last_gives_full_batches() {
        let data = numbered(10);
        let mut b = Batcher::new(&data, 4, 1).unwrap().with_drop_last(true).unwrap();
        assert_eq!(b.batches_per_epoch(), 2);
        for k in 0..9 {
            let (s, _) = b.next_batch();
            assert_eq!(s.nrows(), 4);
            assert_eq!(b.epoch(), k / 2);
        }
        assert!(matches!(
            Batcher::new(&data, 11, 0).unwrap().with_drop_last(true),
            Err(DataError::Config(_))
        ));
        // Without drop_last an oversized batch is the whole (shuffled) dataset.
        let mut b = Batcher::new(&data, 11, 0).unwrap();
        assert_eq!(b.next_batch().0.nrows(), 10);
    }

    #[test]
    fn bad_batchers_and_matrix_datasets_are_rejected() {
        let data = numbered(3);
        assert!(matches!(Batcher::new(&data, 0, 0), Err(DataError::Config(_))));
        let m = |r, c| Mat::<f32>::zeros(r, c);
        assert!(matches!(MatrixDataset::new(m(0, 2), m(0, 1)), Err(DataError::Empty(_))));
        assert!(matches!(MatrixDataset::new(m(3, 2), m(2, 1)), Err(DataError::Shape { .. })));
        assert!(matches!(MatrixDataset::new(m(3, 0), m(3, 1)), Err(DataError::Shape { .. })));
        let mut nan = m(3, 1);
        nan[(1, 0)] = f32::NAN;
        assert!(matches!(
            MatrixDataset::new(m(3, 2), nan),
            Err(DataError::NonFinite { what: "actions", step: 1, .. })
        ));
    }
}
