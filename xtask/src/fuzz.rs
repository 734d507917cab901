//! `cargo xtask fuzz <target|all> --cases N --seed S --out DIR`: the runner of the mutation
//! fuzzer whose engine is the `vdd-fuzz` crate (targets, seed inputs, mutations, case logic,
//! outcomes and `fuzz.json`).
//!
//! Each case is written by `vdd_fuzz::prepare_case` and run in a child process (this binary,
//! hidden subcommand `fuzz-case`) with an address-space limit (`--memory-mib`), a CPU-time
//! limit and a wall-clock limit (`--timeout`, after which the child is killed: a `hang`),
//! `--jobs` children at a time. `DIR/fuzz.json` has the counts per target; the first crashing
//! inputs of each target and outcome are kept in `DIR/crashes/<target>-<outcome>-<case>/` with
//! the child's stderr, and `cargo xtask fuzz-case <target> <dir>` replays one. The recipe
//! target's check is xtask's (`tasks::check_toy_gmm`).

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use vdd_fuzz::{Counts, Outcome, Report, Target, TargetReport};

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

/// Crashing inputs kept per target and outcome.
const KEEP: usize = 5;

/// Runs one case in this process and exits with its outcome's code (0 ok, 1 err, 3
/// ok_nonfinite; a panic exits 101).
pub fn case(a: &CaseArgs) -> ! {
    limit(libc::RLIMIT_AS, a.memory_mib << 20);
    limit(libc::RLIMIT_CPU, a.cpu_seconds);
    let check_recipe = |path: &Path| -> XResult {
        crate::tasks::check_toy_gmm(&crate::recipe::read_recipe(path)?)
    };
    let run = a.target.parse().and_then(|t| vdd_fuzz::run_case(t, &a.dir, check_recipe));
    match run {
        Ok(loaded) => {
            if let vdd_fuzz::Loaded::NonFinite(what) = &loaded {
                eprintln!("non-finite output: {what}");
            }
            std::process::exit(loaded.exit_code())
        }
        Err(e) => {
            match std::error::Error::source(&e) {
                Some(source) => eprintln!("error: {e}: {source}"),
                None => eprintln!("error: {e}"),
            }
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
    let targets = match a.target.as_str() {
        "all" => Target::ALL.to_vec(),
        t => vec![t.parse::<Target>()?],
    };
    if a.jobs == 0 || !(a.timeout.is_finite() && a.timeout > 0.0) {
        return Err("--jobs must be positive and --timeout a positive number".into());
    }
    let work = a.out.join("work");
    let _ = std::fs::remove_dir_all(&work);
    std::fs::create_dir_all(&work)?;
    let started = Instant::now();
    let mut report = Report {
        seed: a.seed,
        cases_per_target: a.cases,
        timeout_seconds: a.timeout,
        memory_mib: a.memory_mib,
        jobs: a.jobs,
        seconds: 0.0,
        targets: Vec::new(),
        crashes: Vec::new(),
    };
    for target in targets {
        let t0 = Instant::now();
        let counts = campaign(a, target, &work, &mut report.crashes)?;
        progress::log(format!("{target:>12}: {}", counts.summary()));
        report.targets.push(TargetReport { target, counts, seconds: t0.elapsed().as_secs_f64() });
    }
    let _ = std::fs::remove_dir_all(&work);
    report.seconds = started.elapsed().as_secs_f64();
    std::fs::write(a.out.join("fuzz.json"), report.to_json())?;
    progress::log(format!("wrote {}", a.out.join("fuzz.json").display()));
    match report.failures() {
        0 => Ok(()),
        n => {
            Err(format!("{n} failing case(s); inputs in {}", a.out.join("crashes").display())
                .into())
        }
    }
}

/// A case running in a child.
struct Running {
    child: Child,
    started: Instant,
    case: usize,
    dir: PathBuf,
}

/// The cases of one target, `a.jobs` children at a time.
fn campaign(a: &Args, target: Target, work: &Path, crashes: &mut Vec<String>) -> XResult<Counts> {
    let seeds = vdd_fuzz::write_seeds(target, &work.join(format!("seeds-{target}")))?;
    let exe = std::env::current_exe()?;
    let mut counts = Counts::default();
    let bar = progress::bar(a.cases as u64, target.name());
    let mut slots: Vec<Option<Running>> = (0..a.jobs).map(|_| None).collect();
    let (mut next, mut done) = (0, 0);
    let timeout = Duration::from_secs_f64(a.timeout);
    while done < a.cases {
        for (k, slot) in slots.iter_mut().enumerate() {
            if slot.is_none() && next < a.cases {
                let dir = work.join(format!("case{k}"));
                vdd_fuzz::prepare_case(target, &seeds, a.seed, next, &dir)?;
                let stderr = std::fs::File::create(dir.join("stderr.txt"))?;
                let child = Command::new(&exe)
                    .args(["fuzz-case", target.name()])
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
                Some(status) => Outcome::from_exit_code(status.code()),
                None if r.started.elapsed() > timeout => {
                    let _ = r.child.kill();
                    let _ = r.child.wait();
                    Outcome::Hang
                }
                None => continue,
            };
            idle = false;
            counts.add(outcome);
            if outcome.is_failure() {
                let prefix = format!("{target}-{}-", outcome.name());
                if crashes.iter().filter(|c| c.starts_with(&prefix)).count() < KEEP {
                    let name = format!("{prefix}{}", r.case);
                    vdd_fuzz::copy_case(&r.dir, &a.out.join("crashes").join(&name))?;
                    crashes.push(name);
                }
                bar.set_message(format!("{} at case {}", outcome.name(), r.case));
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
