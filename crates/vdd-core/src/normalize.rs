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

/// Largest magnitude of a normaliser offset. Data of any task here is orders of magnitude
/// inside it; beyond it, `(x − offset) / scale` loses every digit of `x` in `f32` (an offset of
/// `2^63` maps every observation to the same state).
pub const MAX_ABS_NORMALIZER_OFFSET: f32 = 1e6;

/// Smallest normaliser scale. Fitted normalisers floor their scales far above it (`1e-4`);
/// below it, a normalised value (or a denormalised action, or the log-determinant of a
/// likelihood) overflows for ordinary inputs.
pub const MIN_NORMALIZER_SCALE: f32 = 1e-6;

/// Largest normaliser scale (see [`MIN_NORMALIZER_SCALE`]).
pub const MAX_NORMALIZER_SCALE: f32 = 1e6;

impl Affine {
    /// Builds the map. Every offset must be finite with `|offset| <=`
    /// [`MAX_ABS_NORMALIZER_OFFSET`] and every scale finite within
    /// [`MIN_NORMALIZER_SCALE`]`..=`[`MAX_NORMALIZER_SCALE`]; the error names the dimension and
    /// the value.
    ///
    /// ```
    /// use vdd_core::Affine;
    /// assert!(Affine::new(vec![9.2e18], vec![1.0]).is_err()); // offset 2^63
    /// assert!(Affine::new(vec![0.0], vec![1e-38]).unwrap_err().to_string().contains("1e-38"));
    /// ```
    pub fn new(offset: Vec<f32>, scale: Vec<f32>) -> Result<Self> {
        check_len("normalizer scale", scale.len(), offset.len())?;
        if offset.iter().any(|x| !x.is_finite()) {
            return Err(CoreError::NonFinite { what: "normalizer offset" });
        }
        if let Some((j, x)) =
            offset.iter().enumerate().find(|(_, x)| x.abs() > MAX_ABS_NORMALIZER_OFFSET)
        {
            return Err(CoreError::Config(format!(
                "normalizer offset {x:e} of dimension {j} is beyond the bound \
                 |offset| <= {MAX_ABS_NORMALIZER_OFFSET:e}"
            )));
        }
        if scale.iter().any(|s| !(s.is_finite() && *s > 0.0)) {
            return Err(CoreError::Config("normalizer scales must be positive and finite".into()));
        }
        if let Some((j, s)) = scale
            .iter()
            .enumerate()
            .find(|(_, s)| !(MIN_NORMALIZER_SCALE..=MAX_NORMALIZER_SCALE).contains(*s))
        {
            return Err(CoreError::Config(format!(
                "normalizer scale {s:e} of dimension {j} is outside the bounds \
                 {MIN_NORMALIZER_SCALE:e}..={MAX_NORMALIZER_SCALE:e}"
            )));
        }
        Ok(Self { offset, scale })
    }

    /// Checks this map with [`Affine::new`]'s rules (its fields are public, so a value built or
    /// deserialised without `new` may break them).
    pub fn validate(&self) -> Result<()> {
        Self::new(self.offset.clone(), self.scale.clone()).map(|_| ())
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
