//! Two rows of one run that train the same student (here `vdd-beso` and
//! `vdd-beso-selected`, two jobs at a time) train it once: the second waits for the first's
//! claim on the student cache and loads what it stored, with and without `--fresh`. In a test
//! binary of its own, because it counts the process-wide progress lines.

use std::sync::{Arc, Mutex};

mod common;

const TINY: &str = r#"
name = "tiny"
task = "avoiding"
description = "Avoiding on a tiny budget, two rows of one training"
seeds = [0]
methods = ["vdd-beso", "vdd-beso-selected"]
jobs = 2

[data]
demonstrations = 4
validation_fraction = 0.0

[teachers.beso.train]
steps = 30
batch_size = 32
log_every = 10

[vdd]
beso_expert_visits = false

[vdd.beso]
iterations = 200
batch_size = 8

[eval]
rollouts = 4
lockstep_batch = 2
timing_calls = 20
timing_warmup = 2
timing_min_round_ms = 0.1
curve_points = 3
curve_rollouts = 4

[plots]
enabled = false
"#;

#[derive(Default)]
struct Lines(Mutex<Vec<String>>);

impl vdd_lab::progress::Sink for Lines {
    fn log(&self, line: &str) {
        self.0.lock().unwrap().push(line.to_owned());
    }
}

#[test]
fn two_rows_of_one_training_train_it_once() {
    let lines = Arc::new(Lines::default());
    vdd_lab::progress::set_sink(lines.clone());
    for fresh in [false, true] {
        lines.0.lock().unwrap().clear();
        let root = common::root(&format!("claims-{fresh}"), TINY);
        common::run(&root, "tests/student_claims.rs", fresh).unwrap_or_else(|e| panic!("{e}"));
        let lines = lines.0.lock().unwrap().clone();
        let count = |what: &str| lines.iter().filter(|l| l.contains(what)).count();
        assert_eq!(count("cache/students/"), 1, "fresh = {fresh}: {lines:#?}");
        assert_eq!(count("student loaded from the cache"), 1, "fresh = {fresh}: {lines:#?}");
        std::fs::remove_dir_all(&root).unwrap();
    }
}
