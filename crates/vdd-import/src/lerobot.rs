//! LeRobot's `DiffusionPolicy` as `save_pretrained` writes it: `config.json`,
//! `model.safetensors` (`diffusion.unet.*`) and the normaliser statistics, from the
//! pre/post-processor files of lerobot ≥ 0.4 (`policy_preprocessor.json` and the
//! `normalizer_processor` state file) or, for older versions, from the model's
//! `normalize_inputs.buffer_*` / `unnormalize_outputs.buffer_*` tensors.

use std::collections::HashMap;
use std::path::Path;

use safetensors::SafeTensors;
use serde_json::Value;
use vdd_data::features::FeatureMapId;
use vdd_torch::{Unet1dConfig, UnetLayout};

use crate::diffusers::{BetaSchedule, Prediction, SamplerKind, SchedulerConfig};
use crate::error::ImportError;
use crate::json::{Fields, MAX_WEIGHTS_BYTES, Prefixed, load_strict, read_bounded, read_json};
use crate::normalize::{FeatureNorm, NormKind};
use crate::options::{ObsMap, Sampler};
use crate::unet_teacher::{UnetTeacher, UnetTeacherSpec};

/// The file a training run may write beside LeRobot's files to record the registered feature
/// map ([`vdd_data::features`]) its observations went through, as
/// `{"name": "position_and_lag", "version": 1}`; absent, the policy sees raw observations.
/// `scripts/import/train_lerobot_avoiding.py` writes it.
pub const FEATURES_FILE: &str = "vdd_features.json";

/// The observation features a state-only LeRobot diffusion policy conditions on, in order.
const OBS_KEYS: [&str; 2] = ["observation.state", "observation.environment_state"];

/// What a user states when importing a LeRobot policy, beyond the package's files.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct LerobotOptions {
    /// Where the policy's `observation.*` features come from in the raw observation; `None`:
    /// the raw observation is the features concatenated in the policy's order
    /// (`observation.state`, then `observation.environment_state`). Checked against the
    /// features' shapes and stored in the teacher file.
    pub obs_map: Option<ObsMap>,
    /// The sampler the teacher acts with; `None`: the package's (`noise_scheduler_type`,
    /// `num_inference_steps`). Can be changed after loading with
    /// [`UnetTeacher::set_sampler`].
    pub sampler: Option<Sampler>,
}

/// Imports a LeRobot diffusion policy directory (the raw observation is its features in
/// order, the package's sampler: [`import_lerobot_with`] to state them).
pub fn import_lerobot(dir: &Path) -> Result<UnetTeacher, ImportError> {
    import_lerobot_with(dir, &LerobotOptions::default())
}

/// Imports a LeRobot diffusion policy directory with the user's `options`: an observation map
/// that does not fit the policy's features (a feature missing or of another width, an index
/// out of range or repeated within a feature, a key the policy does not have) is refused with
/// an error naming the map's key.
///
/// ```
/// # let dir = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/import/lerobot_unet_ddim");
/// use vdd_import::{LerobotOptions, ObsMap, import_lerobot_with};
/// // The fixture's policy has observation.state [4] and observation.environment_state [3].
/// let obs_map: ObsMap = "observation.state=3..7;observation.environment_state=0..3".parse()?;
/// let options = LerobotOptions { obs_map: Some(obs_map), sampler: None };
/// let teacher = import_lerobot_with(&dir, &options)?;
/// assert_eq!(teacher.spec().raw_obs_dim(), 7);
/// let bad: ObsMap = "observation.state=0..3;observation.environment_state=4..7".parse()?;
/// let err = import_lerobot_with(&dir, &LerobotOptions { obs_map: Some(bad), sampler: None });
/// assert!(err.unwrap_err().to_string().contains("obs_map.observation.state"));
/// # Ok::<(), vdd_import::ImportError>(())
/// ```
pub fn import_lerobot_with(
    dir: &Path,
    options: &LerobotOptions,
) -> Result<UnetTeacher, ImportError> {
    let cfg_path = dir.join("config.json");
    let cfg_json = read_json(&cfg_path)?;
    let cfg = Fields::new(cfg_path.display().to_string(), &cfg_json);
    let kind = cfg.str("type")?;
    if kind != "diffusion" {
        return Err(ImportError::bad(&cfg.file, "type", kind));
    }
    let inputs = cfg.sub("input_features")?;
    let in_map = inputs
        .value
        .as_object()
        .ok_or_else(|| ImportError::bad(&cfg.file, "input_features", inputs.value))?;
    if let Some(k) = in_map.keys().find(|k| !OBS_KEYS.contains(&k.as_str())) {
        return Err(ImportError::bad(
            &cfg.file,
            format!("input_features.{k}"),
            "an input other than observation.state / observation.environment_state (images are not imported)",
        ));
    }
    let norm_map = cfg.sub("normalization_mapping")?;
    let norm_kind = |ty: &str| -> Result<NormKind, ImportError> {
        match norm_map.opt(ty).and_then(Value::as_str) {
            None | Some("IDENTITY") => Ok(NormKind::Identity),
            Some("MEAN_STD") => Ok(NormKind::MeanStd),
            Some("MIN_MAX" | "QUANTILES" | "QUANTILE10") => Ok(NormKind::MinMax),
            Some(other) => Err(ImportError::bad(&norm_map.file, ty, other)),
        }
    };
    let feature = |fields: &Fields<'_>, key: &str| -> Result<(String, usize), ImportError> {
        let f = fields.sub(key)?;
        let ty = f.str("type")?.to_owned();
        let shape = f.usizes("shape")?;
        if shape.len() != 1 || shape[0] == 0 {
            return Err(ImportError::bad(&f.file, "shape", format!("{shape:?}")));
        }
        Ok((ty, shape[0]))
    };
    let mut obs = Vec::new();
    for key in OBS_KEYS {
        if in_map.contains_key(key) {
            let (ty, dim) = feature(&inputs, key)?;
            obs.push((key, norm_kind(&ty)?, dim));
        }
    }
    if obs.first().map(|o| o.0) != Some(OBS_KEYS[0]) {
        return Err(ImportError::missing(&inputs.file, OBS_KEYS[0]));
    }
    let outputs = cfg.sub("output_features")?;
    let (aty, adim) = feature(&outputs, "action")?;
    let akind = norm_kind(&aty)?;

    let n_obs = cfg.usize("n_obs_steps")?;
    let obs_dim: usize = obs.iter().map(|o| o.2).sum();
    let sampler = match cfg.str("noise_scheduler_type")? {
        "DDPM" => SamplerKind::Ddpm,
        "DDIM" => SamplerKind::Ddim,
        other => return Err(ImportError::bad(&cfg.file, "noise_scheduler_type", other)),
    };
    let n_train = cfg.usize("num_train_timesteps")?;
    let scheduler = SchedulerConfig {
        sampler,
        num_train_timesteps: n_train,
        beta_start: cfg.f32("beta_start")?,
        beta_end: cfg.f32("beta_end")?,
        beta_schedule: beta_schedule(&cfg, "beta_schedule")?,
        prediction: prediction(&cfg, "prediction_type")?,
        clip_sample: cfg.bool("clip_sample")?,
        clip_sample_range: cfg.f32("clip_sample_range")?,
        num_inference_steps: match cfg.opt("num_inference_steps") {
            None => n_train,
            Some(_) => cfg.usize("num_inference_steps")?,
        },
    };
    let spec = UnetTeacherSpec {
        source: "lerobot".into(),
        unet: Unet1dConfig {
            input_dim: adim,
            global_cond_dim: obs_dim * n_obs,
            step_embed_dim: cfg.usize("diffusion_step_embed_dim")?,
            down_dims: cfg.usizes("down_dims")?,
            kernel_size: cfg.usize("kernel_size")?,
            n_groups: cfg.usize("n_groups")?,
            film_scale: cfg.bool("use_film_scale_modulation")?,
            layout: UnetLayout::Lerobot,
        },
        scheduler,
        horizon: cfg.usize("horizon")?,
        n_obs_steps: n_obs,
        n_action_steps: cfg.usize("n_action_steps")?,
        action_start: n_obs.saturating_sub(1),
        obs_features: Vec::new(),
        action: FeatureNorm::identity("action", adim).spec(),
        features: read_features(dir)?,
        obs_map: None,
    };

    // Sizes first: nothing is read or built for a network past the limits.
    crate::limits::check_unet(&spec.unet, spec.horizon, n_obs).map_err(|r| r.import(&cfg.file))?;
    let model_path = dir.join("model.safetensors");
    let model_bytes = read_bounded(&model_path, MAX_WEIGHTS_BYTES)?;
    let stats = Stats::find(dir, &model_path, &model_bytes)?;
    let eps = stats.eps;
    let norm = |name: &str, kind: NormKind, dim: usize| -> Result<FeatureNorm, ImportError> {
        let (ka, kb) = match kind {
            NormKind::Identity => return Ok(FeatureNorm::identity(name, dim)),
            NormKind::MeanStd => ("mean", "std"),
            _ => ("min", "max"),
        };
        let (ka, kb) = match (kind, norm_mode_name(&cfg_json, name)) {
            (NormKind::MinMax, Some("QUANTILES")) => ("q01", "q99"),
            (NormKind::MinMax, Some("QUANTILE10")) => ("q10", "q90"),
            _ => (ka, kb),
        };
        let a = stats.get(name, ka, dim)?;
        let b = stats.get(name, kb, dim)?;
        FeatureNorm::new(name, kind, a, b, eps)
    };
    let obs_norms =
        obs.iter().map(|&(k, kind, d)| norm(k, kind, d)).collect::<Result<Vec<_>, _>>()?;
    let action_norm = norm("action", akind, adim)?;
    let obs_features: Vec<_> = obs_norms.iter().map(FeatureNorm::spec).collect();
    let obs_map = match &options.obs_map {
        Some(m) => {
            m.check_features(&obs_features, "observation map")?;
            Some(m.ordered(&obs_features))
        }
        None => None,
    };
    let scheduler = match options.sampler {
        Some(s) => s.apply(&spec.scheduler)?,
        None => spec.scheduler.clone(),
    };
    let spec =
        UnetTeacherSpec { obs_features, action: action_norm.spec(), obs_map, scheduler, ..spec };
    spec.validate(&cfg.file)?;
    let mut teacher = UnetTeacher::new(spec)?;
    teacher.set_normalizers(obs_norms, action_norm)?;
    let mut view = Prefixed { inner: teacher.unet_mut(), prefix: "diffusion.unet" };
    load_strict(&model_path, &model_bytes, &mut view, &["diffusion."])?;
    Ok(teacher)
}

/// The feature map recorded in [`FEATURES_FILE`], the identity without one.
fn read_features(dir: &Path) -> Result<FeatureMapId, ImportError> {
    let path = dir.join(FEATURES_FILE);
    if !path.exists() {
        return Ok(vdd_data::features::IDENTITY.id());
    }
    let id: FeatureMapId = serde_json::from_value(read_json(&path)?)
        .map_err(|e| ImportError::bad(path.display().to_string(), "feature map", e))?;
    id.resolve().map_err(|e| ImportError::bad(path.display().to_string(), "feature map", e))?;
    Ok(id)
}

/// The `normalization_mapping` entry of a feature's type, for the quantile variants.
fn norm_mode_name<'a>(cfg: &'a Value, feature: &str) -> Option<&'a str> {
    let ty = if feature == "action" {
        cfg.get("output_features")?.get(feature)?.get("type")?.as_str()?
    } else {
        cfg.get("input_features")?.get(feature)?.get("type")?.as_str()?
    };
    cfg.get("normalization_mapping")?.get(ty)?.as_str()
}

pub(crate) fn beta_schedule(f: &Fields<'_>, key: &str) -> Result<BetaSchedule, ImportError> {
    match f.str(key)? {
        "linear" => Ok(BetaSchedule::Linear),
        "scaled_linear" => Ok(BetaSchedule::ScaledLinear),
        "squaredcos_cap_v2" => Ok(BetaSchedule::SquaredcosCapV2),
        other => Err(ImportError::bad(&f.file, key, other)),
    }
}

pub(crate) fn prediction(f: &Fields<'_>, key: &str) -> Result<Prediction, ImportError> {
    match f.str(key)? {
        "epsilon" => Ok(Prediction::Epsilon),
        "sample" => Ok(Prediction::Sample),
        other => Err(ImportError::bad(&f.file, key, other)),
    }
}

/// Where the normaliser statistics are.
struct Stats {
    file: String,
    tensors: HashMap<String, Vec<f32>>,
    eps: f32,
    /// Older lerobot: `normalize_inputs.buffer_observation_state.min` style names.
    legacy: bool,
}

impl Stats {
    fn find(dir: &Path, model_path: &Path, model_bytes: &[u8]) -> Result<Self, ImportError> {
        let pre = dir.join("policy_preprocessor.json");
        if !pre.exists() {
            return Ok(Self {
                file: model_path.display().to_string(),
                tensors: read_tensors(model_path, model_bytes)?,
                eps: 1e-8,
                legacy: true,
            });
        }
        let json = read_json(&pre)?;
        let f = Fields::new(pre.display().to_string(), &json);
        let steps = f
            .get("steps")?
            .as_array()
            .ok_or_else(|| ImportError::bad(&f.file, "steps", "not a list"))?;
        let step = steps
            .iter()
            .find(|s| {
                s.get("registry_name").and_then(Value::as_str) == Some("normalizer_processor")
            })
            .ok_or_else(|| {
                ImportError::missing(&f.file, "steps[registry_name = normalizer_processor]")
            })?;
        let sf = Fields::new(format!("{}: normalizer_processor", f.file), step);
        let state = sf.str("state_file")?;
        if state.contains('/') || state.contains('\\') || state.starts_with('.') {
            return Err(ImportError::bad(&sf.file, "state_file", state));
        }
        let eps = sf.sub("config")?.opt("eps").and_then(Value::as_f64).unwrap_or(1e-8) as f32;
        let path = dir.join(state);
        let bytes = read_bounded(&path, MAX_WEIGHTS_BYTES)?;
        Ok(Self {
            file: path.display().to_string(),
            tensors: read_tensors(&path, &bytes)?,
            eps,
            legacy: false,
        })
    }

    fn get(&self, feature: &str, stat: &str, dim: usize) -> Result<Vec<f32>, ImportError> {
        let key = if self.legacy {
            let module =
                if feature == "action" { "unnormalize_outputs" } else { "normalize_inputs" };
            format!("{module}.buffer_{}.{stat}", feature.replace('.', "_"))
        } else {
            format!("{feature}.{stat}")
        };
        let v = self.tensors.get(&key).ok_or_else(|| ImportError::missing(&self.file, &key))?;
        if v.len() != dim {
            return Err(ImportError::bad(
                &self.file,
                key,
                format!("{} values for a {dim}-wide feature", v.len()),
            ));
        }
        Ok(v.clone())
    }
}

/// Every f32/f64 tensor of a safetensors file, flattened.
pub(crate) fn read_tensors(
    path: &Path,
    bytes: &[u8],
) -> Result<HashMap<String, Vec<f32>>, ImportError> {
    let file = SafeTensors::deserialize(bytes)
        .map_err(|e| ImportError::bad(path.display().to_string(), "safetensors", e))?;
    let mut out = HashMap::new();
    for (name, view) in file.tensors() {
        let data = view.data();
        let v: Vec<f32> = match view.dtype() {
            safetensors::Dtype::F32 => {
                data.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
            }
            safetensors::Dtype::F64 => data
                .chunks_exact(8)
                .map(|c| {
                    f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]) as f32
                })
                .collect(),
            _ => continue,
        };
        out.insert(name, v);
    }
    Ok(out)
}
