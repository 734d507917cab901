//! Reading a BESO/D3IL run directory: the hydra `config.yaml` (with OmegaConf's `${key}`
//! interpolations resolved), the state dict converted to safetensors by
//! `scripts/import/beso_pth.py`, and the data scaler it exported.

use std::path::{Path, PathBuf};

use serde::Deserialize;
use serde_yaml_ng::Value;
use vdd_core::Affine;
use vdd_diffusion::KarrasSampler;
use vdd_torch::{BlockNorm, DiffusionGptConfig, MlpActivation, ResMlpScoreConfig, SigmaEmbedding};

use crate::beso::{BesoNetworkConfig, BesoScaler, BesoTeacher, BesoTeacherConfig};
use crate::beso_error::BesoError;
use crate::karras::SigmaSchedule;
use crate::limits::{MAX_NESTING, MAX_TEXT_BYTES, json_nesting, yaml_nesting};

/// The state dict as `beso_pth.py` writes it next to `model_state_dict.pth`.
pub const BESO_WEIGHTS_FILE: &str = "model_state_dict.safetensors";
/// The scaler statistics as `beso_pth.py` writes them.
pub const BESO_SCALER_FILE: &str = "scaler.json";
fn read_text(path: &Path) -> Result<String, BesoError> {
    vdd_core::files::read_bounded_string(path, MAX_TEXT_BYTES)
        .map_err(|source| BesoError::Io { path: path.to_owned(), source })
}

/// Refuses text nested deeper than [`MAX_NESTING`] (`depth` as measured by
/// [`crate::limits`]'s pre-scan) before a parser sees it.
fn check_nesting(path: &Path, depth: usize) -> Result<(), BesoError> {
    if depth > MAX_NESTING {
        return Err(BesoError::BadValue {
            path: path.to_owned(),
            key: "<nesting depth>".into(),
            value: format!("more than {depth} levels"),
            reason: format!("nested deeper than {MAX_NESTING} levels"),
        });
    }
    Ok(())
}

/// A hydra config with its root kept for `${…}` interpolations.
struct Hydra {
    path: PathBuf,
    root: Value,
}

impl Hydra {
    fn lookup<'a>(&'a self, key: &str, depth: usize) -> Option<&'a Value> {
        let mut v = &self.root;
        for part in key.split('.') {
            v = v.get(part)?;
        }
        self.resolve(v, depth)
    }

    /// Follows `"${a.b}"` interpolations (at most 16 deep).
    fn resolve<'a>(&'a self, v: &'a Value, depth: usize) -> Option<&'a Value> {
        match v.as_str() {
            Some(s) if s.starts_with("${") && s.ends_with('}') && depth < 16 => {
                self.lookup(&s[2..s.len() - 1], depth + 1)
            }
            _ => Some(v),
        }
    }

    fn get(&self, key: &str) -> Option<&Value> {
        self.lookup(key, 0).filter(|v| !v.is_null())
    }

    fn req(&self, key: &str) -> Result<&Value, BesoError> {
        self.get(key)
            .ok_or_else(|| BesoError::MissingKey { path: self.path.clone(), key: key.into() })
    }

    fn bad(&self, key: &str, v: &Value, reason: &str) -> BesoError {
        let value = serde_yaml_ng::to_string(v).unwrap_or_default().trim().to_owned();
        BesoError::BadValue {
            path: self.path.clone(),
            key: key.into(),
            value,
            reason: reason.into(),
        }
    }

    fn f32(&self, key: &str) -> Result<f32, BesoError> {
        let v = self.req(key)?;
        let x = v.as_f64().or_else(|| v.as_str().and_then(|s| s.trim().parse().ok()));
        match x {
            Some(x) if x.is_finite() && x.abs() < 1e30 => Ok(x as f32),
            _ => Err(self.bad(key, v, "expected a finite number")),
        }
    }

    fn usize(&self, key: &str) -> Result<usize, BesoError> {
        let v = self.req(key)?;
        match v.as_u64() {
            Some(x) if x <= 1 << 20 => Ok(x as usize),
            _ => Err(self.bad(key, v, "expected a non-negative integer below 2^20")),
        }
    }

    fn usize_or(&self, key: &str, default: usize) -> Result<usize, BesoError> {
        if self.get(key).is_none() { Ok(default) } else { self.usize(key) }
    }

    fn bool_or(&self, key: &str, default: bool) -> Result<bool, BesoError> {
        match self.get(key) {
            None => Ok(default),
            Some(v) => v.as_bool().ok_or_else(|| self.bad(key, v, "expected true or false")),
        }
    }

    fn str(&self, key: &str) -> Result<&str, BesoError> {
        let v = self.req(key)?;
        v.as_str().ok_or_else(|| self.bad(key, v, "expected a string"))
    }

    fn str_or<'a>(&'a self, key: &str, default: &'a str) -> Result<&'a str, BesoError> {
        if self.get(key).is_none() { Ok(default) } else { self.str(key) }
    }
}

/// The hydra config of a run: `DIR/.hydra/config.yaml` or `DIR/config.yaml`.
fn find_config(dir: &Path) -> Result<PathBuf, BesoError> {
    let candidates = [dir.join(".hydra").join("config.yaml"), dir.join("config.yaml")];
    candidates.iter().find(|p| p.is_file()).cloned().ok_or_else(|| BesoError::Io {
        path: candidates[1].clone(),
        source: std::io::Error::new(
            std::io::ErrorKind::NotFound,
            "no hydra config.yaml in the run",
        ),
    })
}

/// Builds the teacher configuration from a BESO/D3IL hydra config (`config.yaml` text) and
/// the scaler; `path` names the file in errors.
///
/// Supported: `agents._target_` D3IL's `agents.beso_agent.BesoAgent` (linear σ schedule) or
/// BESO's `beso.agents.diffusion_agents.beso_agent.BesoAgent` (exponential), a `GCDenoiser`
/// around `DiffusionGPT` or `GCTimeScoreNetwork` (ResNet-MLP, without goals, spectral norm
/// or BatchNorm), and the samplers `euler`, `euler_ancestral`, `ddim` and `heun`.
pub fn beso_config_from_yaml(
    path: &Path,
    yaml: &str,
    scaler: Option<BesoScaler>,
) -> Result<BesoTeacherConfig, BesoError> {
    if yaml.len() as u64 > MAX_TEXT_BYTES {
        return Err(BesoError::BadValue {
            path: path.to_owned(),
            key: "<file size>".into(),
            value: yaml.len().to_string(),
            reason: format!("larger than {MAX_TEXT_BYTES} bytes"),
        });
    }
    check_nesting(path, yaml_nesting(yaml))?;
    let root: Value = serde_yaml_ng::from_str(yaml)
        .map_err(|source| BesoError::Yaml { path: path.to_owned(), source })?;
    let h = Hydra { path: path.to_owned(), root };
    let agent = h.str("agents._target_")?;
    let schedule = match agent {
        "agents.beso_agent.BesoAgent" => SigmaSchedule::Linear,
        "beso.agents.diffusion_agents.beso_agent.BesoAgent" => SigmaSchedule::Exponential,
        _ => return Err(h.bad("agents._target_", h.req("agents._target_")?, "not a BESO agent")),
    };
    let model = h.str("agents.model._target_")?;
    if !model.ends_with("score_wrappers.GCDenoiser") {
        return Err(h.bad(
            "agents.model._target_",
            h.req("agents.model._target_")?,
            "expected GCDenoiser",
        ));
    }
    let inner = "agents.model.inner_model";
    let k = |s: &str| format!("{inner}.{s}");
    let target = h.str(&k("_target_"))?;
    let mut goal_window = 0;
    let network = if target.ends_with("score_gpts.DiffusionGPT") {
        let c = DiffusionGptConfig {
            state_dim: h.usize(&k("state_dim"))?,
            action_dim: h.usize(&k("action_dim"))?,
            embed_dim: h.usize(&k("embed_dim"))?,
            n_layers: h.usize(&k("n_layers"))?,
            n_heads: h.usize(&k("n_heads"))?,
            obs_seq_len: h.usize(&k("obs_seq_len"))?,
            goal_seq_len: h.usize_or(&k("goal_seq_len"), 0)?,
            goal_conditioned: h.bool_or(&k("goal_conditioned"), false)?,
            linear_output: h.bool_or(&k("linear_output"), false)?,
        };
        goal_window = c.goal_tokens();
        BesoNetworkConfig::DiffusionGpt(c)
    } else if target.ends_with("GCTimeScoreNetwork") {
        let unsupported = |key: &str, why: &str| -> Result<(), BesoError> {
            Err(h.bad(&k(key), h.req(&k(key))?, why))
        };
        if h.bool_or(&k("goal_conditional"), true)? {
            unsupported(
                "goal_conditional",
                "goal-conditioned ResNet-MLP teachers are not imported",
            )?;
        }
        if !h.bool_or(&k("model_style"), true)? {
            unsupported("model_style", "only the residual MLP (model_style: true) is imported")?;
        }
        if h.bool_or(&k("use_spectral_norm"), false)? {
            unsupported("use_spectral_norm", "spectral norm is not imported")?;
        }
        let norm = match h.bool_or(&k("use_norm"), false)? {
            false => BlockNorm::None,
            true if h.str_or(&k("norm_style"), "BatchNorm")? == "LayerNorm" => BlockNorm::LayerNorm,
            true => {
                return Err(h.bad(&k("norm_style"), h.req(&k("norm_style"))?, "only LayerNorm"));
            }
        };
        let ek = k("embed_fn.embedding_type");
        let embedding = match h.str(&ek)? {
            "FourierFeatures" => SigmaEmbedding::FourierFeatures,
            "GaussianFourier" => SigmaEmbedding::GaussianFourier,
            "Sinusoidal" => SigmaEmbedding::Sinusoidal,
            _ => {
                return Err(h.bad(
                    &ek,
                    h.req(&ek)?,
                    "expected FourierFeatures, GaussianFourier or Sinusoidal",
                ));
            }
        };
        BesoNetworkConfig::ResMlp(ResMlpScoreConfig {
            obs_dim: h.usize(&k("obs_dim"))?,
            action_dim: h.usize(&k("plan_dim"))?,
            goal_dim: 0,
            goal_conditional: false,
            hidden_dim: h.usize(&k("hidden_dim"))?,
            num_hidden_layers: h.usize_or(&k("num_hidden_layers"), 1)?,
            output_dim: h.usize_or(&k("output_dim"), 1)?,
            time_embed_dim: h.usize(&k("embed_fn.time_embed_dim"))?,
            embedding,
            activation: MlpActivation::from_beso_name(h.str_or(&k("activation"), "ReLU")?),
            norm,
        })
    } else {
        return Err(h.bad(
            &k("_target_"),
            h.req(&k("_target_"))?,
            "expected DiffusionGPT or GCTimeScoreNetwork",
        ));
    };
    // Sizes first: nothing is built for a network past the limits.
    match &network {
        BesoNetworkConfig::DiffusionGpt(c) => crate::limits::check_gpt(c).map(drop),
        BesoNetworkConfig::ResMlp(c) => crate::limits::check_resmlp(c).map(drop),
    }
    .map_err(|r| r.beso(path, inner))?;
    if let BesoNetworkConfig::ResMlp(c) = &network {
        if c.output_dim != c.action_dim {
            return Err(h.bad(&k("output_dim"), h.req(&k("output_dim"))?, "must equal plan_dim"));
        }
    }
    let sampler = match h.str("agents.sampler_type")? {
        "euler" => KarrasSampler::Euler,
        "euler_ancestral" => KarrasSampler::EulerAncestral,
        "ddim" => KarrasSampler::Ddim,
        "heun" => KarrasSampler::Heun,
        _ => {
            return Err(h.bad(
                "agents.sampler_type",
                h.req("agents.sampler_type")?,
                "sampler not imported",
            ));
        }
    };
    let (od, ad) = match &network {
        BesoNetworkConfig::DiffusionGpt(c) => (c.state_dim, c.action_dim),
        BesoNetworkConfig::ResMlp(c) => (c.obs_dim, c.action_dim),
    };
    let scale_data = match h.get("agents.scale_data").or_else(|| h.get("scale_data")) {
        None => true,
        Some(v) => {
            v.as_bool().ok_or_else(|| h.bad("agents.scale_data", v, "expected true or false"))?
        }
    };
    let scaler = match (scaler, scale_data) {
        (Some(s), _) => s,
        (None, false) => BesoScaler {
            obs: Affine::identity(od),
            action: Affine::identity(ad),
            action_min: vec![f32::MIN; ad],
            action_max: vec![f32::MAX; ad],
        },
        (None, true) => {
            return Err(BesoError::MissingKey {
                path: path.with_file_name(BESO_SCALER_FILE),
                key: "x_mean (scale_data is true: export the scaler with beso_pth.py --scaler)"
                    .into(),
            });
        }
    };
    let config = BesoTeacherConfig {
        network,
        sigma_data: h.f32("agents.model.sigma_data")?,
        sigma_min: h.f32("agents.sigma_min")?,
        sigma_max: h.f32("agents.sigma_max")?,
        steps: h.usize("agents.num_sampling_steps")?,
        sampler,
        schedule,
        window: h.usize("agents.window_size")?,
        goal_window,
        scaler,
    };
    config.validate()?;
    Ok(config)
}

/// `scaler.json` as `beso_pth.py` writes it.
#[derive(Debug, Deserialize)]
struct ScalerFile {
    scale_data: bool,
    x_mean: Vec<f64>,
    x_std: Vec<f64>,
    y_mean: Vec<f64>,
    y_std: Vec<f64>,
    y_bounds: [Vec<f64>; 2],
}

/// Reads `scaler.json` (D3IL's `Scaler` statistics) into a [`BesoScaler`].
pub fn read_beso_scaler(path: &Path) -> Result<BesoScaler, BesoError> {
    let text = read_text(path)?;
    check_nesting(path, json_nesting(text.as_bytes()))?;
    let s: ScalerFile = serde_json::from_str(&text)
        .map_err(|source| BesoError::Json { what: path.display().to_string(), source })?;
    let bad = |key: &str, reason: &str| BesoError::BadValue {
        path: path.to_owned(),
        key: key.into(),
        value: "…".into(),
        reason: reason.into(),
    };
    let finite = |v: &[f64]| v.iter().all(|x| x.is_finite() && x.abs() < 1e30);
    for (key, v) in
        [("x_mean", &s.x_mean), ("x_std", &s.x_std), ("y_mean", &s.y_mean), ("y_std", &s.y_std)]
    {
        if !finite(v) {
            return Err(bad(key, "non-finite or absurd entry"));
        }
    }
    if s.x_std.len() != s.x_mean.len() || s.y_std.len() != s.y_mean.len() {
        return Err(bad("x_std", "mean and std lengths differ"));
    }
    if s.y_bounds.iter().any(|b| b.len() != s.y_mean.len() || b.iter().any(|x| x.is_nan())) {
        return Err(bad("y_bounds", "expected two rows of the action width, no NaN"));
    }
    // D3IL divides by `std + 1e-12`.
    let affine = |mean: &[f64], std: &[f64], key: &str| -> Result<Affine, BesoError> {
        if !s.scale_data {
            return Ok(Affine::identity(mean.len()));
        }
        let scale = std.iter().map(|&x| (x + 1e-12) as f32).collect();
        Affine::new(mean.iter().map(|&x| x as f32).collect(), scale)
            .map_err(|_| bad(key, "standard deviations must be non-negative"))
    };
    Ok(BesoScaler {
        obs: affine(&s.x_mean, &s.x_std, "x_std")?,
        action: affine(&s.y_mean, &s.y_std, "y_std")?,
        action_min: s.y_bounds[0].iter().map(|&x| x as f32).collect(),
        action_max: s.y_bounds[1].iter().map(|&x| x as f32).collect(),
    })
}

/// Imports a BESO/D3IL run directory (after `scripts/import/beso_pth.py DIR`): reads the
/// hydra config, `scaler.json` (when present) and `model_state_dict.safetensors`, and returns
/// the teacher (save it with [`BesoTeacher::save`]).
pub fn import_beso_run(dir: &Path) -> Result<BesoTeacher, BesoError> {
    let config_path = find_config(dir)?;
    let yaml = read_text(&config_path)?;
    let scaler_path = dir.join(BESO_SCALER_FILE);
    let scaler = if scaler_path.is_file() { Some(read_beso_scaler(&scaler_path)?) } else { None };
    let config = beso_config_from_yaml(&config_path, &yaml, scaler)?;
    let mut teacher = BesoTeacher::new(config)?;
    let weights = dir.join(BESO_WEIGHTS_FILE);
    if !weights.is_file() {
        return Err(BesoError::Io {
            path: weights,
            source: std::io::Error::new(
                std::io::ErrorKind::NotFound,
                "convert model_state_dict.pth first: python scripts/import/beso_pth.py DIR",
            ),
        });
    }
    teacher.load_state_dict(&weights)?;
    Ok(teacher)
}
