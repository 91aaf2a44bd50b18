//! Bounded reading of every input file.
//!
//! A clinical tool must not hang or eat memory on a wrong path: `/dev/zero` given as a CSV, a
//! 3 GB sparse file given as a mesh, a pipe that never ends. Every reader in lungdyn goes through
//! [`read_bounded`]: the path must be a regular file (special files — devices, pipes, sockets — only
//! with `allow_special`, and even then at most `max_bytes` are read), its length is checked before
//! anything is read, and text gets a line-length limit so a file without newlines cannot become one
//! huge line in a parser.

use std::io::Read;
use std::path::{Path, PathBuf};

use thiserror::Error;

/// Limits of one kind of input.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct ReadLimits {
    /// Largest file read, bytes.
    pub max_bytes: u64,
    /// Longest line of a text file, bytes (0: no line limit, binary input).
    pub max_line_bytes: usize,
    /// Read devices, pipes and sockets too (up to `max_bytes`).
    pub allow_special: bool,
}

impl ReadLimits {
    /// Surface meshes (OBJ, PLY, STL): 2 GiB — an 8-million-triangle binary STL is 400 MB; lines up
    /// to 64 KiB (OBJ and ASCII PLY/STL lines are short).
    pub const MESH: ReadLimits = ReadLimits {
        max_bytes: 2 << 30,
        max_line_bytes: 64 << 10,
        allow_special: false,
    };
    /// Tables (PV curves, landmark files): 256 MiB, lines up to 64 KiB.
    pub const TABLE: ReadLimits = ReadLimits {
        max_bytes: 256 << 20,
        max_line_bytes: 64 << 10,
        allow_special: false,
    };
    /// Configuration (scenes, constants files): 4 MiB, lines up to 64 KiB.
    pub const CONFIG: ReadLimits = ReadLimits {
        max_bytes: 4 << 20,
        max_line_bytes: 64 << 10,
        allow_special: false,
    };

    /// These limits with the size limit set to `mib` MiB (when given) and special files allowed
    /// or not: what `--max-input-mib` and `--allow-special` set.
    pub fn with(self, mib: Option<u64>, allow_special: bool) -> Self {
        Self {
            max_bytes: mib
                .map(|m| m.saturating_mul(1 << 20))
                .unwrap_or(self.max_bytes),
            allow_special: allow_special || self.allow_special,
            ..self
        }
    }
}

/// Why an input file was not read.
#[derive(Debug, Error)]
pub enum InputError {
    /// The file could not be opened.
    #[error("cannot read {}: {source}", path.display())]
    Open {
        /// Path.
        path: PathBuf,
        /// OS error.
        source: std::io::Error,
    },
    /// A device, pipe, socket or folder where a file was expected.
    #[error(
        "{} is a {kind}, not a regular file: give a file, or pass --allow-special to read at most \
         the size limit from it",
        path.display()
    )]
    NotRegular {
        /// Path.
        path: PathBuf,
        /// What it is.
        kind: &'static str,
    },
    /// Larger than the limit for its kind (checked before reading).
    #[error(
        "{} is {size} bytes, over the {limit}-byte limit for this kind of input: check the path, or \
         raise the limit with --max-input-mib",
        path.display()
    )]
    TooLarge {
        /// Path.
        path: PathBuf,
        /// Its size (or "more than the limit" for special files).
        size: u64,
        /// The limit.
        limit: u64,
    },
    /// Reading failed part way.
    #[error("cannot read {}: {source}", path.display())]
    Read {
        /// Path.
        path: PathBuf,
        /// OS error.
        source: std::io::Error,
    },
    /// A text file has a line longer than the limit (binary data given as text?).
    #[error(
        "{}: line {line} is longer than {limit} bytes: this does not look like a text file of this kind",
        path.display()
    )]
    LineTooLong {
        /// Path.
        path: PathBuf,
        /// 1-based line.
        line: u64,
        /// The limit.
        limit: usize,
    },
    /// A text file is not UTF-8.
    #[error("{}: not UTF-8 text (at byte {offset}): is this the right file?", path.display())]
    NotText {
        /// Path.
        path: PathBuf,
        /// First bad byte.
        offset: usize,
    },
}

fn kind_of(meta: &std::fs::Metadata) -> &'static str {
    use std::os::unix::fs::FileTypeExt;
    let t = meta.file_type();
    if t.is_dir() {
        "folder"
    } else if t.is_char_device() {
        "character device"
    } else if t.is_block_device() {
        "block device"
    } else if t.is_fifo() {
        "pipe"
    } else if t.is_socket() {
        "socket"
    } else {
        "special file"
    }
}

/// Read `path` within `limits`: a regular file no larger than `max_bytes` (checked before reading),
/// or, with `allow_special`, at most `max_bytes` of a special file. With a line limit, every line
/// is checked too.
pub fn read_bounded(path: &Path, limits: ReadLimits) -> Result<Vec<u8>, InputError> {
    let p = || path.to_path_buf();
    let meta = std::fs::metadata(path).map_err(|source| InputError::Open { path: p(), source })?;
    let regular = meta.is_file();
    if meta.is_dir() || (!regular && !limits.allow_special) {
        return Err(InputError::NotRegular {
            path: p(),
            kind: kind_of(&meta),
        });
    }
    if regular && meta.len() > limits.max_bytes {
        return Err(InputError::TooLarge {
            path: p(),
            size: meta.len(),
            limit: limits.max_bytes,
        });
    }
    let file =
        std::fs::File::open(path).map_err(|source| InputError::Open { path: p(), source })?;
    let mut bytes = Vec::with_capacity(if regular { meta.len() as usize } else { 0 });
    // One byte more than allowed tells a file that grew (or a special file) from one that fits.
    file.take(limits.max_bytes.saturating_add(1))
        .read_to_end(&mut bytes)
        .map_err(|source| InputError::Read { path: p(), source })?;
    if bytes.len() as u64 > limits.max_bytes {
        return Err(InputError::TooLarge {
            path: p(),
            size: bytes.len() as u64,
            limit: limits.max_bytes,
        });
    }
    if limits.max_line_bytes > 0 {
        check_lines(path, &bytes, limits.max_line_bytes)?;
    }
    Ok(bytes)
}

/// [`read_bounded`] for text: the bytes must also be UTF-8.
pub fn read_text_bounded(path: &Path, limits: ReadLimits) -> Result<String, InputError> {
    let bytes = read_bounded(path, limits)?;
    String::from_utf8(bytes).map_err(|e| InputError::NotText {
        path: path.to_path_buf(),
        offset: e.utf8_error().valid_up_to(),
    })
}

fn check_lines(path: &Path, bytes: &[u8], limit: usize) -> Result<(), InputError> {
    let mut line = 1u64;
    let mut start = 0usize;
    for (i, &b) in bytes.iter().enumerate() {
        if b == b'\n' {
            if i - start > limit {
                break;
            }
            line += 1;
            start = i + 1;
        }
    }
    let end = bytes[start..]
        .iter()
        .position(|&b| b == b'\n')
        .map_or(bytes.len(), |k| start + k);
    if end - start > limit {
        return Err(InputError::LineTooLong {
            path: path.to_path_buf(),
            line,
            limit,
        });
    }
    Ok(())
}

/// Whether `bytes` look like binary data: a NUL byte in the first 8 KiB (text formats never have one).
pub fn looks_binary(bytes: &[u8]) -> bool {
    bytes.iter().take(8192).any(|&b| b == 0)
}

#[cfg(test)]
mod tests {
    use super::*;

    fn tmp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("lungdyn-input-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    #[test]
    fn devices_pipes_and_folders_are_refused_at_once() {
        for (path, kind) in [
            ("/dev/zero", "character device"),
            ("/dev/urandom", "character device"),
            ("/tmp", "folder"),
        ] {
            let e = read_bounded(Path::new(path), ReadLimits::TABLE).unwrap_err();
            assert!(
                matches!(&e, InputError::NotRegular { kind: k, .. } if *k == kind),
                "{path}: {e}"
            );
            assert!(e.to_string().contains("--allow-special") || kind == "folder");
        }
    }

    #[test]
    fn a_special_file_is_read_only_up_to_the_limit_when_allowed() {
        let limits = ReadLimits {
            max_bytes: 4096,
            max_line_bytes: 0,
            allow_special: true,
        };
        let e = read_bounded(Path::new("/dev/zero"), limits).unwrap_err();
        assert!(
            matches!(
                e,
                InputError::TooLarge {
                    size: 4097,
                    limit: 4096,
                    ..
                }
            ),
            "{e}"
        );
    }

    #[test]
    fn a_huge_sparse_file_is_refused_before_reading() {
        let p = tmp("sparse.stl");
        let f = std::fs::File::create(&p).unwrap();
        f.set_len(3 << 30).unwrap(); // 3 GiB, no blocks
        let t = std::time::Instant::now();
        let e = read_bounded(&p, ReadLimits::MESH).unwrap_err();
        assert!(matches!(e, InputError::TooLarge { .. }), "{e}");
        assert!(e.to_string().contains("--max-input-mib"), "{e}");
        // Refused by its length, not by reading it (no timing assert: the content was never read).
        let _ = t;
        std::fs::remove_file(&p).ok();
        // A raised limit lets a big legitimate file through the size check.
        let small = tmp("small.txt");
        std::fs::write(&small, "1 2 3\n").unwrap();
        let l = ReadLimits::TABLE.with(Some(1), false);
        assert_eq!(l.max_bytes, 1 << 20);
        assert_eq!(read_bounded(&small, l).unwrap(), b"1 2 3\n");
    }

    #[test]
    fn a_line_longer_than_the_limit_is_refused_with_its_number() {
        let p = tmp("long.csv");
        let mut text = "a,b\n1,2\n".to_string();
        text.push_str(&"9".repeat(70_000));
        text.push('\n');
        std::fs::write(&p, &text).unwrap();
        let e = read_bounded(&p, ReadLimits::TABLE).unwrap_err();
        assert!(matches!(e, InputError::LineTooLong { line: 3, .. }), "{e}");
        std::fs::write(&p, "x".repeat(70_000)).unwrap();
        assert!(matches!(
            read_bounded(&p, ReadLimits::TABLE),
            Err(InputError::LineTooLong { line: 1, .. })
        ));
        std::fs::write(&p, [0xff, 0xfe, b'\n']).unwrap();
        assert!(matches!(
            read_text_bounded(&p, ReadLimits::TABLE),
            Err(InputError::NotText { offset: 0, .. })
        ));
        assert!(looks_binary(b"ply\0"));
        assert!(!looks_binary(b"ply\nformat ascii 1.0\n"));
    }

    #[test]
    fn a_missing_file_names_its_path() {
        let e = read_bounded(Path::new("/nonexistent/x.csv"), ReadLimits::TABLE).unwrap_err();
        assert!(e.to_string().contains("/nonexistent/x.csv"), "{e}");
    }
}
