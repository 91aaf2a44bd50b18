//! The one way lungdyn writes a file a person named (`--out`, `--plot`, `--stats-json`, snapshots,
//! kernels, calibrations, …).
//!
//! 1. **The target is checked** ([`check`]): a path that exists and is not a regular file — a
//!    character or block device, a FIFO, a socket, a folder, or a symbolic link to one of those or to
//!    nothing — is refused with [`WriteError::NotAFile`], naming the path and what it is, and nothing
//!    is written. Renaming a finished file over `/dev/null` (or a twin made with `mknod`) would
//!    silently turn the device into a regular file; writing into a FIFO would block or feed another
//!    process. A symbolic link to a regular file is followed: the file it points to is replaced and
//!    the link kept, which is what a person who linked `latest.toml` to a file expects.
//! 2. **The file is written atomically** ([`write_atomically`], [`Staged`]): into a temporary sibling
//!    (same folder, so the rename cannot cross file systems), flushed and synced, then renamed over
//!    the target after checking it again. An interrupted or failed run leaves the old file whole and
//!    removes its temporary file.
//!
//! A race where someone replaces the target between the second check and the rename is not guarded
//! against (no portable rename-if-regular exists); the checks are for mistakes, not attackers.
//!
//! This crate sits below every crate that writes (lung-model, tracker-bridge, renderer, cli) and
//! depends on nothing of lungdyn, so there is one checked path instead of one per crate.

use std::fs::File;
use std::io::BufWriter;
use std::os::unix::fs::FileTypeExt;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicU64, Ordering};

/// What a path that is not a regular file is.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Kind {
    /// A folder.
    Directory,
    /// A character device (`/dev/null`, a terminal, a serial port).
    CharDevice,
    /// A block device (a disk).
    BlockDevice,
    /// A named pipe.
    Fifo,
    /// A Unix-domain socket.
    Socket,
    /// A symbolic link whose target does not exist.
    DanglingLink,
    /// Anything else the OS reports.
    Other,
}

impl std::fmt::Display for Kind {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        f.write_str(match self {
            Kind::Directory => "a directory",
            Kind::CharDevice => "a character device",
            Kind::BlockDevice => "a block device",
            Kind::Fifo => "a FIFO (named pipe)",
            Kind::Socket => "a socket",
            Kind::DanglingLink => "a symbolic link to nothing",
            Kind::Other => "not a regular file",
        })
    }
}

/// Errors writing a file.
#[derive(Debug, thiserror::Error)]
pub enum WriteError {
    /// The target exists and is not a regular file; nothing was written.
    #[error(
        "{}: exists and is {kind}{}, not a regular file: refusing to replace it (nothing was written; \
         give the path of a regular file)",
        path.display(),
        via.as_ref().map(|t| format!(" (a symbolic link to {})", t.display())).unwrap_or_default()
    )]
    NotAFile {
        /// The path given.
        path: PathBuf,
        /// What it is.
        kind: Kind,
        /// Where the symbolic link points, if the path is one.
        via: Option<PathBuf>,
    },
    /// The path ends in no file name (`/`, `..`, empty).
    #[error("{}: the path names no file", path.display())]
    NoFileName {
        /// The path given.
        path: PathBuf,
    },
    /// The OS refused (permissions, a missing folder, a full disk, …).
    #[error("cannot write {}: {source}", path.display())]
    Io {
        /// The path given.
        path: PathBuf,
        /// The OS error.
        source: std::io::Error,
    },
}

impl WriteError {
    /// The path given.
    pub fn path(&self) -> &Path {
        match self {
            WriteError::NotAFile { path, .. }
            | WriteError::NoFileName { path }
            | WriteError::Io { path, .. } => path,
        }
    }
}

fn kind_of(t: std::fs::FileType) -> Kind {
    if t.is_dir() {
        Kind::Directory
    } else if t.is_char_device() {
        Kind::CharDevice
    } else if t.is_block_device() {
        Kind::BlockDevice
    } else if t.is_fifo() {
        Kind::Fifo
    } else if t.is_socket() {
        Kind::Socket
    } else {
        Kind::Other
    }
}

/// Check that `path` may be written (see the crate doc) and return the file to replace: `path`
/// itself, or the regular file a symbolic link at `path` points to. Nothing is created.
pub fn check(path: &Path) -> Result<PathBuf, WriteError> {
    let io = |source| WriteError::Io {
        path: path.to_path_buf(),
        source,
    };
    if path.file_name().is_none() {
        return Err(WriteError::NoFileName {
            path: path.to_path_buf(),
        });
    }
    let meta = match std::fs::symlink_metadata(path) {
        Ok(m) => m,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => return Ok(path.to_path_buf()),
        Err(e) => return Err(io(e)),
    };
    let not_a_file = |kind, via| WriteError::NotAFile {
        path: path.to_path_buf(),
        kind,
        via,
    };
    if meta.file_type().is_symlink() {
        let via = std::fs::read_link(path).map_err(io)?;
        return match std::fs::metadata(path) {
            Ok(m) if m.is_file() => std::fs::canonicalize(path).map_err(io),
            Ok(m) => Err(not_a_file(kind_of(m.file_type()), Some(via))),
            Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
                Err(not_a_file(Kind::DanglingLink, Some(via)))
            }
            Err(e) => Err(io(e)),
        };
    }
    if meta.is_file() {
        Ok(path.to_path_buf())
    } else {
        Err(not_a_file(kind_of(meta.file_type()), None))
    }
}

/// A temporary sibling of a checked target, for writers that want a path to draw into (plotters,
/// several files put in place together). [`Staged::commit`] renames it over the target after
/// checking the target again; dropped uncommitted, the temporary file is removed.
#[derive(Debug)]
pub struct Staged {
    given: PathBuf,
    tmp: PathBuf,
    committed: bool,
}

static SERIAL: AtomicU64 = AtomicU64::new(0);

impl Staged {
    /// Check `path` ([`check`]) and name a temporary sibling of the file it will replace. The
    /// temporary name keeps the target's extension, so a writer that picks its format by extension
    /// (an image encoder) writes the right one. Nothing is created.
    pub fn new(path: &Path) -> Result<Self, WriteError> {
        let target = check(path)?;
        let name = target
            .file_name()
            .ok_or_else(|| WriteError::NoFileName {
                path: path.to_path_buf(),
            })?
            .to_string_lossy();
        let ext = target
            .extension()
            .map(|e| format!(".{}", e.to_string_lossy()))
            .unwrap_or_default();
        let tmp = target.with_file_name(format!(
            ".{name}.tmp-{}-{}{ext}",
            std::process::id(),
            SERIAL.fetch_add(1, Ordering::Relaxed)
        ));
        Ok(Self {
            given: path.to_path_buf(),
            tmp,
            committed: false,
        })
    }

    /// Where to write the contents.
    pub fn path(&self) -> &Path {
        &self.tmp
    }

    /// The path the file will have (as given).
    pub fn target(&self) -> &Path {
        &self.given
    }

    /// Check the target again and rename the temporary file over it; returns the path as given.
    pub fn commit(mut self) -> Result<PathBuf, WriteError> {
        let target = check(&self.given)?;
        std::fs::rename(&self.tmp, &target).map_err(|source| WriteError::Io {
            path: self.given.clone(),
            source,
        })?;
        self.committed = true;
        Ok(std::mem::take(&mut self.given))
    }
}

impl Drop for Staged {
    fn drop(&mut self) {
        if !self.committed {
            let _ = std::fs::remove_file(&self.tmp);
        }
    }
}

/// Write through `body` into a temporary sibling of `path`, sync it, then rename it over `path`
/// (see the crate doc: a target that is not a regular file is refused before anything is written).
pub fn write_atomically(
    path: &Path,
    body: impl FnOnce(&mut BufWriter<File>) -> std::io::Result<()>,
) -> Result<(), WriteError> {
    let staged = Staged::new(path)?;
    let io = |source| WriteError::Io {
        path: path.to_path_buf(),
        source,
    };
    let mut w = BufWriter::new(File::create(staged.path()).map_err(io)?);
    body(&mut w).map_err(io)?;
    let file = w.into_inner().map_err(|e| io(e.into_error()))?;
    file.sync_all().map_err(io)?;
    drop(file);
    staged.commit()?;
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::Write;
    use std::process::Command;

    fn dir(name: &str) -> PathBuf {
        let d = std::env::temp_dir().join(format!("outfile-{name}-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        std::fs::create_dir_all(&d).unwrap();
        d
    }

    fn leftovers(d: &Path) -> Vec<String> {
        std::fs::read_dir(d)
            .unwrap()
            .map(|e| e.unwrap().file_name().to_string_lossy().into_owned())
            .filter(|n| n.contains(".tmp-"))
            .collect()
    }

    fn run(cmd: &str, args: &[&str]) {
        let s = Command::new(cmd).args(args).status().unwrap();
        assert!(s.success(), "{cmd} {args:?} failed (mknod needs root)");
    }

    #[test]
    fn writes_new_and_replaces_regular_files_atomically() {
        let d = dir("regular");
        let p = d.join("a.toml");
        write_atomically(&p, |w| w.write_all(b"one")).unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"one");
        write_atomically(&p, |w| w.write_all(b"two")).unwrap();
        assert_eq!(std::fs::read(&p).unwrap(), b"two");
        // A failing body leaves the old file whole and no temporary file behind.
        let e = write_atomically(&p, |w| {
            w.write_all(b"half")?;
            Err(std::io::Error::other("disk on fire"))
        })
        .unwrap_err();
        assert!(e.to_string().contains("disk on fire"), "{e}");
        assert_eq!(std::fs::read(&p).unwrap(), b"two");
        assert!(leftovers(&d).is_empty(), "{:?}", leftovers(&d));
        // A link to a regular file: the file is replaced, the link kept.
        let link = d.join("latest.toml");
        std::os::unix::fs::symlink(&p, &link).unwrap();
        write_atomically(&link, |w| w.write_all(b"three")).unwrap();
        assert!(std::fs::symlink_metadata(&link)
            .unwrap()
            .file_type()
            .is_symlink());
        assert_eq!(std::fs::read(&p).unwrap(), b"three");
        std::fs::remove_dir_all(&d).ok();
    }

    #[test]
    fn special_files_are_refused_naming_path_and_kind_and_left_alone() {
        let d = dir("special");
        let null = d.join("mynull");
        run("mknod", &[null.to_str().unwrap(), "c", "1", "3"]);
        let fifo = d.join("fifo");
        run("mkfifo", &[fifo.to_str().unwrap()]);
        let sock = d.join("sock");
        let _listener = std::os::unix::net::UnixListener::bind(&sock).unwrap();
        let folder = d.join("folder");
        std::fs::create_dir(&folder).unwrap();
        let to_null = d.join("to_null");
        std::os::unix::fs::symlink(&null, &to_null).unwrap();
        let dangling = d.join("dangling");
        std::os::unix::fs::symlink(d.join("nothing"), &dangling).unwrap();
        let cases = [
            (&null, Kind::CharDevice, "a character device"),
            (&fifo, Kind::Fifo, "a FIFO"),
            (&sock, Kind::Socket, "a socket"),
            (&folder, Kind::Directory, "a directory"),
            (&to_null, Kind::CharDevice, "a symbolic link to"),
            (&dangling, Kind::DanglingLink, "a symbolic link to nothing"),
        ];
        for (path, kind, words) in cases {
            let before = std::fs::symlink_metadata(path).unwrap().file_type();
            let mut ran = false;
            let e = write_atomically(path, |w| {
                ran = true;
                w.write_all(b"x")
            })
            .unwrap_err();
            assert!(!ran, "{}: the body ran", path.display());
            let text = e.to_string();
            assert!(
                matches!(&e, WriteError::NotAFile { kind: k, .. } if *k == kind),
                "{text}"
            );
            assert!(text.contains(&path.display().to_string()), "{text}");
            assert!(text.contains(words) && text.contains("refusing"), "{text}");
            assert_eq!(
                std::fs::symlink_metadata(path).unwrap().file_type(),
                before,
                "{} changed",
                path.display()
            );
            assert!(Staged::new(path).is_err());
        }
        assert!(leftovers(&d).is_empty(), "{:?}", leftovers(&d));
        std::fs::remove_dir_all(&d).ok();
    }

    #[test]
    fn a_target_that_turns_special_before_the_rename_is_refused() {
        let d = dir("race");
        let p = d.join("out.png");
        let staged = Staged::new(&p).unwrap();
        assert!(staged.path().extension().is_some_and(|e| e == "png"));
        std::fs::write(staged.path(), b"drawn").unwrap();
        run("mkfifo", &[p.to_str().unwrap()]);
        let tmp = staged.path().to_path_buf();
        let e = staged.commit().unwrap_err();
        assert!(
            matches!(
                e,
                WriteError::NotAFile {
                    kind: Kind::Fifo,
                    ..
                }
            ),
            "{e}"
        );
        assert!(!tmp.exists(), "the temporary file stays");
        assert!(std::fs::symlink_metadata(&p).unwrap().file_type().is_fifo());
        std::fs::remove_dir_all(&d).ok();
    }

    #[test]
    fn paths_without_a_file_name_and_missing_folders_are_errors() {
        assert!(matches!(
            check(Path::new("/")),
            Err(WriteError::NoFileName { .. })
        ));
        let e = write_atomically(Path::new("/nonexistent-lungdyn/x.toml"), |w| {
            w.write_all(b"x")
        })
        .unwrap_err();
        assert!(matches!(e, WriteError::Io { .. }), "{e}");
        assert!(e.to_string().contains("/nonexistent-lungdyn/x.toml"), "{e}");
    }
}
