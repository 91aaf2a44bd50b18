//! OpenIGTLink client: connects to a PLUS server or 3D Slicer's OpenIGTLinkIF (the usual port
//! 18944), reads whatever they push, and reconnects with back-off when the peer is gone.
//!
//! Also the shared reading of one OpenIGTLink connection ([`pump`], used by the server for each
//! sender) and the mapping of messages to samples ([`message_inputs`]):
//!
//! | message | samples |
//! |---|---|
//! | `TRANSFORM` | one, named by the device name, rotation as a matrix |
//! | `POSITION` (28/24 bytes) | one, named by the device name, quaternion |
//! | `POSITION` (12 bytes) | one with no orientation: rejected `not_rotation` |
//! | `POSITION` (pyigtl, 152·N) | one per item, named by the item name (the device name when empty) |
//! | `TDATA` / `QTDATA` | one per element, named by the element name |
//! | `STATUS` | a device-status event |
//! | anything else | counted as ignored |
//!
//! The header timestamp becomes the sample's device time (repeats and backwards steps are
//! flagged); OpenIGTLink has no frame counter, so gaps cannot be seen. A CRC mismatch or a
//! malformed body rejects that message and reading goes on; a bad header version (not
//! OpenIGTLink, or a stream out of sync) or a body above the size limit drops the connection, so
//! the decoder never buffers more than one header plus the limit.

use std::io::{ErrorKind, Read};
use std::net::{TcpStream, ToSocketAddrs};
use std::os::fd::AsRawFd;
use std::sync::atomic::{AtomicU64, Ordering};
use std::time::Duration;

use transport::now_ns;

use crate::igtl::{Body, Decoder, IgtlError, Message, QuatOrder, Transform};
use crate::sample::{Event, EventKind, Input, Reject, Rotation, Sample, ToolName};
use crate::source::{Backoff, Feed, Inbox, Poll, Source, SourceError, SourceOptions};

/// How reads wait, so a stop request is seen within this time.
pub const READ_TIMEOUT: Duration = Duration::from_millis(100);

/// A connection that has delivered no message for this long is dropped (a sender that stopped
/// sending without closing, or a connection that never sent anything) — the default of
/// [`SourceOptions::igtl_idle_timeout`].
pub const IDLE_TIMEOUT: Duration = Duration::from_secs(10);

/// TCP keepalive on a connection: the first probe after `KEEPALIVE_IDLE_S` seconds without
/// traffic, then every `KEEPALIVE_INTERVAL_S`, dropped after `KEEPALIVE_PROBES` unanswered — a
/// peer gone without a FIN (cable pulled, Wi-Fi lost, the sender's machine off) is noticed in
/// 5 s, and its slot freed.
pub const KEEPALIVE_IDLE_S: i32 = 2;
/// See [`KEEPALIVE_IDLE_S`].
pub const KEEPALIVE_INTERVAL_S: i32 = 1;
/// See [`KEEPALIVE_IDLE_S`].
pub const KEEPALIVE_PROBES: i32 = 3;

/// Turn TCP keepalive on for `stream` with the timing of [`KEEPALIVE_IDLE_S`] (Linux options;
/// libc is already a dependency, so no socket crate for four `setsockopt` calls).
pub fn keepalive(stream: &TcpStream) -> std::io::Result<()> {
    let fd = stream.as_raw_fd();
    let set = |level: libc::c_int, name: libc::c_int, value: libc::c_int| {
        // SAFETY: `fd` is an open socket owned by `stream`; the option value is one c_int that
        // outlives the call.
        let rc = unsafe {
            libc::setsockopt(
                fd,
                level,
                name,
                (&value as *const libc::c_int).cast(),
                std::mem::size_of::<libc::c_int>() as libc::socklen_t,
            )
        };
        if rc == 0 {
            Ok(())
        } else {
            Err(std::io::Error::last_os_error())
        }
    };
    set(libc::SOL_SOCKET, libc::SO_KEEPALIVE, 1)?;
    set(libc::IPPROTO_TCP, libc::TCP_KEEPIDLE, KEEPALIVE_IDLE_S)?;
    set(libc::IPPROTO_TCP, libc::TCP_KEEPINTVL, KEEPALIVE_INTERVAL_S)?;
    set(libc::IPPROTO_TCP, libc::TCP_KEEPCNT, KEEPALIVE_PROBES)
}

/// The reason an OpenIGTLink decoding error is counted under.
pub fn reject_of(e: &IgtlError) -> Reject {
    match e {
        IgtlError::Crc { .. } => Reject::Crc,
        IgtlError::BodyTooLarge { .. } => Reject::Oversized,
        IgtlError::BadVersion(_) => Reject::Garbage,
        IgtlError::Truncated { .. } => Reject::Truncated,
        _ => Reject::Malformed,
    }
}

fn matrix(t: &Transform) -> Rotation {
    Rotation::Matrix(t.rotation)
}

/// The inputs one decoded message gives.
pub fn message_inputs(
    msg: &Message,
    receive_ns: u64,
    order: QuatOrder,
    out: &mut dyn FnMut(Input),
) {
    let device = ToolName::from_bytes_lossy(msg.device_name.as_bytes());
    let device_time_ns = if msg.timestamp.is_unset() {
        0
    } else {
        msg.timestamp.to_unix_ns()
    };
    let sample = |name: ToolName, rotation: Rotation, t: [f32; 3]| Sample {
        receive_ns,
        device_time_ns,
        device_frame: None,
        name,
        tool_id: 0,
        rotation,
        translation_mm: t,
        rms_error_mm: None,
        device_flags: 0,
    };
    match &msg.body {
        Body::Transform(t) => out(Input::Sample(sample(device, matrix(t), t.translation_mm))),
        Body::Position(p) => {
            let rotation = match p.form {
                crate::igtl::PositionForm::PositionOnly => Rotation::None,
                _ => Rotation::Quat(p.quaternion),
            };
            out(Input::Sample(sample(device, rotation, p.position_mm)));
        }
        Body::PyigtlPosition(items) => {
            for item in items {
                let name = if item.name.is_empty() {
                    device
                } else {
                    ToolName::from_bytes_lossy(item.name.as_bytes())
                };
                out(Input::Sample(sample(
                    name,
                    Rotation::Quat(item.quaternion(order)),
                    item.position_mm,
                )));
            }
        }
        Body::TData(elements) => {
            for e in elements {
                let name = ToolName::from_bytes_lossy(e.name.as_bytes());
                out(Input::Sample(sample(
                    name,
                    matrix(&e.transform),
                    e.transform.translation_mm,
                )));
            }
        }
        Body::QtData(elements) => {
            for e in elements {
                let name = ToolName::from_bytes_lossy(e.name.as_bytes());
                out(Input::Sample(sample(
                    name,
                    Rotation::Quat(e.quaternion),
                    e.position_mm,
                )));
            }
        }
        Body::Status(s) => out(Input::Event(Event::new(
            EventKind::DeviceStatus,
            u32::from(s.code),
            format!(
                "{}: STATUS {} ({}) {} {}",
                msg.device_name,
                s.code,
                s.code_name(),
                s.error_name,
                s.message
            ),
        ))),
        body @ (Body::Sensor(_) | Body::Text(_)) => {
            if let Some(value) = crate::signal_igtl::reading_of(body) {
                out(Input::Reading(crate::sample::Reading {
                    receive_ns,
                    name: device,
                    value,
                }));
            }
        }
        other => out(Input::Event(Event::new(
            EventKind::Ignored,
            1,
            format!("{} message from {:?}", other.type_name(), msg.device_name),
        ))),
    }
}

/// How a connection ended.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum PumpEnd {
    /// The source is being dropped.
    Stopped,
    /// The link closed or failed; why.
    Lost(String),
}

/// Read one OpenIGTLink connection until it ends, handing every message's inputs to `feed`;
/// `last_message_ns` gets the receive time of each message. A connection with no message for
/// [`SourceOptions::igtl_idle_timeout`] is dropped; keepalive ([`keepalive`]) drops one whose peer
/// is gone. Returns how it ended and whether any message arrived.
pub fn pump(
    stream: &mut TcpStream,
    feed: &Feed,
    peer: &str,
    options: &SourceOptions,
    last_message_ns: &AtomicU64,
    owners: Option<&super::igtl_owners::ToolOwners>,
) -> (PumpEnd, bool) {
    let _ = stream.set_nodelay(true);
    if let Err(e) = keepalive(stream) {
        feed.event(Event::new(
            EventKind::Note,
            0,
            format!("{peer}: TCP keepalive not set ({e}); a peer that vanishes is noticed only by the idle timeout"),
        ));
    }
    let idle_ns = u64::try_from(options.igtl_idle_timeout.as_nanos()).unwrap_or(u64::MAX);
    let mut last = now_ns();
    if let Err(e) = stream.set_read_timeout(Some(READ_TIMEOUT)) {
        return (
            PumpEnd::Lost(format!("cannot set a read timeout: {e}")),
            false,
        );
    }
    let mut decoder = Decoder::new(options.igtl_limits);
    let mut buf = [0u8; 16 * 1024];
    let mut got_any = false;
    loop {
        if feed.stopping() {
            return (PumpEnd::Stopped, got_any);
        }
        let n = match stream.read(&mut buf) {
            Ok(0) => {
                if decoder.buffered_len() > 0 {
                    feed.event(Event::rejected(
                        Reject::Truncated,
                        1,
                        format!(
                            "{peer} closed the connection {} bytes into a message",
                            decoder.buffered_len()
                        ),
                    ));
                }
                return (
                    PumpEnd::Lost(format!("{peer} closed the connection")),
                    got_any,
                );
            }
            Ok(n) => n,
            Err(e)
                if matches!(
                    e.kind(),
                    ErrorKind::WouldBlock | ErrorKind::TimedOut | ErrorKind::Interrupted
                ) =>
            {
                if now_ns().saturating_sub(last) > idle_ns {
                    return (
                        PumpEnd::Lost(format!(
                            "{peer} sent no message for {:.1} s; dropping the connection",
                            options.igtl_idle_timeout.as_secs_f64()
                        )),
                        got_any,
                    );
                }
                continue;
            }
            Err(e) => return (PumpEnd::Lost(format!("reading from {peer}: {e}")), got_any),
        };
        let receive_ns = now_ns();
        let _batch = feed.batch();
        decoder.push(buf.get(..n).unwrap_or(&[]));
        for item in decoder.by_ref() {
            match item {
                Ok(msg) => {
                    got_any = true;
                    last = receive_ns;
                    last_message_ns.store(receive_ns, Ordering::Relaxed);
                    message_inputs(&msg, receive_ns, options.pyigtl_quat_order, &mut |i| {
                        if let (Some(o), Input::Sample(s)) = (owners, &i) {
                            match o.claim(s.name.as_str(), peer, receive_ns) {
                                Ok(None) => {}
                                Ok(Some(note)) => feed.event(Event::new(EventKind::Note, 0, note)),
                                Err(why) => {
                                    feed.event(Event::rejected(Reject::CompetingSender, 1, why));
                                    return;
                                }
                            }
                        }
                        feed.send(i)
                    });
                }
                Err(e) => feed.event(Event::rejected(reject_of(&e), 1, format!("{peer}: {e}"))),
            }
        }
        if decoder.is_failed() {
            return (
                PumpEnd::Lost(format!(
                    "{peer} sent something that is not OpenIGTLink; dropping the connection"
                )),
                got_any,
            );
        }
    }
}

/// Connect to `host:port`, trying each address it resolves to.
pub fn connect(host: &str, port: u16, timeout: Duration) -> std::io::Result<TcpStream> {
    let mut last = None;
    for addr in (host, port).to_socket_addrs()? {
        match TcpStream::connect_timeout(&addr, timeout) {
            Ok(s) => return Ok(s),
            Err(e) => last = Some(e),
        }
    }
    Err(last.unwrap_or_else(|| std::io::Error::new(ErrorKind::NotFound, "no address")))
}

/// The OpenIGTLink client source.
#[derive(Debug)]
pub struct IgtlClient {
    inbox: Inbox,
    peer: String,
}

impl IgtlClient {
    /// Start connecting to `host:port` in the background.
    pub fn start(host: String, port: u16, options: &SourceOptions) -> Self {
        let mut inbox = Inbox::new();
        let feed = inbox.feed();
        let peer = format!("{host}:{port}");
        let options = options.clone();
        let name = peer.clone();
        let t = std::thread::Builder::new()
            .name("igtl-client".into())
            .spawn(move || client_thread(&host, port, &name, &feed, &options))
            .expect("spawning a thread");
        inbox.adopt(t);
        IgtlClient { inbox, peer }
    }
}

fn client_thread(host: &str, port: u16, peer: &str, feed: &Feed, options: &SourceOptions) {
    let mut backoff = Backoff::default();
    while !feed.stopping() {
        match connect(host, port, Duration::from_secs(1)) {
            Ok(mut stream) => {
                feed.event(Event::new(
                    EventKind::Connected,
                    0,
                    format!("connected to {peer}"),
                ));
                let (end, got_any) =
                    pump(&mut stream, feed, peer, options, &AtomicU64::new(0), None);
                if got_any {
                    backoff.reset();
                }
                match end {
                    PumpEnd::Stopped => return,
                    PumpEnd::Lost(why) => feed.event(Event::new(EventKind::Disconnected, 0, why)),
                }
            }
            Err(e) => {
                let d = backoff.next_delay();
                feed.event(Event::new(
                    EventKind::Retrying,
                    d.as_millis() as u32,
                    format!(
                        "cannot connect to {peer}: {e}; retrying in {} ms",
                        d.as_millis()
                    ),
                ));
                if !feed.sleep(d) {
                    return;
                }
                continue;
            }
        }
        let d = backoff.next_delay();
        if !feed.sleep(d) {
            return;
        }
    }
}

impl Source for IgtlClient {
    fn describe(&self) -> String {
        format!("OpenIGTLink client of {}", self.peer)
    }

    fn poll(&mut self, now_ns: u64, sink: &mut dyn FnMut(&Input)) -> Result<Poll, SourceError> {
        self.inbox.drain(sink);
        Ok(Poll::Tick { at_ns: now_ns })
    }

    fn wait(&mut self, _pace: &dyn transport::Clock, deadline_ns: u64) -> bool {
        // A reader thread on the host's clock: publish on arrival.
        self.inbox.wait(deadline_ns)
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::igtl::{Sensor, Text, Timestamp};
    use crate::sample::{NotAmplitude, Reading};

    fn inputs(device: &str, body: Body) -> Vec<Input> {
        let m = Message::new(device, Timestamp::from_parts(1_700_000_000, 0), body);
        let mut out = Vec::new();
        message_inputs(&m, 42, QuatOrder::Xyzw, &mut |i| out.push(i));
        out
    }

    /// A SENSOR or STRING becomes a reading stamped with its arrival, in the unit its message
    /// states (a SENSOR in micro-m³ is ml); a SENSOR in another unit says why it is no amplitude.
    #[test]
    fn sensor_and_string_messages_are_readings_stamped_on_arrival() {
        let resp = ToolName::new("Resp").unwrap();
        let ml = crate::signal_igtl::SensorUnit::pack(0xC, &[(1, 3)]);
        let got = inputs(
            "Resp",
            Body::Sensor(Sensor {
                status: 0,
                unit: ml,
                values: vec![420.0],
            }),
        );
        assert_eq!(
            got,
            [Input::Reading(Reading {
                receive_ns: 42,
                name: resp,
                value: Ok((ipc_types::signal_unit::ML, Some(420.0))),
            })]
        );
        let pascal = crate::signal_igtl::SensorUnit::pack(0, &[(0x0C, 1)]);
        let got = inputs(
            "Resp",
            Body::Sensor(Sensor {
                status: 0,
                unit: pascal,
                values: vec![3.0],
            }),
        );
        assert!(
            matches!(&got[..], [Input::Reading(Reading { value: Err(NotAmplitude::Unit(u)), .. })] if *u == pascal),
            "{got:?}"
        );
        let got = inputs(
            "Resp",
            Body::Text(Text {
                encoding: 106,
                text: "au=0.25\n".into(),
            }),
        );
        assert!(
            matches!(&got[..], [Input::Reading(Reading { value: Ok((u, Some(v))), .. })] if *u == ipc_types::signal_unit::ARBITRARY && *v == 0.25),
            "{got:?}"
        );
    }
}
