//! Bad settings on the command line give a clean error (exit 1, a message) before any work,
//! and leave no run directory behind.

use std::path::{Path, PathBuf};
use std::process::Command;

/// Runs `cargo xtask <args>` (the built binary); `(exit code, stderr)`.
fn xtask(args: &[&str]) -> (Option<i32>, String) {
    let out = Command::new(env!("CARGO_BIN_EXE_xtask")).args(args).output().unwrap();
    (out.status.code(), String::from_utf8_lossy(&out.stderr).into_owned())
}

fn scratch(tag: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("xtask-cli-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

/// Exit 1 with an error naming `needle`, and no `out` left behind.
fn refused(args: &[&str], out: &Path, needle: &str) {
    let (code, err) = xtask(args);
    assert_eq!(code, Some(1), "{args:?}: {err}");
    assert!(err.starts_with("error") && err.contains(needle), "{args:?}: {err}");
    assert!(!out.exists(), "{args:?} left {}", out.display());
}

#[test]
fn bad_settings_fail_before_any_work_and_leave_nothing() {
    let dir = scratch("run");
    let out = dir.to_str().unwrap();
    let toy = |set: &str| {
        vec!["experiment", "toy-gmm", "--quick", "--set", set, "--out", out]
            .into_iter()
            .map(str::to_owned)
            .collect::<Vec<_>>()
    };
    for (set, needle) in [
        ("student.num_experts=100000000", "num_experts must be in"),
        ("student.experts_network.hidden_dim=1000000", "hidden_dim must be in"),
        ("student.experts_network.hidden_dim=60000", "memory"),
        ("eval.kl_samples=0", "kl_samples"),
        ("eval.coverage_radius=nan", "coverage_radius"),
        ("vdd.exact.expert_optimizer.eps=-1", "eps"),
        ("vdd.exact.student_ema=3.0", "student_ema"),
        ("plots.grid=100000000", "grid"),
        ("data.points=1000000000000", "data.points"),
    ] {
        let args = toy(set);
        refused(&args.iter().map(String::as_str).collect::<Vec<_>>(), &dir, needle);
    }
    let avoiding = ["experiment", "avoiding", "--quick", "--set", "eval.rollouts=0", "--out", out];
    refused(&avoiding, &dir, "rollouts");
    for seeds in ["0..100000000000", "0..18446744073709551615"] {
        refused(&["experiment", "toy-gmm", "--seeds", seeds, "--out", out], &dir, "seed");
    }
    refused(&["demos", "avoiding", "--n", "1000000000000", "--out", out], &dir, "memory");
}

#[test]
fn out_may_be_neither_empty_nor_a_file() {
    let (code, err) = xtask(&["experiment", "toy-gmm", "--quick", "--out", ""]);
    assert_eq!(code, Some(1), "{err}");
    let file = scratch("file");
    std::fs::write(&file, "keep").unwrap();
    let (code, err) = xtask(&["experiment", "toy-gmm", "--quick", "--out", file.to_str().unwrap()]);
    assert_eq!(code, Some(1), "{err}");
    assert_eq!(std::fs::read_to_string(&file).unwrap(), "keep");
    std::fs::remove_file(&file).unwrap();
}
