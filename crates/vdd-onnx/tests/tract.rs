//! The exported graph, run by a pure-Rust ONNX runtime (tract), equals the Rust policy's
//! components to 1e-5, for every architecture the exporter supports.

use faer::Mat;
use tract_onnx::prelude::*;
use vdd_core::Affine;
use vdd_data::DeploySpec;
use vdd_data::features::POSITION_AND_LAG;
use vdd_moe::{ExpertKind, GatingKind, Moe, MoeConfig, NetworkConfig};
use vdd_nn::Activation;

fn run(bytes: &[u8], obs: &Mat<f32>) -> Vec<Vec<f32>> {
    let (n, w) = (obs.nrows(), obs.ncols());
    let model = tract_onnx::onnx()
        .model_for_read(&mut &bytes[..])
        .expect("tract reads the graph")
        .with_input_fact(0, f32::fact([n, w]).into())
        .expect("input fact")
        .into_optimized()
        .expect("optimised")
        .into_runnable()
        .expect("runnable");
    let data: Vec<f32> = (0..n).flat_map(|i| (0..w).map(move |j| obs[(i, j)])).collect();
    let input: Tensor = tract_ndarray::Array2::from_shape_vec((n, w), data).unwrap().into();
    let out = model.run(tvec!(input.into())).expect("tract runs the graph");
    out.iter().map(|t| t.to_plain_array_view::<f32>().unwrap().iter().copied().collect()).collect()
}

fn close(what: &str, got: &[f32], want: &[f32]) {
    assert_eq!(got.len(), want.len(), "{what}: lengths");
    for (k, (g, w)) in got.iter().zip(want).enumerate() {
        assert!((g - w).abs() <= 1e-5 * (1.0 + w.abs()), "{what}[{k}]: onnx {g} vs rust {w}");
    }
}

fn mixtures() -> Vec<Moe> {
    let mut out = Vec::new();
    let acts = [Activation::Mish, Activation::Relu, Activation::Gelu, Activation::Silu];
    let mut k = 0;
    for kind in [ExpertKind::Diagonal, ExpertKind::Full] {
        for shared in [true, false] {
            for gating in [GatingKind::Learned, GatingKind::Uniform] {
                let net = NetworkConfig { hidden_dim: 16, num_blocks: 2, activation: acts[k % 4] };
                k += 1;
                let cfg = MoeConfig {
                    expert_kind: kind,
                    shared_trunk: shared,
                    gating,
                    experts_network: net.clone(),
                    gating_network: net,
                    ..MoeConfig::toy(8, 3, 4)
                };
                let mut moe = Moe::from_config(cfg, k as u64).unwrap();
                moe.set_normalizers(
                    Some(
                        Affine::new((0..8).map(|i| 0.1 * i as f32).collect(), vec![1.5; 8])
                            .unwrap(),
                    ),
                    Some(Affine::new(vec![1.0, -2.0, 0.5], vec![0.5, 2.0, 3.0]).unwrap()),
                )
                .unwrap();
                // Windows of two 4-D observations (position_and_lag) on half of them.
                if k % 2 == 0 {
                    let spec = DeploySpec { obs_window: 2, ..DeploySpec::identity() };
                    moe.set_deploy_spec(spec.with_features(POSITION_AND_LAG)).unwrap();
                }
                out.push(moe);
            }
        }
    }
    out
}

#[test]
fn onnx_outputs_equal_the_components_of_the_rust_policy() {
    for moe in mixtures() {
        let bytes = vdd_onnx::export(&moe).unwrap();
        let obs = Mat::from_fn(5, 8, |i, j| ((i * 8 + j) as f32 * 0.731).sin() * 2.0);
        let mut policy = moe.clone().into_policy().unwrap();
        let c = vdd_moe::deployed_components(&mut policy, obs.as_ref()).unwrap();
        let out = run(&bytes, &obs);
        let cfg = moe.config();
        close(&format!("{cfg:?} log_gating"), &out[0], &c.log_gating);
        close(&format!("{cfg:?} means"), &out[1], &c.means);
        close(&format!("{cfg:?} scale_tril"), &out[2], &c.scale_tril);
    }
}

#[test]
fn a_saved_policy_exports_to_a_file() {
    let moe = mixtures().remove(1);
    let dir = std::env::temp_dir().join(format!("vdd-onnx-test-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let (model, out) = (dir.join("policy.safetensors"), dir.join("policy.onnx"));
    moe.save(&model).unwrap();
    vdd_onnx::export_file(&model, &out).unwrap();
    assert_eq!(std::fs::read(&out).unwrap(), vdd_onnx::export(&moe).unwrap());
    let err = vdd_onnx::export_file(&dir.join("missing.safetensors"), &out).unwrap_err();
    assert!(err.to_string().contains("missing.safetensors"), "{err}");
    std::fs::remove_dir_all(&dir).unwrap();
}
