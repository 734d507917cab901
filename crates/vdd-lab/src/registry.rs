//! The methods and tasks a run can name: `Registry::builtin` (in the crate root) holds the
//! workspace's own (`methods::BUILTIN`, `tasks::BUILTIN`); a program adds its own with
//! [`Registry::with_method`] and [`Registry::with_task`] and runs recipes through them with
//! [`crate::experiment::run_with`]. The order of the methods is the table order and what
//! `all` expands to.

use crate::method::Method;
use crate::report::Column;
use crate::task::Task;

/// The methods and tasks of a run.
#[derive(Clone)]
pub struct Registry {
    methods: Vec<&'static dyn Method>,
    tasks: Vec<&'static dyn Task>,
}

impl std::fmt::Debug for Registry {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        let methods: Vec<_> = self.methods.iter().map(|m| m.name()).collect();
        let tasks: Vec<_> = self.tasks.iter().map(|t| t.name()).collect();
        f.debug_struct("Registry").field("methods", &methods).field("tasks", &tasks).finish()
    }
}

impl Registry {
    /// A registry of `methods` (in table order) and `tasks`.
    pub fn new(methods: Vec<&'static dyn Method>, tasks: Vec<&'static dyn Task>) -> Self {
        Self { methods, tasks }
    }
}

/// Whether `name` is lower-case ASCII letters, digits and hyphens, starting with a letter.
fn valid_name(name: &str) -> bool {
    name.starts_with(|c: char| c.is_ascii_lowercase())
        && name.chars().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-')
}

impl Registry {
    /// Adds `method` after the others (its place in tables); an error for a name taken or not
    /// lower-case hyphenated.
    pub fn with_method(mut self, method: &'static dyn Method) -> crate::Result<Self> {
        let name = method.name();
        if !valid_name(name) {
            return Err(format!("method name `{name}` is not lower-case-hyphenated").into());
        }
        if self.methods.iter().any(|m| m.name() == name) {
            return Err(format!("a method `{name}` is registered already").into());
        }
        self.methods.push(method);
        Ok(self)
    }

    /// Adds `task`; an error for a name taken or not lower-case hyphenated.
    pub fn with_task(mut self, task: &'static dyn Task) -> crate::Result<Self> {
        let name = task.name();
        if !valid_name(name) {
            return Err(format!("task name `{name}` is not lower-case-hyphenated").into());
        }
        if self.tasks.iter().any(|t| t.name() == name) {
            return Err(format!("a task `{name}` is registered already").into());
        }
        self.tasks.push(task);
        Ok(self)
    }

    /// Every method, in table order.
    pub fn methods(&self) -> &[&'static dyn Method] {
        &self.methods
    }

    /// Every task.
    pub fn tasks(&self) -> &[&'static dyn Task] {
        &self.tasks
    }

    /// The method called `name`, or an error listing the known ones.
    pub fn method(&self, name: &str) -> crate::Result<&'static dyn Method> {
        self.methods.iter().copied().find(|m| m.name() == name).ok_or_else(|| {
            let names: Vec<&str> = self.methods.iter().map(|m| m.name()).collect();
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

    /// The methods that run on `task`, in table order.
    pub fn methods_of(&self, task: &str) -> Vec<&'static dyn Method> {
        self.methods.iter().copied().filter(|m| self.supports(*m, task)).collect()
    }

    /// Whether `method` runs on `task`: the task is registered, offers everything the method
    /// needs ([`Task::offers`], [`crate::method::Info::needs`]) and is not excluded by the
    /// method's [`crate::method::Info::only_on`].
    pub fn supports(&self, method: &dyn Method, task: &str) -> bool {
        let info = method.info();
        let Ok(t) = self.task(task) else { return false };
        (info.only_on.is_empty() || info.only_on.contains(&task))
            && info.needs.iter().all(|n| t.offers().contains(n))
    }

    /// Parses and checks a recipe's method list: known names available on `task`, no
    /// duplicates. `all` stands for every method the task supports, in table order.
    pub fn parse_methods(
        &self,
        names: &[String],
        task: &str,
    ) -> crate::Result<Vec<&'static dyn Method>> {
        if names.is_empty() {
            return Err("the recipe lists no methods".into());
        }
        if names.len() == 1 && names[0] == "all" {
            return Ok(self.methods_of(task));
        }
        let mut out: Vec<&'static dyn Method> = Vec::with_capacity(names.len());
        for n in names {
            let m = self.method(n)?;
            if !self.supports(m, task) {
                return Err(format!("method `{n}` is not available on task `{task}`").into());
            }
            if out.iter().any(|o| o.name() == m.name()) {
                return Err(format!("method `{n}` is listed twice").into());
            }
            out.push(m);
        }
        Ok(out)
    }

    /// The columns of `task`'s tables ([`Task::columns`]; none for an unknown task), for
    /// [`vdd_report::table::table_of_runs`].
    pub fn columns_of(&self, task: &str) -> Vec<Column> {
        self.task(task).map(|t| t.columns()).unwrap_or_default()
    }
}

/// The label of a method in results: `vdd-beso`, or `vdd-beso-z4` under variant `z4`.
pub fn label(method: &dyn Method, variant: Option<&str>) -> String {
    match variant {
        Some(v) => format!("{}-{v}", method.name()),
        None => method.name().to_owned(),
    }
}
