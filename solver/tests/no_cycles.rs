//! No top-level module of the library crates (solver, io) uses a module that uses it, directly
//! or through others: the `crate::` and root-reaching `super::` paths of every source file are
//! read, and the graph of top-level modules must have no strongly connected component with more
//! than one module (Tarjan's algorithm). The same holds inside every folder among its files (a
//! trait's module names none of its implementations either).

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// Every `.rs` file under `dir`.
fn sources(dir: &Path, out: &mut Vec<PathBuf>) {
    let mut entries: Vec<PathBuf> = std::fs::read_dir(dir)
        .unwrap()
        .map(|e| e.unwrap().path())
        .collect();
    entries.sort();
    for p in entries {
        if p.is_dir() {
            sources(&p, out);
        } else if p.extension().is_some_and(|e| e == "rs") {
            out.push(p);
        }
    }
}

fn identifier(s: &str) -> &str {
    let end = s
        .find(|c: char| !(c.is_alphanumeric() || c == '_'))
        .unwrap_or(s.len());
    &s[..end]
}

/// The top-level modules named right after each `crate::` in `text` (braced groups included).
fn crate_paths(text: &str, deps: &mut BTreeSet<String>) {
    for (i, _) in text.match_indices("crate::") {
        // `preston_solver::` or `xcrate::` are not this crate.
        if text[..i]
            .chars()
            .next_back()
            .is_some_and(|c| c.is_alphanumeric() || c == '_')
        {
            continue;
        }
        let rest = &text[i + "crate::".len()..];
        if let Some(group) = rest.strip_prefix('{') {
            let mut depth = 0usize;
            let mut start = 0;
            for (k, c) in group.char_indices() {
                match c {
                    '{' => depth += 1,
                    '}' if depth == 0 => {
                        deps.insert(identifier(group[start..k].trim()).to_string());
                        break;
                    }
                    '}' => depth -= 1,
                    ',' if depth == 0 => {
                        deps.insert(identifier(group[start..k].trim()).to_string());
                        start = k + 1;
                    }
                    _ => {}
                }
            }
        } else {
            deps.insert(identifier(rest).to_string());
        }
    }
}

/// The top-level modules reached by `super::` chains that climb to the crate root from a module
/// `depth` levels below it.
fn super_paths(text: &str, depth: usize, deps: &mut BTreeSet<String>) {
    let mut rest = text;
    while let Some(i) = rest.find("super::") {
        let mut tail = &rest[i..];
        let mut n = 0;
        while let Some(t) = tail.strip_prefix("super::") {
            n += 1;
            tail = t;
        }
        if n == depth {
            deps.insert(identifier(tail).to_string());
        }
        rest = tail;
    }
}

/// Top-level module -> the top-level modules it uses.
fn module_graph(src: &Path) -> BTreeMap<String, BTreeSet<String>> {
    module_graph_in(src, None)
}

/// The file modules of the folder `folder` (`influence`, `machine/gcode`) of the crate at `src`
/// -> those of them each uses (`crate::influence::x` and `super::x` paths; other `crate::` paths are
/// left out).
fn folder_graph(src: &Path, folder: &str) -> BTreeMap<String, BTreeSet<String>> {
    module_graph_in(&src.join(folder), Some(&folder.replace('/', "::")))
}

/// [`module_graph`] of `src`, or of the folder module `folder` (its path from the crate root)
/// whose files are under `src`.
fn module_graph_in(src: &Path, folder: Option<&str>) -> BTreeMap<String, BTreeSet<String>> {
    let mut files = Vec::new();
    sources(src, &mut files);
    let mut graph: BTreeMap<String, BTreeSet<String>> = BTreeMap::new();
    for f in files {
        let rel: Vec<String> = f
            .strip_prefix(src)
            .unwrap()
            .iter()
            .map(|c| c.to_string_lossy().into_owned())
            .collect();
        if rel.len() == 1 && (rel[0] == "lib.rs" || rel[0] == "main.rs") {
            continue;
        }
        // In a folder, its files are the modules; each sub-folder is checked on its own.
        if folder.is_some() && (rel.len() > 1 || rel[0] == "mod.rs") {
            continue;
        }
        let top = rel[0].trim_end_matches(".rs").to_string();
        // Module depth below the root: `a.rs` and `a/mod.rs` are 1, `a/b.rs` is 2.
        let depth = if rel.last().is_some_and(|l| l == "mod.rs") {
            rel.len() - 1
        } else {
            rel.len()
        };
        let mut text: String = std::fs::read_to_string(&f)
            .unwrap()
            .lines()
            .filter(|l| !l.trim_start().starts_with("//"))
            .collect::<Vec<_>>()
            .join("\n");
        if let Some(folder) = folder {
            // Paths into the folder read as paths from its root; every other crate path is left
            // out.
            text = text
                .replace("crate::", "other_crate_path::")
                .replace(&format!("other_crate_path::{folder}::"), "crate::");
        }
        let mut deps = BTreeSet::new();
        crate_paths(&text, &mut deps);
        super_paths(&text, depth, &mut deps);
        deps.remove(&top);
        graph.entry(top).or_default().extend(deps);
    }
    let modules: BTreeSet<String> = graph.keys().cloned().collect();
    for deps in graph.values_mut() {
        deps.retain(|d| modules.contains(d));
    }
    graph
}

/// Strongly connected components with more than one module (Tarjan).
fn cycles(graph: &BTreeMap<String, BTreeSet<String>>) -> Vec<Vec<String>> {
    struct Tarjan<'a> {
        graph: &'a BTreeMap<String, BTreeSet<String>>,
        index: BTreeMap<&'a str, usize>,
        low: BTreeMap<&'a str, usize>,
        stack: Vec<&'a str>,
        on_stack: BTreeSet<&'a str>,
        out: Vec<Vec<String>>,
    }
    impl<'a> Tarjan<'a> {
        fn visit(&mut self, v: &'a str) {
            let i = self.index.len();
            self.index.insert(v, i);
            self.low.insert(v, i);
            self.stack.push(v);
            self.on_stack.insert(v);
            for w in &self.graph[v] {
                let w = w.as_str();
                if !self.index.contains_key(w) {
                    self.visit(w);
                    let lw = self.low[w];
                    let lv = self.low.get_mut(v).unwrap();
                    *lv = (*lv).min(lw);
                } else if self.on_stack.contains(w) {
                    let iw = self.index[w];
                    let lv = self.low.get_mut(v).unwrap();
                    *lv = (*lv).min(iw);
                }
            }
            if self.low[v] == self.index[v] {
                let mut comp = Vec::new();
                while let Some(w) = self.stack.pop() {
                    self.on_stack.remove(w);
                    comp.push(w.to_string());
                    if w == v {
                        break;
                    }
                }
                if comp.len() > 1 {
                    comp.sort();
                    self.out.push(comp);
                }
            }
        }
    }
    let mut t = Tarjan {
        graph,
        index: BTreeMap::new(),
        low: BTreeMap::new(),
        stack: Vec::new(),
        on_stack: BTreeSet::new(),
        out: Vec::new(),
    };
    for v in graph.keys() {
        if !t.index.contains_key(v.as_str()) {
            t.visit(v);
        }
    }
    t.out
}

fn crate_src(name: &str) -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join(name)
        .join("src")
}

#[test]
fn the_checker_finds_a_planted_cycle() {
    let dir = std::env::temp_dir().join(format!("preston-cycles-{}", std::process::id()));
    std::fs::create_dir_all(dir.join("b")).unwrap();
    std::fs::write(dir.join("lib.rs"), "pub mod a;\npub mod b;\n").unwrap();
    std::fs::write(dir.join("a.rs"), "use crate::{c, b::x};\n").unwrap();
    std::fs::write(dir.join("c.rs"), "// use crate::a;\n").unwrap();
    std::fs::write(dir.join("b/mod.rs"), "pub mod y;\n").unwrap();
    std::fs::write(dir.join("b/y.rs"), "use super::super::a::f;\n").unwrap();
    let g = module_graph(&dir);
    let _ = std::fs::remove_dir_all(&dir);
    assert_eq!(cycles(&g), vec![vec!["a".to_string(), "b".to_string()]]);
}

/// Every folder below `src`, as a path from it (`influence`, `machine/gcode`).
fn folders(src: &Path, prefix: &str, out: &mut Vec<String>) {
    let mut entries: Vec<PathBuf> = std::fs::read_dir(src)
        .unwrap()
        .map(|e| e.unwrap().path())
        .filter(|p| p.is_dir())
        .collect();
    entries.sort();
    for d in entries {
        let name = d.file_name().unwrap().to_string_lossy().into_owned();
        let path = if prefix.is_empty() {
            name
        } else {
            format!("{prefix}/{name}")
        };
        folders(&d, &path, out);
        out.push(path);
    }
}

#[test]
fn the_folder_checker_finds_a_planted_cycle_and_ignores_other_crate_paths() {
    let dir = std::env::temp_dir().join(format!("preston-folder-cycles-{}", std::process::id()));
    std::fs::create_dir_all(dir.join("f")).unwrap();
    std::fs::write(
        dir.join("f/mod.rs"),
        "pub mod p;\npub mod q;\npub mod surface;\n",
    )
    .unwrap();
    std::fs::write(
        dir.join("f/p.rs"),
        "use super::q::X;\nuse crate::surface::S;\n",
    )
    .unwrap();
    std::fs::write(dir.join("f/q.rs"), "use crate::f::{p::Y, other};\n").unwrap();
    std::fs::write(dir.join("f/surface.rs"), "use super::super::p::Z;\n").unwrap();
    let g = folder_graph(&dir, "f");
    let _ = std::fs::remove_dir_all(&dir);
    assert_eq!(cycles(&g), vec![vec!["p".to_string(), "q".to_string()]]);
    assert!(g["p"].contains("q") && !g["p"].contains("surface"), "{g:?}");
}

#[test]
fn inside_every_folder_no_module_uses_one_that_uses_it() {
    for name in ["solver", "io"] {
        let src = crate_src(name);
        let mut all = Vec::new();
        folders(&src, "", &mut all);
        assert!(!all.is_empty(), "{name}: no folders read");
        for folder in all {
            let c = cycles(&folder_graph(&src, &folder));
            assert!(
                c.is_empty(),
                "{name}/src/{folder}: modules that use each other: {c:?}"
            );
        }
    }
}

#[test]
fn no_module_of_solver_or_io_uses_a_module_that_uses_it() {
    for name in ["solver", "io"] {
        let g = module_graph(&crate_src(name));
        assert!(g.len() > 5, "{name}: {} modules read", g.len());
        let c = cycles(&g);
        assert!(
            c.is_empty(),
            "{name}/src: modules that use each other: {c:?}"
        );
    }
}
