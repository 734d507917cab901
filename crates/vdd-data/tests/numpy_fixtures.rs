//! Loads every fixture written by `tests/fixtures/make_fixtures.py` (numpy): the good ones must
//! equal the reference dataset, the bad ones must fail with the right `DataError`.

use std::path::PathBuf;

use faer::Mat;
use vdd_data::{DataError, Episodes, LoadOptions, SequenceDataset, WindowConfig};

fn fixture(name: &str) -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("tests/fixtures").join(name)
}

const LENGTHS: [usize; 3] = [5, 3, 4];

/// The reference dataset of `make_fixtures.py`, computed with the same float64 arithmetic and
/// rounded to f32 as the loader does.
fn reference() -> Episodes {
    let obs = LENGTHS
        .iter()
        .enumerate()
        .map(|(n, &len)| Mat::from_fn(len, 4, |t, k| ((100 * n + 10 * t + k) as f64 * 0.1) as f32))
        .collect();
    let act = LENGTHS
        .iter()
        .enumerate()
        .map(|(n, &len)| {
            Mat::from_fn(len, 2, |t, k| (-((100 * n + 10 * t + k) as f64) * 0.25) as f32)
        })
        .collect();
    Episodes::from_episodes(obs, act).unwrap()
}

fn assert_bit_identical(a: &Episodes, b: &Episodes) {
    assert_eq!(a.lengths(), b.lengths());
    let bits = |v: &[f32]| v.iter().map(|x| x.to_bits()).collect::<Vec<_>>();
    assert_eq!(bits(a.padded_observations()), bits(b.padded_observations()));
    assert_eq!(bits(a.padded_actions()), bits(b.padded_actions()));
}

#[test]
fn good_fixtures_load_to_the_reference() {
    let want = reference();
    // The f64 -> f32 rounding really happens (0.1 is not an f32).
    assert_eq!(want.observations(0)[(0, 1)], 0.1f32);
    let cases: Vec<(&str, Result<Episodes, DataError>)> = vec![
        ("good_npy_dir", Episodes::load_npy_dir(&fixture("good_npy_dir"))),
        ("good_npy_dir via load", Episodes::load(&fixture("good_npy_dir"))),
        ("good_f64_bool_mask", Episodes::load_npz(&fixture("good_f64_bool_mask.npz"))),
        ("good_compressed_int_mask", Episodes::load_npz(&fixture("good_compressed_int_mask.npz"))),
        ("good_fortran_big_endian", Episodes::load_npz(&fixture("good_fortran_big_endian.npz"))),
        ("good_padding_ignored", Episodes::load(&fixture("good_padding_ignored.npz"))),
        (
            "good_relay_kitchen_time_major",
            Episodes::load_npy_dir_with(
                &fixture("good_relay_kitchen_time_major"),
                &LoadOptions::relay_kitchen(),
            ),
        ),
        (
            "good_block_push",
            Episodes::load_npy_dir_with(&fixture("good_block_push"), &LoadOptions::block_push()),
        ),
    ];
    for (name, got) in cases {
        let got = got.unwrap_or_else(|e| panic!("{name}: {e}"));
        assert_eq!(got, want, "{name}");
        assert_bit_identical(&got, &want);
    }
}

#[test]
fn numpy_data_saves_and_loads_back_bit_identically() {
    let loaded = Episodes::load_npz(&fixture("good_f64_bool_mask.npz")).unwrap();
    let dir = std::env::temp_dir().join(format!("vdd-data-fixture-rt-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let npz = dir.join("copy.npz");
    loaded.save_npz(&npz).unwrap();
    assert_bit_identical(&Episodes::load_npz(&npz).unwrap(), &loaded);
    loaded.save_npy_dir(&dir.join("npy")).unwrap();
    assert_bit_identical(&Episodes::load_npy_dir(&dir.join("npy")).unwrap(), &loaded);
    // The saved float32 directory is byte-for-byte what numpy wrote for the same data, apart
    // from header padding conventions: compare the data bytes at the end of each file.
    for name in ["observations_seq.npy", "actions_seq.npy", "existence_mask.npy"] {
        let ours = std::fs::read(dir.join("npy").join(name)).unwrap();
        let numpy = std::fs::read(fixture("good_npy_dir").join(name)).unwrap();
        let data_len = if name == "observations_seq.npy" {
            3 * 5 * 4 * 4
        } else if name == "actions_seq.npy" {
            3 * 5 * 2 * 4
        } else {
            3 * 5 * 4
        };
        assert_eq!(ours[ours.len() - data_len..], numpy[numpy.len() - data_len..], "{name}");
    }
    std::fs::remove_dir_all(&dir).unwrap();
}

#[test]
fn windows_on_fixture_data() {
    let e = Episodes::load_npy_dir(&fixture("good_npy_dir")).unwrap();
    let data = SequenceDataset::new(e.clone(), WindowConfig::new(2, 3)).unwrap();
    // Lengths 5, 3, 4 -> 5 - 3, 3 - 3, 4 - 3 samples.
    assert_eq!(data.len(), 3);
    assert_eq!(data.skipped_episodes(), 1);
    // Longest episode has 5 valid steps; a window of 4 + chunk of 3 needs 6.
    match SequenceDataset::new(e, WindowConfig::new(4, 3)) {
        Err(DataError::WindowTooLong { needed: 6, longest: 5, .. }) => {}
        other => panic!("expected WindowTooLong, got {other:?}"),
    }
}

fn load_err(name: &str) -> DataError {
    let p = fixture(name);
    match Episodes::load(&p) {
        Ok(_) => panic!("{name} loaded but should have failed"),
        Err(e) => {
            // Every message names what is wrong; print them for the record.
            println!("{name}: {e}");
            e
        }
    }
}

#[test]
fn bad_dtypes_are_rejected() {
    for (name, array) in [
        ("bad_dtype_int_observations.npz", "observations_seq"),
        ("bad_dtype_complex_actions.npz", "actions_seq"),
        ("bad_dtype_string_mask.npz", "existence_mask"),
        ("bad_dtype_object_observations.npz", "observations_seq"),
    ] {
        match load_err(name) {
            DataError::Dtype { array: a, .. } => assert_eq!(a, array, "{name}"),
            e => panic!("{name}: expected a dtype error, got {e}"),
        }
    }
}

#[test]
fn bad_shapes_are_rejected() {
    for name in [
        "bad_rank_observations_2d.npz",
        "bad_rank_mask_3d.npz",
        "bad_mismatched_episodes.npz",
        "bad_mismatched_steps.npz",
        "bad_zero_obs_dim.npz",
    ] {
        assert!(matches!(load_err(name), DataError::Shape { .. }), "{name}");
    }
    for name in ["bad_empty.npz", "bad_zero_steps.npz"] {
        assert!(matches!(load_err(name), DataError::Empty(_)), "{name}");
    }
}

#[test]
fn non_finite_values_are_rejected_with_their_position() {
    let pos = |e: DataError| match e {
        DataError::NonFinite { what, episode, step } => (what, episode, step),
        e => panic!("expected NonFinite, got {e}"),
    };
    assert_eq!(pos(load_err("bad_nan_observation.npz")), ("observations", 1, 2));
    assert_eq!(pos(load_err("bad_inf_action.npz")), ("actions", 2, 3));
    assert_eq!(pos(load_err("bad_f64_overflow.npz")), ("observations", 0, 4));
}

#[test]
fn bad_masks_are_rejected() {
    for name in ["bad_mask_value.npz", "bad_mask_hole.npz", "bad_mask_empty_episode.npz"] {
        match load_err(name) {
            DataError::Mask(msg) => assert!(msg.contains("episode"), "{name}: {msg}"),
            e => panic!("{name}: expected a mask error, got {e}"),
        }
    }
}

#[test]
fn missing_arrays_and_broken_files_are_rejected() {
    match load_err("bad_missing_mask.npz") {
        DataError::MissingKey { key, present, .. } => {
            assert_eq!(key, "existence_mask");
            assert!(present.contains("observations_seq") && present.contains("actions_seq"));
        }
        e => panic!("expected MissingKey, got {e}"),
    }
    match load_err("bad_missing_file_npy_dir") {
        DataError::MissingKey { key, .. } => assert_eq!(key, "actions_seq"),
        e => panic!("expected MissingKey, got {e}"),
    }
    match load_err("bad_not_a_zip.npz") {
        e @ DataError::Archive { .. } => {
            let source = std::error::Error::source(&e).expect("the zip error is the source");
            assert!(source.downcast_ref::<zip::result::ZipError>().is_some(), "{e}");
        }
        e => panic!("expected Archive, got {e}"),
    }
    assert!(matches!(load_err("bad_truncated_npy_dir"), DataError::Format { .. }));
    // The right files under the wrong preset: keys absent.
    assert!(matches!(
        Episodes::load_npy_dir_with(&fixture("good_npy_dir"), &LoadOptions::block_push()),
        Err(DataError::MissingKey { .. })
    ));
}

/// An archive entry is never inflated beyond what its `.npy` header declares: 10 MB of
/// compressed zeros behind a header declaring a few bytes is refused after reading one byte
/// more than declared, and a header declaring more than the limit is refused before reading.
#[test]
fn compressed_entries_are_read_only_up_to_their_declared_size() {
    use std::io::Write;
    let dir = std::env::temp_dir().join(format!("vdd-data-bomb-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let npy = |shape: &str, data: usize| {
        let header = format!("{{'descr': '<f4', 'fortran_order': False, 'shape': ({shape}), }}");
        let mut b = b"\x93NUMPY\x01\x00".to_vec();
        b.extend((header.len() as u16).to_le_bytes());
        b.extend(header.as_bytes());
        b.extend(std::iter::repeat_n(0u8, data));
        b
    };
    let write = |name: &str, obs: Vec<u8>| {
        let path = dir.join(name);
        let mut z = zip::ZipWriter::new(std::fs::File::create(&path).unwrap());
        let opts =
            zip::write::FileOptions::default().compression_method(zip::CompressionMethod::Deflated);
        for (key, bytes) in [
            ("observations_seq", obs),
            ("actions_seq", npy("1, 2, 1", 8)),
            ("existence_mask", npy("1, 2", 8)),
        ] {
            z.start_file(format!("{key}.npy"), opts).unwrap();
            z.write_all(&bytes).unwrap();
        }
        z.finish().unwrap();
        path
    };
    let bomb = write("bomb.npz", npy("1, 2, 1", 10_000_000));
    assert!(std::fs::metadata(&bomb).unwrap().len() < 100_000);
    let err = Episodes::load_npz(&bomb).unwrap_err().to_string();
    assert!(
        err.contains("observations_seq") && err.contains("needs 8 data bytes, the file has 9"),
        "{err}"
    );
    let huge = write("huge.npz", npy("100000, 100000, 1000", 0));
    let err = Episodes::load_npz(&huge).unwrap_err().to_string();
    assert!(err.contains("observations_seq") && err.contains("limit"), "{err}");
    let _ = std::fs::remove_dir_all(&dir);
}
