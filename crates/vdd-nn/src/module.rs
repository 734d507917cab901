//! The [`Module`] trait: a differentiable map on batches with explicit forward and backward.

use faer::MatRef;

use crate::param::Parameters;

/// A layer or network mapping a batch `n x in_dim` to `n x out_dim`.
///
/// `forward` keeps what `backward` needs (inputs or activations) in buffers owned by the
/// module and reused across calls of the same batch size, so a training loop does not
/// allocate. `backward` takes the gradient of a scalar loss with respect to the last forward's
/// output, **accumulates** parameter gradients (call [`Parameters::zero_grad`] between steps)
/// and returns the gradient with respect to the input. Both return views into the module's own
/// buffers, valid until its next call.
pub trait Module: Parameters {
    /// Input features.
    fn in_dim(&self) -> usize;

    /// Output features.
    fn out_dim(&self) -> usize;

    /// Forward pass over a batch (`n x in_dim`); returns `n x out_dim`.
    ///
    /// # Panics
    /// If `x.ncols() != self.in_dim()`: callers validate user data before it reaches a network.
    fn forward(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32>;

    /// [`Module::forward`] for inference: the same output, bit for bit, without keeping what
    /// `backward` needs (no copy of the input, no activation derivatives). Use it where nothing
    /// is differentiated: a teacher's score, a sampler, a policy acting. The default is
    /// `forward`.
    ///
    /// # Panics
    /// As [`Module::forward`]; and a `backward` right after it panics (no forward kept its
    /// inputs).
    fn forward_inference(&mut self, x: MatRef<'_, f32>) -> MatRef<'_, f32> {
        self.forward(x)
    }

    /// Backward pass for the last forward; `grad_out` is `n x out_dim`, returns `n x in_dim`.
    ///
    /// # Panics
    /// If `grad_out` does not match the last forward's output shape.
    fn backward(&mut self, grad_out: MatRef<'_, f32>) -> MatRef<'_, f32>;
}

/// `m`'s [`Module::forward`], or its [`Module::forward_inference`] when `inference`: for code
/// that runs one path for training and inference alike.
///
/// ```
/// use vdd_nn::{Linear, Module, forward_as};
/// let mut layer = Linear::new(3, 2, &mut vdd_core::Seeds::new(0).stream("init"));
/// let x = faer::Mat::<f32>::ones(4, 3);
/// let train = forward_as(&mut layer, x.as_ref(), false).to_owned();
/// assert_eq!(forward_as(&mut layer, x.as_ref(), true).to_owned(), train);
/// ```
#[inline]
pub fn forward_as<'a, M: Module + ?Sized>(
    m: &'a mut M,
    x: MatRef<'_, f32>,
    inference: bool,
) -> MatRef<'a, f32> {
    if inference { m.forward_inference(x) } else { m.forward(x) }
}

/// Copies the single row of `x` (`1 x dst.len()`) into `dst`: a slice copy when the row is
/// contiguous (the single-row outputs of the crate's layers are).
#[inline]
pub(crate) fn gather_row(x: MatRef<'_, f32>, dst: &mut [f32]) {
    debug_assert_eq!((x.nrows(), x.ncols()), (1, dst.len()));
    match x.row(0).try_as_row_major() {
        Some(r) => dst.copy_from_slice(r.as_slice()),
        None => {
            for (j, v) in dst.iter_mut().enumerate() {
                *v = x[(0, j)];
            }
        }
    }
}

/// `x` itself when its columns are contiguous, otherwise a contiguous copy in `scratch`.
pub(crate) fn contiguous<'a>(
    x: MatRef<'a, f32>,
    scratch: &'a mut faer::Mat<f32>,
) -> MatRef<'a, f32> {
    if x.row_stride() == 1 {
        x
    } else {
        ensure_shape(scratch, x.nrows(), x.ncols());
        scratch.copy_from(x);
        scratch.as_ref()
    }
}

/// Column `j` of a matrix with contiguous columns (see [`contiguous`]) as a slice.
#[inline]
pub(crate) fn col_slice(m: MatRef<'_, f32>, j: usize) -> &[f32] {
    match m.col(j).try_as_col_major() {
        Some(c) => c.as_slice(),
        None => panic!("column {j} is not contiguous"),
    }
}

/// Resizes an owned buffer to `rows x cols` if needed (no allocation when it already fits).
pub(crate) fn ensure_shape(m: &mut faer::Mat<f32>, rows: usize, cols: usize) {
    if m.nrows() != rows || m.ncols() != cols {
        *m = faer::Mat::zeros(rows, cols);
    }
}
