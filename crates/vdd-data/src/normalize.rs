//! Normalisation of observations and actions, fitted on the training split and saved with any
//! model trained on it.
//!
//! Both kinds are per-dimension affine maps `x' = (x − offset) / scale`, returned as
//! [`vdd_core::Affine`] so a model can store them beside its weights:
//!
//! * **standard**: `offset = mean`, `scale = max(std, std_floor)` (population std, `ddof = 0`);
//! * **min-max** to `[-1, 1]`: `offset = (max + min) / 2`, `scale = max((max − min) / 2, floor)`.
//!
//! Statistics use every valid step (never the padding) of the episodes they are fitted on, and
//! are accumulated in `f64`.

use serde::{Deserialize, Serialize};
use vdd_core::Affine;

use crate::episodes::Episodes;
use crate::error::{DataError, Result};

/// Which normalisation to fit.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(tag = "kind", rename_all = "snake_case")]
pub enum NormalizationKind {
    /// No normalisation (offset 0, scale 1).
    Identity,
    /// Zero mean and unit variance per dimension; a dimension whose std is below `std_floor`
    /// is divided by `std_floor` instead (so constant dimensions map to 0, not NaN).
    Standard {
        /// Smallest scale used (positive).
        std_floor: f32,
    },
    /// The training range of each dimension onto `[-1, 1]`; a dimension whose half-range is
    /// below `half_range_floor` is divided by the floor instead.
    MinMax {
        /// Smallest scale used (positive).
        half_range_floor: f32,
    },
}

impl NormalizationKind {
    /// Standard normalisation with `std_floor = 1e-4`.
    pub const fn standard() -> Self {
        Self::Standard { std_floor: 1e-4 }
    }

    /// Min-max normalisation to `[-1, 1]` with `half_range_floor = 1e-4`.
    pub const fn min_max() -> Self {
        Self::MinMax { half_range_floor: 1e-4 }
    }

    fn floor(&self) -> Option<f32> {
        match *self {
            Self::Identity => None,
            Self::Standard { std_floor } => Some(std_floor),
            Self::MinMax { half_range_floor } => Some(half_range_floor),
        }
    }
}

/// A fitted normalisation of observations and actions, serialisable with serde.
///
/// ```
/// use faer::Mat;
/// use vdd_data::{Episodes, Normalization, NormalizationKind};
/// let obs = vec![Mat::from_fn(4, 1, |t, _| t as f32)]; // 0, 1, 2, 3
/// let act = vec![Mat::from_fn(4, 1, |t, _| 10.0 * t as f32)]; // 0, 10, 20, 30
/// let train = Episodes::from_episodes(obs, act).unwrap();
/// let norm = Normalization::fit(&train, NormalizationKind::min_max()).unwrap();
/// assert_eq!(norm.observations.offset, vec![1.5]);
/// assert_eq!(norm.actions.scale, vec![15.0]);
/// let normalized = train.normalized(&norm).unwrap();
/// assert_eq!(normalized.observations(0)[(0, 0)], -1.0);
/// assert_eq!(normalized.actions(0)[(3, 0)], 1.0);
/// // Saved beside a model, loaded back identically.
/// let json = norm.to_json().unwrap();
/// assert_eq!(Normalization::from_json(&json).unwrap(), norm);
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Normalization {
    /// The kind it was fitted as.
    pub kind: NormalizationKind,
    /// The map for (single-step) observations, dimension `d_obs`. [`Affine::normalize`] also
    /// applies it to a flattened observation window (concatenated steps).
    pub observations: Affine,
    /// The map for (single-step) actions, dimension `d_act`; applies to action chunks likewise.
    pub actions: Affine,
}

impl Normalization {
    /// The identity normalisation for the given dimensions.
    pub fn identity(obs_dim: usize, act_dim: usize) -> Self {
        Self {
            kind: NormalizationKind::Identity,
            observations: Affine::identity(obs_dim),
            actions: Affine::identity(act_dim),
        }
    }

    /// Fits `kind` on every valid step of `train` (pass the training split only).
    ///
    /// Errors: [`DataError::Config`] for a floor that is not positive and finite;
    /// [`DataError::Core`] if a fitted offset or scale is not a finite `f32` (data near the
    /// `f32` range limits).
    pub fn fit(train: &Episodes, kind: NormalizationKind) -> Result<Self> {
        if let Some(floor) = kind.floor() {
            if !(floor.is_finite() && floor > 0.0) {
                return Err(DataError::Config(format!(
                    "normalisation floor must be positive and finite, got {floor}"
                )));
            }
        }
        let observations = fit_affine(train, kind, |i, t| train.step_observation(i, t))?;
        let actions = fit_affine(train, kind, |i, t| train.step_action(i, t))?;
        Ok(Self { kind, observations, actions })
    }

    /// JSON text of this normalisation (to store beside a model).
    pub fn to_json(&self) -> Result<String> {
        serde_json::to_string_pretty(self).map_err(DataError::Json)
    }

    /// Parses [`Normalization::to_json`] output, re-validating both maps (finite offsets,
    /// positive finite scales, matching lengths).
    pub fn from_json(text: &str) -> Result<Self> {
        let parsed: Self = serde_json::from_str(text).map_err(DataError::Json)?;
        let observations =
            Affine::new(parsed.observations.offset.clone(), parsed.observations.scale.clone())?;
        let actions = Affine::new(parsed.actions.offset.clone(), parsed.actions.scale.clone())?;
        Ok(Self { kind: parsed.kind, observations, actions })
    }

    pub(crate) fn check_dims(&self, obs_dim: usize, act_dim: usize) -> Result<()> {
        if self.observations.dim() != obs_dim || self.actions.dim() != act_dim {
            return Err(DataError::Shape {
                what: "normalisation dimensions (observations, actions)".into(),
                expected: format!("({obs_dim}, {act_dim})"),
                got: format!("({}, {})", self.observations.dim(), self.actions.dim()),
            });
        }
        Ok(())
    }
}

fn fit_affine<'a>(
    episodes: &'a Episodes,
    kind: NormalizationKind,
    step: impl Fn(usize, usize) -> &'a [f32],
) -> Result<Affine> {
    let d = step(0, 0).len();
    let steps = || {
        episodes
            .lengths()
            .iter()
            .enumerate()
            .flat_map(move |(i, &len)| (0..len).map(move |t| (i, t)))
    };
    let (offset, scale): (Vec<f64>, Vec<f64>) = match kind {
        NormalizationKind::Identity => return Ok(Affine::identity(d)),
        NormalizationKind::Standard { std_floor } => {
            let n = episodes.num_steps() as f64;
            let mut mean = vec![0.0f64; d];
            for (i, t) in steps() {
                for (m, &x) in mean.iter_mut().zip(step(i, t)) {
                    *m += x as f64;
                }
            }
            mean.iter_mut().for_each(|m| *m /= n);
            let mut var = vec![0.0f64; d];
            for (i, t) in steps() {
                for ((v, &x), m) in var.iter_mut().zip(step(i, t)).zip(&mean) {
                    *v += (x as f64 - m).powi(2);
                }
            }
            let std = var.iter().map(|v| (v / n).sqrt().max(std_floor as f64)).collect();
            (mean, std)
        }
        NormalizationKind::MinMax { half_range_floor } => {
            let mut lo = vec![f64::INFINITY; d];
            let mut hi = vec![f64::NEG_INFINITY; d];
            for (i, t) in steps() {
                for (j, &x) in step(i, t).iter().enumerate() {
                    lo[j] = lo[j].min(x as f64);
                    hi[j] = hi[j].max(x as f64);
                }
            }
            let mid = lo.iter().zip(&hi).map(|(l, h)| 0.5 * (l + h)).collect();
            let half = lo
                .iter()
                .zip(&hi)
                .map(|(l, h)| (0.5 * (h - l)).max(half_range_floor as f64))
                .collect();
            (mid, half)
        }
    };
    let offset = offset.into_iter().map(|x| x as f32).collect();
    // A scale can only round to zero or overflow with extreme data; Affine::new rejects it.
    let scale = scale.into_iter().map(|x| x as f32).collect();
    Ok(Affine::new(offset, scale)?)
}

impl Episodes {
    /// A copy with observations and actions mapped through `normalization` (valid steps only;
    /// padding stays zero).
    ///
    /// Errors: [`DataError::Shape`] when the normalisation's dimensions differ from the data's,
    /// [`DataError::NonFinite`] if a value overflows.
    pub fn normalized(&self, normalization: &Normalization) -> Result<Self> {
        normalization.check_dims(self.obs_dim(), self.act_dim())?;
        self.map_steps(
            |o| normalization.observations.normalize(o),
            |a| normalization.actions.normalize(a),
        )
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::episodes::tests::ramp_episodes;
    use faer::Mat;

    fn column_stats(m: &Mat<f32>, j: usize) -> (f64, f64, f32, f32) {
        let xs: Vec<f64> = (0..m.nrows()).map(|i| m[(i, j)] as f64).collect();
        let mean = xs.iter().sum::<f64>() / xs.len() as f64;
        let var = xs.iter().map(|x| (x - mean).powi(2)).sum::<f64>() / xs.len() as f64;
        let lo = (0..m.nrows()).map(|i| m[(i, j)]).fold(f32::INFINITY, f32::min);
        let hi = (0..m.nrows()).map(|i| m[(i, j)]).fold(f32::NEG_INFINITY, f32::max);
        (mean, var.sqrt(), lo, hi)
    }

    #[test]
    fn standard_gives_zero_mean_unit_std_on_valid_steps() {
        let e = ramp_episodes(7, 3, 2);
        let norm = Normalization::fit(&e, NormalizationKind::standard()).unwrap();
        let (s, a) = e.normalized(&norm).unwrap().to_matrices();
        for m in [&s, &a] {
            for j in 0..m.ncols() {
                let (mean, std, _, _) = column_stats(m, j);
                assert!(mean.abs() < 1e-5, "mean {mean}");
                assert!((std - 1.0).abs() < 1e-5, "std {std}");
            }
        }
        // The padding (zeros) must not enter the statistics: the valid observations of
        // dimension 0 have mean 100 * mean(i) + 10 * mean(t) > 250, far from a zero-diluted mean.
        let (raw, _) = e.to_matrices();
        let (mean0, std0, _, _) = column_stats(&raw, 0);
        assert!((norm.observations.offset[0] as f64 - mean0).abs() < 1e-3);
        assert!((norm.observations.scale[0] as f64 - std0).abs() < 1e-3);
    }

    #[test]
    fn min_max_maps_training_range_onto_unit_interval() {
        let e = ramp_episodes(5, 2, 3);
        let norm = Normalization::fit(&e, NormalizationKind::min_max()).unwrap();
        let (s, a) = e.normalized(&norm).unwrap().to_matrices();
        for m in [&s, &a] {
            for j in 0..m.ncols() {
                let (_, _, lo, hi) = column_stats(m, j);
                assert!((lo + 1.0).abs() < 1e-6 && (hi - 1.0).abs() < 1e-6, "{lo} {hi}");
            }
        }
    }

    #[test]
    fn constant_dimensions_use_the_floor() {
        let obs = vec![Mat::from_fn(5, 2, |t, j| if j == 0 { 3.0 } else { t as f32 })];
        let act = vec![Mat::from_fn(5, 1, |_, _| -2.0)];
        let e = Episodes::from_episodes(obs, act).unwrap();
        for kind in [
            NormalizationKind::Standard { std_floor: 0.01 },
            NormalizationKind::MinMax { half_range_floor: 0.01 },
        ] {
            let norm = Normalization::fit(&e, kind).unwrap();
            assert_eq!(norm.observations.scale[0], 0.01);
            assert_eq!(norm.actions.scale[0], 0.01);
            assert!(norm.observations.scale[1] > 1.0);
            let n = e.normalized(&norm).unwrap();
            assert_eq!(n.observations(0)[(2, 0)], 0.0);
            assert_eq!(n.actions(0)[(4, 0)], 0.0);
        }
        for floor in [0.0, -1.0, f32::NAN, f32::INFINITY] {
            let kind = NormalizationKind::Standard { std_floor: floor };
            assert!(matches!(Normalization::fit(&e, kind), Err(DataError::Config(_))));
        }
    }

    #[test]
    fn fitted_on_the_training_split_only() {
        let e = ramp_episodes(10, 2, 1);
        let split = e.split(0.3, 3).unwrap();
        let on_train = Normalization::fit(&split.train, NormalizationKind::standard()).unwrap();
        let on_all = Normalization::fit(&e, NormalizationKind::standard()).unwrap();
        assert_ne!(on_train, on_all);
        let (s, _) = split.train.to_matrices();
        let (mean, _, _, _) = column_stats(&s, 1);
        assert!((on_train.observations.offset[1] as f64 - mean).abs() < 1e-3);
    }

    #[test]
    fn identity_and_round_trip_through_affine() {
        let e = ramp_episodes(3, 2, 2);
        let id = Normalization::fit(&e, NormalizationKind::Identity).unwrap();
        assert_eq!(id, Normalization::identity(2, 2));
        assert_eq!(e.normalized(&id).unwrap(), e);
        let norm = Normalization::fit(&e, NormalizationKind::standard()).unwrap();
        let n = e.normalized(&norm).unwrap();
        let mut row: Vec<f32> = (0..2).map(|j| n.observations(2)[(3, j)]).collect();
        norm.observations.denormalize(&mut row);
        for j in 0..2 {
            approx::assert_relative_eq!(row[j], e.observations(2)[(3, j)], max_relative = 1e-5);
        }
        assert!(matches!(
            e.normalized(&Normalization::identity(3, 2)),
            Err(DataError::Shape { .. })
        ));
    }

    #[test]
    fn json_round_trip_and_validation() {
        let e = ramp_episodes(4, 2, 1);
        for kind in [NormalizationKind::standard(), NormalizationKind::min_max()] {
            let norm = Normalization::fit(&e, kind).unwrap();
            let json = norm.to_json().unwrap();
            assert!(json.contains(if matches!(kind, NormalizationKind::MinMax { .. }) {
                "min_max"
            } else {
                "standard"
            }));
            assert_eq!(Normalization::from_json(&json).unwrap(), norm);
        }
        let bad = r#"{"kind":{"kind":"identity"},"observations":{"offset":[0.0],"scale":[-1.0]},
                      "actions":{"offset":[0.0],"scale":[1.0]}}"#;
        assert!(matches!(Normalization::from_json(bad), Err(DataError::Core(_))));
        assert!(matches!(Normalization::from_json("{"), Err(DataError::Json(_))));
    }
}
