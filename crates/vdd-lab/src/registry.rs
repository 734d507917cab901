//! What a run can name: the methods (algorithms), the teacher sources, the rows of the
//! results tables built from them ([`crate::row`]) and the tasks. `Registry::builtin` (in the
//! crate root) holds the workspace's own (`methods::BUILTIN`, `teachers::BUILTIN`, the rows of
//! `recipes/defaults/runs.toml`, `tasks::BUILTIN`); a program adds its own with
//! [`Registry::with_method`], [`Registry::with_teacher`], [`Registry::with_rows`] and
//! [`Registry::with_task`] and runs recipes through them with
//! [`crate::experiment::run_with`]. The order of the rows is the table order and what `all`
//! expands to.

use crate::method::Method;
use crate::report::Column;
use crate::row::{self, Row};
use crate::task::Task;
use crate::teachers::TeacherSource;

/// The methods, teacher sources, rows and tasks of a run.
#[derive(Clone)]
pub struct Registry {
    methods: Vec<&'static dyn Method>,
    teachers: Vec<&'static dyn TeacherSource>,
    rows: Vec<Row>,
    tasks: Vec<&'static dyn Task>,
}

impl std::fmt::Debug for Registry {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let methods: Vec<_> = self.methods.iter().map(|m| m.name()).collect();
        let teachers: Vec<_> = self.teachers.iter().map(|t| t.name()).collect();
        let rows: Vec<_> = self.rows.iter().map(|r| r.name.as_str()).collect();
        let tasks: Vec<_> = self.tasks.iter().map(|t| t.name()).collect();
        f.debug_struct("Registry")
            .field("methods", &methods)
            .field("teachers", &teachers)
            .field("rows", &rows)
            .field("tasks", &tasks)
            .finish()
    }
}

impl Registry {
    /// A registry of `methods`, teacher sources and `tasks`, with no rows yet
    /// ([`Registry::with_rows`]).
    pub fn new(
        methods: Vec<&'static dyn Method>,
        teachers: Vec<&'static dyn TeacherSource>,
        tasks: Vec<&'static dyn Task>,
    ) -> Self {
        Self { methods, teachers, rows: Vec::new(), tasks }
    }
}

/// Whether `name` is lower-case ASCII letters, digits and hyphens, starting with a letter.
fn valid_name(name: &str) -> bool {
    name.starts_with(|c: char| c.is_ascii_lowercase())
        && name.chars().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-')
}

/// `Err` unless `name` is a valid, new name of a `what`.
fn check_new(what: &str, name: &str, taken: bool) -> crate::Result {
    if !valid_name(name) {
        return Err(format!("{what} name `{name}` is not lower-case-hyphenated").into());
    }
    if taken {
        return Err(format!("a {what} `{name}` is registered already").into());
    }
    Ok(())
}

/// The one of `items` called `name`, or an error listing the known ones.
fn find<T: Copy>(
    what: &str,
    items: &[T],
    name: &str,
    name_of: impl Fn(&T) -> &str,
) -> crate::Result<T> {
    items.iter().find(|i| name_of(i) == name).copied().ok_or_else(|| {
        let names: Vec<&str> = items.iter().map(&name_of).collect();
        format!("unknown {what} `{name}` (known: {})", names.join(", ")).into()
    })
}

impl Registry {
    /// Adds `method` (an algorithm rows can name); an error for a name taken or not lower-case
    /// hyphenated.
    pub fn with_method(mut self, method: &'static dyn Method) -> crate::Result<Self> {
        let name = method.name();
        check_new("method", name, self.methods.iter().any(|m| m.name() == name))?;
        self.methods.push(method);
        Ok(self)
    }

    /// Adds a teacher source rows can name; an error for a name taken or not lower-case
    /// hyphenated.
    pub fn with_teacher(mut self, teacher: &'static dyn TeacherSource) -> crate::Result<Self> {
        let name = teacher.name();
        check_new("teacher source", name, self.teachers.iter().any(|t| t.name() == name))?;
        self.teachers.push(teacher);
        Ok(self)
    }

    /// Adds the rows of `runs` (`[runs.<name>]` tables, [`crate::row::RowSpec`]) after the
    /// others, in order; an error names a malformed row, a name taken, an unknown method or
    /// teacher, or a teacher the method does not take.
    pub fn with_rows(mut self, runs: &toml::Table) -> crate::Result<Self> {
        for (name, spec) in row::parse_specs(runs)? {
            check_new("row", &name, self.rows.iter().any(|r| r.name == name))?;
            let r = Row::new(&name, spec, |m| self.method(m), |t| self.teacher(t))?;
            self.rows.push(r);
        }
        Ok(self)
    }

    /// Adds `task`; an error for a name taken or not lower-case hyphenated.
    pub fn with_task(mut self, task: &'static dyn Task) -> crate::Result<Self> {
        let name = task.name();
        check_new("task", name, self.tasks.iter().any(|t| t.name() == name))?;
        self.tasks.push(task);
        Ok(self)
    }

    /// Every method.
    pub fn methods(&self) -> &[&'static dyn Method] {
        &self.methods
    }

    /// Every teacher source.
    pub fn teachers(&self) -> &[&'static dyn TeacherSource] {
        &self.teachers
    }

    /// Every row, in table order.
    pub fn rows(&self) -> &[Row] {
        &self.rows
    }

    /// Every task.
    pub fn tasks(&self) -> &[&'static dyn Task] {
        &self.tasks
    }

    /// The method called `name`, or an error listing the known ones.
    pub fn method(&self, name: &str) -> crate::Result<&'static dyn Method> {
        find("method", &self.methods, name, |m| m.name())
    }

    /// The teacher source called `name`, or an error listing the known ones.
    pub fn teacher(&self, name: &str) -> crate::Result<&'static dyn TeacherSource> {
        find("teacher", &self.teachers, name, |t| t.name())
    }

    /// The row called `name`, or an error listing the known ones.
    pub fn row(&self, name: &str) -> crate::Result<&Row> {
        self.rows.iter().find(|r| r.name == name).ok_or_else(|| {
            let names: Vec<&str> = self.rows.iter().map(|r| r.name.as_str()).collect();
            format!("unknown method `{name}` (known: {})", names.join(", ")).into()
        })
    }

    /// The task called `name`, or an error listing the known ones.
    pub fn task(&self, name: &str) -> crate::Result<&'static dyn Task> {
        self.tasks.iter().copied().find(|t| t.name() == name).ok_or_else(|| {
            let names: Vec<&str> = self.tasks.iter().map(|t| t.name()).collect();
            format!("unknown task `{name}` ({})", names.join(", ")).into()
        })
    }

    /// The rows that run on `task`, in table order.
    pub fn rows_of(&self, task: &str) -> Vec<&Row> {
        self.rows.iter().filter(|r| self.supports(r, task)).collect()
    }

    /// Whether `row` runs on `task`: the task is registered, offers everything the row needs
    /// ([`Task::offers`], [`Row::needs`]) and is not excluded by the row's `only_on`.
    pub fn supports(&self, row: &Row, task: &str) -> bool {
        self.why_not(row, task).is_none()
    }

    /// Why `row` does not run on `task`, or `None` when it does: the task is unknown, the
    /// row's `only_on` leaves it out, or it lacks what the row needs (named as in a row's
    /// `needs`).
    fn why_not(&self, row: &Row, task: &str) -> Option<String> {
        let n = &row.name;
        let Ok(t) = self.task(task) else { return Some(format!("method `{n}`: no task `{task}`")) };
        if !(row.only_on.is_empty() || row.only_on.iter().any(|o| o == task)) {
            let only = row.only_on.join(", ");
            return Some(format!("method `{n}` runs only on {only}, not on `{task}`"));
        }
        let mut missing: Vec<String> = Vec::new();
        for c in row.needs().into_iter().filter(|c| !t.offers().contains(c)) {
            let name = serde_json::to_value(c).map_or_else(|_| format!("{c:?}"), |v| v.to_string());
            if !missing.contains(&name) {
                missing.push(name);
            }
        }
        (!missing.is_empty()).then(|| {
            format!(
                "method `{n}` is not available on task `{task}`: it needs {}, which the task \
                 does not offer",
                missing.join(", ")
            )
        })
    }

    /// Parses and checks a recipe's row list (`methods`): known names available on `task`, no
    /// duplicates. `all` stands for every row the task supports, in table order, but those of
    /// a teacher file ([`crate::teachers::TeacherSource::loads_file`]).
    pub fn parse_rows(&self, names: &[String], task: &str) -> crate::Result<Vec<&Row>> {
        if names.is_empty() {
            return Err("the recipe lists no methods".into());
        }
        if names.len() == 1 && names[0] == "all" {
            // Rows of a teacher file run only when named: `all` needs no file.
            let from_file = |r: &&Row| r.teacher.is_some_and(|t| t.loads_file());
            return Ok(self.rows_of(task).into_iter().filter(|r| !from_file(r)).collect());
        }
        let mut out: Vec<&Row> = Vec::with_capacity(names.len());
        for n in names {
            let r = self.row(n)?;
            if let Some(why) = self.why_not(r, task) {
                return Err(why.into());
            }
            if out.iter().any(|o| o.name == r.name) {
                return Err(format!("method `{n}` is listed twice").into());
            }
            out.push(r);
        }
        Ok(out)
    }

    /// The columns of `task`'s tables ([`Task::columns`]; none for an unknown task), for
    /// [`vdd_report::table::table_of_runs`].
    pub fn columns_of(&self, task: &str) -> Vec<Column> {
        self.task(task).map(|t| t.columns()).unwrap_or_default()
    }
}
