//! `cargo xtask fuzz <target|all> --cases N --seed S --out DIR`: a mutation fuzzer of the
//! workspace's file loaders.
//!
//! Each target ([`targets::TARGETS`]: `npy`, `npz`, `safetensors`, `moe`, `teacher`,
//! `checkpoint`, `recipe`) starts from valid files the fuzzer writes itself, mutates a copy per
//! case with a stream of `S` indexed by the case ([`mutate`]: bit flips, interesting bytes and
//! floats, truncation, extension, header and JSON/TOML field edits with huge, negative,
//! non-finite and `1e39` values, shape and dtype edits), and runs it in a child process (this
//! binary, hidden subcommand `fuzz-case`) with an address-space limit (`--memory-mib`) and a
//! wall-clock limit (`--timeout`). A child that loads the input also uses it (acts, scores,
//! runs a training step) and checks the outputs. Outcomes: `ok`, `err` (a clean error),
//! `panic` (exit 101), `abort` (killed by a signal, e.g. an allocation over the limit),
//! `hang` (over the time limit), `ok_nonfinite` (loaded, and use returned a non-finite number).
//! `DIR/fuzz.json` has the counts per target; the first crashing inputs of each target and
//! outcome are kept in `DIR/crashes/<target>-<case>/` with the child's stderr, and
//! `cargo xtask fuzz-case <target> <dir>` replays one.

mod mutate;
mod targets;

use std::collections::BTreeMap;
use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use serde_json::json;

use crate::XResult;
use crate::progress;

/// Options of `cargo xtask fuzz`.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// npy, npz, safetensors, moe, teacher, checkpoint, recipe, or all.
    pub target: String,
    /// Cases per target.
    #[arg(long, default_value_t = 1000)]
    pub cases: usize,
    /// Seed of the mutations.
    #[arg(long, default_value_t = 0)]
    pub seed: u64,
    /// Output directory (fuzz.json, crashes/).
    #[arg(long, default_value = "results/fuzz")]
    pub out: PathBuf,
    /// Seconds after which a case is a hang.
    #[arg(long, default_value_t = 5.0)]
    pub timeout: f64,
    /// Address-space limit of a case, in MiB.
    #[arg(long, default_value_t = 2048)]
    pub memory_mib: u64,
    /// Cases run at a time.
    #[arg(long, default_value_t = 2)]
    pub jobs: usize,
}

/// Options of the hidden `cargo xtask fuzz-case` (one case, in the child).
#[derive(Debug, Clone, clap::Args)]
pub struct CaseArgs {
    /// The target.
    pub target: String,
    /// The case directory.
    pub dir: PathBuf,
    /// Address-space limit, in MiB (0: none).
    #[arg(long, default_value_t = 0)]
    pub memory_mib: u64,
    /// CPU-time limit in seconds (0: none).
    #[arg(long, default_value_t = 0)]
    pub cpu_seconds: u64,
}

/// Exit code of a case that loaded and returned a non-finite output.
const EXIT_NONFINITE: i32 = 3;
/// Crashing inputs kept per target and outcome.
const KEEP: usize = 5;
const OUTCOMES: [&str; 6] = ["ok", "err", "panic", "abort", "hang", "ok_nonfinite"];

/// Runs one case in this process and exits with its outcome's code (0 ok, 1 err, 3
/// ok_nonfinite; a panic exits 101).
pub fn case(a: &CaseArgs) -> ! {
    limit(libc::RLIMIT_AS, a.memory_mib << 20);
    limit(libc::RLIMIT_CPU, a.cpu_seconds);
    match targets::run_case(&a.target, &a.dir) {
        Ok(targets::Loaded::Finite) => std::process::exit(0),
        Ok(targets::Loaded::NonFinite(what)) => {
            eprintln!("non-finite output: {what}");
            std::process::exit(EXIT_NONFINITE)
        }
        Err(e) => {
            eprintln!("error: {e}");
            std::process::exit(1)
        }
    }
}

fn limit(resource: libc::__rlimit_resource_t, value: u64) {
    if value > 0 {
        let lim = libc::rlimit { rlim_cur: value, rlim_max: value };
        // SAFETY: setrlimit reads the struct we pass and changes only this process's limits.
        unsafe { libc::setrlimit(resource, &lim) };
    }
}

/// Runs the campaign.
pub fn run(a: &Args) -> XResult {
    let names: Vec<&'static str> = match a.target.as_str() {
        "all" => targets::TARGETS.to_vec(),
        t => match targets::TARGETS.iter().find(|n| **n == t) {
            Some(n) => vec![*n],
            None => {
                let all = targets::TARGETS.join(", ");
                return Err(format!("unknown fuzz target `{t}` ({all}, all)").into());
            }
        },
    };
    if a.jobs == 0 || !(a.timeout.is_finite() && a.timeout > 0.0) {
        return Err("--jobs must be positive and --timeout a positive number".into());
    }
    let work = a.out.join("work");
    let _ = std::fs::remove_dir_all(&work);
    std::fs::create_dir_all(&work)?;
    let started = Instant::now();
    let mut report = BTreeMap::new();
    let mut crashes = Vec::new();
    for target in names {
        let t0 = Instant::now();
        let counts = campaign(a, target, &work, &mut crashes)?;
        let mut row: BTreeMap<&str, serde_json::Value> =
            counts.iter().map(|(k, v)| (*k, json!(v))).collect();
        row.insert("seconds", json!(t0.elapsed().as_secs_f64()));
        progress::log(format!("{target:>12}: {}", summary(&counts)));
        report.insert(target, row);
    }
    let _ = std::fs::remove_dir_all(&work);
    let out = json!({
        "seed": a.seed,
        "cases_per_target": a.cases,
        "timeout_seconds": a.timeout,
        "memory_mib": a.memory_mib,
        "jobs": a.jobs,
        "seconds": started.elapsed().as_secs_f64(),
        "targets": report,
        "crashes": crashes,
    });
    std::fs::write(a.out.join("fuzz.json"), serde_json::to_string_pretty(&out)?)?;
    progress::log(format!("wrote {}", a.out.join("fuzz.json").display()));
    let bad: usize = report
        .values()
        .flat_map(|row| ["panic", "abort", "hang", "ok_nonfinite"].map(|k| row[k].as_u64()))
        .map(|n| n.unwrap_or(0) as usize)
        .sum();
    match bad {
        0 => Ok(()),
        n => {
            Err(format!("{n} failing case(s); inputs in {}", a.out.join("crashes").display())
                .into())
        }
    }
}

fn summary(counts: &BTreeMap<&'static str, usize>) -> String {
    OUTCOMES.iter().map(|k| format!("{k} {}", counts[k])).collect::<Vec<_>>().join(", ")
}

/// A case running in a child.
struct Running {
    child: Child,
    started: Instant,
    case: usize,
    dir: PathBuf,
}

/// The cases of one target, `a.jobs` children at a time.
fn campaign(
    a: &Args,
    target: &'static str,
    work: &Path,
    crashes: &mut Vec<String>,
) -> XResult<BTreeMap<&'static str, usize>> {
    let seeds = targets::write_seeds(target, &work.join(format!("seeds-{target}")))?;
    let exe = std::env::current_exe()?;
    let mut counts: BTreeMap<&'static str, usize> = OUTCOMES.iter().map(|k| (*k, 0)).collect();
    let bar = progress::bar(a.cases as u64, target);
    let mut slots: Vec<Option<Running>> = (0..a.jobs).map(|_| None).collect();
    let (mut next, mut done) = (0, 0);
    let timeout = Duration::from_secs_f64(a.timeout);
    while done < a.cases {
        for (k, slot) in slots.iter_mut().enumerate() {
            if slot.is_none() && next < a.cases {
                let dir = work.join(format!("case{k}"));
                let _ = std::fs::remove_dir_all(&dir);
                let mut rng = vdd_core::Seeds::new(a.seed)
                    .stream_indexed(&format!("fuzz-{target}"), next as u64);
                copy_dir(&seeds[rand::Rng::random_range(&mut rng, 0..seeds.len())], &dir)?;
                targets::mutate_case(target, &dir, &mut rng)?;
                let stderr = std::fs::File::create(dir.join("stderr.txt"))?;
                let child = Command::new(&exe)
                    .args(["fuzz-case", target])
                    .arg(&dir)
                    .args(["--memory-mib", &a.memory_mib.to_string()])
                    .args(["--cpu-seconds", &(a.timeout.ceil() as u64 + 2).to_string()])
                    .stdin(Stdio::null())
                    .stdout(Stdio::null())
                    .stderr(stderr)
                    .spawn()?;
                *slot = Some(Running { child, started: Instant::now(), case: next, dir });
                next += 1;
            }
        }
        let mut idle = true;
        for slot in slots.iter_mut() {
            let Some(r) = slot else { continue };
            let outcome = match r.child.try_wait()? {
                Some(status) => classify(status),
                None if r.started.elapsed() > timeout => {
                    let _ = r.child.kill();
                    let _ = r.child.wait();
                    "hang"
                }
                None => continue,
            };
            idle = false;
            *counts.get_mut(outcome).ok_or("internal: unknown outcome")? += 1;
            if !matches!(outcome, "ok" | "err") {
                let kept =
                    crashes.iter().filter(|c| c.starts_with(&format!("{target}-{outcome}-")));
                if kept.count() < KEEP {
                    let name = format!("{target}-{outcome}-{}", r.case);
                    copy_dir(&r.dir, &a.out.join("crashes").join(&name))?;
                    crashes.push(name);
                }
                bar.set_message(format!("{outcome} at case {}", r.case));
            }
            *slot = None;
            done += 1;
            bar.inc(1);
        }
        if idle {
            std::thread::sleep(Duration::from_millis(1));
        }
    }
    bar.finish_and_clear();
    Ok(counts)
}

fn classify(status: std::process::ExitStatus) -> &'static str {
    match status.code() {
        Some(0) => "ok",
        Some(1) => "err",
        Some(EXIT_NONFINITE) => "ok_nonfinite",
        Some(101) => "panic",
        _ => "abort",
    }
}

fn copy_dir(from: &Path, to: &Path) -> XResult {
    std::fs::create_dir_all(to)?;
    for e in std::fs::read_dir(from)? {
        let e = e?;
        if e.file_type()?.is_file() {
            std::fs::copy(e.path(), to.join(e.file_name()))?;
        }
    }
    Ok(())
}
