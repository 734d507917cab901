use super::*;
use faer::Mat;
use vdd_core::ScoreModel;
use vdd_core::hash::fnv1a;

use crate::NetConfig;

fn tiny_config() -> TeachersConfig {
    let net = NetConfig { hidden_dim: 8, num_blocks: 1, ..Default::default() };
    let train = TrainConfig { steps: 3, batch_size: 8, log_every: 1, ..Default::default() };
    TeachersConfig {
        beso: BesoTeacherConfig {
            config: BesoConfig { net: net.clone(), ..Default::default() },
            train: train.clone(),
        },
        ddpm: DdpmTeacherConfig { config: DdpmConfig { net, ..Default::default() }, train },
    }
}

fn data() -> (Mat<f32>, Mat<f32>) {
    let states = Mat::from_fn(16, 1, |i, _| i as f32 / 16.0);
    let actions = Mat::from_fn(16, 2, |i, j| (i * (j + 1)) as f32 / 8.0);
    (states, actions)
}

fn key_hash(key: &TeacherCacheKey) -> String {
    format!("{:016x}", fnv1a(serde_json::to_string(key).unwrap().as_bytes()))
}

#[test]
fn the_key_of_a_fixed_config_is_pinned() {
    // Existing caches must keep hitting: this pins the key's JSON bytes and their hash (changed
    // once when the training configuration gained `chunks`).
    let (s, a) = data();
    let config = tiny_config();
    let beso = TeacherCacheKey::new(TeacherKind::Beso, &config, s.as_ref(), a.as_ref(), 4).unwrap();
    let ddpm = TeacherCacheKey::new(TeacherKind::Ddpm, &config, s.as_ref(), a.as_ref(), 4).unwrap();
    let got = (data_hash(s.as_ref(), a.as_ref()), key_hash(&beso), key_hash(&ddpm));
    assert_eq!(
        got,
        ("8763399800319411".into(), "ebeac8a191df0abd".into(), "a3f8d09857b18fd2".into())
    );
}

#[test]
fn the_cache_stores_then_loads_the_same_teacher_under_one_key() {
    let dir = std::env::temp_dir().join(format!("vdd-teacher-cache-{}", std::process::id()));
    let config = tiny_config();
    let (states, actions) = data();
    let (s, a) = (states.as_ref(), actions.as_ref());
    let hash = key_hash(&TeacherCacheKey::new(TeacherKind::Beso, &config, s, a, 4).unwrap());
    let go = |fresh| {
        let cache = TeacherCache { dir: &dir, fresh };
        let mut reports = 0;
        let t = cache
            .train_or_load(TeacherKind::Beso, &config, s, a, 4, &hash, &mut |_| reports += 1)
            .unwrap();
        (t, reports)
    };
    let (first, reports) = go(false);
    assert_eq!(reports, first.losses.len());
    let (loaded, reports) = go(false);
    assert_eq!(reports, 0);
    assert!(!first.cached && loaded.cached);
    let entry = loaded.log_entry(TeacherKind::Beso, 4);
    assert_eq!((entry["teacher"].as_str(), entry["seed"].as_u64()), (Some("beso"), Some(4)));
    assert_eq!((entry["hash"].as_str(), entry["cached"].as_bool()), (Some(&*hash), Some(true)));
    assert_eq!(first.hash, loaded.hash);
    assert_eq!(loaded.losses, first.losses);
    let levels = vec![0.3f32; 16];
    let mut x = Mat::<f32>::zeros(16, 2);
    let mut y = Mat::<f32>::zeros(16, 2);
    first.teacher.clone().score(a, s, &levels, x.as_mut()).unwrap();
    loaded.teacher.clone().score(a, s, &levels, y.as_mut()).unwrap();
    assert_eq!(x, y, "a cached teacher scores bit-identically");
    assert!(!go(true).0.cached, "fresh retrains");
    std::fs::remove_dir_all(&dir).unwrap();
}
