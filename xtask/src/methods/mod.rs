//! The methods an experiment can run, one file each, and their [`REGISTRY`]: the source of the
//! names `--methods` accepts, of `all` and of the table order.
//!
//! Adding a method: a new file here implementing [`crate::method::Method`], one line in
//! [`REGISTRY`], and its settings in `recipes/defaults/<task>.toml` under the keys it declares
//! (docs/recipes.md, "Adding a method", walks through an example).

use crate::method::Method;

mod beso_d3il;
mod cd;
mod ctm;
mod em;
mod imc;
mod teacher;
mod vdd;
mod vdd_learned;

/// Every method, in the paper's table order, then the paper's own configurations beside ours
/// (D3IL's BESO teacher and its rows, VDD-BESO with a learned gating, the authors' IMC).
pub static REGISTRY: &[&dyn Method] = &[
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
];

/// The method called `name`.
pub fn find(name: &str) -> Result<&'static dyn Method, String> {
    REGISTRY.iter().copied().find(|m| m.name() == name).ok_or_else(|| {
        let names: Vec<&str> = REGISTRY.iter().map(|m| m.name()).collect();
        format!("unknown method `{name}` (known: {})", names.join(", "))
    })
}

/// Whether `method` runs on `task`.
pub fn supports(method: &dyn Method, task: &str) -> bool {
    method.info().tasks.contains(&task)
}

/// Parses and checks a recipe's method list: known names available on `task`, no duplicates.
/// `all` stands for every method the task supports, in the paper's table order.
pub fn parse_methods(names: &[String], task: &str) -> Result<Vec<&'static dyn Method>, String> {
    if names.is_empty() {
        return Err("the recipe lists no methods".into());
    }
    if names.len() == 1 && names[0] == "all" {
        return Ok(REGISTRY.iter().copied().filter(|m| supports(*m, task)).collect());
    }
    let mut out: Vec<&'static dyn Method> = Vec::with_capacity(names.len());
    for n in names {
        let m = find(n)?;
        if !supports(m, task) {
            return Err(format!("method `{n}` is not available on task `{task}`"));
        }
        if out.iter().any(|o| o.name() == m.name()) {
            return Err(format!("method `{n}` is listed twice"));
        }
        out.push(m);
    }
    Ok(out)
}

/// The label of a method in results: `vdd-beso`, or `vdd-beso-z4` under variant `z4`.
pub fn label(method: &dyn Method, variant: Option<&str>) -> String {
    match variant {
        Some(v) => format!("{}-{v}", method.name()),
        None => method.name().to_owned(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn names(ms: &[&dyn Method]) -> Vec<&'static str> {
        ms.iter().map(|m| m.name()).collect()
    }

    #[test]
    fn names_are_unique_lower_case_hyphenated_and_found() {
        for (i, m) in REGISTRY.iter().enumerate() {
            let n = m.name();
            assert_eq!(find(n).unwrap().name(), n);
            assert!(n.chars().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-'));
            assert!(REGISTRY[..i].iter().all(|o| o.name() != n), "{n} twice");
            assert!(!m.info().tasks.is_empty(), "{n} runs nowhere");
        }
        assert!(find("VDD-BESO").is_err());
        assert!(find("vdd").err().unwrap().contains("known: ddpm, beso"));
    }

    #[test]
    fn unavailable_methods_fail_clearly() {
        let e = parse_methods(&["beso".into(), "cd".into()], "toy-gmm").err().unwrap();
        assert!(e.contains("not available on task `toy-gmm`"), "{e}");
        let all = parse_methods(&["all".into()], "avoiding").unwrap();
        let expected = "ddpm beso ddpm-1 beso-1 cd ctm em imc vdd-ddpm vdd-beso beso-d3il \
                        beso-d3il-1 vdd-beso-learned vdd-beso-d3il imc-authors";
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
