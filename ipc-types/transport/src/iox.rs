//! The product transport: iceoryx2 zero-copy shared memory.
//!
//! A stream is a publish–subscribe service carrying one [`Message`] plus an event service that wakes
//! its consumers: [`Outlet`] (publisher + notifier) implements [`Publish`], [`Inlet`] (subscriber +
//! listener) implements [`Receive`]. Payloads travel as [`Wire<T>`], a transparent wrapper that
//! gives the protocol's `Pod` types iceoryx2's `ZeroCopySend` with their versioned type name, so
//! iceoryx2 itself refuses a peer of another layout ([`PortError::LayoutMismatch`]).
//!
//! Each instance uses its own iceoryx2 file prefix ([`Instance::file_prefix`]), so leftovers are
//! attributable and two runs never share a segment.

use core::time::Duration;

use iceoryx2::node::NodeView;
use iceoryx2::prelude::*;
use ipc_types::{ControlPacket, ControlReply, EngineFrame, FrameReport, Message, TrackerFrame};

use crate::clock::now_ns;
use crate::instance::Instance;
use crate::port::{PortError, Publish, Receive};
use crate::wake::{Arrivals, Wake};

/// A protocol payload as iceoryx2 carries it: the same bytes, with the payload's versioned type name.
#[repr(transparent)]
#[derive(Debug, Clone, Copy)]
pub struct Wire<T>(pub T);

// SAFETY: `Wire<T>` is `repr(transparent)` over a `Pod` payload: no pointers, no padding, a fixed
// layout pinned by const assertions in `ipc-types`, valid in any process that maps the same bytes.
// Its type name (iceoryx2 derives `TypeName` from this) carries the layout version.
unsafe impl<T: Message> ZeroCopySend for Wire<T> {
    unsafe fn type_name() -> &'static str {
        T::TYPE_NAME
    }
}

/// Per-stream quality of service: how many samples each subscriber keeps, and how many ports and
/// processes may use the stream (and its wake-up event) at once.
pub trait Topic: Message {
    /// Buffer depth per subscriber (the oldest sample is dropped when full).
    const BUFFER: usize;
    /// Publishers (and notifiers of the wake-up event) at once.
    const MAX_PUBLISHERS: usize = 4;
    /// Subscribers (and listeners of the wake-up event) at once.
    const MAX_SUBSCRIBERS: usize = 8;
    /// Processes (iceoryx2 nodes) using the stream at once.
    const MAX_NODES: usize = 16;
}
impl Topic for TrackerFrame {
    const BUFFER: usize = 4;
}
impl Topic for EngineFrame {
    const BUFFER: usize = 4;
}
/// Senders of a trainee's actions at once (`lungdyn scene event` processes, the renderer): each
/// keeps its publisher until the engine answers, so every one needs its own port.
pub const MAX_CONTROL_SENDERS: usize = 40;
impl Topic for ControlPacket {
    // Every sender has one action in flight (the renderer a few): the buffer holds one from each
    // even while the engine is stalled, so none is overwritten before the engine takes it.
    const BUFFER: usize = 2 * MAX_CONTROL_SENDERS;
    const MAX_PUBLISHERS: usize = MAX_CONTROL_SENDERS;
    const MAX_SUBSCRIBERS: usize = 2;
    const MAX_NODES: usize = MAX_CONTROL_SENDERS + 8;
}
impl Topic for ControlReply {
    // Each sender sees every reply (two per action) and keeps its own: room for two per sender.
    const BUFFER: usize = 2 * MAX_CONTROL_SENDERS;
    const MAX_PUBLISHERS: usize = 2;
    const MAX_SUBSCRIBERS: usize = MAX_CONTROL_SENDERS;
    const MAX_NODES: usize = MAX_CONTROL_SENDERS + 8;
}
impl Topic for control_state::ControlStateFrame {
    // One per breathing cycle; the remote bridge drains them every few ms. History 1 gives a
    // bridge started late the current state at once.
    const BUFFER: usize = 8;
}
impl Topic for FrameReport {
    // Drained in batches by the launcher: a deeper buffer keeps every frame.
    const BUFFER: usize = 512;
}

/// An iceoryx2 node of this transport.
pub type IoxNode = Node<ipc::Service>;

/// iceoryx2's root folder (where node and service files live besides `/dev/shm`).
pub use crate::instance::root_path;

/// An iceoryx2 config whose files carry the instance's prefix.
pub fn config(instance: &Instance) -> Result<Config, PortError> {
    let mut config = Config::default();
    config.global.prefix = FileName::new(instance.file_prefix().as_bytes()).map_err(|_| {
        PortError::BadInstanceName {
            name: instance.name().to_string(),
        }
    })?;
    Ok(config)
}

/// Create the iceoryx2 node of process `role` (e.g. "engine") in `instance`. iceoryx2's signal
/// handling is disabled (it would install handlers that keep only the last signal caught, so a
/// SIGCONT after a SIGTERM lost the stop): stop requests are [`crate::stop`]'s.
pub fn node(instance: &Instance, role: &str) -> Result<IoxNode, PortError> {
    let name = format!("lungdyn-{}-{}", instance.name(), role);
    let node_name = NodeName::new(&name).map_err(|_| PortError::BadInstanceName {
        name: instance.name().to_string(),
    })?;
    NodeBuilder::new()
        .name(&node_name)
        .config(&config(instance)?)
        .signal_handling_mode(SignalHandlingMode::Disabled)
        .create::<ipc::Service>()
        .map_err(|source| PortError::Node { node: name, source })
}

/// How long [`remove_dead_nodes`] waits for another process already removing a dead node.
const DEAD_NODE_CLEANUP_WAIT: std::time::Duration = std::time::Duration::from_secs(10);

/// Remove the iceoryx2 resources of this instance's dead nodes (a process killed before it could
/// clean up: its node, ports and the segments only it held), as iceoryx2 prescribes: `Node::list`,
/// then `blocking_remove_stale_resources` on each node in [`NodeState::Dead`]. Returns the names of
/// the nodes cleaned. Run before restarting a process, so the new one does not meet its
/// predecessor's ports (a stream's publisher or subscriber count would otherwise include the dead
/// one). Another process of the instance may be removing the same node at that moment: that is
/// waited for ([`DEAD_NODE_CLEANUP_WAIT`] at most; iceoryx2 takes the cleanup over should that
/// process die meanwhile), and a node it has finished counts as cleaned. (With
/// `try_remove_stale_resources` that was `AnotherInstanceIsCleaningUpTheNode`, an error that failed
/// the restart and the run: seen under load in `demo_faults`' restart storm.)
pub fn remove_dead_nodes(instance: &Instance) -> Result<Vec<String>, PortError> {
    let config = config(instance)?;
    let mut cleaned = Vec::new();
    let mut failure = None;
    Node::<ipc::Service>::list(&config, |state| {
        if let NodeState::Dead(view) = state {
            let name = view
                .details()
                .as_ref()
                .map_or_else(|| "(unnamed)".to_string(), |d| d.name().to_string());
            match view.blocking_remove_stale_resources(DEAD_NODE_CLEANUP_WAIT) {
                Ok(()) => cleaned.push(name),
                Err(e) => failure = Some(format!("node {name}: {e:?}")),
            }
        }
        CallbackProgression::Continue
    })
    .map_err(|e| PortError::DeadNodes {
        instance: instance.name().to_string(),
        reason: format!("cannot list the nodes: {e}"),
    })?;
    match failure {
        Some(reason) => Err(PortError::DeadNodes {
            instance: instance.name().to_string(),
            reason,
        }),
        None => Ok(cleaned),
    }
}

/// The port factory of a stream of `T`.
pub type Stream<T> =
    iceoryx2::service::port_factory::publish_subscribe::PortFactory<ipc::Service, Wire<T>, ()>;
/// The port factory of a wake-up event.
pub type Event = iceoryx2::service::port_factory::event::PortFactory<ipc::Service>;

fn service_name(name: &str) -> Result<ServiceName, PortError> {
    name.try_into().map_err(|_| PortError::BadServiceName {
        name: name.to_string(),
    })
}

/// Open (or create) the stream `name` carrying `T` with lungdyn's QoS. A peer built with another
/// payload layout yields [`PortError::LayoutMismatch`].
pub fn open_stream<T: Topic>(node: &IoxNode, name: &str) -> Result<Stream<T>, PortError> {
    use iceoryx2::service::builder::publish_subscribe::{
        PublishSubscribeOpenError as O, PublishSubscribeOpenOrCreateError as E,
    };
    node.service_builder(&service_name(name)?)
        .publish_subscribe::<Wire<T>>()
        .history_size(1)
        .subscriber_max_buffer_size(T::BUFFER)
        .enable_safe_overflow(true)
        .max_publishers(T::MAX_PUBLISHERS)
        .max_subscribers(T::MAX_SUBSCRIBERS)
        .max_nodes(T::MAX_NODES)
        .open_or_create()
        .map_err(|e| match e {
            E::PublishSubscribeOpenError(O::IncompatibleTypes) => PortError::LayoutMismatch {
                service: name.to_string(),
                payload: T::NAME,
                ours: ipc_types::LAYOUT_VERSION,
            },
            source => PortError::OpenStream {
                service: name.to_string(),
                source,
            },
        })
}

/// Open (or create) the wake-up event `name` of a stream of `T` (as many notifiers and listeners as
/// the stream has publishers and subscribers).
pub fn open_event<T: Topic>(node: &IoxNode, name: &str) -> Result<Event, PortError> {
    node.service_builder(&service_name(name)?)
        .event()
        .max_notifiers(T::MAX_PUBLISHERS)
        .max_listeners(T::MAX_SUBSCRIBERS)
        .max_nodes(T::MAX_NODES)
        .open_or_create()
        .map_err(|source| PortError::OpenEvent {
            service: name.to_string(),
            source,
        })
}

fn create_port<'a, E: std::error::Error + Send + Sync + 'static>(
    port: &'static str,
    service: &'a str,
) -> impl FnOnce(E) -> PortError + 'a {
    move |e| PortError::CreatePort {
        port,
        service: service.to_string(),
        source: Box::new(e),
    }
}

fn io<'a, E: std::error::Error + Send + Sync + 'static>(
    operation: &'static str,
    service: &'a str,
) -> impl FnOnce(E) -> PortError + 'a {
    move |e| PortError::Io {
        operation,
        service: service.to_string(),
        source: Box::new(e),
    }
}

/// The sending end of a stream: a publisher plus the event that wakes its consumers.
pub struct Outlet<T: Topic> {
    publisher: iceoryx2::port::publisher::Publisher<ipc::Service, Wire<T>, ()>,
    notifier: iceoryx2::port::notifier::Notifier<ipc::Service>,
    name: String,
    _data: Stream<T>,
    _event: Event,
}

impl<T: Topic> Outlet<T> {
    /// Open the stream `data` and its wake-up event `event`.
    pub fn new(node: &IoxNode, data: &str, event: &str) -> Result<Self, PortError> {
        let data_service = open_stream::<T>(node, data)?;
        let event_service = open_event::<T>(node, event)?;
        let publisher = data_service
            .publisher_builder()
            .create()
            .map_err(create_port("publisher", data))?;
        let notifier = event_service
            .notifier_builder()
            .create()
            .map_err(create_port("notifier", event))?;
        Ok(Self {
            publisher,
            notifier,
            name: data.to_string(),
            _data: data_service,
            _event: event_service,
        })
    }
}

impl<T: Topic> Outlet<T> {
    /// Subscribers connected to this stream now (a one-off sender waits for its reader: a sample
    /// sent before anyone subscribes is not kept).
    pub fn subscribers(&self) -> usize {
        use iceoryx2::service::port_factory::PortFactory as _;
        self._data.dynamic_config().number_of_subscribers()
    }
}

impl<T: Topic> Publish<T> for Outlet<T> {
    /// Zero-copy loan, no allocation; then wake the consumers.
    fn publish(&mut self, value: &T) -> Result<(), PortError> {
        let sample = self
            .publisher
            .loan_uninit()
            .map_err(io("loan a sample", &self.name))?;
        sample
            .write_payload(Wire(*value))
            .send()
            .map_err(io("send", &self.name))?;
        self.notifier.notify().map_err(io("notify", &self.name))?;
        Ok(())
    }
}

/// The receiving end of a stream: a subscriber plus the event listener that wakes us, waiting by
/// its [`Wake`] strategy ([`Wake::Event`] unless [`Inlet::set_wake`] says otherwise).
pub struct Inlet<T: Topic> {
    subscriber: iceoryx2::port::subscriber::Subscriber<ipc::Service, Wire<T>, ()>,
    listener: iceoryx2::port::listener::Listener<ipc::Service>,
    name: String,
    wake: Wake,
    arrivals: Arrivals,
    /// When a wait saw the sample now pending (0: none seen), for [`Arrivals`].
    seen_ns: u64,
    _data: Stream<T>,
    _event: Event,
}

impl<T: Topic> Inlet<T> {
    /// Open the stream `data` and its wake-up event `event`.
    pub fn new(node: &IoxNode, data: &str, event: &str) -> Result<Self, PortError> {
        let data_service = open_stream::<T>(node, data)?;
        let event_service = open_event::<T>(node, event)?;
        let subscriber = data_service
            .subscriber_builder()
            .create()
            .map_err(create_port("subscriber", data))?;
        let listener = event_service
            .listener_builder()
            .create()
            .map_err(create_port("listener", event))?;
        Ok(Self {
            subscriber,
            listener,
            name: data.to_string(),
            wake: Wake::Event,
            arrivals: Arrivals::default(),
            seen_ns: 0,
            _data: data_service,
            _event: event_service,
        })
    }

    /// Wait by `wake` from now on (the process chose it with [`crate::wake::choose`]). Call it from
    /// the thread that waits: spin-then-park sets that thread's timer slack to 1 µs (the kernel's
    /// default 50 µs would start the spin window late; real-time threads have none anyway).
    pub fn set_wake(&mut self, wake: Wake) {
        self.wake = wake;
        if let Wake::SpinThenPark { .. } = wake {
            let slack_ns: libc::c_ulong = 1_000;
            // SAFETY: PR_SET_TIMERSLACK takes one integer and changes only the calling thread.
            unsafe { libc::prctl(libc::PR_SET_TIMERSLACK, slack_ns) };
        }
    }

    /// The strategy in force.
    pub fn wake(&self) -> Wake {
        self.wake
    }

    /// Sleep on the event until `until_ns` (absolute; at once when past, still consuming pending
    /// wake-ups). True when woken before it: a notification or a signal (SIGINT/SIGTERM end the
    /// wait early on purpose: the loop checks for a stop request next, see `crate::stop`).
    fn park(&mut self, until_ns: u64) -> Result<bool, PortError> {
        use iceoryx2::port::listener::ListenerWaitError;
        let now = now_ns();
        let waited = if until_ns <= now {
            self.listener.try_wait(|_| {})
        } else {
            self.listener
                .timed_wait(|_| {}, Duration::from_nanos(until_ns - now))
        };
        match waited {
            Ok(n) => Ok(n > 0),
            Err(ListenerWaitError::InterruptSignal) => Ok(true),
            Err(e) => Err(io("wait", &self.name)(e)),
        }
    }

    /// [`Self::park`] with the clock's precision: `ppoll` on the listener's descriptor (an hrtimer)
    /// instead of iceoryx2's timed wait, whose socket timeout (`SO_RCVTIMEO`) counts whole
    /// scheduler ticks and would sleep through a spin window a fraction of a period away; every
    /// deadline wait uses it (measured by `cargo bench -p lungdyn-bench --bench ipc_hop`, last
    /// table: a deadline 2 ms away with nothing arriving returned 6.0 ms late at p50 with
    /// iceoryx2's timed wait, on the 2-core VM).
    /// Wake-ups signalled before must be consumed first ([`Self::clear_wakeups`]): iceoryx2 sends
    /// no datagram while one is pending.
    fn park_precisely(&mut self, until_ns: u64) -> Result<bool, PortError> {
        let now = now_ns();
        if until_ns <= now {
            return self.park(0);
        }
        let left = until_ns - now;
        // SAFETY: the descriptor is the listener's, open for as long as `self` lives.
        let fd = unsafe { self.listener.file_descriptor().native_handle() };
        let mut poll = libc::pollfd {
            fd,
            events: libc::POLLIN,
            revents: 0,
        };
        let timeout = libc::timespec {
            tv_sec: (left / 1_000_000_000) as libc::time_t,
            tv_nsec: (left % 1_000_000_000) as libc::c_long,
        };
        // SAFETY: one pollfd we own, a valid timespec, no signal mask.
        let ready = unsafe { libc::ppoll(&mut poll, 1, &timeout, core::ptr::null()) };
        match ready {
            0 => Ok(false),
            // A signal (ready < 0, EINTR): woken early on purpose, as in `park`.
            r if r < 0 => Ok(true),
            _ => {
                self.park(0)?;
                Ok(true)
            }
        }
    }

    /// Consume the wake-ups already signalled (a spin about to start makes them unnecessary; left
    /// alone they would pile up in the listener and cut the next park short).
    fn clear_wakeups(&mut self) -> Result<(), PortError> {
        self.park(0).map(|_| ())
    }

    /// Spin on the subscriber until a sample is pending (true, its time noted) or `until_ns`
    /// passes (false); looks at least once.
    fn spin(&mut self, until_ns: u64) -> Result<bool, PortError> {
        loop {
            if self
                .subscriber
                .has_samples()
                .map_err(io("receive", &self.name))?
            {
                self.seen_ns = now_ns();
                return Ok(true);
            }
            if now_ns() >= until_ns {
                return Ok(false);
            }
            core::hint::spin_loop();
        }
    }

    /// Samples were taken: note when they arrived (spin-then-park learns the stream's rhythm).
    fn arrived(&mut self) {
        if matches!(self.wake, Wake::SpinThenPark { .. }) {
            let at = match self.seen_ns {
                0 => now_ns(),
                t => t,
            };
            self.arrivals.observe(at);
        }
        self.seen_ns = 0;
    }
}

impl<T: Topic> Receive<T> for Inlet<T> {
    fn wait_until(&mut self, deadline_ns: u64) -> Result<(), PortError> {
        match self.wake {
            Wake::Event => {
                self.park_precisely(deadline_ns)?;
            }
            Wake::BusyPoll => {
                self.clear_wakeups()?;
                self.spin(deadline_ns)?;
            }
            Wake::SpinThenPark { spin_ns } => {
                self.clear_wakeups()?;
                if self.spin(0)? {
                    return Ok(());
                }
                if let Some(w) = self.arrivals.window(spin_ns) {
                    let now = now_ns();
                    if w.until_ns > now && w.from_ns < deadline_ns {
                        // Woken before the window: an early sample (or a signal); the caller
                        // looks and waits again.
                        if w.from_ns > now && self.park_precisely(w.from_ns)? {
                            return Ok(());
                        }
                        self.arrivals.spun(w.due_ns);
                        if self.spin(w.until_ns.min(deadline_ns))? {
                            return Ok(());
                        }
                    }
                }
                self.park_precisely(deadline_ns)?;
            }
        }
        Ok(())
    }

    fn take_latest(&mut self) -> Result<Option<T>, PortError> {
        let mut latest = None;
        while let Some(sample) = self
            .subscriber
            .receive()
            .map_err(io("receive", &self.name))?
        {
            latest = Some(sample.payload().0);
        }
        if latest.is_some() {
            self.arrived();
        }
        Ok(latest)
    }

    fn drain(&mut self, f: &mut dyn FnMut(&T)) -> Result<usize, PortError> {
        let mut n = 0;
        while let Some(sample) = self
            .subscriber
            .receive()
            .map_err(io("receive", &self.name))?
        {
            f(&sample.payload().0);
            n += 1;
        }
        if n > 0 {
            self.arrived();
        }
        Ok(n)
    }
}

/// The three streams of a process, opened on its node.
impl Instance {
    /// Outlet of the tracker stream.
    pub fn tracker_outlet(&self, node: &IoxNode) -> Result<Outlet<TrackerFrame>, PortError> {
        Outlet::new(node, &self.tracker(), &self.tracker_event())
    }
    /// Inlet of the tracker stream.
    pub fn tracker_inlet(&self, node: &IoxNode) -> Result<Inlet<TrackerFrame>, PortError> {
        Inlet::new(node, &self.tracker(), &self.tracker_event())
    }
    /// Outlet of the engine stream.
    pub fn engine_outlet(&self, node: &IoxNode) -> Result<Outlet<EngineFrame>, PortError> {
        Outlet::new(node, &self.engine(), &self.engine_event())
    }
    /// Inlet of the engine stream.
    pub fn engine_inlet(&self, node: &IoxNode) -> Result<Inlet<EngineFrame>, PortError> {
        Inlet::new(node, &self.engine(), &self.engine_event())
    }
    /// Outlet of the report stream.
    pub fn report_outlet(&self, node: &IoxNode) -> Result<Outlet<FrameReport>, PortError> {
        Outlet::new(node, &self.report(), &self.report_event())
    }
    /// Inlet of the report stream.
    pub fn report_inlet(&self, node: &IoxNode) -> Result<Inlet<FrameReport>, PortError> {
        Inlet::new(node, &self.report(), &self.report_event())
    }
    /// Outlet of the control stream (a trainee's actions).
    pub fn control_outlet(&self, node: &IoxNode) -> Result<Outlet<ControlPacket>, PortError> {
        Outlet::new(node, &self.control(), &self.control_event())
    }
    /// Inlet of the control stream.
    pub fn control_inlet(&self, node: &IoxNode) -> Result<Inlet<ControlPacket>, PortError> {
        Inlet::new(node, &self.control(), &self.control_event())
    }
    /// Outlet of the control replies (the engine's answers).
    pub fn control_reply_outlet(&self, node: &IoxNode) -> Result<Outlet<ControlReply>, PortError> {
        Outlet::new(node, &self.control_reply(), &self.control_reply_event())
    }
    /// Outlet of the engine's control state (remote sites).
    pub fn control_state_outlet(
        &self,
        node: &IoxNode,
    ) -> Result<Outlet<control_state::ControlStateFrame>, PortError> {
        Outlet::new(node, &self.control_state(), &self.control_state_event())
    }
    /// Inlet of the engine's control state.
    pub fn control_state_inlet(
        &self,
        node: &IoxNode,
    ) -> Result<Inlet<control_state::ControlStateFrame>, PortError> {
        Inlet::new(node, &self.control_state(), &self.control_state_event())
    }
    /// Inlet of the control replies.
    pub fn control_reply_inlet(&self, node: &IoxNode) -> Result<Inlet<ControlReply>, PortError> {
        Inlet::new(node, &self.control_reply(), &self.control_reply_event())
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use bytemuck::{Pod, Zeroable};

    /// A peer built with another layout version must be refused when it opens the stream.
    #[repr(C)]
    #[derive(Debug, Clone, Copy, Pod, Zeroable)]
    struct FutureTrackerFrame {
        layout_version: u32,
        other: u32,
    }
    impl Message for FutureTrackerFrame {
        const NAME: &'static str = "TrackerFrame";
        const TYPE_NAME: &'static str = "lungdyn.TrackerFrame.v999";
        fn layout_version(&self) -> u32 {
            self.layout_version
        }
    }
    impl Topic for FutureTrackerFrame {
        const BUFFER: usize = 4;
    }

    #[test]
    fn a_peer_with_another_layout_version_is_refused_with_a_clear_error() {
        let instance = Instance::new(&format!("layout-test-{}", std::process::id())).unwrap();
        let node = node(&instance, "test").unwrap();
        let ours = open_stream::<TrackerFrame>(&node, &instance.tracker()).unwrap();
        let err =
            open_stream::<FutureTrackerFrame>(&node, &instance.tracker()).expect_err("refused");
        assert!(
            matches!(
                err,
                PortError::LayoutMismatch {
                    ours: ipc_types::LAYOUT_VERSION,
                    ..
                }
            ),
            "{err:?}"
        );
        assert!(err.to_string().contains("different TrackerFrame layout"));
        drop(ours);
        drop(node);
        let cleanup = instance.remove_leftovers();
        assert!(cleanup.unexpected.is_empty(), "{cleanup:?}");
        assert!(
            instance.leftovers().is_empty(),
            "{:?}",
            instance.leftovers()
        );
    }

    #[test]
    fn samples_cross_a_stream_with_their_exact_bytes() {
        let instance = Instance::new(&format!("wire-test-{}", std::process::id())).unwrap();
        let node = node(&instance, "test").unwrap();
        let mut rx = instance.engine_inlet(&node).unwrap();
        let mut tx = instance.engine_outlet(&node).unwrap();
        let mut f = EngineFrame {
            layout_version: ipc_types::LAYOUT_VERSION,
            tick: 9,
            ..Default::default()
        };
        f.lungs[1].coeffs[5] = f32::from_bits(0x7f7f_1234);
        tx.publish(&f).unwrap();
        f.tick = 10;
        tx.publish(&f).unwrap();
        rx.wait_until(now_ns() + 1_000_000_000).unwrap();
        let got = rx.take_latest().unwrap().expect("a sample");
        assert_eq!(bytemuck::bytes_of(&got), bytemuck::bytes_of(&f));
        assert_eq!(rx.take_latest().unwrap(), None, "drained");
        drop((rx, tx, node));
        let cleanup = instance.remove_leftovers();
        assert!(
            cleanup.node_counter && cleanup.unexpected.is_empty(),
            "{cleanup:?}"
        );
        assert!(instance.leftovers().is_empty());
    }

    /// Each wake strategy takes every sample of a periodic stream in order, learns its period
    /// (spin-then-park), and with nothing published waits until the deadline (a spurious early
    /// return is allowed by [`Receive::wait_until`], a handful of them is not).
    #[test]
    fn every_wake_strategy_takes_each_sample_and_waits_out_the_deadline() {
        const N: u64 = 30;
        const PERIOD: u64 = 4_000_000;
        for (k, wake) in [
            Wake::Event,
            Wake::SpinThenPark { spin_ns: 300_000 },
            Wake::BusyPoll,
        ]
        .into_iter()
        .enumerate()
        {
            let name = format!("wake-test-{}-{k}", std::process::id());
            let instance = Instance::new(&name).unwrap();
            let node = node(&instance, "test").unwrap();
            let mut rx = instance.engine_inlet(&node).unwrap();
            rx.set_wake(wake);
            assert_eq!(rx.wake(), wake);
            let sender = std::thread::spawn(move || {
                let instance = Instance::new(&name).unwrap();
                let node = super::node(&instance, "sender").unwrap();
                let mut tx = instance.engine_outlet(&node).unwrap();
                let mut next = now_ns() + 50_000_000;
                for tick in 1..=N {
                    crate::clock::sleep_until_ns(next);
                    next += PERIOD;
                    tx.publish(&EngineFrame {
                        layout_version: ipc_types::LAYOUT_VERSION,
                        tick,
                        ..Default::default()
                    })
                    .unwrap();
                }
            });
            let mut got = Vec::new();
            let give_up = now_ns() + 10_000_000_000;
            while got.last() != Some(&N) && now_ns() < give_up {
                rx.wait_until(now_ns() + 20_000_000).unwrap();
                rx.drain(&mut |f: &EngineFrame| got.push(f.tick)).unwrap();
            }
            sender.join().unwrap();
            assert_eq!(got.last(), Some(&N), "{wake}: {got:?}");
            // A wait that missed its sample (a spin that never looks) returns only at its 20 ms
            // timeout: five samples arrive meanwhile into a buffer of four, one per wait is lost.
            assert!(got.len() as u64 >= N - 3, "{wake}: {got:?}");
            assert!(got.windows(2).all(|w| w[0] < w[1]), "{wake}: {got:?}");
            if let Wake::SpinThenPark { .. } = wake {
                let p = rx.arrivals.period_ns();
                assert!(p > PERIOD / 2 && p < 2 * PERIOD, "learnt period {p}");
            }
            let deadline = now_ns() + 30_000_000;
            let mut waits = 0;
            while now_ns() < deadline {
                rx.wait_until(deadline).unwrap();
                waits += 1;
            }
            assert!(waits <= 3, "{wake}: {waits} waits for one deadline");
            assert_eq!(rx.take_latest().unwrap(), None);
            drop((rx, node));
            instance.remove_leftovers();
        }
    }

    /// What a SIGKILLed launcher leaves (iceoryx2's node counter, world-writable) is removed by the
    /// next start's sweep; a running instance's files and a lock-less test prefix are kept.
    #[test]
    fn the_sweep_removes_a_dead_instances_files_only() {
        let _one_sweep_test_at_a_time = crate::instance::tests::SWEEP_TEST
            .lock()
            .unwrap_or_else(|e| e.into_inner());
        let pid = std::process::id();
        let dead = Instance::new(&format!("sweep-dead-{pid}")).unwrap();
        let live = Instance::new(&format!("sweep-live-{pid}")).unwrap();
        let lockless = Instance::new(&format!("sweep-none-{pid}")).unwrap();
        // The dead instance's lock file names a process that is gone.
        let stale = Instance::lock_dir().join(format!("{}.launcher.lock", dead.name()));
        std::fs::create_dir_all(Instance::lock_dir()).unwrap();
        std::fs::write(
            &stale,
            format!("process {pid} (a launcher killed long ago)"),
        )
        .unwrap();
        drop(node(&dead, "launcher").unwrap());
        drop(node(&lockless, "test").unwrap());
        let _held = live.lock("launcher").unwrap();
        let live_node = node(&live, "launcher").unwrap();
        let left = dead.leftovers();
        assert!(!left.is_empty(), "a dropped node leaves its counter");
        let removed = Instance::sweep_dead();
        for f in &left {
            assert!(removed.contains(f), "{f:?} not in {removed:?}");
        }
        assert!(dead.leftovers().is_empty());
        assert!(!live.leftovers().is_empty(), "a running instance is kept");
        assert!(
            !lockless.leftovers().is_empty(),
            "no lock: not ours to judge"
        );
        std::fs::remove_file(&stale).unwrap();
        drop(live_node);
        live.remove_leftovers();
        lockless.remove_leftovers();
    }

    /// A node whose process died is found dead and its resources removed; a live one is kept.
    #[test]
    fn a_dead_processs_node_is_cleaned_before_a_restart() {
        let instance = Instance::new(&format!("dead-node-{}", std::process::id())).unwrap();
        let ours = node(&instance, "launcher").unwrap();
        // A child that creates a node and is killed before it can clean up.
        let exe = std::env::current_exe().unwrap();
        let mut child = std::process::Command::new(exe)
            .args([
                "--exact",
                "iox::tests::child_node_then_hang",
                "--ignored",
                "--nocapture",
            ])
            .env("LUNGDYN_DEAD_NODE_INSTANCE", instance.name())
            .stdout(std::process::Stdio::piped())
            .spawn()
            .unwrap();
        let mut line = String::new();
        use std::io::BufRead;
        let mut out = std::io::BufReader::new(child.stdout.take().unwrap());
        while !line.contains("node ready") {
            line.clear();
            assert!(out.read_line(&mut line).unwrap() > 0, "child ended early");
        }
        child.kill().unwrap();
        child.wait().unwrap();
        let cleaned = remove_dead_nodes(&instance).unwrap();
        assert_eq!(
            cleaned,
            vec![format!("lungdyn-{}-engine", instance.name())],
            "only the dead node"
        );
        assert!(remove_dead_nodes(&instance).unwrap().is_empty(), "once");
        drop(ours);
        let cleanup = instance.remove_leftovers();
        assert!(cleanup.unexpected.is_empty(), "{cleanup:?}");
    }

    /// The child half of the test above (run only by it).
    #[test]
    #[ignore = "started by a_dead_processs_node_is_cleaned_before_a_restart"]
    fn child_node_then_hang() {
        let Ok(name) = std::env::var("LUNGDYN_DEAD_NODE_INSTANCE") else {
            return;
        };
        let instance = Instance::new(&name).unwrap();
        let n = node(&instance, "engine").unwrap();
        let _stream = instance.engine_outlet(&n).unwrap();
        println!("node ready");
        std::thread::sleep(Duration::from_secs(60));
    }
}
