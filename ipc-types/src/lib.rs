//! # ipc-types: what crosses a process boundary
//!
//! The three lungdyn processes (`tracker-bridge`, `engine`, `renderer`) and the launcher exchange
//! only the fixed-size, `#[repr(C)]`, pointer-free payloads defined here, through iceoryx2
//! zero-copy publish–subscribe services whose names are built here too.
//!
//! Every payload carries [`HopStamps`]: the monotonic time (CLOCK_MONOTONIC, ns, shared by all
//! processes on the host) at which it passed each hop, so the latency harness can attribute every
//! microsecond of the tracker-sample-to-submitted-frame path.
//!
//! ## Layout versioning
//! [`LAYOUT_VERSION`] is written into every payload and into every payload's iceoryx2 type name
//! (`"lungdyn.TrackerFrame.v1"`). iceoryx2 refuses to open a service whose payload type name, size
//! or alignment differ from the creator's, so a process built from another layout fails at start-up
//! with [`IpcError::LayoutMismatch`] instead of reading garbage; the field in the payload is a
//! second check for peers that bypass the type name. Bump both together (a test checks this).

use core::fmt;
use core::time::Duration;

use iceoryx2::prelude::*;

/// Version of every payload layout in this crate. Part of each iceoryx2 type name.
pub const LAYOUT_VERSION: u32 = 1;

/// Maximum number of tracked tools in one [`TrackerFrame`].
pub const MAX_TOOLS: usize = 4;
/// Capacity for spherical-harmonic force coefficients per lung (8 bands).
pub const MAX_SH_COEFFS: usize = 64;
/// Number of lungs in an [`EngineFrame`]: index [`LUNG_RIGHT`] and [`LUNG_LEFT`].
pub const NUM_LUNGS: usize = 2;
/// Index of the right lung in per-lung arrays.
pub const LUNG_RIGHT: usize = 0;
/// Index of the left lung in per-lung arrays.
pub const LUNG_LEFT: usize = 1;

/// Conventional tool slot of the patient reference (dynamic reference frame on the sternum).
pub const TOOL_PATIENT: usize = 0;
/// Conventional tool slot of the head-mounted display.
pub const TOOL_HMD: usize = 1;

/// Monotonic time in nanoseconds (CLOCK_MONOTONIC), comparable across processes on one host.
#[inline]
pub fn now_ns() -> u64 {
    let mut ts = libc::timespec {
        tv_sec: 0,
        tv_nsec: 0,
    };
    // SAFETY: clock_gettime writes into the timespec we own; CLOCK_MONOTONIC always exists on Linux.
    unsafe { libc::clock_gettime(libc::CLOCK_MONOTONIC, &mut ts) };
    ts.tv_sec as u64 * 1_000_000_000 + ts.tv_nsec as u64
}

/// Sleep until the monotonic clock reaches `deadline_ns` (absolute), so periodic loops never drift;
/// returns early when a signal arrives.
pub fn sleep_until_ns(deadline_ns: u64) {
    let ts = libc::timespec {
        tv_sec: (deadline_ns / 1_000_000_000) as libc::time_t,
        tv_nsec: (deadline_ns % 1_000_000_000) as libc::c_long,
    };
    // SAFETY: plain syscall with a valid timespec. A signal (EINTR) ends the sleep early on
    // purpose, so the caller's loop sees a termination request promptly.
    unsafe {
        libc::clock_nanosleep(
            libc::CLOCK_MONOTONIC,
            libc::TIMER_ABSTIME,
            &ts,
            core::ptr::null_mut(),
        )
    };
}

/// Monotonic timestamps (ns) of each hop a sample passed. Zero means "not passed (yet)".
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq, ZeroCopySend)]
#[repr(C)]
pub struct HopStamps {
    /// When the tracker captured the sample (for a synthetic source: when it was generated).
    pub capture_ns: u64,
    /// When the tracker-bridge published the tracker frame.
    pub bridge_publish_ns: u64,
    /// When the engine took the tracker frame out of its subscriber.
    pub engine_receive_ns: u64,
    /// When the engine published the engine frame derived from it.
    pub engine_publish_ns: u64,
    /// When the renderer took the engine frame out of its subscriber.
    pub renderer_receive_ns: u64,
    /// When the renderer submitted the GPU work that draws it.
    pub renderer_submit_ns: u64,
}

impl HopStamps {
    /// The hop names, in path order, as used by the latency report.
    pub const NAMES: [&'static str; 6] = [
        "capture",
        "bridge publish",
        "engine receive",
        "engine publish",
        "renderer receive",
        "renderer submit",
    ];

    /// The stamps in path order.
    pub fn as_array(&self) -> [u64; 6] {
        [
            self.capture_ns,
            self.bridge_publish_ns,
            self.engine_receive_ns,
            self.engine_publish_ns,
            self.renderer_receive_ns,
            self.renderer_submit_ns,
        ]
    }

    /// True when every hop is stamped and the stamps never go backwards.
    pub fn is_complete_and_ordered(&self) -> bool {
        let a = self.as_array();
        a.iter().all(|&t| t != 0) && a.windows(2).all(|w| w[0] <= w[1])
    }
}

/// A rigid pose: unit quaternion `(x, y, z, w)` and translation in millimetres.
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct Pose {
    /// Rotation as a unit quaternion, `[x, y, z, w]`.
    pub quat: [f32; 4],
    /// Translation in mm.
    pub translation_mm: [f32; 3],
    /// Explicit padding so the layout has no implicit holes.
    pub _pad: u32,
}

impl Default for Pose {
    fn default() -> Self {
        Self::IDENTITY
    }
}

impl Pose {
    /// No rotation, no translation.
    pub const IDENTITY: Pose = Pose {
        quat: [0.0, 0.0, 0.0, 1.0],
        translation_mm: [0.0; 3],
        _pad: 0,
    };

    /// True when every component is finite.
    pub fn is_finite(&self) -> bool {
        self.quat
            .iter()
            .chain(self.translation_mm.iter())
            .all(|v| v.is_finite())
    }
}

/// Status bits of a [`ToolPose`].
pub mod tool_status {
    /// The pose is valid and may be used.
    pub const VALID: u32 = 1 << 0;
    /// The tool was not seen in this sample.
    pub const MISSING: u32 = 1 << 1;
    /// The tool was outside the tracker's measurement volume.
    pub const OUT_OF_VOLUME: u32 = 1 << 2;
    /// The pose had non-finite components and was rejected by the bridge.
    pub const NON_FINITE: u32 = 1 << 3;
    /// Only some of the tool's markers were seen (pose less accurate).
    pub const PARTIALLY_VISIBLE: u32 = 1 << 4;
}

/// One tool's pose in a tracker sample.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct ToolPose {
    /// Tracker-assigned tool handle.
    pub tool_id: u32,
    /// [`tool_status`] bits.
    pub status: u32,
    /// Tool pose in the tracker's frame.
    pub pose: Pose,
    /// RMS marker-fit error in mm reported by the tracker.
    pub rms_error_mm: f32,
    /// Explicit padding.
    pub _pad: u32,
}

impl ToolPose {
    /// True when the tool's pose may be used.
    pub fn is_valid(&self) -> bool {
        self.status & tool_status::VALID != 0
    }
}

/// One tracker sample, published by `tracker-bridge` at 60 Hz.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("lungdyn.TrackerFrame.v1")]
#[repr(C)]
pub struct TrackerFrame {
    /// [`LAYOUT_VERSION`] of the publisher.
    pub layout_version: u32,
    /// Number of used entries in `tools`.
    pub tool_count: u32,
    /// Frame number, +1 per sample since the bridge started.
    pub frame_number: u64,
    /// Hop timestamps (capture and bridge publish set by the bridge).
    pub stamps: HopStamps,
    /// Tool poses; slot [`TOOL_PATIENT`] is the patient reference, [`TOOL_HMD`] the HMD.
    pub tools: [ToolPose; MAX_TOOLS],
}

/// Bits of [`EngineFrame::state`].
pub mod engine_state {
    /// The tick used a fresh tracker frame (woken by its arrival).
    pub const TRACKER_FRESH: u32 = 1 << 0;
    /// No tracker frame arrived before the tick deadline: the tick ran on the deadline fallback.
    pub const DEADLINE_FALLBACK: u32 = 1 << 1;
    /// The patient pose is held from an earlier sample (tracker flagged it or it was missing).
    pub const PATIENT_POSE_HELD: u32 = 1 << 2;
    /// The patient pose has been held longer than the allowed staleness.
    pub const PATIENT_POSE_STALE: u32 = 1 << 3;
    /// Currently inhaling (clear: exhaling).
    pub const INHALING: u32 = 1 << 4;
    /// No tracker sample has been seen yet.
    pub const NO_TRACKER_YET: u32 = 1 << 5;
}

/// Per-lung state in an [`EngineFrame`].
#[derive(Debug, Clone, Copy, PartialEq, ZeroCopySend)]
#[repr(C)]
pub struct LungState {
    /// Lung volume from the PV model, ml.
    pub volume_ml: f32,
    /// Scale applied to the lung's unit displacement field this tick.
    pub deform_scale: f32,
    /// Number of used entries of `sh_force` (0 when the scene's deformation mode uses none).
    pub sh_count: u32,
    /// 1 when this lung is simulated in the current scene.
    pub active: u32,
    /// Spherical-harmonic force coefficients (eq. 7.2), room for 8 bands.
    pub sh_force: [f32; MAX_SH_COEFFS],
}

impl Default for LungState {
    fn default() -> Self {
        Self {
            volume_ml: 0.0,
            deform_scale: 0.0,
            sh_count: 0,
            active: 0,
            sh_force: [0.0; MAX_SH_COEFFS],
        }
    }
}

/// One engine tick's output, published by `engine` every tick.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("lungdyn.EngineFrame.v1")]
#[repr(C)]
pub struct EngineFrame {
    /// [`LAYOUT_VERSION`] of the publisher.
    pub layout_version: u32,
    /// [`engine_state`] bits.
    pub state: u32,
    /// Fault word: 0 when healthy, else a [`fault`] code.
    pub fault: u32,
    /// Ticks per breathing cycle in force (so consumers can derive the phase).
    pub cycle_ticks: u32,
    /// Integer tick counter since the engine started (tick 0 = start of an inhalation).
    pub tick: u64,
    /// `frame_number` of the tracker frame this tick used (0 when none yet).
    pub tracker_frame: u64,
    /// Hop timestamps, inherited from the tracker frame and extended by the engine.
    pub stamps: HopStamps,
    /// Patient reference pose used for registration (held when the tracker flagged it).
    pub patient_pose: Pose,
    /// Per-lung state, indexed by [`LUNG_RIGHT`] and [`LUNG_LEFT`].
    pub lungs: [LungState; NUM_LUNGS],
}

/// Fault codes of [`EngineFrame::fault`].
pub mod fault {
    /// Healthy.
    pub const NONE: u32 = 0;
    /// The tracker has been silent for longer than the staleness bound.
    pub const TRACKER_LOST: u32 = 1;
    /// The PV model produced a non-finite value and the engine held the last good volume.
    pub const NON_FINITE_VOLUME: u32 = 2;
}

/// Bits of [`FrameReport::flags`].
pub mod report_flags {
    /// This frame also wrote a PNG snapshot (its CPU time includes the readback).
    pub const SNAPSHOT: u32 = 1 << 0;
    /// GPU time was measured with timestamp queries.
    pub const GPU_TIMED: u32 = 1 << 1;
    /// The renderer drew without a fresh engine frame (deadline fallback).
    pub const STALE_ENGINE: u32 = 1 << 2;
}

/// The renderer's per-frame report, consumed by the launcher's latency harness and by tests.
#[derive(Debug, Clone, Copy, Default, PartialEq, ZeroCopySend)]
#[type_name("lungdyn.FrameReport.v1")]
#[repr(C)]
pub struct FrameReport {
    /// [`LAYOUT_VERSION`] of the publisher.
    pub layout_version: u32,
    /// [`report_flags`] bits.
    pub flags: u32,
    /// Renderer frame counter.
    pub frame: u64,
    /// Engine tick drawn.
    pub engine_tick: u64,
    /// Tracker frame number behind the engine tick.
    pub tracker_frame: u64,
    /// All hop stamps of the drawn frame.
    pub stamps: HopStamps,
    /// CPU time of the frame (receive → submit), ns.
    pub cpu_frame_ns: u64,
    /// GPU time of the frame's passes from timestamp queries, ns (0 when unsupported).
    pub gpu_frame_ns: u64,
    /// Lung volumes drawn, ml (right, left).
    pub volume_ml: [f32; NUM_LUNGS],
}

/// The services of one lungdyn instance. Every process of an instance uses the same `instance`
/// string; tests use a unique one so they never meet another run.
#[derive(Debug, Clone)]
pub struct Services {
    /// Instance name (alphanumerics, `-`, `_`).
    pub instance: String,
}

impl Services {
    /// Services of `instance`; the name must be 1–48 characters of `[A-Za-z0-9_-]`.
    pub fn new(instance: &str) -> Result<Self, IpcError> {
        let ok = !instance.is_empty()
            && instance.len() <= 48
            && instance
                .bytes()
                .all(|b| b.is_ascii_alphanumeric() || b == b'-' || b == b'_');
        if !ok {
            return Err(IpcError::BadInstanceName {
                name: instance.to_string(),
            });
        }
        Ok(Self {
            instance: instance.to_string(),
        })
    }

    /// Publish–subscribe service for [`TrackerFrame`]s.
    pub fn tracker(&self) -> String {
        format!("lungdyn/{}/tracker", self.instance)
    }
    /// Event service signalled after each tracker frame is published.
    pub fn tracker_event(&self) -> String {
        format!("lungdyn/{}/tracker-ready", self.instance)
    }
    /// Publish–subscribe service for [`EngineFrame`]s.
    pub fn engine(&self) -> String {
        format!("lungdyn/{}/engine", self.instance)
    }
    /// Event service signalled after each engine frame is published.
    pub fn engine_event(&self) -> String {
        format!("lungdyn/{}/engine-ready", self.instance)
    }
    /// Publish–subscribe service for [`FrameReport`]s.
    pub fn report(&self) -> String {
        format!("lungdyn/{}/report", self.instance)
    }

    /// The iceoryx2 file prefix of this instance: every shared-memory segment and file the
    /// instance creates starts with it, so leftovers can be found and are never another run's.
    pub fn file_prefix(&self) -> String {
        format!("lungdyn_{}_", self.instance)
    }

    /// An iceoryx2 config whose files carry [`Self::file_prefix`].
    pub fn config(&self) -> Result<Config, IpcError> {
        let mut config = Config::default();
        config.global.prefix = FileName::new(self.file_prefix().as_bytes()).map_err(|_| {
            IpcError::BadInstanceName {
                name: self.instance.clone(),
            }
        })?;
        Ok(config)
    }

    /// Remove the instance's persistent iceoryx2 management segment (a node counter that outlives
    /// its nodes by design). Call only after every process of the instance has exited: the file
    /// prefix is unique to the instance, so no other run can be using it.
    pub fn remove_instance_segment(&self) -> Result<(), IpcError> {
        let config = self.config()?;
        // SAFETY: iceoryx2 requires that no process uses this domain; the caller guarantees that
        // every process of this instance (the only users of its unique prefix) has exited.
        unsafe { iceoryx2::testing::remove_global_mgmt_segment::<ipc::Service>(&config) }
            .map(|_| ())
            .map_err(|e| IpcError::Service {
                service: self.file_prefix(),
                detail: format!("{e:?}"),
            })
    }

    /// Files of this instance still present in shared memory (`/dev/shm`) or under iceoryx2's root
    /// folder. Empty after a clean shutdown.
    pub fn leftovers(&self) -> Vec<std::path::PathBuf> {
        let prefix = self.file_prefix();
        let mut found = Vec::new();
        let root = Config::default().global.root_path().as_str().to_string();
        let mut stack = vec![
            std::path::PathBuf::from("/dev/shm"),
            std::path::PathBuf::from(root),
        ];
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
                if entry.file_name().to_string_lossy().starts_with(&prefix) {
                    found.push(path);
                }
            }
        }
        found.sort();
        found
    }

    /// Delete the files [`Self::leftovers`] finds, and node folders left empty by that. Only for
    /// after every process of the instance has exited (the prefix is unique to the instance).
    /// Returns how many files were removed.
    pub fn remove_leftovers(&self) -> usize {
        let mut removed = 0;
        for path in self.leftovers() {
            if std::fs::remove_file(&path).is_ok() {
                removed += 1;
                if let Some(dir) = path.parent() {
                    // Only succeeds when the folder is now empty.
                    let _ = std::fs::remove_dir(dir);
                }
            }
        }
        removed
    }

    /// Create an iceoryx2 node for `role` (e.g. "engine") in this instance.
    pub fn node(&self, role: &str) -> Result<Node<ipc::Service>, IpcError> {
        let name = NodeName::new(&format!("lungdyn-{}-{}", self.instance, role)).map_err(|_| {
            IpcError::BadInstanceName {
                name: self.instance.clone(),
            }
        })?;
        NodeBuilder::new()
            .name(&name)
            .config(&self.config()?)
            .create::<ipc::Service>()
            .map_err(|e| IpcError::Node {
                detail: format!("{e:?}"),
            })
    }
}

/// Queue depths shared by every opener of a service, so open_or_create never disagrees.
const SUBSCRIBER_BUFFER: usize = 4;
/// The report stream is drained in batches by the launcher; a deeper buffer keeps every frame.
const REPORT_BUFFER: usize = 512;
const MAX_SUBSCRIBERS: usize = 8;
const MAX_PUBLISHERS: usize = 2;
const MAX_NODES: usize = 16;

/// Which buffer depth a payload's service uses.
pub trait ServicePayload: ZeroCopySend + Copy + fmt::Debug + 'static {
    /// Human-readable payload name used in error messages.
    const NAME: &'static str;
    /// Buffer depth per subscriber.
    const BUFFER: usize;
}
impl ServicePayload for TrackerFrame {
    const NAME: &'static str = "TrackerFrame";
    const BUFFER: usize = SUBSCRIBER_BUFFER;
}
impl ServicePayload for EngineFrame {
    const NAME: &'static str = "EngineFrame";
    const BUFFER: usize = SUBSCRIBER_BUFFER;
}
impl ServicePayload for FrameReport {
    const NAME: &'static str = "FrameReport";
    const BUFFER: usize = REPORT_BUFFER;
}

/// The port factory type of a publish–subscribe service of payload `T`.
pub type PubSub<T> =
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, T, ()>;
/// The port factory type of an event service.
pub type EventService = iceoryx2::service::port_factory::event::PortFactory<ipc::Service>;

/// Open (or create) the publish–subscribe service `name` carrying `T` with lungdyn's QoS.
/// A peer built with another payload layout yields [`IpcError::LayoutMismatch`].
pub fn open_pubsub<T: ServicePayload>(
    node: &Node<ipc::Service>,
    name: &str,
) -> Result<PubSub<T>, IpcError> {
    let service_name: ServiceName = name.try_into().map_err(|_| IpcError::BadServiceName {
        name: name.to_string(),
    })?;
    node.service_builder(&service_name)
        .publish_subscribe::<T>()
        .history_size(1)
        .subscriber_max_buffer_size(T::BUFFER)
        .enable_safe_overflow(true)
        .max_publishers(MAX_PUBLISHERS)
        .max_subscribers(MAX_SUBSCRIBERS)
        .max_nodes(MAX_NODES)
        .open_or_create()
        .map_err(|e| {
            use iceoryx2::service::builder::publish_subscribe::{
                PublishSubscribeOpenError as O, PublishSubscribeOpenOrCreateError as E,
            };
            match e {
                E::PublishSubscribeOpenError(O::IncompatibleTypes) => IpcError::LayoutMismatch {
                    service: name.to_string(),
                    payload: T::NAME,
                    ours: LAYOUT_VERSION,
                },
                other => IpcError::Service {
                    service: name.to_string(),
                    detail: format!("{other:?}"),
                },
            }
        })
}

/// Open (or create) the event service `name`.
pub fn open_event(node: &Node<ipc::Service>, name: &str) -> Result<EventService, IpcError> {
    let service_name: ServiceName = name.try_into().map_err(|_| IpcError::BadServiceName {
        name: name.to_string(),
    })?;
    node.service_builder(&service_name)
        .event()
        .max_notifiers(MAX_PUBLISHERS)
        .max_listeners(MAX_SUBSCRIBERS)
        .max_nodes(MAX_NODES)
        .open_or_create()
        .map_err(|e| IpcError::Service {
            service: name.to_string(),
            detail: format!("{e:?}"),
        })
}

/// Check the layout version a received payload claims.
pub fn check_layout(payload: &'static str, theirs: u32) -> Result<(), IpcError> {
    if theirs == LAYOUT_VERSION {
        Ok(())
    } else {
        Err(IpcError::PeerLayoutVersion {
            payload,
            theirs,
            ours: LAYOUT_VERSION,
        })
    }
}

/// True when the process was asked to terminate (SIGINT/SIGTERM), as seen by iceoryx2's handler.
pub fn termination_requested(node: &Node<ipc::Service>) -> bool {
    node.wait(Duration::ZERO).is_err()
}

/// The sending end of a stream: a publisher plus the event that wakes its consumers.
pub struct Outlet<T: ServicePayload> {
    publisher: iceoryx2::port::publisher::Publisher<ipc::Service, T, ()>,
    notifier: iceoryx2::port::notifier::Notifier<ipc::Service>,
    name: String,
    _data: PubSub<T>,
    _event: EventService,
}

impl<T: ServicePayload> Outlet<T> {
    /// Open the data service `data` and its wake-up event `event`.
    pub fn new(node: &Node<ipc::Service>, data: &str, event: &str) -> Result<Self, IpcError> {
        let data_service = open_pubsub::<T>(node, data)?;
        let event_service = open_event(node, event)?;
        let publisher =
            data_service
                .publisher_builder()
                .create()
                .map_err(|e| IpcError::Service {
                    service: data.to_string(),
                    detail: format!("{e:?}"),
                })?;
        let notifier =
            event_service
                .notifier_builder()
                .create()
                .map_err(|e| IpcError::Service {
                    service: event.to_string(),
                    detail: format!("{e:?}"),
                })?;
        Ok(Self {
            publisher,
            notifier,
            name: data.to_string(),
            _data: data_service,
            _event: event_service,
        })
    }

    /// Publish `value` (zero-copy loan, no allocation) and wake the consumers.
    pub fn publish(&self, value: T) -> Result<(), IpcError> {
        let sample = self
            .publisher
            .loan_uninit()
            .map_err(|e| IpcError::Service {
                service: self.name.clone(),
                detail: format!("{e:?}"),
            })?;
        sample
            .write_payload(value)
            .send()
            .map_err(|e| IpcError::Service {
                service: self.name.clone(),
                detail: format!("{e:?}"),
            })?;
        self.notifier.notify().map_err(|e| IpcError::Service {
            service: self.name.clone(),
            detail: format!("{e:?}"),
        })?;
        Ok(())
    }
}

/// The receiving end of a stream: a subscriber plus the event listener that wakes us.
pub struct Inlet<T: ServicePayload> {
    subscriber: iceoryx2::port::subscriber::Subscriber<ipc::Service, T, ()>,
    listener: iceoryx2::port::listener::Listener<ipc::Service>,
    name: String,
    _data: PubSub<T>,
    _event: EventService,
}

impl<T: ServicePayload> Inlet<T> {
    /// Open the data service `data` and its wake-up event `event`.
    pub fn new(node: &Node<ipc::Service>, data: &str, event: &str) -> Result<Self, IpcError> {
        let data_service = open_pubsub::<T>(node, data)?;
        let event_service = open_event(node, event)?;
        let subscriber =
            data_service
                .subscriber_builder()
                .create()
                .map_err(|e| IpcError::Service {
                    service: data.to_string(),
                    detail: format!("{e:?}"),
                })?;
        let listener =
            event_service
                .listener_builder()
                .create()
                .map_err(|e| IpcError::Service {
                    service: event.to_string(),
                    detail: format!("{e:?}"),
                })?;
        Ok(Self {
            subscriber,
            listener,
            name: data.to_string(),
            _data: data_service,
            _event: event_service,
        })
    }

    /// Sleep until the producer signals new data or the monotonic clock reaches `deadline_ns`
    /// (absolute), whichever comes first. Returns at once if the deadline has passed.
    pub fn wait_until(&self, deadline_ns: u64) {
        let now = now_ns();
        if deadline_ns <= now {
            // Still consume pending wake-ups so they do not pile up.
            let _ = self.listener.try_wait(|_| {});
            return;
        }
        let _ = self
            .listener
            .timed_wait(|_| {}, Duration::from_nanos(deadline_ns - now));
    }

    /// Drain the subscriber and return the newest sample, if any arrived (a copy; `T` is small).
    pub fn take_latest(&self) -> Result<Option<T>, IpcError> {
        let mut latest = None;
        loop {
            match self.subscriber.receive() {
                Ok(Some(sample)) => latest = Some(*sample.payload()),
                Ok(None) => return Ok(latest),
                Err(e) => {
                    return Err(IpcError::Service {
                        service: self.name.clone(),
                        detail: format!("{e:?}"),
                    })
                }
            }
        }
    }

    /// Drain every pending sample into `f`, oldest first.
    pub fn drain(&self, mut f: impl FnMut(&T)) -> Result<usize, IpcError> {
        let mut n = 0;
        loop {
            match self.subscriber.receive() {
                Ok(Some(sample)) => {
                    f(sample.payload());
                    n += 1;
                }
                Ok(None) => return Ok(n),
                Err(e) => {
                    return Err(IpcError::Service {
                        service: self.name.clone(),
                        detail: format!("{e:?}"),
                    })
                }
            }
        }
    }
}

/// Pin the calling thread to CPU `core` if one is given (`role` names the process in errors).
pub fn pin_to_core(core: Option<usize>, role: &str) -> Result<(), PinError> {
    let Some(id) = core else { return Ok(()) };
    let cores = core_affinity::get_core_ids().unwrap_or_default();
    let available = cores.len();
    let Some(c) = cores.into_iter().find(|c| c.id == id) else {
        return Err(PinError {
            role: role.to_string(),
            core: id,
            available,
        });
    };
    if core_affinity::set_for_current(c) {
        Ok(())
    } else {
        Err(PinError {
            role: role.to_string(),
            core: id,
            available,
        })
    }
}

/// A process could not be pinned to the core it was given.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct PinError {
    /// Process role.
    pub role: String,
    /// Core asked for.
    pub core: usize,
    /// Cores this process may use.
    pub available: usize,
}

impl fmt::Display for PinError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        write!(
            f,
            "{}: cannot pin to CPU core {} ({} cores available to this process)",
            self.role, self.core, self.available
        )
    }
}

impl std::error::Error for PinError {}

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

/// Errors at the process boundary.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum IpcError {
    /// The instance name cannot be used in service and file names.
    BadInstanceName {
        /// The offending name.
        name: String,
    },
    /// A service name was rejected by iceoryx2.
    BadServiceName {
        /// The offending name.
        name: String,
    },
    /// The iceoryx2 node could not be created.
    Node {
        /// iceoryx2's reason.
        detail: String,
    },
    /// The service exists with another payload layout (built from another lungdyn version).
    LayoutMismatch {
        /// Service name.
        service: String,
        /// Payload type.
        payload: &'static str,
        /// Our layout version.
        ours: u32,
    },
    /// A received payload claims another layout version.
    PeerLayoutVersion {
        /// Payload type.
        payload: &'static str,
        /// What the payload says.
        theirs: u32,
        /// What we speak.
        ours: u32,
    },
    /// Any other failure opening or using a service.
    Service {
        /// Service name.
        service: String,
        /// iceoryx2's reason.
        detail: String,
    },
}

impl fmt::Display for IpcError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            IpcError::BadInstanceName { name } => write!(
                f,
                "instance name {name:?} is not usable: use 1-48 characters from A-Z, a-z, 0-9, '-' and '_'"
            ),
            IpcError::BadServiceName { name } => write!(f, "service name {name:?} was rejected by iceoryx2"),
            IpcError::Node { detail } => write!(f, "cannot create the iceoryx2 node: {detail}"),
            IpcError::LayoutMismatch { service, payload, ours } => write!(
                f,
                "service {service:?} already exists with a different {payload} layout (this process speaks \
                 layout v{ours}): another lungdyn build is running with the same instance name; stop it or \
                 rebuild all processes from one version"
            ),
            IpcError::PeerLayoutVersion { payload, theirs, ours } => write!(
                f,
                "received a {payload} with layout v{theirs}, but this process speaks layout v{ours}: \
                 rebuild all lungdyn processes from one version"
            ),
            IpcError::Service { service, detail } => write!(f, "iceoryx2 service {service:?}: {detail}"),
        }
    }
}

impl std::error::Error for IpcError {}

#[cfg(test)]
mod tests {
    use super::*;
    use core::mem::{align_of, offset_of, size_of};

    #[test]
    fn hop_stamps_layout_is_pinned() {
        assert_eq!(size_of::<HopStamps>(), 48);
        assert_eq!(align_of::<HopStamps>(), 8);
        assert_eq!(offset_of!(HopStamps, capture_ns), 0);
        assert_eq!(offset_of!(HopStamps, bridge_publish_ns), 8);
        assert_eq!(offset_of!(HopStamps, engine_receive_ns), 16);
        assert_eq!(offset_of!(HopStamps, engine_publish_ns), 24);
        assert_eq!(offset_of!(HopStamps, renderer_receive_ns), 32);
        assert_eq!(offset_of!(HopStamps, renderer_submit_ns), 40);
    }

    #[test]
    fn pose_and_tool_layout_is_pinned() {
        assert_eq!(size_of::<Pose>(), 32);
        assert_eq!(align_of::<Pose>(), 4);
        assert_eq!(offset_of!(Pose, quat), 0);
        assert_eq!(offset_of!(Pose, translation_mm), 16);
        assert_eq!(offset_of!(Pose, _pad), 28);
        assert_eq!(size_of::<ToolPose>(), 48);
        assert_eq!(offset_of!(ToolPose, tool_id), 0);
        assert_eq!(offset_of!(ToolPose, status), 4);
        assert_eq!(offset_of!(ToolPose, pose), 8);
        assert_eq!(offset_of!(ToolPose, rms_error_mm), 40);
    }

    #[test]
    fn tracker_frame_layout_is_pinned() {
        assert_eq!(size_of::<TrackerFrame>(), 256);
        assert_eq!(align_of::<TrackerFrame>(), 8);
        assert_eq!(offset_of!(TrackerFrame, layout_version), 0);
        assert_eq!(offset_of!(TrackerFrame, tool_count), 4);
        assert_eq!(offset_of!(TrackerFrame, frame_number), 8);
        assert_eq!(offset_of!(TrackerFrame, stamps), 16);
        assert_eq!(offset_of!(TrackerFrame, tools), 64);
    }

    #[test]
    fn lung_state_layout_is_pinned() {
        assert_eq!(size_of::<LungState>(), 16 + 4 * MAX_SH_COEFFS);
        assert_eq!(offset_of!(LungState, volume_ml), 0);
        assert_eq!(offset_of!(LungState, deform_scale), 4);
        assert_eq!(offset_of!(LungState, sh_count), 8);
        assert_eq!(offset_of!(LungState, active), 12);
        assert_eq!(offset_of!(LungState, sh_force), 16);
    }

    #[test]
    fn engine_frame_layout_is_pinned() {
        assert_eq!(size_of::<EngineFrame>(), 656);
        assert_eq!(align_of::<EngineFrame>(), 8);
        assert_eq!(offset_of!(EngineFrame, layout_version), 0);
        assert_eq!(offset_of!(EngineFrame, state), 4);
        assert_eq!(offset_of!(EngineFrame, fault), 8);
        assert_eq!(offset_of!(EngineFrame, cycle_ticks), 12);
        assert_eq!(offset_of!(EngineFrame, tick), 16);
        assert_eq!(offset_of!(EngineFrame, tracker_frame), 24);
        assert_eq!(offset_of!(EngineFrame, stamps), 32);
        assert_eq!(offset_of!(EngineFrame, patient_pose), 80);
        assert_eq!(offset_of!(EngineFrame, lungs), 112);
    }

    #[test]
    fn frame_report_layout_is_pinned() {
        assert_eq!(size_of::<FrameReport>(), 104);
        assert_eq!(align_of::<FrameReport>(), 8);
        assert_eq!(offset_of!(FrameReport, flags), 4);
        assert_eq!(offset_of!(FrameReport, frame), 8);
        assert_eq!(offset_of!(FrameReport, engine_tick), 16);
        assert_eq!(offset_of!(FrameReport, tracker_frame), 24);
        assert_eq!(offset_of!(FrameReport, stamps), 32);
        assert_eq!(offset_of!(FrameReport, cpu_frame_ns), 80);
        assert_eq!(offset_of!(FrameReport, gpu_frame_ns), 88);
        assert_eq!(offset_of!(FrameReport, volume_ml), 96);
    }

    #[test]
    fn type_names_carry_the_layout_version() {
        let suffix = format!(".v{LAYOUT_VERSION}");
        // SAFETY: type_name only returns the static string the derive generated.
        unsafe {
            assert!(<TrackerFrame as ZeroCopySend>::type_name().ends_with(&suffix));
            assert!(<EngineFrame as ZeroCopySend>::type_name().ends_with(&suffix));
            assert!(<FrameReport as ZeroCopySend>::type_name().ends_with(&suffix));
        }
    }

    #[test]
    fn instance_names_are_validated() {
        assert!(Services::new("demo-1_a").is_ok());
        assert!(matches!(
            Services::new(""),
            Err(IpcError::BadInstanceName { .. })
        ));
        assert!(matches!(
            Services::new("a/b"),
            Err(IpcError::BadInstanceName { .. })
        ));
        assert!(matches!(
            Services::new(&"x".repeat(49)),
            Err(IpcError::BadInstanceName { .. })
        ));
    }

    #[test]
    fn stamps_order_check_rejects_gaps_and_reversals() {
        let mut s = HopStamps {
            capture_ns: 1,
            bridge_publish_ns: 2,
            engine_receive_ns: 3,
            engine_publish_ns: 4,
            renderer_receive_ns: 5,
            renderer_submit_ns: 6,
        };
        assert!(s.is_complete_and_ordered());
        s.engine_publish_ns = 0;
        assert!(!s.is_complete_and_ordered());
        s.engine_publish_ns = 2;
        assert!(!s.is_complete_and_ordered());
    }

    #[test]
    fn monotonic_clock_advances() {
        let a = now_ns();
        let b = now_ns();
        assert!(b >= a && a > 0);
    }

    /// A peer built with another layout version must be refused when it opens the service.
    #[repr(C)]
    #[derive(Debug, Clone, Copy, ZeroCopySend)]
    #[type_name("lungdyn.TrackerFrame.v999")]
    struct FutureTrackerFrame {
        layout_version: u32,
        other: u32,
    }
    impl ServicePayload for FutureTrackerFrame {
        const NAME: &'static str = "TrackerFrame";
        const BUFFER: usize = SUBSCRIBER_BUFFER;
    }

    #[test]
    fn a_peer_with_another_layout_version_is_refused_with_a_clear_error() {
        let services = Services::new(&format!("layout-test-{}", std::process::id())).unwrap();
        let node = services.node("test").unwrap();
        let _ours = open_pubsub::<TrackerFrame>(&node, &services.tracker()).unwrap();
        let err = open_pubsub::<FutureTrackerFrame>(&node, &services.tracker()).unwrap_err();
        assert!(
            matches!(
                err,
                IpcError::LayoutMismatch {
                    ours: LAYOUT_VERSION,
                    ..
                }
            ),
            "{err:?}"
        );
        assert!(err.to_string().contains("different TrackerFrame layout"));
        assert!(check_layout("EngineFrame", 7)
            .unwrap_err()
            .to_string()
            .contains("layout v7"));
        drop(_ours);
        drop(node);
        services.remove_instance_segment().unwrap();
        assert!(
            services.leftovers().is_empty(),
            "{:?}",
            services.leftovers()
        );
    }
}
