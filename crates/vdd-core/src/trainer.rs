//! One shape for every training loop: [`Trainer`].
//!
//! VDD, the mixture baselines (EM, IMC), the consistency baselines (CD, CTM) and the diffusion
//! teachers' training all step the same way: a fixed number of optimiser iterations, each
//! returning a small report, then a trained model. Code that drives training (progress bars,
//! checkpoints, learning curves) is written once against this trait.

/// A training run that advances one iteration at a time.
///
/// Implementors provide [`step`](Trainer::step), [`iteration`](Trainer::iteration),
/// [`iterations`](Trainer::iterations) and [`finish`](Trainer::finish); [`done`](Trainer::done),
/// [`progress`](Trainer::progress) and [`run`](Trainer::run) have defaults.
///
/// ```
/// use vdd_core::Trainer;
///
/// /// Gradient descent on `(x - 3)²`.
/// struct Descent { x: f32, it: usize, total: usize }
///
/// impl Trainer for Descent {
///     type Report = f32;                 // the loss of the step
///     type Output = f32;                 // the trained parameter
///     type Error = std::convert::Infallible;
///     fn step(&mut self) -> Result<f32, Self::Error> {
///         self.x -= 0.1 * 2.0 * (self.x - 3.0);
///         self.it += 1;
///         Ok((self.x - 3.0).powi(2))
///     }
///     fn iteration(&self) -> usize { self.it }
///     fn iterations(&self) -> usize { self.total }
///     fn finish(self) -> Result<f32, Self::Error> { Ok(self.x) }
/// }
///
/// let mut t = Descent { x: 0.0, it: 0, total: 50 };
/// let mut losses = Vec::new();
/// t.run(|loss| losses.push(*loss)).unwrap();
/// assert!(t.done() && losses.len() == 50);
/// assert!((t.finish().unwrap() - 3.0).abs() < 1e-3);
/// ```
pub trait Trainer {
    /// What one iteration reports (losses, learning rates, ...).
    type Report;
    /// The trained model [`finish`](Trainer::finish) returns.
    type Output;
    /// The trainer's error.
    type Error: std::error::Error + Send + Sync + 'static;

    /// Runs one iteration and reports on it. On error the iteration counter does not advance.
    fn step(&mut self) -> Result<Self::Report, Self::Error>;

    /// Iterations done so far.
    fn iteration(&self) -> usize;

    /// Iterations of the whole run.
    fn iterations(&self) -> usize;

    /// Ends training and returns the trained model.
    fn finish(self) -> Result<Self::Output, Self::Error>
    where
        Self: Sized;

    /// Whether every iteration has run.
    fn done(&self) -> bool {
        self.iteration() >= self.iterations()
    }

    /// The share of the run done, in `[0, 1]` (1 for a run of no iterations).
    fn progress(&self) -> f64 {
        match self.iterations() {
            0 => 1.0,
            n => (self.iteration() as f64 / n as f64).min(1.0),
        }
    }

    /// Runs the remaining iterations, passing each report to `report`.
    fn run(&mut self, mut report: impl FnMut(&Self::Report)) -> Result<(), Self::Error>
    where
        Self: Sized,
    {
        while !self.done() {
            let r = self.step()?;
            report(&r);
        }
        Ok(())
    }

    /// Runs the remaining iterations like [`run`](Trainer::run), and whenever the iterations
    /// done reach an entry of `at` (e.g. [`checkpoints`]), calls `checkpoint` with the trainer
    /// (to evaluate a [`Snapshot`], write a checkpoint, ...). Entries at or below the
    /// iterations already done, or above the run's length, are skipped; the training itself is
    /// the same as `run`'s whatever `at` holds, as long as `checkpoint` leaves the trainer as
    /// it found it.
    ///
    /// ```
    /// use vdd_core::{Snapshot, Trainer, trainer::checkpoints};
    /// # struct Count { it: usize }
    /// # impl Trainer for Count {
    /// #     type Report = ();
    /// #     type Output = usize;
    /// #     type Error = std::convert::Infallible;
    /// #     fn step(&mut self) -> Result<(), Self::Error> { self.it += 1; Ok(()) }
    /// #     fn iteration(&self) -> usize { self.it }
    /// #     fn iterations(&self) -> usize { 10 }
    /// #     fn finish(self) -> Result<usize, Self::Error> { Ok(self.it) }
    /// # }
    /// # impl Snapshot for Count {
    /// #     fn snapshot(&self) -> Result<usize, Self::Error> { Ok(self.it) }
    /// # }
    /// let mut t = Count { it: 0 };
    /// let mut seen = Vec::new();
    /// t.run_with_checkpoints(&checkpoints(10, 5), |_| {}, |t| {
    ///     seen.push(t.snapshot()?);
    ///     Ok::<(), std::convert::Infallible>(())
    /// })?;
    /// assert_eq!(seen, [2, 4, 6, 8, 10]);
    /// # Ok::<(), std::convert::Infallible>(())
    /// ```
    fn run_with_checkpoints<E: From<Self::Error>>(
        &mut self,
        at: &[usize],
        mut report: impl FnMut(&Self::Report),
        mut checkpoint: impl FnMut(&mut Self) -> Result<(), E>,
    ) -> Result<(), E>
    where
        Self: Sized,
    {
        while !self.done() {
            let r = self.step()?;
            report(&r);
            if at.contains(&self.iteration()) {
                checkpoint(self)?;
            }
        }
        Ok(())
    }
}

/// A trainer that can hand out the model [`Trainer::finish`] would return now, without ending
/// training (for curves over training: evaluate the snapshot, keep training).
pub trait Snapshot: Trainer {
    /// A copy of the model as [`Trainer::finish`] would return it after the iterations done
    /// so far. The trainer is left as it was: training on gives the same results as without
    /// the call.
    fn snapshot(&self) -> Result<Self::Output, Self::Error>;
}

/// `points` iterations spread evenly over a run of `iterations`, ending with the last one
/// (fewer when the run is shorter; none for `points == 0`): where to take a curve's points.
///
/// ```
/// use vdd_core::trainer::checkpoints;
/// assert_eq!(checkpoints(100, 4), [25, 50, 75, 100]);
/// assert_eq!(checkpoints(3, 5), [1, 2, 3]);
/// assert!(checkpoints(100, 0).is_empty());
/// ```
pub fn checkpoints(iterations: usize, points: usize) -> Vec<usize> {
    let n = points.min(iterations);
    let mut out: Vec<usize> = (1..=n).map(|k| (k * iterations).div_ceil(n)).collect();
    out.dedup();
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Sums the iteration indices; the snapshot is the sum so far.
    struct Sum {
        it: usize,
        total: usize,
        sum: usize,
    }

    impl Trainer for Sum {
        type Report = usize;
        type Output = usize;
        type Error = std::fmt::Error;
        fn step(&mut self) -> Result<usize, Self::Error> {
            self.sum += self.it;
            self.it += 1;
            Ok(self.sum)
        }
        fn iteration(&self) -> usize {
            self.it
        }
        fn iterations(&self) -> usize {
            self.total
        }
        fn finish(self) -> Result<usize, Self::Error> {
            Ok(self.sum)
        }
    }

    impl Snapshot for Sum {
        fn snapshot(&self) -> Result<usize, Self::Error> {
            Ok(self.sum)
        }
    }

    #[test]
    fn checkpoints_see_the_trainer_after_their_iteration_and_change_nothing() {
        let mut plain = Sum { it: 0, total: 9, sum: 0 };
        let mut reports = Vec::new();
        plain.run(|r| reports.push(*r)).unwrap();
        let mut probed = Sum { it: 2, total: 9, sum: 1 };
        let mut seen = Vec::new();
        let mut probed_reports = vec![0, 1];
        probed
            .run_with_checkpoints(
                &[0, 2, 3, 9, 12],
                |r| probed_reports.push(*r),
                |t| {
                    seen.push((t.iteration(), t.snapshot()?));
                    Ok::<(), std::fmt::Error>(())
                },
            )
            .unwrap();
        assert_eq!(seen, [(3, 3), (9, 36)], "past and out-of-range entries are skipped");
        assert_eq!(probed_reports, reports);
        assert_eq!(probed.finish().unwrap(), plain.finish().unwrap());
        let mut failing = Sum { it: 0, total: 4, sum: 0 };
        let e = failing.run_with_checkpoints(
            &[2],
            |_| {},
            |_| Err::<(), Box<dyn std::error::Error>>("stop".into()),
        );
        assert_eq!(e.unwrap_err().to_string(), "stop");
        assert_eq!(failing.iteration(), 2, "a failing checkpoint stops the run");
    }

    #[test]
    fn checkpoints_are_spread_evenly_and_end_with_the_run() {
        assert_eq!(checkpoints(60_000, 6), [10_000, 20_000, 30_000, 40_000, 50_000, 60_000]);
        assert_eq!(checkpoints(10, 3), [4, 7, 10]);
        assert_eq!(checkpoints(0, 3), Vec::<usize>::new());
    }
}
