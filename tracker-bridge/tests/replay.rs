//! The shared loop on a fake clock: the synthetic source gives the frames the bridge gave before
//! sources existed, a recorded session (with bad, missing, late and unknown samples) replays into
//! the same frames bit for bit, paced or as fast as possible (with the respiratory signal it was
//! recorded with), and a silent sender shows as stale.

use ipc_types::{tool_status, TrackerFrame, TOOL_HMD, TOOL_PATIENT};
use tracker_bridge::assemble::{Assembler, BridgeConfig};
use tracker_bridge::record::RecordWriter;
use tracker_bridge::run::Ended;
use tracker_bridge::sample::{Event, EventKind, Input, Reject, Rotation, Sample, ToolName};
use tracker_bridge::source::replay::Replay;
use tracker_bridge::source::synthetic::SyntheticSource;
use tracker_bridge::source::{Poll, Source, SourceError};
use tracker_bridge::synthetic::Synthetic;
use tracker_bridge::testing::{run_assembled, run_source};
use tracker_bridge::validate::{Validation, Volume};
use transport::FakeClock;

const MS: u64 = 1_000_000;

/// Inputs delivered at scripted times (what a network source's queue would hold at each tick).
struct ScriptedSource {
    clock: FakeClock,
    script: std::collections::VecDeque<(u64, Input)>,
}

impl Source for ScriptedSource {
    fn describe(&self) -> String {
        "scripted".into()
    }
    fn poll(&mut self, now_ns: u64, sink: &mut dyn FnMut(&Input)) -> Result<Poll, SourceError> {
        while self.script.front().is_some_and(|(t, _)| *t <= now_ns) {
            let (_, i) = self.script.pop_front().unwrap();
            sink(&i);
        }
        let _ = &self.clock;
        Ok(Poll::Tick { at_ns: now_ns })
    }
}

fn config() -> BridgeConfig {
    BridgeConfig {
        validation: Validation {
            volume: Volume::Cone {
                height_mm: 1500.0,
                radius_mm: 500.0,
            },
            ..Validation::default()
        },
        ..BridgeConfig::default()
    }
}

fn sample(name: &str, t: u64, frame: u64, x: f32) -> Input {
    Input::Sample(Sample {
        device_frame: Some(frame),
        rms_error_mm: Some(0.2),
        ..Sample::quat(
            t,
            ToolName::new(name).unwrap(),
            [0.0, 0.0, 0.6, 0.8],
            [x, 5.0, -1000.0],
        )
    })
}

/// A 3-second session at a 60 Hz sender with everything that can go wrong in it.
fn script(start: u64) -> Vec<(u64, Input)> {
    let mut s = Vec::new();
    let mut hmd_frame = 0;
    for k in 0..180u64 {
        let t = start + k * 16_666_667 + 3 * MS;
        let x = (k as f32 * 0.1).sin() * 50.0;
        match k {
            20 => s.push((t, sample("Patient", t, k, f32::NAN))),
            30..=45 => {} // the patient tool is silent for a quarter second: stale
            50 => {
                let mut i = sample("Patient", t, k, x);
                if let Input::Sample(ref mut smp) = i {
                    smp.rotation = Rotation::Quat([0.0, 0.0, 0.0, 1.2]);
                }
                s.push((t, i));
            }
            60 => s.push((t, sample("Patient", t, k, 900.0))), // out of the cone
            70 => s.push((t, sample("Patient", t, k - 1, x))), // repeat
            80 => s.push((t, sample("Patient", t, k + 5, x))), // gap
            _ => s.push((t, sample("Patient", t, k + if k > 80 { 5 } else { 0 }, x))),
        }
        // The HMD sender runs at 40 Hz: two samples every three ticks.
        if k % 3 != 0 {
            hmd_frame += 1;
            s.push((t + MS, sample("HMD", t + MS, hmd_frame, -x)));
        }
        if k == 100 {
            s.push((t, sample("Pointer", t, k, 0.0)));
            s.push((
                t,
                Input::Event(Event::rejected(Reject::Crc, 1, "bad CRC from 127.0.0.1")),
            ));
        }
    }
    s
}

fn tmp(name: &str) -> std::path::PathBuf {
    let p = std::env::temp_dir().join(format!("lungdyn-bridge-{}-{name}.ldtr", std::process::id()));
    let _ = std::fs::remove_file(&p);
    p
}

/// Run `source` on the fake clock for `ticks` ticks (or to its end); the frames and the assembler.
fn run(
    source: &mut dyn Source,
    config: BridgeConfig,
    clock: &FakeClock,
    ticks: u64,
    record: Option<&std::path::Path>,
) -> (Vec<TrackerFrame>, Assembler) {
    let mut recorder =
        record.map(|p| RecordWriter::create(p, &config, &source.describe()).unwrap());
    let mut n = 0;
    let r = run_source(
        source,
        config,
        clock,
        &mut recorder,
        &mut || {
            n += 1;
            n > ticks
        },
        "",
    )
    .unwrap();
    if let Some(w) = recorder {
        w.finish().unwrap();
    }
    assert!(r.ended == Ended::Stopped || r.ended == Ended::SourceEnded);
    (r.frames, r.assembler)
}

fn without_stamps(frames: &[TrackerFrame]) -> Vec<TrackerFrame> {
    frames
        .iter()
        .map(|f| TrackerFrame {
            stamps: Default::default(),
            ..*f
        })
        .collect()
}

#[test]
fn the_synthetic_source_gives_the_frames_of_the_bridge_before_sources() {
    let clock = FakeClock::at(1_000_000_000);
    let mut src = SyntheticSource::new(Synthetic::default());
    let config = BridgeConfig {
        validation: Validation {
            volume: Volume::Unbounded,
            ..Validation::default()
        },
        ..BridgeConfig::default()
    };
    let (frames, asm) = run(&mut src, config, &clock, 600, None);
    assert_eq!(frames.len(), 600);
    let old = Synthetic::default();
    for f in &frames {
        let expected = old.frame(f.frame_number, f.stamps.capture_ns);
        assert_eq!(f.tools, expected.tools, "frame {}", f.frame_number);
        assert_eq!(
            (f.tool_count, f.layout_version),
            (2, expected.layout_version)
        );
        assert!(f.stamps.bridge_publish_ns >= f.stamps.capture_ns);
    }
    assert_eq!(asm.stats.rejected_total(), 0);
    assert_eq!(
        asm.stats.frame_gaps + asm.stats.frame_repeats + asm.stats.stale,
        0
    );
    // On the fake clock every tick is exactly on its slot.
    assert_eq!(asm.stats.jitter_us(1.0), 0.001);
}

#[test]
fn a_recorded_session_replays_into_the_same_frames_bit_for_bit() {
    let start = 5_000_000_000;
    let clock = FakeClock::at(start);
    let mut live = ScriptedSource {
        clock: clock.clone(),
        script: script(start).into(),
    };
    let path = tmp("session");
    let (live_frames, live_asm) = run(&mut live, config(), &clock, 185, Some(&path));
    assert_eq!(live_frames.len(), 185);

    // Everything that went wrong shows in the frames and the counters.
    let s = &live_asm.stats;
    assert_eq!(s.rejected_for(Reject::NonFinite), 1);
    assert_eq!(s.rejected_for(Reject::NotRotation), 1);
    assert_eq!(s.rejected_for(Reject::OutOfVolume), 1);
    assert_eq!(s.rejected_for(Reject::Unmapped), 1);
    assert_eq!(s.rejected_for(Reject::Crc), 1);
    // Gaps: the silent quarter second (frames 30..=45 never came), frame 70 (its slot carried a
    // repeat of 69) and the jump 79 → 85.
    assert_eq!(
        (s.frame_repeats, s.frame_gaps, s.frames_lost),
        (1, 3, 16 + 1 + 5)
    );
    assert!(s.stale > 5, "the silent quarter second: {}", s.stale);
    let status = |bit| {
        live_frames
            .iter()
            .filter(|f| f.tools[TOOL_PATIENT].status & bit != 0)
            .count()
    };
    assert_eq!(status(tool_status::NON_FINITE), 1);
    assert!(status(tool_status::STALE) > 5);
    assert_eq!(status(tool_status::FRAME_GAP), 3);
    assert!(live_frames
        .iter()
        .all(|f| f.tools.iter().all(|t| t.pose.is_finite())));
    // A frame with a rejected patient sample keeps the previous good pose and is not valid.
    let nan_frame = live_frames
        .iter()
        .find(|f| f.tools[TOOL_PATIENT].status & tool_status::NON_FINITE != 0)
        .unwrap();
    assert!(!nan_frame.tools[TOOL_PATIENT].is_valid());
    assert!(live_frames.iter().any(|f| f.tools[TOOL_HMD].is_valid()));

    for paced in [false, true] {
        let clock = FakeClock::at(77_000_000_000);
        let mut replay = Replay::open(&path, paced).unwrap();
        let cfg = replay.recorded_config().unwrap().clone();
        assert_eq!(cfg, config());
        let (frames, asm) = run(&mut replay, cfg, &clock, u64::MAX, None);
        assert_eq!(frames.len(), live_frames.len(), "paced {paced}");
        let (a, b) = (without_stamps(&live_frames), without_stamps(&frames));
        for (x, y) in a.iter().zip(&b) {
            assert_eq!(
                bytemuck::bytes_of(x),
                bytemuck::bytes_of(y),
                "frame {}",
                x.frame_number
            );
        }
        assert_eq!(asm.stats.frames_digest, live_asm.stats.frames_digest);
        assert_eq!(asm.stats.rejected, live_asm.stats.rejected);
        // Each replayed sample is as old at its tick as when it was recorded.
        for (x, y) in live_frames.iter().zip(&frames) {
            assert_eq!(
                x.stamps.bridge_publish_ns - x.stamps.capture_ns,
                y.stamps.bridge_publish_ns - y.stamps.capture_ns
            );
        }
    }
    let _ = std::fs::remove_file(&path);
}

#[test]
fn a_recording_made_with_a_respiratory_signal_replays_it_bit_for_bit() {
    // A 25 Hz amplitude trace (mm) of 12 s (a reader wants 10 s at least), one sample invalid,
    // played live beside the 3 s scripted session.
    let trace =
        std::env::temp_dir().join(format!("lungdyn-bridge-{}-trace.csv", std::process::id()));
    let mut csv = String::from("time_s,amplitude_mm,valid\n");
    for k in 0..300 {
        let t = k as f64 * 0.04;
        let valid = if k == 30 { 0 } else { 1 };
        csv.push_str(&format!(
            "{t:.3},{:.4},{valid}\n",
            5.0 * (1.0 - (std::f64::consts::TAU * t / 4.0).cos())
        ));
    }
    std::fs::write(&trace, csv).unwrap();
    let start = 5_000_000_000;
    let clock = FakeClock::at(start);
    let mut live = ScriptedSource {
        clock: clock.clone(),
        script: script(start).into(),
    };
    let path = tmp("session-signal");
    let mut asm = Assembler::new(config());
    asm.set_signal(tracker_bridge::signal::TraceReplay::open(&trace).unwrap());
    let mut recorder = Some(RecordWriter::create(&path, &config(), "scripted").unwrap());
    let mut n = 0;
    // The pipeline's latency as the renderer's reports measured it: none for the first frames,
    // then one that changes from frame to frame (an input the engine predicts across).
    let mut asked = 0u64;
    let r = run_assembled(
        &mut live,
        asm,
        &clock,
        &mut recorder,
        &mut || {
            n += 1;
            n > 185
        },
        "",
        &mut || {
            asked += 1;
            if asked < 20 {
                0
            } else {
                9_000_000 + 1_000 * asked
            }
        },
    )
    .unwrap();
    recorder.unwrap().finish().unwrap();
    let live_frames = r.frames;
    let with_signal = live_frames.iter().filter(|f| f.signal.count > 0).count();
    assert!(
        with_signal > 60,
        "{with_signal} frames carried signal samples"
    );
    assert!(live_frames
        .iter()
        .any(|f| f.signal.count > 0 && f.signal.valid_mask != (1 << f.signal.count) - 1));
    let measured: std::collections::BTreeSet<u64> = live_frames
        .iter()
        .map(|f| f.signal.pipeline_latency_ns)
        .collect();
    assert!(
        measured.contains(&0) && measured.len() > 60,
        "frames carry none, then the latency measured at their tick ({} values)",
        measured.len()
    );
    for paced in [false, true] {
        let clock = FakeClock::at(77_000_000_000);
        let mut replay = Replay::open(&path, paced).unwrap();
        let cfg = replay.recorded_config().unwrap().clone();
        // No signal on the replay's assembler: the recording carries it.
        let (frames, asm) = run(&mut replay, cfg, &clock, u64::MAX, None);
        assert_eq!(frames.len(), live_frames.len(), "paced {paced}");
        assert_eq!(asm.stats.frames_digest, r.assembler.stats.frames_digest);
        // The replay counts what it played as the live run counted what it sent.
        let counts = |s: &tracker_bridge::stats::Stats| s.signal.map(|c| (c.sent, c.invalid));
        assert_eq!(counts(&asm.stats), counts(&r.assembler.stats));
        assert_eq!(counts(&asm.stats).unwrap().1, 1, "the one invalid sample");
        for (x, y) in live_frames.iter().zip(&frames) {
            let (a, b) = (&x.signal, &y.signal);
            assert_eq!(
                (a.count, a.unit, a.status, a.valid_mask, a.period_ns),
                (b.count, b.unit, b.status, b.valid_mask, b.period_ns),
                "frame {}",
                x.frame_number
            );
            assert_eq!(
                a.pipeline_latency_ns, b.pipeline_latency_ns,
                "frame {}: the measured latency replays as it was",
                x.frame_number
            );
            // Each sample as old against its frame's capture as when recorded; values bit for bit.
            let age = |f: &TrackerFrame, t: u64| i128::from(t) - i128::from(f.stamps.capture_ns);
            for i in 0..a.count as usize {
                assert_eq!(a.samples[i].value.to_bits(), b.samples[i].value.to_bits());
                assert_eq!(age(x, a.samples[i].t_ns), age(y, b.samples[i].t_ns));
            }
            assert_eq!(age(x, a.origin_ns), age(y, b.origin_ns));
        }
    }
    let _ = std::fs::remove_file(&path);
    let _ = std::fs::remove_file(&trace);
}

#[test]
fn a_sender_that_falls_silent_goes_stale_within_the_bound() {
    let start = 1_000_000_000;
    let clock = FakeClock::at(start);
    let mut script = Vec::new();
    for k in 0..30u64 {
        let t = start + k * 16_666_667;
        script.push((t, sample("Patient", t, k, 0.0)));
        script.push((t, sample("HMD", t, k, 0.0)));
    }
    let mut src = ScriptedSource {
        clock: clock.clone(),
        script: script.into(),
    };
    let (frames, _) = run(&mut src, config(), &clock, 60, None);
    let last_sample = start + 29 * 16_666_667;
    for f in &frames {
        let age = f.stamps.bridge_publish_ns as i64 - last_sample as i64;
        let valid = f.tools[TOOL_PATIENT].is_valid();
        if f.stamps.bridge_publish_ns > last_sample + 50 * MS {
            assert!(
                !valid && f.tools[TOOL_PATIENT].status & tool_status::STALE != 0,
                "age {age}"
            );
        } else {
            assert!(valid, "frame {} age {}", f.frame_number, age);
        }
    }
}

#[test]
fn a_recorded_sample_stamped_at_the_end_of_time_goes_stale_on_replay() {
    let path = tmp("future");
    let t0 = 5_000_000_000;
    let mut w = RecordWriter::create(&path, &config(), "probe").unwrap();
    let Input::Sample(far) = sample("Patient", u64::MAX, 1, 0.0) else {
        unreachable!()
    };
    w.sample(&far).unwrap();
    w.tick(t0, 1).unwrap();
    for k in 1..=10u64 {
        w.tick(t0 + k * 16_666_667, k + 1).unwrap();
    }
    w.finish().unwrap();

    let clock = FakeClock::at(77_000_000_000);
    let mut replay = Replay::open(&path, false).unwrap();
    let (frames, asm) = run(&mut replay, config(), &clock, u64::MAX, None);
    assert_eq!(frames.len(), 11);
    for f in &frames {
        let p = f.tools[TOOL_PATIENT];
        assert!(
            p.status & tool_status::STALE != 0 && !p.is_valid(),
            "frame {}: status {:#x}",
            f.frame_number,
            p.status
        );
    }
    assert_eq!(asm.stats.stale, 11);

    // The replay says why, once.
    let mut replay = Replay::open(&path, false).unwrap();
    let mut notes = Vec::new();
    while let Poll::Tick { .. } = replay
        .poll(0, &mut |i| {
            if let Input::Event(e) = i {
                notes.push(e.clone());
            }
        })
        .unwrap()
    {}
    assert_eq!(notes.len(), 1, "{notes:?}");
    assert_eq!(notes[0].kind, EventKind::Note);
    assert!(
        notes[0].text.contains("clock is damaged"),
        "{}",
        notes[0].text
    );
    let _ = std::fs::remove_file(&path);
}
