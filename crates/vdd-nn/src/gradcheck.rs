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

/// Derivative at `x0` of `f` by central differences with steps `h` and `h/2` combined by
/// Richardson extrapolation, `(4·D(h/2) − D(h)) / 3`, which cancels the `O(h²)` truncation
/// error (what limits `f32` checks of curved networks, e.g. with layer norm). Each difference
/// divides by the step actually taken in `f32`.
fn richardson(x0: f32, h: f32, mut f: impl FnMut(f32) -> f64) -> f64 {
    let mut central = |step: f32| {
        let (xp, xm) = (x0 + step, x0 - step);
        let (fp, fm) = (f(xp), f(xm));
        (fp - fm) / (f64::from(xp) - f64::from(xm))
    };
    let d1 = central(h);
    let d2 = central(0.5 * h);
    (4.0 * d2 - d1) / 3.0
}

fn rel_err(analytic: f32, numeric: f64, scale: f64) -> f32 {
    ((f64::from(analytic) - numeric).abs() / (numeric.abs().max(scale))) as f32
}

/// Compares `backward` with central finite differences of the scalar `Σ r ⊙ forward(x)` for a
/// random `r`, perturbing every input entry and every trainable parameter entry by `h` and
/// `h/2` (Richardson extrapolation of the two central differences).
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
    module.visit_params("", &mut |_, p| {
        // Buffers are not differentiated: nothing to compare.
        analytic_params.push(if p.trainable { p.grad.clone() } else { Vec::new() })
    });

    let mut input_error = 0.0f32;
    let mut xp = x.to_owned();
    for j in 0..x.ncols() {
        for i in 0..n {
            let orig = xp[(i, j)];
            let numeric = richardson(orig, h, |v| {
                xp[(i, j)] = v;
                loss(module, xp.as_ref(), &r)
            });
            xp[(i, j)] = orig;
            input_error = input_error.max(rel_err(dx[(i, j)], numeric, scale));
        }
    }

    let mut param_error = 0.0f32;
    for (pi, analytic) in analytic_params.iter().enumerate() {
        for (e, &a) in analytic.iter().enumerate() {
            let orig = get_param(module, pi, e);
            let numeric = richardson(orig, h, |v| {
                set_param(module, pi, e, v);
                loss(module, x, &r)
            });
            set_param(module, pi, e, orig);
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
