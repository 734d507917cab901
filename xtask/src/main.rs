//! `cargo xtask`: experiment recipes, result tables, benchmarks and demos.
//!
//! ```text
//! cargo xtask experiment <recipe> [--seed N | --seeds 0,1,2] [--methods a,b] [--set k.path=v]...
//!                                 [--quick] [--out DIR] [--fresh]
//! cargo xtask table RUN_DIR... [--out FILE]
//! cargo xtask compare RUN_DIR_A RUN_DIR_B
//! cargo xtask bench nn|teachers
//! cargo xtask demos avoiding --n 200 --seed 0 --out DIR
//! ```
//!
//! Recipes are the TOML files in `recipes/` (see [`recipe`] for how they resolve and
//! [`experiment`] for the run directory layout).

mod avoiding;
mod bench_nn;
mod bench_teachers;
mod demos;
mod experiment;
mod methods;
mod plots;
mod policy;
mod recipe;
mod report;
mod student_cache;
mod teachers;
mod toy;

/// Errors of any xtask command, printed at the top level.
pub type XResult<T = ()> = Result<T, Box<dyn std::error::Error>>;

const USAGE: &str = "usage:
  cargo xtask experiment <recipe> [options]   run a recipe from recipes/ (or a .toml path)
      --seed N | --seeds 0,1,2     seeds (default: the recipe's)
      --methods a,b|all            methods (ddpm, beso, ddpm-1, beso-1, cd, ctm, em, imc,
                                   vdd-ddpm, vdd-beso; toys: vdd-exact)
      --set key.path=value         override any recipe key (repeatable; value parsed as TOML)
      --quick                      the recipe's smaller [quick] settings
      --out DIR                    results directory (default results/<recipe>/<run>)
      --fresh                      retrain cached teachers
    toy-gmm also takes --teacher exact|ddpm|beso and --iterations N;
    toy-conditional --iterations N, --experts N, --lr X, --weighting gating|uniform
  cargo xtask table RUN_DIR... [--out FILE]   mean ± std tables over the runs' seeds
  cargo xtask compare RUN_A RUN_B             metrics.json equal apart from timings?
  cargo xtask bench nn|teachers
  cargo xtask demos avoiding [--n N] [--seed S] [--out DIR]";

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let result = match args.iter().map(String::as_str).collect::<Vec<_>>().as_slice() {
        ["experiment", rest @ ..] => experiment::run(&strings(rest)),
        ["table", rest @ ..] => report::run_table(&strings(rest)),
        ["compare", rest @ ..] => report::run_compare(&strings(rest)),
        ["bench", "nn", rest @ ..] => bench_nn::run(&strings(rest)),
        ["bench", "teachers", rest @ ..] => bench_teachers::run(&strings(rest)),
        ["demos", rest @ ..] => demos::run(&strings(rest)),
        ["help" | "--help" | "-h"] | [] => {
            println!("{USAGE}");
            Ok(())
        }
        _ => Err(format!("unknown command `{}`\n{USAGE}", args.join(" ")).into()),
    };
    if let Err(e) = result {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

fn strings(s: &[&str]) -> Vec<String> {
    s.iter().map(|x| x.to_string()).collect()
}

/// Progress bars shared by the commands (stderr, hidden when not a terminal). Bars of
/// concurrent jobs stack in one [`MultiProgress`](indicatif::MultiProgress); log lines go
/// through [`log`](progress::log) so they print above the bars instead of through them.
pub mod progress {
    use std::sync::OnceLock;

    use indicatif::{MultiProgress, ProgressBar, ProgressStyle};

    fn multi() -> &'static MultiProgress {
        static MULTI: OnceLock<MultiProgress> = OnceLock::new();
        MULTI.get_or_init(MultiProgress::new)
    }

    /// A bar of `len` steps labelled `what`.
    pub fn bar(len: u64, what: &str) -> ProgressBar {
        let bar = ProgressBar::new(len);
        bar.set_style(
            ProgressStyle::with_template("{prefix:>14} [{bar:30}] {pos}/{len} {elapsed} {msg}")
                .expect("valid template")
                .progress_chars("=> "),
        );
        bar.set_prefix(what.to_owned());
        multi().add(bar)
    }

    /// A spinner labelled `what` with message `msg`, for stages without a step count.
    pub fn spinner(what: &str, msg: &str) -> ProgressBar {
        let bar = ProgressBar::new_spinner();
        bar.set_style(
            ProgressStyle::with_template("{prefix:>14} {spinner} {elapsed} {msg}")
                .expect("valid template"),
        );
        bar.set_prefix(what.to_owned());
        bar.set_message(msg.to_owned());
        let bar = multi().add(bar);
        bar.enable_steady_tick(std::time::Duration::from_millis(200));
        bar
    }

    /// Prints a log line to stderr above any active bars.
    pub fn log(line: impl AsRef<str>) {
        multi().suspend(|| eprintln!("{}", line.as_ref()));
    }
}

/// Minimal `--key value` / `--flag` parser shared by the commands.
pub mod cli {
    use std::collections::BTreeMap;

    /// Parsed options: `--key value` pairs and bare `--flag`s (value `"true"`).
    #[derive(Debug, Default)]
    pub struct Opts(pub BTreeMap<String, String>);

    impl Opts {
        /// Parses `args`; `flags` names the options that take no value.
        pub fn parse(args: &[String], flags: &[&str]) -> Result<Self, String> {
            let mut map = BTreeMap::new();
            let mut it = args.iter();
            while let Some(a) = it.next() {
                let key =
                    a.strip_prefix("--").ok_or_else(|| format!("unexpected argument `{a}`"))?;
                if flags.contains(&key) {
                    map.insert(key.to_owned(), "true".to_owned());
                } else {
                    let v = it.next().ok_or_else(|| format!("option --{key} needs a value"))?;
                    map.insert(key.to_owned(), v.clone());
                }
            }
            Ok(Self(map))
        }

        /// The value of `--key` parsed as `T`, or `default`.
        pub fn get<T: std::str::FromStr>(&self, key: &str, default: T) -> Result<T, String> {
            match self.0.get(key) {
                None => Ok(default),
                Some(v) => v.parse().map_err(|_| format!("invalid value `{v}` for --{key}")),
            }
        }

        /// Whether the bare flag `--key` was given.
        pub fn flag(&self, key: &str) -> bool {
            self.0.contains_key(key)
        }

        /// Fails on options not in `known`.
        pub fn only(&self, known: &[&str]) -> Result<(), String> {
            match self.0.keys().find(|k| !known.contains(&k.as_str())) {
                Some(k) => Err(format!("unknown option --{k}")),
                None => Ok(()),
            }
        }
    }
}
