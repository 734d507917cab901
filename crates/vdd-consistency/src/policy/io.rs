//! Saving a distilled policy ([`crate::ConsistencyModel`], [`crate::TrajectoryModel`]) to one
//! `safetensors` file, with everything it acts by: the network's weights and architecture, the
//! preconditioning, the sampling levels, the teacher's normalisers and the deployment spec
//! (features, window, chunk). Loading checks every value against the file before allocating.

use std::collections::BTreeMap;
use std::path::Path;

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use vdd_core::{Affine, Seeds};
use vdd_data::DeploySpec;
use vdd_diffusion::{DenoiserNet, NetConfig, Preconditioning};

use super::{DistilledPolicy, Sampling};
use crate::error::ConsistencyError;
use crate::network::BoundaryPreconditioning;

/// The metadata key naming the kind of distilled policy (`cd`, `ctm`).
const KIND_KEY: &str = "vdd_consistency.kind";
/// The metadata key of the policy's settings (JSON).
const MODEL_KEY: &str = "vdd_consistency.model";
/// The format's version.
const FORMAT_VERSION: u32 = 1;

/// The preconditionings a saved policy can have: each names its kind in the file and the
/// random stream its policy samples from.
pub trait SavedKind: Sampling + Serialize + DeserializeOwned {
    /// The kind in the file (`cd`, `ctm`).
    const KIND: &'static str;
    /// The policy's random stream (its trainer's).
    const STREAM: &'static str;
}

impl SavedKind for BoundaryPreconditioning {
    const KIND: &'static str = "cd";
    const STREAM: &'static str = "cd-policy";
}

impl SavedKind for Preconditioning {
    const KIND: &'static str = "ctm";
    const STREAM: &'static str = "ctm-policy";
}

/// What a file holds besides the weights.
#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Saved<P> {
    version: u32,
    preconditioning: P,
    net: NetConfig,
    action_dim: usize,
    state_dim: usize,
    net_levels: usize,
    sigma_min: f32,
    sigma_max: f32,
    rho: f32,
    /// The sampling levels, `σ_max = l_0 > … > l_k = σ_min`.
    sampling_levels: Vec<f32>,
    state_normalizer: Affine,
    action_normalizer: Affine,
    deploy_spec: DeploySpec,
}

impl<P: SavedKind> DistilledPolicy<P> {
    /// Saves the policy (weights, architecture, preconditioning, sampling levels, normalisers
    /// and deployment spec) to one `safetensors` file; the write is atomic.
    ///
    /// ```no_run
    /// # fn main() -> Result<(), Box<dyn std::error::Error>> {
    /// # let model: vdd_consistency::ConsistencyModel = todo!();
    /// model.save("cd-s0.safetensors".as_ref())?;
    /// let mut policy = vdd_consistency::ConsistencyModel::load_policy("cd-s0.safetensors".as_ref(), 0)?;
    /// # Ok(()) }
    /// ```
    pub fn save(&self, path: &Path) -> Result<(), ConsistencyError> {
        let saved = Saved {
            version: FORMAT_VERSION,
            preconditioning: self.pre,
            net: self.net.config().clone(),
            action_dim: self.net.action_dim(),
            state_dim: self.net.state_dim(),
            net_levels: self.net.levels(),
            sigma_min: self.sigma_min,
            sigma_max: self.sigma_max,
            rho: self.rho,
            sampling_levels: self.levels.clone(),
            state_normalizer: self.state_norm.clone(),
            action_normalizer: self.action_norm.clone(),
            deploy_spec: self.deploy_spec.clone(),
        };
        let json = serde_json::to_string(&saved).map_err(|e| ConsistencyError::Format {
            path: path.to_owned(),
            key: MODEL_KEY.to_owned(),
            reason: e.to_string(),
        })?;
        let meta = BTreeMap::from([
            (KIND_KEY.to_owned(), P::KIND.to_owned()),
            (MODEL_KEY.to_owned(), json),
        ]);
        vdd_nn::io::save_safetensors(path, &self.net, &meta)?;
        Ok(())
    }

    /// Loads a policy saved by [`DistilledPolicy::save`]; it samples from a stream seeded by
    /// `seed`. The kind, the sizes (against the file's tensors and the networks' limits), the
    /// levels, the normalisers and the deployment spec are checked; an error names the file
    /// and the key.
    pub fn load(path: &Path, seed: u64) -> Result<Self, ConsistencyError> {
        let (meta, elements) = vdd_nn::io::read_header(path)?;
        let bad = |key: &str, reason: String| ConsistencyError::Format {
            path: path.to_owned(),
            key: key.to_owned(),
            reason,
        };
        match meta.get(KIND_KEY) {
            Some(k) if k == P::KIND => {}
            Some(k) => return Err(bad(KIND_KEY, format!("a `{k}` policy, not `{}`", P::KIND))),
            None => return Err(bad(KIND_KEY, "missing: not a distilled policy".into())),
        }
        let json = meta.get(MODEL_KEY).ok_or_else(|| bad(MODEL_KEY, "missing".into()))?;
        let s: Saved<P> = serde_json::from_str(json).map_err(|e| bad(MODEL_KEY, e.to_string()))?;
        if s.version != FORMAT_VERSION {
            return Err(bad(
                "version",
                format!("{} (this build reads {FORMAT_VERSION})", s.version),
            ));
        }
        if s.net_levels != P::LEVELS {
            let why = format!("{} noise conditions, the kind has {}", s.net_levels, P::LEVELS);
            return Err(bad("net_levels", why));
        }
        let max = vdd_nn::limits::MAX_WIDTH;
        if s.action_dim == 0 || s.action_dim > max || s.state_dim > max {
            let why = format!(
                "action_dim {} and state_dim {} must be in 1..={max}",
                s.action_dim, s.state_dim
            );
            return Err(bad("shape", why));
        }
        s.net.validate().map_err(|e| bad("net", e.to_string()))?;
        let mlp = s.net.mlp_config(s.action_dim, s.state_dim, s.net_levels);
        vdd_nn::io::check_fits(path, "the `net` metadata", mlp.num_params(), elements)?;
        for (key, n, dim) in [
            ("state_normalizer", &s.state_normalizer, s.state_dim),
            ("action_normalizer", &s.action_normalizer, s.action_dim),
        ] {
            n.validate().map_err(|e| bad(key, e.to_string()))?;
            if n.dim() != dim {
                return Err(bad(key, format!("{} wide, the network takes {dim}", n.dim())));
            }
        }
        let finite_positive = |x: f32| x.is_finite() && x > 0.0;
        let range_ok = finite_positive(s.sigma_min) && s.sigma_max > s.sigma_min;
        if !(range_ok && s.sigma_max.is_finite() && finite_positive(s.rho)) {
            let why = format!("σ_min {}, σ_max {}, ρ {}", s.sigma_min, s.sigma_max, s.rho);
            return Err(bad("sigma_min, sigma_max, rho", why));
        }
        let levels_ok = s.sampling_levels.len() >= 2
            && s.sampling_levels.len() <= vdd_diffusion::MAX_SAMPLING_STEPS + 1
            && s.sampling_levels.last() == Some(&s.sigma_min);
        if !levels_ok {
            return Err(bad("sampling_levels", format!("{:?}", s.sampling_levels)));
        }
        s.deploy_spec.validate().map_err(|e| bad("deploy_spec", e.to_string()))?;
        let mut net = DenoiserNet::with_levels(
            &s.net,
            s.action_dim,
            s.state_dim,
            s.net_levels,
            &mut Seeds::new(0).stream("init"),
        )?;
        vdd_nn::io::load_safetensors(path, &mut net)?;
        let mut policy = Self {
            net,
            pre: s.preconditioning,
            sigma_min: s.sigma_min,
            sigma_max: s.sigma_max,
            rho: s.rho,
            levels: Vec::new(),
            state_norm: s.state_normalizer,
            action_norm: s.action_normalizer,
            rng: Seeds::new(seed).stream(P::STREAM),
            stream: P::STREAM,
            obs: faer::Mat::zeros(0, 0),
            act: faer::Mat::zeros(0, 0),
            scratch: Default::default(),
            deploy_spec: DeploySpec::identity(),
        };
        let (head, _) = s.sampling_levels.split_at(s.sampling_levels.len() - 1);
        policy.set_sampling_levels(head).map_err(|e| bad("sampling_levels", e.to_string()))?;
        policy.set_deploy_spec(s.deploy_spec).map_err(|e| bad("deploy_spec", e.to_string()))?;
        Ok(policy)
    }

    /// The policy on raw observations, by its [`DistilledPolicy::deploy_spec`].
    pub fn into_policy(self) -> Result<vdd_data::Windowed<Self>, ConsistencyError> {
        let spec = self.deploy_spec.clone();
        Ok(vdd_data::Windowed::new(self, spec)?)
    }

    /// A saved policy on raw observations ([`DistilledPolicy::load`], then
    /// [`DistilledPolicy::into_policy`]).
    pub fn load_policy(
        path: &Path,
        seed: u64,
    ) -> Result<vdd_data::Windowed<Self>, ConsistencyError> {
        Self::load(path, seed)?.into_policy()
    }
}
