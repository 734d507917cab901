//! Learning-rate schedules: a factor in `(0, 1]` multiplied into an optimiser's base rate.
//!
//! Schedules are relative to the run: [`LrSchedule::factor`] takes the step and the run's total
//! number of steps, which the trainer supplies, so a configuration never bakes in a length and
//! changing a run's iterations keeps the schedule's shape.

use serde::{Deserialize, Serialize};

/// A learning-rate schedule over a run; [`LrSchedule::factor`] gives the multiplier at a step
/// of a run of `total_steps` steps.
///
/// ```
/// use vdd_nn::LrSchedule;
/// let s = LrSchedule::LinearDecay { final_factor: 0.1 };
/// assert_eq!(s.factor(0, 100), 1.0);
/// assert!((s.factor(50, 100) - 0.55).abs() < 1e-6);
/// assert!((s.factor(1000, 100) - 0.1).abs() < 1e-6);
/// // The same schedule over a run twice as long is halfway at step 100.
/// assert!((s.factor(100, 200) - 0.55).abs() < 1e-6);
/// ```
#[derive(Debug, Clone, Default, PartialEq, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
pub enum LrSchedule {
    /// Always 1.
    #[default]
    Constant,
    /// Linear from 1 at the first step to `final_factor` at the end of the run.
    LinearDecay {
        /// The factor at the end of the run (and after it).
        final_factor: f32,
    },
    /// Cosine from 1 at the first step to `final_factor` at the end of the run.
    Cosine {
        /// The factor at the end of the run (and after it).
        final_factor: f32,
    },
    /// Linear warm-up from `1 / warmup_steps` to 1 over the first `warmup_steps` steps, then
    /// `then` over the rest of the run (counted from the warm-up's end).
    Warmup {
        /// Warm-up length in steps.
        warmup_steps: u64,
        /// The schedule after warm-up.
        then: Box<LrSchedule>,
    },
}

impl LrSchedule {
    /// The multiplier at `step` (0-based) of a run of `total_steps` steps (a run of 0 steps
    /// counts as 1).
    pub fn factor(&self, step: u64, total_steps: u64) -> f32 {
        let progress = || (step as f64 / total_steps.max(1) as f64).min(1.0);
        match self {
            Self::Constant => 1.0,
            Self::LinearDecay { final_factor } => {
                let p = progress() as f32;
                1.0 + p * (final_factor - 1.0)
            }
            Self::Cosine { final_factor } => {
                let p = progress();
                let c = 0.5 * (1.0 + (std::f64::consts::PI * p).cos());
                (*final_factor as f64 + (1.0 - *final_factor as f64) * c) as f32
            }
            Self::Warmup { warmup_steps, then } => {
                if step < *warmup_steps {
                    (step + 1) as f32 / *warmup_steps as f32
                } else {
                    then.factor(step - warmup_steps, total_steps.saturating_sub(*warmup_steps))
                }
            }
        }
    }

    /// Checks the schedule's numbers (factors finite and positive).
    pub fn validate(&self) -> Result<(), crate::NnError> {
        match self {
            Self::Constant => Ok(()),
            Self::LinearDecay { final_factor } | Self::Cosine { final_factor } => {
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
        let cos = LrSchedule::Cosine { final_factor: 0.2 };
        assert!((cos.factor(0, 10) - 1.0).abs() < 1e-6);
        assert!((cos.factor(5, 10) - 0.6).abs() < 1e-6);
        assert!((cos.factor(10, 10) - 0.2).abs() < 1e-6);
        assert!((cos.factor(99, 10) - 0.2).abs() < 1e-6);
        let w = LrSchedule::Warmup { warmup_steps: 4, then: Box::new(cos.clone()) };
        assert!((w.factor(0, 14) - 0.25).abs() < 1e-6);
        assert!((w.factor(3, 14) - 1.0).abs() < 1e-6);
        assert!((w.factor(9, 14) - 0.6).abs() < 1e-6);
        let lin = LrSchedule::LinearDecay { final_factor: 0.0 };
        assert_eq!(lin.factor(2, 4), 0.5);
        assert_eq!(LrSchedule::Constant.factor(7, 1), 1.0);
        assert!(LrSchedule::LinearDecay { final_factor: f32::NAN }.validate().is_err());
    }

    /// A decay never reaches 0 before the run ends, whatever its length: the trap of a
    /// schedule fixed at 600 steps in a run of 1500 is gone.
    #[test]
    fn schedules_follow_the_length_of_the_run() {
        let lin = LrSchedule::LinearDecay { final_factor: 0.0 };
        for total in [1u64, 600, 1500] {
            assert!((0..total).all(|s| lin.factor(s, total) > 0.0), "{total}");
            assert_eq!(lin.factor(total, total), 0.0);
        }
        // The formula of a decay fitted to `total` steps, bit for bit.
        for (step, total) in [(0u64, 7u64), (3, 7), (599, 600), (1234, 20_000)] {
            let p = (step as f64 / total as f64).min(1.0) as f32;
            assert_eq!(lin.factor(step, total).to_bits(), (1.0 + p * (0.0 - 1.0)).to_bits());
        }
    }

    #[test]
    fn schedules_round_trip_through_serde() {
        let w = LrSchedule::Warmup {
            warmup_steps: 3,
            then: Box::new(LrSchedule::LinearDecay { final_factor: 0.1 }),
        };
        let s = serde_json::to_string(&w).unwrap();
        assert_eq!(serde_json::from_str::<LrSchedule>(&s).unwrap(), w);
        // A configuration written with a baked-in length still reads (the length is ignored).
        let old = r#"{"linear_decay":{"total_steps":600,"final_factor":0.0}}"#;
        assert_eq!(
            serde_json::from_str::<LrSchedule>(old).unwrap(),
            LrSchedule::LinearDecay { final_factor: 0.0 }
        );
    }
}
