//! The architecture's invariants, enforced (see `docs/architecture.md`).
//!
//! These read the workspace's own files: each crate's `Cargo.toml` for the dependency rules and
//! the sources for what library code must not do. A failure names the file and the rule.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

#[path = "architecture/module_cycles.rs"]
mod module_cycles;

fn root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).parent().expect("tests/ has a parent").to_path_buf()
}

/// The workspace dependencies (`vdd*`, `xtask`; normal, not dev) of every library crate under
/// `crates/`.
fn crate_deps() -> BTreeMap<String, BTreeSet<String>> {
    let mut out = BTreeMap::new();
    for entry in std::fs::read_dir(root().join("crates")).expect("crates/ exists") {
        let dir = entry.expect("readable crates/").path();
        let manifest = dir.join("Cargo.toml");
        let Ok(text) = std::fs::read_to_string(&manifest) else { continue };
        let doc: toml::Table = text.parse().unwrap_or_else(|e| panic!("{manifest:?}: {e}"));
        let name = doc["package"]["name"].as_str().expect("package.name").to_owned();
        let deps = doc
            .get("dependencies")
            .and_then(|d| d.as_table())
            .map(|t| {
                let workspace = |k: &String| k.starts_with("vdd") || k.as_str() == "xtask";
                t.keys().filter(|k| workspace(k)).cloned().collect()
            })
            .unwrap_or_default();
        out.insert(name, deps);
    }
    out
}

/// Every `.rs` file below `dir`.
fn rust_files(dir: &Path) -> Vec<PathBuf> {
    let mut out = Vec::new();
    let mut stack = vec![dir.to_path_buf()];
    while let Some(d) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&d) else { continue };
        for e in entries.flatten() {
            let p = e.path();
            if p.is_dir() {
                if p.file_name().is_some_and(|n| n != "target" && n != "fixtures") {
                    stack.push(p);
                }
            } else if p.extension().is_some_and(|x| x == "rs") {
                out.push(p);
            }
        }
    }
    out.sort();
    out
}

fn library_crates() -> Vec<PathBuf> {
    let mut v: Vec<PathBuf> = std::fs::read_dir(root().join("crates"))
        .expect("crates/ exists")
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.join("Cargo.toml").exists())
        .collect();
    v.sort();
    v
}

#[test]
fn crate_dependency_rules_hold() {
    let deps = crate_deps();
    assert!(deps.contains_key("vdd-core"), "found crates: {:?}", deps.keys());
    // (crate, the workspace crates it may depend on): everything else is what it must not know.
    // A new crate fails here until its place is stated.
    let allowed: &[(&str, &[&str])] = &[
        // The vocabulary knows nothing of its implementations.
        ("vdd-core", &[]),
        // Layers are reusable by any model.
        ("vdd-nn", &["vdd-core"]),
        // PyTorch architectures are networks: they know no files, importers or tasks.
        ("vdd-torch", &["vdd-core", "vdd-nn"]),
        // Datasets and the observation pipeline serve any model and any task.
        ("vdd-data", &["vdd-core"]),
        // A teacher is trained and used on its own.
        ("vdd-diffusion", &["vdd-core", "vdd-nn", "vdd-data"]),
        // The deployed student loads without any training code.
        ("vdd-moe", &["vdd-core", "vdd-nn", "vdd-data"]),
        // A teacher is any ScoreModel: the trainer never knows diffusion.
        ("vdd", &["vdd-core", "vdd-nn", "vdd-moe"]),
        // A user who wants EM does not compile the diffusion stack.
        ("vdd-mixture", &["vdd-core", "vdd-nn", "vdd-moe"]),
        // CD and CTM are diffusion models of their own.
        ("vdd-consistency", &["vdd-core", "vdd-nn", "vdd-diffusion", "vdd-data"]),
        // Tasks roll out any Policy; they know no teacher, student or trainer.
        ("vdd-tasks", &["vdd-core", "vdd-data"]),
        // Plain data in, files and strings out.
        ("vdd-report", &[]),
        // Recipes of any tool resolve the same way (vdd-core only for its stable hash).
        ("vdd-recipe", &["vdd-core"]),
        // PyTorch teachers are networks plus noise processes; they know no student or trainer.
        ("vdd-import", &["vdd-core", "vdd-nn", "vdd-torch", "vdd-diffusion", "vdd-data"]),
        // The Python package binds the deployed student, the trainer and the learned and
        // imported teachers.
        (
            "vdd-py",
            &[
                "vdd-core",
                "vdd-data",
                "vdd-moe",
                "vdd",
                "vdd-diffusion",
                "vdd-import",
                "vdd-onnx",
                "vdd-tasks",
            ],
        ),
        // ONNX export reads a saved student; it knows no teacher, trainer or task.
        ("vdd-onnx", &["vdd-core", "vdd-nn", "vdd-data", "vdd-moe"]),
        // The experiment layer wires teachers, methods and tasks into rows of results; no
        // tool (xtask), binding (vdd-py) or exporter depends on it or is known by it.
        (
            "vdd-lab",
            &[
                "vdd-core",
                "vdd-nn",
                "vdd-data",
                "vdd-diffusion",
                "vdd-moe",
                "vdd",
                "vdd-mixture",
                "vdd-consistency",
                "vdd-tasks",
                "vdd-report",
                "vdd-recipe",
                "vdd-import",
            ],
        ),
        // The fuzzer's engine exercises the loaders it fuzzes; no task, recipe or tool code.
        (
            "vdd-fuzz",
            &["vdd-core", "vdd-nn", "vdd-data", "vdd-moe", "vdd-diffusion", "vdd", "vdd-import"],
        ),
    ];
    let mut broken = Vec::new();
    for (krate, deps) in &deps {
        let Some((_, ok)) = allowed.iter().find(|(k, _)| k == krate) else {
            broken.push(format!("crate {krate} has no rule: add it to `allowed` and the docs"));
            continue;
        };
        for d in deps {
            if !ok.contains(&d.as_str()) {
                broken.push(format!("{krate} depends on {d}"));
            }
        }
    }
    for (krate, _) in allowed {
        if !deps.contains_key(*krate) {
            broken.push(format!("crate {krate} is missing"));
        }
    }
    assert!(broken.is_empty(), "crate dependency rules broken: {broken:#?}");
}

/// `file:line: text` of every source line under `dirs` whose code (comments cut) `hit` matches,
/// files whose path ends in `skip` left out.
fn code_lines_where(
    dirs: &[PathBuf],
    skip: Option<&str>,
    hit: impl Fn(&str) -> bool,
) -> Vec<String> {
    let mut hits = Vec::new();
    for f in
        dirs.iter().flat_map(|d| rust_files(d)).filter(|f| skip.is_none_or(|s| !f.ends_with(s)))
    {
        let text = std::fs::read_to_string(&f).expect("readable source");
        for (i, line) in text.lines().enumerate() {
            if hit(line.split("//").next().unwrap_or("")) {
                hits.push(format!("{}:{}: {}", f.display(), i + 1, line.trim()));
            }
        }
    }
    hits
}

#[test]
fn library_code_never_prints() {
    let dirs: Vec<PathBuf> = library_crates().iter().map(|k| k.join("src")).collect();
    let hits = code_lines_where(&dirs, None, |code| {
        ["println!", "eprintln!", "print!(", "eprint!(", "dbg!("].iter().any(|m| code.contains(m))
    });
    assert!(hits.is_empty(), "library code prints (progress goes through callbacks): {hits:#?}");
}

/// Matrix products go through `vdd_nn::matmul`, which clears the AVX registers' upper halves
/// that faer's kernels leave set (the scalar code after a bare product runs several times
/// slower; `crates/vdd-nn/src/gemm.rs`).
#[test]
fn every_matrix_product_goes_through_vdd_nn_matmul() {
    let mut dirs: Vec<PathBuf> = library_crates().iter().map(|k| k.join("src")).collect();
    dirs.push(root().join("xtask").join("src"));
    let hits =
        code_lines_where(&dirs, Some("vdd-nn/src/gemm.rs"), |code| code.contains("linalg::matmul"));
    assert!(hits.is_empty(), "bare faer products (use vdd_nn::matmul): {hits:#?}");
}

/// xtask is a command line: teachers, experts and policies are crate types (the dispatch enum
/// over the methods' trained policies is `vdd_lab::policy::TrainedPolicy`).
#[test]
fn xtask_implements_no_teacher_expert_or_policy() {
    let hits = code_lines_where(&[root().join("xtask/src")], None, |code| {
        let l = code.trim_start();
        l.starts_with("impl")
            && ["ScoreModel for", "Expert for", "Policy for"].iter().any(|t| l.contains(t))
    });
    assert!(hits.is_empty(), "xtask wires crates and implements none of their traits: {hits:#?}");
}

/// The `fn` names of the first block after the line containing `header`, up to the line
/// that closes it (the first line `}` at the header's indentation).
fn fns_of_block(text: &str, header: &str) -> Option<BTreeSet<String>> {
    let lines: Vec<&str> = text.lines().collect();
    let start = lines.iter().position(|l| l.contains(header))?;
    let indent = lines[start].len() - lines[start].trim_start().len();
    let close = format!("{}}}", " ".repeat(indent));
    let mut names = BTreeSet::new();
    for l in &lines[start + 1..] {
        if *l == close {
            return Some(names);
        }
        let t = l.trim_start();
        if let Some(rest) = t.strip_prefix("fn ") {
            let name: String =
                rest.chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect();
            names.insert(name);
        }
    }
    None
}

/// A teacher wrapper states every fact and capability of the teacher it wraps: each of these
/// `ScoreModel` implementations defines every method of the trait, so none falls back to a
/// default (a wrapper that forgot `noise_range` hid the in-house teachers' trained range from
/// `Vdd::auto`).
#[test]
fn teacher_wrappers_forward_every_score_model_method() {
    let read = |p: &str| std::fs::read_to_string(root().join(p)).expect("readable source");
    let core = read("crates/vdd-core/src/score.rs");
    let all = fns_of_block(&core, "pub trait ScoreModel").expect("the trait is in score.rs");
    assert!(all.len() >= 9 && all.contains("noise_range"), "{all:?}");
    let wrappers = [
        ("crates/vdd-diffusion/src/teacher.rs", "impl ScoreModel for DiffusionTeacher"),
        ("crates/vdd-core/src/denoiser.rs", "ScoreModel for ClampedDenoiser<S>"),
        ("crates/vdd/src/spaces.rs", "ScoreModel for MappedTeacher<'_, S>"),
        ("crates/vdd-import/src/teacher.rs", "impl ScoreModel for ImportedTeacher"),
        ("crates/vdd-core/src/score.rs", "ScoreModel for $($pointer)*"),
    ];
    let mut missing = Vec::new();
    for (file, header) in wrappers {
        let Some(fns) = fns_of_block(&read(file), header) else {
            missing.push(format!("{file}: no `{header}` block"));
            continue;
        };
        let lacking: Vec<_> = all.difference(&fns).collect();
        if !lacking.is_empty() {
            missing.push(format!("{file}: `{header}` does not forward {lacking:?}"));
        }
    }
    assert!(missing.is_empty(), "teacher wrappers drop methods: {missing:#?}");
}

/// xtask parses command lines and calls the crates; experiment logic lives in `vdd-lab`.
#[test]
fn xtask_is_a_command_line_of_at_most_1500_lines() {
    let files = rust_files(&root().join("xtask/src"));
    let count = |f: &PathBuf| std::fs::read_to_string(f).expect("readable source").lines().count();
    let total: usize = files.iter().map(count).sum();
    assert!(total <= 1500, "xtask/src has {total} lines (at most 1,500: move logic into a crate)");
}

/// vdd-report takes rows and columns as data: no task or method is named in its code (doc
/// examples and tests may use them as data).
#[test]
fn vdd_report_names_no_task_or_method() {
    let names = [
        "avoiding",
        "toy-gmm",
        "toy-conditional",
        "beso",
        "ddpm",
        "vdd-beso",
        "vdd-ddpm",
        "cd",
        "ctm",
        "em",
        "imc",
        "vdd-exact",
    ];
    let mut hits = Vec::new();
    for f in rust_files(&root().join("crates/vdd-report/src")) {
        if f.file_name().is_some_and(|n| n == "tests.rs") {
            continue;
        }
        let text = std::fs::read_to_string(&f).expect("readable source");
        for (i, line) in text.lines().enumerate() {
            if line.trim_start().starts_with("#[cfg(test)]") {
                break;
            }
            let code = line.split("//").next().unwrap_or("");
            if let Some(n) = names.iter().find(|n| code.contains(&format!("\"{n}\""))) {
                hits.push(format!("{}:{}: {n}", f.display(), i + 1));
            }
        }
    }
    assert!(hits.is_empty(), "vdd-report names tasks or methods: {hits:#?}");
}

#[test]
fn no_source_file_is_over_800_lines() {
    let mut long = Vec::new();
    let mut dirs: Vec<PathBuf> = library_crates();
    dirs.push(root().join("xtask"));
    dirs.push(root().join("tests"));
    for d in dirs {
        for f in rust_files(&d) {
            let n = std::fs::read_to_string(&f).expect("readable source").lines().count();
            if n > 800 {
                long.push(format!("{}: {n} lines", f.display()));
            }
        }
    }
    assert!(
        long.is_empty(),
        "split these files (long test modules go into their own files): {long:#?}"
    );
}
