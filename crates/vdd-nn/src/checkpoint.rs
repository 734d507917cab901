//! Crash-safe checkpoint directories: numbered generations, an atomically replaced pointer to
//! the newest complete one, and a lock against a second writer.
//!
//! A [`CheckpointDir`] `root` holds
//!
//! * `gen-<N>/`: one generation, the files a trainer writes for its state after `N` steps;
//! * `LATEST`: the name of the newest complete generation, replaced atomically (written to a
//!   temporary file, fsynced, renamed, and the directory fsynced) after every file of the
//!   generation and the generation directory itself have been fsynced;
//! * `LOCK`: the process id (and start time) of the writer, created exclusively.
//!
//! A crash (even `kill -9`, or a power cut once the data reached the disk) at any point leaves
//! `LATEST` naming a complete generation, or no `LATEST` when none was completed: the pointer
//! only ever moves to a generation that is complete on disk. Older generations are pruned, the
//! newest [`KEEP`] kept. A lock left by a process that no longer runs (on Linux: its pid is gone,
//! a zombie, or a different process with the same pid) is taken over; a live owner is an
//! error ([`NnError::Locked`]).

use std::fs::{self, File, OpenOptions};
use std::io::Write;
use std::path::{Path, PathBuf};

use crate::error::NnError;

/// Generations kept after a new one is complete: it and the previous complete one.
pub const KEEP: usize = 2;

const POINTER: &str = "LATEST";
const LOCK: &str = "LOCK";
const PREFIX: &str = "gen-";

fn io(path: &Path) -> impl FnOnce(std::io::Error) -> NnError + '_ {
    move |source| NnError::Io { path: path.to_owned(), source }
}

/// A checkpoint directory opened for writing: the lock is held until it is dropped.
///
/// ```
/// use vdd_nn::checkpoint::CheckpointDir;
/// let root = std::env::temp_dir().join(format!("vdd-ck-doc-{}", std::process::id()));
/// let ck = CheckpointDir::open(&root)?;
/// assert!(CheckpointDir::open(&root).is_err(), "a second writer is refused");
/// for step in 1..=3u64 {
///     ck.commit(step, |dir| std::fs::write(dir.join("state.txt"), step.to_string()).map_err(
///         |source| vdd_nn::NnError::Io { path: dir.to_owned(), source }))?;
/// }
/// let (step, dir) = ck.latest()?.unwrap();
/// assert_eq!((step, std::fs::read_to_string(dir.join("state.txt"))?), (3, "3".to_owned()));
/// assert_eq!(vdd_nn::checkpoint::generations(&root)?.len(), 2); // pruned
/// drop(ck);
/// std::fs::remove_dir_all(&root)?;
/// # Ok::<(), Box<dyn std::error::Error>>(())
/// ```
#[derive(Debug)]
pub struct CheckpointDir {
    root: PathBuf,
    lock: PathBuf,
}

impl CheckpointDir {
    /// Creates `root` if needed and takes its lock (see the module docs).
    pub fn open(root: &Path) -> Result<Self, NnError> {
        fs::create_dir_all(root).map_err(io(root))?;
        let lock = root.join(LOCK);
        let me = owner_tag(std::process::id());
        for _ in 0..3 {
            match OpenOptions::new().write(true).create_new(true).open(&lock) {
                Ok(mut f) => {
                    f.write_all(me.as_bytes()).and_then(|()| f.sync_all()).map_err(io(&lock))?;
                    sync_dir(root);
                    return Ok(Self { root: root.to_owned(), lock });
                }
                Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => {
                    let owner = fs::read_to_string(&lock).unwrap_or_default();
                    if owner_alive(&owner) {
                        return Err(NnError::Locked { path: lock, owner: owner.trim().into() });
                    }
                    // Stale: move it aside under a unique name (only one taker succeeds).
                    let aside = root.join(format!(".{LOCK}.stale-{}", std::process::id()));
                    if fs::rename(&lock, &aside).is_ok() {
                        let _ = fs::remove_file(&aside);
                    }
                }
                Err(e) => return Err(io(&lock)(e)),
            }
        }
        Err(NnError::Locked { path: lock, owner: "contended".into() })
    }

    /// The directory.
    pub fn root(&self) -> &Path {
        &self.root
    }

    /// The newest complete generation, `(step, directory)` ([`latest`]).
    pub fn latest(&self) -> Result<Option<(u64, PathBuf)>, NnError> {
        latest(&self.root)
    }

    /// Writes generation `step`: `write` fills a fresh directory, whose files are then fsynced
    /// before `LATEST` moves to it; older generations are pruned to [`KEEP`]. Returns the
    /// generation's directory. An error leaves `LATEST` where it was.
    pub fn commit<E: From<NnError>>(
        &self,
        step: u64,
        write: impl FnOnce(&Path) -> Result<(), E>,
    ) -> Result<PathBuf, E> {
        let name = gen_name(step);
        let dir = self.root.join(&name);
        if dir.exists() {
            // A generation of this step that a crash left incomplete, or one being replaced.
            if self.latest()?.is_some_and(|(s, _)| s == step) {
                return Err(NnError::Config(format!(
                    "{}: generation {step} is the current checkpoint; write a newer step",
                    self.root.display()
                ))
                .into());
            }
            fs::remove_dir_all(&dir).map_err(io(&dir))?;
        }
        let previous = self.latest().ok().flatten().map(|(s, _)| s);
        fs::create_dir(&dir).map_err(io(&dir))?;
        write(&dir)?;
        for entry in fs::read_dir(&dir).map_err(io(&dir))? {
            let path = entry.map_err(io(&dir))?.path();
            File::open(&path).and_then(|f| f.sync_all()).map_err(io(&path))?;
        }
        sync_dir(&dir);
        sync_dir(&self.root);
        crate::io::write_atomic(&self.root.join(POINTER), format!("{name}\n").as_bytes())?;
        self.prune(&[Some(step), previous])?;
        Ok(dir)
    }

    /// Removes every generation but `keep` (the new one and the previous complete one, so
    /// [`KEEP`]): older ones, and any other left incomplete by a crash or abandoned by resuming
    /// an older generation.
    fn prune(&self, keep: &[Option<u64>]) -> Result<(), NnError> {
        for (step, dir) in generations(&self.root)? {
            if !keep.contains(&Some(step)) {
                fs::remove_dir_all(&dir).map_err(io(&dir))?;
            }
        }
        sync_dir(&self.root);
        Ok(())
    }
}

impl Drop for CheckpointDir {
    fn drop(&mut self) {
        let _ = fs::remove_file(&self.lock);
    }
}

/// The newest complete generation of the checkpoint directory `root`, `(step, directory)`, or
/// `None` when no generation was completed (or `root` does not exist). Reading needs no lock.
pub fn latest(root: &Path) -> Result<Option<(u64, PathBuf)>, NnError> {
    let pointer = root.join(POINTER);
    let name = match fs::read_to_string(&pointer) {
        Ok(n) => n.trim().to_owned(),
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(None),
        Err(e) => return Err(io(&pointer)(e)),
    };
    let step = parse_gen(&name).ok_or_else(|| NnError::Format {
        path: pointer.clone(),
        reason: format!("`{name}` is not a generation name ({PREFIX}<step>)"),
    })?;
    let dir = root.join(&name);
    if !dir.is_dir() {
        return Err(NnError::Format {
            path: pointer,
            reason: format!("names generation `{name}`, which does not exist"),
        });
    }
    Ok(Some((step, dir)))
}

/// The generation directories in `root`, newest first (complete or not).
pub fn generations(root: &Path) -> Result<Vec<(u64, PathBuf)>, NnError> {
    let mut out = Vec::new();
    for entry in fs::read_dir(root).map_err(io(root))? {
        let entry = entry.map_err(io(root))?;
        if let Some(step) = entry.file_name().to_str().and_then(parse_gen) {
            out.push((step, entry.path()));
        }
    }
    out.sort_by_key(|g| std::cmp::Reverse(g.0));
    Ok(out)
}

fn gen_name(step: u64) -> String {
    format!("{PREFIX}{step:020}")
}

fn parse_gen(name: &str) -> Option<u64> {
    let digits = name.strip_prefix(PREFIX)?;
    (digits.len() == 20 && digits.bytes().all(|b| b.is_ascii_digit()))
        .then(|| digits.parse().ok())?
}

/// Best-effort fsync of a directory (not every platform can open one).
fn sync_dir(dir: &Path) {
    if let Ok(d) = File::open(dir) {
        let _ = d.sync_all();
    }
}

/// `"<pid> <start time>"`: the start time (Linux: field 22 of `/proc/<pid>/stat`) tells a
/// reused pid from the owner.
fn owner_tag(pid: u32) -> String {
    match proc_stat(pid) {
        Some((_, start)) => format!("{pid} {start}"),
        None => format!("{pid}"),
    }
}

/// `(state, start time)` of a process from `/proc`, `None` when it does not exist (or there is
/// no `/proc`).
fn proc_stat(pid: u32) -> Option<(char, String)> {
    let stat = fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    let rest = stat.get(stat.rfind(')')? + 2..)?;
    let f: Vec<&str> = rest.split_whitespace().collect();
    Some((f.first()?.chars().next()?, (*f.get(19)?).to_owned()))
}

/// Whether the owner recorded in a lock file still runs. Without `/proc` a well-formed lock
/// counts as alive (the user removes it); an unreadable one as stale.
fn owner_alive(owner: &str) -> bool {
    let mut words = owner.split_whitespace();
    let Some(pid) = words.next().and_then(|p| p.parse::<u32>().ok()) else {
        return false;
    };
    if !Path::new("/proc/self/stat").exists() {
        return true;
    }
    match proc_stat(pid) {
        None => false,
        Some(('Z' | 'X', _)) => false,
        Some((_, start)) => words.next().is_none_or(|s| s == start),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn temp(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("vdd-ck-{tag}-{}", std::process::id()));
        let _ = fs::remove_dir_all(&d);
        d
    }

    fn put(dir: &Path, text: &str) -> Result<(), NnError> {
        fs::write(dir.join("f"), text).map_err(io(dir))
    }

    #[test]
    fn generations_advance_prune_and_survive_an_interrupted_write() {
        let root = temp("gens");
        let ck = CheckpointDir::open(&root).unwrap();
        assert!(ck.latest().unwrap().is_none());
        for s in [1, 2, 3, 4] {
            ck.commit(s, |d| put(d, &s.to_string())).unwrap();
        }
        let steps: Vec<u64> = generations(&root).unwrap().iter().map(|g| g.0).collect();
        assert_eq!(steps, vec![4, 3]);
        // A write that fails half-way (a crash) leaves the pointer on the last complete one.
        let r: Result<PathBuf, NnError> = ck.commit(5, |d| {
            put(d, "half")?;
            Err(NnError::Config("crash".into()))
        });
        assert!(r.is_err());
        let (s, dir) = ck.latest().unwrap().unwrap();
        assert_eq!((s, fs::read_to_string(dir.join("f")).unwrap()), (4, "4".to_owned()));
        // The next commit replaces the leftover and prunes it.
        ck.commit(5, |d| put(d, "5")).unwrap();
        assert_eq!(latest(&root).unwrap().unwrap().0, 5);
        assert!(ck.commit(5, |d| put(d, "again")).is_err(), "the current one is not rewritten");
        // Resuming from an older generation drops the newer ones at the next commit.
        fs::write(root.join(POINTER), gen_name(4)).unwrap();
        ck.commit(6, |d| put(d, "6")).unwrap();
        let steps: Vec<u64> = generations(&root).unwrap().iter().map(|g| g.0).collect();
        assert_eq!(steps, vec![6, 4]);
        drop(ck);
        fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn the_lock_refuses_a_live_writer_and_recovers_from_a_dead_one() {
        let root = temp("lock");
        let ck = CheckpointDir::open(&root).unwrap();
        let e = CheckpointDir::open(&root).unwrap_err();
        assert!(matches!(e, NnError::Locked { .. }), "{e}");
        assert!(e.to_string().contains(&std::process::id().to_string()), "{e}");
        drop(ck);
        // A lock left by a process that is gone (pid beyond any real one), or garbage.
        for stale in [format!("{}", u32::MAX - 1), "not a pid".to_owned()] {
            fs::write(root.join(LOCK), stale).unwrap();
            drop(CheckpointDir::open(&root).unwrap());
        }
        if Path::new("/proc/self/stat").exists() {
            // Our pid with another start time: a reused pid, so stale.
            fs::write(root.join(LOCK), format!("{} 1", std::process::id())).unwrap();
            drop(CheckpointDir::open(&root).unwrap());
        }
        assert!(!root.join(LOCK).exists(), "dropping releases the lock");
        fs::remove_dir_all(&root).unwrap();
    }

    #[test]
    fn a_broken_pointer_is_an_error_naming_the_file() {
        let root = temp("ptr");
        fs::create_dir_all(&root).unwrap();
        fs::write(root.join(POINTER), "../../etc").unwrap();
        let e = latest(&root).unwrap_err().to_string();
        assert!(e.contains("LATEST") && e.contains("not a generation"), "{e}");
        fs::write(root.join(POINTER), gen_name(7)).unwrap();
        assert!(latest(&root).unwrap_err().to_string().contains("does not exist"));
        fs::remove_dir_all(&root).unwrap();
    }
}
