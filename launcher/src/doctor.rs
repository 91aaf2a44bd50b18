//! `lungdyn doctor`: what the HMD workstation has and lacks for running lungdyn as a service.
//!
//! Every check reads the machine once (the GPU adapter, the displays, the session type, the
//! real-time limits and capabilities, the kernel's isolated cores, the CPU frequency governors, the
//! tracker's serial ports, the OpenIGTLink port, the shared-memory folders) and says ok / warning /
//! missing, what it saw and the command or file that fixes it. The parsing of `/proc` and `/sys`
//! text is pure (unit-tested on fixed strings); only [`run`] touches the machine.

use std::net::TcpListener;
use std::path::{Path, PathBuf};

use lung_model::scene::SceneExt;
use serde::Serialize;

/// Command-line options of `lungdyn doctor`.
#[derive(Debug, Clone, clap::Args)]
pub struct DoctorArgs {
    /// Print `{"checks": [{name, status, detail, fix}]}` instead of the table.
    #[arg(long)]
    pub json: bool,
    /// The scene the service runs: its `[processes] cpus` are checked against the isolated cores.
    #[arg(long, value_name = "FILE")]
    pub scene: Option<PathBuf>,
    /// OpenIGTLink port the tracker-bridge listens on.
    #[arg(long, value_name = "PORT", default_value_t = tracker_bridge::igtl::DEFAULT_PORT,
          value_parser = clap::value_parser!(u16).range(1..))]
    pub igtl_port: u16,
    /// Skip opening the GPU adapter and the display (each can take seconds on a software driver);
    /// both are then reported as warnings saying they were not checked.
    #[arg(long)]
    pub no_gpu: bool,
    /// A remote room's keys (`lungdyn remote keys`) to check: the authority, every certificate
    /// (room, role, expiry) and the private keys (mode 0600, matching their certificates).
    /// Default: the scene's `[remote] keys`.
    #[arg(long, value_name = "DIR")]
    pub keys: Option<PathBuf>,
}

/// How a check came out.
#[derive(Debug, Clone, Copy, PartialEq, Eq, PartialOrd, Ord, Serialize)]
#[serde(rename_all = "lowercase")]
pub enum Status {
    /// Ready for the service.
    Ok,
    /// Works, but not as a workstation should (software GPU, no isolated cores, ...).
    Warning,
    /// lungdyn cannot run as a service until it is fixed.
    Missing,
}

impl Status {
    fn word(self) -> &'static str {
        match self {
            Status::Ok => "ok",
            Status::Warning => "warning",
            Status::Missing => "missing",
        }
    }
}

/// One check's result.
#[derive(Debug, Clone, PartialEq, Eq, Serialize)]
pub struct Check {
    /// Short name (`gpu`, `rtprio`, ...).
    pub name: &'static str,
    /// Ok / warning / missing.
    pub status: Status,
    /// What was seen.
    pub detail: String,
    /// The command or file that fixes it (what to keep doing when ok).
    pub fix: String,
}

fn check(
    name: &'static str,
    status: Status,
    detail: impl Into<String>,
    fix: impl Into<String>,
) -> Check {
    Check {
        name,
        status,
        detail: detail.into(),
        fix: fix.into(),
    }
}

/// Every check, in the order they are printed.
#[derive(Debug, Clone, Serialize)]
pub struct Report {
    /// The checks.
    pub checks: Vec<Check>,
}

impl Report {
    /// The worst status of any check.
    pub fn worst(&self) -> Status {
        self.checks
            .iter()
            .map(|c| c.status)
            .max()
            .unwrap_or(Status::Ok)
    }
}

/// The names of the checks [`run`] makes, in order (the CLI test holds the JSON to this list).
pub const CHECKS: [&str; 15] = [
    "gpu",
    "displays",
    "session",
    "rtprio",
    "memlock",
    "cap_sys_nice",
    "sched_fifo",
    "isolated_cores",
    "cpu_governor",
    "serial_ports",
    "igtl_port",
    "iceoryx2_folders",
    "systemd",
    "remote_keys",
    "cache",
];

/// The real-time priority the units allow (`LimitRTPRIO=` in deploy/*.service).
pub const RTPRIO_WANTED: u64 = 90;
/// Locked memory the units allow is unlimited; below this much, a real-time process that locks its
/// pages (GPU drivers pin staging buffers too) runs out.
pub const MEMLOCK_WANTED_BYTES: u64 = 256 << 20;

/// A soft or hard resource limit from `/proc/<pid>/limits`.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Limit {
    /// A number (bytes, priority, ...).
    Value(u64),
    /// `unlimited`.
    Unlimited,
}

impl Limit {
    fn at_least(self, wanted: u64) -> bool {
        match self {
            Limit::Unlimited => true,
            Limit::Value(v) => v >= wanted,
        }
    }
}

impl std::fmt::Display for Limit {
    fn fmt(&self, f: &mut std::fmt::Formatter<'_>) -> std::fmt::Result {
        match self {
            Limit::Unlimited => f.write_str("unlimited"),
            Limit::Value(v) => write!(f, "{v}"),
        }
    }
}

/// The (soft, hard) limit of the row named `what` (e.g. `Max realtime priority`) in the text of
/// `/proc/<pid>/limits`; `None` when the row is absent or unreadable.
pub fn parse_limit(limits: &str, what: &str) -> Option<(Limit, Limit)> {
    let line = limits.lines().find(|l| {
        l.strip_prefix(what)
            .is_some_and(|rest| rest.starts_with(char::is_whitespace))
    })?;
    let mut fields = line[what.len()..].split_whitespace();
    let one = |s: Option<&str>| match s? {
        "unlimited" => Some(Limit::Unlimited),
        n => n.parse().ok().map(Limit::Value),
    };
    Some((one(fields.next())?, one(fields.next())?))
}

/// The effective capability mask (`CapEff:` in `/proc/<pid>/status`).
pub fn parse_cap_eff(status: &str) -> Option<u64> {
    let hex = status
        .lines()
        .find_map(|l| l.strip_prefix("CapEff:"))?
        .trim();
    u64::from_str_radix(hex, 16).ok()
}

/// CAP_SYS_NICE's bit (linux/capability.h).
pub const CAP_SYS_NICE: u32 = 23;

pub use transport::process::parse_cpu_list;

/// The cores a kernel command line (`/proc/cmdline`) isolates with `key` (`isolcpus` or
/// `nohz_full`): `None` when the key is absent, `Some(Err(value))` when its value is not a CPU list.
/// isolcpus may lead with its flags (`isolcpus=domain,managed_irq,2-3`; kernel-parameters.txt),
/// which are skipped.
pub fn parse_cmdline_cpus(cmdline: &str, key: &str) -> Option<Result<Vec<usize>, String>> {
    let value = cmdline
        .split_whitespace()
        .filter_map(|w| w.split_once('='))
        .filter(|(k, _)| *k == key)
        .map(|(_, v)| v)
        .next_back()?;
    let list: Vec<&str> = value
        .split(',')
        .skip_while(|p| ["domain", "managed_irq", "nohz"].contains(p))
        .collect();
    Some(parse_cpu_list(&list.join(",")).ok_or_else(|| value.to_string()))
}

/// The isolated-cores check from the kernel command line and the scene's `[processes] cpus`.
pub fn isolated_cores_check(cmdline: &str, scene_cpus: &[usize]) -> Check {
    let fix_for = |cpus: &str| {
        format!(
            "add `isolcpus=domain,managed_irq,{cpus} nohz_full={cpus} rcu_nocbs={cpus}` to \
             GRUB_CMDLINE_LINUX in /etc/default/grub, then `sudo update-grub` and reboot (docs/DEPLOY.md)"
        )
    };
    let wanted = if scene_cpus.is_empty() {
        "2-3".to_string()
    } else {
        let mut c = scene_cpus.to_vec();
        c.sort_unstable();
        c.dedup();
        c.iter()
            .map(|c| c.to_string())
            .collect::<Vec<_>>()
            .join(",")
    };
    let iso = parse_cmdline_cpus(cmdline, "isolcpus");
    let nohz = parse_cmdline_cpus(cmdline, "nohz_full");
    match (iso, nohz) {
        (Some(Err(v)), _) | (_, Some(Err(v))) => check(
            "isolated_cores",
            Status::Warning,
            format!("the kernel command line has a CPU list it cannot read: {v:?}"),
            fix_for(&wanted),
        ),
        (None, None) => check(
            "isolated_cores",
            Status::Warning,
            "no isolcpus or nohz_full on the kernel command line: the scheduler and timer ticks \
             share every core with the engine and renderer",
            fix_for(&wanted),
        ),
        (iso, nohz) => {
            let iso = iso.and_then(Result::ok).unwrap_or_default();
            let nohz = nohz.and_then(Result::ok).unwrap_or_default();
            let outside: Vec<usize> = scene_cpus
                .iter()
                .copied()
                .filter(|c| !iso.contains(c))
                .collect();
            let detail = format!("isolcpus {iso:?}, nohz_full {nohz:?}");
            if !outside.is_empty() {
                check(
                    "isolated_cores",
                    Status::Warning,
                    format!("{detail}; the scene pins processes to {outside:?}, which are not isolated"),
                    format!("isolate the scene's cores or change its [processes] cpus to isolated ones; {}", fix_for(&wanted)),
                )
            } else if iso.is_empty() || nohz.is_empty() {
                check(
                    "isolated_cores",
                    Status::Warning,
                    format!("{detail}: isolate both (isolcpus keeps tasks off, nohz_full the timer tick)"),
                    fix_for(&wanted),
                )
            } else {
                check(
                    "isolated_cores",
                    Status::Ok,
                    detail,
                    "keep the kernel command line",
                )
            }
        }
    }
}

/// The governor check from each core's `scaling_governor` (empty: no cpufreq, e.g. a VM).
pub fn governor_check(governors: &[(usize, String)]) -> Check {
    const FIX: &str = "`sudo cpupower frequency-set -g performance` (persist: \
                       /etc/default/cpupower or a udev/systemd-tmpfiles rule, docs/DEPLOY.md)";
    if governors.is_empty() {
        return check(
            "cpu_governor",
            Status::Warning,
            "no /sys/devices/system/cpu/cpu*/cpufreq (a VM, or the driver is not loaded): frequency \
             is up to the host",
            "on bare metal, load the cpufreq driver (intel_pstate/amd-pstate) and set the \
             performance governor",
        );
    }
    let slow: Vec<String> = governors
        .iter()
        .filter(|(_, g)| g.trim() != "performance")
        .map(|(c, g)| format!("cpu{c}={}", g.trim()))
        .collect();
    if slow.is_empty() {
        check(
            "cpu_governor",
            Status::Ok,
            format!("all {} cores use the performance governor", governors.len()),
            "keep the performance governor",
        )
    } else {
        check(
            "cpu_governor",
            Status::Warning,
            format!(
                "{} of {} cores are not on performance ({}): clock ramps add jitter to the frame",
                slow.len(),
                governors.len(),
                slow.join(", ")
            ),
            FIX,
        )
    }
}

/// The real-time priority limit check.
pub fn rtprio_check(limits: Option<(Limit, Limit)>) -> Check {
    const FIX: &str = "the service units set LimitRTPRIO=90 (deploy/); for a login shell add \
                       `@lungdyn - rtprio 90` to /etc/security/limits.d/lungdyn.conf";
    match limits {
        None => check("rtprio", Status::Warning, "cannot read /proc/self/limits", FIX),
        Some((soft, hard)) if soft.at_least(RTPRIO_WANTED) => check(
            "rtprio",
            Status::Ok,
            format!("RLIMIT_RTPRIO soft {soft}, hard {hard}"),
            "keep the limit",
        ),
        Some((soft, hard)) => check(
            "rtprio",
            Status::Warning,
            format!(
                "RLIMIT_RTPRIO soft {soft}, hard {hard}: below {RTPRIO_WANTED}, so this user cannot \
                 give the processes a real-time priority (chrt -f) without CAP_SYS_NICE"
            ),
            FIX,
        ),
    }
}

/// The locked-memory limit check.
pub fn memlock_check(limits: Option<(Limit, Limit)>) -> Check {
    const FIX: &str =
        "the service units set LimitMEMLOCK=infinity (deploy/); for a login shell add \
                       `@lungdyn - memlock unlimited` to /etc/security/limits.d/lungdyn.conf";
    match limits {
        None => check(
            "memlock",
            Status::Warning,
            "cannot read /proc/self/limits",
            FIX,
        ),
        Some((soft, hard)) if soft.at_least(MEMLOCK_WANTED_BYTES) => check(
            "memlock",
            Status::Ok,
            format!("RLIMIT_MEMLOCK soft {soft}, hard {hard} bytes"),
            "keep the limit",
        ),
        Some((soft, hard)) => check(
            "memlock",
            Status::Warning,
            format!(
                "RLIMIT_MEMLOCK soft {soft}, hard {hard} bytes: under {} MiB, too little to lock a \
                 real-time process's pages",
                MEMLOCK_WANTED_BYTES >> 20
            ),
            FIX,
        ),
    }
}

/// The CAP_SYS_NICE check from the effective capability mask.
pub fn cap_sys_nice_check(cap_eff: Option<u64>, rtprio_ok: bool) -> Check {
    match cap_eff {
        None => check(
            "cap_sys_nice",
            Status::Warning,
            "cannot read CapEff from /proc/self/status",
            "run doctor on Linux with /proc mounted",
        ),
        Some(mask) if mask & (1 << CAP_SYS_NICE) != 0 => check(
            "cap_sys_nice",
            Status::Ok,
            format!("CAP_SYS_NICE is effective (CapEff {mask:016x})"),
            "keep it (the units need none: LimitRTPRIO suffices)",
        ),
        Some(mask) => check(
            "cap_sys_nice",
            if rtprio_ok {
                Status::Ok
            } else {
                Status::Warning
            },
            format!(
                "CAP_SYS_NICE is not effective (CapEff {mask:016x}){}",
                if rtprio_ok {
                    "; not needed, RLIMIT_RTPRIO allows real-time priorities"
                } else {
                    ""
                }
            ),
            "raise RLIMIT_RTPRIO (the units' LimitRTPRIO=90), or \
             `sudo setcap cap_sys_nice+ep $(command -v lungdyn)`",
        ),
    }
}

/// Whether SCHED_FIFO is granted, by trying it (transport::realtime::probe_fifo): the limit and the
/// capability checks above can both look fine where a cgroup or a VM still refuses.
pub fn sched_fifo_check(probe: Result<(), String>) -> Check {
    match probe {
        Ok(()) => check(
            "sched_fifo",
            Status::Ok,
            format!(
                "SCHED_FIFO at priority {} granted (tried on a thread)",
                transport::realtime::FIFO_PRIORITY
            ),
            "keep it",
        ),
        Err(why) => check(
            "sched_fifo",
            Status::Warning,
            why,
            "the processes run without real-time priority (a warning says so at start); see the \
             rtprio and cap_sys_nice checks, and where both are fine, the cgroup's or VM's real-time \
             policy named here",
        ),
    }
}

/// The display session from its environment (`XDG_SESSION_TYPE`, `DISPLAY`, `WAYLAND_DISPLAY`).
pub fn session_check(
    session_type: Option<&str>,
    display: Option<&str>,
    wayland: Option<&str>,
) -> Check {
    let seen = format!(
        "XDG_SESSION_TYPE={}, DISPLAY={}, WAYLAND_DISPLAY={}",
        session_type.unwrap_or("(unset)"),
        display.unwrap_or("(unset)"),
        wayland.unwrap_or("(unset)")
    );
    match (display, wayland) {
        (Some(_), None) => check("session", Status::Ok, format!("X11: {seen}"), "keep the X11 session"),
        (Some(_), Some(_)) => check(
            "session",
            Status::Warning,
            format!("Wayland with XWayland: {seen}; lungdyn is built for X11 and runs through XWayland (a compositor's frame of latency)"),
            "log in to an X11 session (GDM: 'Ubuntu on Xorg'; /etc/gdm3/custom.conf WaylandEnable=false)",
        ),
        (None, Some(_)) => check(
            "session",
            Status::Missing,
            format!("Wayland without XWayland: {seen}; lungdyn's window needs X11"),
            "enable XWayland or log in to an X11 session (/etc/gdm3/custom.conf WaylandEnable=false)",
        ),
        (None, None) => check(
            "session",
            Status::Missing,
            format!("no display session: {seen}"),
            "run in the headset's X session (the user unit runs in it; over ssh: `export DISPLAY=:0`), \
             or `xvfb-run -a` for tests",
        ),
    }
}

/// The displays check from winit's list (or why none could be listed).
pub fn displays_check(monitors: Result<&[renderer::window::MonitorInfo], String>) -> Check {
    let fix = "connect the headset and check `xrandr --query`; pick it with `--display NAME|INDEX`";
    match monitors {
        Err(why) => check(
            "displays",
            Status::Missing,
            format!("cannot list displays: {why}"),
            fix,
        ),
        Ok([]) => check(
            "displays",
            Status::Missing,
            "the session reports no displays",
            fix,
        ),
        Ok(list) => {
            let each: Vec<String> = list
                .iter()
                .enumerate()
                .map(|(i, m)| format!("{i}: {m}"))
                .collect();
            check(
                "displays",
                if list.len() >= 2 {
                    Status::Ok
                } else {
                    Status::Warning
                },
                format!(
                    "{}{}",
                    each.join("; "),
                    if list.len() < 2 {
                        "; one display only: the headset is usually a second output beside the console"
                    } else {
                        ""
                    }
                ),
                fix,
            )
        }
    }
}

/// The GPU check from [`renderer::gpu::probe_adapter`]'s answer.
pub fn gpu_check(probe: Result<String, String>) -> Check {
    match probe {
        Err(why) => check(
            "gpu",
            Status::Missing,
            why,
            "install the GPU's Vulkan driver (NVIDIA: the proprietary driver; AMD/Intel: \
             `sudo apt-get install mesa-vulkan-drivers libvulkan1`); check with `vulkaninfo --summary`",
        ),
        Ok(desc) if desc.contains("software rasteriser") => check(
            "gpu",
            Status::Warning,
            format!("{desc}: drawing on the CPU, far from 60 fps at the workstation's sizes"),
            "install the GPU's Vulkan driver; `WGPU_ADAPTER_NAME` picks an adapter when several exist",
        ),
        Ok(desc) => check("gpu", Status::Ok, desc, "keep the driver"),
    }
}

/// Tracker serial devices: (path, readable and writable by this user).
pub fn serial_check(ports: &[(PathBuf, bool)]) -> Check {
    let fix =
        "install deploy/99-lungdyn-tracker.rules (`lungdyn install`) for /dev/lungdyn-tracker \
               and group lungdyn access, then `sudo usermod -aG lungdyn $USER`";
    if ports.is_empty() {
        return check(
            "serial_ports",
            Status::Warning,
            "no /dev/ttyUSB*, /dev/ttyACM*, /dev/serial/by-id or /dev/lungdyn-tracker: no serial \
             tracker is plugged in (an OpenIGTLink source needs none)",
            fix,
        );
    }
    let listed: Vec<String> = ports
        .iter()
        .map(|(p, rw)| {
            format!(
                "{}{}",
                p.display(),
                if *rw { "" } else { " (no read/write access)" }
            )
        })
        .collect();
    let status = if ports.iter().any(|(_, rw)| *rw) {
        Status::Ok
    } else {
        Status::Missing
    };
    check("serial_ports", status, listed.join(", "), fix)
}

fn read(path: &str) -> Option<String> {
    std::fs::read_to_string(path).ok()
}

fn governors() -> Vec<(usize, String)> {
    let mut out = Vec::new();
    let Ok(dir) = std::fs::read_dir("/sys/devices/system/cpu") else {
        return out;
    };
    for e in dir.flatten() {
        let name = e.file_name().to_string_lossy().into_owned();
        let Some(n) = name
            .strip_prefix("cpu")
            .and_then(|n| n.parse::<usize>().ok())
        else {
            continue;
        };
        if let Ok(g) = std::fs::read_to_string(e.path().join("cpufreq/scaling_governor")) {
            out.push((n, g.trim().to_string()));
        }
    }
    out.sort();
    out
}

fn accessible(path: &Path) -> bool {
    use std::os::unix::ffi::OsStrExt;
    let Ok(c) = std::ffi::CString::new(path.as_os_str().as_bytes()) else {
        return false;
    };
    // SAFETY: a valid NUL-terminated path; access(2) only reads it.
    unsafe { libc::access(c.as_ptr(), libc::R_OK | libc::W_OK) == 0 }
}

fn serial_ports() -> Vec<(PathBuf, bool)> {
    let mut ports: Vec<PathBuf> = Vec::new();
    if let Ok(dir) = std::fs::read_dir("/dev") {
        for e in dir.flatten() {
            let n = e.file_name().to_string_lossy().into_owned();
            if n.starts_with("ttyUSB") || n.starts_with("ttyACM") || n == "lungdyn-tracker" {
                ports.push(e.path());
            }
        }
    }
    if let Ok(dir) = std::fs::read_dir("/dev/serial/by-id") {
        ports.extend(dir.flatten().map(|e| e.path()));
    }
    ports.sort();
    ports
        .into_iter()
        .map(|p| (p.clone(), accessible(&p)))
        .collect()
}

fn igtl_check(port: u16) -> Check {
    match TcpListener::bind(("0.0.0.0", port)) {
        Ok(_) => check(
            "igtl_port",
            Status::Ok,
            format!("TCP port {port} is free for the OpenIGTLink server"),
            format!(
                "keep it free; the server serves loopback only until told the tracking PC: \
                 `[tracker] allow = [\"TRACKING_PC_IP\"]` in the scene or `--igtl-allow \
                 TRACKING_PC_IP`, and the firewall: `sudo ufw allow from TRACKING_PC_IP to any port \
                 {port} proto tcp`"
            ),
        ),
        Err(e) => check(
            "igtl_port",
            Status::Missing,
            format!("cannot listen on TCP port {port}: {e}"),
            format!(
                "`sudo ss -ltnp 'sport = :{port}'` shows who holds it (another lungdyn: `lungdyn \
                 instances`); or give the bridge another port (--source igtl:PORT)"
            ),
        ),
    }
}

/// The cache folder ([`renderer::lod_cache::dir_from_env`]): the draw levels kept for large lungs
/// and where the quality governor settled for each setting (the next run starts there: docs/LATENCY.md
/// "Where a run starts"), listed so a person can see why a run starts below full quality.
pub fn cache_check(dir: Option<&Path>) -> Check {
    let fix = "set LUNGDYN_CACHE_DIR to a writable folder (the installed units use systemd's \
               CacheDirectory); `--governor-start full` starts a run at full quality whatever is kept";
    let Some(dir) = dir else {
        return check(
            "cache",
            Status::Warning,
            "no cache folder (LUNGDYN_CACHE_DIR=off, or no HOME): a large lung's draw levels are \
             built at every start and every run starts the governor at full quality",
            fix,
        );
    };
    let entries = match std::fs::read_dir(dir) {
        Ok(e) => e,
        Err(e) if e.kind() == std::io::ErrorKind::NotFound => {
            return check(
                "cache",
                Status::Ok,
                format!(
                    "{} (not made yet: the first run that keeps something makes it)",
                    dir.display()
                ),
                "nothing to do",
            )
        }
        Err(e) => {
            return check(
                "cache",
                Status::Warning,
                format!("{}: {e}", dir.display()),
                fix,
            )
        }
    };
    let (mut levels, mut bytes, mut settled) = (0usize, 0u64, Vec::new());
    for entry in entries.flatten() {
        let name = entry.file_name().to_string_lossy().into_owned();
        if name.starts_with("lod-") && name.ends_with(".bin") {
            levels += 1;
            bytes += entry.metadata().map_or(0, |m| m.len());
        } else if name.starts_with("governor-") && name.ends_with(".json") {
            let kept = std::fs::read(entry.path())
                .ok()
                .and_then(|b| serde_json::from_slice::<renderer::governor_memory::Settled>(&b).ok())
                .map_or_else(
                    || {
                        format!(
                            "{name}: not readable (a run refuses it and starts at full quality)"
                        )
                    },
                    |k| format!("{} on {} ({name})", k.quality, k.adapter),
                );
            settled.push(kept);
        }
    }
    settled.sort();
    let mut detail = format!(
        "{}: {levels} lungs' draw levels ({:.1} MB); where the governor settled: {}",
        dir.display(),
        bytes as f64 / 1e6,
        if settled.is_empty() {
            "nothing kept (runs start at full quality)".to_string()
        } else {
            settled.join("; ")
        }
    );
    match writable(dir) {
        Ok(()) => check("cache", Status::Ok, detail, "nothing to do"),
        Err(e) => {
            detail.push_str(&format!("; not writable ({e}): nothing new is kept"));
            check("cache", Status::Warning, detail, fix)
        }
    }
}

/// Whether a file can be created (and removed) in `dir`.
fn writable(dir: &Path) -> Result<(), String> {
    let probe = dir.join(format!(".lungdyn-doctor-{}", std::process::id()));
    std::fs::write(&probe, b"")
        .and_then(|()| std::fs::remove_file(&probe))
        .map_err(|e| format!("{}: {e}", dir.display()))
}

fn iceoryx_check() -> Check {
    let root = transport::iox::root_path();
    let dirs = [
        PathBuf::from("/dev/shm"),
        root.clone(),
        transport::Instance::lock_dir(),
    ];
    let mut bad = Vec::new();
    for d in &dirs {
        // iceoryx2 and the lock code create their own folders; a missing one is made on first use
        // when its parent is writable.
        let target = if d.exists() {
            d.clone()
        } else {
            d.parent()
                .map(Path::to_path_buf)
                .unwrap_or_else(|| d.clone())
        };
        if let Err(e) = writable(&target) {
            bad.push(e);
        }
    }
    let list = dirs
        .iter()
        .map(|d| d.display().to_string())
        .collect::<Vec<_>>()
        .join(", ");
    if bad.is_empty() {
        check(
            "iceoryx2_folders",
            Status::Ok,
            format!("writable: {list}"),
            "keep them writable",
        )
    } else {
        check(
            "iceoryx2_folders",
            Status::Missing,
            format!("not writable: {}", bad.join("; ")),
            format!(
                "give the service user write access (the units use PrivateTmp=no and /dev/shm), e.g. \
                 `sudo install -d -o lungdyn {}`",
                root.display()
            ),
        )
    }
}

fn systemd_check() -> Check {
    let booted = Path::new("/run/systemd/system").exists();
    let in_unit = std::env::var_os("INVOCATION_ID").is_some();
    if booted {
        check(
            "systemd",
            Status::Ok,
            format!(
                "systemd is the init system{}",
                if in_unit { "; doctor runs inside a unit" } else { "" }
            ),
            "`lungdyn install --prefix /usr/local` then `systemctl --user enable --now lungdyn.target` (docs/DEPLOY.md)",
        )
    } else {
        check(
            "systemd",
            Status::Missing,
            "systemd is not running (no /run/systemd/system; a container?): the service and its \
             watchdog cannot run here",
            "run on the workstation's OS (systemd); meanwhile start the processes with `lungdyn demo`",
        )
    }
}

/// Run every check on this machine.
pub fn run(args: &DoctorArgs) -> anyhow::Result<Report> {
    let scene = args
        .scene
        .as_ref()
        .map(|p| lung_model::scene::Scene::load(p))
        .transpose()?;
    let scene_cpus = scene
        .as_ref()
        .map(|s| s.processes.cpus.clone())
        .unwrap_or_default();
    let remote = scene.as_ref().and_then(|s| s.remote.as_ref());
    let keys_dir = args.keys.clone().or_else(|| {
        let base = args
            .scene
            .as_ref()
            .and_then(|p| p.parent())
            .unwrap_or(Path::new("."));
        remote.and_then(|r| r.keys.as_ref()).map(|k| base.join(k))
    });
    let limits = read("/proc/self/limits").unwrap_or_default();
    let rtprio = parse_limit(&limits, "Max realtime priority");
    let rtprio_ok = rtprio.is_some_and(|(s, _)| s.at_least(RTPRIO_WANTED));
    let env = |k: &str| std::env::var(k).ok().filter(|v| !v.is_empty());
    let (session, display, wayland) = (
        env("XDG_SESSION_TYPE"),
        env("DISPLAY"),
        env("WAYLAND_DISPLAY"),
    );
    let not_checked = |name, what: &str| {
        check(
            name,
            Status::Warning,
            format!("not checked (--no-gpu): {what}"),
            "run `lungdyn doctor` without --no-gpu",
        )
    };
    let gpu = if args.no_gpu {
        not_checked("gpu", "the Vulkan adapter")
    } else {
        gpu_check(renderer::gpu::probe_adapter().map_err(|e| e.to_string()))
    };
    let displays = if args.no_gpu {
        not_checked("displays", "the outputs")
    } else if display.is_none() && wayland.is_none() {
        displays_check(Err("no DISPLAY or WAYLAND_DISPLAY".into()))
    } else {
        let listed = renderer::window::monitors().map_err(|e| e.to_string());
        displays_check(listed.as_deref().map_err(Clone::clone))
    };
    let checks = vec![
        gpu,
        displays,
        session_check(session.as_deref(), display.as_deref(), wayland.as_deref()),
        rtprio_check(rtprio),
        memlock_check(parse_limit(&limits, "Max locked memory")),
        cap_sys_nice_check(
            read("/proc/self/status").as_deref().and_then(parse_cap_eff),
            rtprio_ok,
        ),
        sched_fifo_check(transport::realtime::probe_fifo()),
        isolated_cores_check(&read("/proc/cmdline").unwrap_or_default(), &scene_cpus),
        governor_check(&governors()),
        serial_check(&serial_ports()),
        igtl_check(args.igtl_port),
        iceoryx_check(),
        systemd_check(),
        remote_keys_check(
            keys_dir.as_deref(),
            remote.is_some(),
            keys_dir.as_deref().map(lungdyn_remote::keys::inspect),
            unix_now(),
        ),
        cache_check(renderer::lod_cache::dir_from_env().as_deref()),
    ];
    debug_assert_eq!(checks.iter().map(|c| c.name).collect::<Vec<_>>(), CHECKS);
    Ok(Report { checks })
}

fn unix_now() -> i64 {
    std::time::SystemTime::now()
        .duration_since(std::time::UNIX_EPOCH)
        .map(|d| d.as_secs() as i64)
        .unwrap_or(0)
}

/// A remote room's keys: none named (plain TCP when the scene is remote), or what
/// [`lungdyn_remote::keys::inspect`] found in the folder at `now` (Unix seconds).
fn remote_keys_check(
    dir: Option<&Path>,
    remote_scene: bool,
    found: Option<Result<lungdyn_remote::keys::Inspection, lungdyn_remote::keys::KeysError>>,
    now: i64,
) -> Check {
    const NAME: &str = "remote_keys";
    let make = "lungdyn remote keys --room ROOM --out DIR, then --keys DIR (or [remote] keys)";
    let (Some(dir), Some(found)) = (dir, found) else {
        return if remote_scene {
            check(
                NAME,
                Status::Warning,
                "the scene's [remote] session has no keys: plain TCP, unencrypted, open to anyone \
                 who reaches the port; it stays on this machine (127.0.0.1) unless the scene says \
                 insecure_lab_network = true (a closed lab network only)",
                make,
            )
        } else {
            check(
                NAME,
                Status::Ok,
                "no remote session (no --keys, no [remote] table)",
                "nothing",
            )
        };
    };
    let ins = match found {
        Ok(i) => i,
        Err(e) => return check(NAME, Status::Missing, e.to_string(), make),
    };
    let mut problems: Vec<String> = ins.refused.clone();
    for (name, p) in &ins.keys {
        if let Some(p) = p {
            problems.push(format!("{name}.key: {p}"));
        }
    }
    if !ins.keys.iter().any(|(n, _)| n != "authority") {
        problems.push(format!(
            "no participant's private key in {} (each machine needs its own NAME.key)",
            dir.display()
        ));
    }
    let soonest = ins
        .members
        .iter()
        .map(|m| m.not_after_unix)
        .chain([ins.authority_not_after_unix])
        .min()
        .unwrap_or(now);
    let days = (soonest - now) / 86_400;
    let members: Vec<String> = ins
        .members
        .iter()
        .map(|m| format!("{} ({})", m.name, m.role.name()))
        .collect();
    let detail = format!(
        "room {} in {}: {}; the first certificate expires in {days} day(s)",
        ins.room,
        dir.display(),
        members.join(", ")
    );
    if !problems.is_empty() {
        return check(
            NAME,
            Status::Missing,
            format!("{detail}; {}", problems.join("; ")),
            "fix each named file as it says, or make new keys: lungdyn remote keys",
        );
    }
    if days < 30 {
        return check(
            NAME,
            Status::Warning,
            detail,
            "make the room's keys again before they expire: lungdyn remote keys --room ROOM --out NEW_DIR",
        );
    }
    check(
        NAME,
        Status::Ok,
        detail,
        "keep authority.key off the participants' machines",
    )
}

/// The report as a table: one line per check, then its fix when it is not ok.
pub fn text(r: &Report) -> String {
    let mut out = String::new();
    for c in &r.checks {
        out.push_str(&format!(
            "{:<8} {:<17} {}\n",
            c.status.word(),
            c.name,
            c.detail
        ));
        if c.status != Status::Ok {
            out.push_str(&format!("{:<26} fix: {}\n", "", c.fix));
        }
    }
    let count = |s| r.checks.iter().filter(|c| c.status == s).count();
    out.push_str(&format!(
        "{} ok, {} warning(s), {} missing\n",
        count(Status::Ok),
        count(Status::Warning),
        count(Status::Missing)
    ));
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn remote_keys_are_checked_for_expiry_permissions_and_the_plain_tcp_case() {
        use std::os::unix::fs::PermissionsExt;
        let d = std::env::temp_dir().join(format!("lungdyn-doctor-keys-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&d);
        lungdyn_remote::keys::make(
            "ward",
            &d,
            &lungdyn_remote::keys::default_participants(),
            90,
        )
        .unwrap();
        let now = unix_now();
        let inspect = || Some(lungdyn_remote::keys::inspect(&d));
        let c = remote_keys_check(Some(&d), true, inspect(), now);
        assert_eq!(c.status, Status::Ok, "{c:?}");
        assert!(
            c.detail.contains("room ward") && c.detail.contains("site (site)"),
            "{c:?}"
        );
        // 70 days on: within 30 days of expiry.
        let c = remote_keys_check(Some(&d), true, inspect(), now + 70 * 86_400);
        assert_eq!(c.status, Status::Warning, "{c:?}");
        // A private key others can read.
        std::fs::set_permissions(d.join("site.key"), std::fs::Permissions::from_mode(0o640))
            .unwrap();
        let c = remote_keys_check(Some(&d), true, inspect(), now);
        assert_eq!(c.status, Status::Missing, "{c:?}");
        assert!(c.detail.contains("chmod 600"), "{c:?}");
        // No keys for a remote scene: plain TCP, said as such.
        let c = remote_keys_check(None, true, None, now);
        assert_eq!(c.status, Status::Warning);
        assert!(c.detail.contains("plain TCP"), "{c:?}");
        // A folder that is not a room.
        let c = remote_keys_check(
            Some(Path::new("/nonexistent")),
            true,
            Some(lungdyn_remote::keys::inspect(Path::new("/nonexistent"))),
            now,
        );
        assert_eq!(c.status, Status::Missing);
        assert!(c.detail.contains("not found"), "{c:?}");
        std::fs::remove_dir_all(&d).unwrap();
    }

    const LIMITS: &str =
        "Limit                     Soft Limit           Hard Limit           Units     \n\
        Max cpu time              unlimited            unlimited            seconds   \n\
        Max locked memory         8388608              8388608              bytes     \n\
        Max realtime priority     0                    0                    \n\
        Max realtime timeout      unlimited            unlimited            us        \n";

    #[test]
    fn limits_are_read_by_row_name_with_unlimited() {
        assert_eq!(
            parse_limit(LIMITS, "Max locked memory"),
            Some((Limit::Value(8388608), Limit::Value(8388608)))
        );
        assert_eq!(
            parse_limit(LIMITS, "Max realtime priority"),
            Some((Limit::Value(0), Limit::Value(0)))
        );
        // "Max realtime priority" must not match the "Max realtime timeout" row, nor a prefix.
        assert_eq!(
            parse_limit(LIMITS, "Max realtime timeout"),
            Some((Limit::Unlimited, Limit::Unlimited))
        );
        assert_eq!(parse_limit(LIMITS, "Max realtime"), None);
        assert_eq!(parse_limit("", "Max locked memory"), None);
        assert_eq!(
            parse_limit("Max locked memory  lots  of\n", "Max locked memory"),
            None
        );
    }

    #[test]
    fn rt_limits_are_judged_against_what_the_units_set() {
        let low = parse_limit(LIMITS, "Max realtime priority");
        assert_eq!(rtprio_check(low).status, Status::Warning);
        assert_eq!(
            rtprio_check(Some((Limit::Value(90), Limit::Value(99)))).status,
            Status::Ok
        );
        assert_eq!(rtprio_check(None).status, Status::Warning);
        let mem = parse_limit(LIMITS, "Max locked memory");
        let w = memlock_check(mem);
        assert_eq!(w.status, Status::Warning);
        assert!(
            w.detail.contains("8388608") && w.fix.contains("LimitMEMLOCK"),
            "{w:?}"
        );
        assert_eq!(
            memlock_check(Some((Limit::Unlimited, Limit::Unlimited))).status,
            Status::Ok
        );
    }

    #[test]
    fn cap_sys_nice_is_bit_23_of_cap_eff() {
        let root = "Name:\tx\nCapEff:\t000001ffffffffff\n";
        let user = "Name:\tx\nCapEff:\t0000000000000000\n";
        assert_eq!(parse_cap_eff(root), Some(0x1ff_ffff_ffff));
        assert_eq!(
            cap_sys_nice_check(parse_cap_eff(root), false).status,
            Status::Ok
        );
        assert_eq!(
            cap_sys_nice_check(parse_cap_eff(user), false).status,
            Status::Warning
        );
        assert_eq!(
            cap_sys_nice_check(parse_cap_eff(user), true).status,
            Status::Ok
        );
        assert_eq!(cap_sys_nice_check(Some(1 << 23), false).status, Status::Ok);
        assert_eq!(parse_cap_eff("CapEff:\tzz\n"), None);
        assert_eq!(parse_cap_eff(""), None);
    }

    #[test]
    fn cpu_lists_and_kernel_command_lines() {
        assert_eq!(parse_cpu_list("2-3,5"), Some(vec![2, 3, 5]));
        assert_eq!(parse_cpu_list("5,2-3,3"), Some(vec![2, 3, 5]));
        assert_eq!(parse_cpu_list("3-2"), None);
        assert_eq!(parse_cpu_list("x"), None);
        assert_eq!(parse_cpu_list("0-99999999"), None);
        assert_eq!(parse_cpu_list(""), Some(vec![]));
        let cmd = "BOOT_IMAGE=/vmlinuz root=/dev/sda1 ro quiet isolcpus=domain,managed_irq,2-3 nohz_full=2-3";
        assert_eq!(parse_cmdline_cpus(cmd, "isolcpus"), Some(Ok(vec![2, 3])));
        assert_eq!(parse_cmdline_cpus(cmd, "nohz_full"), Some(Ok(vec![2, 3])));
        assert_eq!(parse_cmdline_cpus(cmd, "rcu_nocbs"), None);
        assert_eq!(
            parse_cmdline_cpus("isolcpus=1,3", "isolcpus"),
            Some(Ok(vec![1, 3]))
        );
        // The last occurrence wins, as in the kernel.
        assert_eq!(
            parse_cmdline_cpus("isolcpus=1 isolcpus=4", "isolcpus"),
            Some(Ok(vec![4]))
        );
        assert_eq!(
            parse_cmdline_cpus("nohz_full=a-b", "nohz_full"),
            Some(Err("a-b".into()))
        );
        // A key that only ends like the one asked for is not it.
        assert_eq!(parse_cmdline_cpus("xisolcpus=1", "isolcpus"), None);
    }

    #[test]
    fn isolated_cores_are_held_to_the_scene() {
        let none = isolated_cores_check("ro quiet", &[]);
        assert_eq!(none.status, Status::Warning);
        assert!(
            none.fix.contains("isolcpus=") && none.fix.contains("/etc/default/grub"),
            "{none:?}"
        );
        let both = "isolcpus=2-3 nohz_full=2-3";
        assert_eq!(isolated_cores_check(both, &[]).status, Status::Ok);
        assert_eq!(isolated_cores_check(both, &[2, 3, 3]).status, Status::Ok);
        let off = isolated_cores_check(both, &[1, 2, 3]);
        assert_eq!(off.status, Status::Warning);
        assert!(
            off.detail.contains("[1]") && off.fix.contains("1,2,3"),
            "{off:?}"
        );
        assert_eq!(
            isolated_cores_check("isolcpus=2-3", &[]).status,
            Status::Warning
        );
        assert_eq!(
            isolated_cores_check("isolcpus=2-x", &[]).status,
            Status::Warning
        );
    }

    #[test]
    fn governors_are_ok_only_when_every_core_is_on_performance() {
        let g = |v: &[&str]| {
            v.iter()
                .enumerate()
                .map(|(i, s)| (i, s.to_string()))
                .collect::<Vec<_>>()
        };
        assert_eq!(
            governor_check(&g(&["performance\n", "performance"])).status,
            Status::Ok
        );
        let w = governor_check(&g(&["performance", "powersave"]));
        assert_eq!(w.status, Status::Warning);
        assert!(
            w.detail.contains("cpu1=powersave") && w.fix.contains("cpupower"),
            "{w:?}"
        );
        assert_eq!(governor_check(&[]).status, Status::Warning);
    }

    #[test]
    fn sessions_gpus_displays_and_ports_say_what_is_missing() {
        assert_eq!(
            session_check(Some("x11"), Some(":0"), None).status,
            Status::Ok
        );
        assert_eq!(
            session_check(Some("wayland"), Some(":0"), Some("wayland-0")).status,
            Status::Warning
        );
        assert_eq!(
            session_check(Some("wayland"), None, Some("wayland-0")).status,
            Status::Missing
        );
        assert_eq!(session_check(None, None, None).status, Status::Missing);
        assert_eq!(gpu_check(Err("no adapter".into())).status, Status::Missing);
        let soft = gpu_check(Ok(
            "llvmpipe (Vulkan, llvmpipe x, a software rasteriser)".into()
        ));
        assert_eq!(soft.status, Status::Warning);
        assert_eq!(
            gpu_check(Ok("NVIDIA RTX (Vulkan, NVIDIA 550)".into())).status,
            Status::Ok
        );
        let m = |name: &str, primary| renderer::window::MonitorInfo {
            name: name.into(),
            width: 1920,
            height: 1080,
            refresh_mhz: Some(60_000),
            modes: 3,
            primary,
        };
        let two = [m("DP-1", true), m("HDMI-1", false)];
        let ok = displays_check(Ok(&two));
        assert_eq!(ok.status, Status::Ok);
        assert!(
            ok.detail.contains("1: HDMI-1 1920x1080 @ 60.00 Hz"),
            "{ok:?}"
        );
        assert_eq!(displays_check(Ok(&two[..1])).status, Status::Warning);
        assert_eq!(displays_check(Ok(&[])).status, Status::Missing);
        assert_eq!(displays_check(Err("x".into())).status, Status::Missing);
        assert_eq!(serial_check(&[]).status, Status::Warning);
        let p = PathBuf::from("/dev/ttyUSB0");
        assert_eq!(serial_check(&[(p.clone(), false)]).status, Status::Missing);
        assert_eq!(serial_check(&[(p, true)]).status, Status::Ok);
    }

    /// The cache folder's check lists where the governor settled (so a run that starts below full
    /// quality is explained), counts the draw levels, names an unreadable memory, and warns where
    /// nothing can be kept.
    #[test]
    fn the_cache_check_says_where_runs_start_and_what_is_kept() {
        let none = cache_check(None);
        assert_eq!(none.status, Status::Warning);
        assert!(none.fix.contains("LUNGDYN_CACHE_DIR"), "{none:?}");
        let dir = std::env::temp_dir().join(format!("lungdyn-doctor-cache-{}", std::process::id()));
        let _ = std::fs::remove_dir_all(&dir);
        let absent = cache_check(Some(&dir));
        assert_eq!(absent.status, Status::Ok);
        assert!(absent.detail.contains("not made yet"), "{absent:?}");
        std::fs::create_dir_all(&dir).unwrap();
        let empty = cache_check(Some(&dir));
        assert!(empty.detail.contains("nothing kept"), "{empty:?}");
        let kept = renderer::governor_memory::Settled {
            format: renderer::governor_memory::FORMAT,
            key: "0123456789abcdef".into(),
            adapter: "llvmpipe (Vulkan) Cpu".into(),
            steps: vec!["MSAA off".into(), "LOD +1".into()],
            given_up: 2,
            quality: "MSAA off, LOD +1".into(),
            bought: vec![2.0, 1.5],
            held_frames: 400,
            frames: 900,
        };
        std::fs::write(
            dir.join("governor-0123456789abcdef.json"),
            serde_json::to_string(&kept).unwrap(),
        )
        .unwrap();
        std::fs::write(dir.join("governor-ffffffffffffffff.json"), "{").unwrap();
        std::fs::write(dir.join("lod-0000000000000001.bin"), [0u8; 1000]).unwrap();
        let c = cache_check(Some(&dir));
        assert_eq!(c.status, Status::Ok, "{c:?}");
        for words in [
            "1 lungs' draw levels",
            "MSAA off, LOD +1 on llvmpipe (Vulkan) Cpu",
            "governor-ffffffffffffffff.json: not readable",
        ] {
            assert!(c.detail.contains(words), "{words}: {}", c.detail);
        }
        let _ = std::fs::remove_dir_all(&dir);
    }
}
