//! End to end: VDD (`vdd`) distils the exact score of the paper's 2-D toy (`vdd_core::gmm`)
//! into a mixture of experts (`vdd-moe`), for both expert families.
//!
//! The run is shorter than the paper's (the full 600-iteration run is
//! `cargo xtask experiment toy-gmm`), but a trainer that dropped a term of the corrected score,
//! mixed up the entropy gradient or the responsibilities loses modes or lands far off in KL.

use faer::Mat;
use vdd::{DistillData, Vdd, VddConfig, eval};
use vdd_core::Seeds;
use vdd_core::gmm::{Gmm, GmmTeacher};
use vdd_moe::{ExpertKind, Moe, MoeConfig};

fn distil(kind: ExpertKind, seed: u64, iterations: usize) -> Moe {
    let student = MoeConfig { expert_kind: kind, ..MoeConfig::toy(1, 2, 8) };
    // The toy's learning rate decays linearly to 0 over the run, whatever its length.
    let mut config = VddConfig { iterations, seed, ..VddConfig::toy() };
    config.expert_optimizer.lr = 1e-2;
    let data = DistillData::from_states(Mat::zeros(32, 1)).unwrap();
    let mut vdd = Vdd::from_config(config, GmmTeacher::circle_toy(), student, data).unwrap();
    let mut last = None;
    vdd.train(|m| last = Some(*m)).unwrap();
    let last = last.expect("metrics reported every iteration");
    assert_eq!(last.iteration + 1, iterations);
    vdd.into_student()
}

fn check_student(student: &mut Moe, what: &str) {
    let toy = Gmm::circle(8, 2.0, 0.5, 0.0).unwrap();
    let modes: Vec<Vec<f32>> = (0..8).map(|k| toy.mean(k).to_vec()).collect();
    let covered = eval::modes_covered(student, &[0.0], &modes, 0.3, 0.05).unwrap();
    assert_eq!(covered, 8, "{what}: modes covered");
    let log_p = |a: &[f32]| toy.log_density(a, 0.0).unwrap();
    let mut rng = Seeds::new(9).stream("eval");
    let reverse = eval::reverse_kl(student, &[0.0], log_p, 20_000, &mut rng).unwrap();
    let truth = GmmTeacher::circle_toy().sample(Mat::zeros(20_000, 1).as_ref(), &mut rng).unwrap();
    let forward = eval::forward_kl(student, &[0.0], log_p, truth.as_ref()).unwrap();
    // Monte-Carlo error at 20k samples is ~0.003 nats; mode-dropping costs ≥ ln(8/7) = 0.13.
    assert!(reverse.abs() < 0.02, "{what}: reverse KL {reverse}");
    assert!(forward.abs() < 0.02, "{what}: forward KL {forward}");
}

#[test]
fn diagonal_experts_keep_every_mode_of_the_toy() {
    let mut student = distil(ExpertKind::Diagonal, 0, 250);
    check_student(&mut student, "diagonal");
}

#[test]
fn full_covariance_experts_keep_every_mode_of_the_toy() {
    let mut student = distil(ExpertKind::Full, 1, 250);
    check_student(&mut student, "full");
}

#[test]
fn the_same_seed_gives_the_same_student() {
    let mut a = distil(ExpertKind::Diagonal, 3, 20);
    let mut b = distil(ExpertKind::Diagonal, 3, 20);
    let s = Mat::<f32>::zeros(1, 1);
    a.forward(s.as_ref()).unwrap();
    b.forward(s.as_ref()).unwrap();
    assert_eq!(a.output().means, b.output().means);
    assert_eq!(a.output().scales, b.output().scales);
}
