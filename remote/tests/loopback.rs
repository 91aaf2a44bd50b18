//! Source and sites as separate Zenoh sessions over TCP on 127.0.0.1 (multicast scouting off,
//! explicit endpoints, 2 s lease): join, late join, loss, a bad packet at a site and at the
//! source, a site's event applied at the same cycle everywhere, a source restart, a site dropping
//! out and rejoining.

mod common;
use common::wait_for;
use std::sync::atomic::{AtomicBool, Ordering};
use std::sync::Arc;
use std::time::{Duration, Instant};

use lung_model::scene::SceneExt;
use lungdyn_remote::harness::{self, harness_core, locator, run_source, HarnessArgs};
use lungdyn_remote::link::Impairment;
use lungdyn_remote::relay::Relay;
use lungdyn_remote::site::{ClockSync, Site};
use lungdyn_remote::source::Source;
use lungdyn_remote::{site_id, Keys, Net};
use zenoh::Wait;

fn args(sites: usize, seconds: f64, loss: f64) -> HarnessArgs {
    HarnessArgs {
        sites,
        seconds,
        delay_ms: 0.0,
        jitter_ms: 0.0,
        loss,
        breaths_per_min: Some(30.0),
        observer: true,
        json: false,
        seed: 3,
        router: false,
        probe_ms: 50,
        skew_ppm: 0.0,
        relay_skew_ppm: 0.0,
        no_clock_rate: false,
        source_exe: None,
        transport: harness::Transport::Tls,
        keys_dir: None,
    }
}

/// The worst phase error `worst_ms` is within `base_ms` — or, when the source skipped deadlines,
/// within `base_ms` of a whole number of periods, at most as many as it skipped: a source woken too
/// late to catch up skips a deadline, which moves its later ticks exactly a period off the schedule
/// the sites follow until the next state (by design, `HarnessReport::source_deadlines_skipped`;
/// under two busy loops the worst was once 33.36 ms, two periods, with a mean of 0.18 ms). A
/// schedule error of our own would not land on whole periods.
fn assert_phase_within(worst_ms: f64, r: &harness::HarnessReport, base_ms: f64, what: &str) {
    // The harness's engines run the default scene's tick rate.
    let period_ms = 1e3 / lung_model::scene::Scene::default().engine.tick_hz;
    let skipped = r.source_deadlines_skipped as f64;
    let periods = (worst_ms / period_ms).round().min(skipped);
    let off = (worst_ms - periods * period_ms).abs();
    assert!(
        off < base_ms,
        "{what}: worst phase error {worst_ms} ms is {off} ms from {periods} periods (the source \
         skipped {skipped} deadlines, its lateness {:?}): {r:?}",
        r.source_lateness
    );
}

fn nets() -> Net {
    let mut n = Net::peer(&["tcp/127.0.0.1:0".to_string()], &[]);
    n.lease_ms = 2000;
    n
}

fn site_net(source: &Source) -> Net {
    let mut n = Net::peer(&[], &[locator(source.session()).unwrap()]);
    n.lease_ms = 2000;
    n
}

#[test]
fn a_site_joins_and_breathes_the_sources_ticks_bit_for_bit() {
    let r = harness::run(&args(2, 3.0, 0.0)).unwrap();
    // Through mutual TLS with the run's own keys, every packet sealed, none refused.
    assert_eq!((r.transport, r.refused_seals), ("tls", 0), "{r:?}");
    for s in &r.per_site {
        assert!(s.ticks > 120, "{s:?}");
        assert_eq!(s.ticks_differing, 0, "{s:?}");
        assert!(s.states_applied >= 1 && s.refused == 0, "{s:?}");
        // One machine, one clock: the offset estimate is within a millisecond of 0.
        assert!(s.offset_ms.abs() < 1.0, "{s:?}");
        // Every tick on the source's schedule within a millisecond, but for whole periods the
        // source skipped; the mean has no such allowance.
        assert_phase_within(s.phase_error_ms_worst, &r, 1.0, &format!("{s:?}"));
        assert!(s.phase_error_ms_mean < 1.0, "{s:?}");
        // Every stepped tick's lateness is counted, its percentiles in order.
        let l = &s.lateness;
        assert_eq!(l.ticks, s.ticks, "{s:?}");
        assert!(
            l.p50_ms <= l.p90_ms && l.p90_ms <= l.p99_ms && l.p99_ms <= l.max_ms,
            "{l:?}"
        );
    }
    assert!(r.source_lateness.ticks > 120, "{:?}", r.source_lateness);
    // One state per 2 s cycle against 60 frames a second.
    assert!(r.reduction > 100.0, "{r:?}");
}

#[test]
fn a_late_joiner_gets_the_current_state_at_once_from_the_cache() {
    // 12 breaths/min: the next state is 5 s away when the site joins at 1 s.
    let (scene, core) = harness_core(None).unwrap();
    let hz = scene.engine.tick_hz;
    let keys = Keys::new("late").unwrap();
    let id = site_id(0);
    let source = Source::open(&nets(), &keys, id, Impairment::default()).unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    std::thread::scope(|s| {
        let (src, st, c) = (&source, stop.clone(), core.clone());
        let h = s.spawn(move || run_source(c, hz, src, id, transport::clock::now_ns(), &st));
        std::thread::sleep(Duration::from_millis(1000));
        assert_eq!(source.counts.states.load(Ordering::Relaxed), 1);
        let joined = Instant::now();
        let site = Site::open(
            &site_net(&source),
            &keys,
            site_id(1),
            true,
            Impairment::default(),
            100,
            ClockSync::Source,
        )
        .unwrap();
        let mut runner = site.runner(core.clone(), hz).unwrap();
        let mut first = None;
        while joined.elapsed() < Duration::from_secs(3) && first.is_none() {
            first = runner.poll(transport::clock::now_ns()).unwrap();
            std::thread::sleep(Duration::from_millis(1));
        }
        let waited = joined.elapsed();
        stop.store(true, Ordering::Relaxed);
        h.join().unwrap().unwrap();
        let k = first.expect("the late joiner stepped a tick");
        assert!(waited < Duration::from_millis(2500), "{waited:?}");
        // Still the first cycle's state: it came from the publisher's cache.
        assert_eq!(source.counts.states.load(Ordering::Relaxed), 1);
        // The engine's first deadline is 1.25 periods after its start.
        assert!(
            k >= 55,
            "joined at tick {k}, about a second after the source started"
        );
        assert_eq!(site.counts.applied.load(Ordering::Relaxed), 1);
    });
}

#[test]
fn lost_states_are_counted_and_the_sites_stay_in_step() {
    // 14 s of 2 s cycles. A site starts comparing only once its Zenoh session is open and its first
    // state has arrived, which on a loaded 2-core machine (the other loopback tests run beside this
    // one) took up to 3.5 s: 6 s runs then compared fewer than two cycles and failed the count below.
    // With 30 % of the packets lost, the first states can be lost too (which ones depends on the
    // timing): a 10 s run once compared 150 ticks (its first state 7.5 s in, CI 2026-12-06). At
    // 14 s a site fails the count only if every state from its connection to 10 s is lost, four to
    // six in a row (0.3⁴ ≈ 1 %, 0.3⁶ ≈ 0.07 %). Plain TCP here: the comparison path stays tested.
    let mut a = args(2, 14.0, 0.3);
    a.transport = harness::Transport::Tcp;
    let r = harness::run(&a).unwrap();
    assert_eq!(r.transport, "tcp");
    let lost: u64 = r.per_site.iter().map(|s| s.lost).sum();
    assert!(lost > 0, "{r:?}");
    // Two whole 2 s cycles of the 60 Hz engine compared against the source, bit for bit.
    let two_cycles = 2 * 2 * 60;
    for s in &r.per_site {
        // Deterministic engines: a lost state of an unchanged breath costs nothing.
        assert_eq!(s.ticks_differing, 0, "{s:?}");
        assert!(s.ticks >= two_cycles, "{s:?}");
    }
}

#[test]
fn a_bad_packet_is_refused_counted_and_the_site_breathes_on() {
    let (scene, core) = harness_core(Some(30.0)).unwrap();
    let hz = scene.engine.tick_hz;
    let keys = Keys::new("bad").unwrap();
    let id = site_id(0);
    let source = Source::open(&nets(), &keys, id, Impairment::default()).unwrap();
    let site = Site::open(
        &site_net(&source),
        &keys,
        site_id(1),
        true,
        Impairment::default(),
        100,
        ClockSync::Source,
    )
    .unwrap();
    // Sites connect to the source only: the bad bytes come through the source's session.
    let rogue = source.session().clone();
    let stop = Arc::new(AtomicBool::new(false));
    std::thread::scope(|s| {
        let (src, st, c) = (&source, stop.clone(), core.clone());
        let h = s.spawn(move || run_source(c, hz, src, id, transport::clock::now_ns(), &st));
        std::thread::sleep(Duration::from_millis(700));
        // Garbage, then a real state of another format version.
        rogue.put(keys.state(), vec![0u8, 1, 2, 3]).wait().unwrap();
        let mut b = control_state::encode_to_vec(&control_state::Packet::Probe {
            from: 1,
            to: 2,
            id: 3,
            t0_ns: 4,
        })
        .unwrap();
        b[4] = 9;
        rogue.put(keys.state(), b).wait().unwrap();
        // And at the source: garbage where sites' events arrive.
        rogue.put(keys.event(), vec![7u8; 40]).wait().unwrap();
        std::thread::sleep(Duration::from_millis(2600));
        stop.store(true, Ordering::Relaxed);
        h.join().unwrap().unwrap();
    });
    assert_eq!(site.counts.refused.load(Ordering::Relaxed), 2);
    assert_eq!(source.counts.refused.load(Ordering::Relaxed), 1);
    assert_eq!(source.counts.events.load(Ordering::Relaxed), 0);
    let why = site.last_refusal.lock().unwrap().clone().unwrap();
    assert!(why.contains("format v9"), "{why}");
    // The real states kept coming: 2 s cycles over 3.3 s.
    assert!(site.counts.states.load(Ordering::Relaxed) >= 2);
}

/// A tension pneumothorax from its first breath at 30 breaths/min (2 s cycles).
fn tension_scene() -> lung_model::scene::Scene {
    lung_model::scene::Scene::parse(
        "[pv]\nbreaths_per_min = 30.0\n[lungs]\nsides = [\"right\", \"left\"]\n[disease]\n\
         kind = \"tension-pneumothorax\"\nside = \"left\"\nonset_s = 0.0\n",
        "test",
    )
    .unwrap()
}

/// A site's event travels site → source: the source engine takes it (with the site's id as its
/// origin), stamps the cycle every site applies it at and announces it with the prepared cycle a
/// breath ahead; both sites put that cycle in at the same source tick as the source, so each
/// shows the source's breath bit for bit, before and after, and the breath changes there.
#[test]
fn a_sites_event_is_applied_at_the_same_cycle_by_the_source_and_every_site() {
    use lungdyn_remote::harness::{run_site, scene_core};
    let scene = tension_scene();
    let hz = scene.engine.tick_hz;
    let keys = Keys::new("event").unwrap();
    let id = site_id(0);
    let source = Source::open(&nets(), &keys, id, Impairment::default()).unwrap();
    let sites: Vec<Site> = (1..=2)
        .map(|k| {
            Site::open(
                &site_net(&source),
                &keys,
                site_id(k),
                k == 2,
                Impairment::default(),
                100,
                ClockSync::Source,
            )
            .unwrap()
        })
        .collect();
    std::thread::sleep(Duration::from_millis(300));
    let stop = Arc::new(AtomicBool::new(false));
    let (sent, source_recs, site_recs) = std::thread::scope(|s| {
        let src = &source;
        let st = stop.clone();
        let core = scene_core(&scene).unwrap();
        let h = s.spawn(move || run_source(core, hz, src, id, transport::clock::now_ns(), &st));
        let runners: Vec<_> = sites
            .iter()
            .map(|site| {
                let mut c = scene_core(&scene).unwrap();
                c.follow_remote();
                let r = site.runner(c, hz).unwrap();
                let st = stop.clone();
                s.spawn(move || run_site(r, &st))
            })
            .collect();
        std::thread::sleep(Duration::from_millis(1500));
        // The trainee site (not the observer) decompresses the affected side.
        let sent = sites[0]
            .send_event(
                ipc_types::Intervention::NeedleDecompression.code(),
                ipc_types::LUNG_AFFECTED,
            )
            .unwrap();
        assert!(sites[1].send_event(1, 0).is_err(), "an observer sends none");
        std::thread::sleep(Duration::from_millis(6500));
        stop.store(true, Ordering::Relaxed);
        let (recs, stats) = h.join().unwrap().unwrap();
        assert_eq!(stats.events_announced, 1);
        assert_eq!(stats.events_unannounced, 0);
        let site_recs: Vec<_> = runners
            .into_iter()
            .map(|r| r.join().unwrap().unwrap())
            .collect();
        (sent, recs, site_recs)
    });
    assert_eq!(source.counts.events.load(Ordering::Relaxed), 1);
    // Every site was told, with the trainee site as its origin.
    let mut apply = None;
    for site in &sites {
        let events = site.events.lock().unwrap().clone();
        assert_eq!(events.len(), 1, "{events:?}");
        let e = events[0];
        assert_eq!((e.origin, e.sequence), (sites[0].id, sent));
        assert!(apply.is_none_or(|a| a == (e.apply_tick, e.apply_cycle)));
        apply = Some((e.apply_tick, e.apply_cycle));
        assert_eq!(site.counts.announced_late.load(Ordering::Relaxed), 0);
        assert!(site.counts.announced_in_time.load(Ordering::Relaxed) >= 3);
    }
    let (at, cycle) = apply.unwrap();
    // At least a breath after it was sent (1.5 s), and at a cycle start (120 ticks a cycle).
    assert!(at > 90 + 120 && at % 120 == 0, "applied at tick {at}");
    assert_eq!(cycle, at / 120);
    // The source's breath changes at that tick and not before: an undisturbed course (the same
    // engine replayed without the event) agrees up to it.
    let mut reference = scene_core(&scene).unwrap();
    let mut f = ipc_types::EngineFrame::default();
    let mut first_change = None;
    for r in source_recs.iter().take(at as usize + 120) {
        reference.step(r.2, None, &mut f);
        reference.prepare_ahead().unwrap();
        let v = f.lungs.iter().map(|l| l.volume_ml).sum::<f32>();
        if first_change.is_none() && v.to_bits() != r.3.to_bits() {
            first_change = Some(r.2);
        }
    }
    let changed = first_change.expect("the decompression changed the breath");
    assert!(
        changed >= at && changed < at + 120,
        "changed at {changed}, applied at {at}"
    );
    // Each site breathed the source's ticks bit for bit, across the change.
    for recs in &site_recs {
        assert!(
            recs.iter().any(|r| r.2 >= at + 60),
            "the site ran past the change"
        );
        for r in recs {
            let src = &source_recs[r.2 as usize];
            assert_eq!(src.3.to_bits(), r.3.to_bits(), "tick {}", r.2);
        }
    }
}

fn source_net(port: u16) -> Net {
    let mut n = Net::peer(&[format!("tcp/127.0.0.1:{port}")], &[]);
    n.lease_ms = 2000;
    n
}

/// Compare a site's ticks with the source runs that stepped the same tick numbers: the volume
/// bit for bit. Returns how many ticks were compared.
fn same_ticks(site: &[harness::Rec], sources: &[&[harness::Rec]]) -> usize {
    let mut n = 0;
    for r in site {
        let src = sources
            .iter()
            .find_map(|s| s.iter().find(|x| x.2 == r.2))
            .unwrap_or_else(|| panic!("no source stepped tick {}", r.2));
        assert_eq!(src.3.to_bits(), r.3.to_bits(), "tick {}", r.2);
        n += 1;
    }
    n
}

/// The source restarts (its engine stops, a new one resumes at the tick after the last it
/// published, as the launcher's supervisor restarts it, with a new Zenoh session and epoch on the
/// same endpoint): the site breathes on through the gap, takes the new source's states from its
/// publisher's cache and is in step with it again — every tick it stepped is the tick the sources
/// stepped, bit for bit, through a tension pneumothorax's course.
#[test]
fn a_source_restart_does_not_make_the_site_diverge() {
    use lungdyn_remote::harness::{run_site, scene_core};
    let scene = tension_scene();
    let scene = &scene;
    let hz = scene.engine.tick_hz;
    let keys = Keys::new("restart").unwrap();
    let port = lungdyn_needs::free_local_port();
    let first = Arc::new(
        Source::open(&source_net(port), &keys, site_id(0), Impairment::default()).unwrap(),
    );
    let site = Site::open(
        &site_net(&first),
        &keys,
        site_id(1),
        true,
        Impairment::default(),
        100,
        ClockSync::Source,
    )
    .unwrap();
    let mut c = scene_core(scene).unwrap();
    c.follow_remote();
    let runner = site.runner(c, hz).unwrap();
    let site_stop = Arc::new(AtomicBool::new(false));
    let (a, b, site_recs, applied_before) = std::thread::scope(|s| {
        let st = site_stop.clone();
        let h_site = s.spawn(move || run_site(runner, &st));
        // The first source: 3 s.
        let stop = Arc::new(AtomicBool::new(false));
        let a = {
            let (src, st) = (first.clone(), stop.clone());
            let h = s.spawn(move || {
                run_source(scene_core(scene).unwrap(), hz, &src, site_id(0), 1, &st)
            });
            std::thread::sleep(Duration::from_millis(3000));
            stop.store(true, Ordering::Relaxed);
            h.join().unwrap().unwrap().0
        };
        drop(first);
        let applied_before = site.counts.applied.load(Ordering::Relaxed);
        std::thread::sleep(Duration::from_millis(500));
        // The restarted source resumes at the tick after the last one published.
        let resume = a.last().unwrap().2 + 1;
        let second = Arc::new(
            Source::open(&source_net(port), &keys, site_id(2), Impairment::default()).unwrap(),
        );
        let stop = Arc::new(AtomicBool::new(false));
        let b = {
            let (src, st) = (second.clone(), stop.clone());
            let h = s.spawn(move || {
                let mut core = scene_core(scene).unwrap();
                core.resume_at(resume).unwrap();
                harness::run_source_at(core, hz, &src, site_id(2), 2, resume, &st)
            });
            std::thread::sleep(Duration::from_millis(4500));
            site_stop.store(true, Ordering::Relaxed);
            stop.store(true, Ordering::Relaxed);
            h.join().unwrap().unwrap().0
        };
        let site_recs = h_site.join().unwrap().unwrap();
        (a, b, site_recs, applied_before)
    });
    // The site took the second source's states (a new epoch) and stepped its ticks.
    assert!(site.counts.applied.load(Ordering::Relaxed) > applied_before + 1);
    let b_first = b.first().unwrap().2;
    let after: Vec<_> = site_recs.iter().filter(|r| r.2 >= b_first + 120).collect();
    assert!(
        after.len() > 60,
        "the site stepped {} ticks a cycle after the restart",
        after.len()
    );
    assert!(same_ticks(&site_recs, &[&b, &a]) > 300);
    // In step with the second source: each tick scheduled within a tick of when it ran there.
    for r in after {
        let src = b.iter().find(|x| x.2 == r.2).unwrap();
        let off_ms = (r.0 - src.0).abs() as f64 / 1e6;
        assert!(off_ms < 16.7, "tick {} scheduled {off_ms} ms off", r.2);
    }
}

/// A site drops out (its session closes: the source sees it leave) and rejoins with a fresh engine:
/// the current state comes from the publisher's cache and the site is in step — the source's
/// ticks, bit for bit, through a tension pneumothorax's course — within one breathing cycle.
#[test]
fn a_site_that_drops_out_and_rejoins_is_in_step_within_one_cycle() {
    use lungdyn_remote::harness::{run_site, scene_core};
    let scene = tension_scene();
    let scene = &scene;
    let hz = scene.engine.tick_hz;
    let keys = Keys::new("rejoin").unwrap();
    let id = site_id(0);
    let source = Source::open(&nets(), &keys, id, Impairment::default()).unwrap();
    let open_site = || {
        Site::open(
            &site_net(&source),
            &keys,
            site_id(1),
            true,
            Impairment::default(),
            100,
            ClockSync::Source,
        )
        .unwrap()
    };
    let site_core = || {
        let mut c = scene_core(scene).unwrap();
        c.follow_remote();
        c
    };
    let stop = Arc::new(AtomicBool::new(false));
    std::thread::scope(|s| {
        let (src, st) = (&source, stop.clone());
        let h = s.spawn(move || run_source(scene_core(scene).unwrap(), hz, src, id, 1, &st));
        // A site joined with a fresh engine, running until its stop flag is set.
        let join = || {
            let site = open_site();
            let st = Arc::new(AtomicBool::new(false));
            let r = site.runner(site_core(), hz).unwrap();
            let h = {
                let st = st.clone();
                s.spawn(move || run_site(r, &st))
            };
            (site, st, h)
        };
        // Joined for 2.5 s, then gone.
        let (first, st, h1) = join();
        std::thread::sleep(Duration::from_millis(2500));
        assert_eq!(source.sites(), 1);
        st.store(true, Ordering::Relaxed);
        let before = h1.join().unwrap().unwrap();
        drop(first);
        let left = Instant::now();
        while source.sites() != 0 && left.elapsed() < Duration::from_secs(3) {
            std::thread::sleep(Duration::from_millis(10));
        }
        assert_eq!(source.sites(), 0, "the source saw the site leave");
        std::thread::sleep(Duration::from_millis(1500));
        // Back, with a fresh engine.
        let joined = transport::clock::now_ns();
        let (_again, st, h2) = join();
        std::thread::sleep(Duration::from_millis(4000));
        st.store(true, Ordering::Relaxed);
        let after = h2.join().unwrap().unwrap();
        stop.store(true, Ordering::Relaxed);
        let (recs, _) = h.join().unwrap().unwrap();
        assert_eq!(same_ticks(&before, &[&recs]), before.len());
        assert_eq!(same_ticks(&after, &[&recs]), after.len());
        // In step within a cycle (2 s) of rejoining: from its first tick on, every tick it steps
        // is the source's, scheduled within a tick of the source's.
        let first_tick = after.first().expect("the rejoined site stepped");
        let waited_ms = (first_tick.1 - joined) as f64 / 1e6;
        assert!(waited_ms < 2000.0, "in step {waited_ms} ms after rejoining");
        for r in &after {
            let src = &recs[r.2 as usize];
            let off_ms = (r.0 - src.0).abs() as f64 / 1e6;
            assert!(off_ms < 16.7, "tick {} scheduled {off_ms} ms off", r.2);
        }
        assert!(after.len() > 120, "{} ticks after rejoining", after.len());
    });
}

/// `mode = "router"` in a scene's `[remote]` table: the source's own session is the router
/// (`lungdyn remote serve --scene` with it); a site in client mode reaches it and breathes the
/// source's ticks bit for bit, and the source sees the site's presence through it.
#[test]
fn a_scenes_router_mode_source_serves_a_client_site() {
    use lungdyn_remote::harness::run_site;
    let port = lungdyn_needs::free_local_port();
    let scene = lung_model::scene::Scene::parse(
        &format!(
            "[pv]\nbreaths_per_min = 30.0\n[remote]\nrole = \"source\"\nroom = \"routed\"\n\
             mode = \"router\"\nlisten = [\"tcp/127.0.0.1:{port}\"]\nlease_ms = 2000\n"
        ),
        "test",
    )
    .unwrap();
    let table = scene.remote.clone().unwrap();
    let net = Net::of(&table);
    assert_eq!((net.mode, net.lease_ms), ("router", 2000));
    let keys = Keys::new(&table.room).unwrap();
    let id = site_id(0);
    let source = Source::open(&net, &keys, id, Impairment::default()).unwrap();
    let site_table = lung_model::scene::Scene::parse(
        &format!(
            "[remote]\nrole = \"observer\"\nroom = \"routed\"\nmode = \"client\"\n\
             connect = [\"tcp/127.0.0.1:{port}\"]\nlease_ms = 2000\n"
        ),
        "test",
    )
    .unwrap()
    .remote
    .unwrap();
    let site_net = Net::of(&site_table);
    assert_eq!(site_net.mode, "client");
    // A client site syncs with the relay; the source that is the router is that relay.
    assert_eq!(site_table.clock(), ClockSync::Relay);
    let site = Site::open(
        &site_net,
        &keys,
        site_id(1),
        true,
        Impairment::default(),
        100,
        site_table.clock(),
    )
    .unwrap();
    let core = harness::scene_core(&scene).unwrap();
    let hz = scene.engine.tick_hz;
    let mut site_core = core.clone();
    site_core.follow_remote();
    let runner = site.runner(site_core, hz).unwrap();
    let stop = Arc::new(AtomicBool::new(false));
    let (source_recs, site_recs) = std::thread::scope(|s| {
        let st = stop.clone();
        let h_site = s.spawn(move || run_site(runner, &st));
        let (src, st) = (&source, stop.clone());
        let h = s.spawn(move || run_source(core, hz, src, id, transport::clock::now_ns(), &st));
        // Slow starts on a loaded machine: wait (up to 20 s) for the site to step a whole 2 s
        // cycle, not a fixed time.
        let began = Instant::now();
        while began.elapsed() < Duration::from_secs(20)
            && site.counts.applied.load(Ordering::Relaxed) < 3
        {
            std::thread::sleep(Duration::from_millis(50));
        }
        stop.store(true, Ordering::Relaxed);
        (
            h.join().unwrap().unwrap().0,
            h_site.join().unwrap().unwrap(),
        )
    });
    assert!(
        site.counts.applied.load(Ordering::Relaxed) >= 3,
        "{:?}",
        site.counts
    );
    assert_eq!(site.counts.refused.load(Ordering::Relaxed), 0);
    assert!(site_recs.len() >= 120, "{} ticks", site_recs.len());
    assert_eq!(same_ticks(&site_recs, &[&source_recs]), site_recs.len());
    assert!(source.counts.probes.load(Ordering::Relaxed) > 0);
    assert_eq!(site.path.answered_by.load(Ordering::Relaxed), id);
    assert!(site.path.relay_present.load(Ordering::Relaxed));
}

/// A router session (as `lungdyn remote router` opens) on 127.0.0.1 and the time relay on it.
fn router_with_relay(keys: &Keys, probe_ms: u64) -> (zenoh::Session, Relay, String) {
    let port = lungdyn_needs::free_local_port();
    let mut net = Net::peer(&[format!("tcp/127.0.0.1:{port}")], &[]);
    net.mode = "router";
    net.lease_ms = 2000;
    let router = net.open().unwrap();
    let relay = Relay::open(
        &router,
        keys,
        site_id(900),
        Impairment::default(),
        probe_ms,
        lungdyn_remote::seal::Guard::new(None),
    )
    .unwrap();
    (router, relay, format!("tcp/127.0.0.1:{port}"))
}

fn client(via: &str) -> Net {
    let mut n = Net::peer(&[], &[via.to_string()]);
    n.mode = "client";
    n.lease_ms = 2000;
    n
}

/// Through a router, 3 sites probing every 20 ms sync their clocks with the relay beside it
/// (every reply theirs comes from the relay, offset within 1 ms of the one clock's 0), and every
/// probe that reaches the source's key is the relay's (probing every 100 ms): counted by a spy on
/// the router and by the source's own answered count.
#[test]
fn through_a_router_the_sites_sync_with_the_relay_and_the_source_answers_only_it() {
    let keys = Keys::new("relayed").unwrap();
    let (router, relay, via) = router_with_relay(&keys, 100);
    let seen = Arc::new(std::sync::Mutex::new(Vec::<u64>::new()));
    let sn = seen.clone();
    let _spy = router
        .declare_subscriber(keys.probe())
        .callback(move |s| {
            if let Ok(control_state::Packet::Probe { from, .. }) =
                control_state::decode(&s.payload().to_bytes())
            {
                sn.lock().unwrap().push(from);
            }
        })
        .wait()
        .unwrap();
    let id = site_id(0);
    let source = Source::open(&client(&via), &keys, id, Impairment::default()).unwrap();
    let sites: Vec<Site> = (0..3)
        .map(|k| {
            Site::open(
                &client(&via),
                &keys,
                site_id(k + 1),
                true,
                Impairment::default(),
                20,
                ClockSync::Relay,
            )
            .unwrap()
        })
        .collect();
    wait_for("every site's 25 relay answers", || {
        sites
            .iter()
            .all(|s| s.counts.probes.load(Ordering::Relaxed) >= 25)
    });
    for s in &sites {
        let p = &s.path;
        assert_eq!(p.answered_by.load(Ordering::Relaxed), relay.id);
        assert!(p.relay_present.load(Ordering::Relaxed));
        assert!(p.have_offset.load(Ordering::Relaxed));
        let o = p.offset_ns.load(Ordering::Relaxed);
        assert!(o.abs() < 1_000_000, "site offset {o} ns on one clock");
    }
    let o = relay.offset_ns().expect("the relay's offset to the source");
    assert!(o.abs() < 1_000_000, "relay offset {o} ns on one clock");
    let site_probes: u64 = sites
        .iter()
        .map(|s| s.counts.probes.load(Ordering::Relaxed))
        .sum();
    let c = &relay.counts;
    assert!(c.answered.load(Ordering::Relaxed) >= site_probes);
    let seen = seen.lock().unwrap().clone();
    assert!(!seen.is_empty());
    assert!(
        seen.iter().all(|f| *f == relay.id),
        "probes on the source's key from {:x?} (relay {:x})",
        seen.iter()
            .filter(|f| **f != relay.id)
            .collect::<std::collections::BTreeSet<_>>(),
        relay.id
    );
    // The source answered the relay's probes alone: no more than the relay sent (one may be in
    // flight), far fewer than the sites' 75+.
    let answered = source.counts.probes.load(Ordering::Relaxed);
    let sent = c.probes_to_source.load(Ordering::Relaxed);
    assert!(
        answered >= 1 && answered <= sent + 1,
        "{answered} of {sent}"
    );
    assert!(answered < site_probes, "{answered} vs {site_probes}");
}

/// The relay goes away (its session's token and subscribers undeclared; the router stays): the
/// site says so (`relay_present` false, `relay_lost` 1), keeps its last offset and gets no
/// answers; a new relay on the router is taken at once and answers again.
#[test]
fn when_the_relay_goes_the_site_says_so_keeps_its_offset_and_takes_a_new_one() {
    let keys = Keys::new("relay-gone").unwrap();
    let (router, relay, via) = router_with_relay(&keys, 50);
    let _source = Source::open(&client(&via), &keys, site_id(0), Impairment::default()).unwrap();
    let site = Site::open(
        &client(&via),
        &keys,
        site_id(1),
        true,
        Impairment::default(),
        20,
        ClockSync::Relay,
    )
    .unwrap();
    let p = site.path.clone();
    wait_for("10 relay answers", || {
        site.counts.probes.load(Ordering::Relaxed) >= 10
    });
    assert!(p.relay_present.load(Ordering::Relaxed));
    drop(relay);
    wait_for("the site to see the relay gone", || {
        !p.relay_present.load(Ordering::Relaxed)
    });
    assert_eq!(p.relay_lost.load(Ordering::Relaxed), 1);
    // In-flight replies settle; then nothing more comes and the offset stays.
    std::thread::sleep(Duration::from_millis(300));
    let (n, o) = (
        site.counts.probes.load(Ordering::Relaxed),
        p.offset_ns.load(Ordering::Relaxed),
    );
    std::thread::sleep(Duration::from_millis(500));
    assert_eq!(site.counts.probes.load(Ordering::Relaxed), n);
    assert_eq!(p.offset_ns.load(Ordering::Relaxed), o);
    assert!(p.have_offset.load(Ordering::Relaxed));
    let again = Relay::open(
        &router,
        &keys,
        site_id(901),
        Impairment::default(),
        50,
        lungdyn_remote::seal::Guard::new(None),
    )
    .unwrap();
    wait_for("the new relay's answers", || {
        site.counts.probes.load(Ordering::Relaxed) >= n + 5
    });
    assert!(p.relay_present.load(Ordering::Relaxed));
    assert_eq!(p.answered_by.load(Ordering::Relaxed), again.id);
    assert_eq!(p.relay_lost.load(Ordering::Relaxed), 1);
}

/// The harness through its router: the sites sync with the relay (its figures reported), the
/// source answers only the relay's probes, and every site breathes the source's ticks bit for bit.
#[test]
fn the_harness_through_a_router_syncs_the_sites_with_the_relay() {
    let mut a = args(2, 3.0, 0.0);
    a.router = true;
    let r = harness::run(&a).unwrap();
    let relay = r.relay.as_ref().expect("the relay's figures");
    assert!(r.clock_sync.starts_with("relay"), "{}", r.clock_sync);
    for s in &r.per_site {
        assert!(s.ticks > 120, "{s:?}");
        assert_eq!(s.ticks_differing, 0, "{s:?}");
        assert!(s.offset_ms.abs() < 1.0, "{s:?}");
    }
    assert!(relay.offset_ms.is_some_and(|o| o.abs() < 1.0), "{relay:?}");
    // Two sites at 50 ms (2400/min) against the relay's one probe stream (1200/min) to the
    // source; the source's answers are the relay's, not the sites'.
    assert!(
        relay.probes_answered_per_minute > 1.5 * r.probes_per_minute,
        "{r:?}"
    );
    assert!(
        r.probes_per_minute <= 1.2 * relay.probes_to_source_per_minute + 60.0,
        "{r:?}"
    );
}

/// A clock `skew_ppm` fast against the source's was followed: its fitted rate applied and within
/// 20 ppm of the truth, dθ/dt = −r / (1 + r) (the source's clock falls behind it), and its offset
/// at the end within 0.1 ms of the true one.
fn assert_followed(what: &str, c: &harness::ClockFigures, skew_ppm: f64) {
    assert_eq!(c.rate, "applied", "{what}: {c:?}");
    let r = skew_ppm * 1e-6;
    let rate = c.rate_ppm.expect("a fitted rate");
    assert!((rate + r / (1.0 + r) * 1e6).abs() < 20.0, "{what}: {c:?}");
    let e = c.offset_error_ms.expect("an offset");
    assert!(e.abs() < 0.1, "{what}: offset error {e} ms: {c:?}");
}

/// Each site's clock runs 200 ppm fast against the source's (the harness's `--skew-ppm` seam:
/// here every session shares CLOCK_MONOTONIC). A 10 s mean offset would trail the true one by
/// ≈ 1 ms (200 ppm × 5 s); the sites fit the rate within seconds on loopback and their offset
/// at the end errs by under 0.1 ms, and so does their tick schedule (phase error, the last 5 s).
#[test]
fn sites_whose_clocks_run_200_ppm_fast_fit_the_rate_and_keep_the_offset() {
    let mut a = args(2, 20.0, 0.0);
    a.skew_ppm = 200.0;
    let r = harness::run(&a).unwrap();
    for s in &r.per_site {
        assert_followed("site", &s.clock, 200.0);
        assert_eq!(s.ticks_differing, 0, "{s:?}");
    }
    assert_phase_within(r.phase_error_ms_worst_last_5_s, &r, 0.2, "the last 5 s");
}

/// Through the router, the relay 100 ppm and the sites 200 ppm fast against the source: the
/// relay fits its rate to the source (−100 ppm) and answers with its offset of the moment; each
/// site fits its rate to the relay's answers (−200 ppm, its rate to the source: the runs test drops
/// the answers from before the relay's rate was applied) and keeps its offset within 0.1 ms where
/// two 10 s means would trail by ≈ 1.5 ms (0.5 ms on the relay's leg, 1 ms on the site's).
#[test]
fn through_the_relay_both_legs_rates_are_fitted() {
    let mut a = args(2, 30.0, 0.0);
    a.router = true;
    a.skew_ppm = 200.0;
    a.relay_skew_ppm = 100.0;
    let r = harness::run(&a).unwrap();
    let relay = r.relay.as_ref().expect("the relay's figures");
    assert_followed("relay", &relay.clock, 100.0);
    for s in &r.per_site {
        assert_followed("site", &s.clock, 200.0);
    }
    assert_phase_within(r.phase_error_ms_worst_last_5_s, &r, 0.2, "the last 5 s");
}
