use super::*;
use crate::metrics::{find_runs, metrics_json};
use serde_json::json;

/// The columns of the tests' tasks.
fn cols(_task: &str) -> Vec<Column> {
    vec![
        Column::new("success_rate", "success rate", 3),
        Column::new("task_entropy", "task entropy", 3),
    ]
}

fn row(v: Value) -> Row {
    v.as_object().unwrap().clone()
}

#[test]
fn tables_aggregate_seeds_across_runs() {
    let run = |seed: u64, sr: f64| {
        Value::Object(metrics_json(
            "avoiding",
            "avoiding",
            &[seed],
            &[
                (
                    "beso".into(),
                    vec![row(json!({"seed": seed, "success_rate": sr, "task_entropy": 0.8}))],
                ),
                ("vdd-beso".into(), vec![row(json!({"seed": seed, "success_rate": 0.5}))]),
            ],
        ))
    };
    let mut notes = Vec::new();
    let rows = collect_rows(&[run(0, 0.9), run(1, 0.7)], &mut notes);
    let table = markdown_table(&rows, &cols("avoiding"));
    assert!(table.contains("| beso | 2 | 0.800 ± 0.100 | 0.800 ± 0.000 |"), "{table}");
    assert!(table.contains("| vdd-beso | 2 | 0.500 ± 0.000 |"), "{table}");
}

#[test]
fn tables_come_from_run_directories() {
    let root = std::env::temp_dir().join(format!("vdd-report-table-{}", std::process::id()));
    let write = |dir: &str, task: &str, seed: u64, sr: f64| {
        let d = root.join(dir);
        std::fs::create_dir_all(&d).unwrap();
        let m = metrics_json(
            "avoiding",
            task,
            &[seed],
            &[("beso".into(), vec![row(json!({"seed": seed, "success_rate": sr}))])],
        );
        std::fs::write(d.join("metrics.json"), Value::Object(m).to_string()).unwrap();
    };
    write("avoiding/seed0", "avoiding", 0, 0.5);
    write("avoiding/seed1", "avoiding", 1, 0.7);
    write("avoiding/again", "avoiding", 1, 0.9);
    write("toy/seed0", "toy-gmm", 0, 0.5);
    std::fs::create_dir_all(root.join("cache/teachers")).unwrap();
    let groups = find_runs(&root);
    assert_eq!(groups.len(), 2, "the cache is skipped");
    assert_eq!(groups[0].0, "avoiding");
    let runs = &groups[0].1;
    assert_eq!(runs.len(), 3);
    let table = table_of_runs(&runs[1..], &cols, &[]).unwrap();
    assert!(table.text.starts_with("## avoiding (avoiding)\n\n"), "{}", table.text);
    assert!(table.text.contains("| beso | 2 | 0.600 ± 0.100 |"), "{}", table.text);
    assert!(table.notes.is_empty());
    let table = table_of_runs(runs, &cols, &[]).unwrap();
    assert_eq!(table.notes, vec!["beso: seed 1 appears twice; the later run is used"]);
    let all = tables_of_all_runs(&root, &cols, &[]).unwrap();
    assert_eq!(
        all.text,
        format!("{}\n{}\n", table.text, table_of_runs(&groups[1].1, &cols, &[]).unwrap().text)
    );
    assert_eq!(all.notes, table.notes);
    assert!(tables_of_all_runs(&root.join("none"), &cols, &[]).unwrap().text.is_empty());
    let mixed = [runs[0].clone(), groups[1].1[0].clone()];
    assert!(
        matches!(table_of_runs(&mixed, &cols, &[]), Err(Error::MixedTasks { tasks }) if tasks.len() == 2)
    );
    std::fs::write(root.join("avoiding/seed0/metrics.json"), "{}").unwrap();
    assert!(matches!(table_of_runs(&runs[1..2], &cols, &[]), Err(Error::NoMethods { .. })));
    std::fs::remove_dir_all(&root).unwrap();
}
