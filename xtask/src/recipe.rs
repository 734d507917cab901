//! Experiment recipes: TOML files in `recipes/` resolved against the task's defaults, the TOML
//! files in `recipes/defaults/`.
//!
//! # Resolution
//!
//! A recipe file only states what differs from the task's defaults
//! (`recipes/defaults/<task>.toml`, embedded in the binary and read with [`defaults_from_toml`];
//! they state every key of the task's recipe type, which has no defaults of its own).
//! Resolution builds one TOML tree and deserialises it once:
//!
//! 1. the task's defaults (deserialised, which validates them, and serialised again);
//! 2. the recipe file merged on top (tables merge key by key; see [`merge`]), except its
//!    `[quick]` table and `[[variants]]` list;
//! 3. with `--quick`, the recipe's `[quick]` table merged on top;
//! 4. the CLI overrides in order: `--seeds`/`--seed` (the `seeds` key), `--methods` (the
//!    `methods` key) and every `--set key.path=value` (the value is parsed as TOML, and taken
//!    as a string when it does not parse: `--set teachers.beso.config.sampler=heun`);
//! 5. each `[[variants]]` entry (`name`, optional `description`, a `set` table of
//!    `"key.path" = value`) merged on top of that, giving one configuration per variant.
//!
//! Keys may be dotted paths anywhere an overlay is given (`"vdd.beso.iterations" = 100` in
//! `[quick]` or in a variant's `set`). A key the resolved configuration does not know (a typo)
//! is an error that names it, as is a value of the wrong type. Tables whose `kind` differs, and
//! one-key tables naming another variant of an externally tagged enum (`{ cosine = { ... } }`
//! over `{ linear_decay = { ... } }`), replace the default instead of merging into it.
//!
//! Floats that came from `f32` fields are written back in their shortest `f32` form (`0.1`, not
//! `0.10000000149011612`).

use std::path::{Path, PathBuf};

use serde::Serialize;
use serde::de::DeserializeOwned;
use toml::{Table, Value};

/// Errors of recipe handling are plain messages.
pub type RecipeResult<T> = Result<T, String>;

/// CLI overrides of a recipe.
#[derive(Debug, Clone, Default, PartialEq)]
pub struct Overrides {
    /// `--quick`: merge the recipe's `[quick]` table.
    pub quick: bool,
    /// `--seeds 0,1,2` or `--seed N`.
    pub seeds: Option<Vec<u64>>,
    /// `--methods a,b`.
    pub methods: Option<Vec<String>>,
    /// `--set key.path=value`, in order.
    pub sets: Vec<(String, String)>,
}

impl Overrides {
    /// Whether anything beyond seeds and `--quick` was overridden (then the default run name
    /// carries a hash of the overrides).
    pub fn has_config_overrides(&self) -> bool {
        self.methods.is_some() || !self.sets.is_empty()
    }
}

/// One `[[variants]]` entry: a named set of overrides on top of the resolved recipe.
#[derive(Debug, Clone, PartialEq, Serialize, serde::Deserialize)]
#[serde(deny_unknown_fields)]
pub struct Variant {
    /// Short lower-case name, appended to method names (`vdd-beso-z4`).
    pub name: String,
    /// What the variant changes, for tables and plots.
    #[serde(default)]
    pub description: String,
    /// `"key.path" = value` overrides.
    #[serde(default)]
    pub set: Table,
}

/// A resolved recipe: the base configuration and one configuration per variant.
#[derive(Debug, Clone)]
pub struct Resolved<R> {
    /// The base configuration (defaults, file, `--quick`, CLI overrides).
    pub base: R,
    /// The base configuration as a TOML tree (what `resolved.toml` holds).
    pub tree: Table,
    /// `(variant, configuration)` pairs; empty when the recipe has no variants.
    pub variants: Vec<(Variant, R)>,
}

impl<R> Resolved<R> {
    /// The configurations to run: `(label suffix, config)`; the base alone when there are no
    /// variants.
    pub fn configs(&self) -> Vec<(Option<&Variant>, &R)> {
        if self.variants.is_empty() {
            vec![(None, &self.base)]
        } else {
            self.variants.iter().map(|(v, r)| (Some(v), r)).collect()
        }
    }

    /// The resolved configuration as TOML text, variants appended as `[[variants]]`.
    pub fn to_toml(&self) -> RecipeResult<String> {
        let mut t = self.tree.clone();
        if !self.variants.is_empty() {
            let vs: Vec<Value> = self
                .variants
                .iter()
                .map(|(v, _)| Value::try_from(v).map_err(|e| e.to_string()))
                .collect::<RecipeResult<_>>()?;
            t.insert("variants".into(), Value::Array(vs));
        }
        toml::to_string_pretty(&t).map_err(|e| e.to_string())
    }
}

/// Resolves a recipe file against `defaults` (see the module docs).
pub fn resolve<R: Serialize + DeserializeOwned>(
    defaults: &R,
    file: &Table,
    overrides: &Overrides,
) -> RecipeResult<Resolved<R>> {
    let mut file = file.clone();
    let quick = match file.remove("quick") {
        None => Table::new(),
        Some(Value::Table(t)) => t,
        Some(_) => return Err("`quick` must be a table".into()),
    };
    let variants: Vec<Variant> = match file.remove("variants") {
        None => Vec::new(),
        Some(v) => v.try_into().map_err(|e| format!("invalid [[variants]]: {e}"))?,
    };
    let mut tree = to_tree(defaults)?;
    merge(&mut tree, &expand_dotted(&file)?);
    if overrides.quick {
        merge(&mut tree, &expand_dotted(&quick)?);
    }
    if let Some(seeds) = &overrides.seeds {
        let v = seeds.iter().map(|&s| Value::Integer(s as i64)).collect();
        tree.insert("seeds".into(), Value::Array(v));
    }
    if let Some(methods) = &overrides.methods {
        let v = methods.iter().map(|m| Value::String(m.clone())).collect();
        tree.insert("methods".into(), Value::Array(v));
    }
    for (path, value) in &overrides.sets {
        set_path(&mut tree, path, parse_value(value))?;
    }
    let base: R = from_tree(&tree)?;
    let tree = to_tree(&base)?;
    let mut names = std::collections::BTreeSet::new();
    let mut resolved_variants = Vec::with_capacity(variants.len());
    for v in variants {
        if v.name.is_empty() || !names.insert(v.name.clone()) {
            return Err(format!("variant names must be non-empty and unique (`{}`)", v.name));
        }
        let mut t = tree.clone();
        merge(&mut t, &expand_dotted(&v.set)?);
        let r: R = from_tree(&t).map_err(|e| format!("variant `{}`: {e}", v.name))?;
        resolved_variants.push((v, r));
    }
    Ok(Resolved { base, tree, variants: resolved_variants })
}

/// A task's defaults: the TOML `files` (`(name, text)`, the first complete, each next merged on
/// top of it as in [`merge`]) deserialised into the recipe type. Every field must be given
/// (the recipe types have no defaults of their own) and every key known.
pub fn defaults_from_toml<R: Serialize + DeserializeOwned>(
    files: &[(&str, &str)],
) -> RecipeResult<R> {
    let names: Vec<&str> = files.iter().map(|(n, _)| *n).collect();
    from_tree(&defaults_tree(files)?).map_err(|e| format!("{}: {e}", names.join(" + ")))
}

/// The merged tree of [`defaults_from_toml`], as written in the files.
pub fn defaults_tree(files: &[(&str, &str)]) -> RecipeResult<Table> {
    let mut tree = Table::new();
    for (name, text) in files {
        let t: Table = text.parse().map_err(|e| format!("parsing {name}: {e}"))?;
        merge(&mut tree, &expand_dotted(&t)?);
    }
    Ok(tree)
}

/// Test helper: the defaults `files` deserialise into `R` and state every key that `R`
/// serialises (none is left to a serde default), with values that read back unchanged.
#[cfg(test)]
pub fn assert_complete_defaults<R: Serialize + DeserializeOwned>(files: &[(&str, &str)]) {
    let tree = defaults_tree(files).unwrap();
    let r: R = defaults_from_toml(files).unwrap();
    let back = to_tree(&r).unwrap();
    let missing = unknown_keys(&back, &tree, "");
    assert!(missing.is_empty(), "keys missing from the defaults: {missing:?}");
    assert_eq!(back, tree, "values that do not read back unchanged");
}

/// Deserialises `tree`, failing on keys the type does not know.
pub fn from_tree<R: Serialize + DeserializeOwned>(tree: &Table) -> RecipeResult<R> {
    let r: R = Value::Table(tree.clone())
        .try_into()
        .map_err(|e: toml::de::Error| format!("invalid recipe: {}", e.to_string().trim()))?;
    let back = to_tree(&r)?;
    let unknown = unknown_keys(tree, &back, "");
    if !unknown.is_empty() {
        return Err(format!("unknown recipe key(s): {}", unknown.join(", ")));
    }
    Ok(r)
}

/// Serialises `value` into a TOML table, with `f32`-born floats in their shortest form.
pub fn to_tree<T: Serialize + ?Sized>(value: &T) -> RecipeResult<Table> {
    match Value::try_from(value).map_err(|e| e.to_string())? {
        Value::Table(mut t) => {
            for (_, v) in t.iter_mut() {
                prettify_floats(v);
            }
            Ok(t)
        }
        _ => Err("a recipe must serialise to a table".into()),
    }
}

fn prettify_floats(v: &mut Value) {
    match v {
        Value::Float(f) => {
            let g = *f as f32;
            if f64::from(g) == *f && g.is_finite() {
                if let Ok(short) = format!("{g}").parse::<f64>() {
                    *f = short;
                }
            }
        }
        Value::Array(a) => a.iter_mut().for_each(prettify_floats),
        Value::Table(t) => t.iter_mut().for_each(|(_, v)| prettify_floats(v)),
        _ => {}
    }
}

/// Merges `overlay` into `base`: tables merge recursively, anything else replaces. A table
/// replaces instead of merging when its `kind` differs from the base's (internally tagged
/// enums), or when both are one-key tables with different keys and the base's value is a
/// table (an externally tagged enum switching variant: `{ cosine = {..} }` over
/// `{ linear_decay = {..} }`).
pub fn merge(base: &mut Table, overlay: &Table) {
    for (k, v) in overlay {
        match (base.get_mut(k), v) {
            (Some(Value::Table(b)), Value::Table(o)) if !replaces(b, o) => merge(b, o),
            _ => {
                base.insert(k.clone(), v.clone());
            }
        }
    }
}

fn replaces(base: &Table, overlay: &Table) -> bool {
    let kind_differs = matches!(
        (base.get("kind"), overlay.get("kind")),
        (Some(a), Some(b)) if a != b
    );
    // An externally tagged enum with fields is a one-key table whose key is the variant.
    let other_variant = base.len() == 1
        && overlay.len() == 1
        && matches!(base.values().next(), Some(Value::Table(_)))
        && overlay.keys().next() != base.keys().next();
    kind_differs || other_variant
}

/// Turns dotted keys (`"a.b" = 1`) into nested tables, recursively.
pub fn expand_dotted(t: &Table) -> RecipeResult<Table> {
    let mut out = Table::new();
    for (k, v) in t {
        let v = match v {
            Value::Table(inner) => Value::Table(expand_dotted(inner)?),
            other => other.clone(),
        };
        let parts: Vec<&str> = k.split('.').collect();
        if parts.iter().any(|p| p.is_empty()) {
            return Err(format!("invalid key `{k}`"));
        }
        let mut nested = Table::new();
        let mut cur = &mut nested;
        for p in &parts[..parts.len() - 1] {
            cur = match cur.entry(p.to_string()).or_insert_with(|| Value::Table(Table::new())) {
                Value::Table(t) => t,
                _ => unreachable!("just inserted a table"),
            };
        }
        cur.insert(parts[parts.len() - 1].to_string(), v);
        merge_plain(&mut out, &nested);
    }
    Ok(out)
}

/// Deep merge without replacement rules (for assembling one overlay from dotted keys).
fn merge_plain(base: &mut Table, overlay: &Table) {
    for (k, v) in overlay {
        match (base.get_mut(k), v) {
            (Some(Value::Table(b)), Value::Table(o)) => merge_plain(b, o),
            _ => {
                base.insert(k.clone(), v.clone());
            }
        }
    }
}

/// Sets `path` (dotted) to `value`. Every table on the way must exist (a typo is an error);
/// the last key may be new (an optional field that is unset by default).
pub fn set_path(root: &mut Table, path: &str, value: Value) -> RecipeResult<()> {
    let parts: Vec<&str> = path.split('.').collect();
    if path.is_empty() || parts.iter().any(|p| p.is_empty()) {
        return Err(format!("invalid key path `{path}`"));
    }
    let mut cur = root;
    for (i, p) in parts[..parts.len() - 1].iter().enumerate() {
        cur = match cur.get_mut(*p) {
            Some(Value::Table(t)) => t,
            Some(_) => {
                return Err(format!("`{}` is not a table", parts[..=i].join(".")));
            }
            None => return Err(format!("unknown recipe key `{}`", parts[..=i].join("."))),
        };
    }
    let last = parts[parts.len() - 1];
    match (cur.get_mut(last), value) {
        (Some(Value::Table(b)), Value::Table(o)) if !replaces(b, &o) => merge(b, &o),
        (_, v) => {
            cur.insert(last.to_string(), v);
        }
    }
    Ok(())
}

/// Parses a CLI value as TOML (`1e-3`, `true`, `[1, 2]`, `{ kind = "fixed", level = 0.1 }`,
/// `"text"`), falling back to a plain string.
pub fn parse_value(s: &str) -> Value {
    match format!("v = {s}").parse::<Table>() {
        Ok(mut t) => t.remove("v").unwrap_or_else(|| Value::String(s.to_owned())),
        Err(_) => Value::String(s.to_owned()),
    }
}

/// Dotted paths of keys in `input` that `resolved` lacks.
pub fn unknown_keys(input: &Table, resolved: &Table, prefix: &str) -> Vec<String> {
    let mut out = Vec::new();
    for (k, v) in input {
        let path = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
        match (v, resolved.get(k)) {
            (_, None) => out.push(path),
            (Value::Table(a), Some(Value::Table(b))) => out.extend(unknown_keys(a, b, &path)),
            (Value::Array(a), Some(Value::Array(b))) => {
                for (i, (x, y)) in a.iter().zip(b).enumerate() {
                    if let (Value::Table(x), Value::Table(y)) = (x, y) {
                        out.extend(unknown_keys(x, y, &format!("{path}[{i}]")));
                    }
                }
            }
            _ => {}
        }
    }
    out
}

/// FNV-1a 64 of `bytes`.
pub fn fnv1a(bytes: &[u8]) -> u64 {
    let mut h: u64 = 0xcbf2_9ce4_8422_2325;
    for &b in bytes {
        h ^= u64::from(b);
        h = h.wrapping_mul(0x0100_0000_01b3);
    }
    h
}

/// A stable 16-hex-digit hash of `value`'s JSON form (struct fields in declaration order).
pub fn config_hash<T: Serialize + ?Sized>(value: &T) -> RecipeResult<String> {
    let json = serde_json::to_string(value).map_err(|e| e.to_string())?;
    Ok(format!("{:016x}", fnv1a(json.as_bytes())))
}

/// The repository root (the parent of the `xtask` crate).
pub fn repo_root() -> PathBuf {
    let manifest = Path::new(env!("CARGO_MANIFEST_DIR"));
    manifest.parent().unwrap_or(manifest).to_path_buf()
}

/// The recipe file for `name`: an existing `.toml` path, or `recipes/<name>.toml`.
pub fn recipe_path(name: &str) -> RecipeResult<PathBuf> {
    let direct = Path::new(name);
    if name.ends_with(".toml") && direct.is_file() {
        return Ok(direct.to_path_buf());
    }
    let p = repo_root().join("recipes").join(format!("{name}.toml"));
    if p.is_file() {
        Ok(p)
    } else {
        Err(format!("no recipe `{name}` ({} does not exist); available: {}", p.display(), {
            available_recipes().join(", ")
        }))
    }
}

/// Names of the recipes in `recipes/`.
pub fn available_recipes() -> Vec<String> {
    let mut names: Vec<String> = std::fs::read_dir(repo_root().join("recipes"))
        .map(|rd| {
            rd.filter_map(|e| e.ok())
                .filter_map(|e| {
                    let p = e.path();
                    (p.extension()? == "toml").then(|| p.file_stem()?.to_str().map(String::from))?
                })
                .collect()
        })
        .unwrap_or_default();
    names.sort();
    names
}

/// Reads and parses a recipe file.
pub fn read_recipe(path: &Path) -> RecipeResult<Table> {
    let text =
        std::fs::read_to_string(path).map_err(|e| format!("reading {}: {e}", path.display()))?;
    text.parse::<Table>().map_err(|e| format!("parsing {}: {e}", path.display()))
}

/// The most seeds one run takes (a longer `--seeds` range is a typo, not a plan).
pub const MAX_SEEDS: usize = 1000;

/// Parses `0,1,2` (or `0..3`, or one seed) into at most [`MAX_SEEDS`] seeds, each a valid TOML
/// integer (at most `i64::MAX`).
pub fn parse_seeds(s: &str) -> RecipeResult<Vec<u64>> {
    let bad = || format!("invalid seed list `{s}` (expected e.g. 0, 0,1,2 or 0..3)");
    let seed = |x: &str| -> RecipeResult<u64> {
        let v: u64 = x.trim().parse().map_err(|_| bad())?;
        if i64::try_from(v).is_err() {
            return Err(format!("seed {v} is too large (at most {})", i64::MAX));
        }
        Ok(v)
    };
    let too_many = || format!("`{s}` gives more than {MAX_SEEDS} seeds");
    let seeds: Vec<u64> = if let Some((a, b)) = s.split_once("..") {
        let (a, b) = (seed(a)?, seed(b)?);
        if b.saturating_sub(a) > MAX_SEEDS as u64 {
            return Err(too_many());
        }
        (a..b).collect()
    } else {
        s.split(',').map(seed).collect::<RecipeResult<_>>()?
    };
    if seeds.is_empty() {
        return Err(bad());
    }
    if seeds.len() > MAX_SEEDS {
        return Err(too_many());
    }
    Ok(seeds)
}

#[cfg(test)]
mod tests {
    use super::*;
    use serde::Deserialize;

    #[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
    #[serde(tag = "kind", rename_all = "snake_case")]
    enum Noise {
        Fixed { level: f32 },
        Uniform { min: f32, max: f32 },
    }

    #[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
    #[serde(rename_all = "snake_case")]
    enum Sched {
        Constant,
        LinearDecay { total_steps: u64 },
        Cosine { total_steps: u64, final_factor: f32 },
    }

    #[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
    struct Inner {
        lr: f32,
        iterations: usize,
        noise: Noise,
        schedule: Sched,
        freeze: Option<usize>,
    }

    #[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
    #[serde(deny_unknown_fields)]
    struct R {
        name: String,
        seeds: Vec<u64>,
        methods: Vec<String>,
        vdd: Inner,
    }

    fn defaults() -> R {
        R {
            name: "t".into(),
            seeds: vec![0],
            methods: vec!["vdd".into()],
            vdd: Inner {
                lr: 1e-3,
                iterations: 100,
                noise: Noise::Fixed { level: 0.1 },
                schedule: Sched::LinearDecay { total_steps: 100 },
                freeze: None,
            },
        }
    }

    fn table(s: &str) -> Table {
        s.parse().unwrap()
    }

    #[test]
    fn file_quick_and_cli_overrides_apply_in_order() {
        let file = table(
            r#"
            name = "r"
            [vdd]
            lr = 5e-4
            [quick]
            "vdd.iterations" = 10
            "#,
        );
        let none = resolve(&defaults(), &file, &Overrides::default()).unwrap();
        assert_eq!(none.base.vdd.lr, 5e-4);
        assert_eq!(none.base.vdd.iterations, 100);
        assert_eq!(none.base.name, "r");
        let o = Overrides {
            quick: true,
            seeds: Some(vec![1, 2]),
            methods: Some(vec!["a".into(), "b".into()]),
            sets: vec![
                ("vdd.iterations".into(), "20".into()),
                ("vdd.freeze".into(), "7".into()),
                ("vdd.lr".into(), "2e-3".into()),
            ],
        };
        let r = resolve(&defaults(), &file, &o).unwrap();
        assert_eq!(r.base.vdd.iterations, 20, "--set wins over --quick");
        assert_eq!(r.base.vdd.freeze, Some(7), "optional keys can be set");
        assert_eq!(r.base.vdd.lr, 2e-3);
        assert_eq!(r.base.seeds, vec![1, 2]);
        assert_eq!(r.base.methods, vec!["a", "b"]);
        // Without --quick the quick table is ignored.
        let o2 = Overrides { quick: false, ..Default::default() };
        assert_eq!(resolve(&defaults(), &file, &o2).unwrap().base.vdd.iterations, 100);
    }

    #[test]
    fn typos_and_bad_types_are_errors() {
        let bad_key = table("[vdd]\nlearning_rate = 1.0");
        let e = resolve(&defaults(), &bad_key, &Overrides::default()).unwrap_err();
        assert!(e.contains("vdd.learning_rate"), "{e}");
        let o = Overrides { sets: vec![("vdd.lrr".into(), "1".into())], ..Default::default() };
        let e = resolve(&defaults(), &Table::new(), &o).unwrap_err();
        assert!(e.contains("vdd.lrr"), "{e}");
        let o = Overrides { sets: vec![("vd.lr".into(), "1".into())], ..Default::default() };
        assert!(resolve(&defaults(), &Table::new(), &o).unwrap_err().contains("`vd`"));
        let o = Overrides {
            sets: vec![("vdd.iterations".into(), "many".into())],
            ..Default::default()
        };
        assert!(resolve(&defaults(), &Table::new(), &o).is_err());
        let top = table("nme = \"x\"");
        assert!(resolve(&defaults(), &top, &Overrides::default()).unwrap_err().contains("nme"));
    }

    #[test]
    fn enum_tables_replace_instead_of_merging() {
        let file = table(
            r#"
            [vdd.noise]
            kind = "uniform"
            min = 0.05
            max = 0.2
            [vdd.schedule.cosine]
            total_steps = 5
            final_factor = 0.1
            "#,
        );
        let r = resolve(&defaults(), &file, &Overrides::default()).unwrap();
        assert_eq!(r.base.vdd.noise, Noise::Uniform { min: 0.05, max: 0.2 });
        assert_eq!(r.base.vdd.schedule, Sched::Cosine { total_steps: 5, final_factor: 0.1 });
        let o = Overrides {
            sets: vec![
                ("vdd.noise".into(), "{ kind = \"fixed\", level = 0.3 }".into()),
                ("vdd.schedule".into(), "constant".into()),
            ],
            ..Default::default()
        };
        let r = resolve(&defaults(), &Table::new(), &o).unwrap();
        assert_eq!(r.base.vdd.noise, Noise::Fixed { level: 0.3 });
        assert_eq!(r.base.vdd.schedule, Sched::Constant);
        // Partial updates of the same variant merge.
        let o = Overrides {
            sets: vec![("vdd.noise.level".into(), "0.2".into())],
            ..Default::default()
        };
        let r = resolve(&defaults(), &Table::new(), &o).unwrap();
        assert_eq!(r.base.vdd.noise, Noise::Fixed { level: 0.2 });
    }

    #[test]
    fn variants_resolve_on_top_of_the_base() {
        let file = table(
            r#"
            [[variants]]
            name = "a"
            set = { "vdd.iterations" = 1 }
            [[variants]]
            name = "b"
            description = "two"
            set = { "vdd.iterations" = 2, "vdd.noise.level" = 0.5 }
            "#,
        );
        let o = Overrides { sets: vec![("vdd.lr".into(), "0.5".into())], ..Default::default() };
        let r = resolve(&defaults(), &file, &o).unwrap();
        let cs = r.configs();
        assert_eq!(cs.len(), 2);
        assert_eq!(cs[0].1.vdd.iterations, 1);
        assert_eq!(cs[1].1.vdd.iterations, 2);
        assert_eq!(cs[1].1.vdd.noise, Noise::Fixed { level: 0.5 });
        assert!(cs.iter().all(|(_, c)| c.vdd.lr == 0.5), "CLI overrides reach every variant");
        assert!(r.to_toml().unwrap().contains("[[variants]]"));
        let dup = table("[[variants]]\nname = \"a\"\n[[variants]]\nname = \"a\"");
        assert!(resolve(&defaults(), &dup, &Overrides::default()).is_err());
        let typo = table("[[variants]]\nname = \"a\"\nset = { \"vdd.nope\" = 1 }");
        assert!(
            resolve(&defaults(), &typo, &Overrides::default()).unwrap_err().contains("vdd.nope")
        );
    }

    #[test]
    fn resolved_toml_round_trips_with_short_floats() {
        let r = resolve(&defaults(), &Table::new(), &Overrides::default()).unwrap();
        let text = r.to_toml().unwrap();
        assert!(text.contains("lr = 0.001"), "{text}");
        let again = resolve(&defaults(), &table(&text), &Overrides::default()).unwrap();
        assert_eq!(again.base, r.base);
    }

    #[test]
    fn sibling_dotted_keys_and_new_optional_keys_merge() {
        let file = table(
            r#"
            [quick]
            "vdd.iterations" = 3
            "vdd.lr" = 0.5
            [vdd]
            freeze = 4
            "#,
        );
        let o = Overrides { quick: true, ..Default::default() };
        let r = resolve(&defaults(), &file, &o).unwrap();
        assert_eq!((r.base.vdd.iterations, r.base.vdd.lr, r.base.vdd.freeze), (3, 0.5, Some(4)));
        assert_eq!(r.base.vdd.noise, Noise::Fixed { level: 0.1 }, "untouched keys stay");
    }

    #[test]
    fn values_parse_as_toml_or_strings() {
        assert_eq!(parse_value("3"), Value::Integer(3));
        assert_eq!(parse_value("1e-3"), Value::Float(1e-3));
        assert_eq!(parse_value("true"), Value::Boolean(true));
        assert_eq!(parse_value("heun"), Value::String("heun".into()));
        assert_eq!(parse_value("\"x y\""), Value::String("x y".into()));
        assert!(matches!(parse_value("[1, 2]"), Value::Array(a) if a.len() == 2));
    }

    #[test]
    fn seed_lists_and_hashes() {
        assert_eq!(parse_seeds("0,1,2").unwrap(), vec![0, 1, 2]);
        assert_eq!(parse_seeds("2..5").unwrap(), vec![2, 3, 4]);
        assert!(parse_seeds("a").is_err());
        assert!(parse_seeds("3..3").is_err());
        assert!(parse_seeds("0..18446744073709551615").is_err());
        assert!(parse_seeds("0..1001").unwrap_err().contains("more than 1000"));
        assert_eq!(parse_seeds("0..1000").unwrap().len(), 1000);
        assert!(parse_seeds("9223372036854775808").unwrap_err().contains("too large"));
        assert!(parse_seeds(&vec!["1"; 1001].join(",")).is_err());
        let a = config_hash(&defaults()).unwrap();
        let mut d = defaults();
        d.vdd.lr = 2e-3;
        assert_ne!(a, config_hash(&d).unwrap());
        assert_eq!(a, config_hash(&defaults()).unwrap());
        assert_eq!(a.len(), 16);
    }
}
