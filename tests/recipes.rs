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

/// The product of each student's optimiser steps × batch in `t`, by the key of its settings:
/// `vdd.<k>` ((iterations + the rounds' iterations of `vdd.<k>_expert_visits`) × batch ×
/// samples), `baselines.<k>` of a mixture (iterations × expert steps × batch) or of a
/// consistency model (`train.steps` × `train.batch_size`).
fn budget(t: &Table, key: &str) -> u64 {
    let product = |fields: &[&str]| fields.iter().map(|f| get(t, &format!("{key}.{f}"))).product();
    match key {
        _ if key.starts_with("vdd.") => {
            let visits = format!("{key}_expert_visits");
            let rounds = match get_path::<toml::Value>(t, &visits).unwrap() {
                Some(_) => {
                    get(t, &format!("{visits}.rounds")) * get(t, &format!("{visits}.iterations"))
                }
                None => 0,
            };
            let iterations = get(t, &format!("{key}.iterations")) + rounds;
            iterations * product(&["batch_size", "vi_samples"])
        }
        "baselines.cd" | "baselines.ctm.base" => product(&["train.steps", "train.batch_size"]),
        _ => product(&["iterations", "expert_steps_per_iter", "batch_size"]),
    }
}

/// Every student of the Avoiding comparison trains on the same optimiser steps × batch
/// (docs/avoiding-tuning.md, "Budgets"), in the default and in the quick run.
#[test]
fn the_avoiding_students_get_equal_budgets_in_the_default_and_the_quick_run() {
    for (quick, expected) in [(false, 7_680_000), (true, 3_072_000)] {
        let t = recipe("avoiding", "avoiding", quick);
        for key in [
            "vdd.beso",
            "vdd.ddpm",
            "vdd.beso_d3il",
            "baselines.cd",
            "baselines.ctm.base",
            "baselines.em",
            "baselines.imc",
            "baselines.imc_authors",
        ] {
            assert_eq!(budget(&t, key), expected, "{key} (quick: {quick})");
        }
    }
}

/// So do the students of the contact tasks (Pushing's and Aligning's defaults copy
/// Block-Push's budgets), both IMCs included.
#[test]
fn the_contact_tasks_students_get_equal_budgets_in_the_default_and_the_quick_run() {
    for task in ["block-push", "pushing", "aligning"] {
        for (quick, expected) in [(false, 7_680_000), (true, 1_536_000)] {
            let t = recipe(task, task, quick);
            for key in [
                "vdd.beso",
                "vdd.ddpm",
                "baselines.cd",
                "baselines.ctm.base",
                "baselines.em",
                "baselines.imc",
                "baselines.imc_authors",
            ] {
                assert_eq!(budget(&t, key), expected, "{task}: {key} (quick: {quick})");
            }
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
