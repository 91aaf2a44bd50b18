//! Per-sample cost of the bridge (goal ≤ 50 µs): bytes of one tracker message in, through parsing,
//! validation and assembly, to one tracker frame published on iceoryx2 — for an OpenIGTLink
//! TRANSFORM (one tool), a QTDATA with both tools, and an NDI BX reply with both tools; plus the
//! parts alone (validation, assembly, recording a sample).
//!
//! Run: `cargo bench -p lungdyn-bench --bench tracker_sample`.

use criterion::{criterion_group, criterion_main, Criterion};
use ipc_types::TrackerFrame;
use tracker_bridge::assemble::{Assembler, BridgeConfig};
use tracker_bridge::igtl::{
    self, Body, Decoder, Limits, Message, QtDataElement, Timestamp, Transform,
};
use tracker_bridge::ndi::{self, ReplyReader};
use tracker_bridge::ndi_sim::{SimDevice, SimTool};
use tracker_bridge::record::RecordWriter;
use tracker_bridge::sample::{Input, Sample, ToolName};
use tracker_bridge::source::igtl_client::message_inputs;
use tracker_bridge::source::ndi_link::sample_of;
use transport::{iox, Instance, Publish};

fn transform_bytes() -> Vec<u8> {
    let t = Transform {
        rotation: [[0.0, -1.0, 0.0], [1.0, 0.0, 0.0], [0.0, 0.0, 1.0]],
        translation_mm: [10.0, -20.0, -1000.0],
    };
    Message::new(
        "Patient",
        Timestamp::from_parts(1_700_000_000, 5),
        Body::Transform(t),
    )
    .encode()
    .unwrap()
}

fn qtdata_bytes() -> Vec<u8> {
    let e = |name: &str, z: f32| QtDataElement {
        name: name.into(),
        instrument_type: 2,
        position_mm: [1.0, 2.0, z],
        quaternion: [0.0, 0.0, 0.38268343, 0.9238795],
    };
    Message::new(
        "Tracker",
        Timestamp::from_parts(1_700_000_000, 5),
        Body::QtData(vec![e("Patient", -1000.0), e("HMD", -900.0)]),
    )
    .encode()
    .unwrap()
}

fn bx_bytes() -> Vec<u8> {
    let mut dev = SimDevice::new(vec![
        SimTool::at(0x0A, [10.0, -20.0, -1000.0]),
        SimTool::at(0x0B, [0.0, 30.0, -900.0]),
    ]);
    for c in [
        ndi::Command::Init,
        ndi::Command::Pinit(0x0A),
        ndi::Command::Pinit(0x0B),
    ] {
        dev.receive(&c.encode().unwrap());
    }
    for h in [0x0A, 0x0B] {
        dev.receive(
            &ndi::Command::Pena {
                handle: h,
                priority: ndi::TrackingPriority::Dynamic,
            }
            .encode()
            .unwrap(),
        );
    }
    dev.receive(&ndi::Command::Tstart.encode().unwrap());
    dev.receive(&ndi::Command::Bx(0x0801).encode().unwrap())
}

fn ndi_config() -> BridgeConfig {
    let mut c = BridgeConfig::default();
    c.slots[0] = ToolName::new("0A").ok();
    c.slots[1] = ToolName::new("0B").ok();
    c
}

fn per_sample(c: &mut Criterion) {
    let instance = Instance::new(&format!("bench-tracker-{}", std::process::id())).unwrap();
    let node = iox::node(&instance, "bench").unwrap();
    let mut outlet = instance.tracker_outlet(&node).unwrap();
    let mut frame = TrackerFrame::default();
    let mut t = 1_000_000_000u64;

    let bytes = transform_bytes();
    let mut asm = Assembler::new(BridgeConfig::default());
    let mut decoder = Decoder::new(Limits::default());
    c.bench_function(
        "OpenIGTLink TRANSFORM: decode + validate + assemble + publish",
        |b| {
            b.iter(|| {
                t += 16_666_667;
                decoder.push(&bytes);
                for m in decoder.by_ref() {
                    message_inputs(&m.unwrap(), t, igtl::QuatOrder::Xyzw, &mut |i| {
                        if let Input::Sample(s) = i {
                            asm.ingest(&s);
                        }
                    });
                }
                asm.frame(t, &mut frame);
                frame.stamps.bridge_publish_ns = t;
                outlet.publish(&frame).unwrap();
            })
        },
    );

    let bytes = qtdata_bytes();
    let mut asm = Assembler::new(BridgeConfig::default());
    c.bench_function(
        "OpenIGTLink QTDATA, 2 tools: decode + validate + assemble + publish",
        |b| {
            b.iter(|| {
                t += 16_666_667;
                decoder.push(&bytes);
                for m in decoder.by_ref() {
                    message_inputs(&m.unwrap(), t, igtl::QuatOrder::Xyzw, &mut |i| {
                        if let Input::Sample(s) = i {
                            asm.ingest(&s);
                        }
                    });
                }
                asm.frame(t, &mut frame);
                outlet.publish(&frame).unwrap();
            })
        },
    );

    let bytes = bx_bytes();
    let mut asm = Assembler::new(ndi_config());
    let mut reader = ReplyReader::new();
    let names = [ToolName::new("0A").unwrap(), ToolName::new("0B").unwrap()];
    c.bench_function(
        "NDI BX, 2 tools: frame + CRC + parse + validate + assemble + publish",
        |b| {
            b.iter(|| {
                t += 16_666_667;
                for r in reader.push(&bytes) {
                    let reply = ndi::parse_bx_reply(r.bytes(), 0x0801).unwrap();
                    for (tool, name) in reply.tools.iter().zip(names) {
                        asm.ingest(&sample_of(tool, name, t));
                    }
                }
                asm.frame(t, &mut frame);
                outlet.publish(&frame).unwrap();
            })
        },
    );

    let s = Sample {
        rms_error_mm: Some(0.2),
        ..Sample::quat(
            t,
            ToolName::new("Patient").unwrap(),
            [0.0, 0.0, 0.38268343, 0.9238795],
            [1.0, 2.0, -1000.0],
        )
    };
    let v = BridgeConfig::default().validation;
    c.bench_function("validate one sample", |b| {
        b.iter(|| std::hint::black_box(v.check(std::hint::black_box(&s))))
    });
    let mut asm = Assembler::new(BridgeConfig::default());
    c.bench_function("assemble one sample + frame", |b| {
        b.iter(|| {
            t += 1;
            asm.ingest(&Sample { receive_ns: t, ..s });
            asm.frame(t, &mut frame);
        })
    });
    let path = std::env::temp_dir().join(format!("lungdyn-bench-{}.ldtr", std::process::id()));
    let _ = std::fs::remove_file(&path);
    let mut w = RecordWriter::create(&path, &BridgeConfig::default(), "bench").unwrap();
    c.bench_function("record one sample", |b| b.iter(|| w.sample(&s).unwrap()));
    w.finish().unwrap();
    let _ = std::fs::remove_file(&path);
    drop(outlet);
    drop(node);
    instance.remove_leftovers();
}

criterion_group!(benches, per_sample);
criterion_main!(benches);
