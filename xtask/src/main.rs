//! `cargo xtask`: experiment recipes, benchmarks and demos.
//!
//! ```text
//! cargo xtask experiment toy-gmm [--teacher exact|ddpm|beso] [--seed N] [--out DIR]
//! cargo xtask bench nn|teachers
//! cargo xtask demos avoiding --n 200 --seed 0 --out DIR
//! ```

mod bench_nn;
mod bench_teachers;
mod demos;
mod toy;

/// Errors of any xtask command, printed at the top level.
pub type XResult<T = ()> = Result<T, Box<dyn std::error::Error>>;

const USAGE: &str = "usage:
  cargo xtask experiment toy-gmm [--teacher exact|ddpm|beso] [--seed N] [--out DIR]
  cargo xtask experiment toy-conditional [--seed N] [--out DIR] [--iterations N]
  cargo xtask bench nn|teachers
  cargo xtask demos avoiding [--n N] [--seed S] [--out DIR]";

fn main() {
    let args: Vec<String> = std::env::args().skip(1).collect();
    let result = match args.iter().map(String::as_str).collect::<Vec<_>>().as_slice() {
        ["experiment", "toy-gmm", rest @ ..] => toy::run(&strings(rest)),
        ["experiment", "toy-conditional", rest @ ..] => toy::run_conditional(&strings(rest)),
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

/// Progress bars shared by the commands (stderr, hidden when not a terminal).
pub mod progress {
    use indicatif::{ProgressBar, ProgressStyle};

    /// A bar of `len` steps labelled `what`.
    pub fn bar(len: u64, what: &str) -> ProgressBar {
        let bar = ProgressBar::new(len);
        bar.set_style(
            ProgressStyle::with_template("{prefix:>10} [{bar:30}] {pos}/{len} {elapsed} {msg}")
                .expect("valid template")
                .progress_chars("=> "),
        );
        bar.set_prefix(what.to_owned());
        bar
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
