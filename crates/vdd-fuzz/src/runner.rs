//! The campaign runner: every case of a target in a child process with an address-space
//! limit, a CPU-time limit and a wall-clock limit (after which the child is killed: a
//! [`Outcome::Hang`]), [`Campaign::jobs`] children at a time ([`run_campaign`]). The first
//! [`KEEP`] failing inputs of each target and outcome are kept in
//! `<out>/crashes/<target>-<outcome>-<case>/` with the child's `stderr.txt`.
//!
//! The child is the caller's program: `exe [prefix...] <target> <case dir> --memory-mib M
//! --cpu-seconds C`; it calls [`set_limits`], runs [`crate::run_case`] and exits with
//! [`crate::Loaded::exit_code`] (1 for a refused input; a panic exits 101).

use std::path::{Path, PathBuf};
use std::process::{Child, Command, Stdio};
use std::time::{Duration, Instant};

use crate::{Counts, Error, Outcome, Report, Target, TargetReport};

/// Failing inputs kept per target and outcome.
pub const KEEP: usize = 5;

/// The settings of a campaign.
#[derive(Debug, Clone, PartialEq)]
pub struct Campaign {
    /// Cases per target.
    pub cases: usize,
    /// Seed of the mutations.
    pub seed: u64,
    /// Output directory (`fuzz.json` is the caller's to write; `crashes/` and a temporary
    /// `work/` are the runner's).
    pub out: PathBuf,
    /// Seconds after which a case is a hang.
    pub timeout: f64,
    /// Address-space limit of a case, in MiB.
    pub memory_mib: u64,
    /// Cases run at a time.
    pub jobs: usize,
}

/// What the runner reports while it runs.
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum Progress<'a> {
    /// A target's `cases` cases start.
    Target(Target, usize),
    /// Case `case` of a target ended with an outcome.
    Case(Target, usize, Outcome),
    /// A target is done.
    Done(Target, &'a Counts),
}

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> Error + '_ {
    move |source| Error::Io { path: path.to_owned(), source }
}

/// Sets this process's address-space limit to `memory_mib` MiB and its CPU-time limit to
/// `cpu_seconds` (0: leave the limit alone). For the child of a case.
pub fn set_limits(memory_mib: u64, cpu_seconds: u64) {
    // The resources' type is the platform's (glibc's own enum type, a C int elsewhere).
    for (resource, value) in [(libc::RLIMIT_AS, memory_mib << 20), (libc::RLIMIT_CPU, cpu_seconds)]
    {
        if value > 0 {
            let lim = libc::rlimit { rlim_cur: value, rlim_max: value };
            // SAFETY: setrlimit reads the struct we pass and changes only this process's limits.
            unsafe { libc::setrlimit(resource, &lim) };
        }
    }
}

/// Runs the campaign `c` on `targets`, each case in a child `exe [prefix...] <target> <dir>
/// --memory-mib M --cpu-seconds C` (see the [module docs](self)), and returns its report.
pub fn run_campaign(
    c: &Campaign,
    targets: &[Target],
    exe: &Path,
    prefix: &[&str],
    progress: &mut dyn FnMut(Progress<'_>),
) -> Result<Report, Error> {
    if c.jobs == 0 || !(c.timeout.is_finite() && c.timeout > 0.0) {
        return Err(Error::Settings("jobs must be positive and the timeout a positive number"));
    }
    let work = c.out.join("work");
    let _ = std::fs::remove_dir_all(&work);
    std::fs::create_dir_all(&work).map_err(io(&work))?;
    let started = Instant::now();
    let mut report = Report {
        seed: c.seed,
        cases_per_target: c.cases,
        timeout_seconds: c.timeout,
        memory_mib: c.memory_mib,
        jobs: c.jobs,
        seconds: 0.0,
        targets: Vec::new(),
        crashes: Vec::new(),
    };
    for &target in targets {
        let t0 = Instant::now();
        progress(Progress::Target(target, c.cases));
        let counts = target_cases(c, target, &work, exe, prefix, &mut report.crashes, progress)?;
        progress(Progress::Done(target, &counts));
        report.targets.push(TargetReport { target, counts, seconds: t0.elapsed().as_secs_f64() });
    }
    let _ = std::fs::remove_dir_all(&work);
    report.seconds = started.elapsed().as_secs_f64();
    Ok(report)
}

/// A case running in a child.
struct Running {
    child: Child,
    started: Instant,
    case: usize,
    dir: PathBuf,
}

/// The cases of one target, `c.jobs` children at a time.
fn target_cases(
    c: &Campaign,
    target: Target,
    work: &Path,
    exe: &Path,
    prefix: &[&str],
    crashes: &mut Vec<String>,
    progress: &mut dyn FnMut(Progress<'_>),
) -> Result<Counts, Error> {
    let seeds = crate::write_seeds(target, &work.join(format!("seeds-{target}")))?;
    let mut counts = Counts::default();
    let mut slots: Vec<Option<Running>> = (0..c.jobs).map(|_| None).collect();
    let (mut next, mut done) = (0, 0);
    let timeout = Duration::from_secs_f64(c.timeout);
    while done < c.cases {
        for (k, slot) in slots.iter_mut().enumerate() {
            if slot.is_none() && next < c.cases {
                let dir = work.join(format!("case{k}"));
                crate::prepare_case(target, &seeds, c.seed, next, &dir)?;
                let stderr_path = dir.join("stderr.txt");
                let stderr = std::fs::File::create(&stderr_path).map_err(io(&stderr_path))?;
                let child = Command::new(exe)
                    .args(prefix)
                    .arg(target.name())
                    .arg(&dir)
                    .args(["--memory-mib", &c.memory_mib.to_string()])
                    .args(["--cpu-seconds", &(c.timeout.ceil() as u64 + 2).to_string()])
                    .stdin(Stdio::null())
                    .stdout(Stdio::null())
                    .stderr(stderr)
                    .spawn()
                    .map_err(io(exe))?;
                *slot = Some(Running { child, started: Instant::now(), case: next, dir });
                next += 1;
            }
        }
        let mut idle = true;
        for slot in slots.iter_mut() {
            let Some(r) = slot else { continue };
            let outcome = match r.child.try_wait().map_err(io(exe))? {
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
                    let to = c.out.join("crashes").join(&name);
                    crate::copy_case(&r.dir, &to).map_err(io(&to))?;
                    crashes.push(name);
                }
            }
            progress(Progress::Case(target, r.case, outcome));
            *slot = None;
            done += 1;
        }
        if idle {
            std::thread::sleep(Duration::from_millis(1));
        }
    }
    Ok(counts)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn campaign(name: &str, cases: usize, timeout: f64) -> Campaign {
        let out =
            std::env::temp_dir().join(format!("vdd-fuzz-runner-{name}-{}", std::process::id()));
        Campaign { cases, seed: 0, out, timeout, memory_mib: 0, jobs: 2 }
    }

    /// A campaign whose child is `sh -c script`.
    fn run(c: &Campaign, script: &str) -> (Report, Vec<Outcome>) {
        let mut seen = Vec::new();
        let mut progress = |p: Progress<'_>| {
            if let Progress::Case(_, _, o) = p {
                seen.push(o);
            }
        };
        let sh = Path::new("/bin/sh");
        let r = run_campaign(c, &[Target::Npy], sh, &["-c", script, "sh"], &mut progress).unwrap();
        (r, seen)
    }

    #[test]
    fn children_exit_codes_and_hangs_become_outcomes_and_failures_are_kept() {
        let c = campaign("panic", 7, 5.0);
        let (report, seen) = run(&c, "exit 101");
        assert_eq!(seen, vec![Outcome::Panic; 7]);
        assert_eq!(report.targets[0].counts.get(Outcome::Panic), 7);
        assert_eq!(report.crashes.len(), KEEP, "{:?}", report.crashes);
        assert!(c.out.join("crashes").join(&report.crashes[0]).join("stderr.txt").is_file());
        assert!(!c.out.join("work").exists());
        std::fs::remove_dir_all(&c.out).unwrap();

        let c = campaign("hang", 2, 0.2);
        let (report, seen) = run(&c, "sleep 1");
        assert_eq!(seen, vec![Outcome::Hang; 2]);
        assert_eq!(report.failures(), 2);
        std::fs::remove_dir_all(&c.out).unwrap();

        let c = campaign("ok", 3, 5.0);
        let (report, _) = run(&c, "exit 1");
        assert_eq!((report.failures(), report.crashes.len()), (0, 0));
        std::fs::remove_dir_all(&c.out).unwrap();

        let bad = Campaign { jobs: 0, ..campaign("bad", 1, 1.0) };
        let e = run_campaign(&bad, &[Target::Npy], Path::new("/bin/sh"), &[], &mut |_| {});
        assert!(matches!(e, Err(Error::Settings(_))));
    }
}
