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
    let fresh = StudentCache { dir: &dir, fresh: true };
    assert!(fresh.load("vdd-beso", "abc").unwrap().is_none(), "--fresh retrains");
    std::fs::remove_dir_all(&dir).unwrap();
}
