//! real-stanford/diffusion_policy's `DiffusionUnetLowdimPolicy` (global observation
//! conditioning), from the directory `scripts/import/diffusion_policy_ckpt.py` writes from a
//! `.ckpt`: `config.json` (the run's resolved hydra config) and `model.safetensors` (the
//! policy's state_dict: `model.*` U-Net, `normalizer.params_dict.{obs,action}.{scale,offset}`).

use std::path::Path;

use serde_json::Value;
use vdd_torch::{Unet1dConfig, UnetLayout};

use crate::diffusers::{SamplerKind, SchedulerConfig};
use crate::error::ImportError;
use crate::json::{Fields, MAX_WEIGHTS_BYTES, Prefixed, load_strict, read_bounded, read_json};
use crate::lerobot::{beta_schedule, prediction, read_tensors};
use crate::normalize::{FeatureNorm, NormKind};
use crate::unet_teacher::{UnetTeacher, UnetTeacherSpec};

/// Imports a converted diffusion_policy checkpoint directory.
pub fn import_diffusion_policy(dir: &Path) -> Result<UnetTeacher, ImportError> {
    let cfg_path = dir.join("config.json");
    let json = read_json(&cfg_path)?;
    let root = Fields::new(cfg_path.display().to_string(), &json);
    let policy = root.sub("policy")?;
    let target = policy.str("_target_")?;
    if !target.ends_with("DiffusionUnetLowdimPolicy") {
        return Err(ImportError::bad(&policy.file, "_target_", target));
    }
    let flag = |key: &str| -> Result<bool, ImportError> {
        Ok(match policy.opt(key) {
            None => false,
            Some(_) => policy.bool(key)?,
        })
    };
    if !flag("obs_as_global_cond")? {
        return Err(ImportError::bad(
            &policy.file,
            "obs_as_global_cond",
            "false (only global observation conditioning is imported)",
        ));
    }
    if flag("pred_action_steps_only")? {
        return Err(ImportError::bad(&policy.file, "pred_action_steps_only", true));
    }
    let model = policy.sub("model")?;
    let mtarget = model.str("_target_")?;
    if !mtarget.ends_with("ConditionalUnet1D") {
        return Err(ImportError::bad(&model.file, "_target_", mtarget));
    }
    if model.opt("local_cond_dim").is_some() {
        return Err(ImportError::bad(&model.file, "local_cond_dim", model.get("local_cond_dim")?));
    }
    let ns = policy.sub("noise_scheduler")?;
    let ntarget = ns.str("_target_")?;
    let sampler = if ntarget.ends_with("DDPMScheduler") {
        if let Some(v) = ns.opt("variance_type").and_then(Value::as_str) {
            if v != "fixed_small" {
                return Err(ImportError::bad(&ns.file, "variance_type", v));
            }
        }
        SamplerKind::Ddpm
    } else if ntarget.ends_with("DDIMScheduler") {
        SamplerKind::Ddim
    } else {
        return Err(ImportError::bad(&ns.file, "_target_", ntarget));
    };
    let or = |key: &str, default: f32| -> Result<f32, ImportError> {
        match ns.opt(key) {
            None => Ok(default),
            Some(_) => ns.f32(key),
        }
    };
    let n_train = ns.usize("num_train_timesteps")?;
    let scheduler = SchedulerConfig {
        sampler,
        num_train_timesteps: n_train,
        beta_start: or("beta_start", 1e-4)?,
        beta_end: or("beta_end", 0.02)?,
        beta_schedule: beta_schedule(&ns, "beta_schedule")?,
        prediction: prediction(&ns, "prediction_type")?,
        clip_sample: match ns.opt("clip_sample") {
            None => true,
            Some(_) => ns.bool("clip_sample")?,
        },
        clip_sample_range: or("clip_sample_range", 1.0)?,
        num_inference_steps: match policy.opt("num_inference_steps") {
            None => n_train,
            Some(_) => policy.usize("num_inference_steps")?,
        },
    };
    let n_obs = policy.usize("n_obs_steps")?;
    let obs_dim = policy.usize("obs_dim")?;
    let act_dim = policy.usize("action_dim")?;
    let unet = Unet1dConfig {
        input_dim: model.usize("input_dim")?,
        global_cond_dim: model.usize("global_cond_dim")?,
        step_embed_dim: model.usize("diffusion_step_embed_dim")?,
        down_dims: model.usizes("down_dims")?,
        kernel_size: model.usize("kernel_size")?,
        n_groups: model.usize("n_groups")?,
        film_scale: match model.opt("cond_predict_scale") {
            None => false,
            Some(_) => model.bool("cond_predict_scale")?,
        },
        layout: UnetLayout::DiffusionPolicy,
    };
    // Sizes first: nothing is read or built for a network past the limits.
    let horizon = policy.usize("horizon")?;
    crate::limits::check_unet(&unet, horizon, n_obs).map_err(|r| r.import(&model.file))?;
    let weights = dir.join("model.safetensors");
    let bytes = read_bounded(&weights, MAX_WEIGHTS_BYTES)?;
    let tensors = read_tensors(&weights, &bytes)?;
    let file = weights.display().to_string();
    let norm = |name: &str, dim: usize| -> Result<FeatureNorm, ImportError> {
        let get = |stat: &str| -> Result<Vec<f32>, ImportError> {
            let key = format!("normalizer.params_dict.{name}.{stat}");
            let v = tensors.get(&key).ok_or_else(|| ImportError::missing(&file, &key))?;
            if v.len() != dim {
                return Err(ImportError::bad(
                    &file,
                    key,
                    format!("{} values for a {dim}-wide feature", v.len()),
                ));
            }
            Ok(v.clone())
        };
        FeatureNorm::new(name, NormKind::ScaleOffset, get("scale")?, get("offset")?, 0.0)
    };
    let obs_norm = norm("obs", obs_dim)?;
    let action_norm = norm("action", act_dim)?;
    let spec = UnetTeacherSpec {
        source: "diffusion_policy".into(),
        unet,
        scheduler,
        horizon,
        n_obs_steps: n_obs,
        n_action_steps: policy.usize("n_action_steps")?,
        action_start: if flag("oa_step_convention")? { n_obs.saturating_sub(1) } else { n_obs },
        obs_features: vec![obs_norm.spec()],
        action: action_norm.spec(),
        features: vdd_data::features::IDENTITY.id(),
        obs_map: None,
    };
    spec.validate(&policy.file)?;
    let mut teacher = UnetTeacher::new(spec)?;
    teacher.set_normalizers(vec![obs_norm], action_norm)?;
    let mut view = Prefixed { inner: teacher.unet_mut(), prefix: "model" };
    load_strict(&weights, &bytes, &mut view, &["model.", "obs_encoder."])?;
    Ok(teacher)
}
