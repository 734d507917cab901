//! The repository's recipe files (`recipes/`), read as `cargo xtask experiment` reads them
//! ([`vdd_recipe::resolve`] over `recipes/defaults/`): the protocol's rules that are facts
//! about the files rather than about code.

use toml::Table;
use vdd::{MoeConfig, VddConfig};
use vdd_recipe::{Overrides, defaults_tree, get_path, read_recipe, resolve};

/// `recipes/<name>.toml` over `recipes/defaults/<defaults>.toml`, with `[quick]` merged when
/// `quick`.
fn recipe(name: &str, defaults: &str, quick: bool) -> Table {
    let root = std::path::Path::new(env!("CARGO_MANIFEST_DIR")).parent().unwrap().to_owned();
    let path = format!("recipes/defaults/{defaults}.toml");
    let defaults = defaults_tree(&[(&path, &std::fs::read_to_string(root.join(&path)).unwrap())]);
    let file = read_recipe(&root.join(format!("recipes/{name}.toml"))).unwrap();
    let o = Overrides { quick, ..Default::default() };
    resolve(&defaults.unwrap(), &file, &o).unwrap().base
}

/// The integer at a dotted `path` of `tree`.
fn get(tree: &Table, path: &str) -> u64 {
    get_path(tree, path).unwrap().unwrap_or_else(|| panic!("no {path}"))
}

/// Every student of the Avoiding comparison trains on the same optimiser steps × batch
/// (docs/avoiding-tuning.md, "Budgets"), in the default and in the quick run.
#[test]
fn the_avoiding_students_get_equal_budgets_in_the_default_and_the_quick_run() {
    for (quick, expected) in [(false, 7_680_000), (true, 3_072_000)] {
        let t = recipe("avoiding", "avoiding", quick);
        let vdd = |k: &str| {
            ["iterations", "batch_size", "vi_samples"].map(|f| get(&t, &format!("vdd.{k}.{f}")))
        };
        let mixture = |k: &str| {
            ["iterations", "expert_steps_per_iter", "batch_size"]
                .map(|f| get(&t, &format!("baselines.{k}.{f}")))
        };
        let consistency =
            |k: &str| ["steps", "batch_size"].map(|f| get(&t, &format!("baselines.{k}.train.{f}")));
        let budgets: [(&str, Vec<u64>); 8] = [
            ("vdd-beso", vdd("beso").to_vec()),
            ("vdd-ddpm", vdd("ddpm").to_vec()),
            ("vdd-beso-d3il", vdd("beso_d3il").to_vec()),
            ("cd", consistency("cd").to_vec()),
            ("ctm", consistency("ctm.base").to_vec()),
            ("em", mixture("em").to_vec()),
            ("imc", mixture("imc").to_vec()),
            ("imc-authors", mixture("imc_authors").to_vec()),
        ];
        for (method, factors) in budgets {
            assert_eq!(factors.iter().product::<u64>(), expected, "{method} (quick: {quick})");
        }
    }
}

/// The toy recipe runs the paper's configuration: VDD's and the student's library defaults
/// for the toy ([`VddConfig::toy`], [`MoeConfig::toy`]), 5,000 data points and 100,000
/// samples per KL estimate.
#[test]
fn the_toy_recipe_is_the_papers_configuration() {
    let t = recipe("toy-gmm", "toy-gmm", false);
    let exact: VddConfig = t["vdd"]["exact"].clone().try_into().unwrap();
    // The recipe also states the unit of its levels (σ, the exact mixture's).
    assert_eq!(exact.noise_unit, Some(vdd_core::NoiseConvention::Sigma));
    assert_eq!(VddConfig { noise_unit: None, ..exact }, VddConfig::toy());
    let student: MoeConfig = t["student"].clone().try_into().unwrap();
    assert_eq!(student, MoeConfig::toy(1, 2, 8));
    assert_eq!((get(&t, "data.points"), get(&t, "eval.kl_samples")), (5000, 100_000));
}
