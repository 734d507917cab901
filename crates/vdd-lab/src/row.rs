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

use serde::{Deserialize, Serialize};
use toml::{Table, Value};

use crate::capability::Capability;
pub use crate::method::Row;
use crate::method::{Method, TeacherUse};
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
            (TeacherUse::Any | TeacherUse::Learned | TeacherUse::Acting, None) => {
                return Err(fail(format!("method `{}` needs a `teacher`", m.name())));
            }
            (TeacherUse::Learned, Some(t)) if t.kind().is_none() => {
                return Err(fail(format!(
                    "method `{}` needs a learned teacher; `{}` is not one",
                    m.name(),
                    t.name()
                )));
            }
            (TeacherUse::Acting, Some(t)) if t.kind().is_none() && !t.loads_file() => {
                return Err(fail(format!(
                    "method `{}` needs a teacher that acts (learned or from a file); `{}` is \
                     not one",
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
