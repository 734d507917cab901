//! Optimisers over any [`Parameters`]: Adam and AdamW.

use serde::{Deserialize, Serialize};

use crate::error::NnError;
use crate::param::Parameters;

/// Hyper-parameters of [`Adam`].
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct AdamConfig {
    /// Base learning rate (multiplied by the schedule's factor at each step).
    pub lr: f32,
    /// First-moment decay.
    pub beta1: f32,
    /// Second-moment decay.
    pub beta2: f32,
    /// Denominator epsilon.
    pub eps: f32,
    /// Weight decay: L2 added to the gradient (Adam) or decoupled (AdamW).
    pub weight_decay: f32,
    /// `true` for AdamW's decoupled weight decay.
    pub decoupled: bool,
}

impl AdamConfig {
    /// Checks the documented ranges: `lr` finite and `>= 0`, `beta1` and `beta2` in `[0, 1)`,
    /// `eps` finite and `> 0`, `weight_decay` finite and `>= 0`.
    ///
    /// ```
    /// use vdd_nn::AdamConfig;
    /// assert!(AdamConfig::default().validate().is_ok());
    /// assert!(AdamConfig { eps: -1.0, ..Default::default() }.validate().is_err());
    /// assert!(AdamConfig { beta2: 1.0, ..Default::default() }.validate().is_err());
    /// ```
    pub fn validate(&self) -> Result<(), NnError> {
        let bad = |name: &str, v: f32, range: &str| {
            Err(NnError::Config(format!("Adam {name} must be {range}, got {v}")))
        };
        if !(self.lr.is_finite() && self.lr >= 0.0) {
            return bad("lr", self.lr, "finite and >= 0");
        }
        for (name, b) in [("beta1", self.beta1), ("beta2", self.beta2)] {
            if !(0.0..1.0).contains(&b) {
                return bad(name, b, "in [0, 1)");
            }
        }
        if !(self.eps.is_finite() && self.eps > 0.0) {
            return bad("eps", self.eps, "finite and > 0");
        }
        if !(self.weight_decay.is_finite() && self.weight_decay >= 0.0) {
            return bad("weight_decay", self.weight_decay, "finite and >= 0");
        }
        Ok(())
    }
}

impl Default for AdamConfig {
    fn default() -> Self {
        Self { lr: 1e-3, beta1: 0.9, beta2: 0.999, eps: 1e-8, weight_decay: 0.0, decoupled: false }
    }
}

/// Adam / AdamW (Kingma & Ba 2015; Loshchilov & Hutter 2019) with PyTorch's update rule.
///
/// State is kept per parameter in visiting order, so one optimiser must always be stepped on
/// the same model.
///
/// ```
/// use vdd_nn::{Adam, AdamConfig, Param, Parameters};
/// struct Scalar(Param);
/// impl Parameters for Scalar {
///     fn visit_params(&self, p: &str, f: &mut dyn FnMut(&str, &Param)) { f(p, &self.0) }
///     fn visit_params_mut(&mut self, p: &str, f: &mut dyn FnMut(&str, &mut Param)) { f(p, &mut self.0) }
/// }
/// let mut x = Scalar(Param::new(&[1], vec![3.0]));
/// let mut opt = Adam::new(AdamConfig { lr: 0.1, ..Default::default() });
/// for _ in 0..200 {
///     x.zero_grad();
///     x.0.grad[0] = 2.0 * x.0.value[0]; // d/dx x²
///     opt.step(&mut x, 1.0).unwrap();
/// }
/// assert!(x.0.value[0].abs() < 0.05);
/// ```
#[derive(Debug, Clone, Serialize, Deserialize)]
pub struct Adam {
    config: AdamConfig,
    step: u64,
    m: Vec<Vec<f32>>,
    v: Vec<Vec<f32>>,
}

impl Adam {
    /// A fresh optimiser.
    pub fn new(config: AdamConfig) -> Self {
        Self { config, step: 0, m: Vec::new(), v: Vec::new() }
    }

    /// The hyper-parameters.
    pub fn config(&self) -> &AdamConfig {
        &self.config
    }

    /// Number of steps taken.
    pub fn steps(&self) -> u64 {
        self.step
    }

    /// Checks that this optimiser's state belongs to `params`: its hyper-parameters are in
    /// range ([`AdamConfig::validate`]), and its moments are either empty (no step taken) or one
    /// finite pair per parameter, in visiting order, of the parameter's size (second moments
    /// `>= 0`), within the bounds of [`crate::limits`] (`|m| <=`
    /// [`MAX_ABS_ADAM_FIRST_MOMENT`](crate::limits::MAX_ABS_ADAM_FIRST_MOMENT), `v <=`
    /// [`MAX_ADAM_SECOND_MOMENT`](crate::limits::MAX_ADAM_SECOND_MOMENT)). The error names the
    /// first parameter that does not match (and the value out of bounds). Checkpoint writers
    /// call it before writing, loaders after reading. A restored
    /// optimiser (e.g. from a checkpoint) should be checked before it steps.
    ///
    /// ```
    /// use vdd_nn::{Adam, AdamConfig, Linear};
    /// let mut rng = vdd_core::Seeds::new(0).stream("init");
    /// let (mut small, big) = (Linear::new(2, 1, &mut rng), Linear::new(3, 1, &mut rng));
    /// let mut opt = Adam::new(AdamConfig::default());
    /// opt.step(&mut small, 1.0).unwrap();
    /// assert!(opt.check(&small).is_ok());
    /// assert!(opt.check(&big).unwrap_err().to_string().contains("weight"));
    /// ```
    pub fn check(&self, params: &dyn Parameters) -> Result<(), NnError> {
        self.config.validate()?;
        let mismatch = |what: String| Err(NnError::ModelMismatch(format!("Adam state: {what}")));
        if self.m.len() != self.v.len() {
            let (m, v) = (self.m.len(), self.v.len());
            return mismatch(format!("{m} first moments but {v} second moments"));
        }
        let mut k = 0;
        let mut err: Option<String> = None;
        params.visit_params("", &mut |name, p| {
            if err.is_none() && !self.m.is_empty() {
                err = match (self.m.get(k), self.v.get(k)) {
                    (Some(m), Some(v)) if m.len() != p.len() || v.len() != p.len() => {
                        Some(format!("`{name}` has {} values but its moments {}", p.len(), m.len()))
                    }
                    (Some(m), Some(v))
                        if !m.iter().all(|x| x.is_finite())
                            || !v.iter().all(|x| x.is_finite() && *x >= 0.0) =>
                    {
                        Some(format!("the moments of `{name}` are not finite (or negative)"))
                    }
                    (Some(m), Some(v)) => check_moments(name, m, v).err(),
                    _ => Some(format!("no moments for `{name}` (parameter {k})")),
                };
            }
            k += 1;
        });
        if let Some(e) = err {
            return mismatch(e);
        }
        if !self.m.is_empty() && self.m.len() != k {
            return mismatch(format!(
                "{} moment pairs for a model of {k} parameters",
                self.m.len()
            ));
        }
        Ok(())
    }

    /// One update with learning rate `config.lr * lr_factor` using the accumulated gradients
    /// (buffers, `trainable == false`, are skipped).
    ///
    /// A model that does not match the optimiser's state ([`Adam::check`]'s sizes: another
    /// architecture than the one it stepped before) is an error, and nothing is changed.
    pub fn step(&mut self, params: &mut dyn Parameters, lr_factor: f32) -> Result<(), NnError> {
        self.check_sizes(params)?;
        self.step += 1;
        let c = self.config;
        let lr = c.lr * lr_factor;
        let bc1 = 1.0 - c.beta1.powi(self.step.min(i32::MAX as u64) as i32);
        let bc2 = 1.0 - c.beta2.powi(self.step.min(i32::MAX as u64) as i32);
        let step_size = lr / bc1;
        let bc2_sqrt = bc2.sqrt();
        let (ms, vs) = (&mut self.m, &mut self.v);
        let mut k = 0;
        params.visit_params_mut("", &mut |_, p| {
            if ms.len() <= k {
                ms.push(vec![0.0; p.len()]);
                vs.push(vec![0.0; p.len()]);
            }
            let (m, v) = (&mut ms[k], &mut vs[k]);
            k += 1;
            if !p.trainable {
                return;
            }
            if p.grad.len() != p.value.len() {
                p.zero_grad();
            }
            let decay = match (c.weight_decay != 0.0, c.decoupled) {
                (false, _) => Decay::None,
                (true, true) => Decay::Decoupled,
                (true, false) => Decay::Coupled,
            };
            let coef = AdamCoefficients { config: c, lr, step_size, bc2_sqrt, decay };
            coef.update(&mut p.value, &p.grad, m, v);
        });
        Ok(())
    }

    /// The size checks of [`Adam::check`] that [`Adam::step`] needs (cheap: no value scan).
    fn check_sizes(&self, params: &dyn Parameters) -> Result<(), NnError> {
        let (mut k, mut err) = (0, None);
        params.visit_params("", &mut |name, p| {
            let sizes = (self.m.get(k).map(Vec::len), self.v.get(k).map(Vec::len));
            let ok = match sizes {
                (Some(m), Some(v)) => m == p.len() && v == p.len(),
                (None, None) => self.m.is_empty(),
                _ => false,
            };
            if !ok && err.is_none() {
                err = Some(format!(
                    "Adam stepped on a different model: `{name}` has {} values, its moments {:?}",
                    p.len(),
                    sizes.0
                ));
            }
            k += 1;
        });
        if err.is_none() && self.m.len() > k {
            err = Some(format!("Adam state of {} tensors, model of {k}", self.m.len()));
        }
        err.map_or(Ok(()), |e| Err(NnError::ModelMismatch(e)))
    }
}

/// How weight decay enters an Adam update.
#[derive(Clone, Copy, PartialEq)]
enum Decay {
    None,
    /// `g += λ θ` (Adam's L2 penalty).
    Coupled,
    /// `θ *= 1 − lr λ` before the update (AdamW).
    Decoupled,
}

/// The per-step constants of an Adam update.
#[derive(Clone, Copy)]
struct AdamCoefficients {
    config: AdamConfig,
    lr: f32,
    step_size: f32,
    bc2_sqrt: f32,
    decay: Decay,
}

impl AdamCoefficients {
    /// Updates `value` with `grad` and the moments `m`, `v` (all of one length), element by
    /// element: compiled for AVX2 where the CPU has it, with the same bits either way
    /// (nothing is fused or reordered; `sqrt` and `/` are correctly rounded in both).
    fn update(&self, value: &mut [f32], grad: &[f32], m: &mut [f32], v: &mut [f32]) {
        #[cfg(target_arch = "x86_64")]
        if std::arch::is_x86_feature_detected!("avx2") {
            // SAFETY: the CPU supports AVX2, checked just above.
            unsafe { self.update_avx2(value, grad, m, v) };
            return;
        }
        self.update_portable(value, grad, m, v)
    }

    /// [`AdamCoefficients::update_portable`] compiled for AVX2.
    ///
    /// # Safety
    /// The CPU must support AVX2.
    #[cfg(target_arch = "x86_64")]
    #[target_feature(enable = "avx2")]
    unsafe fn update_avx2(&self, value: &mut [f32], grad: &[f32], m: &mut [f32], v: &mut [f32]) {
        self.update_portable(value, grad, m, v)
    }

    #[inline(always)]
    fn update_portable(&self, value: &mut [f32], grad: &[f32], m: &mut [f32], v: &mut [f32]) {
        match self.decay {
            Decay::None => self.update_with::<0>(value, grad, m, v),
            Decay::Coupled => self.update_with::<1>(value, grad, m, v),
            Decay::Decoupled => self.update_with::<2>(value, grad, m, v),
        }
    }

    /// The update with the weight decay `DECAY` (0: none, 1: coupled, 2: decoupled) as a
    /// constant, so that the loop has no branch and vectorises.
    #[inline(always)]
    fn update_with<const DECAY: u8>(
        &self,
        value: &mut [f32],
        grad: &[f32],
        m: &mut [f32],
        v: &mut [f32],
    ) {
        let c = &self.config;
        let n = value.len();
        let (grad, m, v) = (&grad[..n], &mut m[..n], &mut v[..n]);
        let (step_size, bc2_sqrt) = (self.step_size, self.bc2_sqrt);
        let shrink = 1.0 - self.lr * c.weight_decay;
        for i in 0..n {
            let mut g = grad[i];
            if DECAY == 2 {
                value[i] *= shrink;
            } else if DECAY == 1 {
                g += c.weight_decay * value[i];
            }
            m[i] = c.beta1 * m[i] + (1.0 - c.beta1) * g;
            v[i] = c.beta2 * v[i] + (1.0 - c.beta2) * g * g;
            value[i] -= step_size * m[i] / (v[i].sqrt() / bc2_sqrt + c.eps);
        }
    }
}

/// Scales all gradients of `model` so their global L2 norm is at most `max_norm` (PyTorch's
/// `clip_grad_norm_`). Returns the norm before clipping; a non-finite norm leaves the
/// gradients untouched (the caller should treat it as divergence).
///
/// ```
/// use vdd_nn::{clip_grad_norm, Param, Parameters};
/// struct Two(Param);
/// impl Parameters for Two {
///     fn visit_params(&self, p: &str, f: &mut dyn FnMut(&str, &Param)) { f(p, &self.0) }
///     fn visit_params_mut(&mut self, p: &str, f: &mut dyn FnMut(&str, &mut Param)) { f(p, &mut self.0) }
/// }
/// let mut m = Two(Param::zeros(&[2]));
/// m.0.grad = vec![3.0, 4.0];
/// assert_eq!(clip_grad_norm(&mut m, 1.0), 5.0);
/// assert!((m.0.grad[0] - 0.6).abs() < 1e-6 && (m.0.grad[1] - 0.8).abs() < 1e-6);
/// ```
pub fn clip_grad_norm(model: &mut dyn Parameters, max_norm: f32) -> f32 {
    let mut sq = 0.0f64;
    model.visit_params("", &mut |_, p| {
        if !p.trainable {
            return;
        }
        sq += p.grad.iter().map(|&g| (g as f64) * (g as f64)).sum::<f64>();
    });
    let norm = sq.sqrt() as f32;
    if norm.is_finite() && norm > max_norm && norm > 0.0 {
        let s = max_norm / (norm + 1e-6);
        model.visit_params_mut("", &mut |_, p| {
            if p.trainable {
                p.grad.iter_mut().for_each(|g| *g *= s)
            }
        });
    }
    norm
}

/// The global gradient norm of a model was NaN or infinite (see [`clip_grad_norm_checked`]).
#[derive(Debug, Clone, Copy, PartialEq, Eq, thiserror::Error)]
#[error("the global gradient norm is not finite")]
pub struct NonFiniteGradient;

/// Checks that the global gradient norm of `model` (over every parameter, trainable or not) is
/// finite, then, when `max_norm` is given, clips it with [`clip_grad_norm`]. A non-finite norm is
/// an error and leaves the gradients untouched, so the caller can skip the update: the checked
/// clipping every trainer applies before an optimiser step.
///
/// ```
/// use vdd_nn::{clip_grad_norm_checked, Param, Parameters};
/// struct One(Param);
/// impl Parameters for One {
///     fn visit_params(&self, p: &str, f: &mut dyn FnMut(&str, &Param)) { f(p, &self.0) }
///     fn visit_params_mut(&mut self, p: &str, f: &mut dyn FnMut(&str, &mut Param)) { f(p, &mut self.0) }
/// }
/// let mut m = One(Param::zeros(&[2]));
/// m.0.grad = vec![3.0, 4.0];
/// clip_grad_norm_checked(&mut m, Some(1.0)).unwrap();
/// assert!((m.0.grad[0] - 0.6).abs() < 1e-6);
/// m.0.grad[1] = f32::NAN;
/// assert!(clip_grad_norm_checked(&mut m, None).is_err());
/// ```
pub fn clip_grad_norm_checked(
    model: &mut dyn Parameters,
    max_norm: Option<f32>,
) -> Result<(), NonFiniteGradient> {
    let mut sq = 0.0f64;
    model.visit_params("", &mut |_, p| {
        sq += p.grad.iter().map(|g| f64::from(*g) * f64::from(*g)).sum::<f64>();
    });
    if !sq.is_finite() {
        return Err(NonFiniteGradient);
    }
    if let Some(max) = max_norm {
        clip_grad_norm(model, max);
    }
    Ok(())
}

/// The bounds on moments ([`MAX_ABS_ADAM_FIRST_MOMENT`](crate::limits::MAX_ABS_ADAM_FIRST_MOMENT),
/// [`MAX_ADAM_SECOND_MOMENT`](crate::limits::MAX_ADAM_SECOND_MOMENT)); the error names the
/// parameter, the index and the value.
fn check_moments(name: &str, m: &[f32], v: &[f32]) -> Result<(), String> {
    let (max_m, max_v) =
        (crate::limits::MAX_ABS_ADAM_FIRST_MOMENT, crate::limits::MAX_ADAM_SECOND_MOMENT);
    if let Some(i) = m.iter().position(|x| x.abs() > max_m) {
        return Err(format!(
            "the first moment of `{name}` holds {:e} at index {i}, beyond the bound {max_m:e}",
            m[i]
        ));
    }
    if let Some(i) = v.iter().position(|x| *x > max_v) {
        return Err(format!(
            "the second moment of `{name}` holds {:e} at index {i}, beyond the bound {max_v:e}",
            v[i]
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use faer::Mat;

    use super::*;
    use crate::{Activation, LrSchedule, Mlp, MlpConfig, Module};

    /// The vectorised update is the element-by-element formula, bit for bit, with and without
    /// weight decay.
    #[test]
    fn the_update_kernel_is_the_scalar_formula() {
        let n = 37;
        let grad: Vec<f32> = (0..n).map(|i| ((i * 7) % 11) as f32 / 3.0 - 1.7).collect();
        let start: Vec<f32> = (0..n).map(|i| ((i * 5) % 13) as f32 / 6.0 - 1.0).collect();
        for (weight_decay, decoupled) in [(0.0, false), (0.1, false), (0.1, true)] {
            let config = AdamConfig { lr: 0.01, weight_decay, decoupled, ..Default::default() };
            let decay = match (weight_decay != 0.0, decoupled) {
                (false, _) => Decay::None,
                (true, true) => Decay::Decoupled,
                (true, false) => Decay::Coupled,
            };
            let coef = AdamCoefficients { config, lr: 0.01, step_size: 0.02, bc2_sqrt: 0.3, decay };
            let (mut value, mut m, mut v) = (start.clone(), vec![0.1f32; n], vec![0.2f32; n]);
            coef.update(&mut value, &grad, &mut m, &mut v);
            for i in 0..n {
                let (c, mut g, mut x) = (config, grad[i], start[i]);
                if weight_decay != 0.0 {
                    if decoupled {
                        x *= 1.0 - 0.01 * c.weight_decay;
                    } else {
                        g += c.weight_decay * x;
                    }
                }
                let mi = c.beta1 * 0.1 + (1.0 - c.beta1) * g;
                let vi = c.beta2 * 0.2 + (1.0 - c.beta2) * g * g;
                x -= 0.02 * mi / (vi.sqrt() / 0.3 + c.eps);
                assert_eq!((value[i], m[i], v[i]), (x, mi, vi), "{weight_decay} {decoupled} {i}");
            }
        }
    }

    /// Mean squared error of `net` on `(x, y)` and its gradient `2 (ŷ − y) / n` in `g`.
    fn mse(net: &mut Mlp, x: &Mat<f32>, y: &Mat<f32>, g: &mut Mat<f32>) -> f32 {
        let pred = net.forward(x.as_ref());
        let n = x.nrows();
        let mut loss = 0.0f64;
        for i in 0..n {
            let e = pred[(i, 0)] - y[(i, 0)];
            loss += f64::from(e * e);
            g[(i, 0)] = 2.0 * e / n as f32;
        }
        (loss / n as f64) as f32
    }

    #[test]
    fn adam_fits_sin_on_minus_pi_to_pi() {
        let seeds = vdd_core::Seeds::new(0);
        let cfg =
            MlpConfig { in_dim: 1, hidden: vec![32, 32], out_dim: 1, activation: Activation::Tanh };
        let mut net = Mlp::new(&cfg, &mut seeds.stream("init")).unwrap();
        let n = 256;
        let pi = std::f32::consts::PI;
        let x = Mat::from_fn(n, 1, |i, _| -pi + 2.0 * pi * i as f32 / (n - 1) as f32);
        let y = Mat::from_fn(n, 1, |i, _| x[(i, 0)].sin());
        let mut g = Mat::zeros(n, 1);
        let steps = 800;
        let schedule = LrSchedule::Cosine { final_factor: 0.05 };
        let mut opt = Adam::new(AdamConfig { lr: 1e-2, ..Default::default() });
        let initial = mse(&mut net, &x, &y, &mut g);
        for step in 0..steps {
            net.zero_grad();
            mse(&mut net, &x, &y, &mut g);
            net.backward(g.as_ref());
            opt.step(&mut net, schedule.factor(step, steps)).unwrap();
        }
        let last = mse(&mut net, &x, &y, &mut g);
        assert!(initial > 0.1, "{initial}");
        assert!(last < 1e-4, "final MSE {last}");
        // Held-out points between the training grid.
        let xt = Mat::from_fn(50, 1, |i, _| -3.0 + 6.0 * (i as f32 + 0.5) / 50.0);
        let pred = net.forward(xt.as_ref());
        let worst = (0..50).map(|i| (pred[(i, 0)] - xt[(i, 0)].sin()).abs()).fold(0.0, f32::max);
        assert!(worst < 0.05, "held-out max error {worst}");
    }

    #[test]
    fn buffers_are_not_updated_and_adamw_decays_weights() {
        let mut rng = vdd_core::Seeds::new(0).stream("i");
        let mut ff = crate::FourierFeatures::new(4, 1.0, &mut rng).unwrap();
        let before = ff.w.value.clone();
        let mut opt =
            Adam::new(AdamConfig { weight_decay: 0.5, decoupled: true, ..Default::default() });
        ff.w.grad = vec![1.0; 2];
        opt.step(&mut ff, 1.0).unwrap();
        assert_eq!(ff.w.value, before);
        assert_eq!(clip_grad_norm(&mut ff, 1e-3), 0.0);

        let mut layer = crate::Linear::new(2, 2, &mut rng);
        let w0 = layer.weight.value.clone();
        layer.zero_grad();
        let mut opt = Adam::new(AdamConfig {
            lr: 0.1,
            weight_decay: 0.5,
            decoupled: true,
            ..Default::default()
        });
        opt.step(&mut layer, 1.0).unwrap();
        // Zero gradient: only the decoupled decay acts, w ← (1 − lr·wd) w.
        for (a, b) in layer.weight.value.iter().zip(&w0) {
            assert!((a - 0.95 * b).abs() < 1e-7);
        }
    }

    #[test]
    fn a_mismatched_state_is_an_error_that_changes_nothing() {
        let mut rng = vdd_core::Seeds::new(0).stream("i");
        let mut small = crate::Linear::new(2, 2, &mut rng);
        let mut big = crate::Linear::new(3, 2, &mut rng);
        let mut fewer = crate::Linear::new(2, 2, &mut rng);
        let mut opt = Adam::new(AdamConfig::default());
        small.zero_grad();
        opt.step(&mut small, 1.0).unwrap();
        let (before, steps) = (big.weight.value.clone(), opt.steps());
        big.zero_grad();
        let e = opt.step(&mut big, 1.0).unwrap_err().to_string();
        assert!(e.contains("weight") && e.contains("different model"), "{e}");
        assert_eq!((big.weight.value.clone(), opt.steps()), (before, steps));
        assert!(opt.check(&big).is_err());
        // A state with fewer tensors than the model, or more, is refused too.
        let mut part = opt.clone();
        part.m.pop();
        part.v.pop();
        assert!(part.step(&mut fewer, 1.0).is_err() && part.check(&fewer).is_err());
        let mut more = opt.clone();
        more.m.push(vec![0.0]);
        more.v.push(vec![0.0]);
        assert!(more.step(&mut fewer, 1.0).is_err() && more.check(&fewer).is_err());
        // Non-finite moments and bad hyper-parameters fail the full check.
        let mut nan = opt.clone();
        nan.v[0][0] = f32::NAN;
        assert!(nan.check(&small).unwrap_err().to_string().contains("not finite"));
        let mut eps = opt.clone();
        eps.config.eps = -1.0;
        assert!(eps.check(&small).is_err());
        assert!(opt.check(&small).is_ok());
    }

    #[test]
    fn moments_beyond_their_bounds_are_refused_naming_the_value() {
        // Before, a checkpoint's Adam moments of 2^63 were accepted.
        let mut rng = vdd_core::Seeds::new(0).stream("init");
        let mut layer = crate::Linear::new(2, 1, &mut rng);
        let mut opt = Adam::new(AdamConfig::default());
        opt.step(&mut layer, 1.0).unwrap();
        opt.check(&layer).unwrap();
        let mut bad = opt.clone();
        bad.m[0][1] = 2f32.powi(63);
        let e = bad.check(&layer).unwrap_err().to_string();
        assert!(e.contains("first moment") && e.contains("weight") && e.contains("e18"), "{e}");
        let mut bad = opt.clone();
        bad.v[1][0] = 1e36;
        let e = bad.check(&layer).unwrap_err().to_string();
        assert!(e.contains("second moment") && e.contains("1e36"), "{e}");
        let mut edge = opt;
        edge.m[0][0] = crate::limits::MAX_ABS_ADAM_FIRST_MOMENT;
        edge.v[0][0] = crate::limits::MAX_ADAM_SECOND_MOMENT;
        edge.check(&layer).unwrap();
    }
}
