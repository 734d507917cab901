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
}
