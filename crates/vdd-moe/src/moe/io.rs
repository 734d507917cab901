//! Saving and loading: one `safetensors` file with the weights, the configuration, the
//! normalisers, the act mode, the deployment spec and a fingerprint of the expert family.

use std::collections::BTreeMap;
use std::path::Path;

use serde::{Deserialize, Serialize};
use vdd_core::{Affine, Expert, check_len};

use super::{Moe, MoeConfig};
use crate::error::MoeError;
use crate::experts::ExpertFamily;

impl Moe<ExpertFamily> {
    /// Loads a mixture saved by [`Moe::save`] (family from the saved configuration).
    pub fn load(path: &Path) -> Result<Self, MoeError> {
        let (config, meta, elements) = read_config(path)?;
        config.validate().map_err(|e| bad_config(path, e))?;
        let family = ExpertFamily::new(
            config.expert_kind,
            config.action_dim,
            config.init_std,
            config.min_std,
        )?;
        Self::load_with(path, family, Some((config, meta, elements)))
    }
}

/// The metadata key of the deployment spec.
const DEPLOY_SPEC_KEY: &str = "deploy_spec";

/// The metadata and config of a saved mixture, with the number of values its tensors hold.
type Header = (MoeConfig, BTreeMap<String, String>, usize);

fn read_config(path: &Path) -> Result<Header, MoeError> {
    let (meta, elements) = vdd_nn::io::read_header(path)?;
    let config: MoeConfig = parse_meta(path, &meta, "config")?;
    Ok((config, meta, elements))
}

/// A `config` metadata entry out of its documented ranges.
fn bad_config(path: &Path, e: vdd_core::CoreError) -> MoeError {
    bad_entry(path, "config", e)
}

/// The metadata entry `key` out of its documented ranges.
fn bad_entry(path: &Path, key: &str, e: vdd_core::CoreError) -> MoeError {
    MoeError::Nn(vdd_nn::NnError::Format {
        path: path.to_owned(),
        reason: format!("`{key}` metadata: {e}"),
    })
}

/// Parses the JSON metadata entry `key` of the file `path`.
fn parse_meta<T: serde::de::DeserializeOwned>(
    path: &Path,
    meta: &BTreeMap<String, String>,
    key: &str,
) -> Result<T, MoeError> {
    let raw = meta
        .get(key)
        .ok_or_else(|| MoeError::MissingMetadata { path: path.to_owned(), key: key.to_owned() })?;
    serde_json::from_str(raw).map_err(|source| MoeError::BadMetadata {
        path: path.to_owned(),
        key: key.to_owned(),
        source,
    })
}

impl<E: Expert> Moe<E> {
    /// Saves weights, configuration, normalisers, act mode, deployment spec
    /// ([`Moe::deploy_spec`]) and a fingerprint of the expert family to one `safetensors` file
    /// (atomically), so a deployed policy needs nothing else ([`crate::load_policy`]).
    ///
    /// What is written can be loaded: the same rules as [`Moe::load`]'s are checked first
    /// (weights finite with `|w| <=` [`MAX_ABS_WEIGHT`](vdd_nn::limits::MAX_ABS_WEIGHT),
    /// normaliser offsets and scales within their bounds, [`vdd_core::Affine::new`]), and a
    /// value breaking them is an error naming it, with nothing written. The same model always
    /// gives the same bytes.
    pub fn save(&self, path: &Path) -> Result<(), MoeError> {
        self.config.validate().map_err(|e| bad_config(path, e))?;
        for (key, n) in [
            ("obs_normalizer", &self.obs_normalizer),
            ("action_normalizer", &self.action_normalizer),
        ] {
            if let Some(n) = n {
                n.validate().map_err(|e| bad_entry(path, key, e))?;
            }
        }
        fn put<T: Serialize>(
            meta: &mut BTreeMap<String, String>,
            key: &'static str,
            v: &T,
        ) -> Result<(), MoeError> {
            let text = serde_json::to_string(v)
                .map_err(|source| MoeError::SerializeMetadata { key, source })?;
            meta.insert(key.to_owned(), text);
            Ok(())
        }
        let mut meta = BTreeMap::new();
        put(&mut meta, "config", &self.config)?;
        put(&mut meta, "obs_normalizer", &self.obs_normalizer)?;
        put(&mut meta, "action_normalizer", &self.action_normalizer)?;
        put(&mut meta, "act_mode", &self.act_mode)?;
        put(&mut meta, DEPLOY_SPEC_KEY, &self.deploy_spec)?;
        put(&mut meta, "expert_family", &FamilyFingerprint::of(&self.expert))?;
        vdd_nn::io::save_safetensors(path, self, &meta)?;
        Ok(())
    }

    /// Loads a mixture saved by [`Moe::save`] with a custom expert family. An error
    /// ([`MoeError::FamilyMismatch`]) if `expert` decodes raw outputs differently from the
    /// family the file was saved with (other kind, dimension or scale activation).
    pub fn load_with_family(path: &Path, expert: E) -> Result<Self, MoeError> {
        Self::load_with(path, expert, None)
    }

    fn load_with(path: &Path, expert: E, config: Option<Header>) -> Result<Self, MoeError> {
        let (config, meta, elements) = match config {
            Some(c) => c,
            None => read_config(path)?,
        };
        config.validate().map_err(|e| bad_config(path, e))?;
        check_len("expert family action_dim", expert.action_dim(), config.action_dim)?;
        vdd_nn::io::check_fits(
            path,
            "the `config` metadata",
            config.num_params(expert.raw_dim()),
            elements,
        )?;
        if meta.contains_key("expert_family") {
            // Files written before the fingerprint existed load without this check.
            let saved: FamilyFingerprint = parse_meta(path, &meta, "expert_family")?;
            let given = FamilyFingerprint::of(&expert);
            if !saved.matches(&given) {
                return Err(MoeError::FamilyMismatch(format!(
                    "{} was saved with {saved}, loading with {given} ({:?}); a mixture built \
                     with a custom family loads with `Moe::load_with_family`",
                    path.display(),
                    expert
                )));
            }
        }
        let mut moe = Self::new(config, expert, 0)?;
        vdd_nn::io::load_safetensors(path, &mut moe)?;
        let obs: Option<Affine> = parse_meta(path, &meta, "obs_normalizer")?;
        let act: Option<Affine> = parse_meta(path, &meta, "action_normalizer")?;
        moe.act_mode = parse_meta(path, &meta, "act_mode")?;
        // Offsets and scales within their bounds (an offset of 2^63 or a scale of 1e-38 would
        // act at 1e18..1e38): the error names the file and the entry.
        for (key, n) in [("obs_normalizer", &obs), ("action_normalizer", &act)] {
            if let Some(n) = n {
                n.validate().map_err(|e| bad_entry(path, key, e))?;
            }
        }
        moe.set_normalizers(obs, act)?;
        // Files written before the spec existed act on raw observations (the identity spec).
        if meta.contains_key(DEPLOY_SPEC_KEY) {
            moe.set_deploy_spec(parse_meta(path, &meta, DEPLOY_SPEC_KEY)?)?;
        }
        Ok(moe)
    }
}

/// What a saved mixture records of its expert family, so that loading it with another family
/// is an error rather than silently different means and scales: the dimensions and the decoded
/// `(μ, L)` of a few fixed raw vectors (which pins down the kind and the scale activation).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
struct FamilyFingerprint {
    action_dim: usize,
    raw_dim: usize,
    is_diagonal: bool,
    /// Per probe: `μ` (`d`) followed by `L` (`d·d`, row-major).
    probes: Vec<Vec<f32>>,
}

impl FamilyFingerprint {
    const PROBES: usize = 3;

    fn of<E: Expert>(expert: &E) -> Self {
        let (d, r) = (expert.action_dim(), expert.raw_dim());
        let probes = (0..Self::PROBES)
            .map(|k| {
                // Probe 0 is the all-zero raw vector (the initial scale); the others spread over
                // [−1, 1] so that means, diagonal and off-diagonal scale entries all differ.
                let raw: Vec<f32> = (0..r)
                    .map(|i| if k == 0 { 0.0 } else { ((i * 7 + k * 5) % 11) as f32 / 5.0 - 1.0 })
                    .collect();
                let mut decoded = vec![0.0; d + d * d];
                let (mean, scale) = decoded.split_at_mut(d);
                expert.decode(&raw, mean, scale);
                decoded
            })
            .collect();
        Self { action_dim: d, raw_dim: r, is_diagonal: expert.is_diagonal(), probes }
    }

    fn matches(&self, other: &Self) -> bool {
        self.action_dim == other.action_dim
            && self.raw_dim == other.raw_dim
            && self.is_diagonal == other.is_diagonal
            && self.probes.len() == other.probes.len()
            && self.probes.iter().zip(&other.probes).all(|(a, b)| {
                a.len() == b.len()
                    && a.iter().zip(b).all(|(x, y)| (x - y).abs() <= 1e-5 * (1.0 + x.abs()))
            })
    }
}

impl std::fmt::Display for FamilyFingerprint {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let kind = if self.is_diagonal { "a diagonal" } else { "a non-diagonal" };
        let d = self.action_dim;
        let std0: Vec<f32> = self.probes.first().map_or(Vec::new(), |p| {
            (0..d.min(p.len()))
                .filter_map(|i| p.get(d.checked_add(i.checked_mul(d.checked_add(1)?)?)?))
                .copied()
                .collect()
        });
        write!(f, "{kind} family (action_dim {d}, raw_dim {}, initial stds {std0:?})", self.raw_dim)
    }
}
