//! Rows of the results tables, named in data: a row runs a method (an algorithm,
//! [`crate::method::Method`]) from a teacher ([`crate::teachers::TeacherSource`]) with its own
//! settings. The built-in rows are `recipes/defaults/runs.toml` ([`BUILTIN_ROWS`], the paper's
//! table in order); a recipe adds its own as `[runs.<name>]` tables ([`RowSpec`]), and
//! `--methods` names rows.
//!
//! ```
//! use vdd_lab::Registry;
//!
//! // A recipe's `[runs.vdd-beso-e4]`: VDD from the BESO teacher with four experts.
//! let runs: toml::Table = r#"
//!     [vdd-beso-e4]
//!     method = "vdd"
//!     teacher = "beso"
//!     set = { "vdd.beso_experts" = 4 }
//! "#.parse()?;
//! let registry = Registry::builtin().with_rows(&runs)?;
//! let row = registry.row("vdd-beso-e4")?;
//! assert_eq!((row.method.name(), row.teacher_name()), ("vdd", Some("beso")));
//! // A row of a method that takes no teacher, given one, is refused with its name.
//! let bad: toml::Table = "[em-beso]\nmethod = \"em\"\nteacher = \"beso\"".parse()?;
//! let err = Registry::builtin().with_rows(&bad).unwrap_err().to_string();
//! assert!(err.contains("em-beso") && err.contains("takes no teacher"), "{err}");
//! # Ok::<(), Box<dyn std::error::Error>>(())
//! ```

use serde::de::DeserializeOwned;
use serde::{Deserialize, Serialize};
use toml::{Table, Value};

use crate::method::{Method, TeacherUse};
use crate::task::Capability;
use crate::teachers::TeacherSource;

/// The built-in rows, `recipes/defaults/runs.toml` (in table order).
pub const BUILTIN_ROWS: &str = include_str!("../../../recipes/defaults/runs.toml");

/// A row as written, the value of `[runs.<name>]`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct RowSpec {
    /// The method (an algorithm's name: `vdd`, `cd`, `teacher`, ...).
    pub method: String,
    /// The teacher source (`beso`, `ddpm`, `beso-d3il`, `exact`), for methods that take one.
    #[serde(default)]
    pub teacher: Option<String>,
    /// The method's own row settings ([`crate::method::Info::row_keys`] lists the keys).
    #[serde(default)]
    pub with: Table,
    /// Recipe keys set for this row alone (dotted paths in the methods' tables).
    #[serde(default)]
    pub set: Table,
    /// What the row needs of a task beyond its method's and its teacher's.
    #[serde(default)]
    pub needs: Vec<Capability>,
    /// When not empty, the only tasks it runs on.
    #[serde(default)]
    pub only_on: Vec<String>,
}

/// A row resolved against the registry's methods and teacher sources.
#[derive(Clone)]
pub struct Row {
    /// The lower-case hyphenated name (`vdd-beso`): `--methods`, tables, `metrics.json`.
    pub name: String,
    /// The method.
    pub method: &'static dyn Method,
    /// The teacher source.
    pub teacher: Option<&'static dyn TeacherSource>,
    /// The method's row settings ([`RowSpec::with`]).
    pub with: Table,
    /// The recipe keys set for this row ([`RowSpec::set`], dotted keys expanded).
    pub set: Table,
    /// [`RowSpec::needs`].
    pub needs: Vec<Capability>,
    /// [`RowSpec::only_on`].
    pub only_on: Vec<String>,
}

impl std::fmt::Debug for Row {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.debug_struct("Row")
            .field("name", &self.name)
            .field("method", &self.method.name())
            .field("teacher", &self.teacher_name())
            .field("with", &self.with)
            .field("set", &self.set)
            .finish()
    }
}

impl Row {
    /// Resolves `spec` (named `name`) with the methods and teacher sources given: the method
    /// and teacher exist, the method takes the teacher, and `with` holds only the method's row
    /// keys. Errors name the row.
    pub fn new(
        name: &str,
        spec: RowSpec,
        method: impl Fn(&str) -> crate::Result<&'static dyn Method>,
        teacher: impl Fn(&str) -> crate::Result<&'static dyn TeacherSource>,
    ) -> crate::Result<Row> {
        let fail = |e: String| -> crate::LabError { format!("row `{name}`: {e}").into() };
        let m = method(&spec.method).map_err(|e| fail(e.to_string()))?;
        let t =
            spec.teacher.as_deref().map(&teacher).transpose().map_err(|e| fail(e.to_string()))?;
        match (m.info().teacher, t) {
            (TeacherUse::Never, Some(t)) => {
                return Err(fail(format!(
                    "method `{}` takes no teacher (got `{}`)",
                    m.name(),
                    t.name()
                )));
            }
            (TeacherUse::Any | TeacherUse::Learned, None) => {
                return Err(fail(format!("method `{}` needs a `teacher`", m.name())));
            }
            (TeacherUse::Learned, Some(t)) if t.kind().is_none() => {
                return Err(fail(format!(
                    "method `{}` needs a learned teacher; `{}` is not one",
                    m.name(),
                    t.name()
                )));
            }
            _ => {}
        }
        if let Some(k) = spec.with.keys().find(|k| !m.info().row_keys.contains(&k.as_str())) {
            let known = m.info().row_keys.join(", ");
            return Err(fail(format!(
                "method `{}` has no row setting `with.{k}` (it has: {})",
                m.name(),
                if known.is_empty() { "none" } else { &known }
            )));
        }
        let set = crate::recipe::expand_dotted(&spec.set).map_err(|e| fail(e.to_string()))?;
        Ok(Row {
            name: name.to_owned(),
            method: m,
            teacher: t,
            with: spec.with,
            set,
            needs: spec.needs,
            only_on: spec.only_on,
        })
    }

    /// The teacher source's name.
    pub fn teacher_name(&self) -> Option<&'static str> {
        self.teacher.map(|t| t.name())
    }

    /// The teacher's name as a recipe key segment (`beso-d3il` → `beso_d3il`), for methods
    /// whose settings are per teacher (`vdd.<teacher>`); an error for a row without one.
    pub fn teacher_key(&self) -> crate::Result<String> {
        let t = self.teacher.ok_or_else(|| format!("row `{}` has no teacher", self.name))?;
        Ok(t.name().replace('-', "_"))
    }

    /// The method's row settings, typed (`T` should deny unknown fields).
    pub fn settings<T: DeserializeOwned>(&self) -> crate::Result<T> {
        Value::Table(self.with.clone())
            .try_into()
            .map_err(|e| format!("row `{}`: `with`: {e}", self.name).into())
    }

    /// The recipe keys the row reads: its teacher source's, then its method's.
    pub fn keys(&self) -> Vec<String> {
        let mut keys: Vec<String> = self
            .teacher
            .map(|t| t.keys().iter().map(|k| (*k).to_owned()).collect())
            .unwrap_or_default();
        keys.extend(self.method.keys(self));
        keys
    }

    /// Everything the row needs of a task: its method's, its teacher's and its own.
    pub fn needs(&self) -> Vec<Capability> {
        let mut needs = self.method.info().needs.to_vec();
        needs.extend(self.teacher.iter().flat_map(|t| t.needs().iter().copied()));
        needs.extend(self.needs.iter().copied());
        needs
    }

    /// The dotted paths of [`Row::set`].
    pub fn set_paths(&self) -> Vec<String> {
        fn walk(prefix: &str, t: &Table, out: &mut Vec<String>) {
            for (k, v) in t {
                let path = if prefix.is_empty() { k.clone() } else { format!("{prefix}.{k}") };
                match v {
                    Value::Table(inner) if !inner.is_empty() => walk(&path, inner, out),
                    _ => out.push(path),
                }
            }
        }
        let mut out = Vec::new();
        walk("", &self.set, &mut out);
        out
    }

    /// `tree` with the row's [`Row::set`] merged in.
    pub fn apply_set(&self, tree: &Table) -> Table {
        let mut tree = tree.clone();
        crate::recipe::merge(&mut tree, &self.set);
        tree
    }
}

/// The `runs` table of [`BUILTIN_ROWS`].
pub fn builtin_runs() -> crate::Result<Table> {
    let file: Table = BUILTIN_ROWS.parse().map_err(|e| format!("{e}"))?;
    match file.get("runs") {
        Some(Value::Table(t)) if file.len() == 1 => Ok(t.clone()),
        _ => Err("the file holds nothing but a `runs` table".into()),
    }
}

/// The `[runs.*]` tables of `runs` as specs, in order; an error names a malformed row.
pub fn parse_specs(runs: &Table) -> crate::Result<Vec<(String, RowSpec)>> {
    runs.iter()
        .map(|(name, v)| {
            let spec: RowSpec =
                v.clone().try_into().map_err(|e| format!("row `{name}` (`[runs.{name}]`): {e}"))?;
            Ok((name.clone(), spec))
        })
        .collect()
}

/// The label of a row in results: `vdd-beso`, or `vdd-beso-z4` under variant `z4`.
pub fn label(row: &str, variant: Option<&str>) -> String {
    match variant {
        Some(v) => format!("{row}-{v}"),
        None => row.to_owned(),
    }
}
