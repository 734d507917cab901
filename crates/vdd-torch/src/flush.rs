//! Subnormal floats kept out of the forward passes.
//!
//! A subnormal `f32` (magnitude below [`f32::MIN_POSITIVE`], about 1.2e-38) can cost a CPU a
//! microcode assist per operation. Where a network runs on inputs or activations that are
//! subnormal, every layer after it can run many times slower than on normal values while the
//! result differs from the flushed one by less than 1e-38. [`FlushSubnormals`] turns on the
//! CPU's flush-to-zero and denormals-are-zero modes for the duration of a forward pass (x86-64:
//! MXCSR's FTZ and DAZ bits; AArch64: FPCR's FZ bit) and restores the caller's mode when
//! dropped; [`flush_subnormal`] is the element-wise software fallback used where a layer can
//! make a subnormal value itself, so targets without the hardware modes get zeros there too.
//!
//! Results on normal values are bit for bit those without flushing: only operations whose
//! operands or results are subnormal see a difference (a zero in their place).

use std::marker::PhantomData;

/// Flushes subnormal results to zero and reads subnormal operands as zero on this thread until
/// dropped, then restores the previous floating-point mode (guards nest).
///
/// The floating-point control register is per thread, so the guard is neither `Send` nor
/// `Sync`: it must be dropped on the thread that made it. On targets other than x86-64 and
/// AArch64 it does nothing ([`FlushSubnormals::is_hardware`] says which); the networks also
/// flush the values their element-wise layers make ([`flush_subnormal`]).
///
/// ```
/// let tiny = std::hint::black_box(f32::MIN_POSITIVE);
/// {
///     let _guard = vdd_torch::FlushSubnormals::new();
///     if vdd_torch::FlushSubnormals::is_hardware() {
///         assert_eq!(std::hint::black_box(tiny * 0.5), 0.0);
///     }
/// }
/// assert!((std::hint::black_box(tiny * 0.5)).is_subnormal());
/// ```
#[derive(Debug)]
#[must_use = "the mode is restored when the guard is dropped"]
pub struct FlushSubnormals {
    /// The control register's value before the guard.
    #[cfg_attr(not(any(target_arch = "x86_64", target_arch = "aarch64")), allow(dead_code))]
    saved: u64,
    /// Not `Send`/`Sync`: the mode belongs to the thread.
    _thread: PhantomData<*const ()>,
}

#[cfg(target_arch = "x86_64")]
mod arch {
    /// MXCSR flush-to-zero (bit 15) and denormals-are-zero (bit 6).
    pub(super) const BITS: u64 = (1 << 15) | (1 << 6);

    pub(super) fn read() -> u64 {
        let mut v: u32 = 0;
        // SAFETY: `stmxcsr` stores the 32-bit MXCSR into `v`, a valid, writable u32.
        unsafe {
            std::arch::asm!("stmxcsr [{}]", in(reg) &mut v, options(nostack, preserves_flags));
        }
        u64::from(v)
    }

    pub(super) fn write(v: u64) {
        let v = v as u32;
        // SAFETY: `ldmxcsr` loads MXCSR from `v`; the values written are ones read from MXCSR
        // with only the FTZ/DAZ bits changed (valid on every x86-64 CPU with SSE2, i.e. all).
        unsafe {
            std::arch::asm!("ldmxcsr [{}]", in(reg) &v, options(nostack, readonly, preserves_flags));
        }
    }
}

#[cfg(target_arch = "aarch64")]
mod arch {
    /// FPCR flush-to-zero (bit 24; on AArch64 it also flushes subnormal inputs).
    pub(super) const BITS: u64 = 1 << 24;

    pub(super) fn read() -> u64 {
        let v: u64;
        // SAFETY: reading FPCR has no side effect.
        unsafe { std::arch::asm!("mrs {}, fpcr", out(reg) v, options(nomem, nostack)) };
        v
    }

    pub(super) fn write(v: u64) {
        // SAFETY: the value is FPCR as read, with only the FZ bit changed.
        unsafe { std::arch::asm!("msr fpcr, {}", in(reg) v, options(nomem, nostack)) };
    }
}

impl FlushSubnormals {
    /// Turns flushing on for this thread (a no-op where [`FlushSubnormals::is_hardware`] is
    /// false).
    pub fn new() -> Self {
        #[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
        {
            let saved = arch::read();
            if saved & arch::BITS != arch::BITS {
                arch::write(saved | arch::BITS);
            }
            Self { saved, _thread: PhantomData }
        }
        #[cfg(not(any(target_arch = "x86_64", target_arch = "aarch64")))]
        Self { saved: 0, _thread: PhantomData }
    }

    /// Whether this target flushes in hardware (x86-64, AArch64).
    pub const fn is_hardware() -> bool {
        cfg!(any(target_arch = "x86_64", target_arch = "aarch64"))
    }
}

impl Default for FlushSubnormals {
    fn default() -> Self {
        Self::new()
    }
}

impl Drop for FlushSubnormals {
    fn drop(&mut self) {
        #[cfg(any(target_arch = "x86_64", target_arch = "aarch64"))]
        if arch::read() != self.saved {
            arch::write(self.saved);
        }
    }
}

/// `x`, or zero when `x` is subnormal (branch-free, so loops vectorise).
///
/// ```
/// assert_eq!(vdd_torch::flush_subnormal(f32::MIN_POSITIVE / 2.0), 0.0);
/// assert_eq!(vdd_torch::flush_subnormal(-1.5), -1.5);
/// ```
#[inline(always)]
pub fn flush_subnormal(x: f32) -> f32 {
    if x.abs() < f32::MIN_POSITIVE { 0.0 } else { x }
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::hint::black_box;

    #[test]
    fn the_guard_flushes_and_restores_the_mode_even_when_nested() {
        let tiny = black_box(f32::MIN_POSITIVE);
        let half = |v: f32| black_box(black_box(v) * 0.5);
        assert!(half(tiny).is_subnormal());
        {
            let _outer = FlushSubnormals::new();
            {
                let _inner = FlushSubnormals::new();
                if FlushSubnormals::is_hardware() {
                    assert_eq!(half(tiny), 0.0);
                    // Denormals-are-zero: a subnormal operand reads as zero.
                    assert_eq!(black_box(black_box(tiny / 4.0) + 0.0), 0.0);
                }
            }
            if FlushSubnormals::is_hardware() {
                assert_eq!(half(tiny), 0.0, "the inner guard keeps the outer's mode");
            }
        }
        assert!(half(tiny).is_subnormal(), "the mode is restored");
        assert_eq!(half(2.0), 1.0);
    }
}
