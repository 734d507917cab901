//! Finished trainings of a run, kept so that a killed run loses only the trainings that were
//! under way: every training that ends writes its policy and what the table reports of it
//! (training seconds, budget, curves) to `<run>/trained/<label>-s<seed>.{safetensors,json}`, and
//! under `--resume` a training whose files are there, with the same key, is loaded instead of
//! run again. Its evaluation runs again, on its own seeded streams, so a resumed run's results
//! equal an uninterrupted run's.
//!
//! The key ([`TrainingKey`]) is the row's whole configuration as the method reads it, the seed,
//! the label, the hash of a file teacher's bytes and a hash of the running executable: a
//! training kept by another build is trained again, not trusted. The JSON sidecar is written
//! after the weights, so a sidecar names a complete training. Only the policy types this
//! workspace saves (a mixture, a diffusion teacher, a consistency or trajectory model) are kept;
//! any other policy trains again.

use std::path::{Path, PathBuf};
use std::sync::OnceLock;

use serde::{Deserialize, Serialize};
use vdd_consistency::{ConsistencyModel, TrajectoryModel};
use vdd_core::hash::Fnv1a;
use vdd_data::DeploySpec;
use vdd_diffusion::DiffusionTeacher;
use vdd_moe::Moe;
use vdd_report::budget::{Budget, BudgetRole};

use vdd_core::Policy;

use crate::method::Trained;
use crate::policy::TrainedPolicy;

/// Largest sidecar read (curves of a long training are the bulk).
const MAX_SIDECAR_BYTES: u64 = 64 << 20;

/// The directory of a run's finished trainings.
pub fn dir(run: &Path) -> PathBuf {
    run.join("trained")
}

/// What a kept training must match to be loaded: a hash of the row's configuration, label and
/// seed, the file teacher's hash and the executable's.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct TrainingKey(String);

impl TrainingKey {
    /// The key of the training `label` on `seed` with the row's configuration `config` (its
    /// TOML text) and the file teacher's hash `teacher_file`, for the running executable.
    pub fn new(config: &str, label: &str, seed: u64, teacher_file: Option<&str>) -> Self {
        let mut h = Fnv1a::default();
        h.write(config.as_bytes()).write(&[0]).write(label.as_bytes()).write(&seed.to_le_bytes());
        h.write(teacher_file.unwrap_or("").as_bytes()).write(&[0]);
        Self(format!("{}-{}", h.hex(), executable_hash()))
    }
}

/// A hash of the running executable's bytes (computed once); `unknown` when it cannot be read,
/// which no kept training matches.
fn executable_hash() -> &'static str {
    static HASH: OnceLock<String> = OnceLock::new();
    HASH.get_or_init(|| {
        let read = std::env::current_exe().and_then(std::fs::read);
        match read {
            Ok(bytes) => {
                let mut h = Fnv1a::default();
                h.write(&bytes);
                h.hex()
            }
            Err(_) => format!("unknown-{}", std::process::id()),
        }
    })
}

#[derive(Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Sidecar {
    key: String,
    kind: Kind,
    /// `None`: not finite (a policy trained elsewhere).
    train_seconds: Option<f64>,
    teacher_seconds: Option<f64>,
    sampling_steps: Option<usize>,
    iterations: Option<usize>,
    noise_level: Option<f32>,
    curves: vdd_core::curves::Curves,
    /// `(steps, batch, student, prefit samples)`.
    budget: Option<(u64, usize, bool, u64)>,
    curve_seconds: f64,
    deploy: Option<DeploySpec>,
}

#[derive(Serialize, Deserialize, Clone, Copy, PartialEq, Eq)]
#[serde(rename_all = "snake_case")]
enum Kind {
    Moe,
    Teacher,
    Consistency,
    Trajectory,
}

fn paths(dir: &Path, label: &str, seed: u64) -> (PathBuf, PathBuf) {
    let stem = format!("{label}-s{seed}");
    (dir.join(format!("{stem}.safetensors")), dir.join(format!("{stem}.json")))
}

/// Keeps `trained` under `dir` with `key`; a policy of a type not saved here is not kept
/// (`Ok(false)`).
pub fn store(
    dir: &Path,
    label: &str,
    seed: u64,
    key: &TrainingKey,
    trained: &Trained,
) -> crate::Result<bool> {
    let (weights, sidecar) = paths(dir, label, seed);
    std::fs::create_dir_all(dir).map_err(|e| format!("creating {}: {e}", dir.display()))?;
    // A sidecar left from an earlier training names these weights no more.
    match std::fs::remove_file(&sidecar) {
        Err(e) if e.kind() != std::io::ErrorKind::NotFound => {
            return Err(format!("removing {}: {e}", sidecar.display()).into());
        }
        _ => {}
    }
    let kind = match &trained.policy {
        TrainedPolicy::Moe(_) => Kind::Moe,
        TrainedPolicy::Teacher(_) => Kind::Teacher,
        TrainedPolicy::Consistency(_) => Kind::Consistency,
        TrainedPolicy::Trajectory(_) => Kind::Trajectory,
        TrainedPolicy::Other(_) => return Ok(false),
    };
    trained.policy.save(&weights)?;
    let finite = |x: f64| x.is_finite().then_some(x);
    let side = Sidecar {
        key: key.0.clone(),
        kind,
        train_seconds: finite(trained.train_seconds),
        teacher_seconds: trained.teacher_seconds.and_then(finite),
        sampling_steps: trained.sampling_steps,
        iterations: trained.iterations,
        noise_level: trained.noise_level.filter(|x| x.is_finite()),
        curves: trained.curves.clone(),
        budget: trained
            .budget
            .map(|b| (b.steps, b.batch, b.role == BudgetRole::Student, b.prefit_samples)),
        curve_seconds: trained.curve_seconds,
        deploy: trained.deploy.clone(),
    };
    let text = serde_json::to_string(&side)?;
    vdd_nn::io::write_atomic(&sidecar, text.as_bytes())?;
    Ok(true)
}

/// The training kept under `dir` for `label` on `seed` if its key is `key`; `None` when there
/// is none, its sidecar does not parse or its key differs (it is trained again). Weights that a
/// matching sidecar names but that do not load, or a deployment spec that does not fit the
/// policy, are an error naming the file.
pub fn load(
    dir: &Path,
    label: &str,
    seed: u64,
    key: &TrainingKey,
) -> crate::Result<Option<Trained>> {
    let (weights, sidecar) = paths(dir, label, seed);
    if !sidecar.is_file() || !weights.is_file() {
        return Ok(None);
    }
    let text = vdd_core::files::read_bounded_string(&sidecar, MAX_SIDECAR_BYTES)
        .map_err(|e| format!("reading {}: {e}", sidecar.display()))?;
    let Ok(side) = serde_json::from_str::<Sidecar>(&text) else { return Ok(None) };
    if side.key != key.0 {
        return Ok(None);
    }
    // Evaluation seeds every policy again; this seed is never drawn from.
    let policy = match side.kind {
        Kind::Moe => TrainedPolicy::Moe(Box::new(Moe::load(&weights)?)),
        Kind::Teacher => TrainedPolicy::Teacher(Box::new(DiffusionTeacher::load(&weights, seed)?)),
        Kind::Consistency => {
            TrainedPolicy::Consistency(Box::new(ConsistencyModel::load(&weights, seed)?))
        }
        Kind::Trajectory => {
            TrainedPolicy::Trajectory(Box::new(TrajectoryModel::load(&weights, seed)?))
        }
    };
    if let Some(spec) = &side.deploy {
        let bad = |e: vdd_data::DataError| format!("{}: key `deploy`: {e}", sidecar.display());
        spec.validate().map_err(bad)?;
        spec.check_policy_dims(policy.obs_dim(), policy.action_dim()).map_err(bad)?;
    }
    let budget = side.budget.map(|(steps, batch, student, prefit)| {
        let b = if student { Budget::student(steps, batch) } else { Budget::teacher(steps, batch) };
        b.with_prefit(prefit)
    });
    Ok(Some(Trained {
        policy,
        train_seconds: side.train_seconds.unwrap_or(f64::NAN),
        teacher_seconds: side.teacher_seconds,
        sampling_steps: side.sampling_steps,
        iterations: side.iterations,
        noise_level: side.noise_level,
        curves: side.curves,
        budget,
        curve_seconds: side.curve_seconds,
        deploy: side.deploy,
    }))
}

#[cfg(test)]
mod tests {
    use super::*;
    use vdd_moe::MoeConfig;

    fn trained() -> Trained {
        let moe = Moe::from_config(MoeConfig::toy(2, 2, 3), 5).unwrap();
        let mut curves = vdd_core::curves::Curves::new();
        curves.insert("success".into(), vec![(1.0, 0.5), (2.0, 0.75)]);
        let mut t = Trained::new(TrainedPolicy::Moe(Box::new(moe)), 12.5, curves);
        t.budget = Some(Budget::student(100, 32).with_prefit(64));
        t.teacher_seconds = Some(3.0);
        t.iterations = Some(100);
        t
    }

    fn temp(name: &str) -> PathBuf {
        let d =
            std::env::temp_dir().join(format!("vdd-lab-finished-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        d
    }

    #[test]
    fn a_kept_training_loads_with_its_key_and_acts_the_same() {
        let dir = temp("round-trip");
        let key = TrainingKey::new("a = 1", "em", 3, None);
        let t = trained();
        assert!(store(&dir, "em", 3, &key, &t).unwrap());
        let back = load(&dir, "em", 3, &key).unwrap().expect("kept");
        assert_eq!(back.train_seconds, 12.5);
        assert_eq!(back.teacher_seconds, Some(3.0));
        assert_eq!(back.iterations, Some(100));
        assert_eq!(back.budget, t.budget);
        assert_eq!(back.curves, t.curves);
        let (mut a, mut b) = (t.policy.clone(), back.policy);
        a.seed(9);
        b.seed(9);
        for _ in 0..4 {
            assert_eq!(a.act(&[0.25, -0.5]).unwrap(), b.act(&[0.25, -0.5]).unwrap());
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn another_key_or_a_broken_sidecar_trains_again() {
        let dir = temp("miss");
        let key = TrainingKey::new("a = 1", "em", 3, None);
        store(&dir, "em", 3, &key, &trained()).unwrap();
        for other in [
            TrainingKey::new("a = 2", "em", 3, None),
            TrainingKey::new("a = 1", "em", 4, None),
            TrainingKey::new("a = 1", "imc", 3, None),
            TrainingKey::new("a = 1", "em", 3, Some("f00d")),
        ] {
            assert_ne!(other, key);
            assert!(load(&dir, "em", 3, &other).unwrap().is_none());
        }
        assert!(load(&dir, "em", 4, &key).unwrap().is_none(), "no files for seed 4");
        std::fs::write(dir.join("em-s3.json"), "{not json").unwrap();
        assert!(load(&dir, "em", 3, &key).unwrap().is_none());
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn a_kept_deployment_that_does_not_fit_the_policy_is_an_error_naming_the_key() {
        let dir = temp("bad-deploy");
        let key = TrainingKey::new("a = 1", "em", 3, None);
        let mut t = trained();
        t.deploy = Some(DeploySpec { obs_window: 2, ..DeploySpec::identity() });
        store(&dir, "em", 3, &key, &t).unwrap();
        // The toy mixture sees 2 numbers: a window of 2 observations of 1.
        assert!(load(&dir, "em", 3, &key).unwrap().is_some());
        let sidecar = dir.join("em-s3.json");
        for window in [3, 0] {
            let text = std::fs::read_to_string(&sidecar).unwrap();
            let mut side: serde_json::Value = serde_json::from_str(&text).unwrap();
            side["deploy"]["obs_window"] = serde_json::json!(window);
            std::fs::write(&sidecar, side.to_string()).unwrap();
            let e = load(&dir, "em", 3, &key).err().expect("an error").to_string();
            assert!(e.contains("em-s3.json") && e.contains("obs_window"), "{e}");
        }
        std::fs::remove_dir_all(&dir).unwrap();
    }

    #[test]
    fn weights_that_a_matching_sidecar_names_but_do_not_load_are_an_error() {
        let dir = temp("bad-weights");
        let key = TrainingKey::new("a = 1", "em", 3, None);
        store(&dir, "em", 3, &key, &trained()).unwrap();
        let weights = dir.join("em-s3.safetensors");
        std::fs::write(&weights, b"not a safetensors file").unwrap();
        let e = load(&dir, "em", 3, &key).err().expect("an error").to_string();
        assert!(e.contains(&weights.display().to_string()), "{e}");
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
