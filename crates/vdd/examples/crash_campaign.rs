//! A kill -9 campaign against checkpointed VDD training.
//!
//! ```text
//! cargo run --release -p vdd --example crash_campaign -- [--kills 300] [--seed 1] [--out DIR]
//! ```
//!
//! A child process distils a 4-mode mixture into a mixture of experts with a learned gating
//! and a moving average, committing a checkpoint generation ([`vdd_nn::checkpoint`]) after
//! every iteration and resuming from the newest one when it starts. The campaign first runs one
//! child uninterrupted (the reference), then kills children with SIGKILL at random moments
//! (so many kills land inside a commit) and starts them again, until `--kills` kills happened.
//! It checks that
//!
//! * every restarted child resumes (no error from a half-written generation or a stale lock);
//! * no completed iteration is lost: a child resumes at or after the last generation the killed
//!   child reported as committed;
//! * every run that finishes ends bit-identical to the reference (a hash of every parameter);
//! * a second writer on a directory in use is refused.
//!
//! It prints the figures and exits 1 when any check fails.

use std::io::{BufRead, BufReader, Write};
use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::sync::mpsc;
use std::time::{Duration, Instant};

use rand::{Rng, SeedableRng};
use vdd::faer::Mat;
use vdd::{DistillData, GatingKind, Moe, MoeConfig, Vdd, VddConfig};
use vdd_core::gmm::{Gmm, GmmTeacher};
use vdd_nn::Parameters;
use vdd_nn::checkpoint::CheckpointDir;

const ITERATIONS: usize = 300;

type Result<T = ()> = std::result::Result<T, Box<dyn std::error::Error>>;

fn main() -> Result {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let value = |flag: &str| args.iter().position(|a| a == flag).and_then(|i| args.get(i + 1));
    if let Some(root) = value("--child") {
        return child(Path::new(root));
    }
    let kills: usize = value("--kills").map_or(Ok(300), |v| v.parse())?;
    let seed: u64 = value("--seed").map_or(Ok(1), |v| v.parse())?;
    let out = value("--out").map_or_else(
        || std::env::temp_dir().join(format!("vdd-crash-campaign-{}", std::process::id())),
        PathBuf::from,
    );
    campaign(kills, seed, &out)
}

/// The training a child runs (and resumes).
fn setup() -> Result<(VddConfig, GmmTeacher, MoeConfig, DistillData)> {
    let teacher = GmmTeacher::fixed(Gmm::circle(4, 2.0, 0.5, 0.0)?, 1);
    let mut mc = MoeConfig::toy(1, 2, 4);
    mc.experts_network.hidden_dim = 32;
    mc.gating = GatingKind::Learned;
    mc.gating_network.hidden_dim = 16;
    let config = VddConfig {
        iterations: ITERATIONS,
        batch_size: 16,
        vi_samples: 16,
        gating_batch_size: 32,
        student_ema: Some(0.95),
        seed: 7,
        ..VddConfig::toy()
    };
    Ok((config, teacher, mc, DistillData::from_states(Mat::zeros(16, 1))?))
}

/// One child: resume (or start), then step and commit a generation after every iteration,
/// reporting on stdout: `resumed I`, `begin I` before committing generation `I`, `ck I` after,
/// and `done HASH` at the end.
fn child(root: &Path) -> Result {
    let mut out = std::io::stdout();
    let store = match CheckpointDir::open(root) {
        Ok(s) => s,
        Err(e) => {
            eprintln!("{e}");
            std::process::exit(3);
        }
    };
    let (config, teacher, mc, data) = setup()?;
    let mut vdd = match store.latest()? {
        Some(_) => Vdd::resume(root, teacher, data)?,
        None => Vdd::from_config(config, teacher, mc, data)?,
    };
    writeln!(out, "resumed {}", vdd.iteration())?;
    while vdd.iteration() < ITERATIONS {
        vdd.step()?;
        let it = vdd.iteration();
        writeln!(out, "begin {it}")?;
        vdd.save_checkpoint(&store)?;
        writeln!(out, "ck {it}")?;
        out.flush()?;
    }
    writeln!(out, "done {:016x}", hash(&vdd.into_student()))?;
    Ok(())
}

/// FNV-1a of every parameter's name and bits.
fn hash(student: &Moe) -> u64 {
    let mut h = 0xcbf2_9ce4_8422_2325u64;
    let mut eat = |bytes: &[u8]| {
        for b in bytes {
            h = (h ^ u64::from(*b)).wrapping_mul(0x100_0000_01b3);
        }
    };
    student.visit_params("", &mut |name, p| {
        eat(name.as_bytes());
        p.value.iter().for_each(|v| eat(&v.to_bits().to_le_bytes()));
    });
    h
}

/// A running child and the lines it printed, arriving on a channel.
struct Child {
    proc: std::process::Child,
    lines: mpsc::Receiver<String>,
}

fn spawn(root: &Path) -> Result<Child> {
    let exe = std::env::current_exe()?;
    let mut proc = Command::new(exe)
        .args(["--child", &root.to_string_lossy()])
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()?;
    let stdout = proc.stdout.take().ok_or("no stdout")?;
    let (tx, lines) = mpsc::channel();
    std::thread::spawn(move || {
        for line in BufReader::new(stdout).lines().map_while(|l| l.ok()) {
            if tx.send(line).is_err() {
                break;
            }
        }
    });
    Ok(Child { proc, lines })
}

/// What a child did before it ended.
#[derive(Default, Debug)]
struct Seen {
    resumed: Option<usize>,
    committed: Option<usize>,
    in_commit: bool,
    done: Option<String>,
}

fn apply(seen: &mut Seen, line: &str) {
    let (tag, v) = line.split_once(' ').unwrap_or((line, ""));
    match tag {
        "resumed" => seen.resumed = v.parse().ok(),
        "begin" => seen.in_commit = true,
        "ck" => {
            seen.committed = v.parse().ok();
            seen.in_commit = false;
        }
        "done" => seen.done = Some(v.to_owned()),
        _ => {}
    }
}

/// Waits for a child to end (on its own or killed) and reads everything it printed.
fn finish(mut c: Child) -> Result<(Seen, std::process::ExitStatus, String)> {
    let status = c.proc.wait()?;
    let mut err = String::new();
    if let Some(mut e) = c.proc.stderr.take() {
        std::io::Read::read_to_string(&mut e, &mut err)?;
    }
    let mut seen = Seen::default();
    // The reader thread ends with the pipe.
    while let Ok(line) = c.lines.recv_timeout(Duration::from_secs(10)) {
        apply(&mut seen, &line);
    }
    Ok((seen, status, err))
}

fn campaign(kills: usize, seed: u64, out: &Path) -> Result {
    let _ = std::fs::remove_dir_all(out);
    std::fs::create_dir_all(out)?;
    // The reference: one uninterrupted run.
    let t0 = Instant::now();
    let (seen, status, err) = finish(spawn(&out.join("reference"))?)?;
    let reference = seen.done.ok_or_else(|| format!("the reference run failed: {status} {err}"))?;
    let duration = t0.elapsed();
    println!(
        "reference: {ITERATIONS} iterations in {:.2} s, hash {reference}",
        duration.as_secs_f64()
    );

    let mut failures: Vec<String> = Vec::new();
    // A second writer is refused while the first runs.
    let lock_root = out.join("lock");
    let mut first = spawn(&lock_root)?;
    while first.lines.recv_timeout(Duration::from_secs(60)).is_ok_and(|l| !l.starts_with("ck")) {}
    let (_, status, err) = finish(spawn(&lock_root)?)?;
    let refused = status.code() == Some(3) && err.contains("another writer");
    if !refused {
        failures.push(format!("a second writer was not refused: {status} {err}"));
    }
    first.proc.kill()?;
    first.proc.wait()?;

    let mut rng = rand::rngs::StdRng::seed_from_u64(seed);
    let (mut killed, mut in_commit, mut runs_finished, mut resumes, mut lost) = (0, 0, 0, 0, 0);
    let mut max_lost = 0;
    let mut run = 0;
    let mut root = out.join(format!("run-{run}"));
    let mut last_committed: Option<usize> = None;
    let max_delay = duration.as_secs_f64() / 4.0;
    while killed < kills {
        let mut c = spawn(&root)?;
        std::thread::sleep(Duration::from_secs_f64(rng.random_range(0.0..max_delay)));
        let ended = c.proc.try_wait()?.is_some();
        if !ended {
            c.proc.kill()?; // SIGKILL
            killed += 1;
        }
        let (seen, status, err) = finish(c)?;
        if !ended && seen.in_commit {
            in_commit += 1;
        }
        if ended && seen.done.is_none() {
            failures.push(format!("{}: the child failed: {status} {err}", root.display()));
        }
        if let Some(r) = seen.resumed {
            resumes += 1;
            let floor = last_committed.unwrap_or(0);
            if r < floor {
                lost += 1;
                max_lost = max_lost.max(floor - r);
                failures.push(format!(
                    "{}: resumed at {r} after {floor} was committed",
                    root.display()
                ));
            }
        }
        if let Some(c) = seen.committed {
            last_committed = Some(c);
        }
        if let Some(h) = seen.done {
            runs_finished += 1;
            if h != reference {
                failures.push(format!("{}: ended with hash {h}, not {reference}", root.display()));
            }
            run += 1;
            root = out.join(format!("run-{run}"));
            last_committed = None;
        }
    }
    // Let the last interrupted run finish.
    let (seen, status, err) = finish(spawn(&root)?)?;
    match seen.done {
        Some(h) if h == reference => runs_finished += 1,
        other => failures.push(format!("the last run ended with {other:?}: {status} {err}")),
    }
    if seen.resumed.is_some_and(|r| r < last_committed.unwrap_or(0)) {
        lost += 1;
    }
    println!(
        "kills: {killed} (seed {seed}; {in_commit} during a checkpoint commit); resumes: {resumes}; \
         lost checkpointed iterations: {lost} (largest {max_lost}); runs finished: {runs_finished}, \
         all bit-identical to the reference: {}; second writer refused: {refused}",
        failures.iter().all(|f| !f.contains("hash"))
    );
    if failures.is_empty() {
        std::fs::remove_dir_all(out)?;
        println!("PASS");
        Ok(())
    } else {
        for f in &failures {
            println!("FAIL {f}");
        }
        std::process::exit(1);
    }
}
