//! The expert step's gradients against finite differences, and expert subsets against the
//! full step.

use super::*;
use crate::test_support::{IsoGmm, output};
use approx::assert_relative_eq;
use vdd_moe::{DiagonalExpert, FullExpert};

/// Monte-Carlo `Ĵ_z` with fixed ε: mean of `log π(a) + log q̃(z|a)` plus the entropy.
fn objective<E: Expert>(
    expert: &E,
    raw_z: &[f32],
    eps: &[f32],
    teacher: &IsoGmm,
    snapshot: &MoeOutput,
    z: usize,
) -> f64 {
    let d = expert.action_dim();
    let (mut mu, mut l) = (vec![0.0; d], vec![0.0; d * d]);
    expert.decode(raw_z, &mut mu, &mut l);
    let v_n = eps.len() / d;
    let (mut a, mut resp, mut work) = (vec![0.0; d], vec![0.0; 2], vec![0.0; d]);
    let mut sum = 0.0f64;
    for v in 0..v_n {
        gaussian::sample_into(&mu, &l, &eps[v * d..(v + 1) * d], &mut a);
        snapshot.log_density_and_responsibilities(0, &a, &mut resp, &mut work);
        sum += f64::from(teacher.log_density(&a, 0.0)) + f64::from(resp[z].ln());
    }
    sum / v_n as f64 + f64::from(gaussian::entropy(&l, d))
}

fn check_expert_step_gradient<E: Expert>(expert: E, raws: Vec<Vec<f32>>) {
    let d = expert.action_dim();
    let mut teacher = IsoGmm { means: vec![vec![1.0; d], vec![-1.0; d]], std: 0.6, state_dim: 1 };
    let current = output(&expert, &raws, [(0.3f32).ln(), (0.7f32).ln()]);
    // The frozen snapshot q̃ differs from the live student, as after an expert update.
    let snap_raws: Vec<Vec<f32>> =
        raws.iter().map(|r| r.iter().map(|x| x * 0.8 + 0.05).collect()).collect();
    let snapshot = output(&expert, &snap_raws, [(0.4f32).ln(), (0.6f32).ln()]);
    let states = faer::Mat::<f32>::zeros(1, 1);
    let v_n = 21;
    let seeds = vdd_core::Seeds::new(5);
    let mut buf = ExpertStepBuffers::default();
    corrected_score_moments(
        &mut teacher,
        &current,
        &snapshot,
        states.as_ref(),
        &NoiseSchedule::Fixed { level: 0.0 },
        0.0,
        v_n,
        &mut seeds.stream("eps"),
        &mut buf,
    )
    .unwrap();
    for z in 0..2 {
        let r = expert.raw_dim();
        let mut grad = vec![0.0; r];
        expert.expert_step_grad(
            &raws[z],
            current.scale(0, z),
            &buf.mean_g[z * d..(z + 1) * d],
            &buf.mean_g_eps[z * d * d..(z + 1) * d * d],
            &mut grad,
        );
        let eps = &buf.eps[z * v_n * d..(z + 1) * v_n * d];
        for k in 0..r {
            let h = 1e-3f32;
            let mut p = raws[z].clone();
            p[k] += h;
            let mut m = raws[z].clone();
            m[k] -= h;
            let fd = (objective(&expert, &p, eps, &teacher, &snapshot, z)
                - objective(&expert, &m, eps, &teacher, &snapshot, z))
                / (2.0 * f64::from(h));
            assert_relative_eq!(f64::from(grad[k]), fd, epsilon = 2e-2, max_relative = 2e-2);
        }
    }
}

#[test]
fn diagonal_expert_step_gradient_matches_finite_differences() {
    let e = DiagonalExpert::new(2, 0.8, 1e-4).unwrap();
    check_expert_step_gradient(e, vec![vec![0.4, 0.9, -0.2, 0.3], vec![-0.7, -0.1, 0.1, -0.4]]);
}

#[test]
fn full_expert_step_gradient_matches_finite_differences() {
    let e = FullExpert::new(2, 0.8, 1e-4).unwrap();
    check_expert_step_gradient(
        e,
        vec![vec![0.4, 0.9, -0.2, 0.35, 0.3], vec![-0.7, -0.1, 0.1, -0.25, -0.4]],
    );
}

/// One state, four full-covariance experts and the same `ε` for each (state, expert) pair
/// whether it is computed alone or with the others: each 2-subset's chosen pairs have the
/// full step's moments, the others zero, and the mean of the six subsets' gradients is the
/// full step's (each pair is in half of them, weighted by 2).
#[test]
fn expert_subsets_average_to_the_full_step() {
    let (z_n, d, v_n) = (4, 2, 5);
    let e = FullExpert::new(d, 0.8, 1e-4).unwrap();
    let r = e.raw_dim();
    let raws: Vec<f32> = (0..z_n * r).map(|i| ((i * 7 % 11) as f32 - 5.0) * 0.13).collect();
    let output = |raws: &[f32], log_gating: Vec<f32>| {
        let mut out = MoeOutput {
            n: 1,
            num_experts: z_n,
            action_dim: d,
            raw: raws.to_vec(),
            means: vec![0.0; z_n * d],
            scales: vec![0.0; z_n * d * d],
            log_gating,
        };
        for z in 0..z_n {
            let (m, l) = (&mut out.means[z * d..(z + 1) * d], &mut out.scales[z * d * d..]);
            e.decode(&raws[z * r..(z + 1) * r], m, &mut l[..d * d]);
        }
        out
    };
    let current = output(&raws, vec![(0.25f32).ln(); z_n]);
    let snap: Vec<f32> = raws.iter().map(|x| x * 0.9 + 0.02).collect();
    let snapshot = output(&snap, [0.1f32, 0.2, 0.3, 0.4].iter().map(|p| p.ln()).collect());
    let weights = [0.1f32, 0.2, 0.3, 0.4];
    let mut teacher = IsoGmm { means: vec![vec![1.0; d], vec![-1.0; d]], std: 0.6, state_dim: 1 };
    let states = faer::Mat::<f32>::zeros(1, 1);
    let mut eps = vec![0.0f32; z_n * v_n * d];
    vdd_core::fill_standard_normal(&mut vdd_core::Seeds::new(3).stream("eps"), &mut eps);

    let mut full = ExpertStepBuffers { eps: eps.clone(), ..Default::default() };
    full.noise_levels = vec![0.0; z_n * v_n];
    let st = states.as_ref();
    moments_from_noise(&mut teacher, &current, &snapshot, st, v_n, None, None, &mut full).unwrap();
    raw_gradients(&e, &current, &weights, None, &mut full);

    let mut mean = vec![0.0f32; z_n * r];
    let mut subsets = 0;
    for a in 0..z_n {
        for b in a + 1..z_n {
            let experts = [a as u32, b as u32];
            let subset = ExpertSubset { experts: &experts, per_state: 2 };
            let rows = |z: usize| &eps[z * v_n * d..(z + 1) * v_n * d];
            let mut buf =
                ExpertStepBuffers { eps: [rows(a), rows(b)].concat(), ..Default::default() };
            buf.noise_levels = vec![0.0; 2 * v_n];
            moments_from_noise(
                &mut teacher,
                &current,
                &snapshot,
                st,
                v_n,
                None,
                Some(subset),
                &mut buf,
            )
            .unwrap();
            for z in 0..z_n {
                let (g, g_full) =
                    (&buf.mean_g[z * d..(z + 1) * d], &full.mean_g[z * d..(z + 1) * d]);
                for (x, y) in g.iter().zip(g_full) {
                    let expected = if experts.contains(&(z as u32)) { *y } else { 0.0 };
                    assert_relative_eq!(*x, expected, epsilon = 1e-5, max_relative = 1e-5);
                }
            }
            raw_gradients(&e, &current, &weights, Some(subset), &mut buf);
            mean.iter_mut().zip(&buf.grad_raw).for_each(|(m, g)| *m += g);
            subsets += 1;
        }
    }
    for (m, g) in mean.iter().zip(&full.grad_raw) {
        assert_relative_eq!(*m / subsets as f32, *g, epsilon = 1e-5, max_relative = 1e-4);
    }
    // An expert index out of range is an error, not a panic.
    let bad = ExpertSubset { experts: &[0, 4], per_state: 2 };
    let mut buf = ExpertStepBuffers { eps: eps[..2 * v_n * d].to_vec(), ..Default::default() };
    buf.noise_levels = vec![0.0; 2 * v_n];
    assert!(
        moments_from_noise(&mut teacher, &current, &snapshot, st, v_n, None, Some(bad), &mut buf)
            .is_err()
    );
}
