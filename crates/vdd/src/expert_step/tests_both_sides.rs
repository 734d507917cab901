//! Noise on both sides ([`crate::both_sides`]): the folded gradients against finite differences
//! (here, beside the kernel they run through, so that `both_sides` does not depend on this module).

use approx::assert_relative_eq;
use faer::Mat;
use vdd_core::{Affine, Expert, ScoreModel, gaussian};
use vdd_moe::{DiagonalExpert, FullExpert, MoeOutput};

use crate::both_sides::*;
use crate::expert_step::{ExpertStepBuffers, moments_from_noise};
use crate::spaces::ActionMap;
use crate::spaces::with_map;
use crate::test_support::{IsoGmm, VpGmm, output};

/// The teacher of a gradient check: VE or VP, with its exact noised log-density.
enum Teacher {
    Ve(IsoGmm),
    Vp(VpGmm),
}

impl Teacher {
    fn model(&mut self) -> &mut dyn ScoreModel {
        match self {
            Teacher::Ve(t) => t,
            Teacher::Vp(t) => t,
        }
    }
    fn log_density(&self, x: &[f32], level: f32) -> f32 {
        match self {
            Teacher::Ve(t) => t.log_density(x, level),
            Teacher::Vp(t) => t.log_density(x, level),
        }
    }
}

/// `log q̃_t(z|x)` under the snapshot noised by `(k, β, γ)`.
fn noised_log_resp(
    snapshot: &MoeOutput,
    k: f32,
    shift: &[f32],
    std: &[f32],
    x: &[f32],
    z: usize,
) -> f64 {
    let (d, z_n) = (x.len(), snapshot.num_experts);
    let (mut chol, mut work, mut mean) = (vec![0.0; d * d], vec![0.0; d], vec![0.0; d]);
    let lps: Vec<f32> = (0..z_n)
        .map(|j| {
            assert!(noised_cholesky(snapshot.scale(0, j), k, std, d, &mut chol));
            for (i, m) in snapshot.mean(0, j).iter().enumerate() {
                mean[i] = k * m + shift[i];
            }
            snapshot.log_gating_row(0)[j] + gaussian::log_density(x, &mean, &chol, &mut work)
        })
        .collect();
    f64::from(lps[z] - gaussian::log_sum_exp(&lps))
}

/// Monte-Carlo `Ĵ_z^t` with fixed `ε`, `η`: the mean of `log π_t(x) + log q̃_t(z|x)` over the
/// samples (the teacher's density in its own coordinates `o + s x`, which differs by a
/// constant), plus the noised expert's entropy.
#[allow(clippy::too_many_arguments)]
fn objective<E: Expert>(
    expert: &E,
    raw_z: &[f32],
    (eps, eta): (&[f32], &[f32]),
    teacher: &Teacher,
    snapshot: &MoeOutput,
    (level, k, shift, std): (f32, f32, &[f32], &[f32]),
    map: Option<&ActionMap>,
    z: usize,
) -> f64 {
    let d = expert.action_dim();
    let (mut mu, mut l, mut a) = (vec![0.0; d], vec![0.0; d * d], vec![0.0; d]);
    expert.decode(raw_z, &mut mu, &mut l);
    let v_n = eps.len() / d;
    let mut sum = 0.0f64;
    for v in 0..v_n {
        gaussian::sample_into(&mu, &l, &eps[v * d..(v + 1) * d], &mut a);
        let x: Vec<f32> = (0..d).map(|j| k * a[j] + shift[j] + std[j] * eta[v * d + j]).collect();
        let xt: Vec<f32> = (0..d)
            .map(|j| map.map_or(x[j], |m| x[j] * m.coefficients(j).0 + m.coefficients(j).1))
            .collect();
        sum += f64::from(teacher.log_density(&xt, level));
        sum += noised_log_resp(snapshot, k, shift, std, &x, z);
    }
    let mut chol = vec![0.0; d * d];
    assert!(noised_cholesky(&l, k, std, d, &mut chol));
    sum / v_n as f64 + f64::from(gaussian::half_log_det(&chol, d))
}

fn check_gradient<E: Expert>(
    expert: E,
    raws: Vec<Vec<f32>>,
    mut teacher: Teacher,
    level: f32,
    map: Option<ActionMap>,
) {
    let d = expert.action_dim();
    let current = output(&expert, &raws, [(0.3f32).ln(), (0.7f32).ln()]);
    let snap_raws: Vec<Vec<f32>> =
        raws.iter().map(|r| r.iter().map(|x| x * 0.8 + 0.05).collect()).collect();
    let snapshot = output(&expert, &snap_raws, [(0.4f32).ln(), (0.6f32).ln()]);
    let states = Mat::<f32>::zeros(1, 1);
    let (v_n, z_n) = (21, 2);
    let mut rng = vdd_core::Seeds::new(5).stream("eps");
    let mut buf = ExpertStepBuffers::default();
    buf.eps.resize(z_n * v_n * d, 0.0);
    vdd_core::fill_standard_normal(&mut rng, &mut buf.eps);
    buf.noise_levels = vec![level; z_n * v_n];
    let mut both = BothSides::default();
    let mut levels = buf.noise_levels.clone();
    both.prepare(teacher.model(), map.as_ref(), &mut levels, z_n * v_n, d, &mut rng).unwrap();
    let view = both.view(0..1, z_n * v_n, d);
    let mut scratch = Vec::new();
    with_map(teacher.model(), map.as_ref(), &mut scratch, |t| {
        moments_from_noise(t, &current, &snapshot, states.as_ref(), v_n, Some(view), None, &mut buf)
    })
    .unwrap();
    let noising = (level, both.scale[0], &both.shift[..], &both.std[..]);
    for z in 0..z_n {
        let r = expert.raw_dim();
        let mut grad = vec![0.0; r];
        expert.expert_step_grad(
            &raws[z],
            current.scale(0, z),
            &buf.mean_g[z * d..(z + 1) * d],
            &buf.mean_g_eps[z * d * d..(z + 1) * d * d],
            &mut grad,
        );
        let samples = z * v_n * d..(z + 1) * v_n * d;
        let noise = (&buf.eps[samples.clone()], &both.eta[samples]);
        for i in 0..r {
            let h = 1e-3f32;
            let (mut p, mut m) = (raws[z].clone(), raws[z].clone());
            p[i] += h;
            m[i] -= h;
            let f = |raw: &[f32]| {
                objective(&expert, raw, noise, &teacher, &snapshot, noising, map.as_ref(), z)
            };
            let fd = (f(&p) - f(&m)) / (2.0 * f64::from(h));
            assert_relative_eq!(f64::from(grad[i]), fd, epsilon = 2e-2, max_relative = 2e-2);
        }
    }
}

fn ve() -> Teacher {
    Teacher::Ve(IsoGmm { means: vec![vec![1.0, 1.0], vec![-1.0, -1.0]], std: 0.6, state_dim: 1 })
}

fn vp() -> Teacher {
    Teacher::Vp(VpGmm(IsoGmm {
        means: vec![vec![1.0, 1.0], vec![-1.0, -1.0]],
        std: 0.6,
        state_dim: 1,
    }))
}

/// A student whose actions are the teacher's halved and shifted.
fn map() -> Option<ActionMap> {
    let student = Affine { offset: vec![0.3, -0.2], scale: vec![0.5, 2.0] };
    ActionMap::between(Some(&student), None, 2).unwrap()
}

const DIAGONAL: [[f32; 4]; 2] = [[0.4, 0.9, -0.2, 0.3], [-0.7, -0.1, 0.1, -0.4]];
const FULL: [[f32; 5]; 2] = [[0.4, 0.9, -0.2, 0.35, 0.3], [-0.7, -0.1, 0.1, -0.25, -0.4]];

fn rows<const N: usize>(r: [[f32; N]; 2]) -> Vec<Vec<f32>> {
    r.iter().map(|x| x.to_vec()).collect()
}

#[test]
fn ve_gradient_matches_finite_differences() {
    let diagonal = DiagonalExpert::new(2, 0.8, 1e-4).unwrap();
    check_gradient(diagonal, rows(DIAGONAL), ve(), 0.5, None);
    let full = FullExpert::new(2, 0.8, 1e-4).unwrap();
    check_gradient(full, rows(FULL), ve(), 0.5, None);
}

#[test]
fn vp_gradient_matches_finite_differences() {
    let diagonal = DiagonalExpert::new(2, 0.8, 1e-4).unwrap();
    check_gradient(diagonal, rows(DIAGONAL), vp(), 0.7, None);
    let full = FullExpert::new(2, 0.8, 1e-4).unwrap();
    check_gradient(full, rows(FULL), vp(), 0.7, None);
}

#[test]
fn gradient_through_an_action_map_matches_finite_differences() {
    let full = FullExpert::new(2, 0.8, 1e-4).unwrap();
    check_gradient(full, rows(FULL), vp(), 0.7, map());
    check_gradient(full, rows(FULL), ve(), 0.5, map());
}

#[test]
fn at_level_zero_the_folded_moments_are_the_papers() {
    // k = 1, γ = 0: tril(C⁻¹ L) = diag(1/L_ii), so the fold changes nothing.
    let l = [0.5f32, 0.0, 0.2, 0.8];
    let (mut g, mut ge) = (vec![0.3f32, -0.1], vec![0.1f32, 0.0, 0.2, -0.3]);
    let (g0, ge0) = (g.clone(), ge.clone());
    let (mut chol, mut col) = (vec![0.0; 4], vec![0.0; 2]);
    fold_into_moments(&l, 1.0, &[0.0, 0.0], 2, &mut g, &mut ge, &mut chol, &mut col).unwrap();
    assert_eq!(g, g0);
    for i in [0, 2, 3] {
        assert!((ge[i] - ge0[i]).abs() < 1e-5, "{ge:?} {ge0:?}");
    }
}

#[test]
fn a_time_teacher_without_a_denoiser_form_is_refused() {
    struct NoForm(VpGmm);
    impl ScoreModel for NoForm {
        fn action_dim(&self) -> usize {
            2
        }
        fn state_dim(&self) -> usize {
            1
        }
        fn noise_convention(&self) -> vdd_core::NoiseConvention {
            vdd_core::NoiseConvention::Time
        }
        fn score(
            &mut self,
            a: faer::MatRef<'_, f32>,
            s: faer::MatRef<'_, f32>,
            t: &[f32],
            out: faer::MatMut<'_, f32>,
        ) -> Result<(), vdd_core::CoreError> {
            self.0.score(a, s, t, out)
        }
    }
    let Teacher::Vp(inner) = vp() else { unreachable!() };
    let mut levels = vec![3.0; 4];
    let mut rng = vdd_core::Seeds::new(0).stream("t");
    let err = BothSides::default()
        .prepare(&NoForm(inner), None, &mut levels, 2, 2, &mut rng)
        .unwrap_err();
    assert!(err.to_string().contains("denoiser form"), "{err}");
}
