//! Checkpoints: tensors in `safetensors` with PyTorch names and layouts, string metadata beside
//! them, and atomic writes (temporary file, fsync, rename) so a crash never leaves a
//! half-written file behind.
//!
//! Reading goes through the workspace's one bounded reader ([`read_bounded`]): only regular
//! files, at most [`MAX_FILE_BYTES`]. Writing checks every value with the loader's rules and
//! writes the metadata in key order, so a written file can always be read back and the same
//! model always gives the same bytes.
//!
//! ```
//! use std::collections::BTreeMap;
//! use vdd_nn::{io, Linear, Parameters};
//! let mut rng = vdd_core::Seeds::new(0).stream("init");
//! let layer = Linear::new(3, 2, &mut rng);
//! let dir = std::env::temp_dir().join(format!("vdd-nn-io-doc-{}", std::process::id()));
//! std::fs::create_dir_all(&dir).unwrap();
//! let path = dir.join("layer.safetensors");
//! let meta = BTreeMap::from([("config".to_owned(), "{}".to_owned())]);
//! io::save_safetensors(&path, &layer, &meta).unwrap();
//! let mut copy = Linear::new(3, 2, &mut rng);
//! let read = io::load_safetensors(&path, &mut copy).unwrap();
//! assert_eq!(read, meta);
//! assert_eq!(copy.weight.value, layer.weight.value);
//! # std::fs::remove_dir_all(&dir).unwrap();
//! ```

use std::collections::BTreeMap;
use std::io::Write;
use std::path::{Path, PathBuf};

use safetensors::{Dtype, SafeTensors, tensor::TensorView};

use crate::{NnError, Param, Parameters};

fn io_err(path: &Path) -> impl FnOnce(std::io::Error) -> NnError + '_ {
    move |source| NnError::Io { path: path.to_owned(), source }
}

fn format_err(path: &Path, reason: impl ToString) -> NnError {
    NnError::Format { path: path.to_owned(), reason: reason.to_string() }
}

fn malformed(path: &Path) -> impl FnOnce(safetensors::SafeTensorError) -> NnError + '_ {
    move |source| NnError::Malformed { path: path.to_owned(), source }
}

/// Writes `bytes` to `path` atomically: a temporary sibling file is written and fsynced, then
/// renamed over `path`. Readers see either the old file or the complete new one.
pub fn write_atomic(path: &Path, bytes: &[u8]) -> Result<(), NnError> {
    let file_name = path
        .file_name()
        .ok_or_else(|| format_err(path, "path has no file name"))?
        .to_string_lossy()
        .into_owned();
    let tmp: PathBuf = path.with_file_name(format!(".{file_name}.tmp-{}", std::process::id()));
    let result = (|| {
        let mut f = std::fs::File::create(&tmp).map_err(io_err(&tmp))?;
        f.write_all(bytes).map_err(io_err(&tmp))?;
        f.sync_all().map_err(io_err(&tmp))?;
        drop(f);
        std::fs::rename(&tmp, path).map_err(io_err(path))?;
        if let Some(dir) = path.parent().filter(|d| !d.as_os_str().is_empty()) {
            // Persist the rename itself; not every platform can open a directory, so a failure
            // here is not an error.
            if let Ok(d) = std::fs::File::open(dir) {
                let _ = d.sync_all();
            }
        }
        Ok(())
    })();
    if result.is_err() {
        let _ = std::fs::remove_file(&tmp);
    }
    result
}

/// Serialises every parameter of `model` (f32, PyTorch names and shapes) plus `metadata` to
/// `safetensors` bytes.
///
/// What is written can be read back: every value is checked with the loader's rules (finite,
/// `|w| <=` [`MAX_ABS_WEIGHT`](crate::limits::MAX_ABS_WEIGHT)) and a value breaking them is an
/// error naming the tensor, the index and the value. The bytes depend only on the model and
/// the metadata (tensors sorted by name, metadata keys in order), so the same model always
/// gives the same file.
pub fn to_safetensors_bytes(
    model: &dyn Parameters,
    metadata: &BTreeMap<String, String>,
) -> Result<Vec<u8>, NnError> {
    let mut tensors: Vec<(String, Vec<usize>, Vec<u8>)> = Vec::new();
    let mut invalid: Option<String> = None;
    model.visit_params("", &mut |name, p| {
        if invalid.is_none() {
            invalid = check_values(name, &p.value).err();
        }
        let bytes = p.value.iter().flat_map(|v| v.to_le_bytes()).collect();
        tensors.push((name.to_owned(), p.shape.clone(), bytes));
    });
    if let Some(reason) = invalid {
        return Err(NnError::Unwritable { what: "a safetensors file".into(), reason });
    }
    let mut views = Vec::with_capacity(tensors.len());
    for (name, shape, bytes) in &tensors {
        let view = TensorView::new(Dtype::F32, shape.clone(), bytes)
            .map_err(|source| NnError::Serialize { what: format!("tensor `{name}`"), source })?;
        views.push((name.clone(), view));
    }
    // The safetensors crate writes its metadata from a `HashMap`, in a per-process random
    // order; the header is written here instead with the keys in order.
    let bytes = safetensors::serialize(views, None)
        .map_err(|source| NnError::Serialize { what: "the safetensors file".into(), source })?;
    with_ordered_metadata(bytes, metadata)
}

/// Inserts `metadata` (keys in order) as the `__metadata__` entry of the header of `bytes`, a
/// `safetensors` file written without metadata. Data offsets are relative to the end of the
/// header, so the data is unchanged.
fn with_ordered_metadata(
    bytes: Vec<u8>,
    metadata: &BTreeMap<String, String>,
) -> Result<Vec<u8>, NnError> {
    let broken = |what: &str| NnError::Config(format!("safetensors serialisation: {what}"));
    let len_bytes: [u8; 8] =
        bytes.get(..8).and_then(|b| b.try_into().ok()).ok_or_else(|| broken("no header"))?;
    let n = usize::try_from(u64::from_le_bytes(len_bytes)).map_err(|_| broken("header size"))?;
    let end = n.checked_add(8).filter(|&e| e <= bytes.len()).ok_or_else(|| broken("header"))?;
    let header = std::str::from_utf8(&bytes[8..end]).map_err(|_| broken("header not UTF-8"))?;
    let tensors = header
        .trim_end()
        .strip_prefix('{')
        .and_then(|h| h.strip_suffix('}'))
        .ok_or_else(|| broken("header not an object"))?;
    let meta = serde_json::to_string(metadata).map_err(|e| broken(&e.to_string()))?;
    let mut text = format!("{{\"__metadata__\":{meta}");
    if !tensors.is_empty() {
        text.push(',');
        text.push_str(tensors);
    }
    text.push('}');
    let padded = text.len().next_multiple_of(8);
    text.extend(std::iter::repeat_n(' ', padded - text.len()));
    let mut out = Vec::with_capacity(8 + text.len() + bytes.len() - end);
    out.extend_from_slice(&(text.len() as u64).to_le_bytes());
    out.extend_from_slice(text.as_bytes());
    out.extend_from_slice(&bytes[end..]);
    Ok(out)
}

/// The loader's rule for values: finite and `|w| <=`
/// [`MAX_ABS_WEIGHT`](crate::limits::MAX_ABS_WEIGHT); the error names the tensor, the index and
/// the value.
pub(crate) fn check_values(name: &str, values: &[f32]) -> Result<(), String> {
    if let Some(i) = values.iter().position(|v| !v.is_finite()) {
        return Err(format!("tensor `{name}` has a non-finite value ({}) at {i}", values[i]));
    }
    let limit = crate::limits::MAX_ABS_WEIGHT;
    if let Some(i) = values.iter().position(|v| v.abs() > limit) {
        return Err(format!(
            "tensor `{name}` holds {:e} at index {i}, beyond the limit |w| <= {limit:e}",
            values[i]
        ));
    }
    Ok(())
}

/// Saves `model`'s parameters and `metadata` to `path` atomically.
pub fn save_safetensors(
    path: &Path,
    model: &dyn Parameters,
    metadata: &BTreeMap<String, String>,
) -> Result<(), NnError> {
    let bytes = to_safetensors_bytes(model, metadata).map_err(|e| match e {
        NnError::Unwritable { reason, .. } => {
            NnError::Unwritable { what: path.display().to_string(), reason }
        }
        other => other,
    })?;
    write_atomic(path, &bytes)
}

/// Largest weights file read: [`MAX_PARAMS`](crate::limits::MAX_PARAMS) values in `f64` plus
/// a header of the `safetensors` format's largest size (100 MB).
pub const MAX_FILE_BYTES: u64 = crate::limits::MAX_PARAMS as u64 * 8 + 100_000_000;

/// Reads the whole file `path`, at most `max_bytes`, through the workspace's one bounded
/// reader ([`vdd_core::files::read_bounded`]): a FIFO, a device (`/dev/zero`), a socket or a
/// directory is refused before it is opened, and no more than the bound is read whatever
/// length the file reports. Errors are [`NnError::Io`] naming the file.
///
/// ```
/// let e = vdd_nn::io::read_bounded(std::path::Path::new("/dev/zero"), 1 << 20).unwrap_err();
/// assert!(e.to_string().contains("/dev/zero"), "{e}");
/// ```
pub fn read_bounded(path: &Path, max_bytes: u64) -> Result<Vec<u8>, NnError> {
    vdd_core::files::read_bounded(path, max_bytes).map_err(io_err(path))
}

/// [`read_bounded`] as UTF-8 text.
pub fn read_bounded_string(path: &Path, max_bytes: u64) -> Result<String, NnError> {
    vdd_core::files::read_bounded_string(path, max_bytes).map_err(io_err(path))
}

/// Opens the regular file `path` (or a symlink to one) for reading, refusing anything else
/// before opening it ([`vdd_core::files::open_regular`]); errors name the file.
pub fn open_regular(path: &Path) -> Result<std::fs::File, NnError> {
    vdd_core::files::open_regular(path).map_err(io_err(path))
}

/// Reads only the string metadata of a `safetensors` file (for example a model's config, to
/// build the model before loading its weights).
pub fn read_metadata(path: &Path) -> Result<BTreeMap<String, String>, NnError> {
    Ok(read_header(path)?.0)
}

/// Reads the string metadata of a `safetensors` file and the total number of tensor elements
/// it holds (over all its tensors), which bounds the parameters of any model it can fill.
pub fn read_header(path: &Path) -> Result<(BTreeMap<String, String>, usize), NnError> {
    let bytes = read_bounded(path, MAX_FILE_BYTES)?;
    let (_, meta) = SafeTensors::read_metadata(&bytes).map_err(malformed(path))?;
    let mut elements = 0usize;
    for (name, info) in meta.tensors() {
        let n = info.shape.iter().try_fold(1usize, |acc, &d| acc.checked_mul(d));
        elements = n.and_then(|n| elements.checked_add(n)).ok_or_else(|| {
            format_err(path, format!("tensor `{name}` has an overflowing shape {:?}", info.shape))
        })?;
    }
    Ok((meta.metadata().clone().unwrap_or_default().into_iter().collect(), elements))
}

/// Checks, before a model is built from a file's metadata, that the file can hold it: the
/// model's parameter count `needed` (`None`: it overflows) must be at most
/// [`MAX_PARAMS`](crate::limits::MAX_PARAMS) and at most the `elements` the file's tensors
/// hold ([`read_header`]). `what` names the metadata entry the model comes from.
pub fn check_fits(
    path: &Path,
    what: &str,
    needed: Option<usize>,
    elements: usize,
) -> Result<(), NnError> {
    let needed = crate::limits::check_params(what, needed)
        .map_err(|e| format_err(path, format!("{what}: {e}")))?;
    if needed > elements {
        return Err(format_err(
            path,
            format!(
                "{what} describes a model of {needed} parameters, the file's tensors hold \
                 {elements} values"
            ),
        ));
    }
    Ok(())
}

/// Loads every parameter of `model` from `path` by name and returns the file's metadata.
///
/// All tensors are checked (present, f32 or f64, same shape, finite) before any parameter is
/// changed, so on error the model is untouched. Extra tensors in the file are ignored, as
/// PyTorch's `load_state_dict(strict=False)` would; missing ones are an error.
pub fn load_safetensors(
    path: &Path,
    model: &mut dyn Parameters,
) -> Result<BTreeMap<String, String>, NnError> {
    let bytes = read_bounded(path, MAX_FILE_BYTES)?;
    load_safetensors_bytes(path, &bytes, model)
}

/// [`load_safetensors`] from bytes in memory; `path` only names the source in errors.
pub fn load_safetensors_bytes(
    path: &Path,
    bytes: &[u8],
    model: &mut dyn Parameters,
) -> Result<BTreeMap<String, String>, NnError> {
    let file = SafeTensors::deserialize(bytes).map_err(malformed(path))?;
    let (_, meta) = SafeTensors::read_metadata(bytes).map_err(malformed(path))?;
    let mut staged: Vec<Vec<f32>> = Vec::new();
    let mut first_error: Option<NnError> = None;
    model.visit_params("", &mut |name, p: &Param| {
        if first_error.is_some() {
            return;
        }
        match read_tensor(path, &file, name, &p.shape) {
            Ok(v) => staged.push(v),
            Err(e) => first_error = Some(e),
        }
    });
    if let Some(e) = first_error {
        return Err(e);
    }
    let mut values = staged.into_iter();
    model.visit_params_mut("", &mut |_, p| {
        if let Some(v) = values.next() {
            p.value = v;
            p.zero_grad();
        }
    });
    Ok(meta.metadata().clone().unwrap_or_default().into_iter().collect())
}

fn read_tensor(
    path: &Path,
    file: &SafeTensors<'_>,
    name: &str,
    shape: &[usize],
) -> Result<Vec<f32>, NnError> {
    let view = file
        .tensor(name)
        .map_err(|_| NnError::MissingTensor { name: name.to_owned(), path: path.to_owned() })?;
    if view.shape() != shape {
        return Err(NnError::ShapeMismatch {
            name: name.to_owned(),
            expected: shape.to_vec(),
            got: view.shape().to_vec(),
        });
    }
    let data = view.data();
    let values: Vec<f32> = match view.dtype() {
        Dtype::F32 => {
            data.chunks_exact(4).map(|c| f32::from_le_bytes([c[0], c[1], c[2], c[3]])).collect()
        }
        Dtype::F64 => data
            .chunks_exact(8)
            .map(|c| f64::from_le_bytes([c[0], c[1], c[2], c[3], c[4], c[5], c[6], c[7]]) as f32)
            .collect(),
        other => {
            return Err(format_err(
                path,
                format!("tensor `{name}` has dtype {other:?}, expected F32"),
            ));
        }
    };
    check_values(name, &values).map_err(|reason| format_err(path, reason))?;
    Ok(values)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::{Activation, Module, ResidualMlp, ResidualMlpConfig};

    fn net(seed: u64) -> ResidualMlp {
        let cfg = ResidualMlpConfig {
            in_dim: 3,
            hidden_dim: 8,
            num_blocks: 2,
            out_dim: 2,
            activation: Activation::Mish,
            layer_norm: false,
        };
        ResidualMlp::new(&cfg, &mut vdd_core::Seeds::new(seed).stream("init")).unwrap()
    }

    fn tmp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("vdd-nn-io-{}-{name}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join("m.safetensors")
    }

    #[test]
    fn round_trip_is_bit_exact() {
        let path = tmp("rt");
        let a = net(1);
        let meta = BTreeMap::from([("k".to_owned(), "v".to_owned())]);
        save_safetensors(&path, &a, &meta).unwrap();
        let mut b = net(2);
        assert_eq!(load_safetensors(&path, &mut b).unwrap(), meta);
        assert_eq!(read_metadata(&path).unwrap(), meta);
        let (mut va, mut vb) = (Vec::new(), Vec::new());
        a.visit_params("", &mut |n, p| va.push((n.to_owned(), p.value.clone())));
        b.visit_params("", &mut |n, p| vb.push((n.to_owned(), p.value.clone())));
        assert_eq!(va, vb);
        let x = faer::Mat::<f32>::from_fn(4, 3, |i, j| (i + j) as f32 * 0.1);
        let mut a = a;
        let out_a = a.forward(x.as_ref()).to_owned();
        let out_b = b.forward(x.as_ref()).to_owned();
        assert_eq!(out_a, out_b);
    }

    #[test]
    fn round_trip_with_layer_norm_and_buffers_is_bit_exact() {
        let cfg = ResidualMlpConfig {
            in_dim: 3,
            hidden_dim: 8,
            num_blocks: 2,
            out_dim: 2,
            activation: Activation::Mish,
            layer_norm: true,
        };
        let mut a = ResidualMlp::new(&cfg, &mut vdd_core::Seeds::new(1).stream("init")).unwrap();
        a.visit_params_mut("", &mut |name, p| {
            if name.contains("normalizer") {
                p.value.iter_mut().enumerate().for_each(|(k, v)| *v += 0.01 * k as f32);
            }
        });
        let path = tmp("ln");
        save_safetensors(&path, &a, &BTreeMap::new()).unwrap();
        let mut b = ResidualMlp::new(&cfg, &mut vdd_core::Seeds::new(2).stream("init")).unwrap();
        load_safetensors(&path, &mut b).unwrap();
        let x = faer::Mat::<f32>::from_fn(4, 3, |i, j| (i + 2 * j) as f32 * 0.3 - 1.0);
        assert_eq!(a.forward(x.as_ref()).to_owned(), b.forward(x.as_ref()).to_owned());
        // A layer-norm file lacks nothing a plain model needs, but a plain file cannot fill a
        // layer-norm model.
        let mut plain = net(3);
        load_safetensors(&path, &mut plain).unwrap();
        save_safetensors(&path, &plain, &BTreeMap::new()).unwrap();
        let err = load_safetensors(&path, &mut b).unwrap_err();
        assert!(
            matches!(err, NnError::MissingTensor { ref name, .. } if name.contains("normalizer"))
        );

        // Fixed buffers (Fourier frequencies) are saved and restored too.
        let ff =
            crate::FourierFeatures::new(6, 30.0, &mut vdd_core::Seeds::new(1).stream("f")).unwrap();
        save_safetensors(&path, &ff, &BTreeMap::new()).unwrap();
        let mut ff2 =
            crate::FourierFeatures::new(6, 30.0, &mut vdd_core::Seeds::new(2).stream("f")).unwrap();
        load_safetensors(&path, &mut ff2).unwrap();
        assert_eq!(ff.w, ff2.w);
    }

    #[test]
    fn truncated_and_mismatched_files_are_clear_errors() {
        let path = tmp("bad");
        save_safetensors(&path, &net(1), &BTreeMap::new()).unwrap();
        let bytes = std::fs::read(&path).unwrap();
        let mut m = net(3);
        let before = m.output_layer_mut().weight.value.clone();
        let err = load_safetensors_bytes(&path, &bytes[..bytes.len() - 7], &mut m).unwrap_err();
        assert!(matches!(err, NnError::Malformed { .. }), "{err}");
        let source = std::error::Error::source(&err).expect("the parser's error is kept");
        assert!(source.downcast_ref::<safetensors::SafeTensorError>().is_some());
        assert_eq!(m.output_layer_mut().weight.value, before, "model changed on error");

        let mut wider = ResidualMlp::new(
            &ResidualMlpConfig {
                in_dim: 3,
                hidden_dim: 9,
                num_blocks: 2,
                out_dim: 2,
                activation: Activation::Mish,
                layer_norm: false,
            },
            &mut vdd_core::Seeds::new(0).stream("init"),
        )
        .unwrap();
        let err = load_safetensors(&path, &mut wider).unwrap_err();
        assert!(matches!(err, NnError::ShapeMismatch { .. }), "{err}");

        let mut deeper = ResidualMlp::new(
            &ResidualMlpConfig {
                in_dim: 3,
                hidden_dim: 8,
                num_blocks: 3,
                out_dim: 2,
                activation: Activation::Mish,
                layer_norm: false,
            },
            &mut vdd_core::Seeds::new(0).stream("init"),
        )
        .unwrap();
        let err = load_safetensors(&path, &mut deeper).unwrap_err();
        assert!(matches!(err, NnError::MissingTensor { .. }), "{err}");

        let missing = path.with_file_name("absent.safetensors");
        assert!(matches!(load_safetensors(&missing, &mut m), Err(NnError::Io { .. })));
    }

    #[test]
    fn hostile_files_are_refused_before_anything_large_is_built() {
        let path = tmp("hostile");
        let mut a = net(1);
        // The writer refuses the value (see below): write a marker and patch the file.
        a.output_layer_mut().weight.value[3] = 0.123_456_7;
        save_safetensors(&path, &a, &BTreeMap::new()).unwrap();
        patch_f32(&path, 0.123_456_7, -2e6);
        let err = load_safetensors(&path, &mut net(2)).unwrap_err().to_string();
        assert!(
            err.contains("-2e6") && err.contains("index 3") && err.contains("hostile"),
            "{err}"
        );

        // The file's own tensors bound the model a config may describe.
        let (_, elements) = read_header(&path).unwrap();
        let mut count = 0;
        a.visit_params("", &mut |_, p| count += p.value.len());
        assert_eq!(elements, count);
        assert_eq!(a.config().num_params(), Some(count));
        check_fits(&path, "config", Some(count), elements).unwrap();
        let err = check_fits(&path, "config", Some(count + 1), elements).unwrap_err();
        assert!(err.to_string().contains(&format!("{} parameters", count + 1)), "{err}");
        let wide = ResidualMlpConfig { hidden_dim: 65536, ..a.config().clone() };
        assert!(check_fits(&path, "config", wide.num_params(), elements).is_err());
        assert!(check_fits(&path, "config", None, elements).is_err());
        let mut rng = vdd_core::Seeds::new(0).stream("init");
        assert!(ResidualMlp::new(&wide, &mut rng).is_err(), "17 GB: refused, not allocated");
        let overflow = ResidualMlpConfig { in_dim: usize::MAX, ..a.config().clone() };
        assert_eq!(overflow.num_params(), None);
        assert!(ResidualMlp::new(&overflow, &mut rng).is_err());
    }

    #[test]
    fn atomic_write_replaces_whole_file_and_leaves_no_temporaries() {
        let path = tmp("atomic").with_file_name("f.bin");
        write_atomic(&path, b"first version").unwrap();
        write_atomic(&path, b"2").unwrap();
        assert_eq!(std::fs::read(&path).unwrap(), b"2");
        let leftovers = std::fs::read_dir(path.parent().unwrap())
            .unwrap()
            .filter(|e| e.as_ref().unwrap().file_name().to_string_lossy().contains(".tmp-"))
            .count();
        assert_eq!(leftovers, 0);
    }

    /// Replaces the one occurrence of `from`'s bytes in the file `path` by `to`'s.
    fn patch_f32(path: &Path, from: f32, to: f32) {
        let mut bytes = std::fs::read(path).unwrap();
        let at = bytes.windows(4).position(|w| w == from.to_le_bytes()).unwrap();
        bytes[at..at + 4].copy_from_slice(&to.to_le_bytes());
        std::fs::write(path, bytes).unwrap();
    }

    #[test]
    fn the_writer_refuses_what_the_loader_would_refuse() {
        let path = tmp("unwritable");
        let _ = std::fs::remove_file(&path);
        for (bad, shown) in [(-2e6f32, "-2e6"), (f32::NAN, "NaN"), (f32::INFINITY, "inf")] {
            let mut a = net(1);
            a.output_layer_mut().weight.value[3] = bad;
            let err = save_safetensors(&path, &a, &BTreeMap::new()).unwrap_err();
            assert!(matches!(err, NnError::Unwritable { .. }), "{err}");
            let msg = err.to_string();
            assert!(msg.contains(shown) && msg.contains("refusing to write"), "{msg}");
            assert!(!path.exists(), "nothing is written");
        }
        // At the bound itself: written and read back.
        let mut a = net(1);
        a.output_layer_mut().weight.value[3] = crate::limits::MAX_ABS_WEIGHT;
        save_safetensors(&path, &a, &BTreeMap::new()).unwrap();
        load_safetensors(&path, &mut net(2)).unwrap();
    }

    #[test]
    fn the_same_model_saves_to_the_same_bytes() {
        // Before, the metadata came out of a `HashMap` in a random order per map.
        let meta: BTreeMap<String, String> =
            (0..32).map(|k| (format!("key{k}"), format!("\"value {k}\""))).collect();
        let a = net(1);
        let first = to_safetensors_bytes(&a, &meta).unwrap();
        for _ in 0..4 {
            assert_eq!(to_safetensors_bytes(&a, &meta).unwrap(), first);
        }
        let header_len = u64::from_le_bytes(first[..8].try_into().unwrap()) as usize;
        assert_eq!(header_len % 8, 0);
        let header = std::str::from_utf8(&first[8..8 + header_len]).unwrap();
        assert!(header.starts_with("{\"__metadata__\":{\"key0\":"), "{header}");
        let mut b = net(2);
        assert_eq!(load_safetensors_bytes(Path::new("mem"), &first, &mut b).unwrap(), meta);
        // No metadata and no tensors are well-formed too.
        struct Empty;
        impl Parameters for Empty {
            fn visit_params(&self, _: &str, _: &mut dyn FnMut(&str, &Param)) {}
            fn visit_params_mut(&mut self, _: &str, _: &mut dyn FnMut(&str, &mut Param)) {}
        }
        let bytes = to_safetensors_bytes(&Empty, &BTreeMap::new()).unwrap();
        assert!(SafeTensors::deserialize(&bytes).is_ok());
        assert!(
            SafeTensors::deserialize(&to_safetensors_bytes(&a, &BTreeMap::new()).unwrap()).is_ok()
        );
    }

    #[test]
    fn special_files_are_refused_naming_them_and_never_read_endlessly() {
        let mut m = net(1);
        if Path::new("/dev/zero").exists() {
            // Length 0 reported, endless content: before, read until memory ran out.
            let err = load_safetensors(Path::new("/dev/zero"), &mut m).unwrap_err().to_string();
            assert!(err.contains("/dev/zero") && err.contains("character device"), "{err}");
            assert!(read_header(Path::new("/dev/urandom")).is_err());
        }
        #[cfg(unix)]
        {
            use std::os::unix::ffi::OsStrExt;
            let fifo = tmp("fifo").with_file_name("pipe.safetensors");
            let _ = std::fs::remove_file(&fifo);
            let c = std::ffi::CString::new(fifo.as_os_str().as_bytes()).unwrap();
            // SAFETY: a valid NUL-terminated path.
            assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
            // Before, this blocked in `open` forever.
            let err = read_metadata(&fifo).unwrap_err().to_string();
            assert!(err.contains("pipe.safetensors") && err.contains("FIFO"), "{err}");
        }
        let dir = tmp("dir").with_file_name("");
        let err = read_bounded(&dir, 10).unwrap_err().to_string();
        assert!(err.contains("directory"), "{err}");
    }
}
