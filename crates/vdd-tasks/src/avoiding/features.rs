//! What the models of the Avoiding recipes see of an observation: [`ObsFeatures`] names the
//! registered feature map (`vdd_data::features`) they are trained and deployed with.

use serde::{Deserialize, Serialize};
use vdd_data::features::{self, FeatureMap};

/// The observation features of an Avoiding model: a fixed, invertible map of the task's
/// observation `(d, c)` (previous desired position, current position), applied to the
/// demonstrations and, at every rollout step, by the deployed policy
/// ([`vdd_data::Windowed`]). A saved model records the map by name and version
/// ([`vdd_data::DeploySpec::features`]).
///
/// ```
/// use vdd_tasks::avoiding::ObsFeatures;
///
/// let map = ObsFeatures::PositionAndLag.feature_map();
/// assert_eq!((map.name(), map.version()), ("position_and_lag", 1));
/// let mut obs = [0.5f32, -0.25, 0.25, -0.5]; // d = (0.5, −0.25), c = (0.25, −0.5)
/// map.apply(&mut obs);
/// assert_eq!(obs, [0.25, -0.5, 0.25, 0.25]); // (c, d − c)
/// assert!(ObsFeatures::Raw.feature_map().is_identity());
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize, Default)]
#[serde(rename_all = "snake_case")]
pub enum ObsFeatures {
    /// The task's observation `(d, c)` unchanged (`identity` v1).
    Raw,
    /// The current position and the tracking lag `(c, d − c)` (`position_and_lag` v1). The
    /// lag is the end effector's velocity (about one step's length, ~5 mm) and sets the next
    /// action, but under a per-dimension normalisation of `(d, c)` it is the small difference of
    /// two large, nearly equal inputs. Given explicitly, it is normalised to unit scale of its
    /// own. The recipes' default.
    #[default]
    PositionAndLag,
}

impl ObsFeatures {
    /// The registered feature map.
    pub fn feature_map(self) -> FeatureMap {
        match self {
            ObsFeatures::Raw => features::IDENTITY,
            ObsFeatures::PositionAndLag => features::POSITION_AND_LAG,
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::avoiding::OBS_DIM;

    #[test]
    fn the_maps_are_registered_and_fit_the_observation() {
        for f in [ObsFeatures::Raw, ObsFeatures::PositionAndLag] {
            let map = f.feature_map();
            assert_eq!(map.id().resolve().unwrap(), map);
            map.check_dim(OBS_DIM).unwrap();
        }
        let mut o = [0.5f32, -0.2, 0.49, -0.25];
        ObsFeatures::PositionAndLag.feature_map().apply(&mut o);
        assert_eq!(o, [0.49, -0.25, 0.5 - 0.49, -0.2 - -0.25]);
        assert_eq!(ObsFeatures::default(), ObsFeatures::PositionAndLag);
        assert_eq!(serde_json::to_string(&ObsFeatures::Raw).unwrap(), "\"raw\"");
    }
}
