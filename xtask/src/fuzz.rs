//! `cargo xtask fuzz <target|all> --cases N --seed S --out DIR`: the mutation fuzzer of the
//! `vdd-fuzz` crate (targets, seed inputs, mutations, case logic, outcomes, `fuzz.json` and the
//! runner, [`vdd_fuzz::runner`]).
//!
//! Each case runs in a child process (this binary, hidden subcommand `fuzz-case`) with an
//! address-space limit (`--memory-mib`), a CPU-time limit and a wall-clock limit (`--timeout`,
//! after which the child is killed: a `hang`), `--jobs` children at a time. `DIR/fuzz.json`
//! has the counts per target; the first crashing inputs of each target and outcome are kept in
//! `DIR/crashes/<target>-<outcome>-<case>/` with the child's stderr, and `cargo xtask
//! fuzz-case <target> <dir>` replays one. The recipe target's check is xtask's
//! (`tasks::check_toy_gmm`).

use std::path::{Path, PathBuf};

use vdd_fuzz::Target;
use vdd_fuzz::runner::{Campaign, Progress, run_campaign, set_limits};

use crate::XResult;
use crate::progress;

/// Options of `cargo xtask fuzz`.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// npy, npz, safetensors, moe, teacher, checkpoint, recipe, lerobot, diffusion-policy, beso,
    /// lock, or all.
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

/// Runs one case in this process and exits with its outcome's code (0 ok, 1 err, 3
/// ok_nonfinite, 4 unreadable, 5 lock_holders; a panic exits 101).
pub fn case(a: &CaseArgs) -> ! {
    set_limits(a.memory_mib, a.cpu_seconds);
    let check_recipe = |path: &Path| -> XResult {
        Ok(vdd_lab::tasks::check_toy_gmm(&vdd_lab::recipe::read_recipe(path)?)?)
    };
    let run = a.target.parse().and_then(|t| vdd_fuzz::run_case(t, &a.dir, check_recipe));
    match run {
        Ok(loaded) => {
            match &loaded {
                vdd_fuzz::Loaded::NonFinite(what) => eprintln!("non-finite output: {what}"),
                vdd_fuzz::Loaded::Unreadable(what) => eprintln!("committed but unreadable: {what}"),
                vdd_fuzz::Loaded::LockHolders(what) => eprintln!("lock race: {what}"),
                vdd_fuzz::Loaded::Finite => {}
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

/// Runs the campaign ([`vdd_fuzz::runner::run_campaign`]) and writes `fuzz.json`.
pub fn run(a: &Args) -> XResult {
    let targets = match a.target.as_str() {
        "all" => Target::ALL.to_vec(),
        t => vec![t.parse::<Target>()?],
    };
    let (cases, seed, out, timeout) = (a.cases, a.seed, a.out.clone(), a.timeout);
    let c = Campaign { cases, seed, out, timeout, memory_mib: a.memory_mib, jobs: a.jobs };
    let mut bar = None;
    let mut show = |p: Progress<'_>| match p {
        Progress::Target(t, n) => bar = Some(progress::bar(n as u64, t.name())),
        Progress::Case(_, case, outcome) => {
            let Some(bar) = &bar else { return };
            if outcome.is_failure() {
                bar.set_message(format!("{} at case {case}", outcome.name()));
            }
            bar.inc(1);
        }
        Progress::Done(t, counts) => {
            if let Some(b) = bar.take() {
                b.finish_and_clear();
            }
            progress::log(format!("{t:>12}: {}", counts.summary()));
        }
    };
    let exe = std::env::current_exe()?;
    let report = run_campaign(&c, &targets, &exe, &["fuzz-case"], &mut show)?;
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
