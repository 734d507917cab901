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
use std::time::Instant;

use faer::Mat;
use vdd_import::bench::{BENCH_BATCH, ImportBenchRecord};
use vdd_import::fixture::check_unet_fixture;

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
}

/// Runs an import.
pub fn run(cmd: &Import) -> XResult {
    let (teacher, out) = match cmd {
        Import::Lerobot(a) => (vdd_import::import_lerobot(&a.input)?, &a.out),
        Import::DiffusionPolicy(a) => {
            let dir = if a.input.is_dir() { a.input.clone() } else { convert_ckpt(a)? };
            (vdd_import::import_diffusion_policy(&dir)?, &a.out)
        }
        Import::Beso(a) => {
            let teacher = vdd_import::import_beso_run(&a.input)?;
            teacher.save(&a.out)?;
            let c = teacher.config();
            println!(
                "wrote {} (BESO teacher, {:?} sampler, {} steps, window {})",
                a.out.display(),
                c.sampler,
                c.steps,
                c.window
            );
            return Ok(());
        }
    };
    vdd_import::save_unet_teacher(out, &teacher)?;
    let s = teacher.spec();
    println!(
        "wrote {} ({} U-Net, {} obs steps, horizon {}, {} executed, {:?} {} steps)",
        out.display(),
        s.source,
        s.n_obs_steps,
        s.horizon,
        s.n_action_steps,
        s.scheduler.sampler,
        s.scheduler.num_inference_steps
    );
    Ok(())
}

fn convert_ckpt(a: &Args) -> XResult<PathBuf> {
    let script =
        Path::new(env!("CARGO_MANIFEST_DIR")).join("../scripts/import/diffusion_policy_ckpt.py");
    let dir = a.out.with_extension("converted");
    let status = std::process::Command::new(&a.python)
        .arg(&script)
        .arg(&a.input)
        .arg("--out")
        .arg(&dir)
        .status()
        .map_err(|e| format!("cannot run {} {}: {e}", a.python, script.display()))?;
    if !status.success() {
        return Err(
            format!("{} failed on {} ({status})", script.display(), a.input.display()).into()
        );
    }
    Ok(dir)
}

/// The command line of `bench import`.
#[derive(Debug, Clone, clap::Args)]
pub struct BenchArgs {
    /// Fixture directories (one per architecture).
    #[arg(long, default_value = "tests/fixtures/import")]
    pub fixtures: PathBuf,
    /// Where import.json goes.
    #[arg(long)]
    pub out: PathBuf,
}

/// Checks every U-Net fixture and times our forward at batch 1024 on this thread.
pub fn bench(a: &BenchArgs) -> XResult {
    let mut dirs: Vec<PathBuf> = std::fs::read_dir(&a.fixtures)
        .map_err(|e| format!("{}: {e}", a.fixtures.display()))?
        .filter_map(|e| e.ok().map(|e| e.path()))
        .filter(|p| p.join("expected.safetensors").is_file())
        .collect();
    dirs.sort();
    let mut records = Vec::new();
    for dir in dirs {
        let name = dir.file_name().map(|n| n.to_string_lossy().into_owned()).unwrap_or_default();
        if !(name.starts_with("lerobot_unet") || name.starts_with("diffusion_policy_unet")) {
            continue;
        }
        let (mut teacher, check) = check_unet_fixture(&dir)?;
        let s = teacher.spec().clone();
        let (w, g) = (s.horizon * s.unet.input_dim, s.unet.global_cond_dim);
        let x = Mat::from_fn(BENCH_BATCH, w, |i, j| ((i * 31 + j * 7) % 17) as f32 / 8.0 - 1.0);
        let c = Mat::from_fn(BENCH_BATCH, g, |i, j| ((i * 13 + j * 5) % 11) as f32 / 5.0 - 1.0);
        let t: Vec<f32> = (0..BENCH_BATCH).map(|i| (i % 100) as f32).collect();
        let mut out = Mat::zeros(BENCH_BATCH, w);
        teacher.predict(x.as_ref(), &t, c.as_ref(), out.as_mut())?;
        let mut best = f64::INFINITY;
        for _ in 0..5 {
            let t0 = Instant::now();
            teacher.predict(x.as_ref(), &t, c.as_ref(), out.as_mut())?;
            best = best.min(t0.elapsed().as_secs_f64());
        }
        let r = ImportBenchRecord {
            fixture: name,
            architecture: check.architecture,
            max_abs_diff: check.unet_max_abs_diff.max(check.sample_max_abs_diff),
            rows_per_s: BENCH_BATCH as f64 / best,
            torch_rows_per_s: check.torch_rows_per_s,
        };
        println!(
            "{:24} max_abs_diff {:.2e} (U-Net {:.2e}, sampling {:.2e})  rows/s {:>9.0}  torch {:>9.0}",
            r.fixture,
            r.max_abs_diff,
            check.unet_max_abs_diff,
            check.sample_max_abs_diff,
            r.rows_per_s,
            r.torch_rows_per_s
        );
        records.push(r);
    }
    let row = |fixture: &str, architecture: &str, diff: f64, ours: f64, torch: f64| {
        println!("{fixture:24} max_abs_diff {diff:.2e}  rows/s {ours:>9.0}  torch {torch:>9.0}");
        ImportBenchRecord {
            fixture: fixture.into(),
            architecture: architecture.into(),
            max_abs_diff: diff as f32,
            rows_per_s: ours,
            torch_rows_per_s: torch,
        }
    };
    for name in vdd_import::BESO_FIXTURES {
        let (report, mut teacher) = vdd_import::check_beso_fixture(&a.fixtures, name)?;
        let ours = vdd_import::beso_rows_per_s(&mut teacher, BENCH_BATCH, 2.0)?;
        let arch = format!("beso_{}", report.arch);
        records.push(row(name, &arch, report.max_abs_diff(), ours, report.torch_rows_per_s));
    }
    for name in vdd_import::DP_TRANSFORMER_FIXTURES {
        let (diff, torch, mut net) = vdd_import::check_dp_transformer_fixture(&a.fixtures, name)?;
        let ours = vdd_import::dp_transformer_rows_per_s(&mut net, BENCH_BATCH, 2.0)?;
        records.push(row(name, "diffusion_policy_transformer", diff, ours, torch));
    }
    std::fs::create_dir_all(&a.out)?;
    let path = a.out.join("import.json");
    std::fs::write(&path, serde_json::to_string_pretty(&records)? + "\n")?;
    println!("wrote {}", path.display());
    Ok(())
}
