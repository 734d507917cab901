//! The methods an experiment can run, one file each, and their list [`BUILTIN`] (what
//! [`crate::registry::Registry::builtin`] holds): the source of the names `--methods` accepts,
//! of `all` and of the table order.
//!
//! Adding a method: a new file here implementing [`crate::method::Method`], one line in
//! [`BUILTIN`], and its settings in `recipes/defaults/<task>.toml` under the keys it declares
//! (docs/recipes.md, "Adding a method", walks through an example).
//!
//! [`em`] is public for its helpers: [`em::fit`] (fit a mixture to a job's normalised data,
//! timed, normalisers set), [`em::snapshot_policy`] and [`em::mixture_budget`], which methods
//! fitting a mixture to the demonstrations share, in this crate or outside it (see
//! `tests/lab_plugins.rs`).

use crate::method::Method;

mod beso_d3il;
mod cd;
mod ctm;
pub mod em;
mod imc;
mod teacher;
mod vdd;
mod vdd_learned;
mod vdd_oracle;
mod vdd_selected;

/// Every method, in the paper's table order, then the paper's own configurations beside ours
/// (D3IL's BESO teacher and its rows, VDD-BESO with a learned gating, the authors' IMC).
pub static BUILTIN: &[&dyn Method] = &[
    &teacher::DDPM,
    &teacher::BESO,
    &teacher::DDPM_1,
    &teacher::BESO_1,
    &cd::Cd,
    &ctm::Ctm,
    &em::Em,
    &imc::IMC,
    &vdd::VDD_DDPM,
    &vdd::VDD_BESO,
    &vdd::VDD_EXACT,
    &beso_d3il::BESO_D3IL,
    &beso_d3il::BESO_D3IL_1,
    &vdd_learned::VddBesoLearned,
    &beso_d3il::VDD_BESO_D3IL,
    &imc::IMC_AUTHORS,
    &vdd_oracle::VddBesoOracle,
    &vdd_selected::VddBesoSelected,
];

#[cfg(test)]
mod tests {
    use super::*;
    use crate::registry::{Registry, label};

    fn names(ms: &[&dyn Method]) -> Vec<&'static str> {
        ms.iter().map(|m| m.name()).collect()
    }

    #[test]
    fn names_are_unique_lower_case_hyphenated_and_found() {
        let r = Registry::builtin();
        for (i, m) in BUILTIN.iter().enumerate() {
            let n = m.name();
            assert_eq!(r.method(n).unwrap().name(), n);
            assert!(n.chars().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-'));
            assert!(BUILTIN[..i].iter().all(|o| o.name() != n), "{n} twice");
            let tasks = r.tasks().iter().filter(|t| r.supports(*m, t.name())).count();
            assert!(tasks > 0, "{n} runs nowhere");
        }
        assert!(r.method("VDD-BESO").is_err());
        assert!(r.method("vdd").err().unwrap().to_string().contains("known: ddpm, beso"));
    }

    #[test]
    fn unavailable_methods_fail_clearly() {
        let r = Registry::builtin();
        let parse_methods = |names: &[String], task: &str| r.parse_methods(names, task);
        let find = |name: &str| r.method(name);
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
        assert_eq!(label(find("vdd-beso").unwrap(), Some("z4")), "vdd-beso-z4");
    }
}
