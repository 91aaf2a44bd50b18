//! The OpenIGTLink sources against Rust peers on loopback: a server with several senders at once
//! (TRANSFORM, QTDATA, TDATA), a bad CRC, garbage, a message cut short and an oversized header
//! (never a published sample, never a large allocation, the server keeps serving); a client whose
//! server goes away and comes back (reconnect with back-off); a slow sender that shows as stale.

use std::io::Write;
use std::net::{TcpListener, TcpStream};
use std::time::{Duration, Instant};

use ipc_types::{tool_status, TrackerFrame, TOOL_HMD, TOOL_PATIENT};
use tracker_bridge::assemble::{Assembler, BridgeConfig};
use tracker_bridge::igtl::{Body, Message, QtDataElement, TDataElement, Timestamp, Transform};
use tracker_bridge::sample::Reject;
use tracker_bridge::source::igtl_client::IgtlClient;
use tracker_bridge::source::igtl_server::IgtlServer;
use tracker_bridge::source::{Source, SourceOptions};
use tracker_bridge::testing::run_source;
use tracker_bridge::validate::{Validation, Volume};
use transport::Monotonic;

fn config() -> BridgeConfig {
    BridgeConfig {
        validation: Validation {
            volume: Volume::SEED_CONE,
            ..Validation::default()
        },
        ..BridgeConfig::default()
    }
}

fn transform(name: &str, k: u32) -> Vec<u8> {
    transform_stamped(name, k, Timestamp::from_parts(1_700_000_000, k * 1000))
}

/// A TRANSFORM at x = `k` mm with the device timestamp `stamp`.
fn transform_stamped(name: &str, k: u32, stamp: Timestamp) -> Vec<u8> {
    let t = Transform {
        translation_mm: [k as f32, 0.0, -1000.0],
        ..Transform::IDENTITY
    };
    Message::new(name, stamp, Body::Transform(t))
        .encode()
        .unwrap()
}

fn qtdata(name: &str, k: u32) -> Vec<u8> {
    Message::new(
        "Tracker",
        Timestamp::from_parts(1_700_000_000, k * 1000 + 1),
        Body::QtData(vec![QtDataElement {
            name: name.into(),
            instrument_type: 2,
            position_mm: [0.0, k as f32, -900.0],
            quaternion: [0.0, 0.0, 0.0, 1.0],
        }]),
    )
    .encode()
    .unwrap()
}

/// One QTDATA with an element per name, in order, all at y = `k` mm.
fn qtdata_many(names: &[&str], k: u32) -> Vec<u8> {
    Message::new(
        "Tracker",
        Timestamp::from_parts(1_700_000_000, k * 1000 + 1),
        Body::QtData(
            names
                .iter()
                .map(|name| QtDataElement {
                    name: (*name).into(),
                    instrument_type: 2,
                    position_mm: [0.0, k as f32, -900.0],
                    quaternion: [0.0, 0.0, 0.0, 1.0],
                })
                .collect(),
        ),
    )
    .encode()
    .unwrap()
}

/// Run the loop until `done()` or `limit`.
fn run(
    source: &mut dyn Source,
    limit: Duration,
    mut done: impl FnMut() -> bool,
) -> (Vec<TrackerFrame>, Assembler) {
    let start = Instant::now();
    let r = run_source(
        source,
        config(),
        &Monotonic,
        &mut None,
        &mut || start.elapsed() > limit || done(),
        "igtl test",
    )
    .unwrap();
    (r.frames, r.assembler)
}

#[test]
fn a_server_takes_several_senders_and_survives_every_kind_of_bad_input() {
    let mut server = IgtlServer::bind("127.0.0.1", 0, &SourceOptions::default()).unwrap();
    let addr = server.local_addr();
    let senders = std::thread::spawn(move || {
        let patient = std::thread::spawn(move || {
            let mut s = TcpStream::connect(addr).unwrap();
            for k in 0..40 {
                s.write_all(&transform("Patient", k)).unwrap();
                if k == 20 {
                    let mut bad = transform("Patient", 999);
                    bad[60] ^= 0x01; // a body bit: the CRC no longer matches
                    s.write_all(&bad).unwrap();
                }
                std::thread::sleep(Duration::from_millis(16));
            }
        });
        let hmd = std::thread::spawn(move || {
            let mut s = TcpStream::connect(addr).unwrap();
            for k in 0..40 {
                // One message in two writes, split inside the header: a partial read is no message.
                let m = qtdata("HMD", k);
                s.write_all(&m[..30]).unwrap();
                s.flush().unwrap();
                std::thread::sleep(Duration::from_millis(3));
                s.write_all(&m[30..]).unwrap();
                std::thread::sleep(Duration::from_millis(13));
            }
        });
        // Garbage: not OpenIGTLink (header version 0x4745 "GE"): the connection is dropped.
        let mut g = TcpStream::connect(addr).unwrap();
        g.write_all(b"GET / HTTP/1.1\r\nHost: x\r\n\r\nand some more bytes to fill a header....")
            .unwrap();
        // An oversized body announced: dropped before anything is allocated for it.
        let mut o = TcpStream::connect(addr).unwrap();
        let mut head = transform("Patient", 1)[..58].to_vec();
        head[42..50].copy_from_slice(&(1u64 << 40).to_be_bytes());
        o.write_all(&head).unwrap();
        // Half a message, then the link closes.
        let mut h = TcpStream::connect(addr).unwrap();
        h.write_all(&transform("Patient", 5)[..80]).unwrap();
        drop(h);
        // A TDATA with a tool we do not map, and another sender's pointer.
        let mut t = TcpStream::connect(addr).unwrap();
        let td = Message::new(
            "Tracker",
            Timestamp::UNSET,
            Body::TData(vec![TDataElement {
                name: "Pointer".into(),
                instrument_type: 2,
                transform: Transform::IDENTITY,
            }]),
        );
        t.write_all(&td.encode().unwrap()).unwrap();
        patient.join().unwrap();
        hmd.join().unwrap();
        std::thread::sleep(Duration::from_millis(200));
    });
    let (frames, asm) = run(&mut server, Duration::from_secs(15), || {
        senders.is_finished()
    });
    let s = &asm.stats;
    eprintln!("{}", s.text());
    assert_eq!(s.rejected_for(Reject::Crc), 1);
    assert_eq!(s.rejected_for(Reject::Garbage), 1);
    assert_eq!(s.rejected_for(Reject::Oversized), 1);
    assert_eq!(s.rejected_for(Reject::Truncated), 1);
    assert_eq!(s.rejected_for(Reject::Unmapped), 1);
    assert_eq!(s.connects, 6);
    assert!(s.disconnects >= 3, "garbage, oversized, half message");
    let patient = s
        .tools
        .iter()
        .find(|t| t.name.as_str() == "Patient")
        .unwrap();
    let hmd = s.tools.iter().find(|t| t.name.as_str() == "HMD").unwrap();
    assert_eq!(
        (patient.samples, patient.accepted),
        (40, 40),
        "the bad ones never became samples"
    );
    assert_eq!((hmd.samples, hmd.accepted), (40, 40));
    assert_eq!(
        patient.last_pose.unwrap().translation_mm,
        [39.0, 0.0, -1000.0]
    );
    assert_eq!(hmd.last_pose.unwrap().translation_mm, [0.0, 39.0, -900.0]);
    // Every published pose is one that was sent.
    for f in frames.iter().filter(|f| f.tools[TOOL_PATIENT].is_valid()) {
        let x = f.tools[TOOL_PATIENT].pose.translation_mm;
        assert!(x[0].fract() == 0.0 && (0.0..40.0).contains(&x[0]) && x[1..] == [0.0, -1000.0]);
    }
    assert!(
        frames
            .iter()
            .filter(|f| f.tools[TOOL_HMD].is_valid())
            .count()
            > 20
    );
}

#[test]
fn forty_junk_names_before_the_patient_in_each_qtdata_do_not_push_it_out_of_the_tools_list() {
    let mut server = IgtlServer::bind("127.0.0.1", 0, &SourceOptions::default()).unwrap();
    let addr = server.local_addr();
    let sender = std::thread::spawn(move || {
        let junk: Vec<String> = (0..40).map(|k| format!("junk{k}")).collect();
        let mut names: Vec<&str> = junk.iter().map(String::as_str).collect();
        names.push("Patient");
        let mut s = TcpStream::connect(addr).unwrap();
        for k in 0..20 {
            s.write_all(&qtdata_many(&names, k)).unwrap();
            std::thread::sleep(Duration::from_millis(16));
        }
        std::thread::sleep(Duration::from_millis(200));
    });
    let (frames, asm) = run(&mut server, Duration::from_secs(15), || {
        sender.is_finished()
    });
    let s = &asm.stats;
    let patient = s.tools.iter().find(|t| t.slot == Some(TOOL_PATIENT as u8));
    assert_eq!(
        patient.map(|p| (p.name.as_str(), p.samples, p.accepted)),
        Some(("Patient", 20, 20)),
        "{}",
        s.text()
    );
    assert_eq!(s.rejected_for(Reject::Unmapped), 20 * 40);
    assert_eq!(s.accepted, 20);
    let json = s.to_json();
    let listed = json["tools"]
        .as_array()
        .unwrap()
        .iter()
        .find(|t| t["name"] == "Patient")
        .cloned();
    assert_eq!(
        listed.map(|t| (t["frames"].as_u64(), t["accepted"].as_u64())),
        Some((Some(20), Some(20))),
        "{json}"
    );
    assert!(frames.iter().any(|f| f.tools[TOOL_PATIENT].is_valid()));
}

#[test]
fn a_sender_whose_timestamp_never_advances_counts_one_accepted_pose_and_the_rest_as_repeats() {
    let mut server = IgtlServer::bind("127.0.0.1", 0, &SourceOptions::default()).unwrap();
    let addr = server.local_addr();
    let sender = std::thread::spawn(move || {
        let mut s = TcpStream::connect(addr).unwrap();
        for k in 1..=70 {
            let stamp = Timestamp::from_parts(1_700_000_000, 0);
            s.write_all(&transform_stamped("Patient", k, stamp))
                .unwrap();
            std::thread::sleep(Duration::from_millis(5));
        }
        std::thread::sleep(Duration::from_millis(200));
    });
    let (frames, asm) = run(&mut server, Duration::from_secs(15), || {
        sender.is_finished()
    });
    let s = &asm.stats;
    let patient = s.tools.iter().find(|t| t.name.as_str() == "Patient");
    assert_eq!(
        patient.map(|p| (p.samples, p.accepted, p.repeats)),
        Some((70, 1, 69)),
        "{}",
        s.text()
    );
    assert_eq!(patient.unwrap().last_pose.unwrap().translation_mm[0], 1.0);
    assert_eq!((s.accepted, s.frame_repeats), (1, 69));
    let mut published: Vec<f32> = frames
        .iter()
        .filter(|f| f.tools[TOOL_PATIENT].is_valid())
        .map(|f| f.tools[TOOL_PATIENT].pose.translation_mm[0])
        .collect();
    published.dedup();
    assert_eq!(published, [1.0], "one pose was published");
    let json = s.to_json();
    assert_eq!(json["tools"][0]["repeats"], 69, "{json}");
}

#[test]
fn a_client_reconnects_with_backoff_when_its_server_goes_and_comes_back() {
    // Find a free port, then let the client try it before anything listens (below the ephemeral
    // range: a port from bind(0) once reached another test's server here).
    let port = lungdyn_needs::free_local_port();
    let mut client = IgtlClient::start("127.0.0.1".into(), port, &SourceOptions::default());
    let server = std::thread::spawn(move || {
        std::thread::sleep(Duration::from_millis(500));
        let l = TcpListener::bind(("127.0.0.1", port)).unwrap();
        for round in 0..2u32 {
            let (mut s, _) = l.accept().unwrap();
            for k in 0..20 {
                if s.write_all(&transform("Patient", round * 100 + k)).is_err() {
                    break;
                }
                std::thread::sleep(Duration::from_millis(16));
            }
            drop(s); // the server goes away; the client must come back
        }
        std::thread::sleep(Duration::from_millis(300));
    });
    let (frames, asm) = run(&mut client, Duration::from_secs(15), || {
        server.is_finished()
    });
    let s = &asm.stats;
    eprintln!("{}", s.text());
    assert!(
        s.retries >= 2,
        "tried while nothing listened: {}",
        s.retries
    );
    assert!(s.connects >= 2 && s.disconnects >= 2);
    let patient = s
        .tools
        .iter()
        .find(|t| t.name.as_str() == "Patient")
        .unwrap();
    assert_eq!(patient.samples, 40);
    assert_eq!(patient.last_pose.unwrap().translation_mm[0], 119.0);
    // Between the rounds the tool went stale, and came back valid.
    let stale = frames
        .iter()
        .position(|f| f.tools[TOOL_PATIENT].status & tool_status::STALE != 0);
    assert!(stale.is_some());
    assert!(frames[stale.unwrap()..]
        .iter()
        .any(|f| f.tools[TOOL_PATIENT].is_valid()));
}

#[test]
fn a_slow_sender_shows_as_stale_between_its_samples() {
    let mut server = IgtlServer::bind("127.0.0.1", 0, &SourceOptions::default()).unwrap();
    let addr = server.local_addr();
    let sender = std::thread::spawn(move || {
        let mut s = TcpStream::connect(addr).unwrap();
        for k in 0..8 {
            s.write_all(&transform("Patient", k)).unwrap();
            std::thread::sleep(Duration::from_millis(150)); // 6.7 Hz against a 50 ms bound
        }
    });
    let (frames, asm) = run(&mut server, Duration::from_secs(10), || {
        sender.is_finished()
    });
    let stale = frames
        .iter()
        .filter(|f| f.tools[TOOL_PATIENT].status & tool_status::STALE != 0)
        .count();
    let valid = frames
        .iter()
        .filter(|f| f.tools[TOOL_PATIENT].is_valid())
        .count();
    assert!(stale > valid, "stale {stale}, valid {valid}");
    assert!(valid >= 8, "each sample is fresh for up to 50 ms: {valid}");
    assert_eq!(asm.stats.stale as usize, stale);
}

#[test]
fn sixteen_idle_connections_do_not_lock_a_real_sender_out() {
    use tracker_bridge::source::igtl_server::{EVICT_AFTER, MAX_SENDERS};
    let mut server = IgtlServer::bind("127.0.0.1", 0, &SourceOptions::default()).unwrap();
    let addr = server.local_addr();
    let sender = std::thread::spawn(move || {
        let idle: Vec<TcpStream> = (0..MAX_SENDERS)
            .map(|_| TcpStream::connect(addr).unwrap())
            .collect();
        std::thread::sleep(EVICT_AFTER + Duration::from_millis(300));
        let mut s = TcpStream::connect(addr).unwrap();
        for k in 1..=30 {
            s.write_all(&transform("Patient", k)).unwrap();
            std::thread::sleep(Duration::from_millis(16));
        }
        // A seventeenth connection while the real sender is live: another idle one makes room,
        // never the sender.
        let late = TcpStream::connect(addr).unwrap();
        for k in 31..=60 {
            s.write_all(&transform("Patient", k)).unwrap();
            std::thread::sleep(Duration::from_millis(16));
        }
        drop((idle, late));
    });
    let (frames, asm) = run(&mut server, Duration::from_secs(15), || {
        sender.is_finished()
    });
    let s = &asm.stats;
    eprintln!("{}", s.text());
    let patient = s.tools.iter().find(|t| t.name.as_str() == "Patient");
    assert_eq!(
        patient.map(|p| (p.samples, p.accepted)),
        Some((60, 60)),
        "every sample of the real sender: {}",
        s.text()
    );
    assert_eq!(s.connects as usize, MAX_SENDERS + 2);
    assert_eq!(
        (s.evicted_idle_connections, s.refused_connections),
        (2, 0),
        "the real sender's connection and the late one each closed an idle one"
    );
    let link = &s.to_json()["link"];
    assert_eq!(
        (
            link["evicted_idle_connections"].as_u64(),
            link["refused_connections"].as_u64()
        ),
        (Some(2), Some(0))
    );
    let published: Vec<f32> = frames
        .iter()
        .filter(|f| f.tools[TOOL_PATIENT].is_valid())
        .map(|f| f.tools[TOOL_PATIENT].pose.translation_mm[0])
        .collect();
    assert!(published.contains(&1.0) && published.contains(&60.0));
}

#[test]
fn a_connection_beyond_sixteen_fresh_ones_is_refused_and_counted() {
    use tracker_bridge::source::igtl_server::MAX_SENDERS;
    let mut server = IgtlServer::bind("127.0.0.1", 0, &SourceOptions::default()).unwrap();
    let addr = server.local_addr();
    let sender = std::thread::spawn(move || {
        let fresh: Vec<TcpStream> = (0..MAX_SENDERS)
            .map(|_| TcpStream::connect(addr).unwrap())
            .collect();
        // At once, well inside EVICT_AFTER: none of the sixteen may be closed for it, so it is
        // refused (the server closes it: the read sees the end of the stream).
        let mut extra = TcpStream::connect(addr).unwrap();
        extra
            .set_read_timeout(Some(Duration::from_secs(5)))
            .unwrap();
        let mut buf = [0u8; 1];
        let n = std::io::Read::read(&mut extra, &mut buf).unwrap_or(1);
        std::thread::sleep(Duration::from_millis(200));
        drop(fresh);
        n
    });
    let (_, asm) = run(&mut server, Duration::from_secs(15), || {
        sender.is_finished()
    });
    assert_eq!(sender.join().unwrap(), 0, "the newcomer was closed");
    let s = &asm.stats;
    assert_eq!(
        (s.refused_connections, s.evicted_idle_connections),
        (1, 0),
        "{}",
        s.text()
    );
    assert_eq!(s.connects as usize, MAX_SENDERS);
    assert_eq!(s.to_json()["link"]["refused_connections"], 1);
    assert!(s.text().contains("1 refused connections"), "{}", s.text());
}

#[test]
fn a_connection_that_sends_nothing_is_dropped_after_the_idle_timeout() {
    let options = SourceOptions {
        igtl_idle_timeout: Duration::from_millis(300),
        ..SourceOptions::default()
    };
    let mut server = IgtlServer::bind("127.0.0.1", 0, &options).unwrap();
    let addr = server.local_addr();
    let peer = std::thread::spawn(move || {
        let mut s = TcpStream::connect(addr).unwrap();
        s.write_all(&transform("Patient", 1)).unwrap();
        // Quiet from now on: the server closes the connection (read sees end of stream).
        s.set_read_timeout(Some(Duration::from_secs(5))).unwrap();
        let mut buf = [0u8; 1];
        let start = Instant::now();
        let n = std::io::Read::read(&mut s, &mut buf).unwrap_or(0);
        (n, start.elapsed())
    });
    let (_, asm) = run(&mut server, Duration::from_secs(10), || peer.is_finished());
    let (n, after) = peer.join().unwrap();
    assert_eq!(n, 0, "closed by the server");
    assert!(after < Duration::from_secs(5), "closed after {after:?}");
    assert_eq!((asm.stats.connects, asm.stats.disconnects), (1, 1));
}

#[test]
fn keepalive_is_set_on_a_connection() {
    let l = TcpListener::bind("127.0.0.1:0").unwrap();
    let s = TcpStream::connect(l.local_addr().unwrap()).unwrap();
    tracker_bridge::source::igtl_client::keepalive(&s).unwrap();
    let get = |level, name| {
        let mut v: libc::c_int = 0;
        let mut len = std::mem::size_of::<libc::c_int>() as libc::socklen_t;
        // SAFETY: reading one c_int option of an open socket into our variable.
        let rc = unsafe {
            libc::getsockopt(
                std::os::fd::AsRawFd::as_raw_fd(&s),
                level,
                name,
                (&mut v as *mut libc::c_int).cast(),
                &mut len,
            )
        };
        assert_eq!(rc, 0);
        v
    };
    assert_eq!(get(libc::SOL_SOCKET, libc::SO_KEEPALIVE), 1);
    assert_eq!(get(libc::IPPROTO_TCP, libc::TCP_KEEPIDLE), 2);
    assert_eq!(get(libc::IPPROTO_TCP, libc::TCP_KEEPINTVL), 1);
    assert_eq!(get(libc::IPPROTO_TCP, libc::TCP_KEEPCNT), 3);
}

/// Two senders stream "Patient" at once (the case: two pyigtl senders from different
/// positions): the first keeps the tool, every sample of the second is refused as a competing
/// sender and counted, and only the first's positions reach the frames; when the first stops, the
/// second takes over and that is said.
#[test]
fn a_second_sender_of_the_same_tool_is_refused_counted_and_takes_over_when_the_first_stops() {
    let mut server = IgtlServer::bind("127.0.0.1", 0, &SourceOptions::default()).unwrap();
    let addr = server.local_addr();
    let senders = std::thread::spawn(move || {
        let mut first = TcpStream::connect(addr).unwrap();
        first.write_all(&transform("Patient", 1)).unwrap();
        std::thread::sleep(Duration::from_millis(100));
        let second = std::thread::spawn(move || {
            let mut s = TcpStream::connect(addr).unwrap();
            // At x = 100 + k mm (inside the tracking volume): never the first sender's (1..=30).
            for k in 0..60 {
                s.write_all(&transform("Patient", 100 + k)).unwrap();
                std::thread::sleep(Duration::from_millis(16));
            }
        });
        for k in 2..=30 {
            first.write_all(&transform("Patient", k)).unwrap();
            std::thread::sleep(Duration::from_millis(16));
        }
        drop(first);
        second.join().unwrap();
        std::thread::sleep(Duration::from_millis(200));
    });
    let (frames, asm) = run(&mut server, Duration::from_secs(15), || {
        senders.is_finished()
    });
    let s = &asm.stats;
    let competing = s.rejected_for(Reject::CompetingSender);
    assert!(competing >= 20, "{}", s.text());
    let json = s.to_json();
    assert!(json.to_string().contains("competing_sender"), "{json}");
    // While the first streamed, no frame carried the second's positions.
    let xs: Vec<f32> = frames
        .iter()
        .filter(|f| f.tools[TOOL_PATIENT].is_valid())
        .map(|f| f.tools[TOOL_PATIENT].pose.translation_mm[0])
        .collect();
    let first_end = xs
        .iter()
        .rposition(|&x| x <= 30.0)
        .expect("the first sender's poses");
    assert!(
        xs[..=first_end].iter().all(|&x| x <= 30.0),
        "interleaved: {xs:?}"
    );
    // After it left, the second took over.
    assert!(
        xs[first_end + 1..].iter().any(|&x| x >= 100.0),
        "no takeover: {xs:?}\n{}",
        s.text()
    );
}
