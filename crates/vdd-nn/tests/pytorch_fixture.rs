//! PyTorch compatibility: weights written by Python's `safetensors` with torch's names and
//! layouts (see `fixtures/make_fixture.py`) load into our networks, which reproduce the
//! outputs the script recorded.

use std::path::PathBuf;

use faer::Mat;
use serde::Deserialize;
use vdd_nn::{FourierFeatures, Module, ResidualMlp, ResidualMlpConfig, SinusoidalEmbedding, io};

#[derive(Deserialize)]
struct Case {
    file: String,
    config: ResidualMlpConfig,
    output: Vec<Vec<f32>>,
}

#[derive(Deserialize)]
struct Embedding {
    file: Option<String>,
    dim: usize,
    output: Vec<Vec<f32>>,
}

#[derive(Deserialize)]
struct Expected {
    input: Vec<Vec<f32>>,
    residual_mlp: Vec<Case>,
    noise_levels: Vec<Vec<f32>>,
    fourier: Embedding,
    sinusoidal: Embedding,
}

fn fixtures() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests").join("fixtures")
}

fn expected() -> Expected {
    let text = std::fs::read_to_string(fixtures().join("expected.json")).unwrap();
    serde_json::from_str(&text).unwrap()
}

fn matrix(rows: &[Vec<f32>]) -> Mat<f32> {
    Mat::from_fn(rows.len(), rows[0].len(), |i, j| rows[i][j])
}

fn assert_close(got: faer::MatRef<'_, f32>, want: &[Vec<f32>], tol: f32, what: &str) {
    assert_eq!((got.nrows(), got.ncols()), (want.len(), want[0].len()), "{what}: shape");
    for (i, row) in want.iter().enumerate() {
        for (j, &w) in row.iter().enumerate() {
            let g = got[(i, j)];
            assert!((g - w).abs() <= tol, "{what} ({i}, {j}): got {g}, want {w}");
        }
    }
}

#[test]
fn residual_mlps_written_by_python_reproduce_recorded_outputs() {
    let exp = expected();
    let x = matrix(&exp.input);
    assert_eq!(exp.residual_mlp.len(), 2);
    for case in &exp.residual_mlp {
        let path = fixtures().join(&case.file);
        // The config travels in the file's metadata, as our own checkpoints do.
        let meta = io::read_metadata(&path).unwrap();
        let cfg: ResidualMlpConfig = serde_json::from_str(&meta["config"]).unwrap();
        assert_eq!(cfg, case.config);
        // Weights from another seed first, so that only the file can make the outputs right.
        let mut net = ResidualMlp::new(&cfg, &mut vdd_core::Seeds::new(99).stream("init")).unwrap();
        io::load_safetensors(&path, &mut net).unwrap();
        let y = net.forward(x.as_ref());
        // Measured max |difference| ≈ 8e-8 (float32 forward vs the script's float64).
        assert_close(y, &case.output, 2e-6, &case.file);
    }
}

#[test]
fn noise_level_embeddings_match_recorded_outputs() {
    let exp = expected();
    let sigma = matrix(&exp.noise_levels);

    let fourier_file = exp.fourier.file.as_deref().unwrap();
    let mut rng = vdd_core::Seeds::new(99).stream("init");
    let mut ff = FourierFeatures::new(exp.fourier.dim, 30.0, &mut rng).unwrap();
    io::load_safetensors(&fixtures().join(fourier_file), &mut ff).unwrap();
    // Arguments reach 2π·σ·|W| ~ 10² rad, where one f32 ulp of the argument is ~8e-6
    // (measured max |difference| ≈ 7e-6; torch's float32 forward has the same rounding).
    assert_close(ff.forward(sigma.as_ref()), &exp.fourier.output, 5e-5, "fourier");

    assert!(exp.sinusoidal.file.is_none());
    let mut emb = SinusoidalEmbedding::new(exp.sinusoidal.dim).unwrap();
    assert_close(emb.forward(sigma.as_ref()), &exp.sinusoidal.output, 1e-6, "sinusoidal");
}

#[test]
fn the_fixture_comparison_can_fail() {
    // A slightly different function (layer-norm epsilon 1e-3 instead of 1e-5) moves the
    // outputs far beyond the tolerance: the comparison pins down the exact function.
    let exp = expected();
    let case = &exp.residual_mlp[1];
    assert!(case.config.layer_norm);
    let mut net =
        ResidualMlp::new(&case.config, &mut vdd_core::Seeds::new(99).stream("init")).unwrap();
    io::load_safetensors(&fixtures().join(&case.file), &mut net).unwrap();
    net.set_layer_norm_eps(1e-3).unwrap();
    let y = net.forward(matrix(&exp.input).as_ref()).to_owned();
    let worst = (0..y.nrows())
        .flat_map(|i| (0..y.ncols()).map(move |j| (i, j)))
        .map(|(i, j)| (y[(i, j)] - case.output[i][j]).abs())
        .fold(0.0f32, f32::max);
    assert!(worst > 1e-4, "{worst}");
}
