//! Pins docs/ARCHITECTURE.md's payload table to the code: the page said EngineFrame 752 B,
//! FrameReport 120 B, LungFrame 320 B and "layout v4" long after the `const` assertions in
//! `ipc-types/src/lib.rs` said 784, 128, 336 and v5 (issue 33, item 6: docs that cannot drift).
//!
//! What is checked: every row of the `| Payload | Bytes | … |` table against `size_of`, with every
//! type below present once; the `Layout version: vN` line against [`LAYOUT_VERSION`]; every
//! versioned type name the page quotes (`lungdyn.EngineFrame.v5`); and any size the prose quotes
//! as "`EngineFrame` 784 B" or "`EngineFrame` is 784 B".

use std::mem::size_of;
use std::path::PathBuf;

use ipc_types::{
    ControlPacket, ControlReply, EngineFrame, FrameReport, HopStamps, LungFrame, TrackerFrame,
    LAYOUT_VERSION,
};

/// The types the table must list, with their sizes as compiled. A new payload is added here and
/// to the table together.
const TYPES: [(&str, usize); 7] = [
    ("TrackerFrame", size_of::<TrackerFrame>()),
    ("EngineFrame", size_of::<EngineFrame>()),
    ("LungFrame", size_of::<LungFrame>()),
    ("FrameReport", size_of::<FrameReport>()),
    ("ControlPacket", size_of::<ControlPacket>()),
    ("ControlReply", size_of::<ControlReply>()),
    ("HopStamps", size_of::<HopStamps>()),
];

const DOC: &str = "docs/ARCHITECTURE.md";

fn doc_path() -> PathBuf {
    PathBuf::from(env!("CARGO_MANIFEST_DIR"))
        .join("..")
        .join(DOC)
}

fn read_doc() -> String {
    let path = doc_path();
    std::fs::read_to_string(&path).unwrap_or_else(|e| panic!("reading {}: {e}", path.display()))
}

fn cells(line: &str) -> Vec<String> {
    let t = line.trim();
    let t = t.strip_prefix('|').unwrap_or(t);
    let t = t.strip_suffix('|').unwrap_or(t);
    t.split('|').map(|c| c.trim().to_string()).collect()
}

/// Line indices (0-based) of the payload table's rows, header and separator excluded.
fn table_rows(lines: &[&str]) -> Option<Vec<usize>> {
    let header = lines.iter().position(|l| {
        let c = cells(l);
        l.trim_start().starts_with('|') && c.len() >= 2 && c[0] == "Payload" && c[1] == "Bytes"
    })?;
    let first = header + 2; // after the `|---|---:|` separator
    Some(
        (first..lines.len())
            .take_while(|&i| lines[i].trim_start().starts_with('|'))
            .collect(),
    )
}

/// Every disagreement between `doc` (the text of docs/ARCHITECTURE.md) and the code, each naming
/// the line, the row or phrase, and both numbers.
fn problems(doc: &str) -> Vec<String> {
    let lines: Vec<&str> = doc.lines().collect();
    let mut out = Vec::new();

    // The table.
    let rows = table_rows(&lines).unwrap_or_else(|| {
        out.push(format!(
            "{DOC}: no payload table (a `| Payload | Bytes | ... |` header) found"
        ));
        Vec::new()
    });
    let mut seen: Vec<&'static str> = Vec::new();
    for &i in &rows {
        let c = cells(lines[i]);
        let name = c[0].trim_matches('`');
        let at = format!("{DOC}:{}", i + 1);
        let Some(bytes) = c.get(1) else {
            out.push(format!("{at}: row `{name}` has no Bytes cell"));
            continue;
        };
        let Some((known, size)) = TYPES.iter().copied().find(|(n, _)| *n == name) else {
            out.push(format!(
                "{at}: row `{name}` is not a type this test knows (add it to TYPES in {})",
                file!()
            ));
            continue;
        };
        if seen.contains(&name) {
            out.push(format!("{at}: row `{name}` appears twice"));
        }
        seen.push(known);
        match bytes.parse::<usize>() {
            Ok(b) if b == size => {}
            Ok(b) => out.push(format!(
                "{at}: row `{name}` says {b} B, size_of::<{name}>() is {size} B"
            )),
            Err(_) => out.push(format!(
                "{at}: row `{name}`: Bytes cell {bytes:?} is not a number (size_of::<{name}>() is {size} B)"
            )),
        }
    }
    if !rows.is_empty() {
        for (name, size) in TYPES {
            if !seen.contains(&name) {
                out.push(format!(
                    "{DOC}: the payload table has no row `{name}` (size_of::<{name}>() is {size} B)"
                ));
            }
        }
    }

    // The layout version line.
    let version_lines: Vec<usize> = (0..lines.len())
        .filter(|&i| lines[i].trim_start().starts_with("Layout version:"))
        .collect();
    if version_lines.len() != 1 {
        out.push(format!(
            "{DOC}: expected one `Layout version: vN` line, found {} (LAYOUT_VERSION is {LAYOUT_VERSION})",
            version_lines.len()
        ));
    }
    for &i in &version_lines {
        let rest = lines[i].trim_start()["Layout version:".len()..].trim_start();
        let digits: String = rest
            .strip_prefix('v')
            .unwrap_or("")
            .chars()
            .take_while(char::is_ascii_digit)
            .collect();
        match digits.parse::<u32>() {
            Ok(v) if v == LAYOUT_VERSION => {}
            Ok(v) => out.push(format!(
                "{DOC}:{}: `Layout version` says v{v}, LAYOUT_VERSION is {LAYOUT_VERSION}",
                i + 1
            )),
            Err(_) => out.push(format!(
                "{DOC}:{}: `Layout version:` is not followed by vN (LAYOUT_VERSION is {LAYOUT_VERSION})",
                i + 1
            )),
        }
    }

    // Versioned type names quoted anywhere (`lungdyn.EngineFrame.v5`).
    for (i, line) in lines.iter().enumerate() {
        let mut from = 0;
        while let Some(k) = line[from..].find("lungdyn.") {
            let start = from + k;
            let rest = &line[start + "lungdyn.".len()..];
            let ident: String = rest
                .chars()
                .take_while(|c| c.is_ascii_alphanumeric() || *c == '_')
                .collect();
            let after = &rest[ident.len()..];
            if let Some(v) = after.strip_prefix(".v") {
                let digits: String = v.chars().take_while(char::is_ascii_digit).collect();
                if let Ok(n) = digits.parse::<u32>() {
                    if n != LAYOUT_VERSION {
                        out.push(format!(
                            "{DOC}:{}: type name `lungdyn.{ident}.v{n}` says v{n}, LAYOUT_VERSION is {LAYOUT_VERSION}",
                            i + 1
                        ));
                    }
                }
            }
            from = start + "lungdyn.".len();
        }
    }

    // Sizes quoted in prose: "`EngineFrame` 784 B", "EngineFrame is 784 B", "... 784 bytes".
    for (i, line) in lines.iter().enumerate() {
        if rows.contains(&i) {
            continue;
        }
        for (name, size) in TYPES {
            for (k, _) in line.match_indices(name) {
                if line[..k]
                    .chars()
                    .next_back()
                    .is_some_and(|c| c.is_ascii_alphanumeric() || c == '_')
                {
                    continue;
                }
                if let Some(b) = quoted_size(&line[k + name.len()..]) {
                    if b != size {
                        out.push(format!(
                            "{DOC}:{}: prose says `{name}` is {b} B, size_of::<{name}>() is {size} B",
                            i + 1
                        ));
                    }
                }
            }
        }
    }
    out
}

/// The size right after a type name: "` is 784 B", " 784 B", " of 784 bytes"; None otherwise.
fn quoted_size(after: &str) -> Option<usize> {
    let mut s = after.strip_prefix('`').unwrap_or(after).trim_start();
    for word in ["is ", "of ", "= ", ": "] {
        if let Some(r) = s.strip_prefix(word) {
            s = r.trim_start();
        }
    }
    let digits: String = s.chars().take_while(char::is_ascii_digit).collect();
    let n = digits.parse().ok()?;
    let unit = s[digits.len()..].trim_start();
    let is_b = unit.starts_with("bytes")
        || (unit.starts_with('B')
            && !unit[1..]
                .chars()
                .next()
                .is_some_and(|c| c.is_ascii_alphanumeric()));
    is_b.then_some(n)
}

#[test]
fn architecture_doc_payload_table_matches_the_code() {
    let found = problems(&read_doc());
    assert!(
        found.is_empty(),
        "{} disagrees with ipc-types (fix the page from the code):\n  {}",
        doc_path().display(),
        found.join("\n  ")
    );
}

// The check itself, on copies of the page made wrong on purpose.

/// The page with `name`'s row's Bytes cell replaced by `bytes`.
fn with_row_bytes(doc: &str, name: &str, bytes: &str) -> String {
    let lines: Vec<&str> = doc.lines().collect();
    let rows = table_rows(&lines).expect("the page has a payload table");
    let mut out: Vec<String> = lines.iter().map(|l| l.to_string()).collect();
    let i = *rows
        .iter()
        .find(|&&i| cells(lines[i])[0].trim_matches('`') == name)
        .expect("row present");
    let mut c = cells(lines[i]);
    c[1] = bytes.to_string();
    out[i] = format!("| {} |", c.join(" | "));
    out.join("\n")
}

#[test]
fn a_wrong_size_is_reported_with_its_row_and_both_numbers() {
    let wrong = with_row_bytes(&read_doc(), "EngineFrame", "752");
    let found = problems(&wrong);
    assert_eq!(found.len(), 1, "{found:#?}");
    let size = size_of::<EngineFrame>();
    assert!(
        found[0].contains(&format!(
            "row `EngineFrame` says 752 B, size_of::<EngineFrame>() is {size} B"
        )),
        "{}",
        found[0]
    );
}

#[test]
fn a_missing_row_an_unknown_row_and_a_non_number_are_reported() {
    let doc = read_doc();
    let lung_row = doc
        .lines()
        .find(|l| l.starts_with("| `LungFrame`"))
        .expect("LungFrame row");
    let wrong = doc.replace(lung_row, "| `Gizmo` | 8 | not a payload |");
    let wrong = with_row_bytes(&wrong, "HopStamps", "forty-eight");
    let found = problems(&wrong).join("\n");
    assert!(found.contains("no row `LungFrame`"), "{found}");
    assert!(
        found.contains("row `Gizmo` is not a type this test knows"),
        "{found}"
    );
    assert!(
        found.contains("row `HopStamps`: Bytes cell \"forty-eight\""),
        "{found}"
    );
}

#[test]
fn a_stale_layout_version_is_reported() {
    let doc = read_doc();
    let line = doc
        .lines()
        .find(|l| l.starts_with("Layout version:"))
        .expect("version line");
    let stale = LAYOUT_VERSION - 1;
    let found = problems(&doc.replace(line, &format!("Layout version: v{stale}")));
    assert_eq!(found.len(), 1, "{found:#?}");
    assert!(
        found[0].contains(&format!(
            "says v{stale}, LAYOUT_VERSION is {LAYOUT_VERSION}"
        )),
        "{}",
        found[0]
    );
}

#[test]
fn a_stale_type_name_or_prose_size_is_reported() {
    let wrong = format!(
        "{}\nThe renderer opens `lungdyn.FrameReport.v4`; an `EngineFrame` is 752 B, a TrackerFrame {} bytes.\n",
        read_doc(),
        size_of::<TrackerFrame>()
    );
    let found = problems(&wrong).join("\n");
    let size = size_of::<EngineFrame>();
    assert!(
        found.contains("`lungdyn.FrameReport.v4` says v4"),
        "{found}"
    );
    assert!(
        found.contains(&format!(
            "prose says `EngineFrame` is 752 B, size_of::<EngineFrame>() is {size} B"
        )),
        "{found}"
    );
    assert!(
        !found.contains("TrackerFrame"),
        "the TrackerFrame's size is right: {found}"
    );
}
