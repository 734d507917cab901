//! Loading and saving [`Episodes`] as `.npz` archives or directories of `.npy` files, in the
//! layout of the play-to-policy / BeT datasets.
//!
//! Three arrays describe a dataset of `N` episodes padded to `T` steps:
//!
//! | array              | shape (episode-major) | dtype read              | dtype written |
//! |--------------------|-----------------------|-------------------------|---------------|
//! | `observations_seq` | `N x T x d_obs`       | float32, float64        | float32       |
//! | `actions_seq`      | `N x T x d_act`       | float32, float64        | float32       |
//! | `existence_mask`   | `N x T`               | bool, int, float (0/1)  | float32       |
//!
//! An `.npz` holds them under those keys (as `np.savez(path, observations_seq=..., ...)`
//! writes); a directory holds `observations_seq.npy` etc. float64 input is rounded to the
//! nearest `f32`. The mask must be a prefix mask (ones, then zeros) with at least one valid step
//! per episode; values in the padding are ignored. Other key names and the time-major layout
//! (`T x N x d`) are read with [`LoadOptions`]; see its presets for the Relay-Kitchen and
//! Block-Push files.
//!
//! Reading is bounded: an array's header must declare at most [`MAX_ARRAY_BYTES`] of data (and
//! have at most [`MAX_NPY_HEADER_BYTES`] of header), and a compressed archive entry is
//! decompressed only up to the size its header declares, so a small hostile archive cannot
//! make the loader allocate gigabytes. Only regular files (or symlinks to them) are opened:
//! a FIFO, a device such as `/dev/zero`, a socket or a directory where a file is expected is
//! refused before it is opened ([`vdd_core::files::open_regular`]).
//!
//! Writes are atomic: each file is written to a temporary sibling, fsynced, then renamed over
//! the target, so a crash leaves either the old file or the complete new one. The npz entries
//! are stored uncompressed with a fixed timestamp, so saving the same data twice gives
//! byte-identical files.

use std::io::{Cursor, Write};
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

use crate::episodes::Episodes;
use crate::error::{DataError, Result, archive_err, format_err, io_err};
pub use crate::npy::{MAX_ARRAY_BYTES, MAX_NPY_HEADER_BYTES};
use crate::npy::{NpyArray, encode_f32};

/// Axis order of the stored arrays.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Layout {
    /// `N x T x d` (episode first), as this crate writes and the Block-Push files use.
    #[default]
    EpisodeMajor,
    /// `T x N x d` (time first), as the Relay-Kitchen files are stored (the BeT loaders
    /// transpose them after loading).
    TimeMajor,
}

/// Where to find the three arrays and how they are laid out.
///
/// ```
/// use vdd_data::{Layout, LoadOptions};
/// let kitchen = LoadOptions::relay_kitchen();
/// assert_eq!(kitchen.layout, Layout::TimeMajor);
/// assert_eq!(kitchen.observations_key, "observations_seq");
/// let push = LoadOptions::block_push();
/// assert_eq!(push.mask_key, "multimodal_push_masks");
/// ```
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct LoadOptions {
    /// Axis order.
    pub layout: Layout,
    /// Name of the observations array (npz key, or file stem in a directory).
    pub observations_key: String,
    /// Name of the actions array.
    pub actions_key: String,
    /// Name of the existence-mask array.
    pub mask_key: String,
}

impl Default for LoadOptions {
    /// Episode-major `observations_seq` / `actions_seq` / `existence_mask`: what
    /// [`Episodes::save_npz`] and [`Episodes::save_npy_dir`] write.
    fn default() -> Self {
        Self::with_keys(Layout::EpisodeMajor, "observations_seq", "actions_seq", "existence_mask")
    }
}

impl LoadOptions {
    /// Custom layout and array names.
    pub fn with_keys(layout: Layout, observations: &str, actions: &str, mask: &str) -> Self {
        Self {
            layout,
            observations_key: observations.to_owned(),
            actions_key: actions.to_owned(),
            mask_key: mask.to_owned(),
        }
    }

    /// The Relay-Kitchen files of BeT / play-to-policy: `observations_seq.npy`,
    /// `actions_seq.npy`, `existence_mask.npy`, stored time-major (`T x N x d`, mask `T x N`).
    pub fn relay_kitchen() -> Self {
        Self { layout: Layout::TimeMajor, ..Self::default() }
    }

    /// The Block-Push files of BeT / play-to-policy: `multimodal_push_observations.npy`,
    /// `multimodal_push_actions.npy`, `multimodal_push_masks.npy`, episode-major.
    pub fn block_push() -> Self {
        Self::with_keys(
            Layout::EpisodeMajor,
            "multimodal_push_observations",
            "multimodal_push_actions",
            "multimodal_push_masks",
        )
    }
}

impl Episodes {
    /// Loads an `.npz` archive with the default keys, episode-major (what
    /// [`Episodes::save_npz`] writes). See the [`io`](crate::io) module docs for the format and
    /// [`Episodes::load_npz_with`] for other layouts.
    ///
    /// Errors: [`DataError::Io`], [`DataError::Archive`] (not a zip, a corrupt entry),
    /// [`DataError::Format`] (not an npy entry, truncated),
    /// [`DataError::MissingKey`], [`DataError::Dtype`], [`DataError::Shape`],
    /// [`DataError::Empty`], [`DataError::Mask`], [`DataError::NonFinite`].
    pub fn load_npz(path: &Path) -> Result<Self> {
        Self::load_npz_with(path, &LoadOptions::default())
    }

    /// Loads an `.npz` archive with the given keys and layout.
    pub fn load_npz_with(path: &Path, options: &LoadOptions) -> Result<Self> {
        // Only a regular file is opened (never a FIFO or a device), and it is read entry by
        // entry, each bounded by its array header ([`crate::npy`]), never whole.
        let file = vdd_core::files::open_regular(path).map_err(io_err(path))?;
        let mut zip =
            zip::ZipArchive::new(std::io::BufReader::new(file)).map_err(archive_err(path, None))?;
        let present: Vec<String> =
            zip.file_names().filter_map(|f| f.strip_suffix(".npy")).map(str::to_owned).collect();
        let mut read = |key: &str| -> Result<Vec<u8>> {
            if !present.iter().any(|p| p == key) {
                return Err(DataError::MissingKey {
                    path: path.to_owned(),
                    key: key.to_owned(),
                    present: present.join(", "),
                });
            }
            let mut entry =
                zip.by_name(&format!("{key}.npy")).map_err(archive_err(path, Some(key)))?;
            crate::npy::read_bounded(&mut entry, path, key)
        };
        let obs = read(&options.observations_key)?;
        let act = read(&options.actions_key)?;
        let mask = read(&options.mask_key)?;
        let arrays = [
            NpyArray::parse(&obs, path, &options.observations_key)?,
            NpyArray::parse(&act, path, &options.actions_key)?,
            NpyArray::parse(&mask, path, &options.mask_key)?,
        ];
        let [o, a, m] = &arrays;
        from_arrays(path, path, path, o, a, m, options)
    }

    /// Loads a directory holding `observations_seq.npy`, `actions_seq.npy` and
    /// `existence_mask.npy`, episode-major (what [`Episodes::save_npy_dir`] writes).
    ///
    /// Errors: as [`Episodes::load_npz`].
    pub fn load_npy_dir(dir: &Path) -> Result<Self> {
        Self::load_npy_dir_with(dir, &LoadOptions::default())
    }

    /// Loads a directory of `.npy` files with the given names and layout.
    pub fn load_npy_dir_with(dir: &Path, options: &LoadOptions) -> Result<Self> {
        let files: Vec<PathBuf> =
            [&options.observations_key, &options.actions_key, &options.mask_key]
                .iter()
                .map(|k| dir.join(format!("{k}.npy")))
                .collect();
        let mut bytes = Vec::with_capacity(3);
        for (file, key) in
            files.iter().zip([&options.observations_key, &options.actions_key, &options.mask_key])
        {
            match vdd_core::files::open_regular(file) {
                Ok(mut f) => bytes.push(crate::npy::read_bounded(&mut f, file, key)?),
                Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                    return Err(DataError::MissingKey {
                        path: dir.to_owned(),
                        key: key.clone(),
                        present: npy_files_in(dir).join(", "),
                    });
                }
                Err(e) => return Err(io_err(file)(e)),
            }
        }
        let o = NpyArray::parse(&bytes[0], &files[0], &options.observations_key)?;
        let a = NpyArray::parse(&bytes[1], &files[1], &options.actions_key)?;
        let m = NpyArray::parse(&bytes[2], &files[2], &options.mask_key)?;
        from_arrays(&files[0], &files[1], &files[2], &o, &a, &m, options)
    }

    /// Loads `path` with the default keys: a directory of `.npy` files if it is a directory,
    /// an `.npz` archive otherwise.
    pub fn load(path: &Path) -> Result<Self> {
        if path.is_dir() { Self::load_npy_dir(path) } else { Self::load_npz(path) }
    }

    /// Saves to an `.npz` archive (episode-major float32 `observations_seq`, `actions_seq`,
    /// `existence_mask`), atomically. [`Episodes::load_npz`] gives back an equal value, every
    /// float bit-identical, and `np.load` reads it.
    ///
    /// Errors: [`DataError::Io`], [`DataError::Archive`].
    pub fn save_npz(&self, path: &Path) -> Result<()> {
        let mut zip = zip::ZipWriter::new(Cursor::new(Vec::new()));
        let io = |e: std::io::Error| io_err(path)(e);
        let zip_err = |e: zip::result::ZipError| archive_err(path, None)(e);
        for (name, bytes) in self.npy_arrays().map_err(io)? {
            let options = zip::write::FileOptions::default()
                .compression_method(zip::CompressionMethod::Stored)
                .last_modified_time(zip::DateTime::default())
                .unix_permissions(0o644)
                .large_file(bytes.len() as u64 >= u64::from(u32::MAX));
            zip.start_file(format!("{name}.npy"), options).map_err(zip_err)?;
            zip.write_all(&bytes).map_err(io)?;
        }
        let bytes = zip.finish().map_err(zip_err)?.into_inner();
        write_files_atomic(&[(path.to_owned(), bytes)])
    }

    /// Saves to a directory (created if needed) as `observations_seq.npy`, `actions_seq.npy` and
    /// `existence_mask.npy` (episode-major float32). Each file is written atomically and the
    /// three renames happen only after all three files are fully written and synced.
    ///
    /// Errors: [`DataError::Io`].
    pub fn save_npy_dir(&self, dir: &Path) -> Result<()> {
        std::fs::create_dir_all(dir).map_err(io_err(dir))?;
        let files: Vec<(PathBuf, Vec<u8>)> = self
            .npy_arrays()
            .map_err(io_err(dir))?
            .into_iter()
            .map(|(name, bytes)| (dir.join(format!("{name}.npy")), bytes))
            .collect();
        write_files_atomic(&files)
    }

    fn npy_arrays(&self) -> std::io::Result<[(&'static str, Vec<u8>); 3]> {
        let (n, t) = (self.num_episodes(), self.max_len());
        Ok([
            ("observations_seq", encode_f32(&[n, t, self.obs_dim()], self.padded_observations())?),
            ("actions_seq", encode_f32(&[n, t, self.act_dim()], self.padded_actions())?),
            ("existence_mask", encode_f32(&[n, t], &self.existence_mask())?),
        ])
    }
}

fn npy_files_in(dir: &Path) -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(dir)
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .filter_map(|e| {
                    e.file_name().to_str().and_then(|n| n.strip_suffix(".npy")).map(str::to_owned)
                })
                .collect()
        })
        .unwrap_or_default();
    names.sort();
    names
}

/// Validates the three parsed arrays against each other and builds the episodes.
fn from_arrays(
    obs_path: &Path,
    act_path: &Path,
    mask_path: &Path,
    obs: &NpyArray<'_>,
    act: &NpyArray<'_>,
    mask: &NpyArray<'_>,
    options: &LoadOptions,
) -> Result<Episodes> {
    let axes = match options.layout {
        Layout::EpisodeMajor => "N x T",
        Layout::TimeMajor => "T x N",
    };
    let rank = |a: &NpyArray<'_>, key: &str, want: usize, dims: &str| -> Result<()> {
        if a.shape.len() != want {
            return Err(DataError::Shape {
                what: format!("array `{key}`"),
                expected: format!("{want} axes ({axes}{dims})"),
                got: format!("shape {:?}", a.shape),
            });
        }
        Ok(())
    };
    rank(obs, &options.observations_key, 3, " x d_obs")?;
    rank(act, &options.actions_key, 3, " x d_act")?;
    rank(mask, &options.mask_key, 2, "")?;
    let lead = [obs.shape[0], obs.shape[1]];
    for (a, key) in [(act, &options.actions_key), (mask, &options.mask_key)] {
        if a.shape[..2] != lead {
            return Err(DataError::Shape {
                what: format!("leading axes ({axes}) of `{key}`"),
                expected: format!("{} x {} (as `{}`)", lead[0], lead[1], options.observations_key),
                got: format!("{} x {}", a.shape[0], a.shape[1]),
            });
        }
    }
    let (n, t) = match options.layout {
        Layout::EpisodeMajor => (lead[0], lead[1]),
        Layout::TimeMajor => (lead[1], lead[0]),
    };
    let (d_obs, d_act) = (obs.shape[2], act.shape[2]);
    if n == 0 {
        return Err(DataError::Empty(format!("`{}` holds no episodes", options.observations_key)));
    }
    if t == 0 {
        return Err(DataError::Empty(format!(
            "`{}` holds no time steps",
            options.observations_key
        )));
    }
    // Decode everything before building anything (dtype errors first, then values).
    let mut o = obs.to_f32(obs_path, &options.observations_key)?;
    let mut a = act.to_f32(act_path, &options.actions_key)?;
    let mut flags = match mask.to_mask(mask_path, &options.mask_key)? {
        Ok(f) => f,
        Err((pos, value)) => {
            let (i, s) = match options.layout {
                Layout::EpisodeMajor => (pos / t, pos % t),
                Layout::TimeMajor => (pos % n, pos / n),
            };
            return Err(DataError::Mask(format!(
                "`{}` holds {value} at episode {i}, step {s}; only 0 and 1 are allowed",
                options.mask_key
            )));
        }
    };
    if options.layout == Layout::TimeMajor {
        o = time_to_episode_major(&o, t, n, d_obs);
        a = time_to_episode_major(&a, t, n, d_act);
        flags = time_to_episode_major(&flags, t, n, 1);
    }
    let mut lengths = Vec::with_capacity(n);
    for i in 0..n {
        let row = &flags[i * t..(i + 1) * t];
        let len = row.iter().position(|&v| !v).unwrap_or(t);
        if let Some(k) = row[len..].iter().position(|&v| v) {
            return Err(DataError::Mask(format!(
                "`{}` of episode {i} is not a prefix mask: step {} is valid after invalid step {len}",
                options.mask_key,
                len + k
            )));
        }
        lengths.push(len);
    }
    Episodes::from_padded(t, d_obs, d_act, lengths, o, a)
}

/// `T x N x d` to `N x T x d`.
fn time_to_episode_major<T: Copy>(src: &[T], t: usize, n: usize, d: usize) -> Vec<T> {
    let mut out = Vec::with_capacity(src.len());
    for i in 0..n {
        for s in 0..t {
            out.extend_from_slice(&src[(s * n + i) * d..(s * n + i + 1) * d]);
        }
    }
    out
}

/// Writes every `(path, bytes)` atomically: all temporary siblings are written and fsynced
/// first, then renamed over their targets, then the parent directories are synced. On error the
/// temporary files are removed and no target has been touched (unless a rename itself fails).
pub(crate) fn write_files_atomic(files: &[(PathBuf, Vec<u8>)]) -> Result<()> {
    static COUNTER: AtomicU64 = AtomicU64::new(0);
    let mut temps: Vec<PathBuf> = Vec::with_capacity(files.len());
    let result = (|| {
        for (path, bytes) in files {
            let name = path
                .file_name()
                .ok_or_else(|| format_err(path, "path has no file name"))?
                .to_string_lossy()
                .into_owned();
            let unique = COUNTER.fetch_add(1, Ordering::Relaxed);
            let tmp = path.with_file_name(format!(".{name}.tmp-{}-{unique}", std::process::id()));
            temps.push(tmp.clone());
            let mut f = std::fs::File::create(&tmp).map_err(io_err(&tmp))?;
            f.write_all(bytes).map_err(io_err(&tmp))?;
            f.sync_all().map_err(io_err(&tmp))?;
        }
        for ((path, _), tmp) in files.iter().zip(&temps) {
            std::fs::rename(tmp, path).map_err(io_err(path))?;
        }
        for (path, _) in files {
            // Persist the renames; not every platform can open a directory, so a failure here
            // is not an error.
            if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
                if let Ok(d) = std::fs::File::open(dir) {
                    let _ = d.sync_all();
                }
            }
        }
        Ok(())
    })();
    if result.is_err() {
        for tmp in &temps {
            let _ = std::fs::remove_file(tmp);
        }
    }
    result
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::episodes::tests::ramp_episodes;
    use faer::Mat;

    pub(crate) struct TempDir(pub(crate) PathBuf);

    impl TempDir {
        pub(crate) fn new(tag: &str) -> Self {
            static N: AtomicU64 = AtomicU64::new(0);
            let dir = std::env::temp_dir().join(format!(
                "vdd-data-{tag}-{}-{}",
                std::process::id(),
                N.fetch_add(1, Ordering::Relaxed)
            ));
            std::fs::create_dir_all(&dir).unwrap();
            Self(dir)
        }
    }

    impl Drop for TempDir {
        fn drop(&mut self) {
            let _ = std::fs::remove_dir_all(&self.0);
        }
    }

    fn awkward_episodes() -> Episodes {
        // Values that exercise every bit: subnormals, extremes, negative zero, odd fractions.
        let specials = [
            f32::MIN_POSITIVE / 3.0,
            f32::MAX,
            f32::MIN,
            -0.0,
            0.1,
            1.0 / 3.0,
            -7.25e-30,
            123456.79,
        ];
        let obs =
            (0..3).map(|i| Mat::from_fn(2 + i, 3, |t, j| specials[(i + t * 3 + j) % 8])).collect();
        let act =
            (0..3).map(|i| Mat::from_fn(2 + i, 2, |t, j| specials[(i * 5 + t + j) % 8])).collect();
        Episodes::from_episodes(obs, act).unwrap()
    }

    fn assert_bit_identical(a: &Episodes, b: &Episodes) {
        assert_eq!(a.lengths(), b.lengths());
        assert_eq!(
            (a.obs_dim(), a.act_dim(), a.max_len()),
            (b.obs_dim(), b.act_dim(), b.max_len())
        );
        let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
        assert_eq!(bits(a.padded_observations()), bits(b.padded_observations()));
        assert_eq!(bits(a.padded_actions()), bits(b.padded_actions()));
    }

    #[test]
    fn npz_and_npy_dir_round_trip_bit_identically() {
        let dir = TempDir::new("roundtrip");
        for e in [awkward_episodes(), ramp_episodes(5, 4, 2)] {
            let npz = dir.0.join("data.npz");
            e.save_npz(&npz).unwrap();
            let back = Episodes::load_npz(&npz).unwrap();
            assert_eq!(back, e);
            assert_bit_identical(&back, &e);
            assert_bit_identical(&Episodes::load(&npz).unwrap(), &e);

            let sub = dir.0.join("npy");
            e.save_npy_dir(&sub).unwrap();
            let back = Episodes::load_npy_dir(&sub).unwrap();
            assert_bit_identical(&back, &e);
            assert_bit_identical(&Episodes::load(&sub).unwrap(), &e);
        }
        // No temporary files are left behind.
        let leftovers: Vec<_> = std::fs::read_dir(&dir.0)
            .unwrap()
            .filter_map(|e| e.ok())
            .filter(|e| e.file_name().to_string_lossy().contains(".tmp-"))
            .collect();
        assert!(leftovers.is_empty());
    }

    #[test]
    fn saving_is_deterministic_and_replaces_old_files() {
        let dir = TempDir::new("determinism");
        let p = dir.0.join("a.npz");
        let q = dir.0.join("b.npz");
        ramp_episodes(3, 2, 1).save_npz(&p).unwrap();
        let e = awkward_episodes();
        e.save_npz(&p).unwrap(); // overwrite
        e.save_npz(&q).unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), std::fs::read(&q).unwrap());
        assert_eq!(Episodes::load_npz(&p).unwrap(), e);
    }

    #[test]
    fn writes_fail_cleanly() {
        let dir = TempDir::new("failing");
        let missing = dir.0.join("no-such-dir").join("x.npz");
        assert!(matches!(ramp_episodes(2, 1, 1).save_npz(&missing), Err(DataError::Io { .. })));
        // A file where the directory should be.
        let file = dir.0.join("file");
        std::fs::write(&file, b"x").unwrap();
        assert!(matches!(ramp_episodes(2, 1, 1).save_npy_dir(&file), Err(DataError::Io { .. })));
        assert!(matches!(Episodes::load_npz(&dir.0.join("absent.npz")), Err(DataError::Io { .. })));
    }

    /// Before, an npz path naming `/dev/zero` was read until memory ran out, and a FIFO (as a
    /// file of an npy directory too) blocked forever in `open`.
    #[cfg(unix)]
    #[test]
    fn special_files_are_refused_before_they_are_opened() {
        use std::os::unix::ffi::OsStrExt;
        let is_special = |e: &DataError| match e {
            DataError::Io { source, .. } => vdd_core::files::is_not_regular(source),
            _ => false,
        };
        if Path::new("/dev/zero").exists() {
            let e = Episodes::load_npz(Path::new("/dev/zero")).unwrap_err();
            assert!(is_special(&e) && e.to_string().contains("/dev/zero"), "{e}");
        }
        let dir = TempDir::new("special");
        ramp_episodes(2, 2, 1).save_npy_dir(&dir.0).unwrap();
        for target in ["actions_seq.npy", "data.npz"] {
            let fifo = dir.0.join(target);
            let _ = std::fs::remove_file(&fifo);
            let c = std::ffi::CString::new(fifo.as_os_str().as_bytes()).unwrap();
            // SAFETY: a valid NUL-terminated path.
            assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        }
        let e = Episodes::load_npz(&dir.0.join("data.npz")).unwrap_err();
        assert!(is_special(&e) && e.to_string().contains("data.npz"), "{e}");
        let e = Episodes::load_npy_dir(&dir.0).unwrap_err();
        assert!(is_special(&e) && e.to_string().contains("actions_seq.npy"), "{e}");
    }

    #[test]
    fn time_major_layout_is_transposed() {
        // Write a time-major copy by hand and read it with the Relay-Kitchen preset.
        let e = ramp_episodes(4, 3, 2);
        let (n, t) = (e.num_episodes(), e.max_len());
        let to_time_major = |src: &[f32], d: usize| {
            let mut out = vec![0.0f32; src.len()];
            for i in 0..n {
                for s in 0..t {
                    for j in 0..d {
                        out[(s * n + i) * d + j] = src[(i * t + s) * d + j];
                    }
                }
            }
            out
        };
        let dir = TempDir::new("time-major");
        let files = vec![
            (
                dir.0.join("observations_seq.npy"),
                encode_f32(&[t, n, 3], &to_time_major(e.padded_observations(), 3)).unwrap(),
            ),
            (
                dir.0.join("actions_seq.npy"),
                encode_f32(&[t, n, 2], &to_time_major(e.padded_actions(), 2)).unwrap(),
            ),
            (
                dir.0.join("existence_mask.npy"),
                encode_f32(&[t, n], &to_time_major(&e.existence_mask(), 1)).unwrap(),
            ),
        ];
        write_files_atomic(&files).unwrap();
        assert_eq!(Episodes::load_npy_dir_with(&dir.0, &LoadOptions::relay_kitchen()).unwrap(), e);
        // Read episode-major, the same files are a different (wrong) dataset or an error.
        assert!(Episodes::load_npy_dir(&dir.0).map(|x| x != e).unwrap_or(true));
    }
}
