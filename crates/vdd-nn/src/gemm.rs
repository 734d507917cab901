//! The one matrix product every network of the workspace runs: [`matmul`], faer's
//! single-threaded product followed by clearing the upper halves of the AVX registers.
//!
//! faer's x86 kernels (hand-written assembly in `private-gemm-x86`) return with the upper
//! halves of the `ymm` registers still set. The rest of the workspace is compiled for the
//! baseline x86-64 target, so the scalar code that runs after a product (libm's `expf` and
//! `log1pf`, the experts' decoding, VDD's per-sample kernel, Cholesky factors) is legacy SSE,
//! and on CPUs that track that state every SSE instruction then pays for the dirty upper
//! halves. Measured here on an AMD EPYC: decoding 32 states × 32 experts after the trunk's
//! products took 4.8× as long as after a `vzeroupper`. [`matmul`] issues the `vzeroupper`
//! itself, so no caller has to know; it changes no value.

use faer::linalg::matmul::matmul as faer_matmul;
use faer::{Accum, MatMut, MatRef, Par};

/// `dst = alpha · lhs · rhs` (`Accum::Replace`) or `dst += alpha · lhs · rhs`
/// (`Accum::Add`), single-threaded, the same bits as faer's product; then clears the upper
/// halves of the AVX registers (see the module docs).
///
/// ```
/// use vdd_nn::matmul;
/// use faer::{Accum, Mat};
/// let a = Mat::from_fn(2, 3, |i, j| (i + j) as f32);
/// let b = Mat::from_fn(3, 1, |i, _| i as f32);
/// let mut c = Mat::zeros(2, 1);
/// matmul(c.as_mut(), Accum::Replace, a.as_ref(), b.as_ref(), 1.0);
/// assert_eq!((c[(0, 0)], c[(1, 0)]), (5.0, 8.0));
/// ```
///
/// # Panics
/// On mismatched shapes, as faer's product does.
#[inline]
pub fn matmul(
    dst: MatMut<'_, f32>,
    accum: Accum,
    lhs: MatRef<'_, f32>,
    rhs: MatRef<'_, f32>,
    alpha: f32,
) {
    faer_matmul(dst, accum, lhs, rhs, alpha, Par::Seq);
    clear_upper_avx();
}

/// Clears the upper halves of the AVX registers (`vzeroupper`) where the CPU has AVX; a no-op
/// elsewhere.
#[inline]
fn clear_upper_avx() {
    #[cfg(target_arch = "x86_64")]
    if std::arch::is_x86_feature_detected!("avx") {
        // SAFETY: the CPU supports AVX, checked just above.
        unsafe { vzeroupper() };
    }
}

/// `vzeroupper`.
///
/// # Safety
/// The CPU must support AVX.
#[cfg(target_arch = "x86_64")]
#[target_feature(enable = "avx")]
unsafe fn vzeroupper() {
    std::arch::x86_64::_mm256_zeroupper();
}

#[cfg(test)]
mod tests {
    use super::*;
    use faer::Mat;

    #[test]
    fn equals_faers_product_bit_for_bit() {
        let a = Mat::from_fn(37, 19, |i, j| ((i * 7 + j * 3) % 11) as f32 * 0.37 - 1.3);
        let b = Mat::from_fn(19, 23, |i, j| ((i * 5 + j) % 13) as f32 * -0.21 + 0.7);
        for accum in [Accum::Replace, Accum::Add] {
            let mut ours = Mat::from_fn(37, 23, |i, j| (i + j) as f32 * 0.01);
            let mut faers = ours.clone();
            matmul(ours.as_mut(), accum, a.as_ref(), b.as_ref(), 0.5);
            faer_matmul(faers.as_mut(), accum, a.as_ref(), b.as_ref(), 0.5, Par::Seq);
            assert_eq!(ours, faers);
        }
    }
}
