//! The BESO teacher file, importer errors and the policy's behaviour.

use std::path::{Path, PathBuf};

use faer::Mat;
use vdd_core::{Policy, ScoreModel};
use vdd_import::{BesoError, BesoPolicy, BesoTeacher, beso_config_from_yaml, check_beso_fixture};

fn fixtures() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/import")
}

fn gpt() -> BesoTeacher {
    check_beso_fixture(&fixtures(), "beso_gpt").unwrap().1
}

fn yaml() -> String {
    std::fs::read_to_string(fixtures().join("beso_gpt.yaml")).unwrap()
}

fn inputs(t: &BesoTeacher, n: usize) -> (Mat<f32>, Mat<f32>) {
    let s = Mat::from_fn(n, t.state_dim(), |i, j| ((i + 2 * j) % 5) as f32 * 0.3 - 0.6);
    let a = Mat::from_fn(n, t.action_dim(), |i, j| ((3 * i + j) % 7) as f32 * 0.2 - 0.5);
    (s, a)
}

#[test]
fn a_saved_teacher_loads_with_the_same_scores() {
    let mut t = gpt();
    let dir = std::env::temp_dir().join(format!("vdd-import-beso-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("teacher.safetensors");
    t.save(&path).unwrap();
    let mut u = BesoTeacher::load(&path).unwrap();
    assert_eq!(u.config(), t.config());
    let (s, a) = inputs(&t, 5);
    let sigma = [0.1, 0.3, 1.0, 2.0, 5.0];
    let (mut x, mut y) = (Mat::zeros(5, t.action_dim()), Mat::zeros(5, t.action_dim()));
    t.score(a.as_ref(), s.as_ref(), &sigma, x.as_mut()).unwrap();
    u.score(a.as_ref(), s.as_ref(), &sigma, y.as_mut()).unwrap();
    assert_eq!(x, y);
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_fork_scores_bit_for_bit_and_the_range_is_the_samplers() {
    let mut t = gpt();
    let mut f = t.fork().expect("the imported BESO teacher forks");
    let (s, a) = inputs(&t, 4);
    let sigma = [0.1, 0.4, 1.0, 3.0];
    let (mut x, mut y) = (Mat::zeros(4, t.action_dim()), Mat::zeros(4, t.action_dim()));
    t.score(a.as_ref(), s.as_ref(), &sigma, x.as_mut()).unwrap();
    f.score(a.as_ref(), s.as_ref(), &sigma, y.as_mut()).unwrap();
    assert_eq!(x, y);
    let c = t.config();
    assert_eq!(t.noise_range(), Some((c.sigma_min, c.sigma_max)));
}

#[test]
fn the_score_is_tweedie_of_the_denoiser() {
    let mut t = gpt();
    let (s, a) = inputs(&t, 3);
    let sigma = [0.2, 0.7, 3.0];
    let (mut d, mut sc) = (Mat::zeros(3, t.action_dim()), Mat::zeros(3, t.action_dim()));
    t.denoise(s.as_ref(), a.as_ref(), &sigma, d.as_mut()).unwrap();
    t.score(a.as_ref(), s.as_ref(), &sigma, sc.as_mut()).unwrap();
    for i in 0..3 {
        let form = t.denoiser_form(sigma[i]).unwrap();
        for j in 0..t.action_dim() {
            assert!((form.denoise(a[(i, j)], sc[(i, j)]) - d[(i, j)]).abs() < 1e-5);
        }
    }
    assert!(t.denoise(s.as_ref(), a.as_ref(), &[0.2, 0.0, 1.0], d.as_mut()).is_err());
}

fn config_error(yaml: &str) -> String {
    beso_config_from_yaml(Path::new("config.yaml"), yaml, None).unwrap_err().to_string()
}

#[test]
fn malformed_configs_are_refused_naming_the_key() {
    let y = yaml();
    let e = config_error(&y.replace("      n_heads: 2\n", ""));
    assert!(e.contains("agents.model.inner_model.n_heads"), "{e}");
    let e = config_error(&y.replace("sampler_type: euler_ancestral", "sampler_type: lms"));
    assert!(e.contains("agents.sampler_type") && e.contains("lms"), "{e}");
    let e = config_error(&y.replace("sigma_max: 1.0", "sigma_max: .nan"));
    assert!(e.contains("agents.sigma_max"), "{e}");
    let e = config_error(&y.replace("_target_: agents.beso_agent.BesoAgent", "_target_: x.Ddpm"));
    assert!(e.contains("agents._target_"), "{e}");
    let e = config_error(&y.replace("scale_data: false", "scale_data: true"));
    assert!(e.contains("scaler.json"), "{e}");
    let e = config_error("agents: [1, 2");
    assert!(e.contains("malformed YAML"), "{e}");
    // Noise scales whose squares leave f32 (found by the fuzzer: σ_d = 2^64 − 1 imported, and
    // every score was NaN): refused, naming the value.
    for (from, to, key) in [
        ("sigma_data: 0.5\n    inner", "sigma_data: 18446744073709551615\n    inner", "sigma_data"),
        ("sigma_min: 0.1", "sigma_min: 1e-45", "sigma_min"),
        ("sigma_max: 1.0", "sigma_max: 1e25", "sigma_max"),
    ] {
        let e = config_error(&y.replacen(from, to, 1));
        assert!(e.contains(&format!("{key} must lie in")) || e.contains("<= sigma_min <"), "{e}");
    }
}

#[test]
fn weights_of_another_layout_are_refused_naming_the_tensor() {
    let path = fixtures().join("beso_gpt.safetensors");
    let bytes = std::fs::read(&path).unwrap();
    // Two layers in the file, one in the config: the second layer's tensors are unexpected.
    let one_layer = yaml().replace("n_layers: 2", "n_layers: 1");
    let cfg = beso_config_from_yaml(Path::new("c.yaml"), &one_layer, None).unwrap();
    let e = BesoTeacher::new(cfg).unwrap().load_state_dict_bytes(&path, &bytes).unwrap_err();
    assert!(
        matches!(&e, BesoError::UnexpectedTensor { name, .. } if name.contains("blocks.1")),
        "{e}"
    );
    // Three layers in the config: the third layer's first tensor is missing.
    let three = yaml().replace("n_layers: 2", "n_layers: 3");
    let cfg = beso_config_from_yaml(Path::new("c.yaml"), &three, None).unwrap();
    let e = BesoTeacher::new(cfg).unwrap().load_state_dict_bytes(&path, &bytes).unwrap_err();
    assert!(e.to_string().contains("inner_model.blocks.2."), "{e}");
}

#[test]
fn the_policy_is_seeded_windowed_and_clamped() {
    let mut p = BesoPolicy::new(gpt(), 7).unwrap();
    assert_eq!((p.obs_dim(), p.action_dim()), (4, 2));
    let obs = [
        [0.5f32, -0.2, 1.0, 0.3],
        [0.1, 0.0, -1.0, 0.2],
        [0.4, 0.4, 0.4, 0.4],
        [1.0, 2.0, 3.0, 4.0],
    ];
    let run =
        |p: &mut BesoPolicy| -> Vec<Vec<f32>> { obs.iter().map(|o| p.act(o).unwrap()).collect() };
    let first = run(&mut p);
    p.reset();
    p.seed(7);
    assert_eq!(run(&mut p), first);
    p.reset();
    p.seed(8);
    assert_ne!(run(&mut p), first);
    // Statistics that overflow f32 (a scaler.json of ±1e300) are refused, not scored as NaN.
    let mut t = gpt();
    for big in [f32::INFINITY, f32::NEG_INFINITY, 3e38] {
        let mut bad = t.config().scaler.clone();
        bad.obs.offset[0] = big;
        let e = t.set_scaler(bad).unwrap_err().to_string();
        assert!(e.contains("scaler observation statistics"), "{e}");
    }
    // With the scaler's box shrunk to a point, every action is that point (unscaled).
    let mut t = gpt();
    let mut scaler = t.config().scaler.clone();
    scaler.action_min = vec![0.25, -0.5];
    scaler.action_max = vec![0.25, -0.5];
    scaler.action = vdd_core::Affine::new(vec![1.0, 0.0], vec![2.0, 1.0]).unwrap();
    t.set_scaler(scaler).unwrap();
    let mut p = BesoPolicy::new(t, 1).unwrap();
    for o in &obs {
        assert_eq!(p.act(o).unwrap(), vec![1.5, -0.5]);
    }
    assert!(p.act(&[0.0; 3]).is_err());
}
