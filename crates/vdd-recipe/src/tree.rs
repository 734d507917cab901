//! Operations on TOML trees: merging, dotted keys, `--set` paths, CLI values, unknown keys, and
//! conversion from and to recipe types.

use serde::Serialize;
use serde::de::DeserializeOwned;
use toml::{Table, Value};

use crate::{RecipeError, RecipeResult};

/// Deserialises `tree`, failing on keys the type does not know.
///
/// A key is unknown when it does not come back when the deserialised value is serialised
/// again, so this works for types without `#[serde(deny_unknown_fields)]` too.
pub fn from_tree<R: Serialize + DeserializeOwned>(tree: &Table) -> RecipeResult<R> {
    let r: R = Value::Table(tree.clone()).try_into().map_err(RecipeError::Invalid)?;
    let back = to_tree(&r)?;
    let unknown = unknown_keys(tree, &back, "");
    if !unknown.is_empty() {
        return Err(RecipeError::UnknownKeys(unknown));
    }
    Ok(r)
}

/// The value at the dotted `path` of `tree` (`baselines.em`) as a `T`, `None` when a key on
/// the way is absent; a table is read with [`from_tree`] (unknown keys are errors). Errors name
/// the path ([`RecipeError::AtPath`]).
pub fn get_path<T: Serialize + DeserializeOwned>(
    tree: &Table,
    path: &str,
) -> RecipeResult<Option<T>> {
    let mut parts = path.split('.');
    let mut cur = tree.get(parts.next().unwrap_or_default());
    for p in parts {
        cur = match cur {
            Some(Value::Table(t)) => t.get(p),
            _ => None,
        };
    }
    let parsed = match cur {
        None => return Ok(None),
        Some(Value::Table(t)) => from_tree(t),
        Some(v) => v.clone().try_into().map_err(RecipeError::Invalid),
    };
    let at = |e| RecipeError::AtPath { path: path.to_owned(), source: Box::new(e) };
    parsed.map(Some).map_err(at)
}

/// Serialises `value` into a TOML table, with `f32`-born floats in their shortest form.
pub fn to_tree<T: Serialize + ?Sized>(value: &T) -> RecipeResult<Table> {
    match Value::try_from(value).map_err(RecipeError::Serialize)? {
        Value::Table(mut t) => {
            for (_, v) in t.iter_mut() {
                prettify_floats(v);
            }
            Ok(t)
        }
        _ => Err(RecipeError::NotATableValue),
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
///
/// ```
/// let mut base: toml::Table = "noise = { kind = \"fixed\", level = 0.1 }\nlr = 1".parse().unwrap();
/// let overlay: toml::Table = "noise = { kind = \"uniform\", max = 0.2 }".parse().unwrap();
/// vdd_recipe::merge(&mut base, &overlay);
/// assert_eq!(base["noise"].as_table().unwrap().len(), 2, "another kind replaces");
/// assert_eq!(base["lr"].as_integer(), Some(1));
/// ```
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
            return Err(RecipeError::InvalidKey(k.clone()));
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
        return Err(RecipeError::InvalidKeyPath(path.to_owned()));
    }
    let mut cur = root;
    for (i, p) in parts[..parts.len() - 1].iter().enumerate() {
        cur = match cur.get_mut(*p) {
            Some(Value::Table(t)) => t,
            Some(_) => return Err(RecipeError::NotATable(parts[..=i].join("."))),
            None => return Err(RecipeError::UnknownKey(parts[..=i].join("."))),
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
///
/// ```
/// use toml::Value;
/// assert_eq!(vdd_recipe::parse_value("1e-3"), Value::Float(1e-3));
/// assert_eq!(vdd_recipe::parse_value("heun"), Value::String("heun".into()));
/// ```
pub fn parse_value(s: &str) -> Value {
    match format!("v = {s}").parse::<Table>() {
        Ok(mut t) => t.remove("v").unwrap_or_else(|| Value::String(s.to_owned())),
        Err(_) => Value::String(s.to_owned()),
    }
}

/// Dotted paths of keys in `input` that `resolved` lacks (`prefix` is prepended; `""` at the
/// root). Tables inside arrays are compared element by element (`key[0].name`).
pub fn unknown_keys(input: &Table, resolved: &Table, prefix: &str) -> Vec<String> {
    let mut out = Vec::new();
    for (k, v) in input {
        let path = join(prefix, k);
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

/// Dotted paths of keys present in both trees whose values differ (tables are compared key by
/// key; any other value as a whole).
pub(crate) fn changed_keys(a: &Table, b: &Table, prefix: &str) -> Vec<String> {
    let mut out = Vec::new();
    for (k, v) in a {
        let path = join(prefix, k);
        match (v, b.get(k)) {
            (Value::Table(x), Some(Value::Table(y))) => out.extend(changed_keys(x, y, &path)),
            (x, Some(y)) if x != y => out.push(path),
            _ => {}
        }
    }
    out
}

fn join(prefix: &str, k: &str) -> String {
    if prefix.is_empty() { k.to_owned() } else { format!("{prefix}.{k}") }
}
