//! No module cycles inside a crate: a parser of `mod` and `use` paths, the module graph and
//! its cycle finder, with the finder's own tests.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

use super::{library_crates, root, rust_files};

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
