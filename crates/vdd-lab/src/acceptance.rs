//! The Avoiding acceptance of the distilled students against their teachers: success rate at
//! least 0.90, task entropy at least 0.70, success within 0.05 of the teacher's and at least
//! 10x faster per action ([`avoiding_acceptance`]).

use vdd_report::metrics::{Row, mean_std};

/// One line per VDD method in `rows` (`vdd-beso`, `vdd-ddpm`) that has success rate, task
/// entropy and µs per action: its means over seeds against the bars and, when its teacher
/// (`beso`, `ddpm`) is in `rows` too, against the teacher's success rate and speed.
pub fn avoiding_acceptance(rows: &[(String, Vec<Row>)]) -> Vec<String> {
    let mean = |label: &str, key: &str| -> Option<f64> {
        let (_, r) = rows.iter().find(|(l, _)| l == label)?;
        let xs: Vec<f64> = r.iter().filter_map(|x| x.get(key)?.as_f64()).collect();
        (!xs.is_empty()).then(|| mean_std(&xs).0)
    };
    let yes = |b: bool| if b { "yes" } else { "NO" };
    let mut lines = Vec::new();
    for (vdd, teacher) in [("vdd-beso", "beso"), ("vdd-ddpm", "ddpm")] {
        let (Some(vs), Some(ve), Some(vu)) =
            (mean(vdd, "success_rate"), mean(vdd, "task_entropy"), mean(vdd, "us_per_action"))
        else {
            continue;
        };
        let mut line = format!(
            "{vdd}: success {vs:.3} (>= 0.90: {}), entropy {ve:.3} (>= 0.70: {})",
            yes(vs >= 0.90),
            yes(ve >= 0.70)
        );
        if let (Some(ts), Some(tu)) =
            (mean(teacher, "success_rate"), mean(teacher, "us_per_action"))
        {
            line.push_str(&format!(
                "; {teacher} success {ts:.3} (within 0.05: {}); speed-up {:.1}x (>= 10x: {})",
                yes(vs >= ts - 0.05),
                tu / vu,
                yes(tu / vu >= 10.0)
            ));
        }
        lines.push(line);
    }
    lines
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use super::*;

    fn row(sr: f64, te: f64, us: f64) -> Row {
        json!({"success_rate": sr, "task_entropy": te, "us_per_action": us})
            .as_object()
            .unwrap()
            .clone()
    }

    #[test]
    fn students_are_held_to_the_bars_and_their_teachers() {
        let rows = vec![
            ("beso".to_owned(), vec![row(0.95, 0.8, 1000.0)]),
            ("vdd-beso".to_owned(), vec![row(0.92, 0.8, 50.0), row(0.90, 0.7, 50.0)]),
            ("vdd-ddpm".to_owned(), vec![row(0.5, 0.75, 50.0)]),
        ];
        let lines = avoiding_acceptance(&rows);
        assert_eq!(lines.len(), 2);
        assert_eq!(
            lines[0],
            "vdd-beso: success 0.910 (>= 0.90: yes), entropy 0.750 (>= 0.70: yes); beso success \
             0.950 (within 0.05: yes); speed-up 20.0x (>= 10x: yes)"
        );
        assert_eq!(lines[1], "vdd-ddpm: success 0.500 (>= 0.90: NO), entropy 0.750 (>= 0.70: yes)");
        assert!(avoiding_acceptance(&rows[..1]).is_empty());
    }
}
