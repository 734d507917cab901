//! Learning-rate schedules: a factor in `(0, 1]` multiplied into an optimiser's base rate.

use serde::{Deserialize, Serialize};

/// A learning-rate schedule; [`LrSchedule::factor`] gives the multiplier at a step.
///
/// ```
/// use vdd_nn::LrSchedule;
/// let s = LrSchedule::LinearDecay { total_steps: 100, final_factor: 0.1 };
/// assert_eq!(s.factor(0), 1.0);
/// assert!((s.factor(50) - 0.55).abs() < 1e-6);
/// assert!((s.factor(1000) - 0.1).abs() < 1e-6);
/// ```
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LrSchedule {
    /// Always 1.
    #[default]
    Constant,
    /// Linear from 1 at step 0 to `final_factor` at `total_steps`, constant afterwards.
    LinearDecay {
        /// Steps until the final factor is reached.
        total_steps: u64,
        /// The factor at and after `total_steps`.
        final_factor: f32,
    },
    /// Cosine from 1 at step 0 to `final_factor` at `total_steps`, constant afterwards.
    Cosine {
        /// Steps until the final factor is reached.
        total_steps: u64,
        /// The factor at and after `total_steps`.
        final_factor: f32,
    },
    /// Linear warm-up from `1 / warmup_steps` to 1, then `then` (counted from the warm-up's end).
    Warmup {
        /// Warm-up length.
        warmup_steps: u64,
        /// The schedule after warm-up.
        then: Box<LrSchedule>,
    },
}

impl LrSchedule {
    /// The multiplier at `step` (0-based).
    pub fn factor(&self, step: u64) -> f32 {
        let progress =
            |total: u64| if total == 0 { 1.0 } else { (step as f64 / total as f64).min(1.0) };
        match self {
            Self::Constant => 1.0,
            Self::LinearDecay { total_steps, final_factor } => {
                let p = progress(*total_steps) as f32;
                1.0 + p * (final_factor - 1.0)
            }
            Self::Cosine { total_steps, final_factor } => {
                let p = progress(*total_steps);
                let c = 0.5 * (1.0 + (std::f64::consts::PI * p).cos());
                (*final_factor as f64 + (1.0 - *final_factor as f64) * c) as f32
            }
            Self::Warmup { warmup_steps, then } => {
                if step < *warmup_steps {
                    (step + 1) as f32 / *warmup_steps as f32
                } else {
                    then.factor(step - warmup_steps)
                }
            }
        }
    }

    /// Checks the schedule's numbers (factors finite and positive).
    pub fn validate(&self) -> Result<(), crate::NnError> {
        match self {
            Self::Constant => Ok(()),
            Self::LinearDecay { final_factor, .. } | Self::Cosine { final_factor, .. } => {
                if final_factor.is_finite() && *final_factor >= 0.0 {
                    Ok(())
                } else {
                    Err(crate::NnError::Config(format!(
                        "schedule final_factor must be finite and >= 0, got {final_factor}"
                    )))
                }
            }
            Self::Warmup { then, .. } => then.validate(),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn schedules_hit_their_end_points() {
        let cos = LrSchedule::Cosine { total_steps: 10, final_factor: 0.2 };
        assert!((cos.factor(0) - 1.0).abs() < 1e-6);
        assert!((cos.factor(5) - 0.6).abs() < 1e-6);
        assert!((cos.factor(10) - 0.2).abs() < 1e-6);
        assert!((cos.factor(99) - 0.2).abs() < 1e-6);
        let w = LrSchedule::Warmup { warmup_steps: 4, then: Box::new(cos.clone()) };
        assert!((w.factor(0) - 0.25).abs() < 1e-6);
        assert!((w.factor(3) - 1.0).abs() < 1e-6);
        assert!((w.factor(9) - 0.6).abs() < 1e-6);
        let lin = LrSchedule::LinearDecay { total_steps: 4, final_factor: 0.0 };
        assert_eq!(lin.factor(2), 0.5);
        assert_eq!(LrSchedule::Constant.factor(7), 1.0);
        assert!(
            LrSchedule::LinearDecay { total_steps: 1, final_factor: f32::NAN }.validate().is_err()
        );
    }

    #[test]
    fn schedules_round_trip_through_serde() {
        let w = LrSchedule::Warmup {
            warmup_steps: 3,
            then: Box::new(LrSchedule::LinearDecay { total_steps: 5, final_factor: 0.1 }),
        };
        let s = serde_json::to_string(&w).unwrap();
        assert_eq!(serde_json::from_str::<LrSchedule>(&s).unwrap(), w);
    }
}
