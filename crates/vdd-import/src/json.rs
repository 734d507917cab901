//! Reading the packages' JSON and safetensors files defensively: sizes checked before reading,
//! every missing or malformed key named.

use std::collections::BTreeSet;
use std::path::Path;

use serde_json::Value;
use vdd_nn::{Param, Parameters};

use crate::error::ImportError;
use crate::limits::{MAX_NESTING, MAX_TEXT_BYTES, json_nesting};

/// Largest weights file read ([`vdd_nn::io::MAX_FILE_BYTES`]).
pub(crate) const MAX_WEIGHTS_BYTES: u64 = vdd_nn::io::MAX_FILE_BYTES;

/// Reads the regular file `path` whole, at most `max` bytes, through the bounded reader
/// ([`vdd_core::files::read_bounded`]): a FIFO or device is refused before it is opened, and
/// no more than `max` bytes are read whatever length the file reports.
pub(crate) fn read_bounded(path: &Path, max: u64) -> Result<Vec<u8>, ImportError> {
    vdd_core::files::read_bounded(path, max)
        .map_err(|source| ImportError::Io { path: path.to_owned(), source })
}

/// Parses a JSON file (at most [`MAX_TEXT_BYTES`], nested at most [`MAX_NESTING`] deep).
pub(crate) fn read_json(path: &Path) -> Result<Value, ImportError> {
    let bytes = read_bounded(path, MAX_TEXT_BYTES)?;
    check_json_nesting(&path.display().to_string(), &bytes)?;
    serde_json::from_slice(&bytes)
        .map_err(|source| ImportError::Json { path: path.to_owned(), source })
}

/// Refuses JSON text nested deeper than [`MAX_NESTING`] (`file` names it in the error).
pub(crate) fn check_json_nesting(file: &str, bytes: &[u8]) -> Result<(), ImportError> {
    let depth = json_nesting(bytes);
    if depth > MAX_NESTING {
        return Err(ImportError::bad(
            file,
            "nesting depth",
            format!("more than {depth} levels (at most {MAX_NESTING})"),
        ));
    }
    Ok(())
}

/// A JSON object's fields, with the file named in errors.
pub(crate) struct Fields<'a> {
    pub(crate) file: String,
    pub(crate) value: &'a Value,
}

impl<'a> Fields<'a> {
    pub(crate) fn new(file: impl Into<String>, value: &'a Value) -> Self {
        Self { file: file.into(), value }
    }

    pub(crate) fn get(&self, key: &str) -> Result<&'a Value, ImportError> {
        self.value.get(key).ok_or_else(|| ImportError::missing(&self.file, key))
    }

    /// The field, or `None` when absent or null.
    pub(crate) fn opt(&self, key: &str) -> Option<&'a Value> {
        self.value.get(key).filter(|v| !v.is_null())
    }

    pub(crate) fn sub(&self, key: &str) -> Result<Fields<'a>, ImportError> {
        Ok(Fields { file: format!("{}: {key}", self.file), value: self.get(key)? })
    }

    pub(crate) fn usize(&self, key: &str) -> Result<usize, ImportError> {
        let v = self.get(key)?;
        v.as_u64()
            .filter(|&n| n <= 1 << 20)
            .map(|n| n as usize)
            .ok_or_else(|| ImportError::bad(&self.file, key, v))
    }

    pub(crate) fn f32(&self, key: &str) -> Result<f32, ImportError> {
        let v = self.get(key)?;
        v.as_f64()
            .map(|x| x as f32)
            .filter(|x| x.is_finite())
            .ok_or_else(|| ImportError::bad(&self.file, key, v))
    }

    pub(crate) fn bool(&self, key: &str) -> Result<bool, ImportError> {
        let v = self.get(key)?;
        v.as_bool().ok_or_else(|| ImportError::bad(&self.file, key, v))
    }

    pub(crate) fn str(&self, key: &str) -> Result<&'a str, ImportError> {
        let v = self.get(key)?;
        v.as_str().ok_or_else(|| ImportError::bad(&self.file, key, v))
    }

    pub(crate) fn usizes(&self, key: &str) -> Result<Vec<usize>, ImportError> {
        let v = self.get(key)?;
        let bad = || ImportError::bad(&self.file, key, v);
        v.as_array()
            .ok_or_else(bad)?
            .iter()
            .map(|x| x.as_u64().filter(|&n| n <= 1 << 20).map(|n| n as usize).ok_or_else(bad))
            .collect()
    }
}

/// A model's parameters seen under an extra name prefix (a package's `diffusion.unet.` or
/// `model.`).
pub(crate) struct Prefixed<'a> {
    pub(crate) inner: &'a mut dyn Parameters,
    pub(crate) prefix: &'a str,
}

impl Parameters for Prefixed<'_> {
    fn visit_params(&self, prefix: &str, f: &mut dyn FnMut(&str, &Param)) {
        self.inner.visit_params(&vdd_nn::join_name(prefix, self.prefix), f);
    }
    fn visit_params_mut(&mut self, prefix: &str, f: &mut dyn FnMut(&str, &mut Param)) {
        self.inner.visit_params_mut(&vdd_nn::join_name(prefix, self.prefix), f);
    }
}

/// Loads `model`'s tensors from `bytes` (the safetensors file `path`) and refuses tensors under
/// `owned` prefixes that the model does not have (an unknown layout), naming the first.
pub(crate) fn load_strict(
    path: &Path,
    bytes: &[u8],
    model: &mut dyn Parameters,
    owned: &[&str],
) -> Result<(), ImportError> {
    vdd_nn::io::load_safetensors_bytes(path, bytes, model)?;
    let mut known = BTreeSet::new();
    model.visit_params("", &mut |n, _| {
        known.insert(n.to_owned());
    });
    let file = safetensors::SafeTensors::deserialize(bytes)
        .map_err(|e| ImportError::bad(path.display().to_string(), "safetensors", e))?;
    let mut names: Vec<String> = file.names().into_iter().map(str::to_owned).collect();
    names.sort();
    for name in names {
        if owned.iter().any(|p| name.starts_with(p)) && !known.contains(&name) {
            return Err(ImportError::bad(
                path.display().to_string(),
                name,
                "a tensor of a layout this importer does not know",
            ));
        }
    }
    Ok(())
}
