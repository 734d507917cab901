//! Save a mixture of experts with its deployment spec, load it back as a policy on raw
//! observations, act, and see which expert acted.
//!
//! ```text
//! cargo run -p vdd-moe --example load_and_act
//! ```
//!
//! The mixture here is untrained (a trained one comes from `vdd`, `vdd-mixture` or
//! `vdd-consistency` and is saved the same way). It was "trained" on windows of 2 featured
//! observations (`position_and_lag`: the 4-D Avoiding observation) and predicts chunks of 3
//! 2-D actions, of which the policy executes 2 before predicting again. One file holds the
//! weights, the normalisers and that spec; `load_policy` needs nothing else.

use vdd_core::{Affine, Policy};
use vdd_data::DeploySpec;
use vdd_data::features::POSITION_AND_LAG;
use vdd_moe::{ActMode, Moe, MoeConfig};

fn main() -> Result<(), Box<dyn std::error::Error>> {
    // States: a window of 2 featured observations (8 numbers); actions: a chunk of 3 (6).
    let mut moe = Moe::from_config(MoeConfig::toy(8, 6, 4), 0)?;
    moe.set_normalizers(
        Some(Affine::new(vec![0.5; 8], vec![0.2; 8])?),
        Some(Affine::new(vec![0.0; 6], vec![0.01; 6])?),
    )?;
    moe.set_act_mode(ActMode { greedy_gating: false, sample_action: false, hold_steps: 0 });
    let spec =
        DeploySpec { obs_window: 2, action_chunk: 3, execute_steps: 2, ..DeploySpec::identity() };
    moe.set_deploy_spec(spec.with_features(POSITION_AND_LAG))?;

    let dir = std::env::temp_dir().join(format!("vdd-moe-example-{}", std::process::id()));
    std::fs::create_dir_all(&dir)?;
    let path = dir.join("policy.safetensors");
    moe.save(&path)?;
    println!("saved {} ({} bytes)", path.display(), std::fs::metadata(&path)?.len());

    // Deployment: raw 4-D observations in, one 2-D action per step out.
    let mut policy = vdd_moe::load_policy(&path)?;
    println!("loaded: {} -> {} (raw observation -> action)", policy.obs_dim(), policy.action_dim());
    policy.seed(7);
    policy.reset();
    let mut obs = [0.5f32, -0.3, 0.5, -0.3];
    for step in 0..5 {
        let action = policy.act(&obs)?;
        println!(
            "step {step}: obs {obs:?} -> action [{:+.4}, {:+.4}], experts of the last prediction {:?}",
            action[0],
            action[1],
            policy.inner().last_experts()
        );
        // Move the desired position by the action; the current position follows it.
        obs = [obs[0] + action[0], obs[1] + action[1], obs[0], obs[1]];
    }
    std::fs::remove_dir_all(&dir)?;
    Ok(())
}
