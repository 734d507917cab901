//! The imported BESO/D3IL networks against PyTorch (fixtures made by
//! `scripts/import/beso_fixtures.py` with the packages' own model code).

use std::path::PathBuf;

use vdd_import::{BESO_FIXTURES, check_beso_fixture};

fn fixtures() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/import")
}

#[test]
fn every_beso_fixture_matches_pytorch_within_1e_4() {
    for name in BESO_FIXTURES {
        let (report, _) = check_beso_fixture(&fixtures(), name).unwrap();
        eprintln!("{report:?}");
        assert!(report.inner_diff < 1e-4, "{report:?}");
        assert!(report.denoised_diff < 1e-4, "{report:?}");
        assert!(report.sampling_diff < 1e-4, "{report:?}");
    }
}

#[test]
fn every_transformer_for_diffusion_fixture_matches_pytorch_within_1e_4() {
    for name in vdd_import::DP_TRANSFORMER_FIXTURES {
        let (diff, _, _) = vdd_import::check_dp_transformer_fixture(&fixtures(), name).unwrap();
        eprintln!("{name}: max_abs_diff {diff:e}");
        assert!(diff < 1e-4, "{name}: {diff}");
    }
}
