//! Where a run's time went: wall-clock seconds per stage ([`StageTimes`]) and the CPU seconds
//! of the process ([`cpu_seconds`]), for a run's summary line and its `run.json`.

use std::time::Instant;

use crate::metrics::json_f64;

/// Wall-clock seconds spent per pipeline stage (`data`, `teachers`, `students`, `rollouts`,
/// `timing`, `plots`), in first-use order.
#[derive(Debug, Clone, Default)]
pub struct StageTimes(Vec<(&'static str, f64)>);

impl StageTimes {
    /// Adds `seconds` to `stage`.
    pub fn add(&mut self, stage: &'static str, seconds: f64) {
        match self.0.iter_mut().find(|(s, _)| *s == stage) {
            Some((_, t)) => *t += seconds,
            None => self.0.push((stage, seconds)),
        }
    }

    /// Runs `f`, adding its wall-clock time to `stage`.
    pub fn time<T>(&mut self, stage: &'static str, f: impl FnOnce() -> T) -> T {
        let t0 = Instant::now();
        let out = f();
        self.add(stage, t0.elapsed().as_secs_f64());
        out
    }

    /// `{ "stage": seconds, ... }`.
    pub fn to_json(&self) -> serde_json::Value {
        let m: serde_json::Map<String, serde_json::Value> =
            self.0.iter().map(|(s, t)| ((*s).to_owned(), json_f64(*t))).collect();
        serde_json::Value::Object(m)
    }

    /// `teachers 85.2 s, students 40.1 s, ...`.
    pub fn summary(&self) -> String {
        self.0.iter().map(|(s, t)| format!("{s} {t:.1} s")).collect::<Vec<_>>().join(", ")
    }
}

/// CPU seconds (user + system) used by this process so far, from `/proc/self/stat` (Linux;
/// `None` elsewhere). With other jobs on the machine, wall-clock times are inflated; CPU time
/// is not (but it sums over threads).
pub fn cpu_seconds() -> Option<f64> {
    let stat = std::fs::read_to_string("/proc/self/stat").ok()?;
    // Fields after the parenthesised command name; utime and stime are fields 14 and 15.
    let rest = &stat[stat.rfind(')')? + 2..];
    let f: Vec<&str> = rest.split_whitespace().collect();
    let ticks = f.get(11)?.parse::<f64>().ok()? + f.get(12)?.parse::<f64>().ok()?;
    // USER_HZ is 100 on every Linux configuration in practice.
    Some(ticks / 100.0)
}

#[cfg(test)]
mod tests {
    use serde_json::json;

    use super::*;

    #[test]
    fn stage_times_accumulate_in_first_use_order() {
        let mut st = StageTimes::default();
        st.add("teachers", 1.0);
        st.add("students", 2.0);
        st.add("teachers", 0.5);
        assert_eq!(st.summary(), "teachers 1.5 s, students 2.0 s");
        assert_eq!(st.to_json(), json!({"teachers": 1.5, "students": 2.0}));
        assert_eq!(st.time("plots", || 7), 7);
        assert!(st.to_json().get("plots").is_some());
        if let Some(c) = cpu_seconds() {
            assert!(c >= 0.0 && c.is_finite());
        }
    }
}
