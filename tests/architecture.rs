//! The architecture's invariants, enforced (see `docs/architecture.md`).
//!
//! These read the workspace's own files: each crate's `Cargo.toml` for the dependency rules and
//! the sources for what library code must not do. A failure names the file and the rule.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

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
        ("vdd-diffusion", &["vdd-core", "vdd-nn"]),
        // The deployed student loads without any training code.
        ("vdd-moe", &["vdd-core", "vdd-nn", "vdd-data"]),
        // A teacher is any ScoreModel: the trainer never knows diffusion.
        ("vdd", &["vdd-core", "vdd-nn", "vdd-moe"]),
        // A user who wants EM does not compile the diffusion stack.
        ("vdd-mixture", &["vdd-core", "vdd-nn", "vdd-moe"]),
        // CD and CTM are diffusion models of their own.
        ("vdd-consistency", &["vdd-core", "vdd-nn", "vdd-diffusion"]),
        // Tasks roll out any Policy; they know no teacher, student or trainer.
        ("vdd-tasks", &["vdd-core", "vdd-data"]),
        // Plain data in, files and strings out.
        ("vdd-report", &[]),
        // Recipes of any tool resolve the same way (vdd-core only for its stable hash).
        ("vdd-recipe", &["vdd-core"]),
        // PyTorch teachers are networks plus noise processes; they know no student or trainer.
        ("vdd-import", &["vdd-core", "vdd-nn", "vdd-torch", "vdd-diffusion", "vdd-data"]),
        // The Python package binds the deployed student, the trainer and the learned teachers.
        (
            "vdd-py",
            &["vdd-core", "vdd-data", "vdd-moe", "vdd", "vdd-diffusion", "vdd-onnx", "vdd-tasks"],
        ),
        // ONNX export reads a saved student; it knows no teacher, trainer or task.
        ("vdd-onnx", &["vdd-core", "vdd-nn", "vdd-data", "vdd-moe"]),
        // The fuzzer's engine exercises the loaders it fuzzes; no task, recipe or tool code.
        ("vdd-fuzz", &["vdd-core", "vdd-nn", "vdd-data", "vdd-moe", "vdd-diffusion", "vdd"]),
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

#[test]
fn library_code_never_prints() {
    let mut hits = Vec::new();
    for krate in library_crates() {
        for f in rust_files(&krate.join("src")) {
            let text = std::fs::read_to_string(&f).expect("readable source");
            for (i, line) in text.lines().enumerate() {
                let code = line.split("//").next().unwrap_or("");
                if ["println!", "eprintln!", "print!(", "eprint!(", "dbg!("]
                    .iter()
                    .any(|m| code.contains(m))
                {
                    hits.push(format!("{}:{}: {}", f.display(), i + 1, line.trim()));
                }
            }
        }
    }
    assert!(hits.is_empty(), "library code prints (progress goes through callbacks): {hits:#?}");
}

/// xtask wires the crates: teachers, experts and policies are crate types. Its one `Policy`
/// implementation is the private enum that dispatches over the methods' trained policies (the
/// pattern of ripgrep's `PatternMatcher`), so one rollout code path serves every method.
#[test]
fn xtask_implements_no_teacher_expert_or_policy() {
    let mut hits = Vec::new();
    for f in rust_files(&root().join("xtask/src")) {
        let text = std::fs::read_to_string(&f).expect("readable source");
        for (i, line) in text.lines().enumerate() {
            let l = line.trim_start();
            if !l.starts_with("impl") {
                continue;
            }
            let core_trait = ["ScoreModel for", "Expert for"].iter().any(|t| l.contains(t));
            let policy = l.contains("Policy for") && !l.contains("Policy for TrainedPolicy");
            if core_trait || policy {
                hits.push(format!("{}:{}: {}", f.display(), i + 1, l));
            }
        }
    }
    assert!(hits.is_empty(), "xtask wires crates and implements none of their traits: {hits:#?}");
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

/// Top-level modules of a crate's `src/` and the modules each one names via `crate::m`.
fn module_graph(src: &Path) -> BTreeMap<String, BTreeSet<String>> {
    let modules: BTreeSet<String> = std::fs::read_dir(src)
        .expect("src/ exists")
        .flatten()
        .filter_map(|e| {
            let p = e.path();
            let stem = p.file_stem()?.to_str()?.to_owned();
            let is_mod = p.is_dir() || p.extension().is_some_and(|x| x == "rs");
            (is_mod && stem != "lib" && stem != "main").then_some(stem)
        })
        .collect();
    let mut graph: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for f in rust_files(src) {
        let rel = f.strip_prefix(src).expect("below src");
        let first = rel.components().next().expect("a component");
        let module =
            Path::new(first.as_os_str()).file_stem().and_then(|s| s.to_str()).unwrap_or("");
        if !modules.contains(module) {
            continue;
        }
        // Code only: a doc link (`[x](crate::m::x)`) or a comment is no dependency.
        let text: String = std::fs::read_to_string(&f)
            .expect("readable source")
            .lines()
            .map(|l| l.split("//").next().unwrap_or(""))
            .collect::<Vec<_>>()
            .join("\n");
        let mut rest = text.as_str();
        while let Some(at) = rest.find("crate::") {
            rest = &rest[at + "crate::".len()..];
            let name: String =
                rest.chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect();
            if name != module && modules.contains(&name) {
                graph.entry(module.to_owned()).or_default().insert(name);
            }
        }
        // `use crate::{a, b::c}` names several modules at once.
        let mut rest = text.as_str();
        while let Some(at) = rest.find("crate::{") {
            rest = &rest[at + "crate::{".len()..];
            let group = &rest[..rest.find('}').unwrap_or(0)];
            for part in group.split(',') {
                let name: String =
                    part.trim().chars().take_while(|c| c.is_alphanumeric() || *c == '_').collect();
                if name != module && modules.contains(&name) {
                    graph.entry(module.to_owned()).or_default().insert(name);
                }
            }
        }
    }
    graph
}

/// A cycle in `graph`, if there is one.
fn find_cycle(graph: &BTreeMap<String, BTreeSet<String>>) -> Option<Vec<String>> {
    fn visit(
        n: &str,
        graph: &BTreeMap<String, BTreeSet<String>>,
        path: &mut Vec<String>,
        done: &mut BTreeSet<String>,
    ) -> Option<Vec<String>> {
        if let Some(i) = path.iter().position(|p| p == n) {
            let mut c = path[i..].to_vec();
            c.push(n.to_owned());
            return Some(c);
        }
        if done.contains(n) {
            return None;
        }
        path.push(n.to_owned());
        for m in graph.get(n).into_iter().flatten() {
            if let Some(c) = visit(m, graph, path, done) {
                return Some(c);
            }
        }
        path.pop();
        done.insert(n.to_owned());
        None
    }
    let mut done = BTreeSet::new();
    for n in graph.keys() {
        if let Some(c) = visit(n, graph, &mut Vec::new(), &mut done) {
            return Some(c);
        }
    }
    None
}

#[test]
fn no_module_cycles() {
    let mut dirs: Vec<PathBuf> = library_crates();
    dirs.push(root().join("xtask"));
    let mut cycles = Vec::new();
    for d in dirs {
        if let Some(c) = find_cycle(&module_graph(&d.join("src"))) {
            cycles.push(format!("{}: {}", d.display(), c.join(" -> ")));
        }
    }
    assert!(cycles.is_empty(), "module cycles: {cycles:#?}");
}

#[test]
fn the_cycle_finder_finds_cycles() {
    let g: BTreeMap<String, BTreeSet<String>> = [
        ("a".to_owned(), ["b".to_owned()].into()),
        ("b".to_owned(), ["c".to_owned()].into()),
        ("c".to_owned(), ["a".to_owned()].into()),
    ]
    .into();
    assert_eq!(find_cycle(&g).map(|c| c.len()), Some(4));
    let acyclic: BTreeMap<String, BTreeSet<String>> =
        [("a".to_owned(), ["b".to_owned()].into()), ("b".to_owned(), BTreeSet::new())].into();
    assert_eq!(find_cycle(&acyclic), None);
}
