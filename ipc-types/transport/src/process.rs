//! What every lungdyn process does besides its work: its common options, how long it runs, which
//! core it runs on, and how it prints an error.

use std::path::PathBuf;

use thiserror::Error;

/// The longest `--seconds` a process accepts: one week. Beyond that the nanosecond deadline
/// arithmetic would approach overflow and no session is that long.
pub const MAX_SECONDS: f64 = 7.0 * 86_400.0;

/// Options every lungdyn process that reads a scene takes (flattened into its own options).
#[derive(Debug, Clone, clap::Args)]
pub struct ProcessArgs {
    /// Instance name shared by the three processes of one run (service and file names derive from it).
    #[arg(long, default_value = "default")]
    pub instance: String,
    /// Scene file (TOML) with every lung's kernel: what `lungdyn scene prepare` or `lungdyn demo`
    /// writes (`out/kernels/scene.resolved.toml`).
    #[arg(long)]
    pub scene: Option<PathBuf>,
    /// Pin this process to CPU core N.
    #[arg(long, value_name = "N")]
    pub cpu: Option<usize>,
    /// Stop after this many seconds (runs until SIGINT/SIGTERM when omitted); at most one week.
    #[arg(long, value_name = "S")]
    pub seconds: Option<f64>,
    /// Run SCHED_FIFO with locked memory where permitted (a warning names the missing capability or
    /// limit where not); also the scene's `[processes] realtime`.
    #[arg(long)]
    pub realtime: bool,
}

/// A bad option common to all processes.
#[derive(Debug, Clone, PartialEq, Error)]
pub enum ArgError {
    /// `--seconds` is not a positive, finite number of seconds up to [`MAX_SECONDS`].
    #[error(
        "--seconds {0} must be a positive number of seconds, at most {MAX_SECONDS} (one week)"
    )]
    Seconds(f64),
}

impl ProcessArgs {
    /// The run time as nanoseconds, validated: `None` runs until terminated.
    pub fn run_ns(&self) -> Result<Option<u64>, ArgError> {
        run_ns(self.seconds)
    }
}

/// Validate a `--seconds` value and convert it to nanoseconds.
pub fn run_ns(seconds: Option<f64>) -> Result<Option<u64>, ArgError> {
    match seconds {
        None => Ok(None),
        Some(s) if s.is_finite() && s > 0.0 && s <= MAX_SECONDS => Ok(Some((s * 1e9) as u64)),
        Some(s) => Err(ArgError::Seconds(s)),
    }
}

/// Pin the calling thread to CPU `core` if one is given (`role` names the process in errors).
pub fn pin_to_core(core: Option<usize>, role: &str) -> Result<(), PinError> {
    let Some(id) = core else { return Ok(()) };
    let cores = core_affinity::get_core_ids().unwrap_or_default();
    let available = cores.len();
    let err = || PinError {
        role: role.to_string(),
        core: id,
        available,
    };
    let c = cores.into_iter().find(|c| c.id == id).ok_or_else(err)?;
    if core_affinity::set_for_current(c) {
        Ok(())
    } else {
        Err(err())
    }
}

/// A kernel CPU list (`2-3,5`, as in `isolcpus=` and /sys/devices/system/cpu/isolated) as sorted
/// cores; `None` if any part is not one.
pub fn parse_cpu_list(list: &str) -> Option<Vec<usize>> {
    let mut cpus = Vec::new();
    for part in list.trim().split(',').filter(|p| !p.is_empty()) {
        match part.split_once('-') {
            Some((a, b)) => {
                let (a, b): (usize, usize) = (a.parse().ok()?, b.parse().ok()?);
                if b < a || b - a > 4096 {
                    return None;
                }
                cpus.extend(a..=b);
            }
            None => cpus.push(part.parse().ok()?),
        }
    }
    cpus.sort_unstable();
    cpus.dedup();
    Some(cpus)
}

/// The cores the kernel keeps other tasks off (`isolcpus`, read from
/// /sys/devices/system/cpu/isolated); empty when none or unreadable.
pub fn isolated_cores() -> Vec<usize> {
    std::fs::read_to_string("/sys/devices/system/cpu/isolated")
        .ok()
        .and_then(|s| parse_cpu_list(&s))
        .unwrap_or_default()
}

/// A process could not be pinned to the core it was given.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
#[error("{role}: cannot pin to CPU core {core} ({available} cores available to this process)")]
pub struct PinError {
    /// Process role.
    pub role: String,
    /// Core asked for.
    pub core: usize,
    /// Cores this process may use.
    pub available: usize,
}

/// One line for an error and its causes, skipping causes the message already contains (error types
/// that embed their source's text would otherwise print it twice).
pub fn describe_error(e: &(dyn std::error::Error + 'static)) -> String {
    let mut text = e.to_string();
    let mut cause = e.source();
    while let Some(c) = cause {
        let s = c.to_string();
        if !text.contains(&s) {
            text.push_str(": ");
            text.push_str(&s);
        }
        cause = c.source();
    }
    text
}

/// Write `line` and a newline to stderr in one `write(2)`: the three processes share the launcher's
/// stderr, and `eprintln!` may split a line into several writes that another process's line can
/// land between (a pipe keeps one write of up to 4 KiB whole). Errors are ignored, as `eprintln!`
/// would panic on them at exit.
pub fn say(line: &str) {
    use std::io::Write;
    let mut buf = String::with_capacity(line.len() + 1);
    buf.push_str(line);
    buf.push('\n');
    let _ = std::io::stderr().lock().write_all(buf.as_bytes());
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn seconds_must_be_finite_positive_and_bounded() {
        assert_eq!(run_ns(None).unwrap(), None);
        assert_eq!(run_ns(Some(1.5)).unwrap(), Some(1_500_000_000));
        assert_eq!(
            run_ns(Some(MAX_SECONDS)).unwrap(),
            Some(604_800_000_000_000)
        );
        for bad in [0.0, -1.0, f64::NAN, f64::INFINITY, 1e30, MAX_SECONDS * 1.01] {
            let e = run_ns(Some(bad)).unwrap_err();
            assert!(e.to_string().contains("--seconds"), "{e}");
        }
    }

    #[test]
    fn pinning_to_a_core_that_does_not_exist_names_the_role() {
        let e = pin_to_core(Some(100_000), "engine").unwrap_err();
        assert!(
            e.to_string()
                .starts_with("engine: cannot pin to CPU core 100000"),
            "{e}"
        );
        assert!(pin_to_core(None, "engine").is_ok());
    }

    #[test]
    fn causes_are_listed_once() {
        #[derive(Debug, Error)]
        #[error("outer")]
        struct Outer(#[source] std::io::Error);
        let e = Outer(std::io::Error::other("inner"));
        assert_eq!(describe_error(&e), "outer: inner");
    }
}
