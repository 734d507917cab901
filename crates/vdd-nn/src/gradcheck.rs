//! Finite-difference gradient checks for any [`Module`]: the tool every layer's test uses, and
//! that users writing their own layers can use too.

use faer::{Mat, MatRef};
use rand::Rng as _;

use crate::module::Module;

/// Result of a gradient check: the worst relative error over inputs and parameters.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct GradCheck {
    /// Max relative error of the input gradient.
    pub input_error: f32,
    /// Max relative error of the parameter gradients.
    pub param_error: f32,
}

fn loss(module: &mut dyn Module, x: MatRef<'_, f32>, r: &Mat<f32>) -> f64 {
    let y = module.forward(x);
    let mut s = 0.0f64;
    for j in 0..y.ncols() {
        for i in 0..y.nrows() {
            s += f64::from(y[(i, j)]) * f64::from(r[(i, j)]);
        }
    }
    s
}

fn rel_err(analytic: f32, numeric: f64, scale: f64) -> f32 {
    ((f64::from(analytic) - numeric).abs() / (numeric.abs().max(scale))) as f32
}

/// Compares `backward` with central finite differences of the scalar `Σ r ⊙ forward(x)` for a
/// random `r`, perturbing every input entry and every parameter entry by `h`.
///
/// Relative errors are measured against `max(|numeric|, scale)` so that gradients near zero do
/// not blow the ratio up; `scale` around `1e-2` suits `f32` networks of unit-scale inputs.
///
/// ```
/// use vdd_nn::{gradcheck::check_module, Linear};
/// let mut rng = vdd_core::Seeds::new(0).stream("t");
/// let mut layer = Linear::new(3, 2, &mut rng);
/// let x = faer::Mat::from_fn(4, 3, |i, j| (i as f32 - j as f32) * 0.3);
/// let r = check_module(&mut layer, x.as_ref(), 1e-2, 1e-2, &mut rng);
/// assert!(r.input_error < 1e-2 && r.param_error < 1e-2);
/// ```
pub fn check_module(
    module: &mut dyn Module,
    x: MatRef<'_, f32>,
    h: f32,
    scale: f64,
    rng: &mut vdd_core::Rng,
) -> GradCheck {
    let (n, d_out) = (x.nrows(), module.out_dim());
    let r = Mat::from_fn(n, d_out, |_, _| rng.random_range(-1.0f32..1.0));
    module.zero_grad();
    module.forward(x);
    let dx = module.backward(r.as_ref()).to_owned();
    let mut analytic_params = Vec::new();
    module.visit_params("", &mut |_, p| analytic_params.push(p.grad.clone()));

    let mut input_error = 0.0f32;
    let mut xp = x.to_owned();
    for j in 0..x.ncols() {
        for i in 0..n {
            let orig = xp[(i, j)];
            xp[(i, j)] = orig + h;
            let lp = loss(module, xp.as_ref(), &r);
            xp[(i, j)] = orig - h;
            let lm = loss(module, xp.as_ref(), &r);
            xp[(i, j)] = orig;
            let numeric = (lp - lm) / (2.0 * f64::from(h));
            input_error = input_error.max(rel_err(dx[(i, j)], numeric, scale));
        }
    }

    let mut param_error = 0.0f32;
    for (pi, analytic) in analytic_params.iter().enumerate() {
        for (e, &a) in analytic.iter().enumerate() {
            let orig = get_param(module, pi, e);
            set_param(module, pi, e, orig + h);
            let lp = loss(module, x, &r);
            set_param(module, pi, e, orig - h);
            let lm = loss(module, x, &r);
            set_param(module, pi, e, orig);
            let numeric = (lp - lm) / (2.0 * f64::from(h));
            param_error = param_error.max(rel_err(a, numeric, scale));
        }
    }
    GradCheck { input_error, param_error }
}

fn get_param(module: &mut dyn Module, index: usize, entry: usize) -> f32 {
    let mut k = 0;
    let mut out = 0.0;
    module.visit_params("", &mut |_, p| {
        if k == index {
            out = p.value[entry];
        }
        k += 1;
    });
    out
}

fn set_param(module: &mut dyn Module, index: usize, entry: usize, value: f32) {
    let mut k = 0;
    module.visit_params_mut("", &mut |_, p| {
        if k == index {
            p.value[entry] = value;
        }
        k += 1;
    });
}
