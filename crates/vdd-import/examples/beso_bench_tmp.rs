fn main() {
    let dir =
        std::path::PathBuf::from(env!("CARGO_MANIFEST_DIR")).join("../../tests/fixtures/import");
    for name in vdd_import::BESO_FIXTURES {
        let (r, mut t) = vdd_import::check_beso_fixture(&dir, name).unwrap();
        let ours = vdd_import::beso_rows_per_s(&mut t, 1024, 2.0).unwrap();
        println!(
            "{name}: max_abs_diff {:.2e} rows_per_s {ours:.0} torch {:.0} ratio {:.2}",
            r.max_abs_diff(),
            r.torch_rows_per_s,
            ours / r.torch_rows_per_s
        );
    }
}
