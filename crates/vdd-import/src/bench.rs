//! `cargo xtask bench import`: every fixture architecture's agreement with PyTorch and its
//! throughput against PyTorch's ([`bench_fixtures`], one [`ImportBenchRecord`] each).

use std::path::{Path, PathBuf};
use std::time::Instant;

use faer::Mat;
use serde::{Deserialize, Serialize};

use crate::fixture::check_unet_fixture;
use crate::{BesoError, ImportError, UnetTeacher};

/// One fixture architecture's agreement with PyTorch and throughput.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ImportBenchRecord {
    /// The fixture (its directory name under `tests/fixtures/import`).
    pub fixture: String,
    /// The architecture (`lerobot_unet1d`, `diffusion_policy_unet1d`, ...).
    pub architecture: String,
    /// Largest absolute difference of our network's outputs from PyTorch's on the fixture.
    pub max_abs_diff: f32,
    /// Rows (samples) per second of our forward pass at batch [`Self::batch`], one thread.
    pub rows_per_s: f64,
    /// The same for PyTorch, as the fixture script recorded it (`torch.set_num_threads(1)`).
    pub torch_rows_per_s: f64,
    /// The batch both were timed at: [`BENCH_BATCH`], or the fixture's own (a large network's).
    pub batch: usize,
}

/// The batch the throughput is measured at, unless a fixture names its own.
pub const BENCH_BATCH: usize = 1024;

/// Errors of [`bench_fixtures`]: the fixtures' directory, or an importer's error.
#[derive(Debug, thiserror::Error)]
pub enum BenchError {
    /// The fixtures' directory could not be listed.
    #[error("{}: {source}", .path.display())]
    Io {
        /// The directory.
        path: PathBuf,
        /// The underlying error.
        #[source]
        source: std::io::Error,
    },
    /// A U-Net fixture failed.
    #[error(transparent)]
    Import(#[from] ImportError),
    /// A BESO or diffusion_policy transformer fixture failed.
    #[error(transparent)]
    Beso(#[from] BesoError),
}

/// Rows per second of `teacher`'s U-Net forward at batch `batch` on the calling thread: the
/// best of 5 timed calls after one warm-up call, on fixed inputs.
pub fn unet_rows_per_s(teacher: &mut UnetTeacher, batch: usize) -> Result<f64, ImportError> {
    let s = teacher.spec();
    let (w, g) = (s.horizon * s.unet.input_dim, s.unet.global_cond_dim);
    let x = Mat::from_fn(batch, w, |i, j| ((i * 31 + j * 7) % 17) as f32 / 8.0 - 1.0);
    let c = Mat::from_fn(batch, g, |i, j| ((i * 13 + j * 5) % 11) as f32 / 5.0 - 1.0);
    let t: Vec<f32> = (0..batch).map(|i| (i % 100) as f32).collect();
    let mut out = Mat::zeros(batch, w);
    teacher.predict(x.as_ref(), &t, c.as_ref(), out.as_mut())?;
    let mut best = f64::INFINITY;
    for _ in 0..5 {
        let t0 = Instant::now();
        teacher.predict(x.as_ref(), &t, c.as_ref(), out.as_mut())?;
        best = best.min(t0.elapsed().as_secs_f64());
    }
    Ok(batch as f64 / best)
}

/// The U-Net fixture directories below `dir`: those named `lerobot_unet*` or
/// `diffusion_policy_unet*` holding an `expected.safetensors`, sorted.
fn unet_fixture_dirs(dir: &Path) -> Result<Vec<PathBuf>, BenchError> {
    let io = |source| BenchError::Io { path: dir.to_owned(), source };
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(io)?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join("expected.safetensors").is_file())
        .filter(|p| {
            let name = p.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
            name.starts_with("lerobot_unet") || name.starts_with("diffusion_policy_unet")
        })
        .collect();
    dirs.sort();
    Ok(dirs)
}

/// Checks every fixture under `dir` against PyTorch's recorded outputs and times our forward
/// on this thread at [`BENCH_BATCH`] rows (or the batch a fixture names): the U-Net fixtures
/// (directories `lerobot_unet*`, `diffusion_policy_unet*` with an `expected.safetensors`) of
/// `dir` and then of each of `extra` (fixtures too large to commit, such as the LeRobot
/// default-scale U-Net that `scripts/import/unet_fixtures.py --default-scale` writes), then
/// [`crate::BESO_FIXTURES`] and [`crate::DP_TRANSFORMER_FIXTURES`] of `dir`. `row` receives
/// each record with a one-line summary as it is measured.
pub fn bench_fixtures(
    dir: &Path,
    extra: &[PathBuf],
    mut row: impl FnMut(&ImportBenchRecord, &str),
) -> Result<Vec<ImportBenchRecord>, BenchError> {
    let mut dirs = unet_fixture_dirs(dir)?;
    for e in extra {
        dirs.extend(unet_fixture_dirs(e)?);
    }
    let mut records = Vec::new();
    for dir in dirs {
        let name = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        let (mut teacher, check) = check_unet_fixture(&dir)?;
        let batch = check.bench_batch.unwrap_or(BENCH_BATCH);
        let r = ImportBenchRecord {
            fixture: name,
            architecture: check.architecture,
            max_abs_diff: check.unet_max_abs_diff.max(check.sample_max_abs_diff),
            rows_per_s: unet_rows_per_s(&mut teacher, batch)?,
            torch_rows_per_s: check.torch_rows_per_s,
            batch,
        };
        let (u, s) = (check.unet_max_abs_diff, check.sample_max_abs_diff);
        row(
            &r,
            &format!(
                "{:24} max_abs_diff {:.2e} (U-Net {u:.2e}, sampling {s:.2e})  rows/s {:>9.1}  torch {:>9.1}  batch {}",
                r.fixture, r.max_abs_diff, r.rows_per_s, r.torch_rows_per_s, r.batch
            ),
        );
        records.push(r);
    }
    let mut push = |fixture: &str, architecture: String, diff: f64, ours: f64, torch: f64| {
        let r = ImportBenchRecord {
            fixture: fixture.into(),
            architecture,
            max_abs_diff: diff as f32,
            rows_per_s: ours,
            torch_rows_per_s: torch,
            batch: BENCH_BATCH,
        };
        row(
            &r,
            &format!(
                "{fixture:24} max_abs_diff {diff:.2e}  rows/s {ours:>9.1}  torch {torch:>9.1}"
            ),
        );
        records.push(r);
    };
    for name in crate::BESO_FIXTURES {
        let (report, mut teacher) = crate::check_beso_fixture(dir, name)?;
        let ours = crate::beso_rows_per_s(&mut teacher, BENCH_BATCH, 2.0)?;
        let arch = format!("beso_{}", report.arch);
        push(name, arch, report.max_abs_diff(), ours, report.torch_rows_per_s);
    }
    for name in crate::DP_TRANSFORMER_FIXTURES {
        let (diff, torch, mut net) = crate::check_dp_transformer_fixture(dir, name)?;
        let ours = crate::dp_transformer_rows_per_s(&mut net, BENCH_BATCH, 2.0)?;
        push(name, "diffusion_policy_transformer".into(), diff, ours, torch);
    }
    Ok(records)
}
