//! What the launcher's commands share around a run of the three processes: a run's merged trace
//! (`--trace`), and what the launcher can read about its children (CPU time from `/proc`). A command
//! watches a demo run through [`crate::demo::Watch`].

use std::path::{Path, PathBuf};

use anyhow::Context;

/// `--trace FILE`: check the file can be written, before any work.
pub fn check_trace(file: Option<&Path>) -> anyhow::Result<()> {
    if let Some(f) = file {
        crate::outputs::check(&crate::outputs::Output {
            flag: "--trace",
            path: f,
            extensions: &["json"],
        })?;
    }
    Ok(())
}

/// Ask the children for their spans: a fresh folder `trace-<instance>` under `out`, named to them in
/// [`transport::trace::ENV_DIR`] (set before they are started; the launcher is single-threaded
/// then). Returns the folder.
pub fn start_trace(out: &Path, instance: &str) -> anyhow::Result<PathBuf> {
    let dir = out.join(format!("trace-{instance}"));
    if dir.exists() {
        std::fs::remove_dir_all(&dir)
            .with_context(|| format!("--trace: cannot clear {}", dir.display()))?;
    }
    std::fs::create_dir_all(&dir)
        .with_context(|| format!("--trace: cannot create {}", dir.display()))?;
    std::env::set_var(transport::trace::ENV_DIR, &dir);
    Ok(dir)
}

/// After the children have stopped: merge their span files from `dir` into `file` (one
/// Chrome/Perfetto trace on CLOCK_MONOTONIC), read their stage timers, remove `dir`, stop asking
/// later children for spans. Returns the stage timers.
pub fn finish_trace(
    dir: &Path,
    file: &Path,
) -> anyhow::Result<Vec<transport::trace::StageSummary>> {
    std::env::remove_var(transport::trace::ENV_DIR);
    let merged = transport::trace::merge(dir, file)?;
    let mut stages = Vec::new();
    for entry in std::fs::read_dir(dir).into_iter().flatten().flatten() {
        let p = entry.path();
        if p.to_string_lossy().ends_with(".stages.tsv") {
            match transport::trace::read_stages(&p) {
                Ok(s) => stages.extend(s),
                Err(e) => eprintln!("lungdyn: warning: --trace: {}: {e}", p.display()),
            }
        }
    }
    stages.sort_by(|a, b| (&a.process, &a.stage).cmp(&(&b.process, &b.stage)));
    let _ = std::fs::remove_dir_all(dir);
    eprintln!(
        "lungdyn: trace of {merged} processes written to {} (open it in ui.perfetto.dev)",
        file.display()
    );
    if merged < 3 {
        eprintln!("lungdyn: warning: --trace: only {merged} of the 3 processes wrote their spans");
    }
    Ok(stages)
}

/// Check a `--vertices`/`--mesh` count against what the mesh generator accepts.
pub fn check_vertices(v: usize) -> anyhow::Result<()> {
    use lung_model::mesh::generate::{MAX_VERTICES, MIN_VERTICES};
    if !(MIN_VERTICES..=MAX_VERTICES).contains(&v) {
        anyhow::bail!(
            "{v} vertices per lung is out of range: use {MIN_VERTICES} to {MAX_VERTICES}"
        );
    }
    Ok(())
}

/// CPU time (user + system) a process has used so far, seconds, from `/proc/PID/stat` (`None` when
/// the process is gone or the file cannot be read).
pub fn process_cpu_s(pid: u32) -> Option<f64> {
    let stat = std::fs::read_to_string(format!("/proc/{pid}/stat")).ok()?;
    cpu_s_of_stat(&stat, clock_ticks_per_s())
}

/// utime + stime (fields 14 and 15 of `/proc/PID/stat`) in seconds. The command name (field 2) is in
/// parentheses and may hold spaces, so fields are counted after its closing parenthesis.
pub fn cpu_s_of_stat(stat: &str, ticks_per_s: f64) -> Option<f64> {
    let rest = &stat[stat.rfind(')')? + 1..];
    let mut f = rest.split_ascii_whitespace();
    // After ")": field 3 (state) is the first; utime is field 14, i.e. the 12th after it.
    let utime: f64 = f.nth(11)?.parse().ok()?;
    let stime: f64 = f.next()?.parse().ok()?;
    Some((utime + stime) / ticks_per_s)
}

/// The calling thread's CPU time (user + system), seconds (`getrusage(RUSAGE_THREAD)`).
pub fn thread_cpu_s() -> f64 {
    // SAFETY: getrusage fills the zeroed struct we pass; it has no other preconditions.
    unsafe {
        let mut u: libc::rusage = std::mem::zeroed();
        if libc::getrusage(libc::RUSAGE_THREAD, &mut u) != 0 {
            return 0.0;
        }
        let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 / 1e6;
        tv(u.ru_utime) + tv(u.ru_stime)
    }
}

fn clock_ticks_per_s() -> f64 {
    // SAFETY: sysconf has no preconditions.
    let t = unsafe { libc::sysconf(libc::_SC_CLK_TCK) };
    if t > 0 {
        t as f64
    } else {
        100.0
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn cpu_time_is_read_after_the_command_name() {
        // A command name with spaces and parentheses must not shift the fields.
        let stat = "4242 (we (ird) name) S 1 2 3 4 5 6 7 8 9 10 250 50 0 0 20 0 1 0";
        assert_eq!(cpu_s_of_stat(stat, 100.0), Some(3.0));
        assert_eq!(cpu_s_of_stat("garbage", 100.0), None);
        assert_eq!(cpu_s_of_stat("1 (x) S 1", 100.0), None);
        let own = process_cpu_s(std::process::id()).unwrap();
        assert!(own >= 0.0 && own.is_finite());
    }

    #[test]
    fn vertex_counts_out_of_the_generators_range_are_refused() {
        assert!(check_vertices(10_000).is_ok());
        let e = check_vertices(5).unwrap_err().to_string();
        assert!(e.contains("5 vertices"), "{e}");
        assert!(check_vertices(usize::MAX).is_err());
    }
}
