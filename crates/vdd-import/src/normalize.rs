//! The packages' per-feature normalisers, with their exact formulas (LeRobot's
//! `NormalizerProcessorStep`, diffusion_policy's `LinearNormalizer`).

use serde::{Deserialize, Serialize};
use vdd_nn::{Param, Parameters, join_name};

use crate::error::ImportError;

/// How one feature is normalised.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum NormKind {
    /// Unchanged (LeRobot's `IDENTITY`, or a feature type absent from `normalization_mapping`).
    Identity,
    /// LeRobot `MEAN_STD`: `(x − mean)/(std + eps)`, back `x · std + mean`; `a` = mean, `b` = std.
    MeanStd,
    /// LeRobot `MIN_MAX` (and `QUANTILES`, `QUANTILE10` with their quantiles as `a`, `b`):
    /// `2 (x − a)/(b − a) − 1` (`eps` for a zero range), back `(x + 1)/2 · (b − a) + a`.
    MinMax,
    /// diffusion_policy's `LinearNormalizer`: `x · a + b` (`a` = scale, `b` = offset), back
    /// `(x − b)/a`.
    ScaleOffset,
}

/// One feature's normaliser: its name, kind and the two statistics `a`, `b` (see
/// [`NormKind`]), saved with the teacher as tensors `<prefix>.a`, `<prefix>.b`.
#[derive(Debug, Clone)]
pub struct FeatureNorm {
    /// The feature's name in its package (`observation.state`, `obs`, `action`).
    pub name: String,
    /// The formula.
    pub kind: NormKind,
    /// First statistic (`[dim]`).
    pub a: Param,
    /// Second statistic (`[dim]`).
    pub b: Param,
    /// LeRobot's `eps`.
    pub eps: f32,
}

/// What a teacher file stores about a [`FeatureNorm`] besides its tensors.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct FeatureNormSpec {
    /// The feature's name.
    pub name: String,
    /// Its width.
    pub dim: usize,
    /// The formula.
    pub kind: NormKind,
    /// LeRobot's `eps`.
    pub eps: f32,
}

impl FeatureNorm {
    /// A normaliser with statistics `a`, `b` (checked: same length `dim`, finite; a
    /// `ScaleOffset` scale must be non-zero).
    pub fn new(
        name: &str,
        kind: NormKind,
        a: Vec<f32>,
        b: Vec<f32>,
        eps: f32,
    ) -> Result<Self, ImportError> {
        if a.len() != b.len() {
            return Err(ImportError::bad(
                name,
                "statistics",
                format!("lengths {} and {}", a.len(), b.len()),
            ));
        }
        if let Some(v) = a.iter().chain(&b).find(|v| !v.is_finite()) {
            return Err(ImportError::bad(name, "statistics", v));
        }
        if kind == NormKind::ScaleOffset && a.contains(&0.0) {
            return Err(ImportError::bad(name, "scale", 0.0));
        }
        if !(eps.is_finite() && eps >= 0.0) {
            return Err(ImportError::bad(name, "eps", eps));
        }
        let d = a.len();
        Ok(Self {
            name: name.into(),
            kind,
            a: Param::buffer(&[d], a),
            b: Param::buffer(&[d], b),
            eps,
        })
    }

    /// The identity on `dim` values.
    pub fn identity(name: &str, dim: usize) -> Self {
        Self {
            name: name.into(),
            kind: NormKind::Identity,
            a: Param::buffer(&[dim], vec![0.0; dim]),
            b: Param::buffer(&[dim], vec![1.0; dim]),
            eps: 0.0,
        }
    }

    /// A placeholder of the spec's shape, to load the statistics into.
    pub fn from_spec(spec: &FeatureNormSpec) -> Self {
        Self { kind: spec.kind, eps: spec.eps, ..Self::identity(&spec.name, spec.dim) }
    }

    /// The spec saved in a teacher file.
    pub fn spec(&self) -> FeatureNormSpec {
        FeatureNormSpec { name: self.name.clone(), dim: self.dim(), kind: self.kind, eps: self.eps }
    }

    /// The feature's width.
    pub fn dim(&self) -> usize {
        self.a.len()
    }

    /// Normalises one feature vector in place (`x.len() == dim`).
    pub fn normalize(&self, x: &mut [f32]) {
        let (a, b) = (&self.a.value, &self.b.value);
        for (i, v) in x.iter_mut().enumerate() {
            *v = match self.kind {
                NormKind::Identity => *v,
                NormKind::MeanStd => (*v - a[i]) / (b[i] + self.eps),
                NormKind::MinMax => 2.0 * (*v - a[i]) / self.range(i) - 1.0,
                NormKind::ScaleOffset => *v * a[i] + b[i],
            };
        }
    }

    /// Maps one normalised feature vector back in place.
    pub fn unnormalize(&self, x: &mut [f32]) {
        let (a, b) = (&self.a.value, &self.b.value);
        for (i, v) in x.iter_mut().enumerate() {
            *v = match self.kind {
                NormKind::Identity => *v,
                NormKind::MeanStd => *v * b[i] + a[i],
                NormKind::MinMax => (*v + 1.0) / 2.0 * self.range(i) + a[i],
                NormKind::ScaleOffset => (*v - b[i]) / a[i],
            };
        }
    }

    fn range(&self, i: usize) -> f32 {
        let d = self.b.value[i] - self.a.value[i];
        if d == 0.0 { self.eps } else { d }
    }

    /// The normalisation as `(offset, scale)` with `y = (x − offset)/scale` per dimension
    /// (the form of [`vdd_core::Affine`]); `scale` may be negative for a `ScaleOffset` map.
    pub fn as_offset_scale(&self) -> (Vec<f32>, Vec<f32>) {
        let (a, b) = (&self.a.value, &self.b.value);
        (0..self.dim())
            .map(|i| match self.kind {
                NormKind::Identity => (0.0, 1.0),
                NormKind::MeanStd => (a[i], b[i] + self.eps),
                NormKind::MinMax => (a[i] + 0.5 * self.range(i), 0.5 * self.range(i)),
                NormKind::ScaleOffset => (-b[i] / a[i], 1.0 / a[i]),
            })
            .unzip()
    }
}

impl Parameters for FeatureNorm {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        f(&join_name(prefix, "a"), &self.a);
        f(&join_name(prefix, "b"), &self.b);
    }
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        f(&join_name(prefix, "a"), &mut self.a);
        f(&join_name(prefix, "b"), &mut self.b);
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn every_kind_round_trips_and_matches_its_offset_scale_form() {
        for kind in [NormKind::Identity, NormKind::MeanStd, NormKind::MinMax, NormKind::ScaleOffset]
        {
            let n = FeatureNorm::new("f", kind, vec![-1.0, 0.5], vec![3.0, 0.5], 1e-8).unwrap();
            let x = [0.7f32, 0.5];
            let mut y = x;
            n.normalize(&mut y);
            let (off, sc) = n.as_offset_scale();
            // (dimension 1 has a zero range: its eps-wide scale is not worth comparing)
            for i in 0..1 {
                assert!(
                    ((x[i] - off[i]) / sc[i] - y[i]).abs() < 1e-3 * (1.0 + y[i].abs()),
                    "{kind:?}"
                );
            }
            n.unnormalize(&mut y);
            assert!((y[0] - x[0]).abs() < 1e-5, "{kind:?}");
        }
        assert!(FeatureNorm::new("f", NormKind::MinMax, vec![f32::NAN], vec![1.0], 0.0).is_err());
    }
}
