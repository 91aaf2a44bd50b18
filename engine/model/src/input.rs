//! Bounded reading of every input file.
//!
//! A clinical tool must not hang or eat memory on a wrong path: `/dev/zero` given as a CSV, a
//! 3 GB sparse file given as a mesh, a pipe that never ends. Every reader in lungdyn goes through
//! [`read_bounded`]: the path must be a regular file (special files — devices, pipes, sockets — only
//! with `allow_special`, and even then at most `max_bytes` are read), its length is checked before
//! anything is read, and text gets a line-length limit so a file without newlines cannot become one
//! huge line in a parser.
//!
//! Two more things keep a wrong input from costing time or memory before it is refused:
//! * special files are opened without blocking: opening a pipe (FIFO) that no program writes would
//!   otherwise wait forever in `open(2)`; such a pipe reads as empty and is refused as such;
//! * the first [`SNIFF_BYTES`] are looked at before the rest is read ([`read_bounded_with`]): a text
//!   format with a NUL byte, or a binary format whose header contradicts the file size, is refused at
//!   once instead of after reading gigabytes of a sparse file.

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
    /// A text file holds a NUL byte (seen in its first bytes, before the rest is read).
    #[error(
        "{}: binary data (a NUL byte at byte {offset}), not UTF-8 text: is this the right file?",
        path.display()
    )]
    Binary {
        /// Path.
        path: PathBuf,
        /// First NUL byte.
        offset: usize,
    },
    /// A pipe (FIFO) that no program writes: nothing to read.
    #[error(
        "{}: the pipe gave no data (no program is writing it): start the writer first, or give a \
         regular file",
        path.display()
    )]
    EmptyPipe {
        /// Path.
        path: PathBuf,
    },
    /// The first bytes already show the file is not of the expected format (see
    /// [`read_bounded_with`]).
    #[error("{}: {message}", path.display())]
    Format {
        /// Path.
        path: PathBuf,
        /// What the first bytes show.
        message: String,
    },
}

/// Bytes looked at before the rest of a file is read (see [`read_bounded_with`]).
pub const SNIFF_BYTES: usize = 64 << 10;

use std::os::unix::fs::FileTypeExt;

fn kind_of(meta: &std::fs::Metadata) -> &'static str {
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
/// or, with `allow_special`, at most `max_bytes` of a special file. With a line limit (text), a NUL
/// byte in the first [`SNIFF_BYTES`] refuses the file before the rest is read, and every line is
/// checked.
pub fn read_bounded(path: &Path, limits: ReadLimits) -> Result<Vec<u8>, InputError> {
    read_bounded_with(path, limits, |_, _| Ok(()))
}

/// [`read_bounded`] with a format check on the first bytes: `sniff(head, size)` gets the first
/// [`SNIFF_BYTES`] (or the whole file, when shorter) and the file's size (`None` for a special file)
/// before anything else is read; an `Err(message)` refuses the file at once
/// ([`InputError::Format`]). A binary STL whose header claims another size, say, is refused without
/// reading a sparse 3 GiB file.
pub fn read_bounded_with(
    path: &Path,
    limits: ReadLimits,
    sniff: impl FnOnce(&[u8], Option<u64>) -> Result<(), String>,
) -> Result<Vec<u8>, InputError> {
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
    let file = if regular {
        std::fs::File::open(path)
    } else {
        open_special(path)
    }
    .map_err(|source| InputError::Open { path: p(), source })?;
    // One byte more than allowed tells a file that grew (or a special file) from one that fits.
    let mut reader = file.take(limits.max_bytes.saturating_add(1));
    let read = |e| InputError::Read {
        path: p(),
        source: e,
    };
    let mut bytes = Vec::new();
    (&mut reader)
        .take(SNIFF_BYTES as u64)
        .read_to_end(&mut bytes)
        .map_err(read)?;
    if bytes.is_empty() && meta.file_type().is_fifo() {
        return Err(InputError::EmptyPipe { path: p() });
    }
    if limits.max_line_bytes > 0 {
        if let Some(offset) = bytes.iter().position(|&b| b == 0) {
            return Err(InputError::Binary { path: p(), offset });
        }
    }
    sniff(&bytes, regular.then_some(meta.len()))
        .map_err(|message| InputError::Format { path: p(), message })?;
    if regular {
        bytes.reserve((meta.len() as usize).saturating_sub(bytes.len()));
    }
    reader.read_to_end(&mut bytes).map_err(read)?;
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

/// Open a device, pipe or socket for reading without blocking in `open(2)` (a FIFO without a writer
/// would block there forever), then switch the descriptor back to blocking reads: a pipe with a
/// writer is read as it comes, and one without a writer reads as empty at once.
fn open_special(path: &Path) -> std::io::Result<std::fs::File> {
    use std::os::unix::fs::OpenOptionsExt;
    use std::os::unix::io::AsRawFd;
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK)
        .open(path)?;
    let fd = file.as_raw_fd();
    // SAFETY: fcntl on a descriptor we own; F_GETFL/F_SETFL only read and set its status flags.
    let ok = unsafe {
        let flags = libc::fcntl(fd, libc::F_GETFL);
        flags >= 0 && libc::fcntl(fd, libc::F_SETFL, flags & !libc::O_NONBLOCK) >= 0
    };
    if !ok {
        return Err(std::io::Error::last_os_error());
    }
    Ok(file)
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

    fn fifo(name: &str) -> PathBuf {
        let p = tmp(name);
        std::fs::remove_file(&p).ok();
        let c = std::ffi::CString::new(p.to_str().unwrap()).unwrap();
        // SAFETY: mkfifo on a path in our own temporary folder.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        p
    }

    #[test]
    fn a_fifo_without_a_writer_is_refused_at_once_never_waited_on() {
        let p = fifo("nowriter.fifo");
        let e = read_bounded(&p, ReadLimits::TABLE).unwrap_err();
        assert!(
            matches!(e, InputError::NotRegular { kind: "pipe", .. }),
            "{e}"
        );
        // Allowed, it is opened without blocking and reads as empty: refused, naming the pipe.
        let t = std::time::Instant::now();
        let e = read_bounded(&p, ReadLimits::TABLE.with(None, true)).unwrap_err();
        assert!(matches!(e, InputError::EmptyPipe { .. }), "{e}");
        assert!(e.to_string().contains("nowriter.fifo"), "{e}");
        assert!(t.elapsed() < std::time::Duration::from_secs(5));
        // A pipe with a writer is read to its end.
        let writer = {
            let p = p.clone();
            std::thread::spawn(move || {
                use std::io::Write;
                // Opening blocks until a reader has the pipe open; a reader that already saw an
                // empty pipe and left makes the write fail: try again.
                for _ in 0..200 {
                    let w = std::fs::OpenOptions::new().write(true).open(&p);
                    if w.and_then(|mut w| w.write_all(b"1 2 3\n")).is_ok() {
                        return;
                    }
                }
                panic!("no reader took the data");
            })
        };
        // The reader may read before the writer has opened: retry until the data arrives.
        let mut got = None;
        for _ in 0..200 {
            match read_bounded(&p, ReadLimits::TABLE.with(None, true)) {
                Ok(b) => {
                    got = Some(b);
                    break;
                }
                Err(InputError::EmptyPipe { .. }) => {
                    std::thread::sleep(std::time::Duration::from_millis(10))
                }
                Err(e) => panic!("{e}"),
            }
        }
        writer.join().unwrap();
        assert_eq!(got.as_deref(), Some(&b"1 2 3\n"[..]));
        std::fs::remove_file(&p).ok();
    }

    #[test]
    fn the_first_bytes_refuse_a_huge_wrong_file_without_reading_it() {
        // A sparse 3 GiB text file of zeros with the limit raised: refused by its first NUL byte.
        let p = tmp("sparse.csv");
        let f = std::fs::File::create(&p).unwrap();
        f.set_len(3 << 30).unwrap();
        let limits = ReadLimits::TABLE.with(Some(4096), false);
        let t = std::time::Instant::now();
        let e = read_bounded(&p, limits).unwrap_err();
        assert!(matches!(e, InputError::Binary { offset: 0, .. }), "{e}");
        assert!(e.to_string().contains("sparse.csv"), "{e}");
        assert!(t.elapsed() < std::time::Duration::from_secs(2));
        // A format check sees the head and the size before the rest is read.
        let limits = ReadLimits {
            max_line_bytes: 0,
            ..ReadLimits::MESH.with(Some(4096), false)
        };
        let e = read_bounded_with(&p, limits, |head, size| {
            assert_eq!((head.len(), size), (SNIFF_BYTES, Some(3 << 30)));
            Err("the header says 0 triangles".into())
        })
        .unwrap_err();
        assert!(matches!(e, InputError::Format { .. }), "{e}");
        assert!(
            e.to_string()
                .ends_with("sparse.csv: the header says 0 triangles"),
            "{e}"
        );
        std::fs::remove_file(&p).ok();
        // A small file: the head is the whole file, and it is returned whole.
        let small = tmp("small2.txt");
        std::fs::write(&small, "x y z\n").unwrap();
        let got = read_bounded_with(&small, ReadLimits::TABLE, |head, size| {
            assert_eq!((head, size), (&b"x y z\n"[..], Some(6)));
            Ok(())
        });
        assert_eq!(got.unwrap(), b"x y z\n");
    }

    #[test]
    fn a_missing_file_names_its_path() {
        let e = read_bounded(Path::new("/nonexistent/x.csv"), ReadLimits::TABLE).unwrap_err();
        assert!(e.to_string().contains("/nonexistent/x.csv"), "{e}");
    }
}
