//! Tests of the gating fitted to a teacher's samples.

use super::*;
use crate::test_support::{
    CLUSTER_MEANS, assert_gating_matches_shares, expert_params, small_moe_config,
    uniform_cluster_experts,
};
use vdd_core::{Rng, Seeds};
use vdd_moe::ExpertKind;
use vdd_nn::Parameters;

/// A teacher that answers a point of cluster `k` of [`CLUSTER_MEANS`] with probability
/// `shares[k]` (std 0.3), whatever the state; or NaN when `broken`.
struct ClusterTeacher {
    shares: [f32; 3],
    rng: Rng,
    broken: bool,
}

impl ClusterTeacher {
    fn new(shares: [f32; 3]) -> Self {
        Self { shares, rng: Seeds::new(0).stream("teacher"), broken: false }
    }
}

impl Policy for ClusterTeacher {
    fn obs_dim(&self) -> usize {
        1
    }
    fn action_dim(&self) -> usize {
        2
    }
    fn seed(&mut self, seed: u64) {
        self.rng = Seeds::new(seed).stream("teacher");
    }
    fn act_into(&mut self, _obs: &[f32], action: &mut [f32]) -> Result<(), CoreError> {
        let u: f32 = self.rng.random();
        let k = if u < self.shares[0] {
            0
        } else if u < self.shares[0] + self.shares[1] {
            1
        } else {
            2
        };
        for (j, a) in action.iter_mut().enumerate() {
            *a = CLUSTER_MEANS[k][j] + 0.3 * vdd_core::standard_normal(&mut self.rng);
        }
        if self.broken {
            action[0] = f32::NAN;
        }
        Ok(())
    }
}

/// Three experts fitted under a uniform gating to equal clusters (one expert per cluster).
fn uniform_student() -> Moe {
    uniform_cluster_experts([120, 120, 120]).0
}

fn network() -> NetworkConfig {
    small_moe_config(ExpertKind::Diagonal, 3).gating_network
}

const FIT: GatingFitConfig = GatingFitConfig {
    samples_per_state: 32,
    iterations: 30,
    steps_per_iter: 20,
    batch_size: 256,
    lr: 1e-2,
    seed: 3,
    state_noise_share: 0.0,
    state_noise_std: 0.0,
};

/// A teacher that answers the origin and keeps the states it was asked at.
#[derive(Default)]
struct Recorder(Vec<f32>);
impl Policy for Recorder {
    fn obs_dim(&self) -> usize {
        1
    }
    fn action_dim(&self) -> usize {
        2
    }
    fn act_into(&mut self, obs: &[f32], action: &mut [f32]) -> Result<(), vdd_core::CoreError> {
        self.0.push(obs[0]);
        action.fill(0.0);
        Ok(())
    }
}

#[test]
fn state_noise_moves_its_share_of_the_pairs_by_its_std() {
    let asked = |share, std| {
        let config = GatingFitConfig {
            iterations: 1,
            state_noise_share: share,
            state_noise_std: std,
            ..FIT
        };
        let mut teacher = Recorder::default();
        let states = Mat::from_fn(64, 1, |_, _| 2.0f32);
        fit_gating_to_policy(uniform_student(), network(), &mut teacher, states.as_ref(), &config)
            .unwrap();
        teacher.0
    };
    assert!(asked(0.0, 0.5).iter().all(|&s| s == 2.0), "no share: every pair at its state");
    assert!(asked(0.7, 0.0).iter().all(|&s| s == 2.0), "no std: every pair at its state");
    let moved = asked(0.5, 0.5);
    assert_eq!(moved.len(), 64 * 32);
    let off: Vec<f32> = moved.iter().map(|s| s - 2.0).filter(|d| *d != 0.0).collect();
    let share = off.len() as f32 / moved.len() as f32;
    let std = (off.iter().map(|d| d * d).sum::<f32>() / off.len() as f32).sqrt();
    assert!((share - 0.5).abs() < 0.05 && (std - 0.5).abs() < 0.05, "{share} {std}");
    assert_eq!(moved, asked(0.5, 0.5), "the moves follow the seed");
    for (share, std) in [(1.5, 0.1), (f32::NAN, 0.1), (0.5, -1.0), (0.5, f32::INFINITY)] {
        let config =
            GatingFitConfig { state_noise_share: share, state_noise_std: std, ..FIT.clone() };
        let states = Mat::zeros(4, 1);
        let r = fit_gating_to_policy(
            uniform_student(),
            network(),
            &mut Recorder::default(),
            states.as_ref(),
            &config,
        );
        assert!(r.unwrap_err().to_string().contains("state_noise"), "{share} {std}");
    }
}

#[test]
fn the_fitted_gating_learns_the_teachers_shares_and_the_experts_stay() {
    let shares = [0.1, 0.3, 0.6];
    let mut student = uniform_student();
    let before = expert_params(&mut student);
    let states = Mat::zeros(32, 1);
    let mut teacher = ClusterTeacher::new(shares);
    let (mut student, report) =
        fit_gating_to_policy(student, network(), &mut teacher, states.as_ref(), &FIT).unwrap();
    assert_eq!(report.pairs, 32 * 32);
    assert!(report.log_likelihood_after > report.log_likelihood_before + 0.1, "{report:?}");
    assert_eq!(expert_params(&mut student), before, "the experts moved");
    assert_gating_matches_shares(&mut student, shares, 0.05);
}

#[test]
fn the_fit_is_deterministic_and_follows_its_seed() {
    let fit = |seed| {
        let config = GatingFitConfig { seed, iterations: 3, ..FIT };
        let mut teacher = ClusterTeacher::new([0.2, 0.3, 0.5]);
        let states = Mat::zeros(8, 1);
        let (mut s, _) = fit_gating_to_policy(
            uniform_student(),
            network(),
            &mut teacher,
            states.as_ref(),
            &config,
        )
        .unwrap();
        let mut gating = Vec::new();
        s.gating_network_mut().unwrap().visit_params("", &mut |_, p| gating.push(p.value.clone()));
        gating
    };
    assert_eq!(fit(5), fit(5));
    assert_ne!(fit(5), fit(6));
}

#[test]
fn progress_reports_the_sampling_then_every_iteration_and_leaves_the_fit_alone() {
    let config = GatingFitConfig { iterations: 4, ..FIT };
    let states = Mat::zeros(8, 1);
    let gating = |mut s: Moe| {
        let mut g = Vec::new();
        s.gating_network_mut().unwrap().visit_params("", &mut |_, p| g.push(p.value.clone()));
        g
    };
    let mut teacher = ClusterTeacher::new([0.2, 0.3, 0.5]);
    let (plain, plain_report) =
        fit_gating_to_policy(uniform_student(), network(), &mut teacher, states.as_ref(), &config)
            .unwrap();
    let mut seen = Vec::new();
    let mut teacher = ClusterTeacher::new([0.2, 0.3, 0.5]);
    let (reported, report) = fit_gating_to_policy_with_progress(
        uniform_student(),
        network(),
        &mut teacher,
        states.as_ref(),
        &config,
        |p| seen.push(p),
    )
    .unwrap();
    assert_eq!(report, plain_report);
    assert_eq!(gating(reported), gating(plain), "progress changed the fit");
    assert_eq!(seen.len(), 1 + 4, "{seen:?}");
    assert_eq!(seen[0], GatingFitProgress::Sampling { pairs: 8 * config.samples_per_state });
    for (i, p) in seen[1..].iter().enumerate() {
        let GatingFitProgress::Iteration { iteration, iterations, log_likelihood } = *p else {
            panic!("{p:?} after the sampling");
        };
        assert_eq!((iteration, iterations), (i, 4));
        assert!(log_likelihood.is_finite());
    }
    let GatingFitProgress::Iteration { log_likelihood: first, .. } = seen[1] else {
        unreachable!()
    };
    assert_eq!(first, report.log_likelihood_before, "the first E-step is the fit's start");
}

#[test]
fn bad_settings_and_bad_teachers_are_errors() {
    let states = Mat::zeros(8, 1);
    let run = |config: GatingFitConfig, teacher: &mut ClusterTeacher, states: MatRef<'_, f32>| {
        fit_gating_to_policy(uniform_student(), network(), teacher, states, &config)
            .map(drop)
            .unwrap_err()
            .to_string()
    };
    let mut t = ClusterTeacher::new([0.2, 0.3, 0.5]);
    let small = GatingFitConfig { iterations: 1, ..FIT };
    for bad in [
        GatingFitConfig { samples_per_state: 0, ..small.clone() },
        GatingFitConfig { samples_per_state: MAX_SAMPLES_PER_STATE + 1, ..small.clone() },
        GatingFitConfig { steps_per_iter: 0, ..small.clone() },
        GatingFitConfig { iterations: 0, ..small.clone() },
        GatingFitConfig { lr: f32::NAN, ..small.clone() },
    ] {
        assert!(!run(bad, &mut t, states.as_ref()).is_empty());
    }
    assert!(run(small.clone(), &mut t, Mat::zeros(8, 2).as_ref()).contains("state columns"));
    assert!(run(small.clone(), &mut t, Mat::zeros(0, 1).as_ref()).contains("pairs"));
    let nan_states = Mat::from_fn(8, 1, |i, _| if i == 3 { f32::NAN } else { 0.0 });
    assert!(!run(small.clone(), &mut t, nan_states.as_ref()).is_empty());
    let mut broken = ClusterTeacher { broken: true, ..ClusterTeacher::new([0.2, 0.3, 0.5]) };
    assert!(!run(small, &mut broken, states.as_ref()).is_empty());
}
