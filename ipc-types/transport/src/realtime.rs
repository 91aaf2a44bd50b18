//! Real-time settings of a process, opt-in (`--realtime`, or a scene's `[processes] realtime`):
//! the SCHED_FIFO policy at [`FIFO_PRIORITY`] and every page locked in memory (`mlockall`), so a
//! tick is neither preempted by ordinary work nor stalled by a page fault.
//!
//! Each is tried once at start. Where the kernel refuses, the process keeps running as before and
//! says once, on stderr, which capability or resource limit is missing and how to grant it
//! (`lungdyn doctor` checks the same limits).

/// The SCHED_FIFO priority asked for: below the kernel's own real-time threads (priority 99) and
/// within the `LimitRTPRIO=90` of the installed units.
pub const FIFO_PRIORITY: i32 = 80;

/// What [`apply`] achieved.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Outcome {
    /// SCHED_FIFO at [`FIFO_PRIORITY`]; the reason when refused.
    pub fifo: Result<(), String>,
    /// `mlockall(MCL_CURRENT | MCL_FUTURE)`; the reason when refused.
    pub locked: Result<(), String>,
}

/// A (soft, hard) resource limit, as text (`unlimited` or a number).
fn rlimit(resource: libc::__rlimit_resource_t) -> (String, String) {
    // SAFETY: getrlimit fills the struct we pass; no other preconditions.
    let (soft, hard) = unsafe {
        let mut r: libc::rlimit = std::mem::zeroed();
        if libc::getrlimit(resource, &mut r) != 0 {
            return ("unknown".into(), "unknown".into());
        }
        (r.rlim_cur, r.rlim_max)
    };
    let text = |v: libc::rlim_t| {
        if v == libc::RLIM_INFINITY {
            "unlimited".to_string()
        } else {
            v.to_string()
        }
    };
    (text(soft), text(hard))
}

/// Whether the calling process has capability bit `cap` in its effective set.
fn has_capability(cap: u32) -> bool {
    std::fs::read_to_string("/proc/self/status")
        .ok()
        .and_then(|s| {
            let hex = s.lines().find_map(|l| l.strip_prefix("CapEff:"))?.trim();
            u64::from_str_radix(hex, 16).ok()
        })
        .is_some_and(|caps| caps & (1u64 << cap) != 0)
}

const CAP_IPC_LOCK: u32 = 14;
const CAP_SYS_NICE: u32 = 23;

/// Why the kernel refused SCHED_FIFO (`err`, from `sched_setscheduler`): the resource limit and the
/// capability, and where neither is missing (the refusal then comes from elsewhere), the real-time
/// run time the kernel and this process's cgroup allow.
fn fifo_refusal(err: &std::io::Error) -> String {
    let (soft, hard) = rlimit(libc::RLIMIT_RTPRIO);
    let limit_ok = soft == "unlimited"
        || soft
            .parse::<i64>()
            .is_ok_and(|v| v >= i64::from(FIFO_PRIORITY));
    let cap = has_capability(CAP_SYS_NICE);
    let mut text = format!(
        "cannot run SCHED_FIFO at priority {FIFO_PRIORITY} ({err}): RLIMIT_RTPRIO is soft {soft}, \
         hard {hard} (needs {FIFO_PRIORITY} or more){}",
        if cap {
            ", CAP_SYS_NICE is effective"
        } else {
            " and the process lacks CAP_SYS_NICE"
        }
    );
    if cap || limit_ok {
        // Neither is missing: real-time group scheduling (a cgroup with no cpu.rt_runtime_us) or a
        // sandbox (container, VM) refuses real-time policies whatever the limit says.
        let global = std::fs::read_to_string("/proc/sys/kernel/sched_rt_runtime_us")
            .map(|v| v.trim().to_string())
            .unwrap_or_else(|_| "unreadable".into());
        let group = rt_runtime_of_cgroup()
            .map(|(path, v)| format!("; this cgroup's cpu.rt_runtime_us is {v} ({path})"))
            .unwrap_or_default();
        text.push_str(&format!(
            ", so the refusal comes from elsewhere: kernel.sched_rt_runtime_us is {global}{group}. \
             Give the cgroup real-time run time (cgroup v1 cpu.rt_runtime_us, e.g. systemd's \
             CPUAccounting with a real-time budget), or run outside the container or VM that forbids it"
        ));
    } else {
        text.push_str("; grant it with the units' LimitRTPRIO=90, `ulimit -r 90`, or CAP_SYS_NICE");
    }
    text
}

/// The cgroup v1 `cpu.rt_runtime_us` of this process's cpu controller, with its path, where the
/// kernel has real-time group scheduling (cgroup v2 has no such file).
fn rt_runtime_of_cgroup() -> Option<(String, String)> {
    let cgroups = std::fs::read_to_string("/proc/self/cgroup").ok()?;
    cgroups.lines().find_map(|line| {
        let mut parts = line.splitn(3, ':');
        let (_, controllers, path) = (parts.next()?, parts.next()?, parts.next()?);
        if !controllers.split(',').any(|c| c == "cpu") {
            return None;
        }
        let file = format!("/sys/fs/cgroup/{controllers}{path}/cpu.rt_runtime_us");
        let v = std::fs::read_to_string(&file).ok()?;
        Some((file, v.trim().to_string()))
    })
}

/// Whether this process may run SCHED_FIFO at [`FIFO_PRIORITY`], found by trying it on a thread of
/// its own (which then ends; the calling thread's policy is untouched) — a limit or capability that
/// looks sufficient proves nothing where a cgroup or a VM refuses. `Err` holds the reason as
/// [`apply`] would print it.
pub fn probe_fifo() -> Result<(), String> {
    std::thread::spawn(|| {
        let param = libc::sched_param {
            sched_priority: FIFO_PRIORITY,
        };
        // SAFETY: pid 0 is the calling thread on Linux; `param` outlives the call.
        if unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) } == 0 {
            Ok(())
        } else {
            Err(fifo_refusal(&std::io::Error::last_os_error()))
        }
    })
    .join()
    .unwrap_or_else(|_| Err("the probe thread panicked".into()))
}

/// Switch the calling process to SCHED_FIFO and lock its memory, as far as permitted; `role`
/// names the process in the one-line warning printed for each refusal.
pub fn apply(role: &str) -> Outcome {
    let param = libc::sched_param {
        sched_priority: FIFO_PRIORITY,
    };
    // SAFETY: pid 0 is the calling process; `param` outlives the call.
    let fifo = if unsafe { libc::sched_setscheduler(0, libc::SCHED_FIFO, &param) } == 0 {
        Ok(())
    } else {
        Err(fifo_refusal(&std::io::Error::last_os_error()))
    };
    // SAFETY: mlockall only changes how the kernel pages this process's memory.
    let locked = if unsafe { libc::mlockall(libc::MCL_CURRENT | libc::MCL_FUTURE) } == 0 {
        Ok(())
    } else {
        let err = std::io::Error::last_os_error();
        let (soft, hard) = rlimit(libc::RLIMIT_MEMLOCK);
        Err(format!(
            "cannot lock its memory ({err}): RLIMIT_MEMLOCK is soft {soft}, hard {hard} bytes{}; grant \
             it with the units' LimitMEMLOCK=infinity, `ulimit -l unlimited`, or CAP_IPC_LOCK",
            if has_capability(CAP_IPC_LOCK) {
                ""
            } else {
                " and the process lacks CAP_IPC_LOCK"
            }
        ))
    };
    for e in [&fifo, &locked]
        .into_iter()
        .filter_map(|r| r.as_ref().err())
    {
        crate::process::say(&format!(
            "{role}: warning: real time: {e}; running without it"
        ));
    }
    if fifo.is_ok() && locked.is_ok() {
        crate::process::say(&format!(
            "{role}: real time: SCHED_FIFO priority {FIFO_PRIORITY}, memory locked"
        ));
    }
    Outcome { fifo, locked }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Whatever this machine permits, a refusal names the limit to raise and nothing panics; a
    /// thread of the test runner is put back to SCHED_OTHER afterwards.
    /// The probe agrees with what a real switch achieves on this machine, and leaves the calling
    /// thread's policy alone.
    #[test]
    fn the_probe_agrees_with_a_real_switch() {
        let probed = probe_fifo();
        // SAFETY: sched_getscheduler only reads the calling thread's policy.
        assert_eq!(unsafe { libc::sched_getscheduler(0) }, libc::SCHED_OTHER);
        let applied = std::thread::spawn(|| {
            let out = apply("test");
            // SAFETY: back to the default policy for this thread; munlockall undoes MCL_*.
            unsafe {
                let p = libc::sched_param { sched_priority: 0 };
                libc::sched_setscheduler(0, libc::SCHED_OTHER, &p);
                libc::munlockall();
            }
            out.fifo
        })
        .join()
        .unwrap();
        assert_eq!(probed.is_ok(), applied.is_ok(), "{probed:?} vs {applied:?}");
        if let Err(e) = probed {
            assert!(
                e.contains("SCHED_FIFO") && e.contains("RLIMIT_RTPRIO"),
                "{e}"
            );
        }
    }

    #[test]
    fn a_refusal_names_the_missing_limit() {
        let out = std::thread::spawn(|| {
            let out = apply("test");
            // SAFETY: back to the default policy for this (test) process; munlockall undoes MCL_*.
            unsafe {
                let p = libc::sched_param { sched_priority: 0 };
                libc::sched_setscheduler(0, libc::SCHED_OTHER, &p);
                libc::munlockall();
            }
            out
        })
        .join()
        .unwrap();
        if let Err(e) = &out.fifo {
            assert!(
                e.contains("RLIMIT_RTPRIO") && e.contains("CAP_SYS_NICE"),
                "{e}"
            );
        }
        if let Err(e) = &out.locked {
            assert!(
                e.contains("RLIMIT_MEMLOCK") && e.contains("CAP_IPC_LOCK"),
                "{e}"
            );
        }
    }
}
