//! Exponential moving average of a model's parameters.

use serde::{Deserialize, Serialize};

use crate::error::NnError;
use crate::param::{Param, Parameters};

/// An exponential moving average `θ̄ ← decay·θ̄ + (1 − decay)·θ` of every trainable parameter
/// (buffers are copied as they are), for evaluating with averaged weights or as the target
/// network `θ⁻` of consistency distillation.
///
/// The average is itself a [`Parameters`] with the model's names, so it saves with
/// [`crate::io::save_safetensors`] as a loadable `state_dict`; it is serde-serialisable for
/// checkpoints.
///
/// ```
/// use vdd_nn::{Ema, Linear, Parameters};
/// let mut rng = vdd_core::Seeds::new(0).stream("init");
/// let mut layer = Linear::new(2, 1, &mut rng);
/// let mut ema = Ema::new(&layer, 0.9).unwrap();
/// let start = layer.bias.value[0];
/// layer.bias.value[0] = start + 1.0; // a training step
/// ema.update(&layer).unwrap();
/// ema.swap(&mut layer).unwrap(); // evaluate with the average
/// assert!((layer.bias.value[0] - (start + 0.1)).abs() < 1e-6);
/// ema.swap(&mut layer).unwrap(); // back to the trained weights
/// assert_eq!(layer.bias.value[0], start + 1.0);
/// ```
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct Ema {
    decay: f32,
    num_updates: u64,
    names: Vec<String>,
    shadow: Vec<Param>,
}

fn mismatch(what: String) -> NnError {
    NnError::ModelMismatch(format!("EMA: {what}"))
}

impl Ema {
    /// An average starting at the model's current parameters; `decay` in `[0, 1]`.
    pub fn new(model: &dyn Parameters, decay: f32) -> Result<Self, NnError> {
        if !(0.0..=1.0).contains(&decay) {
            return Err(NnError::Config(format!("EMA decay must be in [0, 1], got {decay}")));
        }
        let (mut names, mut shadow) = (Vec::new(), Vec::new());
        model.visit_params("", &mut |name, p| {
            names.push(name.to_owned());
            shadow.push(Param {
                value: p.value.clone(),
                grad: Vec::new(),
                shape: p.shape.clone(),
                trainable: p.trainable,
            });
        });
        Ok(Self { decay, num_updates: 0, names, shadow })
    }

    /// The decay rate.
    pub fn decay(&self) -> f32 {
        self.decay
    }

    /// Number of [`Ema::update`] calls so far.
    pub fn num_updates(&self) -> u64 {
        self.num_updates
    }

    /// Checks that `model` has the same parameter names and sizes, in the same order.
    fn check(&self, model: &dyn Parameters) -> Result<(), NnError> {
        let mut k = 0;
        let mut err = None;
        model.visit_params("", &mut |name, p| {
            if err.is_some() {
                return;
            }
            match (self.names.get(k), self.shadow.get(k)) {
                (Some(n), Some(s)) if n == name && s.len() == p.len() => {}
                (Some(n), Some(s)) => {
                    err = Some(mismatch(format!(
                        "parameter {k} is `{name}` ({} values), the average has `{n}` ({})",
                        p.len(),
                        s.len()
                    )))
                }
                _ => err = Some(mismatch(format!("the model has more parameters (`{name}`)"))),
            }
            k += 1;
        });
        if let Some(e) = err {
            return Err(e);
        }
        if k != self.shadow.len() {
            return Err(mismatch(format!(
                "the model has {k} parameters, the average {}",
                self.shadow.len()
            )));
        }
        Ok(())
    }

    /// Checks a restored average (e.g. from a checkpoint) against `model`: the decay in
    /// `[0, 1]`, the same parameter names and sizes in the same order, and finite values within
    /// [`MAX_ABS_WEIGHT`](crate::limits::MAX_ABS_WEIGHT) (the average becomes weights). The
    /// error names the first parameter that does not match.
    pub fn validate(&self, model: &dyn Parameters) -> Result<(), NnError> {
        if !(0.0..=1.0).contains(&self.decay) {
            return Err(mismatch(format!("decay must be in [0, 1], got {}", self.decay)));
        }
        if self.names.len() != self.shadow.len() {
            return Err(mismatch(format!(
                "{} names for {} tensors",
                self.names.len(),
                self.shadow.len()
            )));
        }
        self.check(model)?;
        for (name, p) in self.names.iter().zip(&self.shadow) {
            let size = p.shape.iter().try_fold(1usize, |n, &d| n.checked_mul(d));
            if size != Some(p.value.len()) {
                return Err(mismatch(format!(
                    "`{name}` has shape {:?} but {} values",
                    p.shape,
                    p.value.len()
                )));
            }
            if !p.value.iter().all(|v| v.is_finite()) {
                return Err(mismatch(format!("`{name}` holds non-finite values")));
            }
            // The average becomes a model's weights: the weights' bound applies.
            crate::io::check_values(name, &p.value).map_err(mismatch)?;
        }
        Ok(())
    }

    /// One averaging step towards the model's current parameters.
    pub fn update(&mut self, model: &dyn Parameters) -> Result<(), NnError> {
        self.check(model)?;
        let a = 1.0 - self.decay;
        let mut k = 0;
        let shadow = &mut self.shadow;
        model.visit_params("", &mut |_, p| {
            let s = &mut shadow[k].value;
            if p.trainable {
                for (s, &v) in s.iter_mut().zip(&p.value) {
                    *s += a * (v - *s);
                }
            } else {
                s.copy_from_slice(&p.value);
            }
            k += 1;
        });
        self.num_updates += 1;
        Ok(())
    }

    /// Overwrites the model's parameters with the average.
    pub fn copy_to(&self, model: &mut dyn Parameters) -> Result<(), NnError> {
        self.check(model)?;
        let mut k = 0;
        model.visit_params_mut("", &mut |_, p| {
            p.value.copy_from_slice(&self.shadow[k].value);
            k += 1;
        });
        Ok(())
    }

    /// Exchanges the model's parameters and the average (call twice to restore).
    pub fn swap(&mut self, model: &mut dyn Parameters) -> Result<(), NnError> {
        self.check(model)?;
        let mut k = 0;
        let shadow = &mut self.shadow;
        model.visit_params_mut("", &mut |_, p| {
            std::mem::swap(&mut p.value, &mut shadow[k].value);
            k += 1;
        });
        Ok(())
    }
}

impl Parameters for Ema {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        for (name, p) in self.names.iter().zip(&self.shadow) {
            f(&crate::join_name(prefix, name), p);
        }
    }
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        for (name, p) in self.names.iter().zip(&mut self.shadow) {
            f(&crate::join_name(prefix, name), p);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Activation, FourierFeatures, Linear, ResidualMlp, ResidualMlpConfig};

    fn net(seed: u64, blocks: usize) -> ResidualMlp {
        let cfg = ResidualMlpConfig {
            in_dim: 2,
            hidden_dim: 4,
            num_blocks: blocks,
            out_dim: 1,
            activation: Activation::Mish,
            layer_norm: true,
        };
        ResidualMlp::new(&cfg, &mut vdd_core::Seeds::new(seed).stream("i")).unwrap()
    }

    fn values(m: &dyn Parameters) -> Vec<Vec<f32>> {
        let mut v = Vec::new();
        m.visit_params("", &mut |_, p| v.push(p.value.clone()));
        v
    }

    #[test]
    fn average_follows_the_closed_form() {
        // Constant target θ₁ from θ₀: θ̄_t = θ₁ + decay^t (θ₀ − θ₁).
        let mut model = net(0, 1);
        let start = values(&model);
        let mut ema = Ema::new(&model, 0.8).unwrap();
        let target = values(&net(1, 1));
        let mut k = 0;
        model.visit_params_mut("", &mut |_, p| {
            p.value.clone_from(&target[k]);
            k += 1;
        });
        for _ in 0..5 {
            ema.update(&model).unwrap();
        }
        assert_eq!(ema.num_updates(), 5);
        let avg = values(&ema);
        let w = 0.8f32.powi(5);
        for ((a, s), t) in avg.iter().zip(&start).zip(&target) {
            for ((a, s), t) in a.iter().zip(s).zip(t) {
                assert!((a - (t + w * (s - t))).abs() < 1e-5);
            }
        }
        // copy_to and swap.
        let mut other = net(2, 1);
        ema.copy_to(&mut other).unwrap();
        assert_eq!(values(&other), avg);
        ema.swap(&mut model).unwrap();
        assert_eq!(values(&model), avg);
        assert_eq!(values(&ema), target);
    }

    #[test]
    fn buffers_are_copied_not_averaged_and_serde_round_trips() {
        let mut rng = vdd_core::Seeds::new(0).stream("i");
        let mut ff = FourierFeatures::new(4, 30.0, &mut rng).unwrap();
        let mut ema = Ema::new(&ff, 0.5).unwrap();
        ff.w.value[0] = 1.0;
        ema.update(&ff).unwrap();
        assert_eq!(values(&ema)[0][0], 1.0);
        let json = serde_json::to_string(&ema).unwrap();
        assert_eq!(serde_json::from_str::<Ema>(&json).unwrap(), ema);
    }

    #[test]
    fn mismatched_models_and_bad_decay_are_errors() {
        let ema = Ema::new(&net(0, 1), 0.99).unwrap();
        let mut deeper = net(0, 2);
        assert!(matches!(ema.copy_to(&mut deeper), Err(NnError::ModelMismatch(_))));
        let mut layer = Linear::new(2, 4, &mut vdd_core::Seeds::new(0).stream("i"));
        assert!(matches!(ema.copy_to(&mut layer), Err(NnError::ModelMismatch(_))));
        assert!(Ema::new(&layer, 1.5).is_err() && Ema::new(&layer, f32::NAN).is_err());
    }

    #[test]
    fn a_restored_shape_that_overflows_is_an_error() {
        let layer = Linear::new(2, 3, &mut vdd_core::Seeds::new(0).stream("i"));
        let mut json = serde_json::to_value(Ema::new(&layer, 0.9).unwrap()).unwrap();
        let huge = 1usize << (usize::BITS / 2 + 1);
        json["shadow"][0]["shape"] = serde_json::json!([huge, huge, 6]);
        let restored: Ema = serde_json::from_value(json).unwrap();
        assert!(matches!(restored.validate(&layer), Err(NnError::ModelMismatch(_))));
    }
}
