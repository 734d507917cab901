//! Checking an imported BESO/D3IL network against the fixtures `scripts/import/beso_fixtures.py`
//! made with the packages' PyTorch code, and timing its forward pass (for `bench import`).

use std::path::Path;
use std::time::Instant;

use faer::Mat;
use serde::Deserialize;

use crate::beso::BesoTeacher;
use crate::beso_error::BesoError;
use crate::beso_import::beso_config_from_yaml;

/// Names of the committed BESO/D3IL fixtures under `tests/fixtures/import/` (each a
/// `.json`, `.yaml` and `.safetensors`).
pub const BESO_FIXTURES: &[&str] = &["beso_gpt", "beso_gpt_goal", "beso_resmlp", "beso_resmlp_sin"];

#[derive(Debug, Deserialize)]
struct Sampling {
    sampler: String,
    schedule: String,
    sigmas: Vec<f64>,
    x_init: Vec<Vec<f64>>,
    noise: Vec<Vec<Vec<f64>>>,
    result: Vec<Vec<f64>>,
}

#[derive(Debug, Deserialize)]
struct Fixture {
    arch: String,
    states: Vec<Vec<f64>>,
    actions: Vec<Vec<f64>>,
    goals: Option<Vec<Vec<f64>>>,
    sigma: Vec<f64>,
    inner: Vec<Vec<f64>>,
    denoised: Vec<Vec<f64>>,
    sampling: Sampling,
    torch_rows_per_s: f64,
}

/// How an imported network compares with PyTorch on one fixture.
#[derive(Debug, Clone, PartialEq)]
pub struct BesoFixtureReport {
    /// The fixture's name.
    pub name: String,
    /// `diffusion_gpt` or `resmlp`.
    pub arch: String,
    /// Largest `|ours − torch|` of the inner network's outputs.
    pub inner_diff: f64,
    /// Largest difference of the preconditioned denoiser `D(a; σ)` at six σ in [0.05, 20].
    pub denoised_diff: f64,
    /// Largest difference of the final sample of the recorded sampling run.
    pub sampling_diff: f64,
    /// Rows per second PyTorch's denoiser forward reached at batch 1024 on one thread, as the
    /// fixture script recorded it.
    pub torch_rows_per_s: f64,
}

impl BesoFixtureReport {
    /// The largest of the three differences.
    pub fn max_abs_diff(&self) -> f64 {
        self.inner_diff.max(self.denoised_diff).max(self.sampling_diff)
    }
}

fn rows(name: &str, v: &[Vec<f64>]) -> Result<Mat<f32>, BesoError> {
    let w = v.first().map_or(0, Vec::len);
    if v.iter().any(|r| r.len() != w || r.iter().any(|x| !x.is_finite())) {
        return Err(BesoError::Core(vdd_core::CoreError::Config(format!(
            "fixture field `{name}`: ragged or non-finite rows"
        ))));
    }
    Ok(Mat::from_fn(v.len(), w, |i, j| v[i][j] as f32))
}

fn max_diff(ours: &Mat<f32>, theirs: &Mat<f32>) -> f64 {
    if ours.nrows() != theirs.nrows() || ours.ncols() != theirs.ncols() {
        return f64::INFINITY;
    }
    let mut m = 0.0f64;
    for j in 0..ours.ncols() {
        for i in 0..ours.nrows() {
            m = m.max((f64::from(ours[(i, j)]) - f64::from(theirs[(i, j)])).abs());
        }
    }
    m
}

/// Loads fixture `name` from `dir` (its hydra config through [`beso_config_from_yaml`], its
/// state dict through [`BesoTeacher::load_state_dict`]) and compares the inner network, the
/// denoiser and the sampling run (replaying PyTorch's noise) with PyTorch's outputs.
pub fn check_beso_fixture(
    dir: &Path,
    name: &str,
) -> Result<(BesoFixtureReport, BesoTeacher), BesoError> {
    let json_path = dir.join(format!("{name}.json"));
    let text = vdd_core::files::read_bounded_string(&json_path, crate::limits::MAX_TEXT_BYTES)
        .map_err(|source| BesoError::Io { path: json_path.clone(), source })?;
    let fx: Fixture = serde_json::from_str(&text)
        .map_err(|source| BesoError::Json { what: json_path.display().to_string(), source })?;
    let yaml_path = dir.join(format!("{name}.yaml"));
    let yaml = vdd_core::files::read_bounded_string(&yaml_path, crate::limits::MAX_TEXT_BYTES)
        .map_err(|source| BesoError::Io { path: yaml_path.clone(), source })?;
    let config = beso_config_from_yaml(&yaml_path, &yaml, None)?;
    let mut teacher = BesoTeacher::new(config)?;
    teacher.load_state_dict(&dir.join(format!("{name}.safetensors")))?;

    let mut states = rows("states", &fx.states)?;
    if let Some(g) = &fx.goals {
        let g = rows("goals", g)?;
        let s = states.clone();
        states = Mat::from_fn(s.nrows(), s.ncols() + g.ncols(), |i, j| {
            if j < s.ncols() { s[(i, j)] } else { g[(i, j - s.ncols())] }
        });
    }
    let actions = rows("actions", &fx.actions)?;
    let sigma: Vec<f32> = fx.sigma.iter().map(|&s| s as f32).collect();
    let (n, w) = (actions.nrows(), actions.ncols());
    let mut out = Mat::<f32>::zeros(n, w);
    teacher.inner(states.as_ref(), actions.as_ref(), &sigma, out.as_mut())?;
    let inner_diff = max_diff(&out, &rows("inner", &fx.inner)?);
    teacher.denoise(states.as_ref(), actions.as_ref(), &sigma, out.as_mut())?;
    let denoised_diff = max_diff(&out, &rows("denoised", &fx.denoised)?);

    let c = teacher.config().clone();
    let sigmas = c.schedule.sigmas(c.steps, c.sigma_min, c.sigma_max)?;
    let grid_diff = sigmas
        .iter()
        .zip(&fx.sampling.sigmas)
        .map(|(a, b)| (f64::from(*a) - b).abs())
        .fold(0.0f64, f64::max);
    let mut x = rows("x_init", &fx.sampling.x_init)?;
    let mut noise = fx.sampling.noise.iter();
    let mut replay = |buf: &mut [f32]| {
        // Euler's unused draws are recorded too; only the ancestral sampler consumes them.
        if let Some(z) = noise.next() {
            for (b, v) in buf.iter_mut().zip(z.iter().flatten()) {
                *b = *v as f32;
            }
        }
    };
    let mut den = |a: faer::MatRef<'_, f32>, s: &[f32], o: faer::MatMut<'_, f32>| {
        teacher.denoise(states.as_ref(), a, s, o)
    };
    let mut buf = crate::karras::KarrasBuffers::default();
    crate::karras::sample(&mut den, c.sampler, &sigmas, x.as_mut(), &mut replay, &mut buf)?;
    let mut sampling_diff = max_diff(&x, &rows("result", &fx.sampling.result)?);
    let sampler = serde_json::to_value(c.sampler).ok();
    let schedule = serde_json::to_value(c.schedule).ok();
    let same_sampler = sampler.as_ref().and_then(|v| v.as_str()) == Some(&fx.sampling.sampler)
        && schedule.as_ref().and_then(|v| v["kind"].as_str()) == Some(&fx.sampling.schedule);
    if !same_sampler || sigmas.len() != fx.sampling.sigmas.len() || grid_diff > 1e-6 {
        sampling_diff = f64::INFINITY;
    }
    let report = BesoFixtureReport {
        name: name.to_owned(),
        arch: fx.arch,
        inner_diff,
        denoised_diff,
        sampling_diff,
        torch_rows_per_s: fx.torch_rows_per_s,
    };
    Ok((report, teacher))
}

/// Rows per second of the teacher's denoiser (`GCDenoiser.forward` on whole windows) at
/// batch `batch` on the calling thread, timed over at least `min_secs` after one warm-up call.
pub fn beso_rows_per_s(
    teacher: &mut BesoTeacher,
    batch: usize,
    min_secs: f64,
) -> Result<f64, BesoError> {
    use vdd_core::ScoreModel as _;
    let (sd, ad) = (teacher.state_dim(), teacher.action_dim());
    let states = Mat::from_fn(batch, sd, |i, j| ((i * 7 + j * 3) % 11) as f32 * 0.2 - 1.0);
    let actions = Mat::from_fn(batch, ad, |i, j| ((i * 5 + j) % 13) as f32 * 0.15 - 0.9);
    let sigma: Vec<f32> = (0..batch).map(|i| 0.05 + (i % 17) as f32 * 0.1).collect();
    let mut out = Mat::<f32>::zeros(batch, ad);
    teacher.denoise(states.as_ref(), actions.as_ref(), &sigma, out.as_mut())?;
    let (start, mut reps) = (Instant::now(), 0u64);
    while reps == 0 || start.elapsed().as_secs_f64() < min_secs {
        teacher.denoise(states.as_ref(), actions.as_ref(), &sigma, out.as_mut())?;
        reps += 1;
    }
    Ok(batch as f64 * reps as f64 / start.elapsed().as_secs_f64())
}
