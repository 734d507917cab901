//! The methods (algorithms) an experiment can run, one file each, and their list [`BUILTIN`]
//! (what [`crate::registry::Registry::builtin`] holds). The rows of the results tables, a
//! method run from a teacher, are data: `recipes/defaults/runs.toml` ([`crate::row`]).
//!
//! Adding a method: a new file here implementing [`crate::method::Method`], one line in
//! [`BUILTIN`], its settings in `recipes/defaults/<task>.toml` under the keys it declares, and
//! a row naming it in `recipes/defaults/runs.toml` (docs/recipes.md, "Adding a method", walks
//! through an example).
//!
//! [`em`] is public for its helpers: [`em::fit`] (fit a mixture to a job's normalised data,
//! timed, normalisers set), [`em::snapshot_policy`] and [`em::mixture_budget`], which methods
//! fitting a mixture to the demonstrations share, in this crate or outside it (see
//! `tests/lab_plugins.rs`).

use crate::method::Method;

mod cd;
mod ctm;
pub mod em;
mod imc;
mod teacher;
mod vdd;
mod vdd_oracle;

/// Every method.
pub static BUILTIN: &[&dyn Method] = &[
    &teacher::TeacherRow,
    &cd::Cd,
    &ctm::Ctm,
    &em::Em,
    &imc::Imc,
    &vdd::Vdd,
    &vdd_oracle::VddOracle,
];

#[cfg(test)]
mod tests {
    use super::*;
    use crate::registry::Registry;
    use crate::row::{Row, label};

    fn names(rows: &[&Row]) -> Vec<String> {
        rows.iter().map(|r| r.name.clone()).collect()
    }

    #[test]
    fn names_are_unique_lower_case_hyphenated_and_found() {
        let r = Registry::builtin();
        for (i, m) in BUILTIN.iter().enumerate() {
            let n = m.name();
            assert_eq!(r.method(n).unwrap().name(), n);
            assert!(BUILTIN[..i].iter().all(|o| o.name() != n), "{n} twice");
            assert!(r.rows().iter().any(|row| row.method.name() == n), "no row runs {n}");
        }
        for (i, row) in r.rows().iter().enumerate() {
            let n = &row.name;
            assert_eq!(&r.row(n).unwrap().name, n);
            assert!(n.chars().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-'));
            assert!(r.rows()[..i].iter().all(|o| &o.name != n), "{n} twice");
            let tasks = r.tasks().iter().filter(|t| r.supports(row, t.name())).count();
            assert!(tasks > 0, "{n} runs nowhere");
        }
        assert!(r.row("VDD-BESO").is_err());
        assert!(r.row("vdd").err().unwrap().to_string().contains("known: ddpm, beso"));
    }

    #[test]
    fn rows_name_their_method_and_teacher() {
        let r = Registry::builtin();
        let row = |n: &str| r.row(n).unwrap();
        assert_eq!(
            (row("vdd-beso").method.name(), row("vdd-beso").teacher_name()),
            ("vdd", Some("beso"))
        );
        assert_eq!(row("vdd-exact").teacher_name(), Some("exact"));
        assert_eq!(row("beso-1").method.name(), "teacher");
        assert_eq!(row("vdd-beso-d3il").teacher_key().unwrap(), "beso_d3il");
        assert_eq!(row("em").teacher_name(), None);
        // The paper's configurations are rows of the same methods with settings.
        assert_eq!(row("vdd-beso-learned").set_paths(), ["vdd.beso_gating"]);
        assert_eq!(row("imc-authors").keys(), ["baselines.imc_authors"]);
        assert_eq!(row("imc").keys(), ["baselines.imc"]);
        assert_eq!(row("vdd-beso-selected").keys()[0], "vdd.select_by");
        assert_eq!(row("vdd-beso-d3il").keys()[..2], ["baselines.beso_d3il", "vdd.beso_d3il"]);
        // Bad rows are refused with their name.
        let bad = |text: &str| {
            let runs: toml::Table = text.parse().unwrap();
            Registry::builtin().with_rows(&runs).unwrap_err().to_string()
        };
        let e = bad("[x]\nmethod = \"vdd\"");
        assert!(e.contains("row `x`") && e.contains("needs a `teacher`"), "{e}");
        let e = bad("[x]\nmethod = \"cd\"\nteacher = \"exact\"");
        assert!(e.contains("needs a learned teacher"), "{e}");
        let e = bad("[x]\nmethod = \"vdd\"\nteacher = \"nope\"");
        assert!(e.contains("unknown teacher `nope`"), "{e}");
        let e = bad("[x]\nmethod = \"teacher\"\nteacher = \"beso\"\nwith = { stepz = 1 }");
        assert!(e.contains("with.stepz") && e.contains("steps"), "{e}");
        let e = bad("[x]\nmethod = \"em\"\ntypo = 1");
        assert!(e.contains("typo"), "{e}");
        let e = bad("[vdd-beso]\nmethod = \"vdd\"\nteacher = \"beso\"");
        assert!(e.contains("registered already"), "{e}");
    }

    #[test]
    fn unavailable_methods_fail_clearly() {
        let r = Registry::builtin();
        let parse_methods = |names: &[String], task: &str| r.parse_rows(names, task);
        let e = parse_methods(&["beso".into(), "cd".into()], "toy-gmm").err().unwrap().to_string();
        assert!(e.contains("not available on task `toy-gmm`"), "{e}");
        let all = parse_methods(&["all".into()], "avoiding").unwrap();
        let expected = "ddpm beso ddpm-1 beso-1 cd ctm em imc vdd-ddpm vdd-beso beso-d3il \
                        beso-d3il-1 vdd-beso-learned vdd-beso-d3il imc-authors vdd-beso-oracle \
                        vdd-beso-selected";
        assert_eq!(
            names(&all).join(" "),
            expected,
            "the paper's ten methods in table order, then the paper's configurations"
        );
        assert_eq!(
            names(&parse_methods(&["all".into()], "toy-conditional").unwrap()),
            ["vdd-exact"]
        );
        assert_eq!(
            names(&parse_methods(&["all".into()], "toy-gmm").unwrap()),
            ["vdd-ddpm", "vdd-beso", "vdd-exact"]
        );
        assert!(parse_methods(&["all".into(), "beso".into()], "avoiding").is_err());
        assert!(parse_methods(&["vdd-exact".into()], "avoiding").is_err());
        assert!(parse_methods(&["beso".into(), "beso".into()], "avoiding").is_err());
        assert!(parse_methods(&[], "avoiding").is_err());
        let ok = parse_methods(&["beso".into(), "vdd-beso".into(), "em".into()], "avoiding");
        assert_eq!(names(&ok.unwrap()), ["beso", "vdd-beso", "em"]);
        assert_eq!(label("vdd-beso", Some("z4")), "vdd-beso-z4");
    }
}
