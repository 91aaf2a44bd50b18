//! What a process costs: its CPU time (`getrusage`) and the bytes its TCP sockets carried
//! (`TCP_INFO` on each of its own sockets) — the harness's source runs in its own process so that
//! both are the source's alone (Zenoh's runtime threads are shared by every session of a process).

/// CPU time (user + system), seconds, of the whole process (`RUSAGE_SELF`: every thread, Zenoh's
/// included) or of the calling thread (`RUSAGE_THREAD`).
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Who {
    /// Every thread of this process.
    Process,
    /// The calling thread.
    Thread,
}

/// CPU time of `who`, seconds (0 when the call fails, which it does not on Linux).
pub fn cpu_s(who: Who) -> f64 {
    let w = match who {
        Who::Process => libc::RUSAGE_SELF,
        Who::Thread => libc::RUSAGE_THREAD,
    };
    // SAFETY: getrusage fills the zeroed struct we pass; it has no other preconditions.
    unsafe {
        let mut u: libc::rusage = std::mem::zeroed();
        if libc::getrusage(w, &mut u) != 0 {
            return 0.0;
        }
        let tv = |t: libc::timeval| t.tv_sec as f64 + t.tv_usec as f64 / 1e6;
        tv(u.ru_utime) + tv(u.ru_stime)
    }
}

/// Bytes over this process's TCP sockets now, socket by socket (by the socket's inode): (sent
/// and acknowledged, received) (`tcpi_bytes_acked` and `tcpi_bytes_received` of Linux's
/// `tcp_info`, kernel 4.1 on). On loopback every byte sent is acknowledged within microseconds, so
/// the first is the bytes sent.
#[derive(Debug, Clone, Default)]
pub struct TcpBytes(std::collections::BTreeMap<String, (u64, u64)>);

impl TcpBytes {
    /// (sent, received) since `earlier`: each socket's growth, a socket opened since counted
    /// whole. A socket closed in between no longer counts (its last bytes are lost to the
    /// measure); before this was per socket, a link replaced during a run made the process's sum
    /// fall and the run's bytes read 0.
    pub fn since(&self, earlier: &TcpBytes) -> (u64, u64) {
        self.0.iter().fold((0, 0), |(s, r), (ino, (s1, r1))| {
            let (s0, r0) = earlier.0.get(ino).copied().unwrap_or((0, 0));
            (s + s1.saturating_sub(s0), r + r1.saturating_sub(r0))
        })
    }
}

/// This process's TCP sockets' bytes now ([`TcpBytes`]); `None` where `/proc/self/fd` cannot be
/// read or the kernel's `tcp_info` is too short.
pub fn tcp_bytes() -> Option<TcpBytes> {
    // struct tcp_info: 8 one-byte fields, 24 u32 (to tcpi_total_retrans), then u64 pacing_rate,
    // max_pacing_rate, bytes_acked (offset 120), bytes_received (offset 128).
    const ACKED: usize = 120;
    const RECEIVED: usize = 128;
    let mut out = TcpBytes::default();
    let mut any_short = false;
    for entry in std::fs::read_dir("/proc/self/fd").ok()?.flatten() {
        let Ok(target) = std::fs::read_link(entry.path()) else {
            continue;
        };
        let target = target.to_string_lossy().into_owned();
        if !target.starts_with("socket:") {
            continue;
        }
        let Some(fd) = entry
            .file_name()
            .to_str()
            .and_then(|s| s.parse::<i32>().ok())
        else {
            continue;
        };
        let mut buf = [0u8; 256];
        let mut len = buf.len() as libc::socklen_t;
        // SAFETY: `buf` is writable for `len` bytes; getsockopt writes at most `len` and sets
        // `len` to what it wrote. A descriptor closed meanwhile or not a TCP socket fails cleanly.
        let rc = unsafe {
            libc::getsockopt(
                fd,
                libc::IPPROTO_TCP,
                libc::TCP_INFO,
                buf.as_mut_ptr().cast(),
                &mut len,
            )
        };
        if rc != 0 {
            continue;
        }
        if (len as usize) < RECEIVED + 8 {
            any_short = true;
            continue;
        }
        let at = |o: usize| u64::from_ne_bytes(buf[o..o + 8].try_into().expect("8 bytes"));
        out.0.insert(target, (at(ACKED), at(RECEIVED)));
    }
    (!any_short).then_some(out)
}

/// How late a thread stepped its ticks: each tick's actual step time (taken after the step) minus
/// the time it was scheduled for, ms. The harness reports it for the source and for each site: the
/// drift at actual step times is, to first order, the *difference* of two engines' lateness times
/// the breath's volume rate, so a constant per-step lateness at one side is a constant drift.
#[derive(Debug, Clone, Copy, Default, PartialEq, serde::Serialize, serde::Deserialize)]
pub struct Lateness {
    /// Ticks counted.
    pub ticks: usize,
    /// Mean, ms.
    pub mean_ms: f64,
    /// Median, ms.
    pub p50_ms: f64,
    /// 90th percentile, ms.
    pub p90_ms: f64,
    /// 99th percentile, ms.
    pub p99_ms: f64,
    /// Largest, ms.
    pub max_ms: f64,
}

impl Lateness {
    /// The figures of `(scheduled ns, actual ns)` pairs (a tick stepped early counts negative);
    /// all zero for none.
    pub fn of(ticks: impl Iterator<Item = (i128, i128)>) -> Self {
        let mut ms: Vec<f64> = ticks.map(|(s, a)| (a - s) as f64 / 1e6).collect();
        if ms.is_empty() {
            return Self::default();
        }
        ms.sort_by(f64::total_cmp);
        // Nearest rank: the smallest value with at least q of them at or below it.
        let q = |q: f64| ms[((q * ms.len() as f64).ceil() as usize).clamp(1, ms.len()) - 1];
        Self {
            ticks: ms.len(),
            mean_ms: ms.iter().sum::<f64>() / ms.len() as f64,
            p50_ms: q(0.5),
            p90_ms: q(0.9),
            p99_ms: q(0.99),
            max_ms: ms[ms.len() - 1],
        }
    }
}

/// The machine's 1-minute load average (`/proc/loadavg`), where the system has one: reports say
/// how busy the machine was while they measured.
pub fn load_average() -> Option<f64> {
    std::fs::read_to_string("/proc/loadavg")
        .ok()?
        .split_whitespace()
        .next()?
        .parse()
        .ok()
}

#[cfg(test)]
mod tests {
    use super::*;
    use std::io::{Read, Write};

    #[test]
    fn bytes_written_to_a_loopback_socket_are_counted_both_ways() {
        let l = std::net::TcpListener::bind("127.0.0.1:0").unwrap();
        let mut a = std::net::TcpStream::connect(l.local_addr().unwrap()).unwrap();
        let (mut b, _) = l.accept().unwrap();
        let before = tcp_bytes().unwrap();
        a.write_all(&[7u8; 10_000]).unwrap();
        let mut got = vec![0u8; 10_000];
        b.read_exact(&mut got).unwrap();
        // Both ends are this process's: 10 000 bytes sent (and acknowledged) and received, plus
        // whatever other tests' sockets carried meanwhile.
        let mut ok = false;
        for _ in 0..100 {
            let (s, r) = tcp_bytes().unwrap().since(&before);
            if s >= 10_000 && r >= 10_000 {
                ok = true;
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(10));
        }
        assert!(ok);
        // A socket opened after the first reading is counted whole, and one that closed no
        // longer takes its bytes off the others'.
        let mut c = std::net::TcpStream::connect(l.local_addr().unwrap()).unwrap();
        let (mut d, _) = l.accept().unwrap();
        let middle = tcp_bytes().unwrap();
        drop((a, b));
        c.write_all(&[1u8; 5_000]).unwrap();
        let mut got = vec![0u8; 5_000];
        d.read_exact(&mut got).unwrap();
        let mut ok = false;
        for _ in 0..100 {
            let (s, r) = tcp_bytes().unwrap().since(&middle);
            if s >= 5_000 && r >= 5_000 {
                ok = true;
                break;
            }
            std::thread::sleep(std::time::Duration::from_millis(10));
        }
        assert!(ok);
    }

    #[test]
    fn cpu_time_grows_with_work() {
        let (p0, t0) = (cpu_s(Who::Process), cpu_s(Who::Thread));
        let mut x = 0u64;
        let start = std::time::Instant::now();
        while start.elapsed() < std::time::Duration::from_millis(50) {
            x = x.wrapping_mul(6364136223846793005).wrapping_add(1);
        }
        std::hint::black_box(x);
        let thread = cpu_s(Who::Thread) - t0;
        let process = cpu_s(Who::Process) - p0;
        assert!(thread > 0.0, "{thread}");
        // The process's time includes this thread's (read after it; 1 ms for the clock's grain).
        assert!(process >= thread - 1e-3, "{process} < {thread}");
    }

    #[test]
    fn lateness_is_actual_minus_scheduled_with_nearest_rank_percentiles() {
        assert_eq!(Lateness::of(std::iter::empty()), Lateness::default());
        // 100 ticks late by 0.01, 0.02, ..., 1.00 ms (in reverse order), scheduled anywhere.
        let l = Lateness::of(
            (1..=100)
                .rev()
                .map(|k| (k * 7_000_000, k * 7_000_000 + k * 10_000)),
        );
        assert_eq!(l.ticks, 100);
        assert!((l.mean_ms - 0.505).abs() < 1e-12, "{l:?}");
        assert_eq!(
            (l.p50_ms, l.p90_ms, l.p99_ms, l.max_ms),
            (0.5, 0.9, 0.99, 1.0)
        );
        // A tick stepped before its time counts negative.
        let early = Lateness::of([(2_000_000, 1_500_000)].into_iter());
        assert_eq!((early.mean_ms, early.max_ms), (-0.5, -0.5));
    }
}
