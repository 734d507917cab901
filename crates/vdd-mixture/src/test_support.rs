//! Small data sets and mixtures for the unit tests.

use faer::Mat;
use rand::Rng as _;
use vdd_core::Seeds;
use vdd_moe::{ExpertKind, GatingKind, Moe, MoeConfig};

use vdd_nn::{AdamConfig, LrSchedule};

use vdd_nn::Parameters;

use crate::{Dataset, Em, EmConfig};

/// Three well-separated 2-D cluster centres (radius 3, 120° apart, at 15°, 135° and 255°, so
/// no two share a coordinate).
pub const CLUSTER_MEANS: [[f32; 2]; 3] = [[2.898, 0.776], [-2.121, 2.121], [-0.776, -2.898]];

/// `sizes[k]` points around cluster `k` of [`CLUSTER_MEANS`] with isotropic `std`, shuffled
/// together; returns the data (state a constant 0, 1-D) and each point's cluster.
pub fn clusters(sizes: [usize; 3], std: f32, seed: u64) -> (Dataset, Vec<usize>) {
    let n: usize = sizes.iter().sum();
    let mut rng = Seeds::new(seed).stream("clusters");
    let mut labels: Vec<usize> = (0..3).flat_map(|k| std::iter::repeat_n(k, sizes[k])).collect();
    for i in (1..n).rev() {
        labels.swap(i, rng.random_range(0..=i));
    }
    let mut noise = vec![0.0f32; 2 * n];
    vdd_core::fill_standard_normal(&mut rng, &mut noise);
    let actions = Mat::from_fn(n, 2, |i, j| CLUSTER_MEANS[labels[i]][j] + std * noise[2 * i + j]);
    (Dataset::new(Mat::zeros(n, 1), actions).expect("valid data"), labels)
}

/// A small `1 → 2` mixture of `num_experts` experts with a learned gating, whose experts start
/// broad (std 3, covering all of [`clusters`]), which keeps EM out of the local optimum where
/// one expert spans two clusters and another starves.
pub fn small_moe_config(kind: ExpertKind, num_experts: usize) -> MoeConfig {
    let mut mc = MoeConfig::toy(1, 2, num_experts);
    mc.expert_kind = kind;
    mc.gating = GatingKind::Learned;
    mc.init_std = 3.0;
    mc.experts_network.hidden_dim = 16;
    mc.gating_network.hidden_dim = 16;
    mc
}

/// [`small_moe_config`] initialised from `seed`.
pub fn small_moe(kind: ExpertKind, num_experts: usize, seed: u64) -> Moe {
    Moe::from_config(small_moe_config(kind, num_experts), seed).expect("valid mixture")
}

/// An EM configuration on the whole dataset (the IMC tests take its loop settings), `steps`
/// expert and gating steps per iteration with Adam at `lr`, decaying along a cosine so that
/// Adam's jitter near the M-step optimum cannot undo an ascent.
pub fn full_batch_config(iterations: usize, steps: usize, lr: f32) -> EmConfig {
    let schedule = LrSchedule::Cosine { final_factor: 0.05 };
    EmConfig {
        iterations,
        expert_steps_per_iter: steps,
        gating_steps_per_iter: steps,
        batch_size: None,
        gating_batch_size: None,
        expert_optimizer: AdamConfig { lr, ..AdamConfig::default() },
        expert_lr_schedule: schedule.clone(),
        gating_optimizer: AdamConfig { lr, ..AdamConfig::default() },
        gating_lr_schedule: schedule,
        ..EmConfig::toy()
    }
}

/// Three experts fitted by EM under a uniform gating to [`clusters`] of `sizes` (std 0.3), one
/// expert per cluster, and the data.
pub fn uniform_cluster_experts(sizes: [usize; 3]) -> (Moe, Dataset) {
    let (data, _) = clusters(sizes, 0.3, 2);
    let mut mc = small_moe_config(ExpertKind::Diagonal, 3);
    mc.gating = GatingKind::Uniform;
    let student = Moe::from_config(mc, 0).expect("valid mixture");
    (Em::fit(full_batch_config(40, 10, 1e-2), student, data.clone()).expect("EM fits"), data)
}

/// The values of the experts' network parameters, in order.
pub fn expert_params(student: &mut Moe) -> Vec<Vec<f32>> {
    let mut out = Vec::new();
    student.expert_networks_mut().visit_params("", &mut |_, p| out.push(p.value.clone()));
    out
}

/// Asserts that each expert's gating weight at state 0 is within `tol` of `shares[c]`, `c` the
/// cluster of [`CLUSTER_MEANS`] nearest the expert's mean.
pub fn assert_gating_matches_shares(student: &mut Moe, shares: [f32; 3], tol: f32) {
    student.forward(Mat::zeros(1, 1).as_ref()).expect("forward");
    let out = student.output();
    for z in 0..3 {
        let m = out.mean(0, z);
        let d =
            |k: usize| (m[0] - CLUSTER_MEANS[k][0]).powi(2) + (m[1] - CLUSTER_MEANS[k][1]).powi(2);
        let c = (0..3).min_by(|&a, &b| d(a).total_cmp(&d(b))).expect("three clusters");
        let q = out.log_gating_row(0)[z].exp();
        assert!(
            (q - shares[c]).abs() < tol,
            "expert {z} (cluster {c}): q = {q}, share {}",
            shares[c]
        );
    }
}
