use super::*;
use proptest::prelude::*;

fn phase(chi: Vec<f64>, q: f64) -> PhaseState {
    PhaseState {
        chi: Bounded::new(chi).unwrap(),
        q,
        c: 1.0,
        t_ext: 0.0,
        t_steps: 100.0,
        beta0: 30.0,
        beta1: -30.0,
    }
}

fn pv() -> PvState {
    PvState {
        inhale: phase(vec![0.1, 0.2, 0.3], 2.0),
        exhale: phase(vec![0.3, 0.2, 0.1, 0.0, -0.1], 1.5),
        frc_ml: 2400.0,
        tv_ml: 500.0,
        rp_cmh2o: 0.0,
        tp_cmh2o: 10.0,
        breaths_per_min: 12.0,
        ie_inhale: 1.0,
        ie_exhale: 1.0,
    }
}

fn lung(side: u8) -> LungState {
    LungState {
        side,
        pv: pv(),
        next: None,
        share: 0.52,
        held_ml: None,
        base_ml: None,
        collapse: 0.0,
        offset_mm: [0.0; 3],
        cycle: 7,
        cycle_start_tick: 1050,
    }
}

fn state() -> ControlState {
    ControlState {
        source: 1,
        epoch: 99,
        sequence: 3,
        tick: 1050,
        tick_hz: 60.0,
        source_time_ns: 17_500_000_000,
        cycle: 7,
        gravity_body: [0.0, -1.0, 0.0],
        disease: Disease::None,
        lungs: Bounded::new(vec![lung(0), lung(1)]).unwrap(),
        events: Bounded::default(),
        pending: None,
        live: None,
    }
}

fn live(last_ml: Vec<f32>) -> LiveBreath {
    LiveBreath {
        start_tick: 1040,
        breath: 3,
        peak: None,
        last_ticks: 240,
        last_peak: 100,
        last_ml: Bounded::new(last_ml).unwrap(),
        clipped: false,
    }
}

fn pending(apply_tick: u64, lungs: Vec<PendingLung>) -> PendingCycle {
    PendingCycle {
        apply_tick,
        apply_cycle: 8,
        course_cycle: 2,
        lungs: Bounded::new(lungs).unwrap(),
    }
}

fn pending_lung(side: u8, pv: Option<PvState>) -> PendingLung {
    PendingLung {
        side,
        pv,
        collapse: 0.25,
        offset_mm: [1.0, -2.0, 3.0],
        base_ml: 1100.0,
        held_ml: None,
    }
}

fn roundtrip(p: &Packet) -> Packet {
    let mut buf = [0u8; FRAME_BYTES];
    let n = encode(p, &mut buf).unwrap();
    decode(&buf[..n]).unwrap()
}

#[test]
fn a_full_state_fits_a_frame_and_reads_back_equal() {
    let mut s = state();
    // The largest state: 15 constants per phase, a pending change on both lungs, every event.
    for l in s.lungs.0.iter_mut() {
        l.pv.inhale = phase(vec![0.5; MAX_CHI], 2.0);
        l.pv.exhale = phase(vec![0.5; MAX_CHI], 2.0);
        l.next = Some(l.pv.clone());
        l.held_ml = Some(1000.0);
        l.base_ml = Some(900.0);
    }
    for k in 0..MAX_EVENTS as u64 {
        assert!(s.events.push(RemoteEvent {
            origin: u64::MAX - k,
            sequence: u64::MAX,
            kind: 1,
            lung: u32::MAX,
            apply_cycle: u64::MAX,
            apply_tick: u64::MAX,
            course_cycle: u64::MAX,
            outcome: u32::MAX,
        }));
    }
    assert!(!s.events.push(s.events[0]), "full");
    // And a pending disease cycle changing both lungs.
    s.pending = Some(PendingCycle {
        apply_tick: u64::MAX,
        apply_cycle: u64::MAX,
        course_cycle: u64::MAX,
        lungs: Bounded::new(vec![
            pending_lung(0, Some(s.lungs[0].pv.clone())),
            pending_lung(1, Some(s.lungs[1].pv.clone())),
        ])
        .unwrap(),
    });
    // And the patient's breath, every sample used.
    s.live = Some(LiveBreath {
        start_tick: u64::MAX - 1,
        breath: u64::MAX,
        peak: Some((u64::MAX, -MAX_LIVE_ML)),
        last_ticks: MAX_LIVE_TICKS,
        last_peak: MAX_LIVE_TICKS - 1,
        last_ml: Bounded::new(vec![-MAX_LIVE_ML; LIVE_SAMPLES]).unwrap(),
        clipped: true,
    });
    let p = Packet::State(s);
    let mut frame = ControlStateFrame::default();
    frame.set(&p).unwrap();
    assert!(frame.len as usize <= FRAME_BYTES);
    assert_eq!(decode(frame.encoded()).unwrap(), p);
}

#[test]
fn a_healthy_state_is_small() {
    let n = encode_to_vec(&Packet::State(state())).unwrap().len();
    assert!(n < 600, "{n} bytes");
}

#[test]
fn an_unknown_version_is_refused_by_name() {
    let mut b = encode_to_vec(&Packet::State(state())).unwrap();
    b[4] = 1;
    let e = decode(&b).unwrap_err();
    assert_eq!(
        e,
        DecodeError::UnknownVersion {
            theirs: 1,
            ours: FORMAT_VERSION
        }
    );
    assert!(e.to_string().contains("v1 is not understood"), "{e}");
}

#[test]
fn a_flipped_bit_fails_the_checksum() {
    let mut b = encode_to_vec(&Packet::State(state())).unwrap();
    let last = b.len() - 1;
    b[last] ^= 0x10;
    assert!(matches!(decode(&b), Err(DecodeError::Checksum { .. })));
}

#[test]
fn bad_magic_lengths_and_trailing_bytes_are_refused() {
    let b = encode_to_vec(&Packet::State(state())).unwrap();
    assert_eq!(decode(&b[..5]), Err(DecodeError::TooShort { got: 5 }));
    let mut m = b.clone();
    m[0] = b'X';
    assert!(matches!(decode(&m), Err(DecodeError::BadMagic { .. })));
    assert!(matches!(
        decode(&b[..b.len() - 1]),
        Err(DecodeError::LengthMismatch { .. })
    ));
    let mut long = b.clone();
    long[8..12].copy_from_slice(&(1u32 << 31).to_le_bytes());
    assert!(matches!(decode(&long), Err(DecodeError::TooLong { .. })));
    // A valid header over a payload with a byte after the packet.
    let mut t = b[HEADER_BYTES..].to_vec();
    t.push(0);
    assert!(matches!(
        decode(&framed(&t)),
        Err(DecodeError::Malformed(_))
    ));
}

/// Bytes with a correct header (length and checksum) around `payload`.
fn framed(payload: &[u8]) -> Vec<u8> {
    let mut b = Vec::new();
    b.extend_from_slice(&MAGIC);
    b.extend_from_slice(&FORMAT_VERSION.to_le_bytes());
    b.extend_from_slice(&0u16.to_le_bytes());
    b.extend_from_slice(&(payload.len() as u32).to_le_bytes());
    b.extend_from_slice(&xxhash_rust::xxh3::xxh3_64(payload).to_le_bytes());
    b.extend_from_slice(payload);
    b
}

#[test]
fn a_sequence_longer_than_its_bound_is_refused_before_it_is_allocated() {
    // State's payload up to the lungs' length, then a length of 2^32-1 lungs (varint).
    let s = state();
    let full = postcard::to_allocvec(&Packet::State(s)).unwrap();
    // Find the lungs' count (2) after the fixed fields by re-encoding a state with 0 lungs.
    let mut empty = state();
    empty.lungs = Bounded::default();
    empty.events = Bounded::default();
    let e = postcard::to_allocvec(&Packet::State(empty)).unwrap();
    // The encodings agree up to the lungs' count byte (then the events' count, no pending cycle and
    // no live breath).
    let at = e.len() - 4;
    assert_eq!(full[..at], e[..at]);
    assert_eq!(full[at], 2);
    let mut evil = e[..at].to_vec();
    evil.extend_from_slice(&[0xff, 0xff, 0xff, 0xff, 0x0f]);
    let err = decode(&framed(&evil)).unwrap_err();
    assert!(
        matches!(&err, DecodeError::Malformed(m) if !m.is_empty()),
        "{err:?}"
    );
    // Three lungs are refused too (the bound, not only an absurd count).
    let mut three = state();
    three.lungs.0.push(lung(0));
    let b = postcard::to_allocvec(&Packet::State(three)).unwrap();
    assert!(matches!(
        decode(&framed(&b)),
        Err(DecodeError::Malformed(_))
    ));
}

#[test]
fn values_out_of_their_domain_are_refused_both_ways() {
    let cases: Vec<(fn(&mut ControlState), &str)> = vec![
        (|s| s.lungs.0[0].pv.inhale.chi.0[1] = f64::NAN, "chi"),
        (|s| s.lungs.0[1].pv.tv_ml = f64::INFINITY, "boundary"),
        (|s| s.lungs.0[1].pv.frc_ml = 0.0, "positive"),
        (|s| s.lungs.0[0].side = 2, "side"),
        (|s| s.lungs.0[1].side = 0, "same lung"),
        (|s| s.tick_hz = 0.0, "tick rate"),
        (|s| s.lungs.0[0].collapse = 1.5, "collapse"),
        (|s| s.lungs.0[0].held_ml = Some(f64::NAN), "held"),
        (|s| s.gravity_body[2] = f64::NAN, "gravity"),
        (|s| s.disease = Disease::Tumour { side: 9 }, "side"),
        (
            |s| s.pending = Some(pending(s.tick - 1, vec![])),
            "before the state's tick",
        ),
        (
            |s| s.pending = Some(pending(s.tick, vec![pending_lung(0, None); 2])),
            "same lung twice in the pending",
        ),
        (
            |s| {
                let mut l = pending_lung(1, None);
                l.held_ml = Some(f64::INFINITY);
                s.pending = Some(pending(s.tick, vec![l]));
            },
            "pending lung's collapse, base or held",
        ),
        (
            |s| {
                let mut l = pending_lung(1, None);
                l.collapse = -0.1;
                s.pending = Some(pending(s.tick, vec![l]));
            },
            "pending lung's collapse is outside",
        ),
        (
            |s| {
                let mut pv = pv();
                pv.tv_ml = -1.0;
                s.pending = Some(pending(s.tick, vec![pending_lung(0, Some(pv))]));
            },
            "positive",
        ),
        (
            |s| s.live = Some(live(vec![0.0, f32::NAN])),
            "live breath's volume",
        ),
        (
            |s| s.live = Some(live(vec![0.0, 9000.0])),
            "live breath's volume",
        ),
        (|s| s.live = Some(live(vec![0.0])), "fewer than 2 samples"),
        (
            |s| {
                let mut l = live(vec![0.0, 1.0]);
                l.last_peak = l.last_ticks;
                s.live = Some(l);
            },
            "peak is not within",
        ),
        (
            |s| {
                let mut l = live(vec![0.0, 1.0]);
                l.peak = Some((l.start_tick - 1, 1.0));
                s.live = Some(l);
            },
            "peak is before its start",
        ),
        (
            |s| {
                let mut l = live(vec![0.0, 1.0]);
                l.peak = Some((l.start_tick, f32::INFINITY));
                s.live = Some(l);
            },
            "live breath's volume",
        ),
        (
            |s| {
                let mut l = live(vec![0.0, 1.0]);
                l.last_ticks = 1;
                s.live = Some(l);
            },
            "under 2 ticks",
        ),
        (
            |s| {
                let mut l = live(vec![0.0, 1.0]);
                l.last_ticks = MAX_LIVE_TICKS + 1;
                s.live = Some(l);
            },
            "over a minute",
        ),
    ];
    for (spoil, word) in cases {
        let mut s = state();
        spoil(&mut s);
        let p = Packet::State(s);
        let e = encode_to_vec(&p).unwrap_err();
        assert!(e.to_string().contains(word), "{e}");
        let b = postcard::to_allocvec(&p).unwrap();
        let d = decode(&framed(&b)).unwrap_err();
        assert!(
            matches!(d, DecodeError::Invalid(w) if w.contains(word)),
            "{d:?}"
        );
    }
}

#[test]
fn a_frame_with_an_impossible_length_reads_as_a_refused_packet() {
    let mut f = ControlStateFrame::default();
    f.set(&Packet::State(state())).unwrap();
    f.len = u32::MAX;
    assert_eq!(f.encoded().len(), FRAME_BYTES);
    assert!(decode(f.encoded()).is_err());
}

fn arb_phase() -> impl Strategy<Value = PhaseState> {
    (
        prop::collection::vec(-1e3f64..1e3, 0..=MAX_CHI),
        -10f64..10.0,
        -10f64..10.0,
    )
        .prop_map(|(chi, q, c)| PhaseState {
            chi: Bounded::new(chi).unwrap(),
            q,
            c,
            t_ext: q * 3.0,
            t_steps: 100.0,
            beta0: c,
            beta1: -c,
        })
}

fn arb_pv() -> impl Strategy<Value = PvState> {
    (arb_phase(), arb_phase(), 1f64..1e4, 1f64..1e4, 1f64..60.0).prop_map(
        |(inhale, exhale, frc_ml, tv_ml, bpm)| PvState {
            inhale,
            exhale,
            frc_ml,
            tv_ml,
            rp_cmh2o: 0.0,
            tp_cmh2o: 10.0,
            breaths_per_min: bpm,
            ie_inhale: 1.0,
            ie_exhale: 2.0,
        },
    )
}

fn arb_state() -> impl Strategy<Value = ControlState> {
    (
        any::<[u64; 4]>(),
        prop::collection::vec(
            (
                arb_pv(),
                prop::option::of(arb_pv()),
                0f64..1.0,
                any::<u32>(),
            ),
            0..=2,
        ),
        prop::collection::vec(any::<(u64, u64, u32, u32, u64, u64)>(), 0..=MAX_EVENTS),
        1f64..1000.0,
        prop::option::of(-1e4f64..1e4),
        prop::option::of((
            any::<[u64; 3]>(),
            prop::collection::vec((prop::option::of(arb_pv()), 0f64..=1.0), 0..=2),
        )),
        prop::option::of((
            any::<(u64, u64, u32)>(),
            2..=MAX_LIVE_TICKS,
            prop::option::of(-MAX_LIVE_ML..=MAX_LIVE_ML),
            prop::collection::vec(-MAX_LIVE_ML..=MAX_LIVE_ML, 2..=LIVE_SAMPLES),
        )),
    )
        .prop_map(
            |(ids, lungs, events, hz, held, pending, live)| ControlState {
                source: ids[0],
                epoch: ids[1],
                sequence: ids[2],
                tick: ids[3],
                tick_hz: hz,
                source_time_ns: ids[3] ^ ids[0],
                cycle: ids[2] >> 3,
                gravity_body: [0.0, -1.0, hz],
                disease: Disease::TensionPneumothorax {
                    side: 1,
                    cycles_run: ids[1],
                },
                lungs: Bounded::new(
                    lungs
                        .into_iter()
                        .enumerate()
                        .map(|(k, (pv, next, c, cycle))| LungState {
                            side: k as u8,
                            pv,
                            next,
                            share: c,
                            held_ml: held,
                            base_ml: held.map(|h| -h),
                            collapse: c,
                            offset_mm: [c, -c, 1e6],
                            cycle,
                            cycle_start_tick: ids[3] / 2,
                        })
                        .collect(),
                )
                .unwrap(),
                events: Bounded::new(
                    events
                        .into_iter()
                        .map(|(origin, sequence, kind, lung, apply_cycle, apply_tick)| {
                            RemoteEvent {
                                origin,
                                sequence,
                                kind,
                                lung,
                                apply_cycle,
                                apply_tick,
                                course_cycle: apply_cycle / 3,
                                outcome: kind ^ lung,
                            }
                        })
                        .collect(),
                )
                .unwrap(),
                pending: pending.map(|(n, lungs)| PendingCycle {
                    apply_tick: ids[3].saturating_add(n[0] >> 1),
                    apply_cycle: n[1],
                    course_cycle: n[2],
                    lungs: Bounded::new(
                        lungs
                            .into_iter()
                            .enumerate()
                            .map(|(k, (pv, c))| PendingLung {
                                side: k as u8,
                                pv,
                                collapse: c,
                                offset_mm: [c, 2.0 * c, -c],
                                base_ml: 1000.0 * c,
                                held_ml: held,
                            })
                            .collect(),
                    )
                    .unwrap(),
                }),
                live: live.map(
                    |((start_tick, breath, k), last_ticks, peak_ml, ml)| LiveBreath {
                        start_tick,
                        breath,
                        peak: peak_ml.map(|v| (start_tick.saturating_add(k as u64), v)),
                        last_ticks,
                        last_peak: k % last_ticks,
                        last_ml: Bounded::new(ml).unwrap(),
                        clipped: k % 2 == 1,
                    },
                ),
            },
        )
}

#[test]
fn a_live_breath_plays_the_previous_breath_then_expires_from_the_announced_peak() {
    // 5 samples over 9 ticks (one every 2 ticks), the peak 4 ticks in; the breath from tick 1040.
    let mut l = LiveBreath {
        last_ticks: 9,
        last_peak: 4,
        ..live(vec![0.0, 100.0, 300.0, 200.0, 50.0])
    };
    assert_eq!(l.volume_at(1040), (0.0, true));
    assert_eq!(l.volume_at(1041), (50.0, true));
    assert_eq!(l.volume_at(1043), (200.0, true));
    // Before the patient's expiration is announced: the previous breath's own, held at its end
    // until the next breath starts, however long.
    assert_eq!(l.volume_at(1045), (250.0, false));
    assert_eq!(l.volume_at(1048), (50.0, false));
    assert_eq!(l.volume_at(u64::MAX), (50.0, false));
    // Before the start (a tick the site stepped before the state's): the start's volume.
    assert_eq!(l.volume_at(0), (0.0, true));
    // The peak announced at tick 1100 at 550 ml: the expiration from there, scaled so it starts
    // at 550 and ends at the previous breath's 50, held there.
    l.peak = Some((1100, 550.0));
    assert_eq!(l.volume_at(1100), (550.0, false));
    assert_eq!(l.volume_at(1102), (50.0 + 150.0 * 500.0 / 250.0, false));
    assert_eq!(l.volume_at(1104), (50.0, false));
    assert_eq!(l.volume_at(u64::MAX), (50.0, false));
}

#[test]
fn on_the_patients_rhythm_the_next_breath_starts_when_this_one_has_played_out() {
    // The same breath as above: 5 samples over 9 ticks, from tick 1040; its end at 1048.
    let mut l = LiveBreath {
        last_ticks: 9,
        last_peak: 4,
        ..live(vec![10.0, 100.0, 300.0, 200.0, 50.0])
    };
    let on = |l: &LiveBreath, t: u64| l.volume_on_rhythm(t, u64::MAX);
    // Within the breath: as `volume_at`.
    for t in [0, 1040, 1041, 1045, 1048] {
        assert_eq!(on(&l, t), l.volume_at(t), "tick {t}");
    }
    // Then the previous breath again from this one's end (50 ml), its own net change (+40 ml over
    // the breath) taken out so that it ends at 50 ml too: 50 at 1049, 50 + 45 - 5 = 90 at 1050,
    // its peak 290 + 50 - 20 = 320 at 1053, and 50 from 1057 on (the prediction's end, where the
    // source holds).
    assert_eq!(on(&l, 1049), (50.0, true));
    assert_eq!(on(&l, 1050), (90.0, true));
    assert_eq!(on(&l, 1053), (320.0, false));
    assert_eq!(on(&l, 1057), (50.0, false));
    assert_eq!(on(&l, u64::MAX), (50.0, false));
    // Not heard within 2 ticks of its predicted start: the patient has not started it, and the
    // prediction fades back to 50 ml over RHYTHM_FADE_TICKS (12) — at 1052, a twelfth of the way
    // (the breath at 225 ml there) — and holds there: an apnoea is held at the breath's end.
    assert_eq!(l.volume_on_rhythm(1051, 2), on(&l, 1051));
    let (v, rising) = l.volume_on_rhythm(1052, 2);
    assert!(
        (v - (50.0 + 175.0 * (1.0 - 1.0 / 12.0))).abs() < 1e-9 && !rising,
        "{v}"
    );
    for t in [1063, 1070, u64::MAX] {
        assert_eq!(l.volume_on_rhythm(t, 2), (50.0, false), "tick {t}");
    }
    // With the peak announced at 1100 (550 ml), this breath's expiration ends 4 ticks later, at
    // 1104, and the next starts at 1105.
    l.peak = Some((1100, 550.0));
    for t in [1100, 1102, 1104] {
        assert_eq!(on(&l, t), l.volume_at(t), "tick {t}");
    }
    assert_eq!(on(&l, 1105), (50.0, true));
    assert_eq!(on(&l, 1109), (320.0, false));
    // A peak at the end of time: no overflow, the breath's expiration held.
    l.peak = Some((u64::MAX - 1, 550.0));
    assert_eq!(on(&l, u64::MAX), l.volume_at(u64::MAX));
}

proptest! {
    #[test]
    fn every_state_round_trips(s in arb_state()) {
        let p = Packet::State(s);
        prop_assert_eq!(roundtrip(&p), p);
    }

    #[test]
    fn probes_and_events_round_trip(a in any::<[u64; 6]>(), k in any::<u32>()) {
        for p in [
            Packet::Probe { from: a[0], to: a[1], id: a[2], t0_ns: a[3] },
            Packet::ProbeReply { from: a[0], to: a[1], id: a[2], t0_ns: a[3], t1_ns: a[4], t2_ns: a[5] },
            Packet::Event(RemoteEvent { origin: a[0], sequence: a[1], kind: k, lung: k ^ 1, apply_cycle: a[5], apply_tick: a[4], course_cycle: a[3], outcome: k }),
        ] {
            prop_assert_eq!(roundtrip(&p), p);
        }
    }

    /// Fuzz-style: random bytes, random bytes behind a valid header, and every truncation and
    /// single-byte change of a valid packet never panic (and the changes never decode to a
    /// different packet).
    #[test]
    fn random_and_damaged_bytes_never_panic(
        junk in prop::collection::vec(any::<u8>(), 0..600),
        s in arb_state(),
        at in any::<prop::sample::Index>(),
        x in 1u8..=255,
    ) {
        let _ = decode(&junk);
        let _ = decode(&framed(&junk));
        let p = Packet::State(s);
        let b = encode_to_vec(&p).unwrap();
        for n in 0..b.len() {
            prop_assert!(decode(&b[..n]).is_err());
        }
        let mut d = b.clone();
        let i = at.index(d.len());
        d[i] ^= x;
        if let Ok(q) = decode(&d) {
            // Only a change in the header's unused flags can pass.
            prop_assert!((6..8).contains(&i));
            prop_assert_eq!(q, p);
        }
    }
}
