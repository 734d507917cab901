//! One call per package format: read a PyTorch package, write one teacher file, and say what
//! was written (`cargo xtask import ...`).

use std::path::{Path, PathBuf};

use crate::{BesoError, ImportError, LerobotOptions, UnetTeacherSpec};

/// Imports a LeRobot DiffusionPolicy directory (`config.json`, `model.safetensors`, processor
/// files) into the U-Net teacher file `out`; returns a summary (see [`lerobot_to_file_with`]).
pub fn lerobot_to_file(dir: &Path, out: &Path) -> Result<String, ImportError> {
    lerobot_to_file_with(dir, out, &LerobotOptions::default())
}

/// [`lerobot_to_file`] with the user's observation map and sampler
/// ([`crate::import_lerobot_with`]); returns the summary: the file, the network, the sampler,
/// and the observation map recorded in the file (the stated one, or the in-order layout of
/// the features when none was stated) with the registered feature map applied before it.
pub fn lerobot_to_file_with(
    dir: &Path,
    out: &Path,
    options: &LerobotOptions,
) -> Result<String, ImportError> {
    let teacher = crate::import_lerobot_with(dir, options)?;
    crate::save_unet_teacher(out, &teacher)?;
    Ok(unet_summary(out, teacher.spec()))
}

/// Imports a diffusion_policy checkpoint directory (written by
/// `scripts/import/diffusion_policy_ckpt.py`, see [`convert_ckpt`]) into the U-Net teacher
/// file `out`; returns a one-line summary.
pub fn diffusion_policy_to_file(dir: &Path, out: &Path) -> Result<String, ImportError> {
    let teacher = crate::import_diffusion_policy(dir)?;
    crate::save_unet_teacher(out, &teacher)?;
    Ok(unet_summary(out, teacher.spec()))
}

/// Imports a BESO/D3IL run directory (hydra `config.yaml` and the weights converted by
/// `scripts/import/beso_pth.py`) into the BESO teacher file `out`
/// ([`crate::BesoTeacher::load`]); returns a one-line summary.
pub fn beso_to_file(run_dir: &Path, out: &Path) -> Result<String, BesoError> {
    let teacher = crate::import_beso_run(run_dir)?;
    teacher.save(out)?;
    let c = teacher.config();
    Ok(format!(
        "wrote {} (BESO teacher, {:?} sampler, {} steps, window {})",
        out.display(),
        c.sampler,
        c.steps,
        c.window
    ))
}

fn unet_summary(out: &Path, s: &UnetTeacherSpec) -> String {
    format!(
        "wrote {} ({} U-Net, {} obs steps, horizon {}, {} executed, sampler {})\n{}",
        out.display(),
        s.source,
        s.n_obs_steps,
        s.horizon,
        s.n_action_steps,
        s.sampler(),
        obs_map_summary(s)
    )
}

/// Which raw entries feed which feature, as the teacher file records it.
pub fn obs_map_summary(s: &UnetTeacherSpec) -> String {
    let mapping = match &s.obs_map {
        Some(m) => format!("{m} (stated; raw observation {} wide)", m.raw_dim()),
        None => {
            let mut at = 0;
            let parts: Vec<String> = s
                .obs_features
                .iter()
                .map(|f| {
                    at += f.dim;
                    format!("{}={}..{}", f.name, at - f.dim, at)
                })
                .collect();
            format!(
                "{} (none stated: features in order; raw observation {} wide)",
                parts.join(";"),
                at
            )
        }
    };
    format!("observation map: {mapping}; feature map before it: {}", s.features)
}

/// Converts a diffusion_policy `.ckpt` (a pickle) into a directory [`diffusion_policy_to_file`]
/// reads, by running `python script ckpt --out dir` (the script needs torch, dill and
/// omegaconf); returns `dir`.
pub fn convert_ckpt(
    python: &str,
    script: &Path,
    ckpt: &Path,
    dir: PathBuf,
) -> Result<PathBuf, ImportError> {
    let status = std::process::Command::new(python)
        .arg(script)
        .arg(ckpt)
        .arg("--out")
        .arg(&dir)
        .status()
        .map_err(|source| ImportError::Io { path: script.to_owned(), source })?;
    if !status.success() {
        let (script, input, status) = (script.to_owned(), ckpt.to_owned(), status.to_string());
        return Err(ImportError::Converter { script, input, status });
    }
    Ok(dir)
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn a_failing_converter_or_a_missing_package_is_an_error_naming_the_file() {
        let dir = std::env::temp_dir().join(format!("vdd-import-convert-{}", std::process::id()));
        let e = convert_ckpt("false", Path::new("x.py"), Path::new("a.ckpt"), dir.clone());
        assert!(e.unwrap_err().to_string().contains("a.ckpt"));
        let e = convert_ckpt("/nonexistent/python", Path::new("x.py"), Path::new("a"), dir.clone());
        assert!(matches!(e, Err(ImportError::Io { .. })));
        let e = lerobot_to_file(&dir.join("none"), &dir.join("t.safetensors")).unwrap_err();
        assert!(e.to_string().contains("config.json"), "{e}");
        let opts = LerobotOptions::default();
        let e = lerobot_to_file_with(&dir.join("none"), &dir.join("t.safetensors"), &opts);
        let e = e.unwrap_err();
        assert!(e.to_string().contains("config.json"), "{e}");
        assert!(beso_to_file(&dir.join("none"), &dir.join("t.safetensors")).is_err());
    }
}
