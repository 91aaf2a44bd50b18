//! `lungdyn install --prefix DIR [--user]`: the HMD workstation's service, written under one prefix.
//!
//! One systemd unit per process (`lungdyn-tracker-bridge`, `lungdyn-engine`, `lungdyn-renderer`)
//! and a `lungdyn.target` that starts the three (docs/DEPLOY.md argues this against one unit for
//! the launcher): each `Type=notify` with its own `WatchdogSec`, `Restart=on-failure` within a start
//! limit, `LimitRTPRIO`/`LimitMEMLOCK`, and `CPUAffinity` from the scene's `[processes] cpus`. Also
//! the binary, the scene prepared with its kernels (the processes never bake), and a udev rule that
//! names the tracker's USB serial adapter `/dev/lungdyn-tracker` with the service's group access.
//! Nothing is written outside the prefix; every file is written atomically; the report lists them.
//! The unit text is made by pure functions ([`unit`], [`target`], [`udev_rule`]), tested here and
//! checked with `systemd-analyze verify` by the tests crate where that tool exists.

use std::path::{Path, PathBuf};

use lung_model::scene::SceneExt;
use serde::Serialize;

/// Command-line options of `lungdyn install`.
#[derive(Debug, Clone, clap::Args)]
pub struct InstallArgs {
    /// Folder to install under (created): PREFIX/bin, PREFIX/share/lungdyn, the units and the udev
    /// rule. /usr/local for a system install, ~/.local with --user.
    #[arg(long, value_name = "DIR")]
    pub prefix: PathBuf,
    /// User units (PREFIX/share/systemd/user, started with the graphical session: the renderer
    /// draws on the logged-in user's X display) instead of system units (PREFIX/lib/systemd/system,
    /// run as --group's user).
    #[arg(long)]
    pub user: bool,
    /// The scene the service runs (prepared here: its kernels baked into PREFIX/share/lungdyn); the
    /// built-in scene when omitted. Its [processes] cpus become each unit's CPUAffinity, its
    /// [tracker] table the bridge's source and posture (the bridge reads it from the prepared scene).
    #[arg(long, value_name = "FILE")]
    pub scene: Option<PathBuf>,
    /// Instance name the three processes share.
    #[arg(long, default_value = "workstation")]
    pub instance: String,
    /// The tracker's USB serial adapter, VENDOR:PRODUCT in hex (`lsusb`); NDI's USB converter is an
    /// FTDI 0403:6001.
    #[arg(long, value_name = "VID:PID", default_value = "0403:6001", value_parser = parse_usb_id)]
    pub tracker_usb: UsbId,
    /// Group (and, for system units, user) of the service; the udev rule gives it the tracker port.
    #[arg(long, default_value = "lungdyn", value_parser = parse_name)]
    pub group: String,
    /// The headset's display the renderer fills (borderless fullscreen, stereo side by side), by
    /// name (e.g. DP-1) or index as `lungdyn doctor` lists them; the primary display by default.
    #[arg(long, value_name = "NAME|INDEX")]
    pub display: Option<renderer::window::DisplaySel>,
    /// Watchdog timeout, seconds: a process that stops pinging this long is restarted.
    #[arg(long, value_name = "S", default_value_t = 2,
          value_parser = clap::value_parser!(u32).range(1..=600))]
    pub watchdog_sec: u32,
    /// Print the report as JSON.
    #[arg(long)]
    pub json: bool,
}

/// A USB vendor and product id.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct UsbId {
    /// idVendor.
    pub vendor: u16,
    /// idProduct.
    pub product: u16,
}

/// `VVVV:PPPP` (hex, as `lsusb` prints them).
pub fn parse_usb_id(s: &str) -> Result<UsbId, String> {
    let bad = || format!("{s:?} is not VENDOR:PRODUCT in hex as lsusb prints it (e.g. 0403:6001)");
    let (v, p) = s.split_once(':').ok_or_else(bad)?;
    let hex = |x: &str| {
        if x.len() == 4 {
            u16::from_str_radix(x, 16).map_err(|_| bad())
        } else {
            Err(bad())
        }
    };
    Ok(UsbId {
        vendor: hex(v)?,
        product: hex(p)?,
    })
}

/// A user or group name systemd and udev accept (`[a-z_][a-z0-9_-]*`, at most 31 characters).
pub fn parse_name(s: &str) -> Result<String, String> {
    let ok = !s.is_empty()
        && s.len() <= 31
        && s.starts_with(|c: char| c.is_ascii_lowercase() || c == '_')
        && s.chars()
            .all(|c| c.is_ascii_lowercase() || c.is_ascii_digit() || c == '_' || c == '-');
    if ok {
        Ok(s.to_string())
    } else {
        Err(format!(
            "{s:?} is not a user/group name (lowercase letters, digits, _ and -, at most 31)"
        ))
    }
}

/// The service's processes: the three in the scene's `[processes] cpus` order, and a shared
/// session's relay when the scene is a session's source.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Role {
    /// tracker-bridge.
    TrackerBridge,
    /// engine.
    Engine,
    /// renderer.
    Renderer,
    /// `remote serve`: the engine's control state to the remote sites (a `[remote]` source only).
    Remote,
}

impl Role {
    /// The three every workstation runs, in the cpus order.
    pub const ALL: [Role; 3] = [Role::TrackerBridge, Role::Engine, Role::Renderer];

    /// The subcommand (and unit suffix).
    pub fn name(self) -> &'static str {
        match self {
            Role::TrackerBridge => "tracker-bridge",
            Role::Engine => "engine",
            Role::Renderer => "renderer",
            Role::Remote => "remote",
        }
    }

    fn what(self) -> &'static str {
        match self {
            Role::TrackerBridge => "tracker poses to shared memory",
            Role::Engine => "the breathing state, one tick per tracker frame",
            Role::Renderer => "the deformed lungs, side-by-side stereo on the headset",
            Role::Remote => "the engine's control state to the shared session's sites over Zenoh",
        }
    }

    /// The processes a scene's service runs: the three, and `remote serve` beside a `[remote]`
    /// source. A site's or an observer's scene is refused: its engine follows a source (`lungdyn
    /// remote join`), which these units do not run, so they would show a breath of its own.
    pub fn for_scene(scene: &lung_model::scene::Scene) -> anyhow::Result<Vec<Role>> {
        use lung_model::scene_remote::RemoteRole;
        let mut roles = Role::ALL.to_vec();
        match scene.remote.as_ref().map(|r| r.role) {
            None => {}
            Some(RemoteRole::Source) => roles.push(Role::Remote),
            Some(role @ (RemoteRole::Site | RemoteRole::Observer)) => anyhow::bail!(
                "the scene's [remote] role is \"{}\": lungdyn install sets up a workstation that \
                 runs its own engine (and, for a session's source, `lungdyn-remote serve` beside \
                 it); a site's engine follows the source, so run it as `lungdyn remote join --scene \
                 SCENE --instance NAME` with a renderer on that instance (docs/REMOTE.md)",
                if role == RemoteRole::Site { "site" } else { "observer" }
            ),
        }
        Ok(roles)
    }

    /// The thin binary the unit runs, as installed (`cargo build` names it after its crate,
    /// [`Role::name`]; installed with the `lungdyn-` prefix, so /usr/local/bin gets no bare
    /// `engine`).
    pub fn binary(self) -> String {
        format!("lungdyn-{}", self.name())
    }

    /// The unit's file name.
    pub fn unit_name(self) -> String {
        format!("lungdyn-{}.service", self.name())
    }
}

/// What every unit needs to know.
#[derive(Debug, Clone, PartialEq)]
pub struct UnitSettings {
    /// The folder of the installed binaries (absolute): each unit runs its thin role binary there,
    /// `lungdyn-<role>`.
    pub bin_dir: PathBuf,
    /// The prepared scene (absolute).
    pub scene: PathBuf,
    /// Instance name.
    pub instance: String,
    /// Cores for tracker-bridge, engine, renderer (empty: unpinned).
    pub cpus: Vec<usize>,
    /// User units (else system units run as `group`).
    pub user: bool,
    /// Service group.
    pub group: String,
    /// The display the renderer fills (`None`: the primary).
    pub display: Option<renderer::window::DisplaySel>,
    /// Watchdog timeout, s.
    pub watchdog_sec: u32,
}

/// A path as one systemd command-line word: `%` and `$` escaped; refused when it holds whitespace,
/// quotes, backslashes or control characters (systemd would split or reinterpret it).
pub fn systemd_word(p: &Path) -> Result<String, String> {
    let s = p.to_str().ok_or_else(|| {
        format!(
            "{} is not UTF-8; systemd units need UTF-8 paths",
            p.display()
        )
    })?;
    if s.chars()
        .any(|c| c.is_whitespace() || c.is_control() || matches!(c, '"' | '\'' | '\\' | ';'))
    {
        return Err(format!(
            "{s:?} holds whitespace, a quote, a backslash or ';', which a systemd ExecStart= line \
             would split; install under a plain path (e.g. /usr/local or ~/.local)"
        ));
    }
    Ok(s.replace('%', "%%").replace('$', "$$"))
}

/// The unit of one process.
pub fn unit(role: Role, s: &UnitSettings) -> Result<String, String> {
    let name = role.name();
    // The relay is not one of the three pinned processes: it runs unpinned.
    let cpu = Role::ALL
        .iter()
        .position(|r| *r == role)
        .and_then(|i| s.cpus.get(i))
        .copied();
    let mut exec = format!(
        "{}{} --instance {}",
        systemd_word(&s.bin_dir.join(role.binary()))?,
        if role == Role::Remote { " serve" } else { "" },
        s.instance
    );
    // Every process reads its own tables from the prepared scene (the bridge its [tracker] source
    // and posture): no scene value is written into the unit.
    exec.push_str(&format!(" --scene {}", systemd_word(&s.scene)?));
    if role == Role::Renderer {
        exec.push_str(" --fullscreen");
        if let Some(d) = &s.display {
            // `--display=VALUE`: a display named "--help" stays a display name, not an option.
            exec.push_str(&format!(
                " --display={}",
                systemd_word(Path::new(&d.to_string()))?
            ));
        }
    }
    if let Some(c) = cpu {
        exec.push_str(&format!(" --cpu {c}"));
    }
    let mut u = format!(
        "# Written by `lungdyn install` (docs/DEPLOY.md); rerun it rather than editing this file.\n\
         [Unit]\n\
         Description=lungdyn {name}: {}\n\
         PartOf=lungdyn.target\n\
         # At most 20 starts a minute: a process that keeps failing stays down and says why \
         (`journalctl -u {}`); with RestartSec=300ms that is 6 s or more of retries, room for X or \
         the tracker's device to come up at boot.\n\
         StartLimitIntervalSec=60\n\
         StartLimitBurst=20\n",
        role.what(),
        role.unit_name()
    );
    if role == Role::Renderer && s.user {
        u.push_str("After=graphical-session.target\n");
    }
    if role == Role::Remote {
        u.push_str(&remote_service(&exec));
    } else {
        u.push_str(&notify_service(&exec, s.watchdog_sec));
    }
    if let Some(c) = cpu {
        u.push_str(&format!("CPUAffinity={c}\n"));
    }
    if role == Role::Renderer {
        // systemd makes the folder, owned by the unit's user, and names it in $CACHE_DIRECTORY.
        u.push_str(
            "# Large lungs' draw levels, kept between starts (renderer/src/lod_cache.rs).\n\
             CacheDirectory=lungdyn\n",
        );
    }
    u.push_str(&format!(
        "# stderr goes to the journal: journalctl -t lungdyn-{name}\n\
         StandardError=journal\n\
         SyslogIdentifier=lungdyn-{name}\n"
    ));
    if !s.user {
        u.push_str(&format!("User={0}\nGroup={0}\n", s.group));
        if role == Role::Renderer {
            u.push_str(
                "# The headset's X display; its session must admit this user \
                 (`xhost +SI:localuser:lungdyn`, docs/DEPLOY.md).\n\
                 Environment=DISPLAY=:0\n",
            );
        }
    }
    u.push_str("\n[Install]\nWantedBy=lungdyn.target\n");
    Ok(u)
}

/// The `[Service]` section of a process on the frame's path: notify and watchdog, real-time limits.
fn notify_service(exec: &str, watchdog_sec: u32) -> String {
    format!(
        "\n[Service]\n\
         # READY=1 once its ports are open; WATCHDOG=1 from its loop every WatchdogSec/2.\n\
         Type=notify\n\
         NotifyAccess=main\n\
         ExecStart={exec}\n\
         Restart=on-failure\n\
         # A hung loop stops pinging: systemd aborts it at most WatchdogSec after the hang and starts\n\
         # it again RestartSec later, so it is back within WatchdogSec + 1 s (start to READY took\n\
         # 0.05-0.2 s: deploy/watchdog_check.sh). StartLimitBurst keeps a crash loop from spinning.\n\
         RestartSec=300ms\n\
         WatchdogSec={}\n\
         TimeoutStartSec=120\n\
         # Stop: SIGTERM then SIGCONT, latched by the process (a later SIGCONT cannot cancel it);\n\
         # SIGKILL after TimeoutStopSec.\n\
         TimeoutStopSec=5\n\
         LimitRTPRIO=90\n\
         LimitMEMLOCK=infinity\n",
        watchdog_sec
    )
}

/// The `[Service]` section of the session's relay: off the frame's path (it reads the engine's
/// control state and sends it on), so no watchdog and no real-time limits; it waits for the
/// engine's stream and is restarted like the others when it fails.
fn remote_service(exec: &str) -> String {
    format!(
        "After=lungdyn-engine.service\n\
         \n[Service]\n\
         Type=simple\n\
         ExecStart={exec}\n\
         Restart=on-failure\n\
         RestartSec=1s\n\
         TimeoutStopSec=5\n"
    )
}

/// The target that starts the service's processes (`roles`, [`Role::for_scene`]).
pub fn target(user: bool, roles: &[Role]) -> String {
    let wants: Vec<String> = roles.iter().map(|r| r.unit_name()).collect();
    let wants = wants.join(" ");
    let names: Vec<&str> = roles.iter().map(|r| r.name()).collect();
    let names = names.join(", ");
    let (after, wanted_by) = if user {
        ("graphical-session.target", "graphical-session.target")
    } else {
        ("network-online.target", "graphical.target")
    };
    format!(
        "# Written by `lungdyn install` (docs/DEPLOY.md).\n\
         [Unit]\n\
         Description=lungdyn on the HMD workstation ({names})\n\
         Wants={wants}\n\
         After={after}\n\
         \n\
         [Install]\n\
         WantedBy={wanted_by}\n"
    )
}

/// The udev rule: the tracker's USB serial adapter as /dev/lungdyn-tracker, read/write for `group`.
pub fn udev_rule(id: UsbId, group: &str) -> String {
    format!(
        "# Written by `lungdyn install` (docs/DEPLOY.md): the tracker's USB serial adapter \
         ({:04x}:{:04x}) as\n\
         # /dev/lungdyn-tracker, read/write for group {group} (start the bridge with \
         --source ndi-serial:/dev/lungdyn-tracker).\n\
         # Install: sudo cp THIS /etc/udev/rules.d/ && sudo udevadm control --reload && sudo udevadm trigger\n\
         SUBSYSTEM==\"tty\", ATTRS{{idVendor}}==\"{:04x}\", ATTRS{{idProduct}}==\"{:04x}\", \
         SYMLINK+=\"lungdyn-tracker\", GROUP=\"{group}\", MODE=\"0660\"\n",
        id.vendor, id.product, id.vendor, id.product
    )
}

/// One file `install` wrote.
#[derive(Debug, Clone, Serialize)]
pub struct Written {
    /// Path.
    pub path: String,
    /// What it is.
    pub what: String,
}

/// What `lungdyn install` did and what the administrator does next.
#[derive(Debug, Clone, Serialize)]
pub struct InstallReport {
    /// The prefix (absolute).
    pub prefix: String,
    /// Files written, in order.
    pub written: Vec<Written>,
    /// The folder of the units.
    pub unit_dir: String,
    /// Commands to run next (as root where they say sudo).
    pub next: Vec<String>,
}

fn write_file(path: &Path, bytes: &[u8], mode: u32) -> anyhow::Result<()> {
    use std::os::unix::fs::PermissionsExt;
    if let Some(dir) = path.parent() {
        std::fs::create_dir_all(dir)
            .map_err(|e| anyhow::anyhow!("cannot create {}: {e}", dir.display()))?;
    }
    outfile::write_atomically(path, |w| {
        use std::io::Write;
        w.get_ref()
            .set_permissions(std::fs::Permissions::from_mode(mode))?;
        w.write_all(bytes)
    })?;
    Ok(())
}

/// The thin role binaries built beside `exe` (`cargo build --release` puts `engine`, `renderer`
/// and `tracker-bridge` in the same folder as `lungdyn`): each found and answering `--help` as
/// that role, or an error naming the build command — the units never run the whole `lungdyn`
/// (with lung-bake, plotters and zenoh) as a service.
pub fn thin_binaries(exe: &Path, roles: &[Role]) -> anyhow::Result<Vec<(Role, PathBuf)>> {
    let dir = exe.parent().unwrap_or(Path::new("."));
    let build = if roles.contains(&Role::Remote) {
        "cargo build --release -p engine -p renderer -p tracker-bridge -p lungdyn-remote"
    } else {
        "cargo build --release -p engine -p renderer -p tracker-bridge"
    };
    let missing: Vec<String> = roles
        .iter()
        .map(|r| dir.join(r.name()))
        .filter(|p| !p.is_file())
        .map(|p| p.display().to_string())
        .collect();
    if !missing.is_empty() {
        anyhow::bail!(
            "the processes' own binaries are not beside {} (missing: {}): the units run the thin \
             role binaries, not lungdyn; build them with `{build}` and run install again",
            exe.display(),
            missing.join(", ")
        );
    }
    roles
        .iter()
        .map(|&role| {
            let path = dir.join(role.name());
            let out = std::process::Command::new(&path)
                .arg("--help")
                .stdin(std::process::Stdio::null())
                .output()
                .map_err(|e| anyhow::anyhow!("cannot run {} --help: {e}", path.display()))?;
            let help = String::from_utf8_lossy(&out.stdout);
            if !(out.status.success() && help.starts_with(&format!("lungdyn {}", role.name()))) {
                anyhow::bail!(
                    "{} is not lungdyn's {} binary (its --help does not say so); rebuild with \
                     `{build}`",
                    path.display(),
                    role.name()
                );
            }
            Ok((role, path))
        })
        .collect()
}

/// The commands to run as root after the install (udev rule, group, the units enabled).
fn next_steps(args: &InstallArgs, rule: &Path, unit_dir: &Path) -> Vec<String> {
    let g = &args.group;
    let mut next = vec![
        format!("sudo cp {} /etc/udev/rules.d/ && sudo udevadm control --reload && sudo udevadm trigger", rule.display()),
        format!("sudo groupadd -f -r {g} && sudo usermod -aG {g} $USER"),
    ];
    if args.user {
        let standard = dirs_user_unit_dir();
        if standard.as_deref() != Some(unit_dir) {
            next.push(format!(
                "systemctl --user link {}/*.service {}/lungdyn.target   # {} is not in the user manager's search path",
                unit_dir.display(),
                unit_dir.display(),
                unit_dir.display()
            ));
        }
        next.push(
            "systemctl --user daemon-reload && systemctl --user enable --now lungdyn.target".into(),
        );
        next.push("sudo loginctl enable-linger $USER   # start at boot, before a login".into());
    } else {
        next.push(format!(
            "sudo useradd -r -g {g} -G video,render,dialout {g}   # once"
        ));
        if !unit_dir.starts_with("/usr/local/lib/systemd/system")
            && !unit_dir.starts_with("/etc/systemd/system")
        {
            next.push(format!(
                "sudo systemctl link {0}/*.service {0}/lungdyn.target   # {0} is not in systemd's search path",
                unit_dir.display()
            ));
        }
        next.push(
            "sudo systemctl daemon-reload && sudo systemctl enable --now lungdyn.target".into(),
        );
    }
    next.push("lungdyn doctor; journalctl -f -t lungdyn-engine -t lungdyn-renderer -t lungdyn-tracker-bridge".into());
    next
}

/// Install under `args.prefix`.
pub fn run(args: &InstallArgs) -> anyhow::Result<InstallReport> {
    transport::Instance::new(&args.instance)?;
    let prefix = std::path::absolute(&args.prefix)
        .map_err(|e| anyhow::anyhow!("--prefix {}: {e}", args.prefix.display()))?;
    systemd_word(&prefix).map_err(|e| anyhow::anyhow!("--prefix: {e}"))?;
    if prefix.exists() && !prefix.is_dir() {
        anyhow::bail!("--prefix {} is not a folder", prefix.display());
    }
    // Check the scene before writing anything.
    let scene = lung_model::scene::Scene::load_or_default(args.scene.as_deref())?;
    tracker_bridge::source::SourceSpec::parse(&scene.tracker.source)?;
    let mut written = Vec::new();
    let mut wrote = |path: PathBuf, what: &str| {
        written.push(Written {
            path: path.display().to_string(),
            what: what.to_string(),
        })
    };

    let exe = std::env::current_exe()?;
    // The thin role binaries the units run, found beside this one before anything is written.
    let roles = Role::for_scene(&scene)?;
    let thin = thin_binaries(&exe, &roles)?;
    let bin_dir = prefix.join("bin");
    let bin = bin_dir.join("lungdyn");
    let bytes =
        std::fs::read(&exe).map_err(|e| anyhow::anyhow!("cannot read {}: {e}", exe.display()))?;
    write_file(&bin, &bytes, 0o755)?;
    wrote(
        bin.clone(),
        "the lungdyn binary (install, doctor, scene event, instances: the tools, not the service)",
    );
    for (role, from) in thin {
        let to = bin_dir.join(role.binary());
        let bytes = std::fs::read(&from)
            .map_err(|e| anyhow::anyhow!("cannot read {}: {e}", from.display()))?;
        write_file(&to, &bytes, 0o755)?;
        wrote(
            to,
            &format!(
                "the {} process's own binary (its unit runs it: {})",
                role.name(),
                role.what()
            ),
        );
    }

    let share = prefix.join("share/lungdyn");
    crate::outputs::check_writable(&share)?;
    // The scene's own files travel with it: the installed scene keeps working once the folder it
    // came from is gone.
    let (prepared, carried) = crate::prepare::prepare_carrying(
        scene.clone(),
        &share.join("kernels"),
        Some(&share.join("files")),
    )?;
    for k in &prepared.kernels {
        wrote(
            PathBuf::from(&k.path),
            &format!("the {} lung's kernel", k.lung),
        );
    }
    for c in &carried {
        wrote(
            PathBuf::from(&c.to),
            &format!("{} (copied from {})", c.key, c.from),
        );
    }
    let scene = prepared.scene;
    let scene_path = std::path::absolute(&prepared.path)?;
    wrote(
        scene_path.clone(),
        "the prepared scene the engine and renderer load",
    );

    let settings = UnitSettings {
        bin_dir,
        scene: scene_path,
        instance: args.instance.clone(),
        cpus: scene.processes.cpus.clone(),
        user: args.user,
        group: args.group.clone(),
        display: args.display.clone(),
        watchdog_sec: args.watchdog_sec,
    };
    let unit_dir = if args.user {
        prefix.join("share/systemd/user")
    } else {
        prefix.join("lib/systemd/system")
    };
    let mut units = Vec::new();
    for &role in &roles {
        let text = unit(role, &settings).map_err(anyhow::Error::msg)?;
        units.push((
            unit_dir.join(role.unit_name()),
            text,
            format!("the {} unit", role.name()),
        ));
    }
    units.push((
        unit_dir.join("lungdyn.target"),
        target(args.user, &roles),
        format!("the target starting all {}", roles.len()),
    ));
    for (path, text, what) in units {
        write_file(&path, text.as_bytes(), 0o644)?;
        wrote(path, &what);
    }
    let rule = prefix.join("lib/udev/rules.d/99-lungdyn-tracker.rules");
    write_file(
        &rule,
        udev_rule(args.tracker_usb, &args.group).as_bytes(),
        0o644,
    )?;
    wrote(
        rule.clone(),
        "the udev rule naming the tracker's serial adapter",
    );

    let next = next_steps(args, &rule, &unit_dir);
    Ok(InstallReport {
        prefix: prefix.display().to_string(),
        written,
        unit_dir: unit_dir.display().to_string(),
        next,
    })
}

/// `$XDG_DATA_HOME/systemd/user` (default ~/.local/share/systemd/user): where the user manager
/// finds units under a ~/.local prefix.
fn dirs_user_unit_dir() -> Option<PathBuf> {
    std::env::var_os("XDG_DATA_HOME")
        .map(PathBuf::from)
        .or_else(|| std::env::var_os("HOME").map(|h| PathBuf::from(h).join(".local/share")))
        .map(|d| d.join("systemd/user"))
}

/// The report as text.
pub fn text(r: &InstallReport) -> String {
    let mut out = String::new();
    for w in &r.written {
        out.push_str(&format!("wrote {}: {}\n", w.path, w.what));
    }
    out.push_str("next:\n");
    for n in &r.next {
        out.push_str(&format!("  {n}\n"));
    }
    out
}

#[cfg(test)]
mod tests {
    use super::*;

    fn settings(user: bool, cpus: Vec<usize>) -> UnitSettings {
        UnitSettings {
            bin_dir: "/usr/local/bin".into(),
            scene: "/usr/local/share/lungdyn/kernels/scene.resolved.toml".into(),
            instance: "workstation".into(),
            cpus,
            user,
            group: "lungdyn".into(),
            display: None,
            watchdog_sec: 2,
        }
    }

    #[test]
    fn units_carry_the_watchdog_restart_limits_and_the_scenes_cores() {
        let s = settings(false, vec![1, 2, 3]);
        let e = unit(Role::Engine, &s).unwrap();
        for line in [
            "Type=notify",
            "WatchdogSec=2",
            "Restart=on-failure",
            "RestartSec=300ms",
            "StartLimitIntervalSec=60",
            "StartLimitBurst=20",
            "LimitRTPRIO=90",
            "LimitMEMLOCK=infinity",
            "CPUAffinity=2",
            "User=lungdyn",
            "SyslogIdentifier=lungdyn-engine",
            "PartOf=lungdyn.target",
            "ExecStart=/usr/local/bin/lungdyn-engine --instance workstation --scene \
             /usr/local/share/lungdyn/kernels/scene.resolved.toml --cpu 2",
        ] {
            assert!(e.lines().any(|l| l == line), "{line:?} missing in:\n{e}");
        }
        let b = unit(Role::TrackerBridge, &s).unwrap();
        assert!(
            b.contains(
                "ExecStart=/usr/local/bin/lungdyn-tracker-bridge --instance workstation --scene \
                 /usr/local/share/lungdyn/kernels/scene.resolved.toml --cpu 1\n"
            ),
            "{b}"
        );
        assert!(b.contains("CPUAffinity=1\n"));
        let r = unit(Role::Renderer, &s).unwrap();
        assert!(
            r.contains("--fullscreen --cpu 3\n")
                && r.contains("Environment=DISPLAY=:0")
                && r.contains("CacheDirectory=lungdyn\n"),
            "{r}"
        );
        // The headset's display by name; a name systemd would split is refused.
        let mut named = settings(false, vec![1, 2, 3]);
        named.display = Some("DP-1".parse().unwrap());
        let r = unit(Role::Renderer, &named).unwrap();
        assert!(r.contains("--fullscreen --display=DP-1 --cpu 3\n"), "{r}");
        named.display = Some("HDMI 1".parse().unwrap());
        assert!(unit(Role::Renderer, &named).is_err());
        // User units: no User=, no CPUAffinity without cores, the renderer after the session.
        let u = unit(Role::Renderer, &settings(true, vec![])).unwrap();
        assert!(
            !u.contains("User=") && !u.contains("CPUAffinity") && !u.contains("--cpu"),
            "{u}"
        );
        assert!(u.contains("After=graphical-session.target"));
        assert!(target(true, &Role::ALL).contains("WantedBy=graphical-session.target"));
        assert!(target(false, &Role::ALL).contains(
            "Wants=lungdyn-tracker-bridge.service lungdyn-engine.service lungdyn-renderer.service"
        ));
    }

    #[test]
    fn a_sessions_source_installs_its_relay_unpinned_and_a_site_is_refused() {
        let source = lung_model::scene::Scene::parse(
            "[remote]\nrole = \"source\"\nroom = \"ward-3\"\n",
            "source.toml",
        )
        .unwrap();
        let roles = Role::for_scene(&source).unwrap();
        assert_eq!(
            roles,
            [
                Role::TrackerBridge,
                Role::Engine,
                Role::Renderer,
                Role::Remote
            ]
        );
        assert_eq!(
            Role::for_scene(&lung_model::scene::Scene::default()).unwrap(),
            Role::ALL
        );
        let s = settings(false, vec![1, 2, 3]);
        let u = unit(Role::Remote, &s).unwrap();
        for line in [
            "ExecStart=/usr/local/bin/lungdyn-remote serve --instance workstation --scene \
             /usr/local/share/lungdyn/kernels/scene.resolved.toml",
            "Type=simple",
            "Restart=on-failure",
            "After=lungdyn-engine.service",
            "PartOf=lungdyn.target",
            "SyslogIdentifier=lungdyn-remote",
            "User=lungdyn",
        ] {
            assert!(u.lines().any(|l| l == line), "{line:?} missing in:\n{u}");
        }
        // Off the frame's path: no watchdog, no real-time limits, no core of the three.
        for absent in [
            "WatchdogSec",
            "LimitRTPRIO",
            "CPUAffinity",
            "--cpu",
            "Type=notify",
        ] {
            assert!(!u.contains(absent), "{absent} in:\n{u}");
        }
        assert!(target(false, &roles).contains(
            "Wants=lungdyn-tracker-bridge.service lungdyn-engine.service lungdyn-renderer.service \
             lungdyn-remote.service"
        ));
        for role in ["site", "observer"] {
            let site = lung_model::scene::Scene::parse(
                &format!(
                    "[remote]\nrole = \"{role}\"\nroom = \"ward-3\"\nconnect = \
                     [\"tcp/10.0.0.1:7447\"]\n"
                ),
                "site.toml",
            )
            .unwrap();
            let e = Role::for_scene(&site).unwrap_err().to_string();
            assert!(e.contains(role) && e.contains("lungdyn remote join"), "{e}");
        }
    }

    #[test]
    fn paths_systemd_would_split_are_refused_and_specifiers_escaped() {
        assert_eq!(
            systemd_word(Path::new("/opt/a%b$c")).unwrap(),
            "/opt/a%%b$$c"
        );
        for bad in [
            "/tmp/a b",
            "/tmp/a\"b",
            "/tmp/a\\b",
            "/tmp/a;b",
            "/tmp/a\nb",
        ] {
            assert!(systemd_word(Path::new(bad)).is_err(), "{bad:?}");
        }
        let mut s = settings(true, vec![]);
        // No scene value reaches a unit: a source with quotes, backslashes or spaces stays in the
        // scene file, which the bridge reads (`--scene`), where TOML's quoting holds it.
        let u = unit(Role::TrackerBridge, &s).unwrap();
        assert!(!u.contains("--source") && !u.contains("--posture"), "{u}");
        s.scene = "/x y/scene.toml".into();
        for role in Role::ALL {
            assert!(unit(role, &s).is_err(), "{role:?}");
        }
    }

    #[test]
    fn usb_ids_and_group_names() {
        assert_eq!(
            parse_usb_id("0403:6001"),
            Ok(UsbId {
                vendor: 0x0403,
                product: 0x6001
            })
        );
        assert_eq!(
            parse_usb_id("ABCD:ef01"),
            Ok(UsbId {
                vendor: 0xabcd,
                product: 0xef01
            })
        );
        for bad in [
            "0403",
            "403:6001",
            "0403:60011",
            "zzzz:6001",
            "0403:",
            ":",
            "",
        ] {
            assert!(parse_usb_id(bad).is_err(), "{bad:?}");
        }
        let rule = udev_rule(parse_usb_id("0403:6001").unwrap(), "lungdyn");
        assert!(
            rule.contains(
                "SUBSYSTEM==\"tty\", ATTRS{idVendor}==\"0403\", ATTRS{idProduct}==\"6001\", \
             SYMLINK+=\"lungdyn-tracker\", GROUP=\"lungdyn\", MODE=\"0660\""
            ),
            "{rule}"
        );
        assert!(parse_name("lungdyn").is_ok() && parse_name("_svc-1").is_ok());
        for bad in ["", "Lungdyn", "1abc", "a b", "a\"b", &"x".repeat(32)] {
            assert!(parse_name(bad).is_err(), "{bad:?}");
        }
    }
}
