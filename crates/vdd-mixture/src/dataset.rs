//! Demonstrations as plain matrices: the data EM and IMC fit by maximum likelihood.

use faer::{Mat, MatRef};
use vdd_core::{CoreError, check_finite, check_len};

/// State–action pairs, one row each: `states` is `n x d_s`, `actions` is `n x d_a`, both
/// already normalised (the networks of a [`vdd_moe::Moe`] see exactly these numbers).
///
/// ```
/// use faer::Mat;
/// use vdd_mixture::Dataset;
/// let data = Dataset::new(Mat::zeros(4, 1), Mat::from_fn(4, 2, |i, j| (i + j) as f32)).unwrap();
/// assert_eq!((data.len(), data.state_dim(), data.action_dim()), (4, 1, 2));
/// assert!(Dataset::new(Mat::zeros(4, 1), Mat::zeros(3, 2)).is_err());
/// ```
#[derive(Debug, Clone, PartialEq)]
pub struct Dataset {
    states: Mat<f32>,
    actions: Mat<f32>,
}

impl Dataset {
    /// Pairs row `i` of `states` with row `i` of `actions`. Errors when the data are empty, the
    /// row counts differ, a dimension is zero or a value is not finite.
    pub fn new(states: Mat<f32>, actions: Mat<f32>) -> Result<Self, CoreError> {
        if states.nrows() == 0 {
            return Err(CoreError::Config("a dataset needs at least one state-action pair".into()));
        }
        if states.ncols() == 0 || actions.ncols() == 0 {
            return Err(CoreError::Config("state and action dimensions must be positive".into()));
        }
        check_len("action rows vs state rows", actions.nrows(), states.nrows())?;
        check_finite("dataset states", states.as_ref())?;
        check_finite("dataset actions", actions.as_ref())?;
        Ok(Self { states, actions })
    }

    /// Number of pairs `n`.
    pub fn len(&self) -> usize {
        self.states.nrows()
    }

    /// Always `false` (an empty dataset is rejected by [`Dataset::new`]).
    pub fn is_empty(&self) -> bool {
        self.states.nrows() == 0
    }

    /// State dimension `d_s`.
    pub fn state_dim(&self) -> usize {
        self.states.ncols()
    }

    /// Action dimension `d_a`.
    pub fn action_dim(&self) -> usize {
        self.actions.ncols()
    }

    /// The states, `n x d_s`.
    pub fn states(&self) -> MatRef<'_, f32> {
        self.states.as_ref()
    }

    /// The actions, `n x d_a`.
    pub fn actions(&self) -> MatRef<'_, f32> {
        self.actions.as_ref()
    }

    /// Checks that a mixture with `state_dim → action_dim` networks can be fitted to the data.
    pub(crate) fn check_dims(&self, state_dim: usize, action_dim: usize) -> Result<(), CoreError> {
        check_len("data state columns vs model state_dim", self.state_dim(), state_dim)?;
        check_len("data action columns vs model action_dim", self.action_dim(), action_dim)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn bad_data_is_rejected() {
        assert!(Dataset::new(Mat::zeros(0, 1), Mat::zeros(0, 2)).is_err());
        assert!(Dataset::new(Mat::zeros(2, 0), Mat::zeros(2, 2)).is_err());
        let mut a = Mat::zeros(2, 2);
        a[(1, 1)] = f32::NAN;
        assert!(matches!(Dataset::new(Mat::zeros(2, 1), a), Err(CoreError::NonFinite { .. })));
        let d = Dataset::new(Mat::zeros(2, 1), Mat::zeros(2, 2)).unwrap();
        assert!(d.check_dims(1, 2).is_ok());
        assert!(d.check_dims(2, 2).is_err());
        assert!(!d.is_empty());
    }
}
