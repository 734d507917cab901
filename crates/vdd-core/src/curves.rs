//! Curves over training: a task's [`CurveEval`] evaluated at checkpoints of a [`Trainer`] run
//! by a [`CurveProbe`], which keeps the time the evaluations take apart from training's.

use std::collections::BTreeMap;
use std::marker::PhantomData;

use crate::trainer::{Snapshot, Trainer};

/// Points by series: `(iteration, value)` in the order they were taken.
pub type Curves = BTreeMap<String, Vec<(f64, f64)>>;

/// What a task evaluates at checkpoints of a training of policies `P` (e.g. held-out rollouts;
/// the evaluation itself is the task crate's).
pub trait CurveEval<P: ?Sized>: Sync {
    /// The evaluation's error.
    type Error;
    /// The iterations of a run of `iterations` after which to evaluate.
    fn checkpoints(&self, iterations: usize) -> Vec<usize>;
    /// Named figures of `policy` for run seed `seed`.
    fn evaluate(&self, policy: &P, seed: u64) -> Result<Vec<(String, f64)>, Self::Error>;
}

/// A training's curve points: evaluates snapshots at the checkpoints of a [`CurveEval`] (none
/// without one) and keeps the time it takes apart from training.
pub struct CurveProbe<'a, P: ?Sized, C: ?Sized + CurveEval<P>> {
    eval: Option<&'a C>,
    seed: u64,
    /// Seconds spent evaluating.
    pub seconds: f64,
    /// The points so far, by series, against iterations.
    pub curves: Curves,
    policy: PhantomData<fn(&P)>,
}

impl<'a, P: ?Sized, C: ?Sized + CurveEval<P>> CurveProbe<'a, P, C> {
    /// The probe of a training with run seed `seed` evaluated by `eval` (nothing for `None`).
    pub fn new(eval: Option<&'a C>, seed: u64) -> Self {
        Self { eval, seed, seconds: 0.0, curves: Curves::default(), policy: PhantomData }
    }

    /// The iterations of a run of `iterations` to evaluate after (none without curves).
    pub fn checkpoints(&self, iterations: usize) -> Vec<usize> {
        self.eval.map_or_else(Vec::new, |c| c.checkpoints(iterations))
    }

    /// Evaluates `policy`, the model after `iteration` iterations.
    pub fn record(&mut self, iteration: usize, policy: &P) -> Result<(), C::Error> {
        let Some(eval) = self.eval else { return Ok(()) };
        let t0 = std::time::Instant::now();
        for (series, v) in eval.evaluate(policy, self.seed)? {
            self.curves.entry(series).or_default().push((iteration as f64, v));
        }
        self.seconds += t0.elapsed().as_secs_f64();
        Ok(())
    }

    /// Runs `trainer` to its end through [`Trainer::run_with_checkpoints`] (reports to
    /// `report`), recording the [`Snapshot`] at each checkpoint as `policy` makes it a policy.
    pub fn run<T: Trainer + Snapshot, E: From<T::Error> + From<C::Error>>(
        &mut self,
        trainer: &mut T,
        report: impl FnMut(&T::Report),
        policy: impl Fn(T::Output) -> Result<P, E>,
    ) -> Result<(), E>
    where
        P: Sized,
    {
        let at = self.checkpoints(trainer.iterations());
        trainer.run_with_checkpoints(&at, report, |t| {
            let p = policy(t.snapshot()?)?;
            Ok(self.record(t.iteration(), &p)?)
        })
    }

    /// Moves the points so far to the end of their series in `curves` and returns the
    /// seconds spent evaluating so far.
    pub fn take_into(&mut self, curves: &mut Curves) -> f64 {
        for (series, points) in std::mem::take(&mut self.curves) {
            curves.entry(series).or_default().extend(points);
        }
        self.seconds
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Counts iterations; its snapshot is the iteration.
    struct Count(usize);

    impl Trainer for Count {
        type Report = ();
        type Output = usize;
        type Error = std::fmt::Error;
        fn step(&mut self) -> Result<(), Self::Error> {
            self.0 += 1;
            Ok(())
        }
        fn iteration(&self) -> usize {
            self.0
        }
        fn iterations(&self) -> usize {
            9
        }
        fn finish(self) -> Result<usize, Self::Error> {
            Ok(self.0)
        }
    }

    impl Snapshot for Count {
        fn snapshot(&self) -> Result<usize, Self::Error> {
            Ok(self.0)
        }
    }

    /// Reports the policy (a number of experts) as its "experts", and the seed.
    struct Experts;

    impl CurveEval<usize> for Experts {
        type Error = std::fmt::Error;
        fn checkpoints(&self, iterations: usize) -> Vec<usize> {
            crate::trainer::checkpoints(iterations, 3)
        }
        fn evaluate(&self, p: &usize, seed: u64) -> Result<Vec<(String, f64)>, Self::Error> {
            Ok(vec![("experts".into(), *p as f64), ("seed".into(), seed as f64)])
        }
    }

    #[test]
    fn the_probe_evaluates_snapshots_at_the_task_checkpoints() {
        let mut probe = CurveProbe::new(Some(&Experts), 7);
        assert_eq!(probe.checkpoints(9), [3, 6, 9]);
        let mut reports = 0;
        let policy = |it: usize| Ok::<_, std::fmt::Error>(it);
        probe.run(&mut Count(0), |_| reports += 1, policy).unwrap();
        assert_eq!(reports, 9);
        let mut curves = Curves::from([("experts".to_owned(), vec![(0.0, 1.0)])]);
        probe.take_into(&mut curves);
        assert_eq!(curves["experts"], [(0.0, 1.0), (3.0, 3.0), (6.0, 6.0), (9.0, 9.0)]);
        assert_eq!(curves["seed"], [(3.0, 7.0), (6.0, 7.0), (9.0, 7.0)], "the run seed");
        let none = CurveProbe::<usize, Experts>::new(None, 7);
        assert!(none.checkpoints(9).is_empty());
    }
}
