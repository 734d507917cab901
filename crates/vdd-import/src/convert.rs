//! One call per package format: read a PyTorch package, write one teacher file, and say what
//! was written (`cargo xtask import ...`).

use std::path::{Path, PathBuf};

use crate::{BesoError, ImportError, UnetTeacherSpec};

/// Imports a LeRobot DiffusionPolicy directory (`config.json`, `model.safetensors`, processor
/// files) into the U-Net teacher file `out`; returns a one-line summary.
pub fn lerobot_to_file(dir: &Path, out: &Path) -> Result<String, ImportError> {
    let teacher = crate::import_lerobot(dir)?;
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
        "wrote {} ({} U-Net, {} obs steps, horizon {}, {} executed, {:?} {} steps)",
        out.display(),
        s.source,
        s.n_obs_steps,
        s.horizon,
        s.n_action_steps,
        s.scheduler.sampler,
        s.scheduler.num_inference_steps
    )
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
        assert!(beso_to_file(&dir.join("none"), &dir.join("t.safetensors")).is_err());
    }
}
