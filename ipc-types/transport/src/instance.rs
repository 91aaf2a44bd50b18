//! One lungdyn run: its name, its stream names and the files its transport leaves on disk.
//!
//! Every process of a run uses the same instance name; stream names (`lungdyn/<instance>/engine`)
//! and iceoryx2's file prefix (`lungdyn_<instance>_`) derive from it, so two runs never meet and the
//! files of one run can be found and removed without touching another's.

use std::path::PathBuf;

use crate::port::PortError;

/// The streams of one lungdyn instance.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Instance {
    name: String,
}

impl Instance {
    /// Instance `name`: 1–48 characters of `[A-Za-z0-9_-]`.
    pub fn new(name: &str) -> Result<Self, PortError> {
        let ok = !name.is_empty()
            && name.len() <= 48
            && name
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_');
        if !ok {
            return Err(PortError::BadInstanceName {
                name: name.to_string(),
            });
        }
        Ok(Self {
            name: name.to_string(),
        })
    }

    /// The instance name.
    pub fn name(&self) -> &str {
        &self.name
    }

    /// Stream of [`ipc_types::TrackerFrame`]s.
    pub fn tracker(&self) -> String {
        format!("lungdyn/{}/tracker", self.name)
    }
    /// Event signalled after each tracker frame.
    pub fn tracker_event(&self) -> String {
        format!("lungdyn/{}/tracker-ready", self.name)
    }
    /// Stream of [`ipc_types::EngineFrame`]s.
    pub fn engine(&self) -> String {
        format!("lungdyn/{}/engine", self.name)
    }
    /// Event signalled after each engine frame.
    pub fn engine_event(&self) -> String {
        format!("lungdyn/{}/engine-ready", self.name)
    }
    /// Stream of [`ipc_types::FrameReport`]s.
    pub fn report(&self) -> String {
        format!("lungdyn/{}/report", self.name)
    }
    /// Event signalled after each frame report.
    pub fn report_event(&self) -> String {
        format!("lungdyn/{}/report-ready", self.name)
    }
    /// Stream of [`ipc_types::ControlPacket`]s (a trainee's actions).
    pub fn control(&self) -> String {
        format!("lungdyn/{}/control", self.name)
    }
    /// Event signalled after each control packet.
    pub fn control_event(&self) -> String {
        format!("lungdyn/{}/control-ready", self.name)
    }
    /// Stream of [`ipc_types::ControlReply`]s (the engine's answers to the control packets).
    pub fn control_reply(&self) -> String {
        format!("lungdyn/{}/control-reply", self.name)
    }
    /// Event signalled after each control reply.
    pub fn control_reply_event(&self) -> String {
        format!("lungdyn/{}/control-reply-ready", self.name)
    }
    /// Stream of the engine's control state (`control_state::ControlStateFrame`, remote sites).
    pub fn control_state(&self) -> String {
        format!("lungdyn/{}/control-state", self.name)
    }
    /// Event signalled after each control state.
    pub fn control_state_event(&self) -> String {
        format!("lungdyn/{}/control-state-ready", self.name)
    }

    /// The transport's file prefix for this instance: every shared-memory segment and file the
    /// instance creates starts with it.
    pub fn file_prefix(&self) -> String {
        format!("lungdyn_{}_", self.name)
    }

    /// Files of this instance still present in shared memory (`/dev/shm`) or under iceoryx2's root
    /// folder. Empty after a clean shutdown (but for iceoryx2's per-prefix node counter, which
    /// outlives the nodes by design until [`Self::remove_leftovers`]).
    pub fn leftovers(&self) -> Vec<PathBuf> {
        files_named(&self.file_prefix())
    }

    /// Remove the files of instances whose processes have all gone (a launcher killed with SIGKILL
    /// leaves iceoryx2's node counter, a process killed before its cleanup its segments — files
    /// every user may read and write, and which a later run of the same name would trip on). An
    /// instance counts as dead when it has lock files (every lungdyn process takes one before it
    /// creates any file) and none of them is locked: the lock itself is asked about
    /// ([`lock_held`]: the open-file-description lock, then the kernel's `/proc/locks`), not the pid written in it, which may be
    /// gone or recycled by an unrelated process (even one with the same command line). Where the
    /// kernel's list cannot be read, the pids and command lines of the lock files decide
    /// ([`Self::running`]). A file that a running instance's prefix also claims (`a_b` running
    /// beside a dead `a`) is kept. Transport files of a prefix that never took a lock (a test's
    /// private node) are not touched. Returns the files removed.
    pub fn sweep_dead() -> Vec<PathBuf> {
        let mut locks: Vec<(String, PathBuf)> = std::fs::read_dir(Self::lock_dir())
            .map(|d| {
                d.flatten()
                    .filter_map(|e| {
                        lock_name_role(&e.file_name().to_string_lossy())
                            .map(|(n, _)| (n.to_string(), e.path()))
                    })
                    .collect()
            })
            .unwrap_or_default();
        locks.sort();
        let held = HeldLocks::read();
        let running = Self::running();
        let live_names: Vec<String> = locks
            .iter()
            .filter(|(name, path)| match lock_held(path, held.as_ref()) {
                Some(held) => held,
                // Neither lock table answers: the pids and command lines decide.
                None => running.iter().any(|r| &r.name == name),
            })
            .map(|(name, _)| name.clone())
            .collect();
        let live: Vec<String> = live_names
            .iter()
            .filter_map(|n| Instance::new(n).ok().map(|i| i.file_prefix()))
            .collect();
        let mut dead: Vec<String> = locks.into_iter().map(|(name, _)| name).collect();
        dead.dedup();
        let mut removed = Vec::new();
        for name in dead {
            let Ok(instance) = Instance::new(&name) else {
                continue;
            };
            if live.contains(&instance.file_prefix()) {
                continue;
            }
            for path in instance.leftovers() {
                let file = path.file_name().map(|n| n.to_string_lossy().into_owned());
                let claimed = file.is_some_and(|f| live.iter().any(|p| f.starts_with(p.as_str())));
                if !claimed && std::fs::remove_file(&path).is_ok() {
                    if let Some(dir) = path.parent() {
                        let _ = std::fs::remove_dir(dir);
                    }
                    removed.push(path);
                }
            }
        }
        removed
    }

    /// Delete the files [`Self::leftovers`] finds, and folders left empty by that. Only for after
    /// every process of the instance has exited: the prefix is unique to the instance, so no other
    /// run is touched. Says which files were expected (iceoryx2's per-prefix node counter, which
    /// outlives its nodes by design) and which were left behind by a process that did not clean up.
    pub fn remove_leftovers(&self) -> Cleanup {
        let mut cleanup = Cleanup::default();
        for path in self.leftovers() {
            // iceoryx2 0.10 names it `<prefix><hash>_node.<version>.global_mgmt`.
            let is_counter = path
                .file_name()
                .is_some_and(|n| n.to_string_lossy().ends_with(".global_mgmt"));
            if std::fs::remove_file(&path).is_ok() {
                if is_counter {
                    cleanup.node_counter = true;
                } else {
                    cleanup.unexpected.push(path.clone());
                }
                if let Some(dir) = path.parent() {
                    // Only succeeds when the folder is now empty.
                    let _ = std::fs::remove_dir(dir);
                }
            }
        }
        cleanup
    }
}

/// iceoryx2's root folder (where node and service files live besides `/dev/shm`), from its
/// default config.
pub fn root_path() -> PathBuf {
    PathBuf::from(
        iceoryx2::config::Config::default()
            .global
            .root_path()
            .as_str(),
    )
}

/// Files whose name starts with `prefix` in shared memory (`/dev/shm`) or anywhere under
/// iceoryx2's root folder, sorted.
fn files_named(prefix: &str) -> Vec<PathBuf> {
    let mut found = Vec::new();
    let mut stack = vec![PathBuf::from("/dev/shm"), root_path()];
    while let Some(dir) = stack.pop() {
        let Ok(entries) = std::fs::read_dir(&dir) else {
            continue;
        };
        for entry in entries.flatten() {
            let path = entry.path();
            if entry.file_type().map(|t| t.is_dir()).unwrap_or(false)
                && !dir.starts_with("/dev/shm")
            {
                stack.push(path.clone());
            }
            if entry.file_name().to_string_lossy().starts_with(prefix) {
                found.push(path);
            }
        }
    }
    found.sort();
    found
}

/// Proof that this process is the only one of its role in its instance (an exclusive `flock` on a
/// lock file, released by the kernel when the process exits, however it exits).
#[derive(Debug)]
pub struct InstanceLock {
    _file: std::fs::File,
    path: PathBuf,
}

impl InstanceLock {
    /// The lock file.
    pub fn path(&self) -> &std::path::Path {
        &self.path
    }
}

impl Instance {
    /// Folder of the lock files.
    pub fn lock_dir() -> PathBuf {
        std::env::temp_dir().join("lungdyn-locks")
    }

    /// The process that holds `role`'s lock in this instance, if one is running — read without
    /// touching the lock (taking it to test, even for an instant, could refuse the real owner as it
    /// starts). The lock itself decides ([`lock_held`]): a pid written in a lock file nobody holds
    /// may have been recycled by an unrelated process, and a holder in another pid namespace is
    /// not in this one's `/proc`. Only where the lock cannot be asked does the pid decide, checked
    /// alive in `/proc`. Returns the pid the holder wrote.
    pub fn holder(&self, role: &str) -> Option<u32> {
        let path = Self::lock_dir().join(format!("{}.{role}.lock", self.name));
        let held = lock_held(&path, None);
        if held == Some(false) {
            return None;
        }
        let text = read_lock_text(&path)?;
        let pid: u32 = text
            .strip_prefix("process ")?
            .split_whitespace()
            .next()?
            .parse()
            .ok()?;
        (held == Some(true) || std::path::Path::new(&format!("/proc/{pid}")).exists())
            .then_some(pid)
    }

    /// Take the exclusive lock of `role` ("launcher", "engine", "renderer", "tracker-bridge") in this
    /// instance. A second process of the same role and instance is refused with a message naming
    /// the one that holds it; never waits.
    pub fn lock(&self, role: &str) -> Result<InstanceLock, PortError> {
        use std::io::{Read, Seek, Write};
        use std::os::fd::AsRawFd;
        let dir = Self::lock_dir();
        let io = |source| PortError::Lock {
            instance: self.name.clone(),
            source,
        };
        std::fs::create_dir_all(&dir).map_err(io)?;
        let path = dir.join(format!("{}.{role}.lock", self.name));
        // Not through a symbolic link (the folder is shared: a link placed there would have this
        // process write into the file it names), never blocking on a FIFO, and only a regular file.
        let mut file = {
            use std::os::unix::fs::OpenOptionsExt;
            std::fs::OpenOptions::new()
                .read(true)
                .write(true)
                .create(true)
                .truncate(false)
                .mode(0o644)
                .custom_flags(libc::O_NONBLOCK | libc::O_NOFOLLOW)
                .open(&path)
        }
        .map_err(|e| {
            io(if e.raw_os_error() == Some(libc::ELOOP) {
                not_a_lock_file(&path, "a symbolic link")
            } else {
                e
            })
        })?;
        match file.metadata() {
            Ok(m) if m.is_file() => {}
            Ok(_) => {
                return Err(io(not_a_lock_file(
                    &path,
                    "not a regular file (a FIFO, socket or device)",
                )))
            }
            Err(e) => return Err(io(e)),
        }
        // SAFETY: flock on a file descriptor we own; non-blocking.
        let r = unsafe { libc::flock(file.as_raw_fd(), libc::LOCK_EX | libc::LOCK_NB) };
        if r != 0 {
            let err = std::io::Error::last_os_error();
            if err.raw_os_error() == Some(libc::EWOULDBLOCK) {
                let mut holder = String::new();
                let _ = (&mut file).take(LOCK_TEXT_MAX).read_to_string(&mut holder);
                return Err(PortError::InstanceBusy {
                    instance: self.name.clone(),
                    role: role.to_string(),
                    holder: holder.trim().to_string(),
                });
            }
            return Err(io(err));
        }
        // Also an open-file-description lock on the same file (independent of the flock on
        // Linux): unlike a flock, it can be asked about without taking it, from any pid namespace
        // (`F_OFD_GETLK`, [`lock_held`]). It cannot conflict: only the flock's holder gets here.
        let mut whole = ofd_whole_file(libc::F_WRLCK);
        // SAFETY: fcntl on a file descriptor we own with a valid `struct flock`; non-blocking.
        if unsafe { libc::fcntl(file.as_raw_fd(), libc::F_OFD_SETLK, &mut whole) } != 0 {
            return Err(io(std::io::Error::last_os_error()));
        }
        let cmdline = std::env::args().collect::<Vec<_>>().join(" ");
        file.set_len(0).map_err(io)?;
        file.rewind().map_err(io)?;
        write!(file, "process {} ({cmdline})", std::process::id()).map_err(io)?;
        Ok(InstanceLock { _file: file, path })
    }
}

/// The most of a lock file read: "process PID (command line)" is far shorter; a larger file (a
/// stray or hostile one in the shared folder) is not read whole.
const LOCK_TEXT_MAX: u64 = 64 * 1024;

/// A lock file opened to be read as untrusted input (the lock folder is shared by every user of
/// the machine): never blocking (a FIFO put in its place would hang `open` until a writer came),
/// never through a symbolic link, and only a regular file.
fn open_lock_file(path: &std::path::Path) -> Option<std::fs::File> {
    use std::os::unix::fs::OpenOptionsExt;
    let file = std::fs::OpenOptions::new()
        .read(true)
        .custom_flags(libc::O_NONBLOCK | libc::O_NOFOLLOW)
        .open(path)
        .ok()?;
    file.metadata().ok().filter(|m| m.is_file())?;
    Some(file)
}

/// A lock file's text, at most [`LOCK_TEXT_MAX`] bytes of it, read as untrusted input
/// ([`open_lock_file`]); `None` when it is not a regular file or not text.
fn read_lock_text(path: &std::path::Path) -> Option<String> {
    use std::io::Read;
    let mut text = String::new();
    open_lock_file(path)?
        .take(LOCK_TEXT_MAX)
        .read_to_string(&mut text)
        .ok()?;
    Some(text)
}

/// The error for something other than a lock file in a lock file's place.
fn not_a_lock_file(path: &std::path::Path, what: &str) -> std::io::Error {
    std::io::Error::new(
        std::io::ErrorKind::InvalidInput,
        format!(
            "{} is {what}, not a lock file: something else was put in the lock folder; remove it \
             (rm {}) and start again",
            path.display(),
            path.display()
        ),
    )
}

/// A `struct flock` covering the whole file.
fn ofd_whole_file(kind: libc::c_int) -> libc::flock {
    // SAFETY: `flock` is plain old data; all zeros is a valid value (l_start 0, l_len 0 = to the end).
    let mut fl: libc::flock = unsafe { std::mem::zeroed() };
    fl.l_type = kind as libc::c_short;
    fl.l_whence = libc::SEEK_SET as libc::c_short;
    fl
}

/// Whether some process holds the lock file at `path` ([`Instance::lock`]), asked without taking
/// it: first the open-file-description lock every lungdyn process takes beside its flock
/// (`F_OFD_GETLK`, which sees holders in every pid namespace), then — for a lock file whose
/// holder predates that — the kernel's flock table (`held`, or `/proc/locks` read now, which
/// lists the reader's pid namespace only). `None` when neither can answer (file gone, unreadable).
pub fn lock_held(path: &std::path::Path, held: Option<&HeldLocks>) -> Option<bool> {
    use std::os::fd::AsRawFd;
    let ofd = open_lock_file(path).and_then(|file| {
        let mut probe = ofd_whole_file(libc::F_WRLCK);
        // SAFETY: fcntl on a file descriptor we own with a valid `struct flock`; F_OFD_GETLK only
        // reports, it takes nothing.
        let r = unsafe { libc::fcntl(file.as_raw_fd(), libc::F_OFD_GETLK, &mut probe) };
        (r == 0).then_some(probe.l_type != libc::F_UNLCK as libc::c_short)
    });
    if ofd == Some(true) {
        return Some(true);
    }
    let flock = match held {
        Some(h) => h.holds(path),
        None => HeldLocks::read().and_then(|h| h.holds(path)),
    };
    flock.or(ofd)
}

/// One process of a running instance, as its lock file says.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RunningProcess {
    /// Its role ("launcher", "engine", "renderer", "tracker-bridge").
    pub role: String,
    /// Its pid.
    pub pid: u32,
    /// Its command line as it recorded it.
    pub cmdline: String,
    /// When it took the lock (seconds since the Unix epoch).
    pub since_unix_s: u64,
}

/// A running instance: its name and the processes that hold its locks.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct RunningInstance {
    /// The instance name (`--instance`, or `demo-<pid>` for a demo without one).
    pub name: String,
    /// Its live processes, launcher first.
    pub processes: Vec<RunningProcess>,
}

impl RunningInstance {
    /// The process of `role`, if it runs.
    pub fn process(&self, role: &str) -> Option<&RunningProcess> {
        self.processes.iter().find(|p| p.role == role)
    }
}

/// The roles whose locks name an instance's processes.
pub const ROLES: [&str; 4] = ["launcher", "engine", "renderer", "tracker-bridge"];

impl Instance {
    /// Every instance with at least one live process, sorted by name. A lock file counts only while
    /// it is locked ([`HeldLocks`]; where the kernel's list cannot be read, this is not asked) and
    /// its pid is alive *and* runs the command line it recorded (so a recycled pid is not taken for
    /// the process that left the file).
    pub fn running() -> Vec<RunningInstance> {
        let mut found: std::collections::BTreeMap<String, Vec<RunningProcess>> = Default::default();
        let Ok(dir) = std::fs::read_dir(Self::lock_dir()) else {
            return Vec::new();
        };
        let held = HeldLocks::read();
        for entry in dir.flatten() {
            let file = entry.file_name();
            let Some((name, role)) = file.to_str().and_then(lock_name_role) else {
                continue;
            };
            if lock_held(&entry.path(), held.as_ref()) == Some(false) {
                continue;
            }
            let Some(text) = read_lock_text(&entry.path()) else {
                continue;
            };
            let Some((pid, cmdline)) = text
                .strip_prefix("process ")
                .and_then(|t| t.split_once(' '))
                .and_then(|(pid, rest)| {
                    let cmd = rest.strip_prefix('(')?.strip_suffix(')')?;
                    Some((pid.parse::<u32>().ok()?, cmd.to_string()))
                })
            else {
                continue;
            };
            let live = std::fs::read(format!("/proc/{pid}/cmdline")).is_ok_and(|raw| {
                let raw = raw.strip_suffix(&[0]).unwrap_or(&raw);
                let args: Vec<String> = raw
                    .split(|&b| b == 0)
                    .map(|a| String::from_utf8_lossy(a).into_owned())
                    .collect();
                args.join(" ") == cmdline
            });
            if !live {
                continue;
            }
            let since_unix_s = entry
                .metadata()
                .ok()
                .and_then(|m| m.modified().ok())
                .and_then(|t| t.duration_since(std::time::UNIX_EPOCH).ok())
                .map_or(0, |d| d.as_secs());
            found
                .entry(name.to_string())
                .or_default()
                .push(RunningProcess {
                    role: role.to_string(),
                    pid,
                    cmdline,
                    since_unix_s,
                });
        }
        found
            .into_iter()
            .map(|(name, mut processes)| {
                processes.sort_by_key(|p| ROLES.iter().position(|r| *r == p.role));
                RunningInstance { name, processes }
            })
            .collect()
    }
}

/// The instance name and role of a lock file's name (`<name>.<role>.lock`).
fn lock_name_role(file: &str) -> Option<(&str, &'static str)> {
    let stem = file.strip_suffix(".lock")?;
    ROLES
        .iter()
        .find_map(|r| stem.strip_suffix(&format!(".{r}")).map(|n| (n, *r)))
}

/// The files locked with `flock` now, as the kernel lists them in `/proc/locks` (by device and
/// inode): whether a lock file is held, asked without touching the lock (taking it to test, even
/// for an instant, could refuse its real owner as it starts). A held lock is proof of a live owner
/// that a pid written in the file is not: the kernel drops the lock when its holder exits, however
/// it exits. (The kernel lists the locks of processes in the reader's pid namespace.)
#[derive(Debug, Clone, Default)]
pub struct HeldLocks {
    /// "MAJOR:MINOR:INODE" (major and minor in hex, as `/proc/locks` writes them) of each file
    /// some process holds a `flock` on.
    files: std::collections::HashSet<String>,
}

impl HeldLocks {
    /// Read `/proc/locks`; `None` when it cannot be read.
    pub fn read() -> Option<Self> {
        std::fs::read_to_string("/proc/locks")
            .ok()
            .map(|t| Self::parse(&t))
    }

    /// The held `flock`s of a `/proc/locks` text: lines "N: FLOCK ADVISORY WRITE PID MM:mm:INODE
    /// START END"; a waiter's line ("N: -> FLOCK …") holds nothing, and POSIX (`fcntl`) locks are
    /// not ours.
    pub fn parse(text: &str) -> Self {
        let files = text
            .lines()
            .filter_map(|l| {
                let mut f = l.split_whitespace().skip(1);
                // FLOCK, ADVISORY, READ/WRITE, pid, then the file.
                (f.next()? == "FLOCK").then(|| f.nth(3).map(str::to_string))?
            })
            .collect();
        Self { files }
    }

    /// Whether the file at `path` is held; `None` when it cannot be looked up (gone, unreadable).
    pub fn holds(&self, path: &std::path::Path) -> Option<bool> {
        use std::os::unix::fs::MetadataExt;
        let m = std::fs::metadata(path).ok()?;
        let key = format!(
            "{:02x}:{:02x}:{}",
            libc::major(m.dev()),
            libc::minor(m.dev()),
            m.ino()
        );
        Some(self.files.contains(&key))
    }
}

/// What [`Instance::remove_leftovers`] removed.
#[derive(Debug, Clone, Default, PartialEq, Eq)]
pub struct Cleanup {
    /// iceoryx2's node-counter segment of the instance was removed (expected after every run).
    pub node_counter: bool,
    /// Other files of the instance that were still there (a process did not clean up).
    pub unexpected: Vec<PathBuf>,
}

#[cfg(test)]
pub(crate) mod tests {
    use super::*;

    #[test]
    fn instance_names_are_validated() {
        assert!(Instance::new("demo-1_a").is_ok());
        for bad in ["", "a/b", "a b", "ü"] {
            assert!(
                matches!(Instance::new(bad), Err(PortError::BadInstanceName { .. })),
                "{bad:?}"
            );
        }
        assert!(Instance::new(&"x".repeat(48)).is_ok());
        assert!(Instance::new(&"x".repeat(49)).is_err());
    }

    #[test]
    fn a_second_holder_of_a_role_is_refused_naming_the_first() {
        let i = Instance::new(&format!("lock-test-{}", std::process::id())).unwrap();
        let held = i.lock("engine").unwrap();
        let e = i.lock("engine").unwrap_err();
        let msg = e.to_string();
        assert!(
            matches!(&e, PortError::InstanceBusy { role, .. } if role == "engine"),
            "{msg}"
        );
        assert!(
            msg.contains(&format!("process {}", std::process::id())),
            "{msg}"
        );
        // Other roles of the instance, and the same role of another instance, are free.
        let _renderer = i.lock("renderer").unwrap();
        let other = Instance::new(&format!("lock-test-b-{}", std::process::id())).unwrap();
        let _o = other.lock("engine").unwrap();
        drop(held);
        let again = i.lock("engine").unwrap();
        assert!(again.path().exists());
    }

    /// `f()` on a thread, within 10 s: a call that blocks (an `open` of a FIFO waits for a
    /// writer forever) fails the test instead of hanging it.
    fn within_10_s<T: Send + 'static>(what: &str, f: impl FnOnce() -> T + Send + 'static) -> T {
        let (tx, rx) = std::sync::mpsc::channel();
        std::thread::spawn(move || {
            let _ = tx.send(f());
        });
        rx.recv_timeout(std::time::Duration::from_secs(10))
            .unwrap_or_else(|_| panic!("{what} blocked on a FIFO in the lock folder"))
    }

    #[test]
    fn a_fifo_a_link_or_a_huge_file_in_the_lock_folder_neither_hangs_nor_is_trusted() {
        let dir = Instance::lock_dir();
        std::fs::create_dir_all(&dir).unwrap();
        let tag = std::process::id();
        // A FIFO in a launcher's lock file's place.
        let fifo_name = format!("fifo-test-{tag}");
        let fifo = dir.join(format!("{fifo_name}.launcher.lock"));
        let _ = std::fs::remove_file(&fifo);
        let c = std::ffi::CString::new(fifo.to_str().unwrap()).unwrap();
        // SAFETY: mkfifo with a valid NUL-terminated path.
        assert_eq!(unsafe { libc::mkfifo(c.as_ptr(), 0o644) }, 0);
        // A sparse 1 GiB lock file (no disk used): not read whole.
        let huge_name = format!("huge-test-{tag}");
        let huge = dir.join(format!("{huge_name}.engine.lock"));
        std::fs::File::create(&huge)
            .unwrap()
            .set_len(1 << 30)
            .unwrap();
        // A symbolic link to a file of ours: taking the lock must not write into the file.
        let target = std::env::temp_dir().join(format!("lungdyn-link-target-{tag}"));
        std::fs::write(&target, "precious").unwrap();
        let link_name = format!("link-test-{tag}");
        let link = dir.join(format!("{link_name}.renderer.lock"));
        let _ = std::fs::remove_file(&link);
        std::os::unix::fs::symlink(&target, &link).unwrap();

        let running = within_10_s("Instance::running", Instance::running);
        assert!(
            running
                .iter()
                .all(|r| ![&fifo_name, &huge_name, &link_name].contains(&&r.name)),
            "{running:?}"
        );
        let fifo_instance = Instance::new(&fifo_name).unwrap();
        let (holder, lock) = within_10_s("holder and lock", move || {
            (
                fifo_instance.holder("launcher"),
                fifo_instance.lock("launcher").map(|_| ()),
            )
        });
        assert_eq!(holder, None);
        let e = lock.unwrap_err().to_string();
        assert!(e.contains("not a regular file") && e.contains("rm "), "{e}");
        within_10_s("sweep_dead", Instance::sweep_dead);
        let e = Instance::new(&link_name)
            .unwrap()
            .lock("renderer")
            .unwrap_err()
            .to_string();
        assert!(e.contains("a symbolic link"), "{e}");
        assert_eq!(std::fs::read_to_string(&target).unwrap(), "precious");
        assert_eq!(Instance::new(&huge_name).unwrap().holder("engine"), None);
        for f in [&fifo, &huge, &link, &target] {
            std::fs::remove_file(f).unwrap();
        }
    }

    #[test]
    fn running_lists_live_holders_and_not_dead_ones() {
        let name = format!("running-test-{}", std::process::id());
        let i = Instance::new(&name).unwrap();
        let held = i.lock("engine").unwrap();
        let running = Instance::running();
        let me = running.iter().find(|r| r.name == name).expect("listed");
        let engine = me.process("engine").expect("engine role");
        assert_eq!(engine.pid, std::process::id());
        assert!(me.process("launcher").is_none());
        // A lock file left by a process that is gone (or a recycled pid running something else).
        let stale = Instance::lock_dir().join(format!("{name}-gone.engine.lock"));
        std::fs::write(
            &stale,
            format!("process {} (not this command)", std::process::id()),
        )
        .unwrap();
        assert!(!Instance::running()
            .iter()
            .any(|r| r.name == format!("{name}-gone")));
        std::fs::remove_file(&stale).unwrap();
        drop(held);
    }

    /// The tests that sweep run one at a time: a sweep removes every dead instance's files, those
    /// another test has just set up to be swept included.
    pub(crate) static SWEEP_TEST: std::sync::Mutex<()> = std::sync::Mutex::new(());

    #[test]
    fn held_locks_are_the_flock_lines_of_proc_locks_not_waiters_or_posix_locks() {
        let h = HeldLocks::parse(
            "1: FLOCK  ADVISORY  WRITE 3064 fe:00:5309073 0 EOF\n\
             2: POSIX  ADVISORY  WRITE 99 fe:00:77 0 EOF\n\
             3: FLOCK  ADVISORY  WRITE 30747 00:2a:10010657 0 EOF\n\
             3: -> FLOCK  ADVISORY  WRITE 31456 00:2a:555 0 EOF\n\
             garbage\n",
        );
        let mut files: Vec<&str> = h.files.iter().map(String::as_str).collect();
        files.sort();
        assert_eq!(files, ["00:2a:10010657", "fe:00:5309073"]);
    }

    /// The lock, not the pid written in it, says whether an instance's owner lives: a held lock
    /// (even one whose text is not written yet) keeps the instance's files; a lock file whose pid
    /// is gone, or whose pid now runs an unrelated process — here this very test, with the very
    /// command line the file records, which the text alone takes for the owner — is swept.
    #[test]
    fn sweep_keeps_a_held_lock_and_sweeps_an_owner_gone_or_its_pid_recycled() {
        let pid = std::process::id();
        let _one_sweep_test_at_a_time = SWEEP_TEST.lock().unwrap_or_else(|e| e.into_inner());
        let live = Instance::new(&format!("held-live-{pid}")).unwrap();
        let gone = Instance::new(&format!("held-gone-{pid}")).unwrap();
        let recycled = Instance::new(&format!("held-recycled-{pid}")).unwrap();
        let held = live.lock("engine").unwrap();
        // Just taken: no pid written yet.
        std::fs::write(held.path(), "").unwrap();
        let mut child = std::process::Command::new("true").spawn().unwrap();
        let gone_pid = child.id();
        child.wait().unwrap();
        let cmdline = std::env::args().collect::<Vec<_>>().join(" ");
        for (i, text) in [
            (&gone, format!("process {gone_pid} (true)")),
            (&recycled, format!("process {pid} ({cmdline})")),
        ] {
            std::fs::write(
                Instance::lock_dir().join(format!("{}.launcher.lock", i.name())),
                text,
            )
            .unwrap();
        }
        let file = |i: &Instance| PathBuf::from(format!("/dev/shm/{}sweep-test", i.file_prefix()));
        for i in [&live, &gone, &recycled] {
            std::fs::write(file(i), b"x").unwrap();
        }
        assert!(
            Instance::running()
                .iter()
                .all(|r| r.name != recycled.name() && r.name != gone.name()),
            "unlocked: not running"
        );
        let removed = Instance::sweep_dead();
        assert!(
            file(&live).exists(),
            "a held lock keeps its instance's files"
        );
        for i in [&gone, &recycled] {
            // (Swept by this sweep, or by another run's at the same moment.)
            assert!(!file(i).exists(), "{} not swept: {removed:?}", i.name());
        }
        std::fs::remove_file(file(&live)).unwrap();
        for i in [&gone, &recycled] {
            std::fs::remove_file(Instance::lock_dir().join(format!("{}.launcher.lock", i.name())))
                .unwrap();
        }
        drop(held);
    }

    /// `holder` (what `lungdyn scene event` asks before sending) goes by the lock, not by the pid
    /// written in it: a lock file nobody holds, whose pid is alive (here this very test — a pid
    /// recycled by an unrelated process looks the same), has no holder; a held one names the pid
    /// even where the kernel's flock table cannot see it (another pid namespace: an empty table
    /// here), because the open-file-description lock answers from anywhere.
    #[test]
    fn the_holder_is_who_holds_the_lock_not_a_live_pid_in_a_stale_file() {
        let pid = std::process::id();
        let i = Instance::new(&format!("holder-test-{pid}")).unwrap();
        let path = Instance::lock_dir().join(format!("{}.engine.lock", i.name()));
        std::fs::create_dir_all(Instance::lock_dir()).unwrap();
        std::fs::write(&path, format!("process {pid} (a stale file)")).unwrap();
        assert_eq!(i.holder("engine"), None, "nobody holds it");
        assert_eq!(lock_held(&path, Some(&HeldLocks::default())), Some(false));
        let held = i.lock("engine").unwrap();
        assert_eq!(i.holder("engine"), Some(pid));
        assert_eq!(
            lock_held(held.path(), Some(&HeldLocks::default())),
            Some(true),
            "the OFD lock answers without the flock table"
        );
        drop(held);
        assert_eq!(i.holder("engine"), None, "released when dropped");
        assert_eq!(lock_held(&path.with_extension("gone"), None), None);
        std::fs::remove_file(&path).unwrap();
    }

    #[test]
    fn streams_and_files_carry_the_instance_name() {
        let i = Instance::new("abc").unwrap();
        assert_eq!(i.engine(), "lungdyn/abc/engine");
        assert_eq!(i.file_prefix(), "lungdyn_abc_");
    }
}
