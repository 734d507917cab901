//! The teacher file: one safetensors file holding an imported teacher's tensors, its kind and
//! its spec (JSON metadata), written by `cargo xtask import` and read by [`load_teacher`].

use std::collections::BTreeMap;
use std::path::Path;

use crate::error::ImportError;
use crate::json::{MAX_WEIGHTS_BYTES, read_bounded};
use crate::teacher::ImportedTeacher;
use crate::unet_teacher::{UnetTeacher, UnetTeacherSpec};

/// Metadata key naming the teacher's kind.
pub const KIND_KEY: &str = "vdd_import.kind";
/// Metadata key holding the teacher's spec (JSON).
pub const SPEC_KEY: &str = "vdd_import.spec";
/// The kind of [`UnetTeacher`] files.
pub const KIND_UNET1D: &str = "unet1d";

/// Saves an imported U-Net teacher to one file.
pub fn save_unet_teacher(path: &Path, teacher: &UnetTeacher) -> Result<(), ImportError> {
    let spec = serde_json::to_string(teacher.spec())
        .map_err(|e| ImportError::bad(path.display().to_string(), SPEC_KEY, e))?;
    let meta = BTreeMap::from([
        (KIND_KEY.to_owned(), KIND_UNET1D.to_owned()),
        (SPEC_KEY.to_owned(), spec),
    ]);
    Ok(vdd_nn::io::save_safetensors(path, teacher, &meta)?)
}

/// Loads a teacher file written by `cargo xtask import` (any kind).
///
/// ```no_run
/// use vdd_core::ScoreModel;
/// let teacher = vdd_import::load_teacher("teacher.safetensors".as_ref())?;
/// println!("chunk of {} values", teacher.action_dim());
/// # Ok::<(), vdd_import::ImportError>(())
/// ```
pub fn load_teacher(path: &Path) -> Result<ImportedTeacher, ImportError> {
    let file = path.display().to_string();
    let bytes = read_bounded(path, MAX_WEIGHTS_BYTES)?;
    let (_, meta) = safetensors::SafeTensors::read_metadata(&bytes)
        .map_err(|e| ImportError::bad(&file, "safetensors", e))?;
    let meta = meta.metadata().clone().unwrap_or_default();
    let kind = meta.get(KIND_KEY).ok_or_else(|| ImportError::missing(&file, KIND_KEY))?;
    match kind.as_str() {
        KIND_UNET1D => {
            let spec_json =
                meta.get(SPEC_KEY).ok_or_else(|| ImportError::missing(&file, SPEC_KEY))?;
            let spec: UnetTeacherSpec = serde_json::from_str(spec_json)
                .map_err(|e| ImportError::bad(&file, SPEC_KEY, e))?;
            spec.validate(&file)?;
            let mut teacher = UnetTeacher::new(spec)?;
            vdd_nn::io::load_safetensors_bytes(path, &bytes, &mut teacher)?;
            teacher.check_normalizers(&file)?;
            Ok(ImportedTeacher::Unet1d(Box::new(teacher)))
        }
        other => Err(ImportError::bad(file, KIND_KEY, other)),
    }
}
