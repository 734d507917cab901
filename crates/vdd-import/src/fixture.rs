//! Checking an imported teacher against the outputs its PyTorch package recorded
//! (`tests/fixtures/import/*/expected.safetensors`, written by `scripts/import/unet_fixtures.py`):
//! the tests and `cargo xtask bench import` share it.

use std::collections::HashMap;
use std::path::Path;

use faer::Mat;

use crate::error::ImportError;
use crate::json::{MAX_WEIGHTS_BYTES, read_bounded};
use crate::lerobot::read_tensors;
use crate::unet_teacher::UnetTeacher;
use crate::{import_diffusion_policy, import_lerobot};

/// How an imported U-Net fixture agrees with PyTorch.
#[derive(Debug, Clone, PartialEq)]
pub struct UnetFixtureCheck {
    /// The architecture the fixture script named (`lerobot_unet1d`, ...).
    pub architecture: String,
    /// Largest absolute difference of the U-Net outputs at the recorded timesteps.
    pub unet_max_abs_diff: f32,
    /// Largest absolute difference of the executed actions of the full sampling run.
    pub sample_max_abs_diff: f32,
    /// PyTorch's rows per second at batch [`Self::bench_batch`] on one thread, as recorded.
    pub torch_rows_per_s: f64,
    /// The batch PyTorch was timed at, when the fixture names one (its metadata's
    /// `bench_batch`); `None` for the committed fixtures, timed at the bench's default batch.
    pub bench_batch: Option<usize>,
}

/// Largest `bench_batch` a fixture may name.
const MAX_BENCH_BATCH: usize = 1 << 16;

/// Imports a fixture directory (LeRobot when it has `policy_preprocessor.json` or a LeRobot
/// `config.json`, diffusion_policy otherwise).
pub fn import_fixture(dir: &Path) -> Result<UnetTeacher, ImportError> {
    let cfg = vdd_core::files::read_bounded_string(
        &dir.join("config.json"),
        crate::limits::MAX_TEXT_BYTES,
    )
    .map_err(|source| ImportError::Io { path: dir.join("config.json"), source })?;
    if cfg.contains("\"policy\"") { import_diffusion_policy(dir) } else { import_lerobot(dir) }
}

fn tensor<'a>(
    t: &'a HashMap<String, (Vec<usize>, Vec<f32>)>,
    file: &str,
    key: &str,
) -> Result<&'a (Vec<usize>, Vec<f32>), ImportError> {
    t.get(key).ok_or_else(|| ImportError::missing(file, key))
}

/// Imports the fixture in `dir` and compares it with its `expected.safetensors`.
pub fn check_unet_fixture(dir: &Path) -> Result<(UnetTeacher, UnetFixtureCheck), ImportError> {
    check_unet_fixture_with(dir, import_fixture(dir)?)
}

/// Compares `teacher` (imported from the fixture in `dir`, possibly with another sampler or an
/// observation map) with the fixture's `expected.safetensors`: the recorded observations are
/// laid out as the teacher's raw observation (through its [`crate::ObsMap`], unmapped entries
/// zero) before it acts.
pub fn check_unet_fixture_with(
    dir: &Path,
    mut teacher: UnetTeacher,
) -> Result<(UnetTeacher, UnetFixtureCheck), ImportError> {
    let path = dir.join("expected.safetensors");
    let file = path.display().to_string();
    let bytes = read_bounded(&path, MAX_WEIGHTS_BYTES)?;
    let (_, meta) = safetensors::SafeTensors::read_metadata(&bytes)
        .map_err(|e| ImportError::bad(&file, "safetensors", e))?;
    let meta = meta.metadata().clone().unwrap_or_default();
    let flat = read_tensors(&path, &bytes)?;
    let st = safetensors::SafeTensors::deserialize(&bytes)
        .map_err(|e| ImportError::bad(&file, "safetensors", e))?;
    let t: HashMap<String, (Vec<usize>, Vec<f32>)> = flat
        .into_iter()
        .filter_map(|(k, v)| st.tensor(&k).ok().map(|view| (k, (view.shape().to_vec(), v))))
        .collect();
    let spec = teacher.spec().clone();
    let (h, a) = (spec.horizon, spec.unet.input_dim);
    let g = spec.unet.global_cond_dim;

    // The U-Net at the recorded timesteps.
    let (_, steps) = tensor(&t, &file, "unet.t")?;
    let n = steps.len();
    let x = row_mat(&tensor(&t, &file, "unet.x")?.1, n, h * a, &file, "unet.x")?;
    let c = row_mat(&tensor(&t, &file, "unet.global_cond")?.1, n, g, &file, "unet.global_cond")?;
    let want = row_mat(&tensor(&t, &file, "unet.out")?.1, n, h * a, &file, "unet.out")?;
    let mut got = Mat::zeros(n, h * a);
    teacher.predict(x.as_ref(), steps, c.as_ref(), got.as_mut())?;
    let unet_max_abs_diff = max_diff(&got, &want);

    // The full sampling run: raw observation windows in, executed raw actions out.
    let obs_keys: Vec<String> = spec
        .obs_features
        .iter()
        .map(|f| if f.name == "obs" { "sample.obs".into() } else { format!("sample.{}", f.name) })
        .collect();
    let (shape, _) = tensor(&t, &file, &obs_keys[0])?;
    let m = shape.first().copied().unwrap_or(0);
    let no = spec.n_obs_steps;
    let od = spec.obs_dim();
    let mut obs = Mat::<f32>::zeros(m, no * od);
    let mut at = 0;
    for (f, key) in spec.obs_features.iter().zip(&obs_keys) {
        let (_, v) = tensor(&t, &file, key)?;
        if v.len() != m * no * f.dim {
            return Err(ImportError::bad(&file, key.as_str(), format!("{} values", v.len())));
        }
        for r in 0..m {
            for s in 0..no {
                for d in 0..f.dim {
                    obs[(r, s * od + at + d)] = v[(r * no + s) * f.dim + d];
                }
            }
        }
        at += f.dim;
    }
    if let Some(map) = &spec.obs_map {
        let raw_dim = map.raw_dim();
        let mut raw = Mat::<f32>::zeros(m, no * raw_dim);
        for r in 0..m {
            for s in 0..no {
                let mut at = 0;
                for (_, idx) in map.features() {
                    for (d, &j) in idx.iter().enumerate() {
                        raw[(r, s * raw_dim + j)] = obs[(r, s * od + at + d)];
                    }
                    at += idx.len();
                }
            }
        }
        obs = raw;
    }
    let initial = row_mat(&tensor(&t, &file, "sample.noise")?.1, m, h * a, &file, "sample.noise")?;
    let step_noise = &tensor(&t, &file, "sample.step_noise")?.1;
    let mut drawn = 0usize;
    let mut noise = |buf: &mut [f32]| {
        let end = (drawn + buf.len()).min(step_noise.len());
        let got = &step_noise[drawn.min(end)..end];
        buf[..got.len()].copy_from_slice(got);
        buf[got.len()..].fill(f32::NAN);
        drawn += buf.len();
    };
    let na = spec.n_action_steps;
    let want =
        row_mat(&tensor(&t, &file, "sample.actions")?.1, m, na * a, &file, "sample.actions")?;
    let mut acts = Mat::zeros(m, na * a);
    teacher.act_batch_with_noise(obs.as_ref(), initial.as_ref(), &mut noise, acts.as_mut())?;
    if drawn != step_noise.len() {
        return Err(ImportError::bad(
            &file,
            "sample.step_noise",
            format!("{} values, {drawn} drawn", step_noise.len()),
        ));
    }
    let sample_max_abs_diff = max_diff(&acts, &want);
    let torch_rows_per_s = meta
        .get("torch_rows_per_s")
        .and_then(|s| s.parse::<f64>().ok())
        .ok_or_else(|| ImportError::missing(&file, "torch_rows_per_s"))?;
    let architecture = meta
        .get("architecture")
        .cloned()
        .ok_or_else(|| ImportError::missing(&file, "architecture"))?;
    let bench_batch = match meta.get("bench_batch") {
        None => None,
        Some(v) => match v.parse::<usize>() {
            Ok(b) if (1..=MAX_BENCH_BATCH).contains(&b) => Some(b),
            _ => {
                let why = format!("`{v}` is not a batch in 1..={MAX_BENCH_BATCH}");
                return Err(ImportError::bad(&file, "bench_batch", why));
            }
        },
    };
    let check = UnetFixtureCheck {
        architecture,
        unet_max_abs_diff,
        sample_max_abs_diff,
        torch_rows_per_s,
        bench_batch,
    };
    Ok((teacher, check))
}

fn row_mat(v: &[f32], r: usize, c: usize, file: &str, key: &str) -> Result<Mat<f32>, ImportError> {
    if v.len() != r * c {
        return Err(ImportError::bad(file, key, format!("{} values, expected {r} x {c}", v.len())));
    }
    Ok(Mat::from_fn(r, c, |i, j| v[i * c + j]))
}

fn max_diff(a: &Mat<f32>, b: &Mat<f32>) -> f32 {
    let mut m = 0.0f32;
    for j in 0..a.ncols() {
        for i in 0..a.nrows() {
            let d = (a[(i, j)] - b[(i, j)]).abs();
            m = if d.is_nan() { f32::INFINITY } else { m.max(d) };
        }
    }
    m
}
