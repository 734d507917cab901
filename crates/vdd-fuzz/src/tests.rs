use std::path::{Path, PathBuf};

use crate::{Loaded, Outcome, Target};

fn scratch(name: &str) -> PathBuf {
    let d = std::env::temp_dir().join(format!("vdd-fuzz-test-{}-{name}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    d
}

fn files(dir: &Path) -> Vec<(std::ffi::OsString, Vec<u8>)> {
    let mut out: Vec<_> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap())
        .map(|e| {
            // A FIFO or a symlink (a non-regular case) is compared by its kind, never read.
            let regular = e.file_type().unwrap().is_file();
            let bytes =
                if regular { std::fs::read(e.path()).unwrap() } else { b"special".to_vec() };
            (e.file_name(), bytes)
        })
        .collect();
    out.sort();
    out
}

#[test]
fn mutations_are_deterministic_for_a_seed() {
    let dir = scratch("determinism");
    for target in [Target::Npz, Target::Moe, Target::Recipe, Target::Lerobot, Target::Beso] {
        let seeds = crate::write_seeds(target, &dir.join(target.name())).unwrap();
        let original: Vec<_> = seeds.iter().map(|s| files(s)).collect();
        let case = |seed, k| {
            let d = dir.join(format!("{target}-{seed}-{k}"));
            crate::prepare_case(target, &seeds, seed, k, &d).unwrap();
            files(&d)
        };
        for k in 0..4 {
            assert_eq!(case(3, k), case(3, k), "{target} case {k}");
        }
        // Some case differs from every seed input, and cases differ between seeds.
        assert!((0..4).any(|k| !original.contains(&case(3, k))), "{target}: nothing mutated");
        assert!((0..4).any(|k| case(3, k) != case(4, k)), "{target}: the seed is ignored");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn every_targets_seed_inputs_load_with_finite_outputs() {
    let dir = scratch("seeds");
    for target in Target::ALL {
        let seeds = crate::write_seeds(target, &dir.join(target.name())).unwrap();
        assert!(!seeds.is_empty());
        for s in &seeds {
            let mut checked = false;
            let loaded = crate::run_case(target, s, |p| {
                checked = p.is_file();
                Ok(())
            });
            assert_eq!(loaded.unwrap(), Loaded::Finite, "{target} {}", s.display());
            assert_eq!(checked, target == Target::Recipe, "{target}");
        }
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_truncated_input_is_a_clean_error() {
    let dir = scratch("truncated");
    let seeds = crate::write_seeds(Target::Moe, &dir).unwrap();
    let file = seeds[0].join("policy.safetensors");
    std::fs::write(&file, &std::fs::read(&file).unwrap()[..100]).unwrap();
    let err = crate::run_case(Target::Moe, &seeds[0], |_| Ok(())).unwrap_err();
    assert!(matches!(err, crate::Error::Target { target: Target::Moe, .. }), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn names_parse_and_exit_codes_classify() {
    for t in Target::ALL {
        assert_eq!(t.name().parse::<Target>().unwrap(), t);
    }
    assert!("npyy".parse::<Target>().is_err());
    let nonfinite = Loaded::NonFinite("output 0 is NaN".into()).exit_code();
    assert_eq!(Outcome::from_exit_code(Some(nonfinite)), Outcome::OkNonfinite);
    assert_eq!(Outcome::from_exit_code(Some(Loaded::Finite.exit_code())), Outcome::Ok);
    assert_eq!(Outcome::from_exit_code(Some(101)), Outcome::Panic);
    let unreadable = Loaded::Unreadable("teacher.safetensors: bad spec".into()).exit_code();
    assert_eq!(Outcome::from_exit_code(Some(unreadable)), Outcome::Unreadable);
    assert!(Outcome::Unreadable.is_failure());
    let holders = Loaded::LockHolders("both writers held the lock".into()).exit_code();
    assert_eq!(Outcome::from_exit_code(Some(holders)), Outcome::LockHolders);
    assert!(Outcome::LockHolders.is_failure());
    assert_eq!(Outcome::from_exit_code(None), Outcome::Abort);
    let mut c = crate::Counts::default();
    for o in [Outcome::Ok, Outcome::Err, Outcome::Hang] {
        c.add(o);
    }
    assert_eq!((c.get(Outcome::Ok), c.failures()), (1, 1));
}

#[test]
fn a_bad_latest_pointer_is_a_clean_error_and_a_stale_lock_is_taken_over() {
    let dir = scratch("latest");
    let seeds = crate::write_seeds(Target::Checkpoint, &dir).unwrap();
    let root = seeds.iter().find(|s| s.join("LATEST").is_file()).expect("a generations seed");
    let latest = std::fs::read_to_string(root.join("LATEST")).unwrap();
    for bad in ["../", "", "gen-x", &latest.repeat(3000)] {
        std::fs::write(root.join("LATEST"), bad).unwrap();
        let e = crate::run_case(Target::Checkpoint, root, |_| Ok(())).unwrap_err();
        assert!(matches!(e, crate::Error::Target { target: Target::Checkpoint, .. }), "{e}");
    }
    std::fs::write(root.join("LATEST"), &latest).unwrap();
    std::fs::write(root.join("LOCK"), "garbage\n").unwrap();
    let loaded = crate::run_case(Target::Checkpoint, root, |_| Ok(())).unwrap();
    assert_eq!(loaded, Loaded::Finite);
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_fifo_or_a_symlink_to_dev_zero_or_a_directory_is_a_clean_error() {
    use std::os::unix::fs::FileTypeExt as _;
    let dir = scratch("not-regular");
    let seeds = crate::write_seeds(Target::Moe, &dir.join("seeds")).unwrap();
    let mut seen = [false; 3];
    for k in 0..2000 {
        let case = dir.join("case");
        crate::prepare_case(Target::Moe, &seeds, 0, k, &case).unwrap();
        let file = case.join("policy.safetensors");
        let meta = std::fs::symlink_metadata(&file).unwrap();
        let kind = match std::fs::read_link(&file) {
            _ if meta.file_type().is_fifo() => 0,
            Ok(to) if to == Path::new("/dev/zero") => 1,
            Ok(_) => 2,
            Err(_) => continue,
        };
        let e = crate::run_case(Target::Moe, &case, |_| Ok(())).unwrap_err();
        assert!(matches!(e, crate::Error::Target { target: Target::Moe, .. }), "{e}");
        seen[kind] = true;
        if seen.iter().all(|s| *s) {
            break;
        }
    }
    assert_eq!(seen, [true; 3], "FIFO, /dev/zero, directory");
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn importer_configs_nested_100000_deep_are_clean_errors() {
    let dir = scratch("deep");
    let deep_json = ["[".repeat(100_000), "{\"a\": ".repeat(100_000) + "1"];
    let dp = crate::write_seeds(Target::DiffusionPolicy, &dir.join("dp")).unwrap();
    for text in &deep_json {
        std::fs::write(dp[0].join("config.json"), text).unwrap();
        let e = crate::run_case(Target::DiffusionPolicy, &dp[0], |_| Ok(())).unwrap_err();
        assert!(format!("{e:?}").contains("nesting"), "{e:?}");
    }
    let beso = crate::write_seeds(Target::Beso, &dir.join("beso")).unwrap();
    let with_scaler = beso.iter().find(|s| s.join(vdd_import::BESO_SCALER_FILE).is_file()).unwrap();
    let yaml = std::fs::read_to_string(with_scaler.join("config.yaml")).unwrap();
    let deep_yaml = [
        format!("deep: {}1{}\n{yaml}", "[".repeat(100_000), "]".repeat(100_000)),
        format!("{}x\n", "- ".repeat(100_000)),
        yaml.replace("sigma_data: 0.5", &format!("sigma_data: {}", "{a: ".repeat(100_000))),
    ];
    for text in &deep_yaml {
        std::fs::write(with_scaler.join("config.yaml"), text).unwrap();
        let e = crate::run_case(Target::Beso, with_scaler, |_| Ok(())).unwrap_err();
        assert!(format!("{e:?}").contains("nesting"), "{e:?}");
    }
    std::fs::write(with_scaler.join("config.yaml"), &yaml).unwrap();
    for text in &deep_json {
        std::fs::write(with_scaler.join(vdd_import::BESO_SCALER_FILE), text).unwrap();
        let e = crate::run_case(Target::Beso, with_scaler, |_| Ok(())).unwrap_err();
        assert!(format!("{e:?}").contains("nesting"), "{e:?}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}

#[test]
fn a_lock_race_has_one_holder_none_under_a_live_writer_and_refuses_a_bad_lock() {
    let dir = scratch("lock");
    let seeds = crate::write_seeds(Target::Lock, &dir).unwrap();
    for s in &seeds {
        for _ in 0..3 {
            assert_eq!(crate::run_case(Target::Lock, s, |_| Ok(())).unwrap(), Loaded::Finite);
        }
        std::fs::write(s.join("HELD"), "").unwrap();
        assert_eq!(crate::run_case(Target::Lock, s, |_| Ok(())).unwrap(), Loaded::Finite);
        std::fs::remove_file(s.join("HELD")).unwrap();
    }
    // The holder removed the stale `LOCK` as it let go; a directory in its place.
    let lock = seeds[1].join("ck").join("LOCK");
    assert!(!lock.exists());
    std::fs::create_dir(&lock).unwrap();
    let e = crate::run_case(Target::Lock, &seeds[1], |_| Ok(())).unwrap_err();
    assert!(format!("{e:?}").contains("LOCK"), "{e:?}");
    let _ = std::fs::remove_dir_all(&dir);
}

/// Cases of the acceptance campaign (`fuzz all --cases 20000 --seed 7`) that once failed,
/// replayed: each is now a clean error.
#[test]
fn cases_the_acceptance_campaign_found_are_clean_errors() {
    let dir = scratch("found");
    // A BESO `sigma_data` of 2^64 − 1: σ_d² overflowed f32 and every score was NaN.
    let seeds = crate::write_seeds(Target::Beso, &dir.join("beso")).unwrap();
    for case in [1084, 2379, 19183] {
        let d = dir.join(format!("beso-{case}"));
        crate::prepare_case(Target::Beso, &seeds, 7, case, &d).unwrap();
        let e = crate::run_case(Target::Beso, &d, |_| Ok(())).unwrap_err();
        assert!(format!("{e:?}").contains("sigma_data"), "case {case}: {e:?}");
    }
    let _ = std::fs::remove_dir_all(&dir);
}
