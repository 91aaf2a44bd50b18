//! The hostile battery (issue 37 item 6) against a room with keys on 127.0.0.1, with real Zenoh
//! sessions: outsiders without the room's certificate (plain TCP, TLS without a client
//! certificate, another room's certificate) cannot connect; a participant holding a certificate of
//! the wrong role forges nothing (a state, an event, a clock answer), replays nothing, and junk is
//! refused; every refusal is counted by reason while the source and its site keep breathing.

mod common;
use common::wait_for;
use std::path::PathBuf;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;

use lungdyn_remote::harness::{harness_core, run_source};
use lungdyn_remote::keys::{self, Participant, Room};
use lungdyn_remote::link::Impairment;
use lungdyn_remote::seal::{Kind, Sealer};
use lungdyn_remote::site::{ClockSync, Site};
use lungdyn_remote::source::Source;
use lungdyn_remote::{site_id, Keys, Net};
use zenoh::Wait;

struct StopOnDrop(Arc<AtomicBool>);
impl Drop for StopOnDrop {
    fn drop(&mut self) {
        self.0.store(true, Ordering::Relaxed);
    }
}

struct Dir(PathBuf);
impl Drop for Dir {
    fn drop(&mut self) {
        let _ = std::fs::remove_dir_all(&self.0);
    }
}

/// A room `room` with a source, a site, an observer and a router, in a fresh folder.
fn room(room: &str, tag: &str) -> Dir {
    let d = std::env::temp_dir().join(format!("lungdyn-hostile-{tag}-{}", std::process::id()));
    let _ = std::fs::remove_dir_all(&d);
    let ps: Vec<Participant> = [
        "source:source",
        "site:site",
        "observer:observer",
        "router:router",
    ]
    .iter()
    .map(|p| p.parse().unwrap())
    .collect();
    keys::make(room, &d, &ps, 30).unwrap();
    Dir(d)
}

fn load(d: &Dir, who: &str) -> Arc<Room> {
    Arc::new(Room::load(&d.0, who).unwrap())
}

fn net(listen: &[String], connect: &[String], auth: Option<Arc<Room>>) -> Net {
    let mut n = Net::peer(listen, connect).with_keys(auth);
    n.lease_ms = 2000;
    n
}

/// A client session to `endpoint` with `cfg` changes: Ok if it connected.
fn client_with(endpoint: &str, extra: &[(&str, String)]) -> Result<zenoh::Session, String> {
    let mut c = zenoh::Config::default();
    let mut set = |k: &str, v: &str| c.insert_json5(k, v).unwrap();
    set("mode", "\"client\"");
    set("scouting/multicast/enabled", "false");
    set("connect/endpoints", &format!("[{endpoint:?}]"));
    for (k, v) in extra {
        set(k, v);
    }
    zenoh::open(c).wait().map_err(|e| e.to_string())
}

/// A client of the router at `endpoint` as `who` of `d`, with Zenoh's access control on or off.
fn client_net(d: &Dir, endpoint: &str, who: &str, acl: bool) -> Net {
    let mut n = net(&[], &[endpoint.to_string()], Some(load(d, who)));
    n.mode = "client";
    n.acl = acl;
    n
}

/// A classroom across networks in room "ward" of `d`: a router on a free TLS port, and as its
/// clients the source (id `site_id(0)`) and a site probing the source every 100 ms; Zenoh's
/// access control on or off everywhere (`acl`). Returns the router's session and endpoint.
fn classroom(d: &Dir, acl: bool) -> (zenoh::Session, String, Source, Site) {
    let keys = Keys::new("ward").unwrap();
    let endpoint = format!("tls/127.0.0.1:{}", lungdyn_needs::free_local_port());
    let mut router_net = net(&[endpoint.clone()], &[], Some(load(d, "router")));
    router_net.mode = "router";
    router_net.acl = acl;
    let router = router_net.open().unwrap();
    let source = Source::open(
        &client_net(d, &endpoint, "source", acl),
        &keys,
        site_id(0),
        Impairment::default(),
    )
    .unwrap();
    let site = Site::open(
        &client_net(d, &endpoint, "site", acl),
        &keys,
        site_id(1),
        false,
        Impairment::default(),
        100,
        ClockSync::Source,
    )
    .unwrap();
    (router, endpoint, source, site)
}

#[test]
fn outsiders_without_the_rooms_certificate_cannot_connect() {
    let ours = room("ward", "outsiders-ours");
    let theirs = room("ward", "outsiders-theirs");
    let port = lungdyn_needs::free_local_port();
    let endpoint = format!("tls/127.0.0.1:{port}");
    let keys = Keys::new("ward").unwrap();
    let source = Source::open(
        &net(&[endpoint.clone()], &[], Some(load(&ours, "source"))),
        &keys,
        site_id(0),
        Impairment::default(),
    )
    .unwrap();
    let path = |d: &Dir, f: &str| format!("{:?}", d.0.join(f).display().to_string());
    // Plain TCP to the TLS port.
    let plain = client_with(&format!("tcp/127.0.0.1:{port}"), &[]);
    assert!(plain.is_err(), "plain TCP connected to the TLS port");
    // TLS trusting the room's authority, but with no certificate of its own.
    let anonymous = client_with(
        &endpoint,
        &[(
            "transport/link/tls/root_ca_certificate",
            path(&ours, "authority.crt"),
        )],
    );
    assert!(
        anonymous.is_err(),
        "a TLS client without a certificate connected"
    );
    // A participant of another room of the same name (its own authority).
    let other = net(&[], &[endpoint.clone()], Some(load(&theirs, "site")));
    let mut other_client = other.clone();
    other_client.mode = "client";
    assert!(
        other_client.open().is_err(),
        "another room's certificate connected"
    );
    // A participant of this room connects (the same path works for the right certificate).
    let mut ok = net(&[], &[endpoint.clone()], Some(load(&ours, "observer")));
    ok.mode = "client";
    let session = ok.open().expect("this room's observer connects");
    drop(session);
    assert_eq!(source.counts.events.load(Ordering::Relaxed), 0);
}

#[test]
fn a_participant_of_the_wrong_role_forges_nothing_and_replays_nothing() {
    // The seals alone: Zenoh's access control off everywhere, so every forgery reaches them (the
    // next test has the access control on, where the router stops these before they are relayed).
    let d = room("ward", "roles");
    let (scene, core) = harness_core(Some(30.0)).unwrap();
    let hz = scene.engine.tick_hz;
    let keys = Keys::new("ward").unwrap();
    // Everyone a client of the room's router (what a classroom across networks runs): the
    // attacker's session hears what the router forwards to it, a captured event included.
    let (_router, endpoint, source, site) = classroom(&d, false);
    let id = site_id(0);
    // The attacker: this room's observer, with its own certificate and key.
    let observer = load(&d, "observer");
    let mut rogue = net(&[], &[endpoint.clone()], Some(observer.clone()));
    rogue.acl = false;
    let rogue = rogue.open().unwrap();
    let forger = Sealer::new(observer);
    // It listens to everything it can reach.
    let captured = Arc::new(std::sync::Mutex::new(Vec::<(String, Vec<u8>)>::new()));
    let cap = captured.clone();
    let _spy = rogue
        .declare_subscriber("lungdyn/ward/**")
        .callback(move |s| {
            cap.lock().unwrap().push((
                s.key_expr().to_string(),
                s.payload().to_bytes().into_owned(),
            ))
        })
        .wait()
        .unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    std::thread::scope(|s| {
        let (src, st, c) = (&source, stop.clone(), core.clone());
        let h = s.spawn(move || run_source(c, hz, src, id, transport::clock::now_ns(), &st));
        // A failed wait below stops the source too (else the scope waits for it forever).
        let _stop_on_panic = StopOnDrop(stop.clone());
        wait_for("the site's first state", || {
            site.counts.states.load(Ordering::Relaxed) >= 1
        });
        wait_for("the site's first clock answer", || {
            site.counts.probes.load(Ordering::Relaxed) >= 1
        });
        // An honest event from the site, which the spy captures.
        site.send_event(
            ipc_types::Intervention::NeedleDecompression.code(),
            ipc_types::LUNG_AFFECTED,
        )
        .unwrap();
        wait_for("the source taking the site's event", || {
            source.counts.events.load(Ordering::Relaxed) == 1
        });
        wait_for("the spy capturing a state and the event", || {
            let c = captured.lock().unwrap();
            c.iter().any(|(k, _)| k.ends_with("/state"))
                && c.iter().any(|(k, _)| k.ends_with("/event"))
        });
        let (state, event) = {
            let c = captured.lock().unwrap();
            let find = |suffix: &str| {
                c.iter()
                    .find(|(k, _)| k.ends_with(suffix))
                    .map(|(_, b)| b.clone())
                    .unwrap()
            };
            (find("/state"), find("/event"))
        };
        // Blocking on a full queue rather than dropping (Zenoh's default for a put): under load a
        // dropped junk packet (the 100 kB one, in fragments) never reached the seals to be counted.
        let put = |key: String, b: Vec<u8>| {
            rogue
                .put(key, b)
                .congestion_control(zenoh::qos::CongestionControl::Block)
                .wait()
                .unwrap()
        };
        // 1. States: the observer's own (its role may not), the source's replayed, one bit of the
        //    source's flipped, the source's with a far sequence and no valid signature.
        put(
            keys.state(),
            forger.seal(Kind::State, &state[state.len() / 2..]),
        );
        put(keys.state(), state.clone());
        let mut flipped = state.clone();
        flipped[state.len() / 2] ^= 1;
        put(keys.state(), flipped);
        // 2. Events: the observer's (its role may not), the site's captured one replayed.
        put(keys.event(), forger.seal(Kind::Event, b"needle"));
        put(keys.event(), event.clone());
        // 3. A forged clock answer to the site.
        put(keys.reply(site.id), forger.seal(Kind::Reply, b"answer"));
        // 4. Junk: unsealed, truncated, oversized, a wrong seal version.
        put(keys.state(), vec![0u8, 1, 2, 3]);
        put(keys.event(), event[..event.len() - 10].to_vec());
        put(keys.event(), vec![0x5a; 100_000]);
        let mut version = event.clone();
        version[3] = b'9';
        put(keys.event(), version);
        // 5. A flood: 2000 sealed events of the wrong role.
        for _ in 0..2000 {
            put(keys.event(), forger.seal(Kind::Event, b"flood"));
        }
        // A burst beyond the source's link queue (1024) is partly dropped there, counted as
        // overflow; every packet that reaches the worker is refused. Half of the burst at least
        // is accounted for either way (Zenoh may drop some of a burst before it arrives).
        let flood_seen = || {
            source.guard.refusals.role.load(Ordering::Relaxed)
                + source.link_counts().overflow.load(Ordering::Relaxed)
        };
        wait_for("the source refusing or dropping the flood", || {
            flood_seen() >= 1002
        });
        let states_before = site.counts.states.load(Ordering::Relaxed);
        // The real states keep coming (2 s cycles).
        wait_for("a new real state at the site", || {
            site.counts.states.load(Ordering::Relaxed) > states_before
        });
        stop.store(true, Ordering::Relaxed);
        h.join().unwrap().unwrap();
    });
    let at_site = &site.guard.refusals;
    let at_source = &source.guard.refusals;
    let n = |a: &std::sync::atomic::AtomicU64| a.load(Ordering::Relaxed);
    // Nothing forged was taken: one event (the site's own), no state but the source's.
    assert_eq!(n(&source.counts.events), 1, "{}", at_source.json());
    assert!(
        n(&at_site.role) >= 2,
        "state and clock answer by role: {}",
        at_site.json()
    );
    assert!(n(&at_site.replay) >= 1, "{}", at_site.json());
    assert!(n(&at_site.forged) >= 1, "{}", at_site.json());
    assert!(n(&at_site.unsealed) >= 1, "{}", at_site.json());
    assert!(n(&at_source.role) >= 2, "{}", at_source.json());
    assert!(n(&at_source.replay) >= 1, "{}", at_source.json());
    // Oversized and wrong-version events unsealed; the truncated one fails its signature.
    assert!(n(&at_source.unsealed) >= 2, "{}", at_source.json());
    assert!(n(&at_source.forged) >= 1, "{}", at_source.json());
    // Every refusal said with its origin.
    let last = at_source.last.lock().unwrap().clone().unwrap();
    assert!(last.contains("observer"), "{last}");
    // The site still breathes the source's states and takes the source's clock answers.
    assert!(
        site.counts.applied.load(Ordering::Relaxed) <= site.counts.states.load(Ordering::Relaxed)
    );
    assert!(site.counts.probes.load(Ordering::Relaxed) >= 1);
    assert_eq!(
        site.counts.refused.load(Ordering::Relaxed),
        at_site.total(),
        "every refusal at the site is a seal's"
    );
}

#[test]
fn the_routers_access_control_stops_a_wrong_roles_packets_and_a_flood_before_they_are_relayed() {
    // The classroom as shipped: Zenoh's access control on (the default with keys). An observer
    // sends a state, an event and a clock answer, then 10 000 events a second for 10 s, and the
    // site a state: the router drops every one on arrival and counts it by the sender's
    // certificate name; the source and the site never see them (their seals refuse nothing) and
    // keep breathing.
    let d = room("ward", "acl");
    let (scene, core) = harness_core(Some(30.0)).unwrap();
    let hz = scene.engine.tick_hz;
    let keys = Keys::new("ward").unwrap();
    let (router, endpoint, source, site) = classroom(&d, true);
    let client = |who: &str| client_net(&d, &endpoint, who, true);
    let id = site_id(0);
    let observer = load(&d, "observer");
    let rogue = client("observer").open().unwrap();
    let forger = Sealer::new(observer);
    let stop = Arc::new(AtomicBool::new(false));
    let n = |a: &std::sync::atomic::AtomicU64| a.load(Ordering::Relaxed);
    let (mut sent, mut states, mut probes) = (0u64, (0, 0), (0, 0));
    std::thread::scope(|s| {
        let (src, st, c) = (&source, stop.clone(), core.clone());
        let h = s.spawn(move || run_source(c, hz, src, id, transport::clock::now_ns(), &st));
        let _stop_on_panic = StopOnDrop(stop.clone());
        wait_for("the site's first state", || n(&site.counts.states) >= 1);
        wait_for("the site's first clock answer", || {
            n(&site.counts.probes) >= 1
        });
        let put = |key: String, b: Vec<u8>| rogue.put(key, b).wait().unwrap();
        put(keys.state(), forger.seal(Kind::State, b"state"));
        put(keys.event(), forger.seal(Kind::Event, b"needle"));
        put(keys.reply(site.id), forger.seal(Kind::Reply, b"answer"));
        sent += 3;
        // The site's certificate on a link of its own, sending a state: stopped too.
        let site_key = Sealer::new(load(&d, "site"));
        let site_rogue = client("site").open().unwrap();
        let publisher = site_rogue.declare_publisher(keys.state()).wait().unwrap();
        // A client sends a put only once it has heard of a subscriber (the source's own
        // subscriber is enough; the router drops the put on arrival all the same).
        wait_for("the second site session hearing of a subscriber", || {
            publisher.matching_status().wait().unwrap().matching()
        });
        publisher
            .put(site_key.seal(Kind::State, b"state"))
            .wait()
            .unwrap();
        states.0 = n(&site.counts.states);
        probes.0 = n(&site.counts.probes);
        // 10 000 a second for 10 s, in 1 ms steps of 10.
        let flood = forger.seal(Kind::Event, b"flood");
        let t0 = std::time::Instant::now();
        for ms in 0..10_000u32 {
            for _ in 0..10 {
                put(keys.event(), flood.clone());
            }
            sent += 10;
            let due = std::time::Duration::from_millis(u64::from(ms) + 1);
            if let Some(wait) = due.checked_sub(t0.elapsed()) {
                std::thread::sleep(wait);
            }
        }
        states.1 = n(&site.counts.states);
        probes.1 = n(&site.counts.probes);
        stop.store(true, Ordering::Relaxed);
        h.join().unwrap().unwrap();
    });
    // Counted by the router, named by the certificate; a put Zenoh drops on the rogue's own
    // congested queue never reaches the router, so most, not all, are counted there.
    let stopped = lungdyn_remote::acl::refusals(&router).unwrap();
    let by_observer = stopped.get("observer").copied().unwrap_or(0);
    eprintln!(
        "access control at the router: {} of {sent} sent ({})",
        by_observer,
        lungdyn_remote::acl::words(&stopped)
    );
    assert!(by_observer >= sent / 2, "{stopped:?} of {sent}");
    assert!(by_observer <= sent, "{stopped:?} of {sent}");
    assert_eq!(
        stopped.get("site"),
        Some(&1),
        "the site's state: {stopped:?}"
    );
    assert_eq!(
        stopped.len(),
        2,
        "only the observer and the site's state: {stopped:?}"
    );
    // Nothing reached the source or the site.
    assert_eq!(n(&source.counts.events), 0);
    assert_eq!(
        source.guard.refusals.total(),
        0,
        "{}",
        source.guard.refusals.json()
    );
    assert_eq!(
        site.guard.refusals.total(),
        0,
        "{}",
        site.guard.refusals.json()
    );
    // The site kept taking the source's states (2 s cycles: 5 in 10 s) and its clock answers
    // (a probe every 100 ms) through the flood.
    assert!(
        states.1 - states.0 >= 3,
        "states applied during the flood: {states:?}"
    );
    assert!(
        probes.1 - probes.0 >= 50,
        "clock answers during the flood: {probes:?}"
    );
}
