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
    let d = room("ward", "roles");
    let (scene, core) = harness_core(Some(30.0)).unwrap();
    let hz = scene.engine.tick_hz;
    let keys = Keys::new("ward").unwrap();
    // Everyone a client of the room's router (what a classroom across networks runs): the
    // attacker's session hears what the router forwards to it, a captured event included.
    let port = lungdyn_needs::free_local_port();
    let endpoint = format!("tls/127.0.0.1:{port}");
    let mut router_net = net(&[endpoint.clone()], &[], Some(load(&d, "router")));
    router_net.mode = "router";
    let _router = router_net.open().unwrap();
    let client = |who: &str| {
        let mut n = net(&[], &[endpoint.clone()], Some(load(&d, who)));
        n.mode = "client";
        n
    };
    let id = site_id(0);
    let source = Source::open(&client("source"), &keys, id, Impairment::default()).unwrap();
    let site = Site::open(
        &client("site"),
        &keys,
        site_id(1),
        false,
        Impairment::default(),
        100,
        ClockSync::Source,
    )
    .unwrap();
    // The attacker: this room's observer, with its own certificate and key.
    let observer = load(&d, "observer");
    let rogue = net(&[], &[endpoint.clone()], Some(observer.clone()))
        .open()
        .unwrap();
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
        let put = |key: String, b: Vec<u8>| rogue.put(key, b).wait().unwrap();
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
