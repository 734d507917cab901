//! Your own teacher and policy behind the core traits: a `ScoreModel` (what VDD distils) and a
//! `Policy` (what rollouts drive), with an error of your own that keeps its source.
//!
//! ```text
//! cargo run -p vdd-core --example user_types
//! ```

use faer::{Mat, MatMut, MatRef};
use vdd_core::{CoreError, Policy, ScoreModel, check_act_args, check_score_args};

/// An isotropic Gaussian `N(μ(s), v I)` over 2-D actions whose mean follows the 1-D state:
/// `μ(s) = (s, −s)`.
struct Linear {
    var: f32,
}

impl ScoreModel for Linear {
    fn action_dim(&self) -> usize {
        2
    }
    fn state_dim(&self) -> usize {
        1
    }
    /// The score of the distribution smoothed by `N(0, σ² I)`: `(μ(s) − a)/(v + σ²)`.
    fn score(
        &mut self,
        a: MatRef<'_, f32>,
        s: MatRef<'_, f32>,
        sigma: &[f32],
        mut out: MatMut<'_, f32>,
    ) -> Result<(), CoreError> {
        check_score_args(self, a, s, sigma, out.as_ref())?;
        for i in 0..a.nrows() {
            let mean = [s[(i, 0)], -s[(i, 0)]];
            for j in 0..2 {
                out[(i, j)] = (mean[j] - a[(i, j)]) / (self.var + sigma[i] * sigma[i]);
            }
        }
        Ok(())
    }
}

/// The error of a controller that only works in a range of states.
#[derive(Debug, thiserror::Error)]
#[error("state {0} is outside the controller's range [-1, 1]")]
struct OutOfRange(f32);

/// A deterministic policy: the mean action of `Linear`, refusing states outside [−1, 1].
struct Controller;

impl Policy for Controller {
    fn obs_dim(&self) -> usize {
        1
    }
    fn action_dim(&self) -> usize {
        2
    }
    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> Result<(), CoreError> {
        check_act_args(self, obs, action)?;
        if obs[0].abs() > 1.0 {
            // Your own error travels as the source of `CoreError::Implementor`.
            return Err(CoreError::implementor(OutOfRange(obs[0])));
        }
        action.copy_from_slice(&[obs[0], -obs[0]]);
        Ok(())
    }
}

fn main() -> Result<(), CoreError> {
    let mut teacher = Linear { var: 0.25 };
    let (a, s) = (Mat::from_fn(3, 2, |i, _| i as f32), Mat::from_fn(3, 1, |_, _| 0.5));
    let mut score = Mat::zeros(3, 2);
    teacher.score(a.as_ref(), s.as_ref(), &[0.1; 3], score.as_mut())?;
    for i in 0..3 {
        println!(
            "score at a = ({}, {}), s = 0.5: ({:.3}, {:.3})",
            a[(i, 0)],
            a[(i, 1)],
            score[(i, 0)],
            score[(i, 1)]
        );
    }

    let mut policy = Controller;
    println!("act(0.3) = {:?}", policy.act(&[0.3])?);
    let err = policy.act(&[3.0]).unwrap_err();
    let source = std::error::Error::source(&err).and_then(|e| e.downcast_ref::<OutOfRange>());
    println!("act(3.0) fails: {err} (source: {source:?})");
    assert!(source.is_some());
    Ok(())
}
