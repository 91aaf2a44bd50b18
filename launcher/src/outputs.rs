//! Output paths are checked before any work, so a bad one never costs a computation or leaves half
//! of a command's outputs written: the name and its extension, the folder (it must exist and take a
//! new file), an existing path that is not a regular file (a folder, a device, a FIFO, a socket, a
//! link to one: [`outfile::check`], the check every writer makes again when it writes), and two
//! outputs of one command that are the same file.

use std::path::{Path, PathBuf};

use anyhow::bail;

/// One output of a command: the flag that names it and its path.
#[derive(Debug, Clone, Copy)]
pub struct Output<'a> {
    /// The flag, e.g. `--plot`.
    pub flag: &'a str,
    /// The path given.
    pub path: &'a Path,
    /// Extensions it may have (lower case, without the dot); empty: any.
    pub extensions: &'a [&'a str],
}

/// Check `out` can be written: see the module doc. Writes and removes a probe file in its folder.
pub fn check(out: &Output) -> anyhow::Result<()> {
    let (flag, path) = (out.flag, out.path);
    // A device, FIFO, socket, folder or a link to one: the same refusal every writer gives
    // (outfile), said before any work rather than at the end.
    outfile::check(path).map_err(|e| anyhow::anyhow!("{flag} {e}"))?;
    if !out.extensions.is_empty() {
        let ext = path
            .extension()
            .and_then(|e| e.to_str())
            .map(|e| e.to_ascii_lowercase());
        if !ext.as_deref().is_some_and(|e| out.extensions.contains(&e)) {
            bail!(
                "{flag} {}: the file name must end in {}",
                path.display(),
                out.extensions
                    .iter()
                    .map(|e| format!(".{e}"))
                    .collect::<Vec<_>>()
                    .join(" or ")
            );
        }
    }
    if path.file_name().is_none() {
        bail!("{flag} {}: the path names no file", path.display());
    }
    let folder = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    if !folder.is_dir() {
        bail!(
            "{flag} {}: the folder {} does not exist (create it first)",
            path.display(),
            folder.display()
        );
    }
    let probe = folder.join(format!(".lungdyn-probe-{}", std::process::id()));
    match std::fs::OpenOptions::new()
        .write(true)
        .create_new(true)
        .open(&probe)
    {
        Ok(_) => {
            let _ = std::fs::remove_file(&probe);
        }
        Err(e) => bail!(
            "{flag} {}: cannot write in the folder {}: {e}",
            path.display(),
            folder.display()
        ),
    }
    Ok(())
}

/// Check every output (see [`check`]) and that no two are the same file; `also` are further files
/// an output implies (a plot's SVG beside its PNG), with the flag that implies them.
pub fn check_all(outputs: &[Output], also: &[(&str, PathBuf)]) -> anyhow::Result<()> {
    for o in outputs {
        check(o)?;
    }
    let mut seen: Vec<(&str, PathBuf)> = Vec::new();
    let all = outputs
        .iter()
        .map(|o| (o.flag, o.path.to_path_buf()))
        .chain(also.iter().map(|(f, p)| (*f, p.clone())));
    for (flag, path) in all {
        let key = normalise(&path);
        if let Some((other, _)) = seen.iter().find(|(_, p)| *p == key) {
            bail!(
                "{flag} {}: the same file as {other}: give each output its own path",
                path.display()
            );
        }
        seen.push((flag, key));
    }
    Ok(())
}

/// The path with its folder made absolute and canonical where it exists (so `a.csv` and `./a.csv`
/// are one file).
fn normalise(path: &Path) -> PathBuf {
    let folder = match path.parent() {
        Some(p) if !p.as_os_str().is_empty() => p.to_path_buf(),
        _ => PathBuf::from("."),
    };
    let folder = std::fs::canonicalize(&folder).unwrap_or(folder);
    match path.file_name() {
        Some(name) => folder.join(name),
        None => folder,
    }
}

/// Check the `--out` folder `dir` can take a command's files: create it, write and remove a probe
/// file.
pub fn check_writable(dir: &Path) -> anyhow::Result<()> {
    use anyhow::Context;
    if let Ok(meta) = std::fs::metadata(dir) {
        if !meta.is_dir() {
            use std::os::unix::fs::FileTypeExt;
            let t = meta.file_type();
            let what = if t.is_char_device() {
                "a character device"
            } else if t.is_block_device() {
                "a block device"
            } else if t.is_fifo() {
                "a FIFO (named pipe)"
            } else if t.is_socket() {
                "a socket"
            } else {
                "a file"
            };
            bail!(
                "--out {}: exists and is {what}, not a folder: give a folder to write into",
                dir.display()
            );
        }
    }
    std::fs::create_dir_all(dir)
        .with_context(|| format!("--out {}: cannot create the folder", dir.display()))?;
    let probe = dir.join(format!(".lungdyn-write-probe-{}", std::process::id()));
    std::fs::write(&probe, b"probe")
        .with_context(|| format!("--out {}: the folder is not writable", dir.display()))?;
    std::fs::remove_file(&probe).ok();
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn out<'a>(flag: &'a str, path: &'a Path, extensions: &'a [&'a str]) -> Output<'a> {
        Output {
            flag,
            path,
            extensions,
        }
    }

    #[test]
    fn bad_output_paths_are_refused_naming_flag_and_path() {
        let dir = std::env::temp_dir().join(format!("lungdyn-outputs-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let png = dir.join("p.png");
        assert!(check(&out("--plot", &png, &["png"])).is_ok());
        let cases: [(PathBuf, &[&str], &str); 5] = [
            (dir.join("p.jpg"), &["png"], "must end in .png"),
            (
                PathBuf::from("/proc/lungdyn.png"),
                &["png"],
                "cannot write in the folder /proc",
            ),
            (dir.join("no/dir/c.csv"), &[], "no/dir does not exist"),
            (dir.clone(), &[], "is a directory, not a regular file"),
            (PathBuf::from("/dev/null"), &[], "is a character device"),
        ];
        for (path, ext, words) in cases {
            let e = check(&out("--x", &path, ext)).unwrap_err().to_string();
            assert!(e.starts_with("--x ") && e.contains(words), "{e}");
            assert!(e.contains(&path.display().to_string()), "{e}");
        }
        // Two outputs that are one file.
        let csv = dir.join("c.csv");
        let same = dir.join(".").join("c.csv");
        let e = check_all(
            &[out("--out", &csv, &[]), out("--plot", &png, &["png"])],
            &[("--plot", same)],
        )
        .unwrap_err()
        .to_string();
        assert!(e.contains("the same file as --out"), "{e}");
        assert!(check_all(
            &[out("--out", &csv, &[]), out("--plot", &png, &["png"])],
            &[("--plot", png.with_extension("svg"))]
        )
        .is_ok());
        std::fs::remove_dir_all(&dir).ok();
    }
}

/// A new, empty folder `parent/stem-N` (the first N from 1 that does not exist yet), created now: where
/// a command writes when the person did not say where, so one run never overwrites another's output
/// (or a committed file).
pub fn new_folder(parent: &Path, stem: &str) -> anyhow::Result<PathBuf> {
    std::fs::create_dir_all(parent)
        .map_err(|e| anyhow::anyhow!("cannot create the folder {}: {e}", parent.display()))?;
    for n in 1..=100_000u32 {
        let dir = parent.join(format!("{stem}-{n}"));
        match std::fs::create_dir(&dir) {
            Ok(()) => return Ok(dir),
            Err(e) if e.kind() == std::io::ErrorKind::AlreadyExists => continue,
            Err(e) => bail!("cannot create the folder {}: {e}", dir.display()),
        }
    }
    bail!(
        "{} already holds 100000 {stem}-N folders: give --out",
        parent.display()
    )
}

#[cfg(test)]
mod new_folder_tests {
    use super::new_folder;

    #[test]
    fn each_call_makes_a_new_empty_folder_and_never_reuses_one() {
        let parent = std::env::temp_dir().join(format!("lungdyn-newfolder-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&parent);
        let a = new_folder(&parent, "tradeoff").unwrap();
        std::fs::write(a.join("x"), b"1").unwrap();
        let b = new_folder(&parent, "tradeoff").unwrap();
        assert_ne!(a, b);
        assert!(
            a.ends_with("tradeoff-1") && b.ends_with("tradeoff-2"),
            "{a:?} {b:?}"
        );
        assert_eq!(std::fs::read_dir(&b).unwrap().count(), 0);
        // A file where the parent should be: a clear error, not a panic.
        let blocked = parent.join("file");
        std::fs::write(&blocked, b"").unwrap();
        let e = new_folder(&blocked, "t").unwrap_err().to_string();
        assert!(e.contains("cannot create"), "{e}");
        std::fs::remove_dir_all(&parent).unwrap();
    }
}
