use super::*;
use serde_json::json;

fn row(v: Value) -> Row {
    v.as_object().unwrap().clone()
}

#[test]
fn summaries_give_mean_and_population_std() {
    let rows = vec![
        row(json!({"seed": 0, "success_rate": 0.9, "train_seconds": 10.0, "name": "x"})),
        row(json!({"seed": 1, "success_rate": 1.0, "train_seconds": 14.0})),
    ];
    let s = summarise(&rows);
    assert!((s["success_rate"].as_f64().unwrap() - 0.95).abs() < 1e-12);
    assert!((s["success_rate_std"].as_f64().unwrap() - 0.05).abs() < 1e-12);
    assert!((s["train_seconds"].as_f64().unwrap() - 12.0).abs() < 1e-12);
    assert_eq!(s["seeds"], json!(2));
    assert!(!s.contains_key("seed") && !s.contains_key("name"));
    assert_eq!(s["per_seed"].as_array().unwrap().len(), 2);
}

#[test]
fn rows_are_collected_across_runs_in_order() {
    let run = |seed: u64, sr: f64| {
        Value::Object(metrics_json(
            "avoiding",
            "avoiding",
            &[seed],
            &[
                ("beso".into(), vec![row(json!({"seed": seed, "success_rate": sr}))]),
                ("vdd-beso".into(), vec![row(json!({"seed": seed, "success_rate": 0.5}))]),
            ],
        ))
    };
    let mut notes = Vec::new();
    let rows = collect_rows(&[run(0, 0.9), run(1, 0.7)], &mut notes);
    assert_eq!(rows.len(), 2);
    assert_eq!(rows[0].0, "beso", "method order is kept");
    assert_eq!(rows[0].1.len(), 2);
    assert!(notes.is_empty());
    // The same seed twice: the later run wins, with a note.
    let rows = collect_rows(&[run(0, 0.9), run(0, 0.1)], &mut notes);
    assert_eq!(rows[0].1.len(), 1);
    assert_eq!(rows[0].1[0]["success_rate"], json!(0.1));
    assert_eq!(notes.len(), 2);
}

#[test]
fn missing_or_malformed_metrics_are_errors_with_their_source() {
    let root = std::env::temp_dir().join(format!("vdd-report-metrics-{}", std::process::id()));
    std::fs::create_dir_all(&root).unwrap();
    let err = read_metrics(&root).unwrap_err();
    assert!(matches!(&err, Error::Read { path, .. } if path == &root.join("metrics.json")));
    assert!(std::error::Error::source(&err).is_some());
    std::fs::write(root.join("metrics.json"), "{ not json").unwrap();
    assert!(matches!(read_metrics(&root), Err(Error::Parse { .. })));
    std::fs::remove_dir_all(&root).unwrap();
}
