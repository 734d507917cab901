//! The methods an experiment can run, by their lower-case hyphenated names.
//!
//! Adding a method: add a variant, give it a name in [`Method::ALL`], say which teacher it
//! needs, and handle it in the task pipelines (`avoiding.rs`, `toy.rs`). A method a task does
//! not support is reported before any work starts ([`Method::check_available`]).

use vdd_diffusion::TeacherKind;

/// One method of the paper's comparison.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, PartialOrd, Ord)]
pub enum Method {
    /// The DDPM teacher with its default sampling steps.
    Ddpm,
    /// The BESO teacher with its default sampling steps.
    Beso,
    /// The DDPM teacher with one sampling step.
    Ddpm1,
    /// The BESO teacher with one sampling step.
    Beso1,
    /// Consistency distillation of the BESO teacher.
    Cd,
    /// Consistency trajectory model distilled from the BESO teacher.
    Ctm,
    /// EM for the mixture of experts (maximum likelihood on the demonstrations).
    Em,
    /// Information Maximizing Curriculum.
    Imc,
    /// VDD distilled from the DDPM teacher.
    VddDdpm,
    /// VDD distilled from the BESO teacher.
    VddBeso,
    /// VDD distilled from the exact Gaussian-mixture teacher (toy tasks).
    VddExact,
}

impl Method {
    /// Every method with its name, in the paper's table order.
    pub const ALL: [(Method, &'static str); 11] = [
        (Method::Ddpm, "ddpm"),
        (Method::Beso, "beso"),
        (Method::Ddpm1, "ddpm-1"),
        (Method::Beso1, "beso-1"),
        (Method::Cd, "cd"),
        (Method::Ctm, "ctm"),
        (Method::Em, "em"),
        (Method::Imc, "imc"),
        (Method::VddDdpm, "vdd-ddpm"),
        (Method::VddBeso, "vdd-beso"),
        (Method::VddExact, "vdd-exact"),
    ];

    /// The method's name (`vdd-beso`).
    pub fn name(self) -> &'static str {
        Self::ALL.iter().find(|(m, _)| *m == self).map(|(_, n)| *n).unwrap_or("?")
    }

    /// Parses a name.
    pub fn parse(s: &str) -> Result<Method, String> {
        Self::ALL.iter().find(|(_, n)| *n == s).map(|(m, _)| *m).ok_or_else(|| {
            let names: Vec<&str> = Self::ALL.iter().map(|(_, n)| *n).collect();
            format!("unknown method `{s}` (known: {})", names.join(", "))
        })
    }

    /// The learned diffusion teacher this method needs, if any.
    pub fn teacher(self) -> Option<TeacherKind> {
        match self {
            Method::Ddpm | Method::Ddpm1 | Method::VddDdpm => Some(TeacherKind::Ddpm),
            Method::Beso | Method::Beso1 | Method::VddBeso | Method::Cd | Method::Ctm => {
                Some(TeacherKind::Beso)
            }
            Method::Em | Method::Imc | Method::VddExact => None,
        }
    }

    /// Whether the method is a learned teacher itself (`ddpm`, `beso`, `ddpm-1`, `beso-1`).
    pub fn is_teacher(self) -> bool {
        matches!(self, Method::Ddpm | Method::Beso | Method::Ddpm1 | Method::Beso1)
    }

    /// Fails for methods `task` does not support.
    pub fn check_available(self, task: &str) -> Result<(), String> {
        let ok = match task {
            "avoiding" => self != Method::VddExact,
            "toy-gmm" => matches!(self, Method::VddExact | Method::VddBeso | Method::VddDdpm),
            "toy-conditional" => self == Method::VddExact,
            _ => false,
        };
        if ok {
            Ok(())
        } else {
            Err(format!("method `{}` is not available on task `{task}`", self.name()))
        }
    }
}

/// Parses and checks a recipe's method list: known names available on `task`, no duplicates.
/// `all` stands for every method the task supports, in the paper's table order.
pub fn parse_methods(names: &[String], task: &str) -> Result<Vec<Method>, String> {
    if names.is_empty() {
        return Err("the recipe lists no methods".into());
    }
    if names.len() == 1 && names[0] == "all" {
        return Ok(Method::ALL
            .iter()
            .map(|(m, _)| *m)
            .filter(|m| m.check_available(task).is_ok())
            .collect());
    }
    let mut out = Vec::with_capacity(names.len());
    for n in names {
        let m = Method::parse(n)?;
        m.check_available(task)?;
        if out.contains(&m) {
            return Err(format!("method `{n}` is listed twice"));
        }
        out.push(m);
    }
    Ok(out)
}

/// The label of a method in results: `vdd-beso`, or `vdd-beso-z4` under variant `z4`.
pub fn label(method: Method, variant: Option<&str>) -> String {
    match variant {
        Some(v) => format!("{}-{v}", method.name()),
        None => method.name().to_owned(),
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip_and_are_lower_case_hyphenated() {
        for (m, n) in Method::ALL {
            assert_eq!(Method::parse(n).unwrap(), m);
            assert_eq!(m.name(), n);
            assert!(n.chars().all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '-'));
        }
        assert!(Method::parse("VDD-BESO").is_err());
    }

    #[test]
    fn unavailable_methods_fail_clearly() {
        let e = parse_methods(&["beso".into(), "cd".into()], "toy-gmm").unwrap_err();
        assert!(e.contains("not available on task `toy-gmm`"), "{e}");
        let all: Vec<String> = Method::ALL[..10].iter().map(|(_, n)| n.to_string()).collect();
        assert_eq!(parse_methods(&all, "avoiding").unwrap().len(), 10, "the paper's ten methods");
        assert_eq!(
            parse_methods(&["all".into()], "avoiding").unwrap(),
            parse_methods(&all, "avoiding").unwrap()
        );
        assert_eq!(
            parse_methods(&["all".into()], "toy-conditional").unwrap(),
            vec![Method::VddExact]
        );
        assert!(parse_methods(&["all".into(), "beso".into()], "avoiding").is_err());
        assert!(parse_methods(&["vdd-exact".into()], "avoiding").is_err());
        assert!(parse_methods(&["beso".into(), "beso".into()], "avoiding").is_err());
        assert!(parse_methods(&[], "avoiding").is_err());
        let ok = parse_methods(&["beso".into(), "vdd-beso".into(), "em".into()], "avoiding");
        assert_eq!(ok.unwrap(), vec![Method::Beso, Method::VddBeso, Method::Em]);
        assert_eq!(label(Method::VddBeso, Some("z4")), "vdd-beso-z4");
    }
}
