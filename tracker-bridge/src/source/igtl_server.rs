//! OpenIGTLink server: senders (PLUS, Slicer, pyigtl, a navigation system) connect to it, several
//! at once, each read on its own thread by [`super::igtl_client::pump`]; their messages meet in one
//! queue. A sender that goes away is reported; the server keeps listening.
//!
//! Connections cannot lock a real sender out: each has TCP keepalive (a peer gone without closing
//! is dropped within seconds) and an idle timeout ([`SourceOptions::igtl_idle_timeout`]); at most
//! [`MAX_SENDERS`] are served at once, and when a new one arrives with every slot taken, the
//! idlest connection — the one longest without a message, if that is at least [`EVICT_AFTER`] —
//! is closed to make room (a live tracker sends every few milliseconds, so it is never the one).
//! Only when every connection has sent (or connected) within [`EVICT_AFTER`] is the newcomer
//! refused. Both are [`EventKind::ConnectionRefused`] events, so they are counted in the
//! statistics (`link.refused_connections`, `link.evicted_idle_connections`), not only printed.

use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use transport::now_ns;

use crate::sample::{Event, EventKind, Input};
use crate::source::igtl_client::{pump, PumpEnd};
use crate::source::{Feed, Inbox, Poll, Source, SourceError, SourceOptions};

/// Connections served at once.
pub const MAX_SENDERS: usize = 16;

/// A connection quiet this long may be closed to make room for a new one.
pub const EVICT_AFTER: Duration = Duration::from_millis(500);

/// The OpenIGTLink server source.
#[derive(Debug)]
pub struct IgtlServer {
    inbox: Inbox,
    local: SocketAddr,
}

impl IgtlServer {
    /// Listen on `bind:port` (port 0: any free port, see [`IgtlServer::local_addr`]).
    pub fn bind(bind: &str, port: u16, options: &SourceOptions) -> Result<Self, SourceError> {
        let addr = format!("{bind}:{port}");
        let bind_err = |source| SourceError::Bind {
            addr: addr.clone(),
            source,
        };
        let listener = TcpListener::bind((bind, port)).map_err(bind_err)?;
        listener.set_nonblocking(true).map_err(bind_err)?;
        let local = listener.local_addr().map_err(bind_err)?;
        let mut inbox = Inbox::new();
        let feed = inbox.feed();
        let options = options.clone();
        let t = std::thread::Builder::new()
            .name("igtl-server".into())
            .spawn(move || accept_thread(listener, &feed, &options))
            .expect("spawning a thread");
        inbox.adopt(t);
        Ok(IgtlServer { inbox, local })
    }

    /// The address it listens on.
    pub fn local_addr(&self) -> SocketAddr {
        self.local
    }
}

/// One served connection, as the accept thread sees it.
struct Sender {
    thread: JoinHandle<()>,
    /// A handle on the socket, to close it when evicted.
    socket: TcpStream,
    peer: SocketAddr,
    /// When it connected and when its last message arrived (0: none yet), ns.
    connected_ns: u64,
    last_message_ns: Arc<AtomicU64>,
}

impl Sender {
    /// How long it has been without a message (since it connected, when it never sent one).
    fn quiet_ns(&self, now: u64) -> u64 {
        let last = self.last_message_ns.load(Ordering::Relaxed);
        now.saturating_sub(last.max(self.connected_ns))
    }
}

/// The connection to close for a newcomer when every slot is taken: the one quiet longest, if
/// at least [`EVICT_AFTER`].
fn idlest(senders: &[Sender], now: u64) -> Option<usize> {
    let min = u64::try_from(EVICT_AFTER.as_nanos()).unwrap_or(u64::MAX);
    senders
        .iter()
        .enumerate()
        .map(|(i, s)| (s.quiet_ns(now), i))
        .filter(|&(q, _)| q >= min)
        .max()
        .map(|(_, i)| i)
}

fn accept_thread(listener: TcpListener, feed: &Feed, options: &SourceOptions) {
    let mut senders: Vec<Sender> = Vec::with_capacity(MAX_SENDERS);
    while !feed.stopping() {
        match listener.accept() {
            Ok((stream, peer)) => {
                senders.retain(|s| !s.thread.is_finished());
                if senders.len() >= MAX_SENDERS {
                    let now = now_ns();
                    match idlest(&senders, now) {
                        Some(i) => {
                            let s = &senders[i];
                            feed.event(Event::new(
                                EventKind::ConnectionRefused,
                                1,
                                format!(
                                    "closing {} (no message for {:.1} s) to make room for {peer}",
                                    s.peer,
                                    s.quiet_ns(now) as f64 / 1e9
                                ),
                            ));
                            let _ = s.socket.shutdown(std::net::Shutdown::Both);
                            let s = senders.swap_remove(i);
                            let _ = s.thread.join();
                        }
                        None => {
                            feed.event(Event::new(
                                EventKind::ConnectionRefused,
                                0,
                                format!(
                                    "refused {peer}: {MAX_SENDERS} senders connected, none quiet for {EVICT_AFTER:?}"
                                ),
                            ));
                            continue;
                        }
                    }
                }
                if let Some(s) = serve(stream, peer, feed, options) {
                    senders.push(s);
                }
            }
            Err(e) if e.kind() == std::io::ErrorKind::WouldBlock => {
                std::thread::sleep(Duration::from_millis(10));
            }
            Err(e) => {
                feed.event(Event::new(
                    EventKind::Note,
                    0,
                    format!("accept failed: {e}"),
                ));
                std::thread::sleep(Duration::from_millis(100));
            }
        }
    }
    for s in senders {
        let _ = s.thread.join();
    }
}

/// Start reading one connection on its own thread.
fn serve(
    mut stream: TcpStream,
    peer: SocketAddr,
    feed: &Feed,
    options: &SourceOptions,
) -> Option<Sender> {
    stream.set_nonblocking(false).ok()?;
    let socket = stream.try_clone().ok()?;
    let last_message_ns = Arc::new(AtomicU64::new(0));
    let (feed, options, last) = (feed.clone(), options.clone(), last_message_ns.clone());
    let thread = std::thread::Builder::new()
        .name("igtl-sender".into())
        .spawn(move || {
            let name = peer.to_string();
            feed.event(Event::new(
                EventKind::Connected,
                0,
                format!("sender {name} connected"),
            ));
            let (end, _) = pump(&mut stream, &feed, &name, &options, &last);
            // Close it now: the accept thread's handle (for eviction) would keep it open.
            let _ = stream.shutdown(std::net::Shutdown::Both);
            if let PumpEnd::Lost(why) = end {
                feed.event(Event::new(EventKind::Disconnected, 0, why));
            }
        })
        .ok()?;
    Some(Sender {
        thread,
        socket,
        peer,
        connected_ns: now_ns(),
        last_message_ns,
    })
}

impl Source for IgtlServer {
    fn describe(&self) -> String {
        format!("OpenIGTLink server on {}", self.local)
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
