//! `cargo xtask experiment <recipe> [options]`: the command line of [`vdd_lab::experiment`],
//! which resolves a recipe and runs its task.
//!
//! ```text
//! cargo xtask experiment <recipe|path.toml> [--seed N | --seeds 0,1,2] [--methods a,b]
//!     [--set key.path=value]... [--quick] [--out DIR] [--fresh]
//! ```
//!
//! Results go to `--out DIR`, by default `results/<recipe>/<run>/` (see
//! [`vdd_lab::context::run_name`]); [`vdd_lab::experiment`] lists what a run directory holds.

use std::path::PathBuf;

use vdd_lab::recipe::{self, Overrides};

/// The command line of `experiment` (repeating an option other than `--set` keeps the last).
#[derive(Debug, Clone, Default, PartialEq, clap::Args)]
#[command(args_override_self = true)]
pub struct ExperimentArgs {
    /// Recipe name (a file in recipes/) or a path to a .toml recipe.
    pub recipe: String,
    /// Run seeds: N, a list 0,1,2 or a range 0..3 (default: the recipe's).
    #[arg(long, visible_alias = "seed", value_name = "SEEDS", value_parser = seed_list)]
    pub seeds: Option<SeedList>,
    /// Rows to run (a method from a teacher), comma-separated, or `all` (every row the task
    /// runs, listed below by task; the rows are recipes/defaults/runs.toml and the recipe's own
    /// [runs.<name>]).
    #[arg(long, value_name = "A,B")]
    pub methods: Option<String>,
    /// Override any recipe key; the value is parsed as TOML, a bare word is a string
    /// (repeatable, applied in order).
    #[arg(long = "set", value_name = "KEY.PATH=VALUE", value_parser = key_value)]
    pub sets: Vec<(String, String)>,
    /// Merge the recipe's smaller `[quick]` settings.
    #[arg(long)]
    pub quick: bool,
    /// Results directory (default: `results/<recipe>/<run>`).
    #[arg(long, value_name = "DIR")]
    pub out: Option<PathBuf>,
    /// Retrain cached teachers and students.
    #[arg(long)]
    pub fresh: bool,
    /// Continue a killed run in the same directory: load its finished trainings
    /// (`<run>/trained/`, kept by the same build) and continue the VDD distillations under way
    /// from their checkpoints (`<run>/checkpoints/`); the results equal an uninterrupted run's.
    #[arg(long)]
    pub resume: bool,
    /// A tuning run: the tuning seeds (100–104 unless --seeds says which) and their own
    /// demonstrations; results under results/tuning/, every method appended to the task's
    /// tuning log, docs/<task>-tuning-log.toml (tasks with rollouts; see vdd_lab::tuning).
    #[arg(long)]
    pub tuning: bool,
    /// toy-gmm: the teacher VDD distils (exact, ddpm, beso; shorthand for `--methods
    /// vdd-<teacher>`). avoiding: a teacher file of `cargo xtask import` (`imported.teacher`),
    /// rolled out and distilled (rows imported, vdd-imported; `teacher` and `vdd` name them).
    #[arg(long, value_name = "TEACHER")]
    pub teacher: Option<String>,
    /// Toys: VDD iterations of the distilled teacher.
    #[arg(long, value_name = "N")]
    pub iterations: Option<usize>,
    /// toy-conditional: number of experts.
    #[arg(long, value_name = "N")]
    pub experts: Option<usize>,
    /// toy-conditional: learning rate of the experts and the gating.
    #[arg(long, value_name = "X", value_parser = finite_float)]
    pub lr: Option<String>,
    /// toy-conditional: expert weighting.
    #[arg(long, value_parser = ["gating", "uniform"])]
    pub weighting: Option<String>,
}

/// Seeds given on the command line (a newtype, so that the parser takes one value).
#[derive(Debug, Clone, Default, PartialEq)]
pub struct SeedList(pub Vec<u64>);

fn seed_list(s: &str) -> Result<SeedList, String> {
    recipe::parse_seeds(s).map(SeedList).map_err(|e| e.to_string())
}

fn key_value(s: &str) -> Result<(String, String), String> {
    let (k, v) = s.split_once('=').ok_or_else(|| format!("expected key.path=value, got `{s}`"))?;
    Ok((k.trim().to_owned(), v.trim().to_owned()))
}

/// Keeps the text (it becomes a recipe value parsed as TOML) after checking it is a number.
fn finite_float(s: &str) -> Result<String, String> {
    match s.trim().parse::<f64>() {
        Ok(x) if x.is_finite() => Ok(s.trim().to_owned()),
        _ => Err(format!("expected a finite number, got `{s}`")),
    }
}

impl ExperimentArgs {
    /// The generic recipe overrides (`--quick`, `--seeds`, `--methods`, `--set`).
    pub fn overrides(&self) -> Overrides {
        Overrides {
            quick: self.quick,
            seeds: self.seeds.as_ref().map(|s| s.0.clone()),
            methods: self.methods.as_ref().map(|v| {
                v.split(',').map(|m| m.trim().to_owned()).filter(|m| !m.is_empty()).collect()
            }),
            sets: self.sets.clone(),
        }
    }

    /// The task-specific shorthands given, as `(option, value)`, translated by the task.
    pub fn shorthands(&self) -> Vec<(String, String)> {
        let given = [
            ("teacher", self.teacher.clone()),
            ("iterations", self.iterations.map(|n| n.to_string())),
            ("experts", self.experts.map(|n| n.to_string())),
            ("lr", self.lr.clone()),
            ("weighting", self.weighting.clone()),
            ("tuning", self.tuning.then(|| "true".to_owned())),
        ];
        given.into_iter().filter_map(|(k, v)| Some((k.to_owned(), v?))).collect()
    }
}

/// Runs the command; `command` is the command line, for `resolved.toml` and `run.json`.
pub fn run(parsed: &ExperimentArgs, command: &str) -> crate::XResult {
    let request = vdd_lab::experiment::Request {
        recipe: parsed.recipe.clone(),
        overrides: parsed.overrides(),
        shorthands: parsed.shorthands(),
        out: parsed.out.clone(),
        fresh: parsed.fresh,
        resume: parsed.resume,
        command: command.to_owned(),
        root: None,
    };
    Ok(vdd_lab::experiment::run(&request)?)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn parse(s: &str) -> Result<ExperimentArgs, clap::Error> {
        #[derive(clap::Parser)]
        struct Cmd {
            #[command(flatten)]
            args: ExperimentArgs,
        }
        use clap::Parser;
        Cmd::try_parse_from(std::iter::once("experiment").chain(s.split_whitespace()))
            .map(|c| c.args)
    }

    #[test]
    fn experiment_options_parse() {
        let a = parse(
            "avoiding --seeds 0,1,2 --methods vdd-beso,beso --set vdd.beso.iterations=10 --set a.b=c=d --quick --out /tmp/x --fresh --teacher ddpm",
        )
        .unwrap();
        assert_eq!(a.recipe, "avoiding");
        let o = a.overrides();
        assert_eq!(o.seeds, Some(vec![0, 1, 2]));
        assert_eq!(o.methods, Some(vec!["vdd-beso".to_owned(), "beso".to_owned()]));
        assert_eq!(
            o.sets,
            vec![("vdd.beso.iterations".into(), "10".into()), ("a.b".into(), "c=d".into())]
        );
        assert!(o.quick && a.fresh);
        assert_eq!(a.out, Some(PathBuf::from("/tmp/x")));
        assert_eq!(a.shorthands(), vec![("teacher".to_owned(), "ddpm".to_owned())]);
        let b = parse("toy-gmm --seed=3").unwrap();
        assert_eq!(b.overrides().seeds, Some(vec![3]));
        let c = parse("toy-gmm --seed 3 --seeds 0..2 --iterations 5 --lr 1e-2").unwrap();
        assert_eq!(c.overrides().seeds, Some(vec![0, 1]), "the last seed option wins");
        assert_eq!(
            c.shorthands(),
            vec![("iterations".to_owned(), "5".to_owned()), ("lr".to_owned(), "1e-2".to_owned())]
        );
        for bad in [
            "--quick",
            "x --bogus 1",
            "x --seed",
            "x --set novalue",
            "x --seeds 0..18446744073709551615",
            "x --seeds 3..3",
            "x --seeds -1",
            "x --weighting w",
            "x --lr inf",
            "x --iterations -5",
            "x y",
        ] {
            let e = parse(bad).unwrap_err();
            assert!(e.use_stderr(), "`{bad}` is an error, not help");
        }
    }
}
