//! Observation feature maps: named, versioned functions applied to every raw observation
//! before a model sees it, in training (to the demonstrations) and in deployment (by
//! [`Windowed`](crate::Windowed), at every step).
//!
//! A model trained on mapped observations only acts correctly on observations mapped the same
//! way, so a saved model records the map it expects by name and version ([`FeatureMapId`], part
//! of a [`DeploySpec`](crate::DeploySpec)) and the loader looks it up here with [`lookup`]. A
//! name and version pin one function bit for bit: a map whose output changes gets a new
//! version, and the old version stays in the [`registry`] so that old models keep loading.
//!
//! | name | version | map | needs |
//! |---|---|---|---|
//! | `identity` | 1 | `o ↦ o` | any dimension |
//! | `position_and_lag` | 1 | `(d, c) ↦ (c, d − c)` for halves `d`, `c` of `k` entries each | an even dimension |
//!
//! `position_and_lag` is for observations made of a commanded (desired) position `d` and the
//! current position `c`: it gives the position and the tracking lag `d − c` explicitly. The lag
//! is small next to the positions, and under a per-dimension normalisation of `(d, c)` it
//! would be the difference of two large, nearly equal inputs; as a feature of its own it is
//! normalised to unit scale. (The Avoiding task's observation is such a pair;
//! `vdd_tasks::avoiding::ObsFeatures` names the map its recipes use.)
//!
//! ```
//! use vdd_data::features::{self, FeatureMapId};
//!
//! let map = features::lookup("position_and_lag", 1)?;
//! let mut obs = [0.5f32, -0.25, 0.25, -0.5]; // d = (0.5, -0.25), c = (0.25, -0.5)
//! map.apply(&mut obs);
//! assert_eq!(obs, [0.25, -0.5, 0.25, 0.25]); // (c, d − c)
//! assert_eq!(map.id(), FeatureMapId::new("position_and_lag", 1));
//!
//! // Unknown names and versions are errors that list what the registry knows.
//! let err = features::lookup("position_and_lag", 2).unwrap_err();
//! assert!(err.to_string().contains("identity v1, position_and_lag v1"), "{err}");
//! # Ok::<(), vdd_data::DataError>(())
//! ```

use std::fmt;

use faer::{Mat, MatRef};
use serde::{Deserialize, Serialize};

use crate::error::{DataError, Result};

/// The name and version of a feature map, as models record it.
///
/// ```
/// use vdd_data::features::FeatureMapId;
/// let id = FeatureMapId::new("identity", 1);
/// assert_eq!(id.to_string(), "identity v1");
/// assert!(id.resolve()?.is_identity());
/// # Ok::<(), vdd_data::DataError>(())
/// ```
#[derive(Debug, Clone, PartialEq, Eq, Hash, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct FeatureMapId {
    /// The map's name in the [`registry`].
    pub name: String,
    /// Its version (from 1).
    pub version: u32,
}

impl FeatureMapId {
    /// The id `name` version `version`.
    pub fn new(name: impl Into<String>, version: u32) -> Self {
        Self { name: name.into(), version }
    }

    /// The registered map with this name and version ([`lookup`]).
    pub fn resolve(&self) -> Result<FeatureMap> {
        lookup(&self.name, self.version)
    }
}

impl fmt::Display for FeatureMapId {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "{} v{}", self.name, self.version)
    }
}

/// A registered feature map: a fixed in-place function of one observation that keeps its
/// dimension. Compare by name and version.
///
/// ```
/// use vdd_data::features::{IDENTITY, POSITION_AND_LAG};
/// assert!(POSITION_AND_LAG.check_dim(4).is_ok());
/// assert!(POSITION_AND_LAG.check_dim(3).is_err()); // needs (d, c) halves
/// let m = faer::mat![[1.0f32, 2.0, 0.5, 1.0]];
/// assert_eq!(POSITION_AND_LAG.apply_rows(m.as_ref())?, faer::mat![[0.5f32, 1.0, 0.5, 1.0]]);
/// assert_eq!(IDENTITY.apply_rows(m.as_ref())?, m);
/// # Ok::<(), vdd_data::DataError>(())
/// ```
#[derive(Clone, Copy)]
pub struct FeatureMap {
    name: &'static str,
    version: u32,
    description: &'static str,
    map: fn(&mut [f32]),
    accepts: fn(usize) -> bool,
    requirement: &'static str,
}

impl FeatureMap {
    /// The name in the registry.
    pub fn name(&self) -> &'static str {
        self.name
    }

    /// The version.
    pub fn version(&self) -> u32 {
        self.version
    }

    /// What the map computes, in one line.
    pub fn description(&self) -> &'static str {
        self.description
    }

    /// Name and version, as models record them.
    pub fn id(&self) -> FeatureMapId {
        FeatureMapId::new(self.name, self.version)
    }

    /// Whether this is the identity (no map at all).
    pub fn is_identity(&self) -> bool {
        self.name == IDENTITY.name && self.version == IDENTITY.version
    }

    /// Checks that the map applies to observations of `dim` entries.
    pub fn check_dim(&self, dim: usize) -> Result<()> {
        if (self.accepts)(dim) {
            Ok(())
        } else {
            Err(DataError::Spec {
                key: "features",
                value: self.id().to_string(),
                reason: format!("needs {}, the observation has {dim} entries", self.requirement),
            })
        }
    }

    /// Maps one observation in place. Its length must pass [`FeatureMap::check_dim`] (callers
    /// check once, not per step); another length gives an unspecified observation, never a
    /// panic.
    pub fn apply(&self, obs: &mut [f32]) {
        (self.map)(obs)
    }

    /// The map applied to each row of `m` (e.g. an episode's observations, one per row).
    pub fn apply_rows(&self, m: MatRef<'_, f32>) -> Result<Mat<f32>> {
        self.check_dim(m.ncols())?;
        let mut out = m.to_owned();
        let mut row = vec![0.0f32; m.ncols()];
        for i in 0..m.nrows() {
            for (j, x) in row.iter_mut().enumerate() {
                *x = m[(i, j)];
            }
            self.apply(&mut row);
            for (j, x) in row.iter().enumerate() {
                out[(i, j)] = *x;
            }
        }
        Ok(out)
    }
}

impl fmt::Debug for FeatureMap {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(f, "FeatureMap({} v{})", self.name, self.version)
    }
}

impl PartialEq for FeatureMap {
    fn eq(&self, other: &Self) -> bool {
        self.name == other.name && self.version == other.version
    }
}

impl Eq for FeatureMap {}

/// `identity` v1: the observation unchanged.
pub const IDENTITY: FeatureMap = FeatureMap {
    name: "identity",
    version: 1,
    description: "the observation unchanged",
    map: |_| {},
    accepts: |_| true,
    requirement: "any dimension",
};

/// `position_and_lag` v1: `(d, c) ↦ (c, d − c)`, where `d` and `c` are the first and second
/// halves of the observation (a commanded and the current position); see the
/// [module docs](self).
pub const POSITION_AND_LAG: FeatureMap = FeatureMap {
    name: "position_and_lag",
    version: 1,
    description: "(d, c) -> (c, d - c) for the halves d (commanded) and c (current position)",
    map: position_and_lag,
    accepts: |dim| dim > 0 && dim % 2 == 0,
    requirement: "an even, non-zero dimension (two halves d and c)",
};

const REGISTRY: &[FeatureMap] = &[IDENTITY, POSITION_AND_LAG];

/// Every registered map, in the order of the table in the [module docs](self).
pub fn registry() -> &'static [FeatureMap] {
    REGISTRY
}

/// The registered map `name` version `version`; [`DataError::UnknownFeatureMap`] (listing the
/// registry) for a name or version it does not hold.
pub fn lookup(name: &str, version: u32) -> Result<FeatureMap> {
    REGISTRY.iter().find(|m| m.name == name && m.version == version).copied().ok_or_else(|| {
        DataError::UnknownFeatureMap {
            name: name.to_owned(),
            version,
            known: REGISTRY
                .iter()
                .map(|m| format!("{} v{}", m.name, m.version))
                .collect::<Vec<_>>()
                .join(", "),
        }
    })
}

/// `(d, c) ↦ (c, d − c)` over the halves of `obs`.
fn position_and_lag(obs: &mut [f32]) {
    let k = obs.len() / 2;
    for i in 0..k {
        let (d, c) = (obs[i], obs[k + i]);
        obs[i] = c;
        obs[k + i] = d - c;
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn position_and_lag_is_position_and_desired_minus_current() {
        let mut o = [0.5f32, -0.2, 0.49, -0.25];
        POSITION_AND_LAG.apply(&mut o);
        assert_eq!(o, [0.49, -0.25, 0.5 - 0.49, -0.2 - -0.25]);
        let mut one = [3.0f32, 1.0];
        POSITION_AND_LAG.apply(&mut one);
        assert_eq!(one, [1.0, 2.0]);
        let mut o = [0.5f32, -0.2, 0.49];
        POSITION_AND_LAG.apply(&mut o); // a wrong length: no panic
        let mut o = [0.5f32, -0.2];
        IDENTITY.apply(&mut o);
        assert_eq!(o, [0.5, -0.2]);
    }

    #[test]
    fn the_registry_finds_every_map_by_name_and_version_and_nothing_else() {
        for m in registry() {
            assert_eq!(lookup(m.name(), m.version()).unwrap(), *m);
            assert_eq!(m.id().resolve().unwrap(), *m);
        }
        assert!(lookup("identity", 1).unwrap().is_identity());
        assert!(!POSITION_AND_LAG.is_identity());
        for (name, version) in
            [("identity", 0), ("identity", 2), ("position_and_lag", 2), ("lag", 1), ("", 1)]
        {
            match lookup(name, version) {
                Err(DataError::UnknownFeatureMap { name: n, version: v, known }) => {
                    assert_eq!((n.as_str(), v), (name, version));
                    assert_eq!(known, "identity v1, position_and_lag v1");
                }
                other => panic!("{name} v{version}: {other:?}"),
            }
        }
    }

    #[test]
    fn dimensions_are_checked_before_mapping_rows() {
        assert!(IDENTITY.check_dim(0).is_ok() && IDENTITY.check_dim(3).is_ok());
        for bad in [0, 1, 3] {
            let e = POSITION_AND_LAG.check_dim(bad).unwrap_err();
            assert!(e.to_string().contains("position_and_lag v1"), "{e}");
        }
        let m = faer::mat![[1.0f32, 2.0, 0.5, 1.0], [0.0, 0.0, 0.0, 0.0]];
        let f = POSITION_AND_LAG.apply_rows(m.as_ref()).unwrap();
        assert_eq!(f, faer::mat![[0.5f32, 1.0, 0.5, 1.0], [0.0, 0.0, 0.0, 0.0]]);
        assert!(POSITION_AND_LAG.apply_rows(Mat::<f32>::zeros(2, 3).as_ref()).is_err());
    }

    #[test]
    fn ids_serialise_as_name_and_version() {
        let id = POSITION_AND_LAG.id();
        let json = serde_json::to_string(&id).unwrap();
        assert_eq!(json, r#"{"name":"position_and_lag","version":1}"#);
        assert_eq!(serde_json::from_str::<FeatureMapId>(&json).unwrap(), id);
        assert!(serde_json::from_str::<FeatureMapId>(r#"{"name":"x","version":1,"v":2}"#).is_err());
    }
}
