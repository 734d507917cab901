//! Resolves a recipe against the defaults of a small training configuration and prints the
//! resolved TOML and its hash.
//!
//! ```text
//! cargo run -p vdd-recipe --example resolve                       # the inline recipe below
//! cargo run -p vdd-recipe --example resolve -- RECIPE.toml --quick --set train.lr=1e-2
//! ```

use serde::{Deserialize, Serialize};
use vdd_recipe::{Overrides, RecipeError, config_hash, defaults_from_toml, read_recipe, resolve};

/// A learning-rate schedule (an externally tagged enum: switching variant replaces the table).
#[derive(Debug, Serialize, Deserialize)]
#[serde(rename_all = "snake_case")]
enum Schedule {
    Constant,
    Cosine { final_factor: f32 },
}

#[derive(Debug, Serialize, Deserialize)]
struct Train {
    lr: f32,
    iterations: usize,
    schedule: Schedule,
}

#[derive(Debug, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
struct Recipe {
    seeds: Vec<u64>,
    methods: Vec<String>,
    train: Train,
}

/// Every key, as a task's embedded defaults file states them.
const DEFAULTS: &str = r#"
seeds = [0]
methods = ["sgd"]

[train]
lr = 1e-3
iterations = 10000
schedule = "constant"
"#;

/// What a recipe file states: only what differs from the defaults.
const RECIPE: &str = r#"
methods = ["sgd", "adam"]

[train]
lr = 3e-4
schedule = { cosine = { final_factor = 0.1 } }

[quick]
"train.iterations" = 100

[[variants]]
name = "long"
description = "four times as many iterations"
set = { "train.iterations" = 40000 }
"#;

fn main() -> Result<(), Box<dyn std::error::Error>> {
    let mut overrides = Overrides::default();
    let mut file = None;
    let mut args = std::env::args().skip(1);
    while let Some(arg) = args.next() {
        match arg.as_str() {
            "--quick" => overrides.quick = true,
            "--seeds" => overrides.seeds = Some(vdd_recipe::parse_seeds(&next(&mut args)?)?),
            "--set" => {
                let kv = next(&mut args)?;
                let (k, v) = kv.split_once('=').ok_or(format!("expected key=value: `{kv}`"))?;
                overrides.sets.push((k.to_owned(), v.to_owned()));
            }
            path => file = Some(read_recipe(path.as_ref())?),
        }
    }
    let file = match file {
        Some(f) => f,
        None => {
            RECIPE.parse().map_err(|e| RecipeError::Parse { name: "RECIPE".into(), source: e })?
        }
    };
    let defaults: Recipe = defaults_from_toml(&[("DEFAULTS", DEFAULTS)])?;
    let resolved = resolve(&defaults, &file, &overrides)?;
    println!("{}", resolved.to_toml()?);
    for (variant, cfg) in resolved.configs() {
        let name = variant.map_or("base", |v| v.name.as_str());
        println!("# {name}: {} iterations, hash {}", cfg.train.iterations, config_hash(cfg)?);
    }
    Ok(())
}

fn next(args: &mut impl Iterator<Item = String>) -> Result<String, String> {
    args.next().ok_or_else(|| "missing value after an option".to_owned())
}
