//! What a task pipeline gets from `cargo xtask experiment`: the [`RunContext`] (recipe file,
//! overrides, output and cache directories) and the helpers every pipeline uses (stage timing,
//! parallel jobs, run names, `run.json`). A leaf module: it knows no task.
//!
//! A run directory is `--out DIR`, by default `results/<recipe>/<run>/` with `<run>` built from
//! the seeds (`seed0`, `seed0-1-2`), `-quick` under `--quick`, and a short hash of `--methods` /
//! `--set` overrides when there are any ([`run_name`]).

use std::path::{Path, PathBuf};
use std::time::Instant;

use serde_json::json;
use toml::Table;

use crate::recipe::{self, Overrides};

/// Everything a task pipeline needs to run a recipe.
#[derive(Debug, Clone)]
pub struct RunContext {
    /// The recipe's name (file stem).
    pub name: String,
    /// The recipe file's contents.
    pub file: Table,
    /// CLI overrides.
    pub overrides: Overrides,
    /// `--out`.
    pub out: Option<PathBuf>,
    /// `--fresh`: retrain cached teachers and students.
    pub fresh: bool,
    /// `--resume`: continue from the run directory's checkpoints.
    pub resume: bool,
    /// The teacher cache directory.
    pub cache_dir: PathBuf,
    /// The VDD student cache directory ([`vdd_moe::cache`]).
    pub student_cache_dir: PathBuf,
    /// The command line, for `run.json`.
    pub command: String,
    /// When the command started.
    pub started: Instant,
}

impl RunContext {
    /// The run directory for the resolved seeds.
    pub fn run_dir(&self, seeds: &[u64]) -> PathBuf {
        match &self.out {
            Some(o) => o.clone(),
            None => recipe::repo_root()
                .join("results")
                .join(&self.name)
                .join(run_name(seeds, &self.overrides)),
        }
    }

    /// Writes `resolved.toml` into `dir` (created; a directory this creates is removed again
    /// when the run fails, [`remove_created_run_dir`]).
    pub fn write_resolved(&self, dir: &Path, resolved_toml: &str) -> crate::XResult {
        if !dir.exists() {
            *CREATED.lock().unwrap_or_else(|e| e.into_inner()) = Some(dir.to_owned());
        }
        std::fs::create_dir_all(dir).map_err(|e| format!("creating {}: {e}", dir.display()))?;
        let header = format!(
            "# Resolved configuration of recipe `{}`.\n# Command: {}\n# Re-run: cargo xtask experiment {}/resolved.toml\n\n",
            self.name,
            self.command,
            dir.display()
        );
        vdd_nn::io::write_atomic(&dir.join("resolved.toml"), (header + resolved_toml).as_bytes())?;
        Ok(())
    }

    /// Writes `run.json` (command, git revision, wall time, `extra`) into `dir`.
    pub fn write_run_info(&self, dir: &Path, extra: serde_json::Value) -> crate::XResult {
        let (revision, dirty) = git_revision();
        let info = json!({
            "recipe": self.name,
            "command": self.command,
            "git": { "revision": revision, "dirty": dirty },
            "wall_seconds": self.started.elapsed().as_secs_f64(),
            "cpu_seconds": cpu_seconds(),
            "threads_available": std::thread::available_parallelism().map_or(1, |p| p.get()),
            "details": extra,
        });
        vdd_nn::io::write_atomic(
            &dir.join("run.json"),
            serde_json::to_string_pretty(&info)?.as_bytes(),
        )?;
        Ok(())
    }
}

static CREATED: std::sync::Mutex<Option<PathBuf>> = std::sync::Mutex::new(None);

/// Removes the run directory [`RunContext::write_resolved`] created, if any: a failed run
/// leaves nothing behind.
pub fn remove_created_run_dir() {
    if let Some(dir) = CREATED.lock().unwrap_or_else(|e| e.into_inner()).take() {
        let _ = std::fs::remove_dir_all(dir);
    }
}

/// Wall-clock seconds spent per pipeline stage (`data`, `teachers`, `students`, `rollouts`,
/// `timing`, `plots`), in first-use order, for the end-of-run summary and `run.json`.
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
            self.0.iter().map(|(s, t)| ((*s).to_owned(), crate::report::json_f64(*t))).collect();
        serde_json::Value::Object(m)
    }

    /// `teachers 85.2 s, students 40.1 s, ...`.
    pub fn summary(&self) -> String {
        self.0.iter().map(|(s, t)| format!("{s} {t:.1} s")).collect::<Vec<_>>().join(", ")
    }
}

/// Runs `f` on every item with up to `workers` threads (work-stealing by index) and returns the
/// results in item order, or the first error in item order. After a failure no new item starts.
pub fn parallel_map<T: Sync, R: Send>(
    items: &[T],
    workers: usize,
    f: impl Fn(&T) -> Result<R, String> + Sync,
) -> Result<Vec<R>, String> {
    use std::sync::Mutex;
    use std::sync::atomic::{AtomicBool, AtomicUsize, Ordering};
    let n = items.len();
    let workers = workers.clamp(1, n.max(1));
    if workers == 1 {
        return items.iter().map(&f).collect();
    }
    let next = AtomicUsize::new(0);
    let failed = AtomicBool::new(false);
    let slots: Vec<Mutex<Option<Result<R, String>>>> = (0..n).map(|_| Mutex::new(None)).collect();
    std::thread::scope(|s| {
        for _ in 0..workers {
            s.spawn(|| {
                while !failed.load(Ordering::Relaxed) {
                    let i = next.fetch_add(1, Ordering::Relaxed);
                    if i >= n {
                        break;
                    }
                    let r = f(&items[i]);
                    if r.is_err() {
                        failed.store(true, Ordering::Relaxed);
                    }
                    *slots[i].lock().unwrap_or_else(|e| e.into_inner()) = Some(r);
                }
            });
        }
    });
    let mut out = Vec::with_capacity(n);
    let mut skipped = false;
    for slot in slots {
        match slot.into_inner().unwrap_or_else(|e| e.into_inner()) {
            Some(Ok(v)) => out.push(v),
            Some(Err(e)) => return Err(e),
            None => skipped = true,
        }
    }
    if skipped {
        return Err("internal: a job was skipped without an error".into());
    }
    Ok(out)
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

/// `seed0`, `seed0-1-2`, `+ -quick`, `+ -o<hash>` when methods or `--set` were overridden.
pub fn run_name(seeds: &[u64], o: &Overrides) -> String {
    let list: Vec<String> = seeds.iter().map(u64::to_string).collect();
    let mut name = format!("seed{}", list.join("-"));
    if o.quick {
        name.push_str("-quick");
    }
    if o.has_config_overrides() {
        let key = format!("{:?}|{:?}", o.methods, o.sets);
        name.push_str(&format!("-o{:06x}", recipe::fnv1a(key.as_bytes()) & 0xff_ffff));
    }
    name
}

/// `(git rev-parse HEAD, working tree dirty)`, or `("unknown", None)` without git.
pub fn git_revision() -> (String, Option<bool>) {
    let root = recipe::repo_root();
    let run = |args: &[&str]| {
        std::process::Command::new("git")
            .args(args)
            .current_dir(&root)
            .output()
            .ok()
            .filter(|o| o.status.success())
            .map(|o| String::from_utf8_lossy(&o.stdout).trim().to_owned())
    };
    match run(&["rev-parse", "HEAD"]) {
        Some(rev) if !rev.is_empty() => {
            let dirty =
                run(&["status", "--porcelain", "--untracked-files=no"]).map(|s| !s.is_empty());
            (rev, dirty)
        }
        _ => ("unknown".into(), None),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn parallel_map_keeps_order_and_reports_the_first_error() {
        let items: Vec<u64> = (0..20).collect();
        for workers in [1, 2, 4] {
            let out = parallel_map(&items, workers, |&x| Ok(x * x)).unwrap();
            assert_eq!(out, items.iter().map(|x| x * x).collect::<Vec<_>>());
        }
        let e = parallel_map(&items, 1, |&x| if x >= 3 { Err(format!("bad {x}")) } else { Ok(x) });
        assert_eq!(e.unwrap_err(), "bad 3");
        let e = parallel_map(&items, 3, |&x| if x == 7 { Err("seven".to_owned()) } else { Ok(x) });
        assert_eq!(e.unwrap_err(), "seven");
        assert!(parallel_map(&Vec::<u8>::new(), 2, |&x| Ok(x)).unwrap().is_empty());
    }

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

    #[test]
    fn run_names_follow_seeds_and_overrides() {
        let mut o = Overrides::default();
        assert_eq!(run_name(&[0], &o), "seed0");
        assert_eq!(run_name(&[0, 1, 2], &o), "seed0-1-2");
        o.quick = true;
        assert_eq!(run_name(&[0], &o), "seed0-quick");
        o.sets.push(("a".into(), "1".into()));
        let n = run_name(&[0], &o);
        assert!(n.starts_with("seed0-quick-o") && n.len() == "seed0-quick-o".len() + 6, "{n}");
        o.sets[0].1 = "2".into();
        assert_ne!(run_name(&[0], &o), n);
    }
}
