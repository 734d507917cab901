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

/// xtask is a command line: teachers, experts and policies are crate types (the dispatch enum
/// over the methods' trained policies is `vdd_lab::policy::TrainedPolicy`).
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
            let policy = l.contains("Policy for");
            if core_trait || policy {
                hits.push(format!("{}:{}: {}", f.display(), i + 1, l));
            }
        }
    }
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

/// Module cycles known when the detector learned to look at every depth, each `(crate
/// directory, the modules of the cycle, sorted)`. A cycle found that is not listed fails the
/// test, and so does a listed one that is gone: remove its line then.
const KNOWN_CYCLES: &[(&str, &[&str])] = &[];

/// `text` with comments, string and character literals blanked to spaces; newlines stay, so
/// line numbers stay too.
fn code_only(text: &str) -> String {
    let c: Vec<char> = text.chars().collect();
    let mut out = String::with_capacity(text.len());
    let blank = |out: &mut String, ch: char| out.push(if ch == '\n' { '\n' } else { ' ' });
    let ident = |ch: char| ch.is_alphanumeric() || ch == '_';
    let mut i = 0;
    while i < c.len() {
        let next = c.get(i + 1).copied();
        if c[i] == '/' && next == Some('/') {
            while i < c.len() && c[i] != '\n' {
                i += 1;
            }
        } else if c[i] == '/' && next == Some('*') {
            // Block comments nest.
            let mut depth = 0;
            while i < c.len() {
                if c[i] == '/' && c.get(i + 1) == Some(&'*') {
                    depth += 1;
                    i += 2;
                    out.push_str("  ");
                } else if c[i] == '*' && c.get(i + 1) == Some(&'/') {
                    depth -= 1;
                    i += 2;
                    out.push_str("  ");
                    if depth == 0 {
                        break;
                    }
                } else {
                    blank(&mut out, c[i]);
                    i += 1;
                }
            }
        } else if c[i] == 'r'
            && (i == 0 || !ident(c[i - 1]) || (c[i - 1] == 'b' && (i < 2 || !ident(c[i - 2]))))
            && matches!(next, Some('"' | '#'))
            && c[i + 1..].iter().find(|&&x| x != '#') == Some(&'"')
        {
            // A raw string: r"...", r#"..."#, br##"..."##.
            let hashes = c[i + 1..].iter().take_while(|&&x| x == '#').count();
            out.push('r');
            i += 2 + hashes;
            while i < c.len() {
                if c[i] == '"'
                    && c[i + 1..].iter().take(hashes).filter(|&&x| x == '#').count() == hashes
                {
                    i += 1 + hashes;
                    break;
                }
                blank(&mut out, c[i]);
                i += 1;
            }
            out.push('"');
        } else if c[i] == '"' {
            out.push('"');
            i += 1;
            while i < c.len() && c[i] != '"' {
                let n = if c[i] == '\\' { 2 } else { 1 };
                for k in i..(i + n).min(c.len()) {
                    blank(&mut out, c[k]);
                }
                i += n;
            }
            out.push('"');
            i += 1;
        } else if c[i] == '\'' && (next == Some('\\') || c.get(i + 2) == Some(&'\'')) {
            // A character literal ('x', '\n', '\u{..}'); a lifetime ('a) has no closing quote.
            i += if next == Some('\\') { 3 } else { 1 };
            while i < c.len() && c[i] != '\'' {
                i += 1;
            }
            out.push_str("' '");
            i += 1;
        } else {
            out.push(c[i]);
            i += 1;
        }
    }
    out
}

/// The module a file under `src/` defines: `lib.rs`/`main.rs` the root (`[]`), `a/mod.rs`
/// and `a.rs` `[a]`, `a/b.rs` `[a, b]`.
fn file_module(rel: &Path) -> Vec<String> {
    let mut m: Vec<String> =
        rel.components().map(|c| c.as_os_str().to_string_lossy().into_owned()).collect();
    let last = m.pop().unwrap_or_default();
    let stem = last.strip_suffix(".rs").unwrap_or(&last);
    if !(["lib", "main", "mod"].contains(&stem) && (stem == "mod" || m.is_empty())) {
        m.push(stem.to_owned());
    }
    m
}

/// The identifier starting at byte `i` of `code` (empty if none).
fn ident_at(code: &str, i: usize) -> &str {
    let rest = &code[i..];
    let n = rest.find(|c: char| !(c.is_alphanumeric() || c == '_')).unwrap_or(rest.len());
    &rest[..n]
}

/// Inline modules (`mod name { ... }`) of a file: (byte range of the body, name), outer first.
fn inline_modules(code: &str) -> Vec<(std::ops::Range<usize>, String)> {
    let mut out = Vec::new();
    let mut from = 0;
    while let Some(at) = code[from..].find("mod ").map(|a| a + from) {
        from = at + 4;
        if at > 0 && code[..at].ends_with(|c: char| c.is_alphanumeric() || c == '_') {
            continue;
        }
        let name_at = from + (code[from..].len() - code[from..].trim_start().len());
        let name = ident_at(code, name_at);
        let after = code[name_at + name.len()..].trim_start();
        if name.is_empty() || !after.starts_with('{') {
            continue;
        }
        let open = code.len() - after.len();
        let mut depth = 0;
        let mut end = code.len();
        for (k, ch) in code[open..].char_indices() {
            depth += match ch {
                '{' => 1,
                '}' => -1,
                _ => 0,
            };
            if depth == 0 {
                end = open + k;
                break;
            }
        }
        out.push((open..end, name.to_owned()));
    }
    out
}

/// Every path that starts with `crate`, `super` or `self` in `code`, with its byte offset;
/// `use` groups expand (`super::{a, b::c}` is `super::a` and `super::b::c`).
fn relative_paths(code: &str) -> Vec<(usize, Vec<String>)> {
    /// The paths of `text` (one path or a group's item) after the segments `prefix`.
    fn expand(text: &str, prefix: &[String], out: &mut Vec<Vec<String>>) {
        let text = text.trim_start();
        if let Some(group) = text.strip_prefix('{') {
            let (mut depth, mut start) = (0, 0);
            for (k, ch) in group.char_indices() {
                match ch {
                    '{' => depth += 1,
                    '}' if depth == 0 => {
                        expand(&group[start..k], prefix, out);
                        return;
                    }
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        expand(&group[start..k], prefix, out);
                        start = k + 1;
                    }
                    _ => {}
                }
            }
            return;
        }
        let seg = ident_at(text, 0);
        if seg.is_empty() {
            // `*` or the end of a group: the path so far.
            out.push(prefix.to_vec());
            return;
        }
        let mut path = prefix.to_vec();
        path.push(seg.to_owned());
        let rest = text[seg.len()..].trim_start();
        match rest.strip_prefix("::") {
            Some(rest) => expand(rest, &path, out),
            None => out.push(path),
        }
    }
    let mut out = Vec::new();
    for key in ["crate", "super", "self"] {
        for (at, _) in code.match_indices(key) {
            let before = code[..at].trim_end();
            let whole_word = !code[..at].ends_with(|c: char| c.is_alphanumeric() || c == '_')
                && !code[at + key.len()..].starts_with(|c: char| c.is_alphanumeric() || c == '_');
            // The first segment only: `super::super::x` is one path.
            if !whole_word || before.ends_with("::") {
                continue;
            }
            let mut paths = Vec::new();
            expand(&code[at..], &[], &mut paths);
            out.extend(paths.into_iter().filter(|p| p.len() > 1).map(|p| (at, p)));
        }
    }
    out
}

/// The module a path names, from module `current`: the longest prefix of the path that is a
/// module of `modules` (`None` for `super` above the root).
fn resolve(
    current: &[String],
    path: &[String],
    modules: &BTreeSet<Vec<String>>,
) -> Option<Vec<String>> {
    let mut at = match path[0].as_str() {
        "crate" => Vec::new(),
        "self" => current.to_vec(),
        "super" => current.split_last()?.1.to_vec(),
        _ => return None,
    };
    for seg in &path[1..] {
        match seg.as_str() {
            "super" => {
                at.pop()?;
            }
            "self" => {}
            name => {
                let mut next = at.clone();
                next.push(name.to_owned());
                if !modules.contains(&next) {
                    break;
                }
                at = next;
            }
        }
    }
    Some(at)
}

/// One crate's module dependencies between siblings at every depth: `a::x -> a::y` when code
/// in `a::x` (or below it) names `a::y` (or something below it) through a `crate::`,
/// `super::` or `self::` path. A module naming its own parent or child is no edge.
#[derive(Debug, Default)]
struct ModuleGraph {
    /// `from -> to`, module paths joined by `::`.
    edges: BTreeMap<String, BTreeSet<String>>,
    /// Where each edge is named: (file below `src/`, line).
    sources: BTreeMap<(String, String), BTreeSet<(PathBuf, usize)>>,
}

impl ModuleGraph {
    /// The graph of a crate whose `src/` holds `files` (path below `src/`, text).
    fn of_files(files: &[(PathBuf, String)]) -> Self {
        let mut modules = BTreeSet::new();
        let mut parsed = Vec::new();
        for (rel, text) in files {
            let module = file_module(rel);
            let code = code_only(text);
            let inline = inline_modules(&code);
            // Each inline module's path: the file's module and the inline modules around it.
            let paths: Vec<Vec<String>> = (0..inline.len())
                .map(|k| {
                    let mut p = module.clone();
                    let (range, name) = &inline[k];
                    p.extend(
                        inline[..k]
                            .iter()
                            .filter(|(r, _)| r.start < range.start && range.end <= r.end)
                            .map(|(_, n)| n.clone()),
                    );
                    p.push(name.clone());
                    p
                })
                .collect();
            modules.insert(module.clone());
            modules.extend(paths.iter().cloned());
            parsed.push((rel, module, code, inline, paths));
        }
        let mut graph = ModuleGraph::default();
        for (rel, module, code, inline, paths) in &parsed {
            for (at, path) in relative_paths(code) {
                // The innermost inline module around `at`, else the file's module.
                let current = inline
                    .iter()
                    .zip(paths)
                    .filter(|((r, _), _)| r.contains(&at))
                    .map(|(_, p)| p)
                    .max_by_key(|p| p.len())
                    .unwrap_or(module);
                let Some(target) = resolve(current, &path, &modules) else { continue };
                let k = current.iter().zip(&target).take_while(|(a, b)| a == b).count();
                if k == current.len() || k == target.len() {
                    continue;
                }
                let (from, to) = (current[..=k].join("::"), target[..=k].join("::"));
                let line = code[..at].matches('\n').count() + 1;
                graph.edges.entry(from.clone()).or_default().insert(to.clone());
                graph.sources.entry((from, to)).or_default().insert((rel.to_path_buf(), line));
            }
        }
        graph
    }

    /// The graph of the crate whose sources are in `src`.
    fn of_crate(src: &Path) -> Self {
        let files: Vec<(PathBuf, String)> = rust_files(src)
            .into_iter()
            .map(|f| {
                let text = std::fs::read_to_string(&f).expect("readable source");
                (f.strip_prefix(src).expect("below src").to_path_buf(), text)
            })
            .collect();
        Self::of_files(&files)
    }

    /// Every cycle: the strongly connected components of more than one module, each sorted.
    fn cycles(&self) -> Vec<Vec<String>> {
        // Tarjan's algorithm.
        struct State<'g> {
            edges: &'g BTreeMap<String, BTreeSet<String>>,
            index: BTreeMap<&'g str, (usize, usize)>,
            stack: Vec<&'g str>,
            on_stack: BTreeSet<&'g str>,
            out: Vec<Vec<String>>,
        }
        fn visit<'g>(n: &'g str, s: &mut State<'g>) {
            let i = s.index.len();
            s.index.insert(n, (i, i));
            s.stack.push(n);
            s.on_stack.insert(n);
            let edges = s.edges;
            for m in edges.get(n).into_iter().flatten() {
                let low = if !s.index.contains_key(m.as_str()) {
                    visit(m, s);
                    s.index[m.as_str()].1
                } else if s.on_stack.contains(m.as_str()) {
                    s.index[m.as_str()].0
                } else {
                    continue;
                };
                let e = s.index.get_mut(n).expect("visited");
                e.1 = e.1.min(low);
            }
            if s.index[n].0 == s.index[n].1 {
                let mut scc = Vec::new();
                while let Some(m) = s.stack.pop() {
                    s.on_stack.remove(m);
                    scc.push(m.to_owned());
                    if m == n {
                        break;
                    }
                }
                if scc.len() > 1 {
                    scc.sort();
                    s.out.push(scc);
                }
            }
        }
        let mut s = State {
            edges: &self.edges,
            index: BTreeMap::new(),
            stack: Vec::new(),
            on_stack: BTreeSet::new(),
            out: Vec::new(),
        };
        for n in self.edges.keys() {
            if !s.index.contains_key(n.as_str()) {
                visit(n, &mut s);
            }
        }
        s.out.sort();
        s.out
    }

    /// A cycle's edges with the files (below `src`) and lines that name them, one per line.
    fn describe(&self, cycle: &[String], src: &Path) -> String {
        let mut lines = Vec::new();
        for ((from, to), files) in &self.sources {
            if cycle.contains(from) && cycle.contains(to) {
                let files: Vec<String> =
                    files.iter().map(|(f, l)| format!("{}:{l}", src.join(f).display())).collect();
                lines.push(format!("  {from} -> {to}: {}", files.join(", ")));
            }
        }
        lines.join("\n")
    }
}

#[test]
fn no_module_cycles() {
    let mut dirs: Vec<PathBuf> = library_crates();
    dirs.push(root().join("xtask"));
    let (mut cycles, mut known) = (Vec::new(), BTreeSet::new());
    for d in dirs {
        let name = d.strip_prefix(root()).expect("below the root").display().to_string();
        let src = d.join("src");
        let graph = ModuleGraph::of_crate(&src);
        let shown = src.strip_prefix(root()).expect("below the root");
        for c in graph.cycles() {
            let listed = KNOWN_CYCLES.iter().position(|(k, m)| *k == name && *m == c);
            match listed {
                Some(i) => {
                    known.insert(i);
                }
                None => cycles.push(format!(
                    "{name}: {}\n{}",
                    c.join(" <-> "),
                    graph.describe(&c, shown)
                )),
            }
        }
    }
    let gone: Vec<_> =
        (0..KNOWN_CYCLES.len()).filter(|i| !known.contains(i)).map(|i| KNOWN_CYCLES[i]).collect();
    assert!(
        cycles.is_empty(),
        "module cycles (each edge with the files naming it):\n{}",
        cycles.join("\n")
    );
    assert!(gone.is_empty(), "these KNOWN_CYCLES are gone; remove them from the list: {gone:?}");
}

/// The graph of synthetic sources, `(path below src/, text)`.
fn graph_of(files: &[(&str, &str)]) -> ModuleGraph {
    let files: Vec<(PathBuf, String)> =
        files.iter().map(|(p, t)| (PathBuf::from(p), (*t).to_owned())).collect();
    ModuleGraph::of_files(&files)
}

#[test]
fn the_cycle_finder_finds_nested_cycles() {
    // `a::x` and `a::y` name each other through `crate::` paths, one inside a `use` group.
    let g = graph_of(&[
        ("lib.rs", "mod a;\nmod b;\n"),
        ("a/mod.rs", "mod x;\nmod y;\npub use self::x::f;\n"),
        ("a/x.rs", "pub fn f() { crate::a::y::g() }\n"),
        ("a/y.rs", "use crate::{b, a::x::{self, f}};\npub fn g() {}\n"),
        ("b.rs", "pub fn h() {}\n"),
    ]);
    assert_eq!(g.cycles(), vec![vec!["a::x".to_owned(), "a::y".to_owned()]]);
    let text = g.describe(&g.cycles()[0], Path::new("src"));
    assert!(text.contains("a::x -> a::y: src/a/x.rs:1"), "{text}");
    assert!(text.contains("a::y -> a::x: src/a/y.rs:1"), "{text}");
}

#[test]
fn the_cycle_finder_finds_super_cycles() {
    // Three siblings in a ring through `super::` paths (one from a test module, two levels
    // up); comments and strings naming modules are no dependency.
    let g = graph_of(&[
        ("main.rs", "mod m;\n"),
        ("m.rs", "mod p;\nmod q;\nmod r;\n"),
        ("m/p.rs", "use super::q::Q;\n// super::r::R\n"),
        ("m/q.rs", "pub struct Q;\nfn f() { super::r::g(\"super::p\") }\n"),
        (
            "m/r.rs",
            "pub fn g(_: &str) {}\n#[cfg(test)]\nmod tests {\n    use super::*;\n    use super::super::p;\n}\n",
        ),
    ]);
    assert_eq!(g.cycles(), vec![vec!["m::p".to_owned(), "m::q".to_owned(), "m::r".to_owned()]]);
}

#[test]
fn the_cycle_finder_passes_acyclic_graphs() {
    // Parents and children name each other (`self::`, `super::`, re-exports) and siblings name
    // each other one way only: no cycle.
    let g = graph_of(&[
        ("lib.rs", "mod a;\nmod b;\npub use a::A;\nuse crate::b::B;\n"),
        ("a.rs", "mod x;\npub struct A;\npub use self::x::X;\nuse crate::b::B;\n"),
        (
            "a/x.rs",
            "pub struct X(super::A, crate::A);\n#[cfg(test)]\nmod tests {\n    use super::*;\n}\n",
        ),
        (
            "b.rs",
            "pub struct B;\nfn f(_: &'static str, _: char) { let _ = ('{', r#\"crate::a\"#); }\n",
        ),
    ]);
    assert_eq!(g.edges.get("b"), None, "{g:?}");
    assert_eq!(g.edges["a"], BTreeSet::from(["b".to_owned()]));
    assert!(g.cycles().is_empty(), "{g:?}");
}
