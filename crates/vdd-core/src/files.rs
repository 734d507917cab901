//! The one way the workspace opens a file for reading: only regular files, never more than a
//! bound.
//!
//! Size checks on `metadata().len()` alone are not enough: `/dev/zero` and `/dev/urandom`
//! report a length of 0 and never end, and opening a FIFO blocks until a writer appears.
//! [`open_regular`] therefore
//!
//! 1. checks [`std::fs::metadata`] (which follows symlinks: a link to a regular file is read
//!    like the file) and refuses anything but a regular file (FIFO, character or block device,
//!    socket, directory) **before** opening it;
//! 2. opens it with `O_NONBLOCK` on Unix, so that a path swapped for a FIFO between the check and
//!    the open cannot block the open (regular files ignore the flag);
//! 3. checks the opened file's own metadata again (what was opened is what is read).
//!
//! [`read_bounded`] then reads at most `max_bytes`, whatever length the file reports: it reads
//! one byte more than the bound and refuses the file if that byte arrives.
//!
//! Errors are [`std::io::Error`]s (every crate wraps them in its own error with the path):
//! [`ErrorKind::InvalidInput`] with a [`NotRegularFile`] source for special files,
//! [`ErrorKind::FileTooLarge`] with a [`TooLarge`] source for files over the bound.
//!
//! ```
//! use vdd_core::files::{read_bounded, NotRegularFile};
//! let dir = std::env::temp_dir().join(format!("vdd-core-files-doc-{}", std::process::id()));
//! std::fs::create_dir_all(&dir)?;
//! std::fs::write(dir.join("a"), b"hello")?;
//! assert_eq!(read_bounded(&dir.join("a"), 5)?, b"hello");
//! assert!(read_bounded(&dir.join("a"), 4).is_err()); // over the bound
//! let e = read_bounded(&dir, 100).unwrap_err(); // a directory
//! assert!(e.get_ref().is_some_and(|s| s.is::<NotRegularFile>()), "{e}");
//! # std::fs::remove_dir_all(&dir)?;
//! # Ok::<(), std::io::Error>(())
//! ```

use std::fs::{File, FileType};
use std::io::{Error, ErrorKind, Read};
use std::path::Path;

/// The error source of a path that is not a regular file.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("not a regular file but {kind}; refusing to read it")]
pub struct NotRegularFile {
    /// What it is ("a FIFO", "a character device", "a directory", ...).
    pub kind: &'static str,
}

/// The error source of a file holding more than the bound it was read with.
#[derive(Debug, Clone, PartialEq, Eq, thiserror::Error)]
#[error("the file holds more than the limit of {limit} bytes")]
pub struct TooLarge {
    /// The bound, in bytes.
    pub limit: u64,
}

/// What a non-regular file type is, in words.
fn describe(t: &FileType) -> &'static str {
    #[cfg(unix)]
    {
        use std::os::unix::fs::FileTypeExt;
        if t.is_fifo() {
            return "a FIFO";
        }
        if t.is_char_device() {
            return "a character device";
        }
        if t.is_block_device() {
            return "a block device";
        }
        if t.is_socket() {
            return "a socket";
        }
    }
    if t.is_dir() {
        "a directory"
    } else if t.is_symlink() {
        "a symbolic link"
    } else {
        "a special file"
    }
}

fn check_regular(t: &FileType) -> std::io::Result<()> {
    if t.is_file() {
        Ok(())
    } else {
        Err(Error::new(ErrorKind::InvalidInput, NotRegularFile { kind: describe(t) }))
    }
}

/// Opens `path` for reading if it is a regular file (or a symlink to one); anything else is
/// refused before it is opened (see the module docs). A missing file is the usual
/// [`ErrorKind::NotFound`].
pub fn open_regular(path: &Path) -> std::io::Result<File> {
    check_regular(&std::fs::metadata(path)?.file_type())?;
    let mut options = std::fs::OpenOptions::new();
    options.read(true);
    #[cfg(unix)]
    {
        use std::os::unix::fs::OpenOptionsExt;
        options.custom_flags(libc::O_NONBLOCK);
    }
    let file = options.open(path)?;
    check_regular(&file.metadata()?.file_type())?;
    Ok(file)
}

/// Reads all of `reader`, at most `max_bytes`: one byte more is an
/// [`ErrorKind::FileTooLarge`] error with a [`TooLarge`] source.
pub fn read_to_end_bounded(reader: impl Read, max_bytes: u64) -> std::io::Result<Vec<u8>> {
    let mut bytes = Vec::new();
    reader.take(max_bytes.saturating_add(1)).read_to_end(&mut bytes)?;
    if bytes.len() as u64 > max_bytes {
        return Err(Error::new(ErrorKind::FileTooLarge, TooLarge { limit: max_bytes }));
    }
    Ok(bytes)
}

/// Reads the regular file `path` whole, at most `max_bytes` ([`open_regular`], then
/// [`read_to_end_bounded`]). A file whose reported length is over the bound is refused before
/// anything is read.
pub fn read_bounded(path: &Path, max_bytes: u64) -> std::io::Result<Vec<u8>> {
    let file = open_regular(path)?;
    if file.metadata()?.len() > max_bytes {
        return Err(Error::new(ErrorKind::FileTooLarge, TooLarge { limit: max_bytes }));
    }
    read_to_end_bounded(file, max_bytes)
}

/// [`read_bounded`] as UTF-8 text (invalid UTF-8 is [`ErrorKind::InvalidData`]).
pub fn read_bounded_string(path: &Path, max_bytes: u64) -> std::io::Result<String> {
    String::from_utf8(read_bounded(path, max_bytes)?)
        .map_err(|e| Error::new(ErrorKind::InvalidData, e))
}

/// Whether `e` is [`open_regular`]'s refusal of a non-regular file.
pub fn is_not_regular(e: &Error) -> bool {
    e.get_ref().is_some_and(|s| s.is::<NotRegularFile>())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::path::PathBuf;
    use std::time::{Duration, Instant};

    fn scratch(tag: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("vdd-core-files-{tag}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    #[test]
    fn regular_files_and_links_to_them_are_read_within_the_bound() {
        let d = scratch("regular");
        std::fs::write(d.join("f"), b"12345").unwrap();
        assert_eq!(read_bounded(&d.join("f"), 5).unwrap(), b"12345");
        let e = read_bounded(&d.join("f"), 4).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::FileTooLarge);
        assert!(e.to_string().contains("limit of 4 bytes"), "{e}");
        #[cfg(unix)]
        {
            std::os::unix::fs::symlink(d.join("f"), d.join("link")).unwrap();
            assert_eq!(read_bounded_string(&d.join("link"), 10).unwrap(), "12345");
        }
        assert_eq!(read_bounded(&d.join("missing"), 5).unwrap_err().kind(), ErrorKind::NotFound);
        std::fs::remove_dir_all(&d).unwrap();
    }

    #[test]
    fn endless_reports_of_zero_length_are_cut_at_the_bound() {
        // /dev/zero reports length 0 and never ends: refused as a device, and even read as a
        // stream it stops one byte past the bound.
        if !Path::new("/dev/zero").exists() {
            return;
        }
        let e = read_bounded(Path::new("/dev/zero"), 1 << 20).unwrap_err();
        assert!(is_not_regular(&e), "{e}");
        assert!(e.to_string().contains("character device"), "{e}");
        let e = read_to_end_bounded(File::open("/dev/zero").unwrap(), 1000).unwrap_err();
        assert_eq!(e.kind(), ErrorKind::FileTooLarge);
    }

    #[cfg(unix)]
    #[test]
    fn a_fifo_is_refused_at_once_not_waited_on() {
        use std::os::unix::ffi::OsStrExt;
        let d = scratch("fifo");
        let fifo = d.join("pipe");
        let c = std::ffi::CString::new(fifo.as_os_str().as_bytes()).unwrap();
        // SAFETY: `c` is a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        let start = Instant::now();
        let e = read_bounded(&fifo, 100).unwrap_err();
        assert!(start.elapsed() < Duration::from_secs(5));
        assert!(is_not_regular(&e) && e.to_string().contains("FIFO"), "{e}");
        // Even past the metadata check (a path swapped after it), the open does not block.
        let mut o = std::fs::OpenOptions::new();
        std::os::unix::fs::OpenOptionsExt::custom_flags(o.read(true), libc::O_NONBLOCK);
        let f = o.open(&fifo).unwrap();
        assert!(check_regular(&f.metadata().unwrap().file_type()).is_err());
        let e = read_bounded(&d, 100).unwrap_err();
        assert!(e.to_string().contains("directory"), "{e}");
        std::fs::remove_dir_all(&d).unwrap();
    }
}
