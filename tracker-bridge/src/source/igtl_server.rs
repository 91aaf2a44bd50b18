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
//!
//! Only senders on the allow-list are served ([`AllowList`]): loopback always, other hosts only
//! when named (`--igtl-allow 10.0.0.5` or a network, `--igtl-allow 10.0.0.0/24`). Listening on
//! 0.0.0.0 without the list would let any host on the network stream a pose for the patient tool
//! and move the overlay. A sender refused is a [`EventKind::ConnectionRefused`] event naming it
//! and the flag that admits it.

use std::net::{SocketAddr, TcpListener, TcpStream};
use std::sync::atomic::{AtomicU64, Ordering};
use std::sync::Arc;
use std::thread::JoinHandle;
use std::time::Duration;

use transport::now_ns;

use crate::sample::{Event, EventKind, Input};
use crate::source::igtl_client::{pump, PumpEnd};
use crate::source::igtl_owners::ToolOwners;
use crate::source::{Feed, Inbox, Poll, Source, SourceError, SourceOptions};

/// Connections served at once.
pub const MAX_SENDERS: usize = 16;

/// A connection quiet this long may be closed to make room for a new one.
pub const EVICT_AFTER: Duration = Duration::from_millis(500);

pub use crate::allow::AllowList;

/// The OpenIGTLink server source.
#[derive(Debug)]
pub struct IgtlServer {
    inbox: Inbox,
    local: SocketAddr,
    allowed: String,
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
        let opts = options.clone();
        let t = std::thread::Builder::new()
            .name("igtl-server".into())
            .spawn(move || accept_thread(listener, &feed, &opts))
            .expect("spawning a thread");
        inbox.adopt(t);
        let allowed = options.igtl_allow.describe();
        Ok(IgtlServer {
            inbox,
            local,
            allowed,
        })
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
    let owners = Arc::new(ToolOwners::default());
    while !feed.stopping() {
        match listener.accept() {
            Ok((stream, peer)) if !options.igtl_allow.allows(peer.ip()) => {
                feed.event(Event::new(
                    EventKind::ConnectionRefused,
                    0,
                    format!(
                        "refused {peer}: not on the allow-list ({}); a tracking PC there is \
                         admitted with --igtl-allow {}",
                        options.igtl_allow.describe(),
                        peer.ip()
                    ),
                ));
                drop(stream);
            }
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
                if let Some(s) = serve(stream, peer, feed, options, &owners) {
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
    owners: &Arc<ToolOwners>,
) -> Option<Sender> {
    stream.set_nonblocking(false).ok()?;
    let socket = stream.try_clone().ok()?;
    let last_message_ns = Arc::new(AtomicU64::new(0));
    let (feed, options, last) = (feed.clone(), options.clone(), last_message_ns.clone());
    let owners = owners.clone();
    let thread = std::thread::Builder::new()
        .name("igtl-sender".into())
        .spawn(move || {
            let name = peer.to_string();
            feed.event(Event::new(
                EventKind::Connected,
                0,
                format!("sender {name} connected"),
            ));
            let (end, _) = pump(&mut stream, &feed, &name, &options, &last, Some(&owners));
            owners.release(&name);
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
        format!(
            "OpenIGTLink server on {} serving senders from {}",
            self.local, self.allowed
        )
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

    #[test]
    fn the_allow_list_takes_loopback_and_the_named_hosts_and_networks_only() {
        let ip = |s: &str| s.parse::<std::net::IpAddr>().unwrap();
        let none = AllowList::default();
        assert!(none.allows(ip("127.0.0.1")) && none.allows(ip("::1")));
        assert!(none.allows(ip("::ffff:127.0.0.1")));
        assert!(!none.allows(ip("10.0.0.5")));
        assert_eq!(none.describe(), "loopback");
        let l = AllowList::parse(&["10.0.0.5".into(), "192.168.7.9/24".into(), "fe80::1".into()])
            .unwrap();
        assert!(l.allows(ip("10.0.0.5")) && !l.allows(ip("10.0.0.6")));
        assert!(l.allows(ip("192.168.7.200")) && !l.allows(ip("192.168.8.1")));
        assert!(l.allows(ip("::ffff:10.0.0.5")));
        assert!(l.allows(ip("fe80::1")) && !l.allows(ip("fe80::2")));
        assert_eq!(l.describe(), "loopback, 10.0.0.5, 192.168.7.0/24, fe80::1");
        for (bad, word) in [
            ("tracker.local", "not an address"),
            ("10.0.0.0/33", "not an address"),
            ("0.0.0.0/0", "every host"),
            ("", "not an address"),
        ] {
            let e = AllowList::parse(&[bad.into()]).unwrap_err();
            assert!(e.contains(word), "{bad}: {e}");
        }
    }

    /// This machine's first IPv4 address that is not loopback (getifaddrs), if any.
    fn non_loopback_v4() -> Option<std::net::Ipv4Addr> {
        let mut list: *mut libc::ifaddrs = std::ptr::null_mut();
        // SAFETY: getifaddrs fills `list`, freed below; each entry's address is read only when it
        // is non-null and of the AF_INET family (a sockaddr_in).
        unsafe {
            if libc::getifaddrs(&mut list) != 0 {
                return None;
            }
            let mut found = None;
            let mut p = list;
            while !p.is_null() {
                let a = (*p).ifa_addr;
                if !a.is_null() && i32::from((*a).sa_family) == libc::AF_INET {
                    let sin = &*(a as *const libc::sockaddr_in);
                    let ip = std::net::Ipv4Addr::from(u32::from_be(sin.sin_addr.s_addr));
                    if !ip.is_loopback() {
                        found = Some(ip);
                        break;
                    }
                }
                p = (*p).ifa_next;
            }
            libc::freeifaddrs(list);
            found
        }
    }

    /// Whether the server closed a connection from `ip` at once (refused) or kept it (served).
    fn closed_at_once(server: &IgtlServer, ip: std::net::Ipv4Addr) -> bool {
        use std::io::Read;
        let mut c = TcpStream::connect((ip, server.local_addr().port())).unwrap();
        c.set_read_timeout(Some(Duration::from_millis(1500)))
            .unwrap();
        let mut b = [0u8; 1];
        match c.read(&mut b) {
            Ok(0) => true,
            Err(e) => e.kind() == std::io::ErrorKind::ConnectionReset,
            Ok(_) => false,
        }
    }

    #[test]
    fn a_sender_from_another_host_is_refused_unless_allowed() {
        let Some(ip) = non_loopback_v4() else {
            eprintln!("no IPv4 address but loopback on this machine: the refusal is tested by the unit test above only");
            return;
        };
        let refused = IgtlServer::bind("0.0.0.0", 0, &SourceOptions::default()).unwrap();
        assert!(
            closed_at_once(&refused, ip),
            "a sender from {ip} was served by default"
        );
        assert!(refused.describe().contains("serving senders from loopback"));
        let opts = SourceOptions {
            igtl_allow: AllowList::parse(&[ip.to_string()]).unwrap(),
            ..Default::default()
        };
        let served = IgtlServer::bind("0.0.0.0", 0, &opts).unwrap();
        assert!(
            !closed_at_once(&served, ip),
            "a sender from {ip} on the list was refused"
        );
    }
}
