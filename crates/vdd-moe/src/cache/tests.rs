use super::*;
use vdd_core::Policy;

use crate::{GatingKind, MoeConfig};

#[test]
fn a_stored_student_loads_identically_under_its_key_only() {
    let dir = std::env::temp_dir().join(format!("vdd-moe-student-cache-{}", std::process::id()));
    let cache = StudentCache { dir: &dir, fresh: false };
    let config = MoeConfig { gating: GatingKind::Learned, ..MoeConfig::toy(3, 2, 4) };
    let mut student = Moe::from_config(config, 5).unwrap();
    let mut curves = Curves::default();
    curves.insert("gating loss".into(), vec![(0.0, 1.5), (10.0, 0.5)]);
    let stored = CachedStudent { student: student.clone(), train_seconds: 12.5, curves };
    assert!(cache.load("vdd-beso", "abc").unwrap().is_none(), "empty cache");
    cache.store("vdd-beso", "abc", &stored).unwrap();

    let mut loaded = cache.load("vdd-beso", "abc").unwrap().expect("a hit");
    assert_eq!(loaded.train_seconds, 12.5);
    assert_eq!(loaded.curves, stored.curves);
    let obs = [0.3f32, -0.2, 0.9];
    student.seed(1);
    loaded.student.seed(1);
    assert_eq!(student.act(&obs).unwrap(), loaded.student.act(&obs).unwrap());

    assert!(cache.load("vdd-beso", "abd").unwrap().is_none(), "another key");
    assert!(cache.load("vdd-ddpm", "abc").unwrap().is_none(), "another method");
    // `--fresh` retrains what an earlier process stored (here: files copied in by hand), and
    // reuses what this process stored.
    let earlier = dir.join("earlier");
    let fresh = StudentCache { dir: &earlier, fresh: true };
    std::fs::create_dir_all(&earlier).unwrap();
    let (from, to) = (cache.paths("vdd-beso", "abc"), fresh.paths("vdd-beso", "abc"));
    std::fs::copy(&from.0, &to.0).unwrap();
    std::fs::copy(&from.1, &to.1).unwrap();
    assert!(fresh.load("vdd-beso", "abc").unwrap().is_none(), "--fresh retrains");
    assert!(StudentCache { fresh: false, ..fresh }.load("vdd-beso", "abc").unwrap().is_some());
    fresh.store("vdd-beso", "abc", &stored).unwrap();
    assert!(fresh.load("vdd-beso", "abc").unwrap().is_some(), "stored in this run");
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn a_claimed_student_waits_for_its_claimant_and_no_other() {
    use std::sync::atomic::{AtomicBool, Ordering};
    let cache = StudentCache { dir: Path::new("claims"), fresh: false };
    let first = cache.claim("vdd-beso", "k1");
    let other = cache.claim("vdd-beso", "k2"); // another student: no wait
    drop(other);
    let released = AtomicBool::new(false);
    std::thread::scope(|s| {
        let waiter = s.spawn(|| {
            let _second = cache.claim("vdd-beso", "k1");
            released.load(Ordering::SeqCst)
        });
        std::thread::sleep(std::time::Duration::from_millis(50));
        released.store(true, Ordering::SeqCst);
        drop(first);
        assert!(waiter.join().unwrap(), "the second claim went on before the first ended");
    });
}
