//! A distilled policy (CD, CTM) saved with its deployment loads back and acts the same on raw
//! observations; a file of the other kind or with hostile metadata is refused naming the key.

use faer::Mat;
use vdd_consistency::{
    BoundaryPreconditioning, CdConfig, CdTrainer, ConsistencyConfig, ConsistencyError, CtmConfig,
    CtmTrainer, DistilledPolicy, SavedKind, ScoreTeacher,
};
use vdd_core::{Policy, Trainer as _};
use vdd_data::DeploySpec;
use vdd_diffusion::{GmmTeacher, NetConfig, Preconditioning};

const KIND_KEY: &str = "vdd_consistency.kind";
const MODEL_KEY: &str = "vdd_consistency.model";

/// An exact two-mode teacher (a 1-D state, ignored; 2-D actions).
fn teacher() -> ScoreTeacher<GmmTeacher> {
    let g = GmmTeacher::isotropic(&[1.0; 2], &[vec![1.0, 0.0], vec![-1.0, 0.0]], 0.1).unwrap();
    ScoreTeacher::identity(g).unwrap()
}

fn tiny_net() -> NetConfig {
    NetConfig { hidden_dim: 6, num_blocks: 1, embed_dim: 4, ..Default::default() }
}

/// 16 actions spread over `[−0.5, 0.5]`, a constant 1-D state.
fn data() -> (Mat<f32>, Mat<f32>) {
    (Mat::zeros(16, 1), Mat::from_fn(16, 2, |i, j| (i * (j + 1)) as f32 / 16.0 - 0.5))
}

fn tmp(name: &str) -> std::path::PathBuf {
    let dir = std::env::temp_dir().join(format!("vdd-consistency-io-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(format!("{name}.safetensors"))
}

fn cd_config() -> CdConfig {
    let mut c = CdConfig { net: tiny_net(), num_scales: 6, sigma_max: 10.0, ..Default::default() };
    c.train.batch_size = 5;
    c
}

/// Saves `model` with a chunked deployment, loads it back and checks that it acts the same on
/// raw observations, and that the other kind `Q` refuses the file.
fn round_trip<P: SavedKind, Q: SavedKind>(mut model: DistilledPolicy<P>, name: &str) {
    let chunked = DeploySpec { action_chunk: 2, execute_steps: 2, ..DeploySpec::identity() };
    // A chunk that does not divide the action is refused, and the spec is kept.
    let odd = DeploySpec { action_chunk: 3, execute_steps: 1, ..DeploySpec::identity() };
    assert!(matches!(model.set_deploy_spec(odd), Err(ConsistencyError::Deploy(_))));
    model.set_deploy_spec(chunked.clone()).unwrap();
    model.set_sampling_steps(2).unwrap();
    let path = tmp(name);
    model.save(&path).unwrap();
    let back = DistilledPolicy::<P>::load(&path, 3).unwrap();
    assert_eq!(back.deploy_spec(), &chunked);
    assert_eq!(back.sampling_levels(), model.sampling_levels());
    let (mut a, mut b) = (model.into_policy().unwrap(), back.into_policy().unwrap());
    assert_eq!((b.obs_dim(), b.action_dim()), (1, 1), "one value of the chunk per step");
    a.seed(5);
    b.seed(5);
    for t in 0..4 {
        assert_eq!(a.act(&[t as f32]).unwrap(), b.act(&[t as f32]).unwrap());
    }
    let e = DistilledPolicy::<Q>::load(&path, 0).err().expect("the other kind").to_string();
    assert!(e.contains(KIND_KEY) && e.contains(P::KIND), "{e}");
}

#[test]
fn saved_cd_and_ctm_policies_act_as_before_with_their_deployment() {
    let (s, a) = data();
    let mut t = CdTrainer::new(cd_config(), teacher(), s.as_ref(), a.as_ref()).unwrap();
    t.step().unwrap();
    round_trip::<_, Preconditioning>(t.model().unwrap(), "cd");

    let base =
        ConsistencyConfig { net: tiny_net(), num_scales: 6, sigma_max: 10.0, ..Default::default() };
    let mut c = CtmConfig { base, max_teacher_steps: 2, ..Default::default() };
    c.base.train.batch_size = 5;
    let mut t = CtmTrainer::new(c, teacher(), s.as_ref(), a.as_ref()).unwrap();
    t.step().unwrap();
    round_trip::<_, BoundaryPreconditioning>(t.model().unwrap(), "ctm");
}

#[test]
fn hostile_metadata_is_refused_naming_the_key() {
    let (s, a) = data();
    let t = CdTrainer::new(cd_config(), teacher(), s.as_ref(), a.as_ref()).unwrap();
    let model = t.model().unwrap();
    let path = tmp("hostile-src");
    model.save(&path).unwrap();
    let (meta, _) = vdd_nn::io::read_header(&path).unwrap();
    let json: serde_json::Value = serde_json::from_str(&meta[MODEL_KEY]).unwrap();
    for (field, value, key) in [
        ("sampling_levels", serde_json::json!([5.0, 7.0]), "sampling_levels"),
        ("sigma_min", serde_json::json!(-1.0), "sigma_min"),
        ("net_levels", serde_json::json!(2), "net_levels"),
        ("state_dim", serde_json::json!(1_000_000_000), "shape"),
        ("deploy_spec", serde_json::json!({"obs_window": 0}), MODEL_KEY),
    ] {
        let mut j = json.clone();
        j[field] = value;
        let mut m = meta.clone();
        m.insert(MODEL_KEY.into(), j.to_string());
        let bad = tmp(&format!("hostile-{field}"));
        vdd_nn::io::save_safetensors(&bad, model.net(), &m).unwrap();
        let e = vdd_consistency::ConsistencyModel::load(&bad, 0).unwrap_err().to_string();
        assert!(e.contains(key), "{field}: {e}");
    }
}
