//! `cargo xtask`: experiment recipes, result tables, benchmarks and demos.
//!
//! ```text
//! cargo xtask experiment <recipe> [--seed N | --seeds 0,1,2 | --seeds 0..3] [--methods a,b]
//!                                 [--set k.path=v]... [--quick] [--out DIR] [--fresh]
//! cargo xtask table [RUN_DIR...] [--out FILE]
//! cargo xtask compare RUN_DIR_A RUN_DIR_B
//! cargo xtask bench nn|teachers|import|robustness
//! cargo xtask import lerobot|diffusion-policy|beso INPUT --out FILE
//! cargo xtask demos avoiding --n 200 --seed 0 --out DIR
//! cargo xtask demos block-push --n 200 --seed 0 --out DIR
//! cargo xtask export-onnx MODEL --out policy.onnx
//! ```
//!
//! `cargo xtask help [COMMAND]` describes every option (the parser is `clap`'s derive API; bad
//! input exits with status 1 and a message). Recipes are the TOML files in `recipes/` (see
//! [`recipe`] for how they resolve and [`experiment`] for the run directory layout).

mod bench_nn;
mod bench_robust;
mod bench_teachers;
mod demos;
mod experiment;
mod export_onnx;
mod fuzz;
mod import;
mod report;

use vdd_lab::recipe;

/// Errors of any xtask command, printed at the top level.
pub type XResult<T = ()> = Result<T, Box<dyn std::error::Error>>;

/// The command line: one subcommand per task.
#[derive(Debug, clap::Parser)]
#[command(
    name = "cargo xtask",
    bin_name = "cargo xtask",
    about = "Experiment recipes, result tables, benchmarks and demos of the VDD workspace.",
    disable_version_flag = true
)]
enum Cli {
    /// Run a recipe from recipes/ (or a .toml path).
    Experiment(experiment::ExperimentArgs),
    /// Mean ± std tables over the runs' seeds.
    Table(report::TableArgs),
    /// Whether two runs' metrics.json are equal apart from timings.
    Compare(report::CompareArgs),
    /// Benchmarks.
    #[command(subcommand)]
    Bench(Bench),
    /// Scripted demonstrations.
    #[command(subcommand)]
    Demos(Demos),
    /// Teachers trained in PyTorch, into teacher files.
    #[command(subcommand)]
    Import(import::Import),
    /// Mutation fuzzing of the file loaders (see xtask/src/fuzz.rs, crates/vdd-fuzz).
    Fuzz(fuzz::Args),
    /// One fuzz case, run in a child process by `fuzz`.
    #[command(hide = true)]
    FuzzCase(fuzz::CaseArgs),
    /// Export a saved policy as an ONNX graph (obs in; log_gating, means, scale_tril out).
    ExportOnnx(export_onnx::Args),
}

/// `cargo xtask bench ...`.
#[derive(Debug, clap::Subcommand)]
enum Bench {
    /// Residual MLP forward+backward throughput against a bare faer matmul.
    Nn(bench_nn::Args),
    /// Acceptance checks and sampling latency of the learned toy teachers.
    Teachers(bench_teachers::Args),
    /// Imported PyTorch networks against their fixtures: max_abs_diff, rows/s against torch.
    Import(import::BenchArgs),
    /// VDD with library defaults on a seeded family of exact-mixture teachers.
    Robustness(bench_robust::Args),
}

/// `cargo xtask demos ...`.
#[derive(Debug, clap::Subcommand)]
enum Demos {
    /// Scripted Avoiding demonstrations written as .npz, and the demonstrator's metrics.
    Avoiding(demos::AvoidingArgs),
    /// Scripted Block-Push demonstrations (rapier2d) as .npz, their modes and a figure.
    BlockPush(demos::BlockPushArgs),
}

/// The command line parser, with the recipes found in `recipes/` and the rows `--methods all`
/// runs on each task listed under `experiment`.
fn command() -> clap::Command {
    use clap::CommandFactory;
    let recipes = recipe::available_recipes().join(", ");
    let registry = vdd_lab::Registry::builtin();
    let rows: Vec<String> = (registry.tasks().iter())
        .map(|t| {
            let all = registry.parse_rows(&["all".to_owned()], t.name()).unwrap_or_default();
            let names: Vec<&str> = all.iter().map(|r| r.name.as_str()).collect();
            format!("  {}: {}", t.name(), names.join(", "))
        })
        .collect();
    let help = format!("Recipes: {recipes}\n\nRows of `--methods all`:\n{}", rows.join("\n"));
    Cli::command().mut_subcommand("experiment", |c| c.after_help(help))
}

/// Parses `args` (without the program name). Help requests come back as errors too; clap's
/// error says which (and how to print it).
fn parse<S: Into<std::ffi::OsString> + Clone>(args: &[S]) -> Result<Cli, clap::Error> {
    use clap::FromArgMatches;
    let words = std::iter::once("cargo xtask".into()).chain(args.iter().cloned().map(Into::into));
    Cli::from_arg_matches(&command().try_get_matches_from(words)?)
}

fn main() {
    vdd_lab::progress::set_sink(std::sync::Arc::new(progress::Terminal));
    // Not `env::args`, which panics on words that are not UTF-8: clap reports them.
    let args: Vec<std::ffi::OsString> = std::env::args_os().skip(1).collect();
    if args.is_empty() {
        println!("{}", command().render_help());
        return;
    }
    let cli = match parse(&args) {
        Ok(cli) => cli,
        Err(e) => {
            // Help goes to stdout and succeeds; bad input is an error (exit 1, not clap's 2).
            let _ = e.print();
            std::process::exit(if e.use_stderr() { 1 } else { 0 });
        }
    };
    let result = match cli {
        Cli::Experiment(a) => {
            let words: Vec<_> = args.iter().map(|w| w.to_string_lossy()).collect();
            experiment::run(&a, &format!("cargo xtask {}", words.join(" ")))
        }
        Cli::Table(a) => report::run_table(&a),
        Cli::Compare(a) => report::run_compare(&a),
        Cli::Bench(Bench::Nn(a)) => bench_nn::run(&a),
        Cli::Bench(Bench::Teachers(a)) => bench_teachers::run(&a),
        Cli::Bench(Bench::Import(a)) => import::bench(&a),
        Cli::Import(a) => import::run(&a),
        Cli::Bench(Bench::Robustness(a)) => bench_robust::run(&a),
        Cli::Demos(Demos::Avoiding(a)) => demos::avoiding(&a),
        Cli::Demos(Demos::BlockPush(a)) => demos::block_push(&a),
        Cli::Fuzz(a) => fuzz::run(&a),
        Cli::FuzzCase(a) => fuzz::case(&a),
        Cli::ExportOnnx(a) => export_onnx::run(&a),
    };
    if let Err(e) = result {
        eprintln!("error: {e}");
        std::process::exit(1);
    }
}

/// Progress bars shared by the commands (stderr, hidden when not a terminal). Bars of
/// concurrent jobs stack in one [`MultiProgress`](indicatif::MultiProgress); log lines go
/// through [`log`](progress::log) so they print above the bars instead of through them.
pub mod progress {
    use std::sync::OnceLock;

    use indicatif::{MultiProgress, ProgressBar, ProgressStyle};
    use vdd_lab::progress::{Bar, Sink};

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

    /// The experiment layer's progress in the terminal: bars, log lines on stderr, result
    /// lines on stdout.
    pub struct Terminal;

    struct Shown(ProgressBar);

    impl Bar for Shown {
        fn set_position(&self, pos: u64) {
            self.0.set_position(pos);
        }
        fn inc(&self, n: u64) {
            self.0.inc(n);
        }
        fn set_message(&self, msg: String) {
            self.0.set_message(msg);
        }
        fn finish_and_clear(&self) {
            self.0.finish_and_clear();
        }
    }

    /// A bar for a log file or pipe (stderr not a terminal, where indicatif draws nothing): a
    /// line `what: pos/len (pct %) secs s msg` at most every [`LINE_EVERY`] and at the end.
    struct Lines {
        what: String,
        len: u64,
        start: std::time::Instant,
        state: std::sync::Mutex<(u64, std::time::Instant, String)>,
    }

    /// How often a [`Lines`] bar prints.
    const LINE_EVERY: std::time::Duration = std::time::Duration::from_secs(30);

    impl Lines {
        fn new(len: u64, what: &str) -> Self {
            let now = std::time::Instant::now();
            Self { what: what.to_owned(), len, start: now, state: (0, now, String::new()).into() }
        }
        fn update(&self, f: impl FnOnce(&mut u64)) {
            let mut s = self.state.lock().unwrap_or_else(|e| e.into_inner());
            f(&mut s.0);
            if s.1.elapsed() >= LINE_EVERY || s.0 >= self.len {
                s.1 = std::time::Instant::now();
                let pct = 100.0 * s.0 as f64 / self.len.max(1) as f64;
                let secs = self.start.elapsed().as_secs_f64();
                log(format!(
                    "{}: {}/{} ({pct:.0} %) {secs:.0} s {}",
                    self.what, s.0, self.len, s.2
                ));
            }
        }
    }

    impl Bar for Lines {
        fn set_position(&self, pos: u64) {
            self.update(|p| *p = pos);
        }
        fn inc(&self, n: u64) {
            self.update(|p| *p += n);
        }
        fn set_message(&self, msg: String) {
            self.state.lock().unwrap_or_else(|e| e.into_inner()).2 = msg;
        }
    }

    fn is_terminal() -> bool {
        use std::io::IsTerminal as _;
        std::io::stderr().is_terminal()
    }

    impl Sink for Terminal {
        fn bar(&self, len: u64, what: &str) -> Box<dyn Bar> {
            if is_terminal() {
                Box::new(Shown(bar(len, what)))
            } else {
                Box::new(Lines::new(len, what))
            }
        }
        fn spinner(&self, what: &str, msg: &str) -> Box<dyn Bar> {
            if is_terminal() {
                Box::new(Shown(spinner(what, msg)))
            } else {
                log(format!("{what}: {msg}"));
                Box::new(vdd_lab::progress::Silent)
            }
        }
        fn log(&self, line: &str) {
            log(line);
        }
        fn print(&self, line: &str) {
            multi().suspend(|| println!("{line}"));
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn words(s: &str) -> Vec<String> {
        s.split_whitespace().map(String::from).collect()
    }

    #[test]
    fn the_command_line_is_consistent_and_parses_every_command() {
        command().debug_assert();
        assert!(
            matches!(parse(&words("table a b --out t.md")), Ok(Cli::Table(t)) if t.runs.len() == 2)
        );
        assert!(matches!(parse(&words("compare a b")), Ok(Cli::Compare(_))));
        let nn = parse(&words("bench nn --batch 8 --layer-norm")).unwrap();
        assert!(matches!(nn, Cli::Bench(Bench::Nn(a)) if a.batch == 8 && a.layer_norm));
        let t = parse(&words("bench teachers --noise-mean -1.2 --retrain")).unwrap();
        assert!(matches!(t, Cli::Bench(Bench::Teachers(a)) if a.noise_mean == -1.2 && a.retrain));
        let i = parse(&words("import lerobot d --out f")).unwrap();
        assert!(matches!(i, Cli::Import(import::Import::Lerobot(a)) if a.out.ends_with("f")));
        let m = "import lerobot d --out f --obs-map observation.state=2,3;observation.environment_state=0,1 --sampler ddim:10";
        let i = parse(&words(m)).unwrap();
        let Cli::Import(import::Import::Lerobot(a)) = i else { panic!("not an import") };
        assert_eq!(a.sampler.map(|s| s.to_string()).as_deref(), Some("ddim:10"));
        assert!(a.obs_map.is_some());
        assert!(
            parse(&words("import lerobot d --out f --sampler ddim:x")).unwrap_err().use_stderr()
        );
        assert!(
            parse(&words("import lerobot d --out f --obs-map nonsense")).unwrap_err().use_stderr()
        );
        let r = parse(&words("bench robustness --quick --out /tmp/r")).unwrap();
        assert!(matches!(r, Cli::Bench(Bench::Robustness(a)) if a.quick && a.threads == 2));
        let r =
            parse(&words("bench robustness --out /tmp/r --seeds 0,3 --only 100 --variant long"));
        assert!(matches!(r.unwrap(), Cli::Bench(Bench::Robustness(a))
            if a.seeds == [0, 3] && a.only == [100] && a.variant.name() == "long"));
        let d = parse(&words("demos avoiding --n 5 --seed 2 --out /tmp/d")).unwrap();
        assert!(matches!(d, Cli::Demos(Demos::Avoiding(a)) if a.n == 5 && a.seed == 2));
        let d = parse(&words("demos block-push --n 7 --figure 3")).unwrap();
        assert!(matches!(d, Cli::Demos(Demos::BlockPush(a)) if a.n == 7 && a.figure == 3));
        // The experiment help lists what `--methods all` runs on each task, from the registry.
        let help = command().find_subcommand_mut("experiment").unwrap().render_help().to_string();
        let line = |task: &str| help.lines().find(|l| l.trim_start().starts_with(task)).unwrap();
        assert!(line("pushing:").contains("imc-authors"), "{help}");
        assert!(!line("pushing:").contains("vdd-beso-selected"), "{help}");
        assert!(line("avoiding:").contains("vdd-beso-selected"), "{help}");
        // Help is not an error; bad input is.
        for help in ["help", "--help", "help experiment", "experiment --help"] {
            assert!(!parse(&words(help)).unwrap_err().use_stderr(), "{help}");
        }
        for bad in ["frobnicate", "bench", "bench gpu", "demos", "compare a", "table --bogus"] {
            assert!(parse(&words(bad)).unwrap_err().use_stderr(), "{bad}");
        }
        #[cfg(unix)]
        {
            use std::os::unix::ffi::OsStringExt;
            let not_utf8 = std::ffi::OsString::from_vec(vec![b'x', 0xff]);
            let args = ["experiment".into(), not_utf8];
            assert!(parse(&args).unwrap_err().use_stderr(), "an error, not a panic");
        }
    }
}
