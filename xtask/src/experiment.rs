//! `cargo xtask experiment <recipe> [options]`: resolves a recipe and runs its task pipeline.
//!
//! ```text
//! cargo xtask experiment <recipe|path.toml> [--seed N | --seeds 0,1,2] [--methods a,b]
//!     [--set key.path=value]... [--quick] [--out DIR] [--fresh]
//! ```
//!
//! Results go to `--out DIR`, by default `results/<recipe>/<run>/` with `<run>` built from the
//! seeds (`seed0`, `seed0-1-2`), `-quick` under `--quick`, and a short hash of `--methods` /
//! `--set` overrides when there are any. A run directory holds `resolved.toml` (the full
//! configuration, enough to re-run it as a recipe), `run.json` (command, git revision and dirty
//! flag, wall time), `metrics.json`, `table.md` and the plots.

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
    /// The teacher cache directory.
    pub cache_dir: PathBuf,
    /// The VDD student cache directory ([`crate::student_cache`]).
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

    /// Writes `resolved.toml` into `dir` (created).
    pub fn write_resolved(&self, dir: &Path, resolved_toml: &str) -> crate::XResult {
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

/// Parsed command line of `experiment`.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct ExperimentArgs {
    /// Recipe name or path.
    pub recipe: String,
    /// Generic overrides.
    pub overrides: Overrides,
    /// `--out`.
    pub out: Option<PathBuf>,
    /// `--fresh`.
    pub fresh: bool,
    /// Task-specific shorthands (`--teacher`, `--iterations`, ...), translated by the task.
    pub shorthands: Vec<(String, String)>,
}

/// Options that take a value and are passed to the task as shorthands.
const SHORTHANDS: [&str; 5] = ["teacher", "iterations", "experts", "lr", "weighting"];

impl ExperimentArgs {
    /// Parses the words after `experiment`.
    pub fn parse(args: &[String]) -> Result<Self, String> {
        let mut it = args.iter();
        let recipe = it.next().filter(|a| !a.starts_with("--")).ok_or_else(|| {
            format!(
                "usage: cargo xtask experiment <recipe> [options]; recipes: {}",
                recipe::available_recipes().join(", ")
            )
        })?;
        let mut out = Self { recipe: recipe.clone(), ..Default::default() };
        while let Some(a) = it.next() {
            let key = a.strip_prefix("--").ok_or_else(|| format!("unexpected argument `{a}`"))?;
            let (key, inline) = match key.split_once('=') {
                Some((k, v)) if k != "set" => (k, Some(v.to_owned())),
                _ => (key, None),
            };
            let mut value = || -> Result<String, String> {
                match &inline {
                    Some(v) => Ok(v.clone()),
                    None => {
                        it.next().cloned().ok_or_else(|| format!("option --{key} needs a value"))
                    }
                }
            };
            match key {
                "quick" => out.overrides.quick = true,
                "fresh" => out.fresh = true,
                "seed" | "seeds" => out.overrides.seeds = Some(recipe::parse_seeds(&value()?)?),
                "methods" => {
                    let v = value()?;
                    out.overrides.methods = Some(
                        v.split(',')
                            .map(|m| m.trim().to_owned())
                            .filter(|m| !m.is_empty())
                            .collect(),
                    );
                }
                "out" => out.out = Some(PathBuf::from(value()?)),
                "set" => {
                    let v = value()?;
                    let (k, val) = v
                        .split_once('=')
                        .ok_or_else(|| format!("--set needs key.path=value, got `{v}`"))?;
                    out.overrides.sets.push((k.trim().to_owned(), val.trim().to_owned()));
                }
                k if SHORTHANDS.contains(&k) => {
                    let v = value()?;
                    out.shorthands.push((k.to_owned(), v));
                }
                other => return Err(format!("unknown option --{other}")),
            }
        }
        Ok(out)
    }
}

/// Runs the command; `args` are the words after `experiment`.
pub fn run(args: &[String]) -> crate::XResult {
    let started = Instant::now();
    let parsed = ExperimentArgs::parse(args)?;
    let path = recipe::recipe_path(&parsed.recipe)?;
    let file = recipe::read_recipe(&path)?;
    let name = file
        .get("name")
        .and_then(|v| v.as_str())
        .map(String::from)
        .or_else(|| path.file_stem().and_then(|s| s.to_str()).map(String::from))
        .unwrap_or_else(|| parsed.recipe.clone());
    let task = file
        .get("task")
        .and_then(|v| v.as_str())
        .ok_or_else(|| {
            format!("{} has no `task` key (toy-gmm, toy-conditional or avoiding)", path.display())
        })?
        .to_owned();
    let mut overrides = parsed.overrides.clone();
    crate::toy::apply_shorthands(&task, &parsed.shorthands, &mut overrides)?;
    let ctx = RunContext {
        name,
        file,
        overrides,
        out: parsed.out.clone(),
        fresh: parsed.fresh,
        cache_dir: recipe::repo_root().join("results").join("cache").join("teachers"),
        student_cache_dir: recipe::repo_root().join("results").join("cache").join("students"),
        command: std::iter::once("cargo xtask experiment".to_owned())
            .chain(args.iter().cloned())
            .collect::<Vec<_>>()
            .join(" "),
        started,
    };
    match task.as_str() {
        "toy-gmm" | "toy-conditional" => crate::toy::run_recipe(&ctx, &task),
        "avoiding" => crate::avoiding::run(&ctx),
        other => Err(format!(
            "unknown task `{other}` in {} (toy-gmm, toy-conditional or avoiding)",
            path.display()
        )
        .into()),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn args(s: &str) -> Vec<String> {
        s.split_whitespace().map(String::from).collect()
    }

    #[test]
    fn experiment_options_parse() {
        let a = ExperimentArgs::parse(&args(
            "avoiding --seeds 0,1,2 --methods vdd-beso,beso --set vdd.beso.iterations=10 --set a.b=c=d --quick --out /tmp/x --fresh --teacher ddpm",
        ))
        .unwrap();
        assert_eq!(a.recipe, "avoiding");
        assert_eq!(a.overrides.seeds, Some(vec![0, 1, 2]));
        assert_eq!(a.overrides.methods, Some(vec!["vdd-beso".to_owned(), "beso".to_owned()]));
        assert_eq!(
            a.overrides.sets,
            vec![("vdd.beso.iterations".into(), "10".into()), ("a.b".into(), "c=d".into())]
        );
        assert!(a.overrides.quick && a.fresh);
        assert_eq!(a.out, Some(PathBuf::from("/tmp/x")));
        assert_eq!(a.shorthands, vec![("teacher".to_owned(), "ddpm".to_owned())]);
        let b = ExperimentArgs::parse(&args("toy-gmm --seed=3")).unwrap();
        assert_eq!(b.overrides.seeds, Some(vec![3]));
        assert!(ExperimentArgs::parse(&args("--quick")).is_err());
        assert!(ExperimentArgs::parse(&args("x --bogus 1")).is_err());
        assert!(ExperimentArgs::parse(&args("x --seed")).is_err());
        assert!(ExperimentArgs::parse(&args("x --set novalue")).is_err());
    }

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
