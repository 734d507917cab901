//! What `vdd.distill` was asked for besides the teacher and the data: its keyword settings
//! (fields of the trainer's and the student's configurations, and a few of its own), shared by
//! the run of a Python or `vdd-diffusion` teacher (`distill`) and that of an imported one
//! (`imported`).

use pyo3::exceptions::PyValueError;
use pyo3::prelude::*;
use serde_json::Value;
use vdd::{MoeConfig, VddConfig, VddError};
use vdd_core::CoreError;

/// Keys of `vdd.distill`'s own arguments, which `**settings` must not repeat.
const RESERVED: &[(&str, &str)] = &[
    ("seed", "seed="),
    ("iterations", "iterations="),
    ("num_experts", "experts="),
    ("action_dim", "action_dim="),
    ("state_dim", "the columns of `states`"),
];

/// Applies `settings` to the trainer's and the student's configurations (each key is a field of
/// `VddConfig` or `MoeConfig`); an unknown key is an error naming it.
pub fn apply_settings(
    vdd: &mut VddConfig,
    moe: &mut MoeConfig,
    settings: &[(String, Value)],
) -> Result<(), String> {
    let mut v = serde_json::to_value(&*vdd).map_err(|e| e.to_string())?;
    let mut m = serde_json::to_value(&*moe).map_err(|e| e.to_string())?;
    // Every trainer field, those left out of the serialised form when unset included.
    let probe = VddConfig {
        noise_anneal_until: Some(0.0),
        score_at: vdd::ScoreAt::NoisedSample,
        state_noise: Some(vdd::StateNoise { share: 1.0, std: 1.0 }),
        experts_per_state: Some(1),
        ..vdd.clone()
    };
    let trainer_fields = serde_json::to_value(&probe).map_err(|e| e.to_string())?;
    for (key, value) in settings {
        if let Some((_, instead)) = RESERVED.iter().find(|(k, _)| k == key) {
            return Err(format!("setting `{key}`: give it as {instead}"));
        }
        let target = if trainer_fields.get(key).is_some() {
            &mut v
        } else if m.get(key).is_some() {
            &mut m
        } else {
            let names = |x: &Value| {
                let own = |k: &String| !RESERVED.iter().any(|(r, _)| r == k);
                x.as_object()
                    .map(|o| o.keys().filter(|k| own(k)).cloned().collect::<Vec<_>>().join(", "))
            };
            return Err(format!(
                "unknown setting `{key}` (trainer settings: {}; student settings: {})",
                names(&trainer_fields).unwrap_or_default(),
                names(&m).unwrap_or_default()
            ));
        };
        target[key.as_str()] = value.clone();
    }
    *vdd = serde_json::from_value(v).map_err(|e| format!("invalid trainer setting: {e}"))?;
    *moe = serde_json::from_value(m).map_err(|e| format!("invalid student setting: {e}"))?;
    Ok(())
}

/// Which defaults `distill` starts from (the setting `defaults`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub(crate) enum Defaults {
    /// [`Vdd::auto`]: picked from the teacher ([`AutoPlan::inspect`]).
    Auto,
    /// The paper's toy settings ([`VddConfig::toy`], [`MoeConfig::toy`]) with [`Vdd::new`].
    Toy,
}

/// A failed run: a training error, or a setting the plan's configurations refuse.
pub(crate) enum RunError {
    Vdd(VddError),
    Setting(String),
}

impl From<VddError> for RunError {
    fn from(e: VddError) -> Self {
        Self::Vdd(e)
    }
}

impl From<CoreError> for RunError {
    fn from(e: CoreError) -> Self {
        Self::Vdd(e.into())
    }
}

impl From<vdd::MoeError> for RunError {
    fn from(e: vdd::MoeError) -> Self {
        Self::Vdd(e.into())
    }
}

/// What `distill` was asked for, besides the teacher and the data.
pub(crate) struct Request {
    pub(crate) defaults: Defaults,
    pub(crate) experts: usize,
    pub(crate) iterations: Option<usize>,
    pub(crate) seed: u64,
    pub(crate) state_dim: usize,
    pub(crate) action_dim: usize,
    pub(crate) settings: Vec<(String, Value)>,
}

/// Settings of `distill` that are neither the trainer's nor the student's: how many teacher
/// actions the plan inspects (`teacher_samples`) and, for an imported teacher, the clamp's
/// margin (`clip_margin`, `None` to distil the raw score).
#[derive(Debug, Default)]
pub(crate) struct Extra {
    pub(crate) teacher_samples: Option<usize>,
    pub(crate) clip_margin: Option<Option<f32>>,
    /// `noise_range=(min, max)`: the VE levels a Python `score_fn` is trustworthy at.
    pub(crate) noise_range: Option<vdd_core::VeProcess>,
}

impl Extra {
    /// Takes `key` if it is one of these settings.
    pub(crate) fn take(&mut self, key: &str, v: &Bound<'_, PyAny>) -> PyResult<bool> {
        match key {
            "teacher_samples" => {
                let n: usize = v.extract().map_err(|_| {
                    PyValueError::new_err("setting `teacher_samples`: expected a positive integer")
                })?;
                if n == 0 {
                    return Err(PyValueError::new_err(
                        "setting `teacher_samples`: must be positive",
                    ));
                }
                self.teacher_samples = Some(n);
                Ok(true)
            }
            "clip_margin" => {
                let m: Option<f32> = v.extract().map_err(|_| {
                    PyValueError::new_err("setting `clip_margin`: expected a number or None")
                })?;
                if m.is_some_and(|m| !(m.is_finite() && m >= 0.0)) {
                    return Err(PyValueError::new_err(
                        "setting `clip_margin`: must be finite and non-negative (or None)",
                    ));
                }
                self.clip_margin = Some(m);
                Ok(true)
            }
            "noise_range" => {
                let bad = || {
                    PyValueError::new_err(format!(
                        "setting `noise_range`: expected (min, max) with 0 <= min < max, min \
                         finite (max may be inf), got {}",
                        v.repr().map(|r| r.to_string()).unwrap_or_default()
                    ))
                };
                let (min, max): (f32, f32) = v.extract().map_err(|_| bad())?;
                if !(min.is_finite() && min >= 0.0 && max > min) {
                    return Err(bad());
                }
                self.noise_range = Some(vdd_core::VeProcess { min, max });
                Ok(true)
            }
            _ => Ok(false),
        }
    }

    /// Errors if a setting only a Python `score_fn` reads was given (a `vdd.Teacher` states
    /// its own noise range).
    pub(crate) fn refuse_score_fn_only(&self) -> PyResult<()> {
        if self.noise_range.is_some() {
            return Err(PyValueError::new_err(
                "setting `noise_range` is for a Python score_fn; a vdd.Teacher states its own",
            ));
        }
        Ok(())
    }

    /// Errors if a setting only an imported teacher reads was given.
    pub(crate) fn refuse_imported_only(&self) -> PyResult<()> {
        if self.clip_margin.is_some() {
            return Err(PyValueError::new_err(
                "setting `clip_margin` applies to a teacher imported from PyTorch \
                 (vdd.import_lerobot)",
            ));
        }
        Ok(())
    }
}

impl Request {
    /// The toy configurations with `iterations`, `seed` and the settings applied.
    pub(crate) fn toy_configs(&self) -> Result<(VddConfig, MoeConfig), String> {
        let mut config = VddConfig { seed: self.seed, ..VddConfig::toy() };
        if let Some(it) = self.iterations {
            config.iterations = it;
        }
        let mut moe = MoeConfig::toy(self.state_dim, self.action_dim, self.experts);
        apply_settings(&mut config, &mut moe, &self.settings)?;
        Ok((config, moe))
    }
}
