//! The students' network and preconditioning, reused from `vdd-diffusion`: the network is the
//! teachers' [`DenoiserNet`] conditioned on one noise level (a consistency model) or two (a
//! trajectory model's jump), evaluated with per-row coefficients
//! ([`DenoiserNet::forward_preconditioned`]); [`BoundaryPreconditioning`] is EDM's
//! [`Preconditioning`] with the consistency models' boundary condition at `σ_min`.

use std::collections::HashMap;

use faer::Mat;
use rand::RngCore;
use serde::{Deserialize, Serialize};
use vdd_core::{CoreError, Seeds};
use vdd_diffusion::{DenoiserNet, Preconditioning};
use vdd_nn::{Param, Parameters};

use crate::error::ConsistencyError;

/// The consistency-model preconditioning of Song et al. (2023): EDM's ([`Preconditioning`])
/// with the boundary condition at `σ_min`,
///
/// * `c_skip(σ) = σ_d² / ((σ − σ_min)² + σ_d²)` (EDM's `c_skip` at `σ − σ_min`),
/// * `c_out(σ) = (σ − σ_min) σ_d / sqrt(σ² + σ_d²)` (EDM's `c_out` with the numerator shifted),
/// * `c_in(σ) = 1 / sqrt(σ² + σ_d²)`, `c_noise(σ) = ln(σ) / 4` (EDM's),
///
/// so `c_skip(σ_min) = 1` and `c_out(σ_min) = 0` exactly: `f(x, σ_min) = x`.
///
/// ```
/// use vdd_consistency::BoundaryPreconditioning;
/// let p = BoundaryPreconditioning::new(0.5, 0.002).unwrap();
/// assert_eq!((p.c_skip(0.002), p.c_out(0.002)), (1.0, 0.0));
/// assert_eq!(p.c_in(3.0), p.edm().c_in(3.0));
/// ```
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
pub struct BoundaryPreconditioning {
    /// The data standard deviation `σ_d` (normalised space).
    pub sigma_data: f32,
    /// The boundary level `σ_min` where the consistency function is the identity.
    pub sigma_min: f32,
}

impl BoundaryPreconditioning {
    /// The preconditioning for `sigma_data > 0` and `sigma_min > 0`.
    pub fn new(sigma_data: f32, sigma_min: f32) -> Result<Self, CoreError> {
        if !(sigma_data.is_finite() && sigma_data > 0.0 && sigma_min.is_finite() && sigma_min > 0.0)
        {
            return Err(CoreError::Config(format!(
                "need sigma_data > 0 and sigma_min > 0, got {sigma_data}, {sigma_min}"
            )));
        }
        Ok(Self { sigma_data, sigma_min })
    }

    /// EDM's preconditioning with the same `σ_d`.
    #[inline]
    pub fn edm(&self) -> Preconditioning {
        Preconditioning { sigma_data: self.sigma_data }
    }

    /// `σ_d² / ((σ − σ_min)² + σ_d²)`.
    #[inline]
    pub fn c_skip(&self, sigma: f32) -> f32 {
        self.edm().c_skip(sigma - self.sigma_min)
    }

    /// `(σ − σ_min) σ_d / sqrt(σ² + σ_d²)`.
    #[inline]
    pub fn c_out(&self, sigma: f32) -> f32 {
        (sigma - self.sigma_min) * self.sigma_data / self.edm().noisy_std(sigma)
    }

    /// `1 / sqrt(σ² + σ_d²)`.
    #[inline]
    pub fn c_in(&self, sigma: f32) -> f32 {
        self.edm().c_in(sigma)
    }

    /// `ln(σ) / 4`.
    #[inline]
    pub fn c_noise(&self, sigma: f32) -> f32 {
        self.edm().c_noise(sigma)
    }
}

/// A student network with the architecture and weights of the teacher's network `teacher`,
/// conditioned on `levels` noise levels: `levels = 1` is an exact copy; with more levels the
/// input columns of the added embeddings start at zero, so the network initially ignores them
/// and reproduces the teacher (a trajectory model's `g(x, t, u)` starts as the teacher's
/// `F(x, t)` for every `u`).
///
/// ```
/// use vdd_consistency::network_from_teacher;
/// use vdd_diffusion::{DenoiserNet, NetConfig};
/// let cfg = NetConfig { hidden_dim: 8, num_blocks: 1, ..Default::default() };
/// let mut teacher = DenoiserNet::new(&cfg, 2, 1, &mut vdd_core::Seeds::new(0).stream("init")).unwrap();
/// let mut student = network_from_teacher(&teacher, 2).unwrap();
/// let (x, s) = (faer::Mat::<f32>::ones(1, 2), faer::Mat::<f32>::zeros(1, 1));
/// let want = teacher.forward(x.as_ref(), s.as_ref(), &[0.3]).to_owned();
/// let got = student.forward_conditioned(x.as_ref(), s.as_ref(), &[[0.3f32], [-1.0]]).to_owned();
/// // Equal up to the rounding of the wider input layer's sums.
/// assert!((0..2).all(|j| (got[(0, j)] - want[(0, j)]).abs() < 1e-6));
/// ```
pub fn network_from_teacher(
    teacher: &DenoiserNet,
    levels: usize,
) -> Result<DenoiserNet, ConsistencyError> {
    let mut net = DenoiserNet::with_levels(
        teacher.config(),
        teacher.action_dim(),
        teacher.state_dim(),
        levels,
        &mut Seeds::new(0).stream("init"),
    )?;
    let mut src: HashMap<String, (Vec<usize>, Vec<f32>)> = HashMap::new();
    teacher.visit_params("", &mut |name, p| {
        src.insert(name.to_owned(), (p.shape.clone(), p.value.clone()));
    });
    let input_name = "net.layers.0.weight";
    let mut missing = None;
    net.visit_params_mut("", &mut |name, p: &mut Param| {
        let Some((shape, value)) = src.get(name) else {
            missing = Some(name.to_owned());
            return;
        };
        if *shape == p.shape {
            p.value.copy_from_slice(value);
        } else if name == input_name && shape.len() == 2 && shape[0] == p.shape[0] {
            // [hidden, in_teacher] into [hidden, in_teacher + k·embed_dim]: leading columns.
            let (rows, cin, cout) = (shape[0], shape[1], p.shape[1]);
            for r in 0..rows {
                let dst = &mut p.value[r * cout..(r + 1) * cout];
                dst[..cin].copy_from_slice(&value[r * cin..(r + 1) * cin]);
                dst[cin..].fill(0.0);
            }
        } else {
            missing = Some(name.to_owned());
        }
    });
    if let Some(name) = missing {
        return Err(CoreError::Config(format!(
            "cannot initialise the student from the teacher: parameter `{name}` differs"
        ))
        .into());
    }
    Ok(net)
}

/// Resizes `m` to `r x c` when its shape differs.
pub(crate) fn ensure(m: &mut Mat<f32>, r: usize, c: usize) {
    if m.nrows() != r || m.ncols() != c {
        *m = Mat::zeros(r, c);
    }
}

/// Fills `m` with standard normal draws.
pub(crate) fn fill_normal(m: &mut Mat<f32>, rng: &mut dyn RngCore) {
    for j in 0..m.ncols() {
        vdd_core::fill_standard_normal(rng, m.col_as_slice_mut(j));
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use vdd_diffusion::NetConfig;
    use vdd_nn::Module as _;

    #[test]
    fn student_from_teacher_reproduces_the_teacher_network() {
        let cfg = NetConfig { hidden_dim: 8, num_blocks: 1, embed_dim: 4, ..Default::default() };
        let mut teacher = DenoiserNet::new(&cfg, 2, 1, &mut Seeds::new(3).stream("init")).unwrap();
        let x = Mat::from_fn(3, 2, |i, j| 0.3 * i as f32 - 0.2 * j as f32);
        let s = Mat::from_fn(3, 1, |i, _| i as f32);
        let c = [0.1f32, -0.4, 0.9];
        let want = teacher.forward(x.as_ref(), s.as_ref(), &c).to_owned();
        let mut one = network_from_teacher(&teacher, 1).unwrap();
        assert_eq!(one.forward(x.as_ref(), s.as_ref(), &c).to_owned(), want);
        let mut two = network_from_teacher(&teacher, 2).unwrap();
        let to = [2.0f32, -1.0, 0.0];
        let got = two.forward_conditioned(x.as_ref(), s.as_ref(), &[&c[..], &to[..]]).to_owned();
        assert_eq!(got, want);
        assert_eq!(two.mlp().in_dim(), 3 + 2 * 4);
        // A fresh network differs.
        let mut fresh =
            DenoiserNet::with_levels(&cfg, 2, 1, 1, &mut Seeds::new(4).stream("init")).unwrap();
        assert_ne!(fresh.forward(x.as_ref(), s.as_ref(), &c).to_owned(), want);
    }

    #[test]
    fn boundary_preconditioning_is_the_identity_at_sigma_min() {
        let p = BoundaryPreconditioning::new(0.5, 0.002).unwrap();
        assert_eq!(p.c_skip(0.002), 1.0);
        assert_eq!(p.c_out(0.002), 0.0);
        // Far from σ_min it approaches EDM's coefficients.
        let edm = Preconditioning::new(0.5).unwrap();
        assert!((p.c_skip(10.0) - edm.c_skip(10.0)).abs() < 1e-4);
        assert!((p.c_out(10.0) - edm.c_out(10.0)).abs() < 1e-3);
        assert!(BoundaryPreconditioning::new(0.0, 0.002).is_err());
        assert!(BoundaryPreconditioning::new(0.5, -1.0).is_err());
    }

    /// The coefficients are the formulas written out (the reuse of EDM's is exact).
    #[test]
    fn boundary_coefficients_are_the_closed_forms_bit_for_bit() {
        let p = BoundaryPreconditioning::new(0.5, 0.002).unwrap();
        let (sd, smin) = (p.sigma_data, p.sigma_min);
        for sigma in [0.002f32, 0.01, 0.37, 1.0, 7.5, 80.0] {
            let sd2 = sd * sd;
            let d = sigma - smin;
            assert_eq!(p.c_skip(sigma), sd2 / (d * d + sd2));
            assert_eq!(p.c_out(sigma), (sigma - smin) * sd / (sigma * sigma + sd * sd).sqrt());
            assert_eq!(p.c_in(sigma), 1.0 / (sigma * sigma + sd * sd).sqrt());
            assert_eq!(p.c_noise(sigma), 0.25 * sigma.ln());
        }
    }
}
