//! Two rows of one run that train the same student (here `vdd-beso` and
//! `vdd-beso-selected`, two jobs at a time) train it once: the second waits for the first's
//! claim on the student cache and loads what it stored, with and without `--fresh`. In a test
//! binary of its own, because it counts the process-wide progress lines.

use std::sync::{Arc, Mutex};

mod common;

/// Both rows, two jobs at a time, no rounds on visited states (the selecting row would make
/// them iterations on the demonstrations, another training), enough iterations that the
/// second row starts while the first trains.
fn recipe() -> String {
    common::TINY_AVOIDING
        .replace(
            r#"methods = ["vdd-beso-selected"]"#,
            "methods = [\"vdd-beso\", \"vdd-beso-selected\"]\njobs = 2",
        )
        .replace("{ episodes = 2, rounds = 2, iterations = 10 }", "false")
        .replace("iterations = 30", "iterations = 200")
}

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
        let root = common::root(&format!("claims-{fresh}"), &recipe());
        common::run(&root, "tests/student_claims.rs", |r| r.fresh = fresh)
            .unwrap_or_else(|e| panic!("{e}"));
        let lines = lines.0.lock().unwrap().clone();
        let count = |what: &str| lines.iter().filter(|l| l.contains(what)).count();
        assert_eq!(count("cache/students/"), 1, "fresh = {fresh}: {lines:#?}");
        assert_eq!(count("student loaded from the cache"), 1, "fresh = {fresh}: {lines:#?}");
        std::fs::remove_dir_all(&root).unwrap();
    }
}
