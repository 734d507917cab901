//! Outcomes of cases, counts per target and the campaign's `fuzz.json`.

use std::collections::BTreeMap;

use serde_json::json;

use crate::Target;

/// Exit code of a case that loaded and returned a non-finite output.
pub(crate) const EXIT_NONFINITE: i32 = 3;
/// Exit code of a case whose writer committed a file its own loader then refused.
pub(crate) const EXIT_UNREADABLE: i32 = 4;
/// Exit code of a lock race with the wrong number of holders.
pub(crate) const EXIT_LOCK_HOLDERS: i32 = 5;

/// How one case ended.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Hash)]
pub enum Outcome {
    /// Loaded and used; every output finite (exit 0).
    Ok,
    /// A clean error (exit 1).
    Err,
    /// A panic (exit 101).
    Panic,
    /// Killed by a signal or another exit code (e.g. an allocation over the memory limit).
    Abort,
    /// Over the time limit (decided and killed by the runner).
    Hang,
    /// Loaded, and use returned a non-finite number without an error (exit 3).
    OkNonfinite,
    /// A writer committed a file (e.g. an importer's teacher) that its loader refused: the
    /// round trip "whatever a writer commits, its loader accepts" broken (exit 4).
    Unreadable,
    /// A lock race ([`Target::Lock`](crate::Target::Lock)) with the wrong number of holders:
    /// two writers held one checkpoint lock at once, a writer took a live writer's lock, or
    /// neither of two writers got a free lock (exit 5).
    LockHolders,
}

impl Outcome {
    /// Every outcome, in report order.
    pub const ALL: [Outcome; 8] = [
        Outcome::Ok,
        Outcome::Err,
        Outcome::Panic,
        Outcome::Abort,
        Outcome::Hang,
        Outcome::OkNonfinite,
        Outcome::Unreadable,
        Outcome::LockHolders,
    ];

    /// The outcome's name in `fuzz.json`.
    pub fn name(self) -> &'static str {
        match self {
            Outcome::Ok => "ok",
            Outcome::Err => "err",
            Outcome::Panic => "panic",
            Outcome::Abort => "abort",
            Outcome::Hang => "hang",
            Outcome::OkNonfinite => "ok_nonfinite",
            Outcome::Unreadable => "unreadable",
            Outcome::LockHolders => "lock_holders",
        }
    }

    /// The outcome of a child that exited with `code` (`None`: killed by a signal).
    pub fn from_exit_code(code: Option<i32>) -> Outcome {
        match code {
            Some(0) => Outcome::Ok,
            Some(1) => Outcome::Err,
            Some(EXIT_NONFINITE) => Outcome::OkNonfinite,
            Some(EXIT_UNREADABLE) => Outcome::Unreadable,
            Some(EXIT_LOCK_HOLDERS) => Outcome::LockHolders,
            Some(101) => Outcome::Panic,
            _ => Outcome::Abort,
        }
    }

    /// Whether the outcome is a bug: anything but `ok` and `err`.
    pub fn is_failure(self) -> bool {
        !matches!(self, Outcome::Ok | Outcome::Err)
    }
}

/// Cases per outcome.
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct Counts([usize; 8]);

impl Counts {
    /// Counts one case.
    pub fn add(&mut self, outcome: Outcome) {
        self.0[outcome as usize] += 1;
    }

    /// The cases that ended with `outcome`.
    pub fn get(&self, outcome: Outcome) -> usize {
        self.0[outcome as usize]
    }

    /// The failing cases ([`Outcome::is_failure`]).
    pub fn failures(&self) -> usize {
        Outcome::ALL.iter().filter(|o| o.is_failure()).map(|o| self.get(*o)).sum()
    }

    /// One line: `ok N, err N, panic N, ...`.
    pub fn summary(&self) -> String {
        let parts: Vec<String> =
            Outcome::ALL.iter().map(|o| format!("{} {}", o.name(), self.get(*o))).collect();
        parts.join(", ")
    }
}

/// The counts of one target.
#[derive(Debug, Clone, PartialEq)]
pub struct TargetReport {
    /// The target.
    pub target: Target,
    /// Cases per outcome.
    pub counts: Counts,
    /// Wall-clock seconds of the target's cases.
    pub seconds: f64,
}

/// A campaign's settings and results, as written to `fuzz.json`.
#[derive(Debug, Clone, PartialEq)]
pub struct Report {
    /// Seed of the mutations.
    pub seed: u64,
    /// Cases per target.
    pub cases_per_target: usize,
    /// Seconds after which a case was a hang.
    pub timeout_seconds: f64,
    /// Address-space limit of a case, in MiB.
    pub memory_mib: u64,
    /// Cases run at a time.
    pub jobs: usize,
    /// Wall-clock seconds of the campaign.
    pub seconds: f64,
    /// The targets run.
    pub targets: Vec<TargetReport>,
    /// Names of the kept crashing cases (`<target>-<outcome>-<case>`).
    pub crashes: Vec<String>,
}

impl Report {
    /// The failing cases over every target.
    pub fn failures(&self) -> usize {
        self.targets.iter().map(|t| t.counts.failures()).sum()
    }

    /// `fuzz.json`: the settings, and per target (by name) each outcome's count and the seconds.
    pub fn to_json(&self) -> String {
        let targets: BTreeMap<&str, BTreeMap<&str, serde_json::Value>> = self
            .targets
            .iter()
            .map(|t| {
                let mut row: BTreeMap<&str, serde_json::Value> =
                    Outcome::ALL.iter().map(|o| (o.name(), json!(t.counts.get(*o)))).collect();
                row.insert("seconds", json!(t.seconds));
                (t.target.name(), row)
            })
            .collect();
        let out = json!({
            "seed": self.seed,
            "cases_per_target": self.cases_per_target,
            "timeout_seconds": self.timeout_seconds,
            "memory_mib": self.memory_mib,
            "jobs": self.jobs,
            "seconds": self.seconds,
            "targets": targets,
            "crashes": self.crashes,
        });
        serde_json::to_string_pretty(&out).unwrap_or_else(|_| out.to_string())
    }
}
