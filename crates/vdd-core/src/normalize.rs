//! Per-dimension affine normalisation `x' = (x − offset) / scale`, the form both standard
//! (offset = mean, scale = std) and min-max normalisation take. Models store it beside their
//! weights so a deployed policy needs nothing else.

use faer::{Mat, MatRef};
use serde::{Deserialize, Serialize};

use crate::error::{CoreError, Result, check_len};

/// A per-dimension affine map `x' = (x − offset) / scale`.
///
/// ```
/// use vdd_core::Affine;
/// let n = Affine::new(vec![1.0, 2.0], vec![2.0, 4.0]).unwrap();
/// let mut x = [3.0f32, 2.0];
/// n.normalize(&mut x);
/// assert_eq!(x, [1.0, 0.0]);
/// n.denormalize(&mut x);
/// assert_eq!(x, [3.0, 2.0]);
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Affine {
    /// Subtracted first.
    pub offset: Vec<f32>,
    /// Divided by second (all positive).
    pub scale: Vec<f32>,
}

impl Affine {
    /// Builds the map; every scale must be positive and finite.
    pub fn new(offset: Vec<f32>, scale: Vec<f32>) -> Result<Self> {
        check_len("normalizer scale", scale.len(), offset.len())?;
        if offset.iter().any(|x| !x.is_finite()) {
            return Err(CoreError::NonFinite { what: "normalizer offset" });
        }
        if scale.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(CoreError::Config("normalizer scales must be positive and finite".into()));
        }
        Ok(Self { offset, scale })
    }

    /// The identity map on `dim` dimensions.
    pub fn identity(dim: usize) -> Self {
        Self { offset: vec![0.0; dim], scale: vec![1.0; dim] }
    }

    /// Number of dimensions.
    pub fn dim(&self) -> usize {
        self.offset.len()
    }

    /// `x ← (x − offset) / scale`, one vector of length `dim()` (or several concatenated).
    pub fn normalize(&self, x: &mut [f32]) {
        let d = self.dim();
        for (i, v) in x.iter_mut().enumerate() {
            *v = (*v - self.offset[i % d]) / self.scale[i % d];
        }
    }

    /// `(m − offset) / scale` on every row of `m` (`n x dim()`), as a new matrix; an error when
    /// the columns are not `dim()`.
    ///
    /// ```
    /// let a = vdd_core::Affine::new(vec![1.0, 0.0], vec![2.0, 4.0])?;
    /// let m = a.normalize_rows(faer::mat![[3.0f32, 8.0], [1.0, -4.0]].as_ref())?;
    /// assert_eq!((m[(0, 0)], m[(0, 1)], m[(1, 0)], m[(1, 1)]), (1.0, 2.0, 0.0, -1.0));
    /// # Ok::<(), vdd_core::CoreError>(())
    /// ```
    pub fn normalize_rows(&self, m: MatRef<'_, f32>) -> Result<Mat<f32>> {
        check_len("columns to normalise", m.ncols(), self.dim())?;
        Ok(Mat::from_fn(m.nrows(), m.ncols(), |i, j| (m[(i, j)] - self.offset[j]) / self.scale[j]))
    }

    /// `x ← x · scale + offset`.
    pub fn denormalize(&self, x: &mut [f32]) {
        let d = self.dim();
        for (i, v) in x.iter_mut().enumerate() {
            *v = *v * self.scale[i % d] + self.offset[i % d];
        }
    }
}
