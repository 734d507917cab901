//! `cargo xtask import ...`: PyTorch teachers into one teacher file the crates load.
//!
//! ```text
//! python scripts/import/beso_pth.py RUN_DIR [--scaler scaler.npz]   # .pth -> safetensors
//! cargo xtask import beso RUN_DIR --out teacher.safetensors
//! ```

use std::path::PathBuf;

use crate::XResult;

/// `cargo xtask import ...`.
#[derive(Debug, clap::Subcommand)]
pub enum Import {
    /// A BESO/D3IL run (hydra config.yaml + model_state_dict.pth, converted first by
    /// scripts/import/beso_pth.py) into a BESO teacher file (vdd_import::BesoTeacher::load).
    Beso(BesoArgs),
}

/// Arguments of `cargo xtask import beso`.
#[derive(Debug, clap::Args)]
pub struct BesoArgs {
    /// The run directory.
    pub dir: PathBuf,
    /// The teacher file to write.
    #[arg(long)]
    pub out: PathBuf,
}

/// Runs an import command.
pub fn run(cmd: &Import) -> XResult {
    match cmd {
        Import::Beso(a) => {
            let teacher = vdd_import::import_beso_run(&a.dir)?;
            teacher.save(&a.out)?;
            let c = teacher.config();
            println!(
                "imported BESO teacher ({:?} sampler, {} steps, window {}) -> {}",
                c.sampler,
                c.steps,
                c.window,
                a.out.display()
            );
            Ok(())
        }
    }
}
