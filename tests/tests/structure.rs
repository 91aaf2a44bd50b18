//! The house rules a newcomer relies on (issue 33), held by a test rather than by review:
//!
//! - **No production function over 150 lines** anywhere in the workspace (tests, benches, examples,
//!   the test-support crates and `#[cfg(test)]` code aside). The functions that were longer when
//!   the rule came are listed in [`LONG_FUNCTIONS`] with the length they had: a listed one may only
//!   shrink, a fixed one must leave the list, and any other function over the limit fails.
//! - **No import cycle among a crate's files** through `crate::` or `super::` paths (comments and
//!   doc links aside, and a module naming its own children aside). [`CYCLES`] is empty: a new one
//!   fails.
//! - **The command line stays a front**: `cli/` at most [`MAX_CLI_LINES`] lines.
//!
//! The source is read by a small lexer of our own (comments, strings, characters and lifetimes
//! told apart, so braces are counted only in code): `syn` would need proc-macro2's span-locations
//! feature for line numbers, which would rebuild the whole workspace's macros.

use std::collections::{BTreeMap, BTreeSet};
use std::path::{Path, PathBuf};

/// The longest a production function may be, lines from its `fn` to its closing brace.
const MAX_LINES: usize = 150;

/// Functions over [`MAX_LINES`] when the rule came (file, name, the most lines it may have): debt
/// to pay down, never to grow.
const LONG_FUNCTIONS: &[(&str, &str, usize)] = &[];

/// Import cycles among a crate's files tolerated (each the files of one strongly connected
/// component): none. The six there were when the rule came are broken (the launcher's check moved
/// to `outputs`, one clock trait, iceoryx2's root folder beside the instance files, the lung
/// builder in its own file, fit-motion's inputs and report in their own modules, the renderer's
/// session, options and display options in theirs). List one here only with its reason.
const CYCLES: &[&[&str]] = &[];

/// Workspace members whose `src/` is production code (the test-support crates `tests`,
/// `tests/needs` and the `bench` crate are left out, as the rule leaves tests and benches out).
fn production_crates(root: &Path) -> Vec<PathBuf> {
    let manifest = std::fs::read_to_string(root.join("Cargo.toml")).unwrap();
    let members = manifest
        .lines()
        .find(|l| l.starts_with("members"))
        .expect("workspace members");
    members
        .split('"')
        .skip(1)
        .step_by(2)
        .filter(|m| !["tests", "tests/needs", "bench"].contains(m))
        .map(|m| root.join(m))
        .collect()
}

fn rust_files(dir: &Path, out: &mut Vec<PathBuf>) {
    let Ok(entries) = std::fs::read_dir(dir) else {
        return;
    };
    for e in entries.flatten() {
        let p = e.path();
        if p.is_dir() {
            rust_files(&p, out);
        } else if p.extension().is_some_and(|x| x == "rs") {
            out.push(p);
        }
    }
}

/// The source with every comment and the contents of every string and character literal
/// replaced by spaces (newlines kept, so line numbers hold): what is left is code, whose braces
/// can be counted.
fn code_only(src: &str) -> Vec<u8> {
    let b = src.as_bytes();
    let mut out = b.to_vec();
    let blank = |out: &mut Vec<u8>, from: usize, to: usize| {
        for c in &mut out[from..to] {
            if *c != b'\n' {
                *c = b' ';
            }
        }
    };
    let mut i = 0;
    while i < b.len() {
        let rest = &b[i..];
        if rest.starts_with(b"//") {
            let end = rest
                .iter()
                .position(|&c| c == b'\n')
                .map_or(b.len(), |n| i + n);
            blank(&mut out, i, end);
            i = end;
        } else if rest.starts_with(b"/*") {
            let (mut depth, mut j) = (0usize, i);
            while j < b.len() {
                if b[j..].starts_with(b"/*") {
                    depth += 1;
                    j += 2;
                } else if b[j..].starts_with(b"*/") {
                    depth -= 1;
                    j += 2;
                    if depth == 0 {
                        break;
                    }
                } else {
                    j += 1;
                }
            }
            blank(&mut out, i, j);
            i = j;
        } else if let Some((start, end)) = raw_string(b, i) {
            blank(&mut out, start, end);
            i = end;
        } else if b[i] == b'"' && !ident_byte(b, i.wrapping_sub(1)) || rest.starts_with(b"b\"") {
            let open = if b[i] == b'"' { i } else { i + 1 };
            let mut j = open + 1;
            while j < b.len() && b[j] != b'"' {
                j += if b[j] == b'\\' { 2 } else { 1 };
            }
            blank(&mut out, open + 1, j.min(b.len()));
            i = j + 1;
        } else if b[i] == b'\'' {
            // A character literal ('a', '\n', '\'', 'é') or a lifetime / label ('a, 'static).
            let j = if b.get(i + 1) == Some(&b'\\') {
                let mut j = i + 2;
                while j < b.len() && b[j] != b'\'' {
                    j += 1;
                }
                Some(j)
            } else {
                let width = src[i + 1..].chars().next().map_or(1, char::len_utf8);
                (b.get(i + 1 + width) == Some(&b'\'')).then_some(i + 1 + width)
            };
            match j {
                Some(j) => {
                    blank(&mut out, i + 1, j);
                    i = j + 1;
                }
                None => i += 1,
            }
        } else {
            i += 1;
        }
    }
    out
}

/// A raw string (`r"…"`, `r#"…"#`, `br#"…"#`) starting at `i`: (contents start, end after it).
fn raw_string(b: &[u8], i: usize) -> Option<(usize, usize)> {
    if ident_byte(b, i.wrapping_sub(1)) {
        return None;
    }
    let mut j = i;
    if b.get(j) == Some(&b'b') {
        j += 1;
    }
    if b.get(j) != Some(&b'r') {
        return None;
    }
    j += 1;
    let hashes = b[j..].iter().take_while(|&&c| c == b'#').count();
    j += hashes;
    if b.get(j) != Some(&b'"') {
        return None;
    }
    let start = j + 1;
    let mut close = vec![b'"'];
    close.extend(std::iter::repeat_n(b'#', hashes));
    let end = b[start..]
        .windows(close.len())
        .position(|w| w == close.as_slice())
        .map_or(b.len(), |n| start + n + close.len());
    Some((start, end))
}

fn ident_byte(b: &[u8], i: usize) -> bool {
    b.get(i)
        .is_some_and(|c| c.is_ascii_alphanumeric() || *c == b'_')
}

/// The index after the brace matching the `{` at `open`.
fn matching(code: &[u8], open: usize) -> usize {
    let mut depth = 0usize;
    for (k, &c) in code.iter().enumerate().skip(open) {
        match c {
            b'{' => depth += 1,
            b'}' => {
                depth -= 1;
                if depth == 0 {
                    return k + 1;
                }
            }
            _ => {}
        }
    }
    code.len()
}

/// Blank every item under `#[cfg(test)]` (a test module, a test-only function or impl).
fn without_test_code(mut code: Vec<u8>) -> Vec<u8> {
    let mut from = 0;
    while let Some(at) = find(&code, b"#[cfg(test)]", from) {
        let item = at + b"#[cfg(test)]".len();
        let end_of_item = code[item..]
            .iter()
            .position(|&c| c == b'{' || c == b';')
            .map(|n| item + n);
        let end = match end_of_item {
            Some(k) if code[k] == b'{' => matching(&code, k),
            Some(k) => k + 1,
            None => code.len(),
        };
        for c in &mut code[at..end] {
            if *c != b'\n' {
                *c = b' ';
            }
        }
        from = end;
    }
    code
}

fn find(hay: &[u8], needle: &[u8], from: usize) -> Option<usize> {
    hay.get(from..)?
        .windows(needle.len())
        .position(|w| w == needle)
        .map(|n| from + n)
}

fn line_of(code: &[u8], at: usize) -> usize {
    code[..at].iter().filter(|&&c| c == b'\n').count() + 1
}

/// Every function with a body in `code`: (name, line of its `fn`, lines to its closing brace).
fn functions(code: &[u8]) -> Vec<(String, usize, usize)> {
    let mut found = Vec::new();
    let mut from = 0;
    while let Some(at) = find(code, b"fn ", from) {
        from = at + 3;
        if ident_byte(code, at.wrapping_sub(1)) {
            continue;
        }
        let name: String = code[at + 3..]
            .iter()
            .skip_while(|c| c.is_ascii_whitespace())
            .take_while(|c| c.is_ascii_alphanumeric() || **c == b'_')
            .map(|&c| c as char)
            .collect();
        if name.is_empty() {
            // `fn(` in a type: a function pointer, no body.
            continue;
        }
        let Some(k) = code[from..]
            .iter()
            .position(|&c| c == b'{' || c == b';')
            .map(|n| from + n)
        else {
            break;
        };
        if code[k] == b';' {
            continue;
        }
        let end = matching(code, k);
        let first = line_of(code, at);
        found.push((
            name,
            first,
            line_of(code, end.saturating_sub(1)) - first + 1,
        ));
    }
    found
}

fn workspace_root() -> PathBuf {
    Path::new(env!("CARGO_MANIFEST_DIR")).join("..")
}

fn relative(root: &Path, p: &Path) -> String {
    p.strip_prefix(root).unwrap_or(p).display().to_string()
}

/// The most lines the command line's crate (`cli/`, every `.rs` file, tests included) may have: it is
/// the front of the libraries (the launcher's `lungdyn-launcher`, lung-bake's tools), not the system.
const MAX_CLI_LINES: usize = 6_000;

#[test]
fn the_command_line_crate_stays_a_thin_front() {
    let root = workspace_root();
    let mut files = Vec::new();
    rust_files(&root.join("cli"), &mut files);
    let lines: Vec<(usize, String)> = files
        .iter()
        .map(|f| {
            let n = std::fs::read_to_string(f).unwrap().lines().count();
            (n, relative(&root, f))
        })
        .collect();
    let total: usize = lines.iter().map(|(n, _)| n).sum();
    assert!(files.len() > 5, "cli/ has its files: {lines:?}");
    let mut largest = lines.clone();
    largest.sort_unstable_by(|a, b| b.cmp(a));
    largest.truncate(5);
    assert!(
        total <= MAX_CLI_LINES,
        "cli/ holds {total} lines, more than {MAX_CLI_LINES}: put what is not parsing a command and \
         printing its result into the library it belongs to (launcher/, engine/bake, ...); largest \
         files: {largest:?}"
    );
}

#[test]
fn no_production_function_is_over_150_lines_but_the_listed_debt() {
    let root = workspace_root().canonicalize().unwrap();
    let mut long: BTreeMap<(String, String), usize> = BTreeMap::new();
    let mut counted = 0;
    for krate in production_crates(&root) {
        let mut files = Vec::new();
        rust_files(&krate.join("src"), &mut files);
        for f in files {
            let code = without_test_code(code_only(&std::fs::read_to_string(&f).unwrap()));
            for (name, _, lines) in functions(&code) {
                counted += 1;
                if lines > MAX_LINES {
                    let key = (relative(&root, &f), name);
                    let e = long.entry(key).or_default();
                    *e = (*e).max(lines);
                }
            }
        }
    }
    assert!(counted > 2000, "the scan found only {counted} functions");
    let mut problems = Vec::new();
    for ((file, name), lines) in &long {
        match LONG_FUNCTIONS
            .iter()
            .find(|(f, n, _)| f == file && n == name)
        {
            None => problems.push(format!(
                "{file}: fn {name} is {lines} lines, over {MAX_LINES}: split it into named steps"
            )),
            Some((_, _, allowed)) if lines > allowed => problems.push(format!(
                "{file}: fn {name} grew to {lines} lines (listed at {allowed}, over {MAX_LINES} \
                 already): split it rather than grow it"
            )),
            Some(_) => {}
        }
    }
    for (file, name, _) in LONG_FUNCTIONS {
        if !long.contains_key(&(file.to_string(), name.to_string())) {
            problems.push(format!(
                "{file}: fn {name} is no longer over {MAX_LINES} lines (or is gone): take it off \
                 LONG_FUNCTIONS in tests/tests/structure.rs"
            ));
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

/// The module path (`["a", "b"]` for `src/a/b.rs` or `src/a/b/mod.rs`; `[]` for the crate root) of
/// a file under `src`, and whether it is a crate root at all.
fn module_of(src: &Path, file: &Path) -> Vec<String> {
    let rel = file.strip_prefix(src).unwrap();
    let mut parts: Vec<String> = rel
        .iter()
        .map(|p| p.to_string_lossy().into_owned())
        .collect();
    let last = parts.pop().unwrap();
    match last.as_str() {
        "lib.rs" | "main.rs" | "mod.rs" => {}
        other => parts.push(other.trim_end_matches(".rs").to_string()),
    }
    parts
}

/// The file of the deepest module of `path` (module segments from the crate root) that exists.
fn file_of(files: &BTreeMap<Vec<String>, PathBuf>, path: &[String]) -> Option<Vec<String>> {
    (0..=path.len())
        .rev()
        .map(|n| path[..n].to_vec())
        .find(|p| files.contains_key(p))
}

/// The module paths a file's code names through `crate::` and `super::` (use trees expanded).
fn named_paths(code: &[u8], me: &[String]) -> Vec<Vec<String>> {
    let text = String::from_utf8_lossy(code);
    let mut out = Vec::new();
    for start in ["crate::", "super::"] {
        let mut from = 0;
        while let Some(at) = text[from..].find(start).map(|n| from + n) {
            from = at + start.len();
            if ident_byte(code, at.wrapping_sub(1)) || code.get(at.wrapping_sub(2)) == Some(&b':') {
                continue;
            }
            let mut base: Vec<String> = Vec::new();
            let mut rest = &text[at..];
            if let Some(r) = rest.strip_prefix("crate::") {
                rest = r;
            } else {
                base = me.to_vec();
                while let Some(r) = rest.strip_prefix("super::") {
                    base.pop();
                    rest = r;
                }
            }
            tree(rest, &base, &mut out);
        }
    }
    out
}

/// Expand one use tree (`a::b::{c, d::e}` or a plain path) after `base`.
fn tree(text: &str, base: &[String], out: &mut Vec<Vec<String>>) {
    let mut path = base.to_vec();
    let mut rest = text.trim_start();
    loop {
        let seg: String = rest
            .chars()
            .take_while(|c| c.is_alphanumeric() || *c == '_')
            .collect();
        if seg.is_empty() {
            break;
        }
        rest = &rest[seg.len()..];
        path.push(seg);
        match rest.strip_prefix("::") {
            Some(r) => rest = r.trim_start(),
            None => break,
        }
    }
    if let Some(inner) = rest.strip_prefix('{') {
        let mut depth = 0usize;
        let mut item = String::new();
        for c in inner.chars() {
            match c {
                '{' => depth += 1,
                '}' if depth == 0 => break,
                '}' => depth -= 1,
                ',' if depth == 0 => {
                    tree(&item, &path, out);
                    item.clear();
                    continue;
                }
                _ => {}
            }
            item.push(c);
        }
        tree(&item, &path, out);
    } else {
        out.push(path);
    }
}

/// Strongly connected components of more than one node (Tarjan).
fn cycles(edges: &BTreeMap<usize, BTreeSet<usize>>, n: usize) -> Vec<Vec<usize>> {
    struct T<'a> {
        edges: &'a BTreeMap<usize, BTreeSet<usize>>,
        index: Vec<Option<usize>>,
        low: Vec<usize>,
        on: Vec<bool>,
        stack: Vec<usize>,
        next: usize,
        out: Vec<Vec<usize>>,
    }
    fn visit(t: &mut T, v: usize) {
        t.index[v] = Some(t.next);
        t.low[v] = t.next;
        t.next += 1;
        t.stack.push(v);
        t.on[v] = true;
        for &w in t.edges.get(&v).into_iter().flatten() {
            match t.index[w] {
                None => {
                    visit(t, w);
                    t.low[v] = t.low[v].min(t.low[w]);
                }
                Some(iw) if t.on[w] => t.low[v] = t.low[v].min(iw),
                _ => {}
            }
        }
        if Some(t.low[v]) == t.index[v] {
            let mut comp = Vec::new();
            while let Some(w) = t.stack.pop() {
                t.on[w] = false;
                comp.push(w);
                if w == v {
                    break;
                }
            }
            if comp.len() > 1 {
                comp.sort();
                t.out.push(comp);
            }
        }
    }
    let mut t = T {
        edges,
        index: vec![None; n],
        low: vec![0; n],
        on: vec![false; n],
        stack: Vec::new(),
        next: 0,
        out: Vec::new(),
    };
    for v in 0..n {
        if t.index[v].is_none() {
            visit(&mut t, v);
        }
    }
    t.out
}

/// Each crate's import cycles, as sorted lists of workspace-relative files.
fn import_cycles(root: &Path) -> Vec<Vec<String>> {
    let mut all = Vec::new();
    for krate in production_crates(root) {
        let src = krate.join("src");
        let mut paths = Vec::new();
        rust_files(&src, &mut paths);
        paths.sort();
        // Each crate root (lib.rs, main.rs, a src/bin file) is a tree of its own; lib.rs's tree
        // is the one the modules hang from.
        let files: BTreeMap<Vec<String>, PathBuf> = paths
            .iter()
            .filter(|p| !p.starts_with(src.join("bin")) && !p.ends_with("main.rs"))
            .map(|p| (module_of(&src, p), p.clone()))
            .collect();
        let ids: Vec<&Vec<String>> = files.keys().collect();
        let mut edges: BTreeMap<usize, BTreeSet<usize>> = BTreeMap::new();
        for (i, (module, path)) in files.iter().enumerate() {
            let code = without_test_code(code_only(&std::fs::read_to_string(path).unwrap()));
            for named in named_paths(&code, module) {
                let Some(target) = file_of(&files, &named) else {
                    continue;
                };
                // Itself, or a module naming its own children, is no cycle.
                if target.starts_with(module) {
                    continue;
                }
                let j = ids.iter().position(|m| **m == target).unwrap();
                edges.entry(i).or_default().insert(j);
            }
        }
        for comp in cycles(&edges, ids.len()) {
            let mut names: Vec<String> = comp
                .iter()
                .map(|&k| relative(root, &files[ids[k]]))
                .collect();
            names.sort();
            all.push(names);
        }
    }
    all
}

#[test]
fn no_crate_has_an_import_cycle_among_its_files_but_the_listed_ones() {
    let root = workspace_root().canonicalize().unwrap();
    let found = import_cycles(&root);
    let mut problems = Vec::new();
    for c in &found {
        let listed = CYCLES
            .iter()
            .any(|l| c.iter().all(|f| l.contains(&f.as_str())));
        if !listed {
            problems.push(format!(
                "an import cycle through crate:: or super:: paths: {} — move what they share to \
                 a module both use, one way",
                c.join(" <-> ")
            ));
        }
    }
    for l in CYCLES {
        if !found
            .iter()
            .any(|c| l.iter().all(|f| c.contains(&f.to_string())))
        {
            problems.push(format!(
                "the cycle {} is broken (or smaller): update CYCLES in tests/tests/structure.rs",
                l.join(" <-> ")
            ));
        }
    }
    assert!(problems.is_empty(), "{}", problems.join("\n"));
}

#[test]
fn the_lexer_counts_braces_in_code_only() {
    let src = "fn a() {\n    let s = \"}{\"; // }\n    let c = '}';\n    /* { */\n    let r = r#\"}\"#;\n    x::<'a>();\n}\n#[cfg(test)]\nmod tests {\n    fn hidden() {}\n}\nfn b(f: fn(u8)) -> u8;\n";
    let code = without_test_code(code_only(src));
    let f = functions(&code);
    assert_eq!(f, vec![("a".to_string(), 1, 7)]);
    let mut out = Vec::new();
    tree("a::{b, c::{d, e}}, f", &["m".to_string()], &mut out);
    assert_eq!(
        out,
        vec![
            vec!["m", "a", "b"],
            vec!["m", "a", "c", "d"],
            vec!["m", "a", "c", "e"]
        ]
        .into_iter()
        .map(|v| v.into_iter().map(String::from).collect::<Vec<_>>())
        .collect::<Vec<_>>()
    );
    let me = vec!["x".to_string(), "y".to_string()];
    let named = named_paths(b"use super::z::W; crate::q::r();", &me);
    assert_eq!(
        named,
        vec![
            vec!["q".to_string(), "r".to_string()],
            vec!["x".to_string(), "z".to_string(), "W".to_string()]
        ]
    );
    let mut edges = BTreeMap::new();
    edges.insert(0, BTreeSet::from([1]));
    edges.insert(1, BTreeSet::from([2]));
    edges.insert(2, BTreeSet::from([0]));
    edges.insert(3, BTreeSet::from([0]));
    assert_eq!(cycles(&edges, 4), vec![vec![0, 1, 2]]);
}
