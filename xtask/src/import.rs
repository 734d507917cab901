//! `cargo xtask import ...` (PyTorch teachers into one teacher file) and
//! `cargo xtask bench import` (the imported networks against PyTorch's recorded outputs).
//!
//! ```text
//! cargo xtask import lerobot DIR --out FILE           # a LeRobot save_pretrained directory
//! cargo xtask import diffusion-policy CKPT --out FILE # a .ckpt, or the directory
//!                                                     # scripts/import/diffusion_policy_ckpt.py writes
//! cargo xtask import beso RUN_DIR --out FILE          # after scripts/import/beso_pth.py RUN_DIR
//! cargo xtask bench import [--fixtures DIR] --out DIR # DIR/import.json
//! ```
//!
//! A `.ckpt` is a pickle: it goes through `scripts/import/diffusion_policy_ckpt.py` (torch, dill,
//! omegaconf) with `--python` (default `python3`) into a directory next to `--out` first.

use std::path::{Path, PathBuf};

use vdd_import::convert;

use crate::XResult;

/// `cargo xtask import ...`.
#[derive(Debug, clap::Subcommand)]
pub enum Import {
    /// A LeRobot DiffusionPolicy directory (config.json, model.safetensors, processor files).
    Lerobot(Args),
    /// A diffusion_policy checkpoint (.ckpt) or its converted directory.
    DiffusionPolicy(Args),
    /// A BESO/D3IL run (hydra config.yaml + model_state_dict.pth, converted first by
    /// scripts/import/beso_pth.py) into a BESO teacher file (vdd_import::BesoTeacher::load).
    Beso(Args),
}

/// Input and output of an import.
#[derive(Debug, Clone, clap::Args)]
pub struct Args {
    /// The package's files.
    pub input: PathBuf,
    /// The teacher file to write.
    #[arg(long)]
    pub out: PathBuf,
    /// The Python that converts a .ckpt.
    #[arg(long, default_value = "python3")]
    pub python: String,
    /// LeRobot: where each `observation.*` feature comes from in the raw observation, e.g.
    /// `observation.state=2,3;observation.environment_state=0,1` (`raw_dim=N;` may lead;
    /// `a..b` ranges are half-open); default: the features concatenated in the policy's order.
    #[arg(long, value_name = "MAP", value_parser = |s: &str| s.parse::<vdd_import::ObsMap>().map_err(|e| e.to_string()))]
    pub obs_map: Option<vdd_import::ObsMap>,
    /// LeRobot: the sampler the teacher acts with (`ddpm`, `ddpm:N`, `ddim:N`); default: the
    /// package's.
    #[arg(long, value_name = "SAMPLER", value_parser = |s: &str| s.parse::<vdd_import::Sampler>().map_err(|e| e.to_string()))]
    pub sampler: Option<vdd_import::Sampler>,
}

/// Runs an import ([`vdd_import::convert`]).
pub fn run(cmd: &Import) -> XResult {
    if let Import::DiffusionPolicy(a) | Import::Beso(a) = cmd {
        if a.obs_map.is_some() || a.sampler.is_some() {
            return Err("--obs-map and --sampler apply to `import lerobot` only".into());
        }
    }
    let line = match cmd {
        Import::Lerobot(a) => {
            let options =
                vdd_import::LerobotOptions { obs_map: a.obs_map.clone(), sampler: a.sampler };
            convert::lerobot_to_file_with(&a.input, &a.out, &options)?
        }
        Import::DiffusionPolicy(a) => {
            let dir = if a.input.is_dir() {
                a.input.clone()
            } else {
                let script = Path::new(env!("CARGO_MANIFEST_DIR"))
                    .join("../scripts/import/diffusion_policy_ckpt.py");
                let dir = a.out.with_extension("converted");
                convert::convert_ckpt(&a.python, &script, &a.input, dir)?
            };
            convert::diffusion_policy_to_file(&dir, &a.out)?
        }
        Import::Beso(a) => convert::beso_to_file(&a.input, &a.out)?,
    };
    println!("{line}");
    Ok(())
}

/// The command line of `bench import`.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchArgs {
    /// Fixture directories (one per architecture).
    #[arg(long, default_value = "tests/fixtures/import")]
    pub fixtures: PathBuf,
    /// Another directory of U-Net fixtures, too large to commit (repeatable): the LeRobot
    /// default-scale U-Net of `scripts/import/unet_fixtures.py --default-scale --out DIR`.
    #[arg(long = "extra")]
    pub extra: Vec<PathBuf>,
    /// Where import.json goes.
    #[arg(long)]
    pub out: PathBuf,
}

/// Checks every fixture and times our forward at batch 1024 on this thread
/// ([`vdd_import::bench::bench_fixtures`]); writes `import.json`.
pub fn bench(a: &BenchArgs) -> XResult {
    let records =
        vdd_import::bench::bench_fixtures(&a.fixtures, &a.extra, |_, line| println!("{line}"))?;
    std::fs::create_dir_all(&a.out)?;
    let path = a.out.join("import.json");
    std::fs::write(&path, serde_json::to_string_pretty(&records)? + "\n")?;
    println!("wrote {}", path.display());
    Ok(())
}
