//! [`TrainingData`]: the matrices a method trains on, as a task prepared them.

use faer::Mat;
use vdd_core::Affine;
use vdd_core::gmm::GmmTeacher;
use vdd_core::hash::data_hash;

/// Training data of a run, as the task prepared it (row `i` of each matrix belongs together).
#[derive(Debug, Clone)]
pub struct TrainingData {
    /// States, raw.
    pub states: Mat<f32>,
    /// Actions, raw.
    pub actions: Mat<f32>,
    /// The task's normalisation of the states (identity when it has none).
    pub state_normalizer: Affine,
    /// The task's normalisation of the actions.
    pub action_normalizer: Affine,
    /// `states` under `state_normalizer`.
    pub states_normalized: Mat<f32>,
    /// `actions` under `action_normalizer`.
    pub actions_normalized: Mat<f32>,
    /// The exact teacher of the data's distribution, when the task knows it (the toys; it
    /// takes raw states and actions).
    pub exact: Option<GmmTeacher>,
}

impl TrainingData {
    /// Data without a normalisation of the task's own (identity normalisers).
    ///
    /// ```
    /// use faer::Mat;
    /// let d = vdd_data::TrainingData::raw(Mat::zeros(3, 1), Mat::ones(3, 2), None);
    /// assert_eq!(d.actions_normalized, d.actions);
    /// assert_eq!(d.hash(), vdd_core::hash::data_hash(d.states.as_ref(), d.actions.as_ref()));
    /// ```
    pub fn raw(states: Mat<f32>, actions: Mat<f32>, exact: Option<GmmTeacher>) -> Self {
        Self {
            state_normalizer: Affine::identity(states.ncols()),
            action_normalizer: Affine::identity(actions.ncols()),
            states_normalized: states.clone(),
            actions_normalized: actions.clone(),
            states,
            actions,
            exact,
        }
    }

    /// [`data_hash`] of the raw `states` and `actions` (what caches of models trained on this
    /// data are keyed by), computed from the matrices as they are now.
    pub fn hash(&self) -> String {
        data_hash(self.states.as_ref(), self.actions.as_ref())
    }
}

impl AsRef<TrainingData> for TrainingData {
    fn as_ref(&self) -> &TrainingData {
        self
    }
}
