//! The bad-input battery: every case of `tests/bad_inputs/cases.toml` is run against the `lungdyn`
//! binary and must end as its table says — refused with a specific message and a non-zero exit,
//! accepted with a warning, or accepted — never a panic, never a hang (60 s), never a clobbered file.
//! Large inputs are generated here, not committed: a 3 GiB sparse file, `/dev/zero`, `/dev/urandom`
//! and a FIFO without a writer; and, as outputs no command may replace (`{specials}`), twins of
//! `/dev/null` made with mknod (root), FIFOs, a socket and symbolic links — after every case each
//! must still be what it was. `tests/bad_inputs/README.md` explains the table.

use std::path::{Path, PathBuf};
use std::process::{Command, Stdio};
use std::time::{Duration, Instant};

use lungdyn_tests::bin;

#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Table {
    case: Vec<Case>,
}

#[derive(Debug, serde::Deserialize)]
#[serde(deny_unknown_fields)]
struct Case {
    name: String,
    args: Vec<String>,
    expect: Expect,
    #[serde(default)]
    words: Vec<String>,
    #[serde(default)]
    unchanged: Vec<String>,
}

#[derive(Debug, Clone, Copy, PartialEq, serde::Deserialize)]
#[serde(rename_all = "lowercase")]
enum Expect {
    Refuse,
    Warn,
    Accept,
}

const SENTINEL: &[u8] = b"lungdyn bad-input battery: this file must not change\n";
const LIMIT: Duration = Duration::from_secs(60);
/// Character devices 1,3 (twins of /dev/null) in {specials}, named as each writer wants its output.
const NULL_TWINS: [&str; 7] = [
    "null",
    "null.obj",
    "null.kernel",
    "null.png",
    "null.toml",
    "null.csv",
    "null.json",
];
/// Symbolic links in {specials}: to a device, and to nothing.
const SPECIAL_LINKS: [(&str, &str); 2] = [("link.toml", "null"), ("dangling.toml", "nothing")];

struct Big {
    dir: PathBuf,
}

impl Big {
    fn new() -> Self {
        let dir = std::env::temp_dir().join(format!("lungdyn-battery-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        for name in ["big.stl", "big.csv", "big.ply", "big.txt"] {
            let f = std::fs::File::create(dir.join(name)).unwrap();
            f.set_len(3 << 30).unwrap(); // sparse: no blocks written
        }
        let fifo = dir.join("fifo");
        let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
        // SAFETY: mkfifo on a path we own.
        unsafe { libc::mkfifo(c.as_ptr(), 0o600) };
        // Outputs no command may replace, in {specials}: twins of /dev/null (character device 1,3;
        // a writer that renamed over one turned it into a regular file), with the extensions the
        // commands ask for, a FIFO, a socket and symbolic links to a device. mknod needs root (CI is).
        let specials = dir.join("specials");
        std::fs::create_dir_all(&specials).unwrap();
        for name in NULL_TWINS {
            let c = std::ffi::CString::new(specials.join(name).to_str().unwrap()).unwrap();
            // SAFETY: mknod on a path we own.
            let made =
                unsafe { libc::mknod(c.as_ptr(), libc::S_IFCHR | 0o600, libc::makedev(1, 3)) };
            assert_eq!(
                made,
                0,
                "mknod {name} c 1 3: {} (the battery's {{specials}} need root)",
                std::io::Error::last_os_error()
            );
        }
        for name in ["fifo", "fifo.toml"] {
            let c = std::ffi::CString::new(specials.join(name).to_str().unwrap()).unwrap();
            // SAFETY: mkfifo on a path we own.
            assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o600) }, 0);
        }
        for (link, to) in SPECIAL_LINKS {
            std::os::unix::fs::symlink(to, specials.join(link)).unwrap();
        }
        drop(std::os::unix::net::UnixListener::bind(specials.join("socket")).unwrap());
        Self { dir }
    }

    /// `Err` if a case replaced one of the files in {specials} (see [`Big::new`]).
    fn intact(&self) -> Result<(), String> {
        use std::os::unix::fs::FileTypeExt;
        let specials = self.dir.join("specials");
        let kinds = NULL_TWINS
            .iter()
            .map(|n| (*n, "a character device"))
            .chain([
                ("fifo", "a FIFO"),
                ("fifo.toml", "a FIFO"),
                ("socket", "a socket"),
            ])
            .chain(SPECIAL_LINKS.iter().map(|(n, _)| (*n, "a symbolic link")));
        for (name, what) in kinds {
            let path = specials.join(name);
            let ok = std::fs::symlink_metadata(&path).is_ok_and(|m| {
                let t = m.file_type();
                match what {
                    "a character device" => t.is_char_device(),
                    "a FIFO" => t.is_fifo(),
                    "a socket" => t.is_socket(),
                    _ => t.is_symlink(),
                }
            });
            if !ok {
                return Err(format!("{} is no longer {what}", path.display()));
            }
        }
        Ok(())
    }

    fn substitute(&self, arg: &str, out: &Path) -> String {
        let fixtures = Path::new(env!("CARGO_MANIFEST_DIR")).join("bad_inputs");
        arg.replace("{fixtures}", fixtures.to_str().unwrap())
            .replace("{out}", out.to_str().unwrap())
            .replace("{sparse3g_stl}", self.dir.join("big.stl").to_str().unwrap())
            .replace("{sparse3g_csv}", self.dir.join("big.csv").to_str().unwrap())
            .replace("{sparse3g_ply}", self.dir.join("big.ply").to_str().unwrap())
            .replace("{sparse3g_txt}", self.dir.join("big.txt").to_str().unwrap())
            .replace("{sparse3g}", self.dir.join("big.stl").to_str().unwrap())
            .replace("{zero}", "/dev/zero")
            .replace("{urandom}", "/dev/urandom")
            .replace("{fifo}", self.dir.join("fifo").to_str().unwrap())
            .replace("{specials}", self.dir.join("specials").to_str().unwrap())
    }
}

impl Drop for Big {
    fn drop(&mut self) {
        std::fs::remove_dir_all(&self.dir).ok();
    }
}

/// Run one case; `Err` says why it failed.
fn run(case: &Case, big: &Big, n: usize) -> Result<Duration, String> {
    let out = std::env::temp_dir().join(format!("lungdyn-battery-{}-{n}", std::process::id()));
    std::fs::create_dir_all(&out).unwrap();
    let guarded: Vec<PathBuf> = case
        .unchanged
        .iter()
        .map(|p| PathBuf::from(big.substitute(p, &out)))
        .collect();
    for p in &guarded {
        if let Some(d) = p.parent() {
            std::fs::create_dir_all(d).unwrap();
        }
        std::fs::write(p, SENTINEL).unwrap();
    }
    let args: Vec<String> = case.args.iter().map(|a| big.substitute(a, &out)).collect();
    let start = Instant::now();
    let mut child = Command::new(bin("lungdyn"))
        .args(&args)
        .stdin(Stdio::null())
        .stdout(Stdio::piped())
        .stderr(Stdio::piped())
        .spawn()
        .map_err(|e| format!("cannot start: {e}"))?;
    // Read the pipes on threads so a chatty child never blocks on a full pipe.
    let mut so = child.stdout.take().unwrap();
    let mut se = child.stderr.take().unwrap();
    let t_out = std::thread::spawn(move || {
        let mut s = Vec::new();
        std::io::Read::read_to_end(&mut so, &mut s).ok();
        s
    });
    let t_err = std::thread::spawn(move || {
        let mut s = Vec::new();
        std::io::Read::read_to_end(&mut se, &mut s).ok();
        s
    });
    let status = loop {
        if let Some(s) = child.try_wait().unwrap() {
            break s;
        }
        if start.elapsed() > LIMIT {
            let _ = child.kill();
            let _ = child.wait();
            return Err(format!("hung: still running after {} s", LIMIT.as_secs()));
        }
        std::thread::sleep(Duration::from_millis(5));
    };
    let took = start.elapsed();
    let _ = t_out.join();
    let stderr = String::from_utf8_lossy(&t_err.join().unwrap_or_default()).into_owned();
    let fail = |why: String| Err(format!("{why}\n    args: {args:?}\n    stderr: {stderr}"));
    if stderr.contains("panicked") {
        return fail("panicked".into());
    }
    if stderr.contains("NaN ml") || stderr.contains("inf ml") {
        return fail("a non-finite volume reached the output".into());
    }
    match (case.expect, status.success()) {
        (Expect::Refuse, true) => return fail("accepted, expected a refusal".into()),
        (Expect::Warn | Expect::Accept, false) => {
            return fail(format!("refused ({status}), expected it to be accepted"))
        }
        _ => {}
    }
    if let Some(w) = case.words.iter().find(|w| !stderr.contains(w.as_str())) {
        return fail(format!("the message lacks {w:?}"));
    }
    if let Err(why) = big.intact() {
        return fail(why);
    }
    if case.expect == Expect::Refuse {
        for p in &guarded {
            if std::fs::read(p).ok().as_deref() != Some(SENTINEL) {
                return fail(format!("{} was changed by a refused run", p.display()));
            }
        }
    }
    std::fs::remove_dir_all(&out).ok();
    Ok(took)
}

#[test]
fn every_bad_input_is_refused_warned_or_converted_as_the_table_says() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR")).join("bad_inputs/cases.toml");
    let text = std::fs::read_to_string(&path).unwrap();
    let table: Table = toml::from_str(&text).unwrap_or_else(|e| panic!("{}: {e}", path.display()));
    let mut names = std::collections::HashSet::new();
    for c in &table.case {
        assert!(
            names.insert(c.name.as_str()),
            "duplicate case name {:?}",
            c.name
        );
        assert!(
            c.expect == Expect::Accept || !c.words.is_empty(),
            "{:?}: a refusal or warning must name the words its message needs",
            c.name
        );
    }
    let big = Big::new();
    let mut failures = Vec::new();
    let mut slowest = (Duration::ZERO, String::new());
    // LUNGDYN_CASES="words|other words" runs only the cases whose name contains one of them (while
    // working on one command); the summary says how many were left out.
    let only = std::env::var("LUNGDYN_CASES").ok();
    let chosen = |c: &Case| {
        only.as_deref()
            .is_none_or(|w| w.split('|').any(|w| c.name.contains(w)))
    };
    for (n, c) in table.case.iter().enumerate().filter(|(_, c)| chosen(c)) {
        match run(c, &big, n) {
            Ok(t) => {
                if t > slowest.0 {
                    slowest = (t, c.name.clone());
                }
            }
            Err(why) => failures.push(format!("{}: {why}", c.name)),
        }
    }
    let counts = |e: Expect| {
        table
            .case
            .iter()
            .filter(|c| chosen(c) && c.expect == e)
            .count()
    };
    let left_out = table.case.iter().filter(|c| !chosen(c)).count();
    if left_out > 0 {
        eprintln!(
            "bad-input battery: LUNGDYN_CASES={:?} left out {left_out} of {} cases",
            only.as_deref().unwrap_or_default(),
            table.case.len()
        );
    }
    eprintln!(
        "bad-input battery: {} cases run ({} refuse, {} warn, {} accept); slowest {:.2} s ({})",
        table.case.len() - left_out,
        counts(Expect::Refuse),
        counts(Expect::Warn),
        counts(Expect::Accept),
        slowest.0.as_secs_f64(),
        slowest.1
    );
    assert!(
        failures.is_empty(),
        "{} of {} cases failed:\n{}",
        failures.len(),
        table.case.len() - left_out,
        failures.join("\n")
    );
}
