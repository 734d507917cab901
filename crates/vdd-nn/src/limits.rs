//! Documented limits on networks: what a configuration may ask for and what a weights file
//! may hold. Every network built here and every file loaded through [`crate::io`] is checked
//! against them before memory is allocated, so a hostile or corrupt configuration (a file's
//! metadata, a recipe) gives an error instead of an abort, a panic or a hang.
//!
//! The limits are far above any model of the paper (its largest networks have well under a
//! million parameters) and leave room for the teachers users import (LeRobot's default
//! diffusion policy has 248 million):
//!
//! | limit | value | what it bounds |
//! |---|---|---|
//! | [`MAX_WIDTH`] | 65,536 | any single input, hidden or output width |
//! | [`MAX_BLOCKS`] | 1,024 | residual blocks of one network |
//! | [`MAX_PARAMS`] | 2^29 (536,870,912; 2 GiB of `f32`) | parameters of one model |
//! | [`MAX_ABS_WEIGHT`] | 10^6 | magnitude of any weight read or written |
//! | [`MAX_ABS_ADAM_FIRST_MOMENT`] | 10^15 | magnitude of an Adam first moment (a gradient average) |
//! | [`MAX_ADAM_SECOND_MOMENT`] | 10^30 | an Adam second moment (a squared-gradient average) |
//!
//! Normaliser offsets and scales are bounded in `vdd_core` ([`vdd_core::MAX_ABS_NORMALIZER_OFFSET`],
//! [`vdd_core::MIN_NORMALIZER_SCALE`], [`vdd_core::MAX_NORMALIZER_SCALE`]). Writers check the
//! same bounds as loaders, so whatever is written can be read back.
//!
//! ```
//! use vdd_nn::{limits, Activation, ResidualMlpConfig};
//! let cfg = ResidualMlpConfig { in_dim: 3, hidden_dim: 32, num_blocks: 2, out_dim: 4,
//!                               activation: Activation::Mish, layer_norm: false };
//! assert_eq!(cfg.num_params(), Some(3 * 32 + 32 + 2 * 2 * (32 * 32 + 32) + 32 * 4 + 4));
//! let huge = ResidualMlpConfig { hidden_dim: 60_000, ..cfg };
//! assert!(limits::check_params("a network", huge.num_params()).is_err());
//! ```

use crate::NnError;

/// Largest width (input, hidden or output features) of one layer.
pub const MAX_WIDTH: usize = 1 << 16;

/// Largest number of residual blocks of one network.
pub const MAX_BLOCKS: usize = 1024;

/// Largest number of parameters of one model (2^29, 2 GiB of `f32`): room for LeRobot's
/// default `DiffusionPolicy` (a U-Net of 248 million parameters) with its image encoders.
pub const MAX_PARAMS: usize = 1 << 29;

/// Largest magnitude of a weight read from a file. Trained networks stay orders of magnitude
/// below it; a value beyond it is corruption, and it would turn outputs non-finite.
pub const MAX_ABS_WEIGHT: f32 = 1e6;

/// Largest magnitude of an Adam first moment (a moving average of gradients) read from or
/// written to a checkpoint. A gradient of this size means a diverged run; beyond it, the next
/// update would throw the weights past [`MAX_ABS_WEIGHT`] at once.
pub const MAX_ABS_ADAM_FIRST_MOMENT: f32 = 1e15;

/// Largest Adam second moment (a moving average of squared gradients), the square of
/// [`MAX_ABS_ADAM_FIRST_MOMENT`].
pub const MAX_ADAM_SECOND_MOMENT: f32 = 1e30;

/// Checks that `value` (the setting `what`) is in `1..=max`.
pub fn check_size(what: &str, value: usize, max: usize) -> Result<(), NnError> {
    if value == 0 || value > max {
        return Err(NnError::Config(format!("{what} must be in 1..={max}, got {value}")));
    }
    Ok(())
}

/// Checks a parameter count computed with checked arithmetic (`None`: it overflowed) against
/// [`MAX_PARAMS`].
pub fn check_params(what: &str, count: Option<usize>) -> Result<usize, NnError> {
    match count {
        Some(n) if n <= MAX_PARAMS => Ok(n),
        Some(n) => Err(NnError::Config(format!(
            "{what} would have {n} parameters, more than the limit of {MAX_PARAMS}"
        ))),
        None => Err(NnError::Config(format!(
            "{what} would have more parameters than the limit of {MAX_PARAMS} (the count overflows)"
        ))),
    }
}

/// Parameters of a linear layer `in_dim → out_dim` (weight and bias), `None` on overflow.
pub fn linear_params(in_dim: usize, out_dim: usize) -> Option<usize> {
    in_dim.checked_mul(out_dim)?.checked_add(out_dim)
}
