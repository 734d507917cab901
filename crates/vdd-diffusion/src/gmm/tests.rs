//! Tests of the exact Gaussian mixture: scores against finite differences, blocked against
//! row-by-row evaluation, sampling and errors.

use super::*;
use vdd_core::Seeds;

fn random_gmm(d: usize, k: usize, seed: u64) -> Gmm {
    let mut rng = Seeds::new(seed).stream("gmm");
    let weights: Vec<f32> = (0..k).map(|_| rng.random_range(0.2..1.0)).collect();
    let means: Vec<Vec<f32>> =
        (0..k).map(|_| (0..d).map(|_| rng.random_range(-2.0..2.0)).collect()).collect();
    let covs: Vec<Vec<f32>> = (0..k)
        .map(|_| {
            // A Aᵀ + 0.2 I, symmetric by construction.
            let a: Vec<f32> = (0..d * d).map(|_| rng.random_range(-0.7..0.7)).collect();
            let mut c = vec![0.0f32; d * d];
            for r in 0..d {
                for s in 0..=r {
                    let v: f32 = (0..d).map(|t| a[r * d + t] * a[s * d + t]).sum::<f32>()
                        + if r == s { 0.2 } else { 0.0 };
                    c[r * d + s] = v;
                    c[s * d + r] = v;
                }
            }
            c
        })
        .collect();
    Gmm::new(&weights, &means, &covs).unwrap()
}

/// The blocked isotropic score (fixed mixtures) equals the row-by-row one (used for
/// conditional mixtures), across block boundaries and changes of the noise level.
#[test]
fn blocked_isotropic_score_equals_the_row_by_row_score() {
    let (d, k, n) = (3, 5, 150);
    let mut rng = Seeds::new(3).stream("iso");
    let means: Vec<Vec<f32>> =
        (0..k).map(|_| (0..d).map(|_| rng.random_range(-2.0..2.0)).collect()).collect();
    let weights: Vec<f32> = (0..k).map(|_| rng.random_range(0.2..1.0)).collect();
    let gmm = Gmm::isotropic(&weights, &means, 0.4).unwrap();
    let mut blocked = GmmTeacher::fixed(gmm.clone(), 1);
    let mut rowwise = GmmTeacher::conditional(1, d, move |_| Ok(gmm.clone()));
    let a = Mat::from_fn(n, d, |_, _| rng.random_range(-3.0f32..3.0));
    let s = Mat::<f32>::zeros(n, 1);
    // Runs of equal noise levels longer and shorter than a block, and single rows.
    let sigma: Vec<f32> = (0..n).map(|i| [0.0, 0.3, 1.5][(i / 70 + i % 3 / 2) % 3]).collect();
    let (mut x, mut y) = (Mat::zeros(n, d), Mat::zeros(n, d));
    blocked.score(a.as_ref(), s.as_ref(), &sigma, x.as_mut()).unwrap();
    rowwise.score(a.as_ref(), s.as_ref(), &sigma, y.as_mut()).unwrap();
    for i in 0..n {
        for j in 0..d {
            assert!((x[(i, j)] - y[(i, j)]).abs() <= 1e-4 * (1.0 + y[(i, j)].abs()), "row {i}");
        }
    }
}

/// The exact score equals the finite-difference gradient of the smoothed log-density.
#[test]
fn score_matches_finite_differences_of_the_log_density_up_to_8_dims() {
    for (d, k) in [(1, 3), (2, 8), (3, 2), (5, 4), (8, 3)] {
        let gmm = random_gmm(d, k, d as u64);
        let mut teacher = GmmTeacher::fixed(gmm.clone(), 2);
        let mut rng = Seeds::new(7).stream("points");
        for sigma in [0.0f32, 0.1, 1.0] {
            let a = Mat::from_fn(4, d, |_, _| rng.random_range(-2.0f32..2.0));
            let s = Mat::<f32>::zeros(4, 2);
            let mut score = Mat::zeros(4, d);
            teacher.score(a.as_ref(), s.as_ref(), &[sigma; 4], score.as_mut()).unwrap();
            for i in 0..4 {
                let x: Vec<f64> = (0..d).map(|j| a[(i, j)] as f64).collect();
                for j in 0..d {
                    let h = 1e-2f32;
                    let mut p: Vec<f32> = x.iter().map(|&v| v as f32).collect();
                    p[j] += h;
                    let up = gmm.log_density(&p, sigma).unwrap() as f64;
                    p[j] -= 2.0 * h;
                    let dn = gmm.log_density(&p, sigma).unwrap() as f64;
                    let fd = (up - dn) / (2.0 * h as f64);
                    let an = score[(i, j)] as f64;
                    assert!(
                        (fd - an).abs() <= 2e-2 * (1.0 + an.abs()),
                        "d={d} k={k} σ={sigma}: fd {fd} vs exact {an}"
                    );
                }
            }
        }
    }
}

#[test]
fn isotropic_fast_path_agrees_with_the_full_path() {
    let iso = Gmm::circle(8, 2.0, 0.5, 0.3).unwrap();
    let means: Vec<Vec<f32>> = (0..8).map(|k| iso.mean(k).to_vec()).collect();
    // Same covariance but flagged full by a tiny symmetric off-diagonal.
    let covs = vec![vec![0.25, 1e-12, 1e-12, 0.25]; 8];
    let full = Gmm::new(&[1.0; 8], &means, &covs).unwrap();
    assert!(iso.isotropic.is_some() && full.isotropic.is_none());
    for a in [[0.1f32, 0.2], [2.0, -1.0], [-3.0, 0.5]] {
        for sigma in [0.0, 0.3] {
            let (x, y) =
                (iso.log_density(&a, sigma).unwrap(), full.log_density(&a, sigma).unwrap());
            assert!((x - y).abs() < 1e-5, "{x} vs {y}");
        }
    }
}

#[test]
fn density_integrates_to_one_in_1d() {
    let g = random_gmm(1, 3, 11);
    let (lo, hi, n) = (-15.0f32, 15.0f32, 30_000);
    let h = (hi - lo) / n as f32;
    let mass: f32 =
        (0..n).map(|i| g.log_density(&[lo + (i as f32 + 0.5) * h], 0.2).unwrap().exp() * h).sum();
    assert!((mass - 1.0).abs() < 1e-3, "mass {mass}");
}

#[test]
fn samples_have_the_mixture_moments() {
    let g = random_gmm(2, 3, 5);
    let mut teacher = GmmTeacher::fixed(g.clone(), 1);
    let n = 40_000;
    let s = Mat::<f32>::zeros(n, 1);
    let x = teacher.sample(s.as_ref(), &mut Seeds::new(3).stream("sample")).unwrap();
    for j in 0..2 {
        let mean: f64 = (0..n).map(|i| x[(i, j)] as f64).sum::<f64>() / n as f64;
        let exact: f64 = (0..3).map(|k| (g.weight(k) * g.mean(k)[j]) as f64).sum();
        let var_exact: f64 = (0..3)
            .map(|k| (g.weight(k) * (g.covariance(k)[j * 2 + j] + g.mean(k)[j].powi(2))) as f64)
            .sum::<f64>()
            - exact * exact;
        let tol = 4.0 * (var_exact / n as f64).sqrt();
        assert!((mean - exact).abs() < tol, "mean {mean} vs {exact}");
    }
}

#[test]
fn rotating_toy_moves_its_modes_with_the_state() {
    let mut t = GmmTeacher::rotating_toy(8, 2.0, 0.5).unwrap();
    let s = std::f32::consts::FRAC_PI_2;
    let g = t.mixture_at(&[s]).unwrap();
    assert!(g.mean(0)[0].abs() < 1e-5 && (g.mean(0)[1] - 2.0).abs() < 1e-5);
    // The score at the rotated mode 0 is ~0; at the unrotated position it is not.
    let a = Mat::from_fn(2, 2, |i, j| match (i, j) {
        (0, 0) => 0.0,
        (0, 1) => 2.0,
        (1, 0) => 2.0 * (std::f32::consts::PI / 8.0).cos(),
        _ => 2.0 * (std::f32::consts::PI / 8.0).sin(),
    });
    let st = Mat::from_fn(2, 1, |_, _| s);
    let mut out = Mat::zeros(2, 2);
    t.score(a.as_ref(), st.as_ref(), &[0.1, 0.1], out.as_mut()).unwrap();
    assert!(out[(0, 0)].abs() + out[(0, 1)].abs() < 0.05);
    assert!(out[(1, 0)].abs() + out[(1, 1)].abs() > 0.5);
}

#[test]
fn bad_mixtures_and_inputs_are_errors() {
    assert!(Gmm::new(&[], &[], &[]).is_err());
    assert!(Gmm::new(&[1.0], &[vec![0.0, 0.0]], &[vec![1.0, 2.0, 2.0, 1.0]]).is_err());
    assert!(Gmm::new(&[1.0], &[vec![0.0, 0.0]], &[vec![1.0, 0.5, 0.0, 1.0]]).is_err());
    assert!(Gmm::new(&[-1.0], &[vec![0.0]], &[vec![1.0]]).is_err());
    assert!(Gmm::isotropic(&[1.0], &[vec![f32::NAN]], 1.0).is_err());
    let mut t = GmmTeacher::circle_toy();
    let a = Mat::<f32>::zeros(2, 3);
    let mut out = Mat::<f32>::zeros(2, 3);
    assert!(
        t.score(a.as_ref(), Mat::<f32>::zeros(2, 1).as_ref(), &[0.1; 2], out.as_mut()).is_err()
    );
    let a = Mat::from_fn(1, 2, |_, _| f32::NAN);
    let mut out = Mat::<f32>::zeros(1, 2);
    assert!(t.score(a.as_ref(), Mat::<f32>::zeros(1, 1).as_ref(), &[0.1], out.as_mut()).is_err());
    let a = Mat::<f32>::zeros(1, 2);
    assert!(t.score(a.as_ref(), Mat::<f32>::zeros(1, 1).as_ref(), &[-1.0], out.as_mut()).is_err());
}
