//! Plumbing shared by both teachers: raw ↔ normalised batches for the policy interface, argument
//! checks, and the checkpoint metadata format.

use std::collections::BTreeMap;
use std::path::Path;

use faer::{Mat, MatMut, MatRef};
use serde::{Deserialize, Serialize, de::DeserializeOwned};
use vdd_core::{Affine, CoreError, check_finite, check_shape};

use crate::error::{DiffusionError, Result};

/// Reused raw ↔ normalised buffers for `Policy::act_into` / `act_batch`.
#[derive(Debug, Clone)]
pub(crate) struct PolicyIo {
    pub obs: Mat<f32>,
    pub act: Mat<f32>,
}

impl Default for PolicyIo {
    fn default() -> Self {
        Self { obs: Mat::zeros(0, 0), act: Mat::zeros(0, 0) }
    }
}

impl PolicyIo {
    pub(crate) fn prepare(&mut self, n: usize, ds: usize, da: usize) {
        if self.obs.nrows() != n || self.obs.ncols() != ds {
            self.obs = Mat::zeros(n, ds);
        }
        if self.act.nrows() != n || self.act.ncols() != da {
            self.act = Mat::zeros(n, da);
        }
    }

    /// Normalises raw observations into `self.obs`.
    pub(crate) fn load_obs(&mut self, obs: MatRef<'_, f32>, norm: &Affine) {
        for j in 0..obs.ncols() {
            let (o, s) = (norm.offset[j], norm.scale[j]);
            let dst = self.obs.col_as_slice_mut(j);
            for i in 0..obs.nrows() {
                dst[i] = (obs[(i, j)] - o) / s;
            }
        }
    }

    /// Writes `self.act`, denormalised, into `out`.
    pub(crate) fn store_actions(&self, norm: &Affine, mut out: MatMut<'_, f32>) {
        for j in 0..out.ncols() {
            let (o, s) = (norm.offset[j], norm.scale[j]);
            let src = self.act.col_as_slice(j);
            for i in 0..out.nrows() {
                out[(i, j)] = src[i] * s + o;
            }
        }
    }
}

/// Checks a batch of `n` rows with `cols` finite columns.
pub(crate) fn check_batch(
    what: &'static str,
    m: MatRef<'_, f32>,
    n: usize,
    cols: usize,
) -> std::result::Result<(), CoreError> {
    check_shape(what, m, n, cols)?;
    check_finite(what, m)
}

/// The dimensions and normalisers of a saved teacher.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub(crate) struct SavedShape {
    pub state_dim: usize,
    pub action_dim: usize,
    pub state_normalizer: Affine,
    pub action_normalizer: Affine,
}

pub(crate) const KIND_KEY: &str = "vdd_diffusion.kind";
pub(crate) const VERSION_KEY: &str = "vdd_diffusion.version";
pub(crate) const CONFIG_KEY: &str = "vdd_diffusion.config";
pub(crate) const SHAPE_KEY: &str = "vdd_diffusion.shape";
pub(crate) const TRAIN_KEY: &str = "vdd_diffusion.train";
pub(crate) const FORMAT_VERSION: &str = "1";

pub(crate) fn format_err(path: &Path, reason: impl ToString) -> DiffusionError {
    DiffusionError::Format { path: path.to_owned(), reason: reason.to_string() }
}

fn to_json<T: Serialize>(key: &'static str, v: &T) -> Result<String> {
    serde_json::to_string(v).map_err(|source| DiffusionError::SerializeMetadata { key, source })
}

fn bad_metadata(
    path: &Path,
    key: &'static str,
) -> impl FnOnce(serde_json::Error) -> DiffusionError {
    let path = path.to_owned();
    move |e| DiffusionError::BadMetadata { path, key, source: Box::new(e) }
}

/// Builds the metadata of a checkpoint.
pub(crate) fn metadata<C: Serialize, T: Serialize>(
    kind: &str,
    config: &C,
    shape: &SavedShape,
    train: Option<&T>,
) -> Result<BTreeMap<String, String>> {
    let mut m = BTreeMap::new();
    m.insert(KIND_KEY.to_owned(), kind.to_owned());
    m.insert(VERSION_KEY.to_owned(), FORMAT_VERSION.to_owned());
    m.insert(CONFIG_KEY.to_owned(), to_json(CONFIG_KEY, config)?);
    m.insert(SHAPE_KEY.to_owned(), to_json(SHAPE_KEY, shape)?);
    if let Some(t) = train {
        m.insert(TRAIN_KEY.to_owned(), to_json(TRAIN_KEY, t)?);
    }
    Ok(m)
}

/// Reads and checks the kind, version, config, shape and optional training config of a
/// checkpoint's metadata.
pub(crate) fn parse_metadata<C: DeserializeOwned, T: DeserializeOwned>(
    path: &Path,
    meta: &BTreeMap<String, String>,
    expected_kind: &str,
) -> Result<(C, SavedShape, Option<T>)> {
    let kind = meta.get(KIND_KEY).ok_or_else(|| {
        format_err(path, format!("no `{KIND_KEY}` metadata: not a vdd-diffusion teacher"))
    })?;
    if kind != expected_kind {
        return Err(format_err(
            path,
            format!("file holds a `{kind}` teacher, expected `{expected_kind}`"),
        ));
    }
    match meta.get(VERSION_KEY) {
        Some(v) if v == FORMAT_VERSION => {}
        other => {
            return Err(format_err(path, format!("unsupported format version {other:?}")));
        }
    }
    let get = |key: &str| {
        meta.get(key).ok_or_else(|| format_err(path, format!("missing `{key}` metadata")))
    };
    let config: C =
        serde_json::from_str(get(CONFIG_KEY)?).map_err(bad_metadata(path, CONFIG_KEY))?;
    let shape: SavedShape =
        serde_json::from_str(get(SHAPE_KEY)?).map_err(bad_metadata(path, SHAPE_KEY))?;
    if shape.state_normalizer.dim() != shape.state_dim
        || shape.action_normalizer.dim() != shape.action_dim
        || shape.action_dim == 0
    {
        return Err(format_err(path, "normaliser dimensions do not match the teacher's"));
    }
    for n in [&shape.state_normalizer, &shape.action_normalizer] {
        Affine::new(n.offset.clone(), n.scale.clone()).map_err(|e| {
            DiffusionError::BadMetadata {
                path: path.to_owned(),
                key: SHAPE_KEY,
                source: Box::new(e),
            }
        })?;
    }
    let train = match meta.get(TRAIN_KEY) {
        None => None,
        Some(s) => Some(serde_json::from_str(s).map_err(bad_metadata(path, TRAIN_KEY))?),
    };
    Ok((config, shape, train))
}
