//! Checks of settings that size memory against the machine, before anything is allocated.
//!
//! Estimates are products of sizes, computed with saturating arithmetic so that absurd settings
//! (`2^62` experts) give `u64::MAX` instead of overflowing; [`check_fits`] compares one with the
//! memory available ([`available_bytes`]).

use crate::error::CoreError;

/// Memory the machine can give a new allocation without swapping: `MemAvailable` of
/// `/proc/meminfo` on Linux, `None` where it is unknown.
pub fn available_bytes() -> Option<u64> {
    let info = std::fs::read_to_string("/proc/meminfo").ok()?;
    let line = info.lines().find(|l| l.starts_with("MemAvailable:"))?;
    let kib: u64 = line.split_whitespace().nth(1)?.parse().ok()?;
    Some(kib.saturating_mul(1024))
}

/// Bytes assumed available where the machine does not say ([`available_bytes`] is `None`).
pub const UNKNOWN_AVAILABLE: u64 = 64 << 30;

/// Checks that `bytes`, the estimated memory of `what`, fits in the memory available (or in
/// [`UNKNOWN_AVAILABLE`] where that is unknown); the error names `what` and both sizes.
///
/// ```
/// use vdd_core::memory::check_fits;
/// assert!(check_fits("a small buffer", 1 << 20).is_ok());
/// let e = check_fits("student.num_experts = 100000000", u64::MAX).unwrap_err();
/// assert!(e.to_string().contains("num_experts"));
/// ```
pub fn check_fits(what: &str, bytes: u64) -> Result<(), CoreError> {
    let available = available_bytes().unwrap_or(UNKNOWN_AVAILABLE);
    if bytes <= available {
        return Ok(());
    }
    let gib = |b: u64| b as f64 / f64::from(1u32 << 30);
    Err(CoreError::Config(format!(
        "{what} needs about {:.1} GiB of memory, more than the {:.1} GiB available",
        gib(bytes),
        gib(available)
    )))
}

/// The product of `factors`, saturating at `u64::MAX`.
///
/// ```
/// assert_eq!(vdd_core::memory::product(&[1 << 40, 1 << 40]), u64::MAX);
/// assert_eq!(vdd_core::memory::product(&[3, 4]), 12);
/// ```
pub fn product(factors: &[usize]) -> u64 {
    factors.iter().fold(1u64, |acc, &f| acc.saturating_mul(f as u64))
}
