//! Tests of resuming: every part of a checkpoint's trainer state is checked.

use std::path::{Path, PathBuf};

use serde_json::Value;
use vdd_nn::checkpoint::CheckpointDir;

use super::tests::{params, small_run};
use super::*;

fn temp(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("vdd-ckpt-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// A checkpoint after 3 of 6 iterations with a moving average; returns its generation.
fn checkpoint(root: &Path) -> PathBuf {
    let (mut config, teacher, student, data) = small_run(6);
    config.student_ema = Some(0.9);
    let mut vdd = Vdd::new(config, teacher, student, data).unwrap();
    for _ in 0..3 {
        vdd.step().unwrap();
    }
    let store = CheckpointDir::open(root).unwrap();
    vdd.save_checkpoint(&store).unwrap()
}

/// Resumes after `edit` changed `trainer.json`; the error's text.
fn resume_after(tag: &str, edit: impl FnOnce(&mut Value)) -> String {
    let root = temp(tag);
    let generation = checkpoint(&root);
    let path = generation.join("trainer.json");
    let mut state: Value = serde_json::from_slice(&std::fs::read(&path).unwrap()).unwrap();
    edit(&mut state);
    std::fs::write(&path, serde_json::to_vec(&state).unwrap()).unwrap();
    let (_, teacher, _, data) = small_run(6);
    let e = Vdd::resume(&root, teacher, data).err().expect("the edited state is refused");
    std::fs::remove_dir_all(&root).unwrap();
    let mut text = e.to_string();
    let mut source = std::error::Error::source(&e);
    while let Some(s) = source {
        text.push_str(&format!(" | {s}"));
        source = s.source();
    }
    text
}

#[test]
fn an_unchanged_checkpoint_resumes_and_continues_like_a_straight_run() {
    let root = temp("ok");
    checkpoint(&root);
    let (mut config, teacher, student, data) = small_run(6);
    config.student_ema = Some(0.9);
    let mut straight = Vdd::new(config, teacher.clone(), student, data.clone()).unwrap();
    straight.train(|_| {}).unwrap();
    let mut resumed = Vdd::resume(&root, teacher, data).unwrap();
    assert_eq!(resumed.iteration(), 3);
    resumed.train(|_| {}).unwrap();
    // The convergence probe's measurements before the checkpoint were kept.
    assert!(straight.convergence().is_some());
    assert_eq!(straight.convergence(), resumed.convergence());
    assert_eq!(params(&straight.into_student()), params(&resumed.into_student()));
    std::fs::remove_dir_all(&root).unwrap();
}

#[test]
fn an_optimiser_state_of_another_model_is_an_error_naming_the_tensor() {
    let e = resume_after("adam", |s| {
        let m = &mut s["expert_optimizer"]["m"][0];
        m.as_array_mut().unwrap().pop();
    });
    assert!(e.contains("expert optimiser") && e.contains('`'), "{e}");
    let e = resume_after("adam-gating", |s| {
        s["gating_optimizer"]["v"].as_array_mut().unwrap().pop();
    });
    assert!(e.contains("gating optimiser"), "{e}");
    let e = resume_after("adam-extra", |s| {
        let m = s["expert_optimizer"]["m"].as_array_mut().unwrap();
        m.push(Value::Array(vec![0.0.into()]));
        s["expert_optimizer"]["v"].as_array_mut().unwrap().push(Value::Array(vec![0.0.into()]));
    });
    assert!(e.contains("expert optimiser"), "{e}");
}

#[test]
fn settings_out_of_range_are_errors_on_resume() {
    let e = resume_after("ema", |s| s["config"]["student_ema"] = 3.0.into());
    assert!(e.contains("student_ema"), "{e}");
    let e = resume_after("ema-state", |s| s["student_ema"]["decay"] = 3.0.into());
    assert!(e.contains("student average") && e.contains("decay"), "{e}");
    let e = resume_after("eps", |s| {
        s["config"]["expert_optimizer"]["eps"] = (-1.0).into();
        s["expert_optimizer"]["config"]["eps"] = (-1.0).into();
    });
    assert!(e.contains("eps"), "{e}");
    let e = resume_after("beta", |s| s["gating_optimizer"]["config"]["beta1"] = 1.5.into());
    assert!(e.contains("gating optimiser"), "{e}");
    let e = resume_after("iteration", |s| s["iteration"] = 99.into());
    assert!(e.contains("iteration"), "{e}");
    // 1e39 reads as an f32 infinity.
    let e = resume_after("inf", |s| {
        let big: Value = serde_json::from_str("1e39").unwrap();
        s["config"]["gating_optimizer"]["lr"] = big;
    });
    assert!(e.contains("lr"), "{e}");
}

#[test]
fn a_second_writer_is_refused() {
    let root = temp("lock");
    let store = CheckpointDir::open(&root).unwrap();
    let e = CheckpointDir::open(&root).unwrap_err();
    assert!(e.to_string().contains("another writer"), "{e}");
    drop(store);
    std::fs::remove_dir_all(&root).unwrap();
}

/// Curves of the iteration, failing once on its first call when `fail` is set (a killed run).
struct FailOnce(std::sync::atomic::AtomicBool);

impl vdd_core::curves::CurveEval<Moe> for FailOnce {
    type Error = VddError;
    fn checkpoints(&self, _iterations: usize) -> Vec<usize> {
        vec![4]
    }
    fn evaluate(&self, _: &Moe, _: u64) -> Result<Vec<(String, f64)>, VddError> {
        if self.0.swap(false, std::sync::atomic::Ordering::SeqCst) {
            return Err(VddError::NonFinite { iteration: 4, quantity: "a test's curve" });
        }
        Ok(vec![("four".into(), 4.0)])
    }
}

/// A resumable run stopped by an error at iteration 4, with a commit after every iteration.
fn resumable(root: &Path, fail: bool, resume: bool) -> Result<ResumableOutcome, VddError> {
    let eval = FailOnce(fail.into());
    let mut probe = vdd_core::curves::CurveProbe::new(Some(&eval), 0);
    let run = Resumable { dir: root, resume, every_seconds: 0, select_by: None };
    run.run(small_run(6), &mut probe, Ok::<_, VddError>, |_| {})
}

#[test]
fn a_resumable_run_continues_from_its_last_commit_like_a_straight_run() {
    let (straight, root) = (resumable(&temp("straight"), false, false).unwrap(), temp("killed"));
    assert!(resumable(&root, true, false).is_err(), "the failing curve stops the run");
    assert!(root.exists(), "the stopped run left its checkpoints");
    let resumed = resumable(&root, false, true).unwrap();
    assert!(!root.exists(), "a finished run removes its checkpoints");
    assert_eq!(params(&straight.student), params(&resumed.student));
    assert_eq!(straight.curves, resumed.curves);
    assert_eq!(straight.mean_noise_level, resumed.mean_noise_level);
    assert_eq!(resumed.curves["four"], [(4.0, 4.0)]);
    // Without `resume`, the checkpoints of an earlier run are discarded.
    assert!(resumable(&root, true, false).is_err());
    assert_eq!(params(&resumable(&root, false, false).unwrap().student), params(&straight.student));
}

/// Before, a run that did not resume removed its directory whoever held it: another writer's
/// checkpoints went with it. Now the lock comes first, and a held one is an error.
#[test]
fn a_fresh_run_never_removes_a_live_writers_checkpoints() {
    let root = temp("held");
    let generation = checkpoint(&root);
    let held = CheckpointDir::open(&root).unwrap();
    let e = resumable(&root, false, false).unwrap_err().to_string();
    assert!(e.contains("LOCK"), "{e}");
    assert!(generation.exists(), "the holder's generation stays");
    drop(held);
    // Unheld, the earlier generations are discarded and the run starts afresh.
    assert!(resumable(&root, false, false).is_ok());
    assert!(!root.exists(), "a finished run removes its checkpoints");
}

/// Before, resume accepted Adam moments of 2^63.
#[test]
fn adam_moments_beyond_their_bounds_are_refused_on_resume() {
    let e = resume_after("moment-m", |s| {
        s["expert_optimizer"]["m"][0][0] = 9_223_372_036_854_775_808.0f64.into();
    });
    assert!(e.contains("expert optimiser") && e.contains("first moment"), "{e}");
    let e = resume_after("moment-v", |s| s["gating_optimizer"]["v"][0][0] = 1e36.into());
    assert!(e.contains("gating optimiser") && e.contains("second moment"), "{e}");
}

/// Before, a run that drifted past |w| = 1e6 committed a generation its resume refused. Now
/// the commit fails naming the value, and `LATEST` stays on the previous generation.
#[test]
fn a_state_resume_would_refuse_is_not_committed() {
    use vdd_nn::Parameters;
    let root = temp("drift");
    let generation = checkpoint(&root);
    let resumed = || {
        let (_, teacher, _, data) = small_run(6);
        let mut vdd = Vdd::resume(&root, teacher, data).unwrap();
        vdd.step().unwrap();
        vdd
    };
    let store = CheckpointDir::open(&root).unwrap();
    let mut drifted = resumed();
    let mut first = true;
    drifted.student_mut().expert_networks_mut().visit_params_mut("", &mut |_, p| {
        if std::mem::take(&mut first) {
            p.value[0] = 2.5e6;
        }
    });
    let e = drifted.save_checkpoint(&store).unwrap_err().to_string();
    assert!(e.contains("2.5e6"), "{e}");
    // Adam moments of 2^63 (a diverged run) likewise.
    let mut diverged = resumed();
    let mut opt = serde_json::to_value(&diverged.expert_optimizer).unwrap();
    opt["m"][0][0] = 9_223_372_036_854_775_808.0f64.into();
    diverged.expert_optimizer = serde_json::from_value(opt).unwrap();
    let e = diverged.save_checkpoint(&store).unwrap_err().to_string();
    assert!(e.contains("expert optimiser"), "{e}");
    assert_eq!(vdd_nn::checkpoint::latest(&root).unwrap().unwrap(), (3, generation));
    // The sound state commits.
    resumed().save_checkpoint(&store).unwrap();
    drop(store);
    std::fs::remove_dir_all(&root).unwrap();
}

/// Scores the checkpoints 2, 4 and 6 with 1, 3 and 2 (the best in the middle; a resumed run
/// starts at checkpoint `from`), and records each snapshot's parameter sum; fails at the
/// third checkpoint when `fail` is set (a run killed after two).
struct Scored {
    calls: std::sync::atomic::AtomicUsize,
    fail: bool,
}

fn sum(student: &Moe) -> f64 {
    params(student).iter().flat_map(|(_, v)| v).map(|&p| f64::from(p)).sum()
}

impl vdd_core::curves::CurveEval<Moe> for Scored {
    type Error = VddError;
    fn checkpoints(&self, _iterations: usize) -> Vec<usize> {
        vec![2, 4, 6]
    }
    fn evaluate(&self, student: &Moe, _: u64) -> Result<Vec<(String, f64)>, VddError> {
        let call = self.calls.fetch_add(1, std::sync::atomic::Ordering::SeqCst);
        if self.fail && call == 2 {
            return Err(VddError::NonFinite { iteration: 6, quantity: "a test's curve" });
        }
        Ok(vec![("score".into(), [1.0, 3.0, 2.0][call]), ("sum".into(), sum(student))])
    }
}

fn selecting(
    root: &Path,
    from: usize,
    fail: bool,
    series: &str,
) -> Result<ResumableOutcome, VddError> {
    let eval = Scored { calls: from.into(), fail };
    let mut probe = vdd_core::curves::CurveProbe::new(Some(&eval), 0);
    let run = Resumable { dir: root, resume: from > 0, every_seconds: 0, select_by: Some(series) };
    run.run(small_run(6), &mut probe, Ok::<_, VddError>, |_| {})
}

#[test]
fn checkpoint_selection_keeps_the_best_snapshot_and_survives_a_resume() {
    let out = selecting(&temp("select"), 0, false, "score").unwrap();
    let selected = out.selected.as_ref().expect("a snapshot was kept");
    assert_eq!((selected.iteration, selected.value), (4, 3.0));
    assert_eq!(sum(&selected.student), out.curves["sum"][1].1, "the snapshot of iteration 4");
    assert_ne!(sum(&selected.student), sum(&out.student), "not the final iterate");
    // Without selection nothing is kept, and the final student is the same.
    let plain = resumable(&temp("select-none"), false, false).unwrap();
    assert!(plain.selected.is_none());
    assert_eq!(params(&plain.student), params(&out.student));
    // Killed at the third checkpoint and resumed: the snapshot of iteration 4 is still kept.
    let root = temp("select-killed");
    assert!(selecting(&root, 0, true, "score").is_err());
    let resumed = selecting(&root, 2, false, "score").unwrap();
    let again = resumed.selected.expect("kept across the resume");
    assert_eq!((again.iteration, again.value), (4, 3.0));
    assert_eq!(params(&again.student), params(&selected.student));
    assert_eq!(params(&resumed.student), params(&out.student));
}

#[test]
fn checkpoint_selection_by_a_series_the_curves_lack_is_an_error_naming_them() {
    let e = selecting(&temp("select-bad"), 0, false, "entropy").unwrap_err().to_string();
    assert!(e.contains("`entropy`") && e.contains("score, sum"), "{e}");
}
