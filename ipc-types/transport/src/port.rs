//! The port traits: what a process loop needs of a stream, whatever carries it.
//!
//! A loop publishes through [`Publish`] and waits on [`Receive`]. The product wires them to iceoryx2
//! ([`crate::iox`]); tests wire them to in-memory ports ([`crate::memory`]) driven by a fake clock; a
//! recording, a fault injector or a network bridge is one more implementation. Errors are typed
//! ([`PortError`]) and keep their cause as `source()`.

use ipc_types::LayoutError;
use thiserror::Error;

/// The sending end of a stream.
pub trait Publish<T> {
    /// Send `value` and wake the stream's consumers. Must not allocate or block on the hot path.
    fn publish(&mut self, value: &T) -> Result<(), PortError>;
}

/// The receiving end of a stream.
pub trait Receive<T> {
    /// Sleep until the producer signals new data or the monotonic clock reaches `deadline_ns`
    /// (absolute), whichever comes first. Returns at once when the deadline has passed. A wake-up
    /// may be spurious: callers check with [`Self::take_latest`].
    fn wait_until(&mut self, deadline_ns: u64) -> Result<(), PortError>;

    /// Drain every pending sample and return the newest, if any arrived.
    fn take_latest(&mut self) -> Result<Option<T>, PortError>;

    /// Drain every pending sample into `f`, oldest first; returns how many.
    fn drain(&mut self, f: &mut dyn FnMut(&T)) -> Result<usize, PortError>;
}

impl<T, P: Publish<T> + ?Sized> Publish<T> for Box<P> {
    fn publish(&mut self, value: &T) -> Result<(), PortError> {
        (**self).publish(value)
    }
}

impl<T, R: Receive<T> + ?Sized> Receive<T> for Box<R> {
    fn wait_until(&mut self, deadline_ns: u64) -> Result<(), PortError> {
        (**self).wait_until(deadline_ns)
    }
    fn take_latest(&mut self) -> Result<Option<T>, PortError> {
        (**self).take_latest()
    }
    fn drain(&mut self, f: &mut dyn FnMut(&T)) -> Result<usize, PortError> {
        (**self).drain(f)
    }
}

/// What went wrong opening or using a port. Each variant names the service; the transport's own
/// error is the `source()`.
#[derive(Debug, Error)]
pub enum PortError {
    /// The instance name cannot be used in service and file names.
    #[error(
        "instance name {name:?} is not usable: use 1-48 characters from A-Z, a-z, 0-9, '-' and '_'"
    )]
    BadInstanceName {
        /// The offending name.
        name: String,
    },
    /// A service name was rejected by the transport.
    #[error("service name {name:?} was rejected by iceoryx2")]
    BadServiceName {
        /// The offending name.
        name: String,
    },
    /// The process's iceoryx2 node could not be created.
    #[error("cannot create the iceoryx2 node {node:?}")]
    Node {
        /// Node name.
        node: String,
        /// iceoryx2's reason.
        #[source]
        source: iceoryx2::node::NodeCreationFailure,
    },
    /// The service exists with another payload layout (a process built from another version).
    #[error(
        "service {service:?} already exists with a different {payload} layout (this process speaks \
         layout v{ours}): another lungdyn build is running with the same instance name; stop it or \
         rebuild all processes from one version"
    )]
    LayoutMismatch {
        /// Service name.
        service: String,
        /// Payload type.
        payload: &'static str,
        /// Our layout version.
        ours: u32,
    },
    /// A publish-subscribe service could not be opened or created.
    #[error("cannot open the stream {service:?}")]
    OpenStream {
        /// Service name.
        service: String,
        /// iceoryx2's reason.
        #[source]
        source: iceoryx2::service::builder::publish_subscribe::PublishSubscribeOpenOrCreateError,
    },
    /// An event service could not be opened or created.
    #[error("cannot open the wake-up event {service:?}")]
    OpenEvent {
        /// Service name.
        service: String,
        /// iceoryx2's reason.
        #[source]
        source: iceoryx2::service::builder::event::EventOpenOrCreateError,
    },
    /// A port (publisher, subscriber, notifier, listener) could not be created on a service.
    #[error("cannot create the {port} of {service:?}")]
    CreatePort {
        /// Which port.
        port: &'static str,
        /// Service name.
        service: String,
        /// iceoryx2's reason.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// The handler of a stop signal could not be installed.
    #[error("cannot install the handler of signal {signal} (stop requests): {source}")]
    Signals {
        /// The signal's number.
        signal: i32,
        /// Why.
        source: std::io::Error,
    },
    /// The resources of a dead process's iceoryx2 node could not be removed.
    #[error("instance {instance:?}: cannot remove a dead process's iceoryx2 resources: {reason}")]
    DeadNodes {
        /// Instance name.
        instance: String,
        /// What failed.
        reason: String,
    },
    /// Sending, receiving or waiting failed on an open port.
    #[error("{operation} on {service:?} failed")]
    Io {
        /// What was being done ("loan a sample", "send", "notify", "receive", "wait").
        operation: &'static str,
        /// Service name.
        service: String,
        /// The transport's reason.
        #[source]
        source: Box<dyn std::error::Error + Send + Sync>,
    },
    /// A received payload speaks another layout.
    #[error(transparent)]
    Layout(#[from] LayoutError),
    /// Another process already holds this role in this instance.
    #[error(
        "instance {instance:?} is already running: its {role} is {holder}; stop it, or give this run \
         another name with --instance"
    )]
    InstanceBusy {
        /// Instance name.
        instance: String,
        /// Role held.
        role: String,
        /// Who holds it ("process 1234 (lungdyn demo ...)").
        holder: String,
    },
    /// The instance's lock file could not be used.
    #[error("cannot take the lock of instance {instance:?}: {source}")]
    Lock {
        /// Instance name.
        instance: String,
        /// OS error.
        source: std::io::Error,
    },
    /// The producer of a finite stream (a recording, a scripted test source) has nothing more.
    #[error("the stream {stream:?} has ended")]
    Ended {
        /// Stream name.
        stream: String,
    },
}
