//! Stage spans of every process on one timeline (`--trace FILE` on `lungdyn demo` and `lungdyn
//! latency`): each process records its `tracing` spans of target [`TARGET`] into a bounded ring,
//! preallocated at start, and writes it at exit as Chrome trace events (`ph: "X"`, microseconds of
//! CLOCK_MONOTONIC, the process's pid and each thread's tid); the launcher merges the files into one
//! JSON trace that ui.perfetto.dev and chrome://tracing open, the three processes on one clock.
//!
//! Off by default: without [`ENV_DIR`] no subscriber is installed and a span costs one relaxed load
//! (tracing's disabled callsite). On, a span costs two clock reads and four atomic stores — no
//! allocation, no lock: the span's id carries its start time and its name's slot, and the ring
//! overwrites its oldest events when full.

use std::io::Write;
use std::path::{Path, PathBuf};
use std::sync::atomic::{AtomicPtr, AtomicU64, AtomicUsize, Ordering};
use std::sync::OnceLock;

use tracing::span::{Attributes, Id, Record};
use tracing::subscriber::Interest;
use tracing::{Event, Metadata, Subscriber};

/// The target of lungdyn's stage spans (`tracing::info_span!(target: TARGET, "tick")`); spans of
/// other targets (libraries) are never recorded.
pub const TARGET: &str = "lungdyn";
/// The folder each process writes its spans into (set by the launcher for its children).
pub const ENV_DIR: &str = "LUNGDYN_TRACE_DIR";
/// Spans each process keeps (the newest; about 90 s of three processes' stages at 60 Hz).
pub const RING_EVENTS: usize = 1 << 14;
/// Distinct span names a process may use.
const MAX_NAMES: usize = 64;
const START_SHIFT: u32 = 8;

/// Sub-buckets per power of two of a stage's time histogram (at most 12.5 % over per percentile).
const SUB: usize = 8;
const BUCKETS: usize = 64 * SUB;

/// One stage's timer (a counters struct like rapier's `StagesCounters`, one per span name): count,
/// total, maximum and a log-linear histogram of its times, all atomics, preallocated — so a stage
/// is timed over the whole run, however long, while the ring keeps only the newest spans.
struct StageTimer {
    count: AtomicU64,
    total_ns: AtomicU64,
    max_ns: AtomicU64,
    buckets: Box<[AtomicU64]>,
}

impl StageTimer {
    fn new() -> Self {
        StageTimer {
            count: AtomicU64::new(0),
            total_ns: AtomicU64::new(0),
            max_ns: AtomicU64::new(0),
            buckets: (0..BUCKETS).map(|_| AtomicU64::new(0)).collect(),
        }
    }

    fn record(&self, ns: u64) {
        self.count.fetch_add(1, Ordering::Relaxed);
        self.total_ns.fetch_add(ns, Ordering::Relaxed);
        self.max_ns.fetch_max(ns, Ordering::Relaxed);
        self.buckets[bucket_of(ns)].fetch_add(1, Ordering::Relaxed);
    }

    /// The upper bound of the bucket holding quantile `q`, ns (capped at the maximum).
    fn quantile_ns(&self, q: f64) -> u64 {
        let n = self.count.load(Ordering::Relaxed);
        if n == 0 {
            return 0;
        }
        let rank = ((q * n as f64).ceil() as u64).clamp(1, n);
        let mut seen = 0;
        for (i, b) in self.buckets.iter().enumerate() {
            seen += b.load(Ordering::Relaxed);
            if seen >= rank {
                return bucket_upper(i).min(self.max_ns.load(Ordering::Relaxed));
            }
        }
        self.max_ns.load(Ordering::Relaxed)
    }
}

/// Log-linear bucket of `ns`: exact below [`SUB`], then [`SUB`] buckets per power of two.
fn bucket_of(ns: u64) -> usize {
    if ns < SUB as u64 {
        return ns as usize;
    }
    let octave = 63 - ns.leading_zeros() as usize; // >= 3
    let sub = ((ns >> (octave - 3)) & (SUB as u64 - 1)) as usize;
    ((octave - 2) * SUB + sub).min(BUCKETS - 1)
}

/// The largest value of bucket `i`.
fn bucket_upper(i: usize) -> u64 {
    if i < SUB {
        return i as u64;
    }
    let octave = i / SUB + 2;
    let sub = (i % SUB) as u64;
    let upper = (u128::from(SUB as u64 + sub + 1) << (octave - 3)) - 1;
    upper.min(u128::from(u64::MAX)) as u64
}

struct Slot {
    name: AtomicU64,
    start: AtomicU64,
    end: AtomicU64,
    tid: AtomicU64,
}

/// The process's span ring and its span names.
struct Ring {
    role: &'static str,
    dir: PathBuf,
    names: [AtomicPtr<Metadata<'static>>; MAX_NAMES],
    timers: Box<[StageTimer]>,
    slots: Box<[Slot]>,
    head: AtomicUsize,
}

static RING: OnceLock<Ring> = OnceLock::new();

impl Ring {
    /// The name slot of a callsite, registering it (once per callsite, at its first use).
    fn slot_of(&self, meta: &'static Metadata<'static>) -> Option<usize> {
        let ptr = meta as *const Metadata<'static> as *mut Metadata<'static>;
        for (i, n) in self.names.iter().enumerate() {
            let cur = n.load(Ordering::Acquire);
            if cur == ptr {
                return Some(i);
            }
            if cur.is_null()
                && n.compare_exchange(
                    std::ptr::null_mut(),
                    ptr,
                    Ordering::AcqRel,
                    Ordering::Acquire,
                )
                .map_or_else(|won| won == ptr, |_| true)
            {
                return Some(i);
            }
        }
        None
    }
}

thread_local! {
    static TID: u64 = {
        // SAFETY: gettid has no preconditions.
        unsafe { libc::syscall(libc::SYS_gettid) as u64 }
    };
}

/// The subscriber: a span's id is `start_ns << 8 | name_slot + 1`.
struct RingSubscriber;

impl Subscriber for RingSubscriber {
    fn register_callsite(&self, meta: &'static Metadata<'static>) -> Interest {
        if meta.is_span() && meta.target() == TARGET {
            Interest::always()
        } else {
            Interest::never()
        }
    }

    fn enabled(&self, meta: &Metadata<'_>) -> bool {
        meta.is_span() && meta.target() == TARGET
    }

    fn new_span(&self, span: &Attributes<'_>) -> Id {
        let slot = RING
            .get()
            .and_then(|r| r.slot_of(span.metadata()))
            .map_or(MAX_NAMES as u64, |s| s as u64);
        Id::from_u64((crate::now_ns() << START_SHIFT) | (slot + 1))
    }

    fn record(&self, _: &Id, _: &Record<'_>) {}
    fn record_follows_from(&self, _: &Id, _: &Id) {}
    fn event(&self, _: &Event<'_>) {}
    fn enter(&self, _: &Id) {}

    fn exit(&self, span: &Id) {
        let Some(ring) = RING.get() else { return };
        let id = span.into_u64();
        let slot = (id & ((1 << START_SHIFT) - 1)) - 1;
        if slot >= MAX_NAMES as u64 {
            return;
        }
        let start = id >> START_SHIFT;
        let end = crate::now_ns();
        ring.timers[slot as usize].record(end.saturating_sub(start));
        let i = ring.head.fetch_add(1, Ordering::Relaxed) % ring.slots.len();
        let s = &ring.slots[i];
        s.name.store(slot + 1, Ordering::Relaxed);
        s.start.store(start, Ordering::Relaxed);
        s.end.store(end, Ordering::Relaxed);
        s.tid.store(TID.with(|t| *t), Ordering::Relaxed);
    }
}

/// Start recording this process's spans if the launcher asked for a trace ([`ENV_DIR`] set):
/// preallocates the ring and installs the subscriber. Returns whether tracing is on. Call once, at
/// start, before the loop.
pub fn init(role: &'static str) -> bool {
    let Some(dir) = std::env::var_os(ENV_DIR) else {
        return false;
    };
    let ring = Ring {
        role,
        dir: PathBuf::from(dir),
        names: std::array::from_fn(|_| AtomicPtr::new(std::ptr::null_mut())),
        timers: (0..MAX_NAMES).map(|_| StageTimer::new()).collect(),
        slots: (0..RING_EVENTS)
            .map(|_| Slot {
                name: AtomicU64::new(0),
                start: AtomicU64::new(0),
                end: AtomicU64::new(0),
                tid: AtomicU64::new(0),
            })
            .collect(),
        head: AtomicUsize::new(0),
    };
    if RING.set(ring).is_err() {
        return true;
    }
    if tracing::subscriber::set_global_default(RingSubscriber).is_err() {
        crate::process::say(&format!(
            "{role}: warning: --trace: another tracing subscriber is installed; no spans recorded"
        ));
        return false;
    }
    true
}

/// The file a process writes its spans to in `dir`.
pub fn process_file(dir: &Path, role: &str, pid: u32) -> PathBuf {
    dir.join(format!("{role}-{pid}.trace.json"))
}

/// The file a process writes its stage timers to in `dir` (one tab-separated line per stage,
/// [`read_stages`]).
pub fn stages_file(dir: &Path, role: &str, pid: u32) -> PathBuf {
    dir.join(format!("{role}-{pid}.stages.tsv"))
}

/// One stage's times over a whole run (what [`flush`] writes per span name).
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct StageSummary {
    /// Process role.
    pub process: String,
    /// Span (stage) name.
    pub stage: String,
    /// Times the stage ran.
    pub count: u64,
    /// Total time, ms.
    pub total_ms: f64,
    /// Median, ms (the upper end of its log-linear bucket: at most 12.5 % over).
    pub p50_ms: f64,
    /// 99th percentile, ms.
    pub p99_ms: f64,
    /// Maximum, ms (exact).
    pub max_ms: f64,
}

fn summaries(ring: &Ring) -> Vec<StageSummary> {
    let ms = |ns: u64| ns as f64 / 1e6;
    ring.names
        .iter()
        .zip(ring.timers.iter())
        .filter_map(|(n, t)| {
            let meta = n.load(Ordering::Acquire);
            let count = t.count.load(Ordering::Relaxed);
            (!meta.is_null() && count > 0).then(|| StageSummary {
                process: ring.role.to_string(),
                // SAFETY: stored from a `&'static Metadata` in `slot_of`.
                stage: unsafe { &*meta }.name().to_string(),
                count,
                total_ms: ms(t.total_ns.load(Ordering::Relaxed)),
                p50_ms: ms(t.quantile_ns(0.5)),
                p99_ms: ms(t.quantile_ns(0.99)),
                max_ms: ms(t.max_ns.load(Ordering::Relaxed)),
            })
        })
        .collect()
}

/// Read a stage file written by [`flush`] (one summary per line: `process\tstage\tcount\ttotal_ms\tp50_ms\tp99_ms\tmax_ms`).
pub fn read_stages(path: &Path) -> std::io::Result<Vec<StageSummary>> {
    let text = std::fs::read_to_string(path)?;
    let bad = || std::io::Error::new(std::io::ErrorKind::InvalidData, "not a stage file");
    text.lines()
        .map(|l| {
            let f: Vec<&str> = l.split('\t').collect();
            if f.len() != 7 {
                return Err(bad());
            }
            let num = |s: &str| s.parse::<f64>().map_err(|_| bad());
            Ok(StageSummary {
                process: f[0].to_string(),
                stage: f[1].to_string(),
                count: f[2].parse().map_err(|_| bad())?,
                total_ms: num(f[3])?,
                p50_ms: num(f[4])?,
                p99_ms: num(f[5])?,
                max_ms: num(f[6])?,
            })
        })
        .collect()
}

/// Write this process's spans (at exit): a JSON array of Chrome trace events into
/// [`process_file`] of the trace folder. Nothing when tracing is off.
pub fn flush() {
    let Some(ring) = RING.get() else { return };
    let pid = std::process::id();
    let path = process_file(&ring.dir, ring.role, pid);
    let written = std::fs::File::create(&path).and_then(|f| {
        let mut w = std::io::BufWriter::new(f);
        write_events(ring, pid, &mut w)?;
        w.flush()
    });
    if let Err(e) = written {
        crate::process::say(&format!(
            "{}: warning: --trace: cannot write {}: {e}",
            ring.role,
            path.display()
        ));
    }
    let path = stages_file(&ring.dir, ring.role, pid);
    let text: String = summaries(ring)
        .iter()
        .map(|s| {
            format!(
                "{}\t{}\t{}\t{}\t{}\t{}\t{}\n",
                s.process, s.stage, s.count, s.total_ms, s.p50_ms, s.p99_ms, s.max_ms
            )
        })
        .collect();
    if let Err(e) = std::fs::write(&path, text) {
        crate::process::say(&format!(
            "{}: warning: --trace: cannot write {}: {e}",
            ring.role,
            path.display()
        ));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn stage_buckets_hold_their_values_within_an_eighth() {
        for ns in [
            0u64,
            1,
            7,
            8,
            9,
            15,
            16,
            100,
            1_000,
            16_666_667,
            1 << 40,
            u64::MAX / 2,
            u64::MAX,
        ] {
            let i = bucket_of(ns);
            let upper = bucket_upper(i);
            assert!(upper >= ns, "{ns}: bucket {i} ends at {upper}");
            if i > 0 {
                assert!(
                    bucket_upper(i - 1) < ns,
                    "{ns}: belongs to an earlier bucket"
                );
            }
            assert!(upper as f64 <= ns as f64 * 1.13 + 1.0, "{ns}: {upper}");
        }
        let t = StageTimer::new();
        for ns in 1..=1000u64 {
            t.record(ns * 1000);
        }
        let p50 = t.quantile_ns(0.5) as f64;
        assert!((500_000.0..=562_500.0).contains(&p50), "{p50}");
        assert_eq!(t.quantile_ns(1.0), 1_000_000);
    }
}

fn write_events(ring: &Ring, pid: u32, w: &mut impl Write) -> std::io::Result<()> {
    write!(
        w,
        "[{{\"ph\":\"M\",\"name\":\"process_name\",\"pid\":{pid},\"tid\":{pid},\"args\":{{\"name\":\"{}\"}}}}",
        ring.role
    )?;
    let n = ring.head.load(Ordering::Acquire).min(ring.slots.len());
    for s in &ring.slots[..n] {
        let slot = s.name.load(Ordering::Relaxed);
        let Some(meta) = slot
            .checked_sub(1)
            .and_then(|i| ring.names.get(i as usize))
            .map(|p| p.load(Ordering::Acquire))
            .filter(|p| !p.is_null())
        else {
            continue;
        };
        // SAFETY: the pointer was stored from a `&'static Metadata` in `slot_of`.
        let name = unsafe { &*meta }.name();
        let (start, end) = (
            s.start.load(Ordering::Relaxed),
            s.end.load(Ordering::Relaxed),
        );
        write!(
            w,
            ",\n{{\"ph\":\"X\",\"cat\":\"{}\",\"name\":\"{}\",\"pid\":{pid},\"tid\":{},\"ts\":{:.3},\"dur\":{:.3}}}",
            ring.role,
            name,
            s.tid.load(Ordering::Relaxed),
            start as f64 / 1e3,
            end.saturating_sub(start) as f64 / 1e3
        )?;
    }
    writeln!(w, "]")
}

/// Merge the per-process files in `dir` into one Chrome trace (`{"traceEvents": [...]}`) written
/// atomically to `out`; returns the number of processes merged. A file that is not a JSON array
/// of events (a process killed mid-write) is skipped with a warning.
pub fn merge(dir: &Path, out: &Path) -> Result<usize, MergeError> {
    let mut files: Vec<PathBuf> = std::fs::read_dir(dir)
        .map_err(|e| MergeError::Read(dir.to_path_buf(), e))?
        .flatten()
        .map(|e| e.path())
        .filter(|p| p.to_string_lossy().ends_with(".trace.json"))
        .collect();
    files.sort();
    let mut merged = 0;
    let mut body = String::from("{\"displayTimeUnit\":\"ms\",\"traceEvents\":[");
    for f in &files {
        let text = std::fs::read_to_string(f).map_err(|e| MergeError::Read(f.clone(), e))?;
        let text = text.trim();
        let inner = text
            .strip_prefix('[')
            .and_then(|t| t.strip_suffix(']'))
            .filter(|t| t.starts_with('{') && t.ends_with('}'));
        match inner {
            Some(events) => {
                if merged > 0 {
                    body.push_str(",\n");
                }
                body.push_str(events);
                merged += 1;
            }
            None => crate::process::say(&format!(
                "lungdyn: warning: --trace: {} is not a finished span file; left out",
                f.display()
            )),
        }
    }
    body.push_str("]}\n");
    outfile::write_atomically(out, |w| w.write_all(body.as_bytes()))
        .map_err(|e| MergeError::Write(out.to_path_buf(), e))?;
    Ok(merged)
}

/// The merged trace could not be made.
#[derive(Debug, thiserror::Error)]
pub enum MergeError {
    /// A span folder or file could not be read.
    #[error("--trace: cannot read {0}: {1}")]
    Read(PathBuf, std::io::Error),
    /// The merged trace could not be written.
    #[error("--trace {0}: {1}")]
    Write(PathBuf, outfile::WriteError),
}
