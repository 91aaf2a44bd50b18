//! OpenIGTLink server: senders (PLUS, Slicer, pyigtl, a navigation system) connect to it, several
//! at once, each read on its own thread by [`super::igtl_client::pump`]; their messages meet in one
//! queue. A sender that goes away is reported; the server keeps listening. At most
//! [`MAX_SENDERS`] connections are served at once; further ones are closed and reported.

use std::net::{SocketAddr, TcpListener};
use std::sync::atomic::{AtomicUsize, Ordering};
use std::sync::Arc;
use std::time::Duration;

use crate::sample::{Event, EventKind, Input};
use crate::source::igtl_client::{pump, PumpEnd};
use crate::source::{Feed, Inbox, Poll, Source, SourceError, SourceOptions};

/// Connections served at once.
pub const MAX_SENDERS: usize = 16;

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

fn accept_thread(listener: TcpListener, feed: &Feed, options: &SourceOptions) {
    let active = Arc::new(AtomicUsize::new(0));
    let mut threads = Vec::new();
    while !feed.stopping() {
        match listener.accept() {
            Ok((mut stream, peer)) => {
                threads.retain(|t: &std::thread::JoinHandle<()>| !t.is_finished());
                if active.load(Ordering::Relaxed) >= MAX_SENDERS {
                    feed.event(Event::new(
                        EventKind::Note,
                        0,
                        format!("refused {peer}: already {MAX_SENDERS} senders connected"),
                    ));
                    drop(stream);
                    continue;
                }
                if stream.set_nonblocking(false).is_err() {
                    continue;
                }
                active.fetch_add(1, Ordering::Relaxed);
                let (feed, options, active_here) = (feed.clone(), options.clone(), active.clone());
                let spawned = std::thread::Builder::new()
                    .name("igtl-sender".into())
                    .spawn(move || {
                        let name = peer.to_string();
                        feed.event(Event::new(
                            EventKind::Connected,
                            0,
                            format!("sender {name} connected"),
                        ));
                        let (end, _) = pump(&mut stream, &feed, &name, &options);
                        if let PumpEnd::Lost(why) = end {
                            feed.event(Event::new(EventKind::Disconnected, 0, why));
                        }
                        active_here.fetch_sub(1, Ordering::Relaxed);
                    });
                match spawned {
                    Ok(t) => threads.push(t),
                    Err(_) => {
                        active.fetch_sub(1, Ordering::Relaxed);
                    }
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
    for t in threads {
        let _ = t.join();
    }
}

impl Source for IgtlServer {
    fn describe(&self) -> String {
        format!("OpenIGTLink server on {}", self.local)
    }

    fn poll(&mut self, now_ns: u64, sink: &mut dyn FnMut(&Input)) -> Result<Poll, SourceError> {
        self.inbox.drain(sink);
        Ok(Poll::Tick { at_ns: now_ns })
    }

    fn wait(&mut self, _pace: &dyn crate::run::Pace, deadline_ns: u64) -> bool {
        // A reader thread on the host's clock: publish on arrival.
        self.inbox.wait(deadline_ns)
    }
}
