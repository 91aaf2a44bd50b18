//! Every relative link and image in README.md, CHANGELOG.md and docs/**/*.md names a file or folder
//! that exists, and every `#anchor` into a Markdown file names one of its headings (GitHub's slugs).
//! The README is a first screen and links into docs/; when a section moves or a file is renamed,
//! this test names the link that no longer resolves instead of a reader finding it broken.
//!
//! Reads files only (no GPU, no processes): `cargo test --release -p lungdyn-tests --test doc_links`.

use std::collections::HashSet;
use std::path::{Component, Path, PathBuf};

fn repo_root() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .canonicalize()
        .expect("repository root")
}

/// README.md, CHANGELOG.md and every .md under docs/, sorted.
fn markdown_files(root: &Path) -> Vec<PathBuf> {
    let mut out = vec![root.join("README.md"), root.join("CHANGELOG.md")];
    let mut stack = vec![root.join("docs")];
    while let Some(dir) = stack.pop() {
        let entries = std::fs::read_dir(&dir).unwrap_or_else(|e| panic!("{}: {e}", dir.display()));
        for entry in entries {
            let path = entry.expect("directory entry").path();
            if path.is_dir() {
                stack.push(path);
            } else if path.extension().is_some_and(|x| x == "md") {
                out.push(path);
            }
        }
    }
    out.sort();
    out
}

/// The text's lines with code blocks emptied: fenced blocks and indented blocks (4 spaces after a
/// blank line or another indented line), so a `# comment` in a shell example is not a heading.
/// Lines are kept (numbering).
fn block_lines(text: &str) -> Vec<String> {
    let mut out = Vec::new();
    let mut fenced = false;
    let mut indented = false;
    let mut prev_blank = true;
    for line in text.lines() {
        let trimmed = line.trim_start();
        if trimmed.starts_with("```") || trimmed.starts_with("~~~") {
            fenced = !fenced;
            out.push(String::new());
            prev_blank = false;
            continue;
        }
        let blank = trimmed.is_empty();
        indented = !fenced && line.starts_with("    ") && (prev_blank || indented);
        if fenced || indented {
            out.push(String::new());
        } else {
            out.push(line.to_string());
        }
        prev_blank = blank;
    }
    out
}

/// As `block_lines`, with `code spans` emptied too, so a `[--flag](…)`-looking command is not a
/// link.
fn prose_lines(text: &str) -> Vec<String> {
    block_lines(text)
        .iter()
        .map(|l| strip_code_spans(l))
        .collect()
}

fn strip_code_spans(line: &str) -> String {
    let mut out = String::new();
    let mut rest = line;
    while let Some(start) = rest.find('`') {
        out.push_str(&rest[..start]);
        let ticks = rest[start..].chars().take_while(|&c| c == '`').count();
        let fence = &rest[start..start + ticks];
        let after = &rest[start + ticks..];
        match after.find(fence) {
            Some(end) => rest = &after[end + ticks..],
            None => {
                out.push_str(&rest[start..]);
                return out;
            }
        }
    }
    out.push_str(rest);
    out
}

/// GitHub's anchor for a heading: inline markup dropped, lower case, anything but letters, digits,
/// `-`, `_` and spaces removed, spaces made `-`; a repeated slug gets `-1`, `-2`, …
fn slugs(text: &str) -> HashSet<String> {
    let mut seen = HashSet::new();
    for line in block_lines(text) {
        let t = line.trim_start_matches(' ');
        if line.len() - t.len() > 3 || !t.starts_with('#') {
            continue;
        }
        let hashes = t.chars().take_while(|&c| c == '#').count();
        if hashes > 6 || !(t[hashes..].is_empty() || t[hashes..].starts_with(' ')) {
            continue;
        }
        let title = t[hashes..].trim().trim_end_matches('#').trim();
        // [text](target) -> text
        let mut plain = String::new();
        let mut rest = title;
        while let Some(k) = rest.find("](") {
            let open = rest[..k].rfind('[').unwrap_or(k);
            plain.push_str(&rest[..open]);
            plain.push_str(&rest[open + 1..k]);
            rest = match rest[k..].find(')') {
                Some(close) => &rest[k + close + 1..],
                None => "",
            };
        }
        plain.push_str(rest);
        let base: String = plain
            .replace('`', "")
            .to_lowercase()
            .chars()
            .filter(|c| c.is_alphanumeric() || matches!(c, '-' | '_' | ' '))
            .map(|c| if c == ' ' { '-' } else { c })
            .collect();
        let mut slug = base.clone();
        let mut n = 0;
        while seen.contains(&slug) {
            n += 1;
            slug = format!("{base}-{n}");
        }
        seen.insert(slug);
    }
    seen
}

/// (line number, target) of every `[text](target)` and `![alt](target)` in the prose.
fn links(text: &str) -> Vec<(usize, String)> {
    let mut out = Vec::new();
    for (i, line) in prose_lines(text).iter().enumerate() {
        let mut rest = line.as_str();
        while let Some(k) = rest.find("](") {
            let after = &rest[k + 2..];
            let after = after.strip_prefix('<').unwrap_or(after);
            let end = after
                .find(|c: char| c == ')' || c == '>' || c.is_whitespace())
                .unwrap_or(after.len());
            out.push((i + 1, after[..end].to_string()));
            rest = &after[end..];
        }
    }
    out
}

/// `a/b/../c` -> `a/c` without touching the file system (the target may not exist).
fn normalize(path: &Path) -> PathBuf {
    let mut out = PathBuf::new();
    for c in path.components() {
        match c {
            Component::ParentDir => {
                out.pop();
            }
            Component::CurDir => {}
            other => out.push(other.as_os_str()),
        }
    }
    out
}

/// Every broken link in `file`, each naming the file, line and target.
fn problems(root: &Path, file: &Path) -> Vec<String> {
    let text = std::fs::read_to_string(file).unwrap_or_else(|e| panic!("{}: {e}", file.display()));
    let shown = file
        .strip_prefix(root)
        .unwrap_or(file)
        .display()
        .to_string();
    let mut out = Vec::new();
    for (line, target) in links(&text) {
        let external = ["http://", "https://", "mailto:", "ftp://"]
            .iter()
            .any(|p| target.starts_with(p));
        if external || target.is_empty() {
            continue;
        }
        let (path_part, anchor) = match target.split_once('#') {
            Some((p, a)) => (p, Some(a)),
            None => (target.as_str(), None),
        };
        let resolved = if path_part.is_empty() {
            file.to_path_buf()
        } else if path_part.starts_with('/') {
            out.push(format!(
                "{shown}:{line}: `{target}` is absolute; use a relative path"
            ));
            continue;
        } else {
            normalize(&file.parent().expect("a file's folder").join(path_part))
        };
        if !resolved.starts_with(root) || !resolved.exists() {
            out.push(format!(
                "{shown}:{line}: `{target}` does not resolve (looked for {})",
                resolved.strip_prefix(root).unwrap_or(&resolved).display()
            ));
            continue;
        }
        if let Some(anchor) = anchor {
            if resolved.extension().is_some_and(|x| x == "md") {
                let target_text = std::fs::read_to_string(&resolved).expect("linked file");
                if !slugs(&target_text).contains(anchor) {
                    out.push(format!(
                        "{shown}:{line}: `{target}`: no heading in {} has the anchor #{anchor}",
                        resolved.strip_prefix(root).unwrap_or(&resolved).display()
                    ));
                }
            }
        }
    }
    out
}

#[test]
fn every_relative_link_in_the_readme_changelog_and_docs_resolves() {
    let root = repo_root();
    let files = markdown_files(&root);
    let mut all = Vec::new();
    let mut checked = 0;
    for file in &files {
        assert!(file.exists(), "{} is missing", file.display());
        checked += links(&std::fs::read_to_string(file).unwrap()).len();
        all.extend(problems(&root, file));
    }
    assert!(checked > 0, "no links found: the parser is broken");
    assert!(
        all.is_empty(),
        "{} broken link(s):\n{}",
        all.len(),
        all.join("\n")
    );
}

#[test]
fn the_checker_sees_links_anchors_and_code() {
    let text = "# A title: `code` (seed §8.3)\n## A title: code (seed §8.3)\n\n\
                See [x](docs/a.md#b) and ![img](images/p.png \"t\") but not `[y](z.md)`.\n\n    \
                lungdyn x [--json](not-a-link)\n";
    let l: Vec<String> = links(text).into_iter().map(|(_, t)| t).collect();
    assert_eq!(l, ["docs/a.md#b", "images/p.png"]);
    let s = slugs(text);
    assert!(s.contains("a-title-code-seed-83"), "{s:?}");
    assert!(s.contains("a-title-code-seed-83-1"), "{s:?}");
    assert_eq!(
        normalize(Path::new("docs/../README.md")),
        PathBuf::from("README.md")
    );
}

/// Most lines the README may have: a first screen (the two commands), what lungdyn does with pictures,
/// and links; a topic's detail belongs in `docs/` (issue 33: it had grown to 855 lines, with a
/// changelog of branch names in its remote section).
const README_MAX_LINES: usize = 300;

#[test]
fn the_readme_stays_a_first_screen_and_links() {
    let root = repo_root();
    let text = std::fs::read_to_string(root.join("README.md")).expect("README.md");
    let lines = text.lines().count();
    assert!(
        lines <= README_MAX_LINES,
        "README.md has {lines} lines, more than {README_MAX_LINES}: move a section's detail into docs/ \
         and leave a line and a link"
    );
    let first_screen: Vec<&str> = text.lines().take(40).collect();
    for command in ["./run demo", "./run test"] {
        assert!(
            first_screen.iter().any(|l| l.trim() == command),
            "the README's first 40 lines must give `{command}` on a line of its own"
        );
    }
}
