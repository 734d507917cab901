//! The fuzzer's targets: the valid seed inputs each one mutates (written by the fuzzer itself),
//! how a case is mutated, and what a case runs in the child process (load, then use: act,
//! score, forward, a training step), with outputs checked for non-finite numbers.

use std::io::{Read as _, Write as _};
use std::path::{Path, PathBuf};

use faer::Mat;
use rand::Rng as _;
use rand::seq::IndexedRandom as _;
use rand_chacha::ChaCha8Rng as Rng;
use vdd_core::{Affine, NoiseSchedule, Policy, ScoreModel, Seeds};
use vdd_data::{DeploySpec, Episodes};
use vdd_moe::{ExpertKind, GatingKind, Moe, MoeConfig};

use crate::{BoxError, Target, mutate};

type Result<T = (), E = BoxError> = std::result::Result<T, E>;

/// What a case did when it loaded: every output finite, or a non-finite one returned as `Ok`.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum Loaded {
    /// Loaded and used; every output finite.
    Finite,
    /// Loaded, and using it returned a non-finite number without an error.
    NonFinite(String),
    /// Loaded, and a file the case's writer then committed was refused by its own loader.
    Unreadable(String),
    /// A lock race ended with the wrong number of holders (what each racer got).
    LockHolders(String),
}

impl Loaded {
    /// The exit code of a child whose case ended so (0 finite, 3 non-finite, 4 unreadable, 5 the
    /// wrong lock holders; see
    /// [`Outcome::from_exit_code`](crate::Outcome::from_exit_code)).
    pub fn exit_code(&self) -> i32 {
        match self {
            Loaded::Finite => 0,
            Loaded::NonFinite(_) => crate::report::EXIT_NONFINITE,
            Loaded::Unreadable(_) => crate::report::EXIT_UNREADABLE,
            Loaded::LockHolders(_) => crate::report::EXIT_LOCK_HOLDERS,
        }
    }
}

/// Writes the seed inputs of `target` under `dir`, one directory each.
pub(crate) fn write_seeds(target: Target, dir: &Path) -> Result<Vec<PathBuf>> {
    let seed_dir = |k: usize| -> Result<PathBuf> {
        let d = dir.join(format!("seed{k}"));
        std::fs::create_dir_all(&d)?;
        Ok(d)
    };
    let mut out = Vec::new();
    match target {
        Target::Npy | Target::Npz => {
            let episodes = (0..3)
                .map(|i| Mat::from_fn(4 + i, 2, |r, c| (r + 2 * c + i) as f32 * 0.1))
                .collect::<Vec<_>>();
            let acts = episodes.iter().map(|m| Mat::from_fn(m.nrows(), 2, |r, c| m[(r, c)] - 0.5));
            let e = Episodes::from_episodes(episodes.clone(), acts.collect())?;
            let d = seed_dir(0)?;
            if target == Target::Npy {
                e.save_npy_dir(&d)?
            } else {
                e.save_npz(&d.join("data.npz"))?
            }
            out.push(d);
        }
        Target::Safetensors => {
            let cfg = net_config();
            let net = vdd_nn::ResidualMlp::new(&cfg, &mut Seeds::new(0).stream("init"))?;
            let meta = [("config".to_owned(), serde_json::to_string(&cfg)?)].into();
            let d = seed_dir(0)?;
            vdd_nn::io::save_safetensors(&d.join("net.safetensors"), &net, &meta)?;
            out.push(d);
        }
        Target::Moe => {
            let d = seed_dir(0)?;
            Moe::from_config(MoeConfig::toy(2, 2, 4), 0)?.save(&d.join("policy.safetensors"))?;
            out.push(d);
            let mut mc = MoeConfig::toy(4, 2, 3);
            mc.expert_kind = ExpertKind::Full;
            mc.gating = GatingKind::Learned;
            mc.experts_network.hidden_dim = 8;
            mc.gating_network.hidden_dim = 8;
            let mut moe = Moe::from_config(mc, 1)?;
            moe.set_normalizers(
                Some(Affine::new(vec![0.0, 1.0, -1.0, 0.5], vec![1.0, 2.0, 0.5, 1.0])?),
                Some(Affine::new(vec![0.5, 0.0], vec![0.1, 0.2])?),
            )?;
            let spec = DeploySpec { obs_window: 2, ..DeploySpec::identity() };
            moe.set_deploy_spec(spec)?;
            let d = seed_dir(1)?;
            moe.save(&d.join("policy.safetensors"))?;
            out.push(d);
        }
        Target::Teacher => {
            use vdd_diffusion::{Beso, BesoConfig, Ddpm, DdpmConfig, NetConfig};
            let net =
                NetConfig { hidden_dim: 8, num_blocks: 1, embed_dim: 4, ..Default::default() };
            let (s, a) = (Affine::identity(1), Affine::new(vec![0.1, -0.2], vec![1.0, 2.0])?);
            let beso = BesoConfig { net: net.clone(), sampling_steps: 4, ..Default::default() };
            let d = seed_dir(0)?;
            let mut t = Beso::new(&beso, s.clone(), a.clone(), 0)?;
            // Its deployment (2-D actions as chunks of two 1-D steps) is in the file too.
            t.set_deploy_spec(DeploySpec {
                action_chunk: 2,
                execute_steps: 2,
                ..DeploySpec::identity()
            })?;
            t.save(&d.join("teacher.safetensors"))?;
            out.push(d);
            let ddpm = DdpmConfig { net, sampling_steps: 4, ..Default::default() };
            let d = seed_dir(1)?;
            Ddpm::new(&ddpm, s, a, 0)?.save(&d.join("teacher.safetensors"))?;
            out.push(d);
        }
        Target::Checkpoint => {
            let (config, teacher, data) = checkpoint_run()?;
            let mut mc = MoeConfig::toy(1, 2, 3);
            mc.gating = GatingKind::Learned;
            mc.experts_network.hidden_dim = 8;
            mc.gating_network.hidden_dim = 8;
            let config = vdd::VddConfig { student_ema: Some(0.9), ..config };
            let mut v = vdd::Vdd::from_config(config, teacher, mc, data)?;
            v.step()?;
            let d = seed_dir(0)?;
            v.write_checkpoint(&d)?;
            out.push(d);
            // A checkpoint directory of generations: `LATEST` names the one to resume.
            let d = seed_dir(1)?;
            v.save_checkpoint(&vdd_nn::checkpoint::CheckpointDir::open(&d)?)?;
            out.push(d);
        }
        Target::Recipe => {
            let d = seed_dir(0)?;
            std::fs::write(d.join("recipe.toml"), include_str!("../../../recipes/toy-gmm.toml"))?;
            out.push(d);
        }
        Target::Lerobot => {
            let d = seed_dir(0)?;
            for (name, bytes) in LEROBOT_FILES {
                std::fs::write(d.join(name), bytes)?;
            }
            out.push(d);
        }
        Target::DiffusionPolicy => {
            let d = seed_dir(0)?;
            for (name, bytes) in DP_FILES {
                std::fs::write(d.join(name), bytes)?;
            }
            out.push(d);
        }
        Target::Beso => {
            // Each fixture as a run directory; two of them again with `scale_data: true` and a
            // `scaler.json` of their widths.
            for (k, (yaml, weights)) in BESO_RUNS.iter().enumerate() {
                let d = seed_dir(k)?;
                std::fs::write(d.join(BESO_CONFIG), yaml)?;
                std::fs::write(d.join(vdd_import::BESO_WEIGHTS_FILE), weights)?;
                out.push(d);
            }
            for (k, &(yaml, weights)) in [BESO_RUNS[0], BESO_RUNS[3]].iter().enumerate() {
                let d = seed_dir(BESO_RUNS.len() + k)?;
                std::fs::write(
                    d.join(BESO_CONFIG),
                    yaml.replace("scale_data: false", "scale_data: true"),
                )?;
                std::fs::write(d.join(vdd_import::BESO_WEIGHTS_FILE), weights)?;
                let cfg = vdd_import::beso_config_from_yaml(&d.join(BESO_CONFIG), yaml, None)?;
                let (od, ad) = (cfg.obs_dim(), cfg.action_dim());
                let row = |n: usize, x: f64| (0..n).map(|i| x + 0.1 * i as f64).collect::<Vec<_>>();
                let scaler = serde_json::json!({
                    "scale_data": true,
                    "x_mean": row(od, -0.2),
                    "x_std": row(od, 0.5),
                    "y_mean": row(ad, 0.1),
                    "y_std": row(ad, 0.8),
                    "y_bounds": [row(ad, -3.0), row(ad, 3.0)],
                });
                std::fs::write(d.join(vdd_import::BESO_SCALER_FILE), scaler.to_string())?;
                out.push(d);
            }
        }
        Target::Lock => {
            // A fresh directory (created by the racers), and one with a stale `LOCK` left by a
            // writer that is gone.
            out.push(seed_dir(0)?);
            let d = seed_dir(1)?;
            std::fs::create_dir_all(d.join(LOCK_ROOT))?;
            std::fs::write(d.join(LOCK_ROOT).join("LOCK"), format!("{} 1\n", u32::MAX - 1))?;
            out.push(d);
        }
    }
    Ok(out)
}

/// The checkpoint directory the racers of a [`Target::Lock`] case open.
const LOCK_ROOT: &str = "ck";
/// A file in a [`Target::Lock`] case: the case holds the lock itself while the racers race.
const LOCK_HELD: &str = "HELD";

/// The hydra config of a BESO seed run.
const BESO_CONFIG: &str = "config.yaml";

/// The BESO/D3IL seed runs: each fixture's hydra config and converted state dict
/// (`tests/fixtures/import/beso_*`).
const BESO_RUNS: [(&str, &[u8]); 4] = {
    macro_rules! fixture {
        ($name:literal) => {
            (
                include_str!(concat!("../../../tests/fixtures/import/", $name, ".yaml")),
                include_bytes!(concat!("../../../tests/fixtures/import/", $name, ".safetensors"))
                    as &[u8],
            )
        };
    }
    [
        fixture!("beso_gpt"),
        fixture!("beso_gpt_goal"),
        fixture!("beso_resmlp"),
        fixture!("beso_resmlp_sin"),
    ]
};

/// The diffusion_policy seed: `tests/fixtures/import/diffusion_policy_unet` as
/// `scripts/import/diffusion_policy_ckpt.py` writes it (a DDPM 1-D U-Net).
const DP_FILES: [(&str, &[u8]); 2] = [
    (
        "config.json",
        include_bytes!("../../../tests/fixtures/import/diffusion_policy_unet/config.json"),
    ),
    (
        "model.safetensors",
        include_bytes!("../../../tests/fixtures/import/diffusion_policy_unet/model.safetensors"),
    ),
];

/// The LeRobot seed policy: the files of `tests/fixtures/import/lerobot_unet_ddpm` the
/// importer reads (a DDPM 1-D U-Net, its config and its processors' JSON and statistics).
const LEROBOT_FILES: [(&str, &[u8]); 6] = {
    macro_rules! fixture {
        ($name:literal) => {
            (
                $name,
                include_bytes!(concat!("../../../tests/fixtures/import/lerobot_unet_ddpm/", $name)),
            )
        };
    }
    [
        fixture!("config.json"),
        fixture!("model.safetensors"),
        fixture!("policy_preprocessor.json"),
        fixture!("policy_preprocessor_step_3_normalizer_processor.safetensors"),
        fixture!("policy_postprocessor.json"),
        fixture!("policy_postprocessor_step_0_unnormalizer_processor.safetensors"),
    ]
};

fn net_config() -> vdd_nn::ResidualMlpConfig {
    vdd_nn::ResidualMlpConfig {
        in_dim: 3,
        hidden_dim: 8,
        num_blocks: 1,
        out_dim: 2,
        activation: vdd_nn::Activation::Mish,
        layer_norm: false,
    }
}

/// The toy run the checkpoint seeds come from and the cases resume.
fn checkpoint_run() -> Result<(vdd::VddConfig, vdd_core::gmm::GmmTeacher, vdd::DistillData)> {
    let gmm = vdd_core::gmm::Gmm::circle(4, 2.0, 0.5, 0.0)?;
    let config = vdd::VddConfig {
        iterations: 4,
        batch_size: 4,
        vi_samples: 4,
        gating_batch_size: 8,
        ..vdd::VddConfig::toy()
    };
    let data = vdd::DistillData::from_states(Mat::zeros(8, 1))?;
    Ok((config, vdd_core::gmm::GmmTeacher::fixed(gmm, 1), data))
}

/// Keys the recipe mutations set (sizes, counts, rates and ranges).
const RECIPE_KEYS: &[&str] = &[
    "seeds",
    "data.points",
    "student.num_experts",
    "student.state_dim",
    "student.action_dim",
    "student.experts_network.hidden_dim",
    "student.experts_network.num_blocks",
    "student.gating_network.hidden_dim",
    "student.mean_bias_init",
    "student.init_std",
    "student.min_std",
    "vdd.exact.iterations",
    "vdd.exact.batch_size",
    "vdd.exact.vi_samples",
    "vdd.exact.gating_batch_size",
    "vdd.exact.expert_steps_per_iter",
    "vdd.exact.expert_optimizer.lr",
    "vdd.exact.noise.level",
    "vdd.exact.student_ema",
    "vdd.exact.max_grad_norm",
    "teachers.beso.config.sampling_steps",
    "teachers.ddpm.config.num_steps",
    "teachers.beso.config.net.hidden_dim",
    "teachers.beso.train.batch_size",
    "teachers.beso.train.steps",
    "eval.kl_samples",
];

/// Case `case` of the campaign with seed `seed`: a copy of one of `seeds`, mutated.
pub(crate) fn prepare_case(
    target: Target,
    seeds: &[PathBuf],
    seed: u64,
    case: usize,
    dir: &Path,
) -> Result {
    if seeds.is_empty() {
        return Err("no seed inputs".into());
    }
    let _ = std::fs::remove_dir_all(dir);
    let mut rng = Seeds::new(seed).stream_indexed(&format!("fuzz-{target}"), case as u64);
    crate::copy_case(&seeds[rng.random_range(0..seeds.len())], dir)?;
    if rng.random_bool(NOT_REGULAR) {
        return not_regular(dir, &mut rng);
    }
    mutate_case(target, dir, &mut rng)
}

/// The share of cases whose input file is replaced by a non-regular one ([`not_regular`]).
const NOT_REGULAR: f64 = 0.06;

/// Replaces one input file of `case` by a FIFO (no writer: opening it for reading would
/// block), a symlink to `/dev/zero` (endless) or a symlink to a directory.
fn not_regular(case: &Path, rng: &mut Rng) -> Result {
    let mut names: Vec<_> = std::fs::read_dir(case)?
        .filter_map(|e| e.ok())
        .filter(|e| e.file_type().is_ok_and(|t| t.is_file()))
        .map(|e| e.path())
        .collect();
    names.sort();
    let Some(path) = names.choose(rng).cloned() else { return Ok(()) };
    std::fs::remove_file(&path)?;
    match rng.random_range(0..3) {
        0 => {
            use std::os::unix::ffi::OsStrExt as _;
            let c = std::ffi::CString::new(path.as_os_str().as_bytes())?;
            // SAFETY: mkfifo reads the NUL-terminated path we pass and creates one file.
            if unsafe { libc::mkfifo(c.as_ptr(), 0o644) } != 0 {
                return Err(std::io::Error::last_os_error().into());
            }
        }
        1 => std::os::unix::fs::symlink("/dev/zero", &path)?,
        _ => std::os::unix::fs::symlink(case, &path)?,
    }
    Ok(())
}

/// Mutates one file of `case` (a copy of a seed directory) in place.
fn mutate_case(target: Target, case: &Path, rng: &mut Rng) -> Result {
    let edit = |name: &str, f: &mut dyn FnMut(&mut Vec<u8>)| -> Result {
        let path = case.join(name);
        let mut bytes = std::fs::read(&path)?;
        f(&mut bytes);
        std::fs::write(&path, bytes)?;
        Ok(())
    };
    match target {
        Target::Npy => {
            let names = ["observations_seq.npy", "actions_seq.npy", "existence_mask.npy"];
            let name = names.choose(rng).copied().unwrap_or(names[0]);
            edit(name, &mut |b| mutate::npy(rng, b))
        }
        Target::Npz if rng.random_bool(0.8) => {
            let path = case.join("data.npz");
            let bytes = std::fs::read(&path)?;
            std::fs::write(&path, rezip(&bytes, rng)?)?;
            Ok(())
        }
        Target::Npz => edit("data.npz", &mut |b| mutate::bytes(rng, b)),
        Target::Safetensors => edit("net.safetensors", &mut |b| mutate::safetensors(rng, b)),
        Target::Moe => edit("policy.safetensors", &mut |b| mutate::safetensors(rng, b)),
        Target::Teacher => edit("teacher.safetensors", &mut |b| mutate::safetensors(rng, b)),
        Target::Checkpoint if case.join(LATEST).is_file() => pointer_or_lock(case, rng),
        Target::Lock => lock_edit(case, rng),
        Target::Checkpoint if rng.random() => {
            edit("trainer.json", &mut |b| mutate::json_file(rng, b))
        }
        Target::Checkpoint => edit("student.safetensors", &mut |b| mutate::safetensors(rng, b)),
        Target::Recipe => edit("recipe.toml", &mut |b| mutate::toml_file(rng, b, RECIPE_KEYS)),
        Target::Lerobot => {
            // The JSON files and the weights' header most of the time: the importer's checks
            // sit behind them.
            let (name, _) = LEROBOT_FILES.choose(rng).copied().unwrap_or(LEROBOT_FILES[0]);
            if name.ends_with(".json") {
                edit(name, &mut |b| mutate::json_file(rng, b))
            } else {
                edit(name, &mut |b| mutate::safetensors(rng, b))
            }
        }
        Target::DiffusionPolicy => match rng.random_range(0..10) {
            0 => edit("config.json", &mut |b| mutate::json_deep(rng, b)),
            1..=6 => edit("config.json", &mut |b| mutate::json_file(rng, b)),
            _ => edit("model.safetensors", &mut |b| mutate::safetensors(rng, b)),
        },
        Target::Beso => {
            let scaler = vdd_import::BESO_SCALER_FILE;
            let has_scaler = case.join(scaler).is_file();
            match rng.random_range(0..10) {
                0 if has_scaler && rng.random() => edit(scaler, &mut |b| mutate::json_deep(rng, b)),
                0 => edit(BESO_CONFIG, &mut |b| mutate::yaml_deep(rng, b)),
                1..=2 if has_scaler => edit(scaler, &mut |b| mutate::json_file(rng, b)),
                1..=6 => edit(BESO_CONFIG, &mut |b| mutate::yaml_file(rng, b)),
                _ => {
                    let weights = vdd_import::BESO_WEIGHTS_FILE;
                    edit(weights, &mut |b| mutate::safetensors(rng, b))
                }
            }
        }
    }
}

/// `LATEST` of a checkpoint directory.
const LATEST: &str = "LATEST";

/// Rewrites `LATEST` (garbage, a missing generation, a path out of the directory, a very long
/// name) or writes a `LOCK` (garbage, a stale owner, huge) in the checkpoint directory `case`.
fn pointer_or_lock(case: &Path, rng: &mut Rng) -> Result {
    let latest = case.join(LATEST);
    let name = std::fs::read_to_string(&latest)?;
    let name = name.trim();
    let lock = case.join("LOCK");
    match rng.random_range(0..9) {
        0 => {
            let mut b = name.as_bytes().to_vec();
            mutate::bytes(rng, &mut b);
            std::fs::write(&latest, b)?
        }
        1 => std::fs::write(&latest, mutate::text_number(rng, name))?,
        2 => std::fs::write(&latest, name.replace(|c: char| c.is_ascii_digit(), "9"))?,
        3 => {
            let up = ["../", "..", "/", "../seed0", "/etc/passwd", "."];
            std::fs::write(&latest, up.choose(rng).copied().unwrap_or("../"))?
        }
        4 => std::fs::write(&latest, name.repeat(rng.random_range(2..5000)))?,
        5 => std::fs::write(&latest, "")?,
        6 => {
            let mut b: Vec<u8> = (0..rng.random_range(0..64)).map(|_| rng.random()).collect();
            mutate::bytes(rng, &mut b);
            std::fs::write(&lock, b)?
        }
        7 => std::fs::write(&lock, format!("{} 1\n", u32::MAX - 1))?,
        _ => std::fs::File::create(&lock)?.set_len(1 << 28)?,
    }
    Ok(())
}

/// Edits the directory a lock race opens: as the seed, a garbage, empty, huge or live-looking
/// `LOCK`, a `LOCK` that is a directory or a symlink, the directory a file, or the lock held
/// by the case itself ([`LOCK_HELD`]).
fn lock_edit(case: &Path, rng: &mut Rng) -> Result {
    let root = case.join(LOCK_ROOT);
    let lock = root.join("LOCK");
    let dir = || std::fs::create_dir_all(&root);
    match rng.random_range(0..10) {
        0..=2 => {}
        3 => {
            dir()?;
            let mut b: Vec<u8> = (0..rng.random_range(0..64)).map(|_| rng.random()).collect();
            mutate::bytes(rng, &mut b);
            std::fs::write(&lock, b)?
        }
        // An owner that is alive (pid 1) but holds no lock.
        4 => {
            dir()?;
            std::fs::write(&lock, "1 1\n")?
        }
        5 => {
            dir()?;
            std::fs::File::create(&lock)?.set_len(1 << 28)?
        }
        6 | 7 => std::fs::write(case.join(LOCK_HELD), "")?,
        8 => {
            dir()?;
            let _ = std::fs::remove_file(&lock);
            match rng.random_range(0..3) {
                0 => std::fs::create_dir(&lock)?,
                1 => std::os::unix::fs::symlink(case.join("elsewhere"), &lock)?,
                _ => std::os::unix::fs::symlink(&root, &lock)?,
            }
        }
        _ => {
            let _ = std::fs::remove_dir_all(&root);
            std::fs::write(&root, "not a directory")?
        }
    }
    Ok(())
}

/// The archive with one entry mutated as an `.npy` file, rewritten stored or deflated.
fn rezip(bytes: &[u8], rng: &mut Rng) -> Result<Vec<u8>> {
    let mut zin = zip::ZipArchive::new(std::io::Cursor::new(bytes))?;
    let mut entries = Vec::new();
    for i in 0..zin.len() {
        let mut f = zin.by_index(i)?;
        let mut data = Vec::new();
        f.read_to_end(&mut data)?;
        entries.push((f.name().to_owned(), data));
    }
    let k = rng.random_range(0..entries.len().max(1));
    if let Some((_, data)) = entries.get_mut(k) {
        mutate::npy(rng, data);
    }
    let method = if rng.random() {
        zip::CompressionMethod::Deflated
    } else {
        zip::CompressionMethod::Stored
    };
    let mut zout = zip::ZipWriter::new(std::io::Cursor::new(Vec::new()));
    for (name, data) in entries {
        zout.start_file(name, zip::write::FileOptions::default().compression_method(method))?;
        zout.write_all(&data)?;
    }
    Ok(zout.finish()?.into_inner())
}

/// Runs one case (in the child process): loads the case's input and uses it.
pub(crate) fn run_case(
    target: Target,
    case: &Path,
    check_recipe: impl FnOnce(&Path) -> Result,
) -> Result<Loaded> {
    let mut outputs: Vec<f32> = Vec::new();
    match target {
        Target::Npy | Target::Npz => {
            let e = if target == Target::Npy {
                Episodes::load_npy_dir(case)?
            } else {
                Episodes::load_npz(&case.join("data.npz"))?
            };
            outputs.extend(e.padded_observations());
            outputs.extend(e.padded_actions());
        }
        Target::Safetensors => {
            let path = case.join("net.safetensors");
            let (meta, elements) = vdd_nn::io::read_header(&path)?;
            let cfg: vdd_nn::ResidualMlpConfig =
                serde_json::from_str(meta.get("config").ok_or("no config metadata")?)?;
            vdd_nn::io::check_fits(&path, "config", cfg.num_params(), elements)?;
            let mut net = vdd_nn::ResidualMlp::new(&cfg, &mut Seeds::new(0).stream("init"))?;
            vdd_nn::io::load_safetensors(&path, &mut net)?;
            let x = Mat::from_fn(4, cfg.in_dim, |i, j| (i as f32 - 1.5) * (j as f32 + 1.0));
            let y = vdd_nn::Module::forward(&mut net, x.as_ref());
            outputs.extend((0..y.nrows()).flat_map(|i| (0..y.ncols()).map(move |j| y[(i, j)])));
        }
        Target::Moe => {
            let path = case.join("policy.safetensors");
            let mut moe = Moe::load(&path)?;
            let obs = Mat::from_fn(3, moe.obs_dim(), |i, j| (i + j) as f32 * 0.3 - 0.5);
            let mut actions = Mat::zeros(3, moe.action_dim());
            moe.act_batch(obs.as_ref(), actions.as_mut())?;
            outputs.extend(
                (0..3)
                    .flat_map(|i| (0..actions.ncols()).map(move |j| (i, j)))
                    .map(|ij| actions[ij]),
            );
            let mut policy = vdd_moe::load_policy(&path)?;
            for step in 0..3 {
                let o: Vec<f32> = (0..policy.obs_dim()).map(|j| (step + j) as f32 * 0.2).collect();
                outputs.extend(policy.act(&o)?);
            }
        }
        Target::Teacher => {
            let mut t =
                vdd_diffusion::DiffusionTeacher::load(&case.join("teacher.safetensors"), 0)?;
            let (ds, da) = (ScoreModel::state_dim(&t), ScoreModel::action_dim(&t));
            let n = 3;
            let mut levels = vec![0.0; n];
            let mut rng = Seeds::new(0).stream("levels");
            t.draw_noise_levels(&NoiseSchedule::Fixed { level: 0.5 }, 0.5, &mut rng, &mut levels);
            let a = Mat::from_fn(n, da, |i, j| (i + j) as f32 * 0.2 - 0.3);
            let s = Mat::from_fn(n, ds, |i, j| (i * j) as f32 * 0.1);
            let mut out = Mat::zeros(n, da);
            t.score(a.as_ref(), s.as_ref(), &levels, out.as_mut())?;
            outputs.extend((0..n).flat_map(|i| (0..da).map(move |j| (i, j))).map(|ij| out[ij]));
            let obs: Vec<f32> = (0..Policy::obs_dim(&t)).map(|j| j as f32 * 0.1).collect();
            outputs.extend(t.act(&obs)?);
            // Through its saved deployment, on raw observations.
            let mut policy = t.into_policy()?;
            for step in 0..3 {
                let o: Vec<f32> = (0..policy.obs_dim()).map(|j| (step + j) as f32 * 0.2).collect();
                outputs.extend(policy.act(&o)?);
            }
        }
        Target::Checkpoint => {
            let (_, teacher, data) = checkpoint_run()?;
            // A directory of generations is resumed as a run does: under its lock; the step's
            // state is then committed, and what was committed must resume.
            let store = match case.join(LATEST).is_file() {
                true => Some(vdd_nn::checkpoint::CheckpointDir::open(case)?),
                false => None,
            };
            let mut v = vdd::Vdd::resume(case, teacher, data)?;
            let m = v.step()?;
            outputs.extend([m.expert.expert_entropy, m.gating_entropy, m.expert_lr]);
            outputs.extend(m.gating_loss);
            if let Some(store) = &store {
                v.save_checkpoint(store)?;
                let (_, teacher, data) = checkpoint_run()?;
                if let Err(e) = vdd::Vdd::resume(case, teacher, data) {
                    return Ok(Loaded::Unreadable(format!("committed checkpoint: {e}")));
                }
            }
            let mut student = v.into_student();
            outputs.extend(student.act(&[0.0])?);
        }
        Target::Recipe => check_recipe(&case.join("recipe.toml"))?,
        Target::Lock => return race(case),
        Target::Lerobot | Target::DiffusionPolicy => {
            let imported = match target {
                Target::Lerobot => vdd_import::import_lerobot(case)?,
                _ => vdd_import::import_diffusion_policy(case)?,
            };
            // The round trip: whatever the importer's output the writer commits, the loader
            // accepts (a refusal is no clean error but a broken file).
            let file = case.join("teacher.safetensors");
            vdd_import::save_unet_teacher(&file, &imported)?;
            let mut t = match vdd_import::load_teacher(&file) {
                Ok(t) => t,
                Err(e) => return Ok(Loaded::Unreadable(format!("{}: {e}", file.display()))),
            };
            score_outputs(&mut t, &mut outputs)?;
        }
        Target::Beso => {
            let imported = vdd_import::import_beso_run(case)?;
            let file = case.join("teacher.safetensors");
            imported.save(&file)?;
            let mut t = match vdd_import::BesoTeacher::load(&file) {
                Ok(t) => t,
                Err(e) => return Ok(Loaded::Unreadable(format!("{}: {e}", file.display()))),
            };
            score_outputs(&mut t, &mut outputs)?;
            let s = Mat::from_fn(2, ScoreModel::state_dim(&t), |i, j| (i + j) as f32 * 0.1 - 0.2);
            let mut a = Mat::zeros(2, ScoreModel::action_dim(&t));
            t.sample_actions(s.as_ref(), &mut Seeds::new(0).stream("sample"), a.as_mut())?;
            outputs
                .extend((0..2).flat_map(|i| (0..a.ncols()).map(move |j| (i, j))).map(|ij| a[ij]));
        }
    }
    Ok(match outputs.iter().position(|v| !v.is_finite()) {
        Some(i) => Loaded::NonFinite(format!("output {i} is {}", outputs[i])),
        None => Loaded::Finite,
    })
}

/// One lock race in the case directory `case` (see [`Target::Lock`]): two processes open its
/// checkpoint directory at the same instant, while the case holds the lock when it says so.
fn race(case: &Path) -> Result<Loaded> {
    use vdd_nn::checkpoint::{CheckpointDir, RaceResult, Racers};
    let root = case.join(LOCK_ROOT);
    let holder = match case.join(LOCK_HELD).exists() {
        true => Some(CheckpointDir::open(&root)?),
        false => None,
    };
    // Whether the lock can be had: the directory new or a directory, its `LOCK` absent or a
    // regular file (never followed if a symlink).
    let kind = |p: &Path| std::fs::symlink_metadata(p).map(|m| m.file_type());
    let usable = kind(&root).map_or(true, |t| t.is_dir())
        && kind(&root.join("LOCK")).map_or(true, |t| t.is_file());
    let got = vdd_nn::checkpoint::race_open(&root, Racers::Processes)?;
    let held = got.iter().filter(|r| **r == RaceResult::Held).count();
    let locked = got.iter().filter(|r| **r == RaceResult::Locked).count();
    let wrong = match (usable, &holder) {
        _ if held > 1 => Some("both writers held the lock"),
        (false, _) if held > 0 => Some("a writer took a lock that is no regular file"),
        (true, Some(_)) if locked < 2 => Some("a writer did not find the live writer's lock"),
        (true, None) if (held, locked) != (1, 1) => Some("not one holder of a free lock"),
        _ => None,
    };
    if let Some(what) = wrong {
        return Ok(Loaded::LockHolders(format!("{what}: {got:?}")));
    }
    drop(holder);
    match got.iter().find_map(|r| match r {
        RaceResult::Failed(e) => Some(e.clone()),
        _ => None,
    }) {
        Some(e) => Err(e.into()),
        None => Ok(Loaded::Finite),
    }
}

/// Scores two rows of an imported teacher at a noise level it draws, into `outputs`.
fn score_outputs(t: &mut dyn ScoreModel, outputs: &mut Vec<f32>) -> Result {
    let (ds, da) = (t.state_dim(), t.action_dim());
    let n = 2;
    let mut levels = vec![0.0; n];
    let mut rng = Seeds::new(0).stream("levels");
    t.draw_noise_levels(&NoiseSchedule::Fixed { level: 0.5 }, 0.5, &mut rng, &mut levels);
    let a = Mat::from_fn(n, da, |i, j| (i + j) as f32 * 0.02 - 0.3);
    let s = Mat::from_fn(n, ds, |i, j| (i * j) as f32 * 0.01);
    let mut out = Mat::zeros(n, da);
    t.score(a.as_ref(), s.as_ref(), &levels, out.as_mut())?;
    outputs.extend((0..n).flat_map(|i| (0..da).map(move |j| (i, j))).map(|ij| out[ij]));
    Ok(())
}
