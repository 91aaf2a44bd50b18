//! Property tests over bytes for everything that parses untrusted input: the OpenIGTLink decoder
//! (one-shot and streaming, arbitrary and mutated messages, any chunking), the NDI reply parsers
//! and reply framer, and the path from any sample to a published frame. No panic, memory bounded
//! by the limits whatever the lengths in the input say, and never a non-finite or non-unit pose in
//! a valid tool. (The recording reader has its own in `record.rs`.)

use ipc_types::TrackerFrame;
use proptest::prelude::*;
use tracker_bridge::assemble::{Assembler, BridgeConfig};
use tracker_bridge::igtl::{self, Body, Decoder, Limits, Message, Timestamp, Transform};
use tracker_bridge::ndi::{self, ReplyReader};
use tracker_bridge::sample::{Rotation, Sample, ToolName};
use tracker_bridge::source::igtl_client::message_inputs;

fn valid_messages() -> Vec<Vec<u8>> {
    let t = Transform {
        translation_mm: [1.0, 2.0, -1000.0],
        ..Transform::IDENTITY
    };
    let mut v2 = Message::new("Patient", Timestamp::from_parts(5, 6), Body::Transform(t));
    v2.version = 2;
    v2.message_id = 9;
    v2.metadata = vec![igtl::MetaEntry::new("Status", "OK")];
    vec![
        Message::new("Patient", Timestamp::from_parts(1, 2), Body::Transform(t))
            .encode()
            .unwrap(),
        v2.encode().unwrap(),
        Message::new(
            "HMD",
            Timestamp::UNSET,
            Body::Position(igtl::Position {
                position_mm: [0.0, 1.0, -900.0],
                quaternion: [0.0, 0.0, 0.0, 1.0],
                form: igtl::PositionForm::Full,
            }),
        )
        .encode()
        .unwrap(),
    ]
}

const BX: &str = "c4a539003f43030a010000803f000000000000000000000000000028410000a2c10080bbc40000003e31000000341200000b0271000000341200000c040000ab69";
const TX: &[u8] = b"020A+10000+00000+00000+00000+001050-002025-150000+012500000003100001234\n0BMISSING0000007100001234\n00006938\r";

fn bx() -> Vec<u8> {
    (0..BX.len())
        .step_by(2)
        .map(|i| u8::from_str_radix(&BX[i..i + 2], 16).unwrap())
        .collect()
}

proptest! {
    #![proptest_config(ProptestConfig::with_cases(3000))]

    #[test]
    fn igtl_one_shot_decoding_never_panics_and_respects_the_limit(bytes in proptest::collection::vec(any::<u8>(), 0..400)) {
        let limits = Limits { max_body_bytes: 256, ..Limits::default() };
        if let Ok((m, used)) = Message::decode(&bytes, &limits) {
            prop_assert!(used <= bytes.len() && used <= igtl::HEADER_SIZE + 256);
            message_inputs(&m, 1, igtl::QuatOrder::Xyzw, &mut |_| {});
        }
    }

    #[test]
    fn igtl_streams_of_mutated_messages_in_any_chunks_stay_bounded(
        picks in proptest::collection::vec(0usize..3, 1..6),
        edits in proptest::collection::vec((any::<usize>(), any::<u8>()), 0..6),
        chunks in proptest::collection::vec(1usize..70, 1..40),
    ) {
        let msgs = valid_messages();
        let mut stream: Vec<u8> = picks.iter().flat_map(|&i| msgs[i].clone()).collect();
        let clean = edits.is_empty();
        for (i, v) in edits {
            let i = i % stream.len();
            stream[i] = v;
        }
        let limits = Limits { max_body_bytes: 512, ..Limits::default() };
        let mut d = Decoder::new(limits);
        let mut pos = 0;
        let mut ok = 0;
        for c in chunks.iter().cycle() {
            if pos >= stream.len() {
                break;
            }
            let end = (pos + c).min(stream.len());
            d.push(&stream[pos..end]);
            pos = end;
            prop_assert!(d.buffered_len() <= igtl::HEADER_SIZE + 512);
            for r in d.by_ref() {
                if let Ok(m) = r {
                    ok += 1;
                    message_inputs(&m, 1, igtl::QuatOrder::Xyzw, &mut |_| {});
                }
            }
        }
        if clean {
            prop_assert_eq!(ok, picks.len(), "unmutated messages all decode, whatever the chunking");
        }
    }

    #[test]
    fn ndi_parsers_never_panic_on_any_bytes(bytes in proptest::collection::vec(any::<u8>(), 0..300)) {
        let _ = ndi::parse_bx_reply(&bytes, 0x0801);
        let _ = ndi::parse_tx_reply(&bytes, 0x0801);
        let _ = ndi::parse_ascii_reply(&bytes);
        let _ = ndi::parse_phsr_reply(&bytes);
        let _ = ndi::binary_body(&bytes);
    }

    #[test]
    fn ndi_mutated_replies_are_rejected_or_parse_to_finite_values(
        which in 0usize..2,
        edits in proptest::collection::vec((any::<usize>(), any::<u8>()), 1..5),
    ) {
        let mut b = if which == 0 { bx() } else { TX.to_vec() };
        for (i, v) in edits {
            let i = i % b.len();
            b[i] = v;
        }
        let r = if which == 0 { ndi::parse_bx_reply(&b, 0x0801) } else { ndi::parse_tx_reply(&b, 0x0801) };
        if let Ok(reply) = r {
            for t in reply.tools.iter().filter(|t| t.has_pose()) {
                prop_assert!(t.quat.iter().chain(&t.translation_mm).all(|v| v.is_finite()));
            }
        }
    }

    #[test]
    fn the_ndi_framer_is_bounded_and_finds_replies_behind_garbage(
        garbage in proptest::collection::vec(any::<u8>(), 0..200),
        chunks in proptest::collection::vec(1usize..50, 1..30),
    ) {
        let mut stream = garbage.clone();
        stream.extend_from_slice(&bx());
        stream.extend_from_slice(TX);
        let mut reader = ReplyReader::with_max_reply(256);
        let mut replies = Vec::new();
        let mut pos = 0;
        for c in chunks.iter().cycle() {
            if pos >= stream.len() {
                break;
            }
            let end = (pos + c).min(stream.len());
            replies.extend(reader.push(&stream[pos..end]));
            pos = end;
            prop_assert!(reader.buffered_len() <= 256);
        }
        // Printable garbage right before the TX reply may join it (then its CRC fails), so only the
        // binary reply is always found intact.
        prop_assert!(replies.iter().any(|r| ndi::parse_bx_reply(r.bytes(), 0x0801).is_ok()));
    }

    #[test]
    fn no_sample_ever_publishes_a_bad_pose(
        vals in proptest::collection::vec(prop_oneof![
            Just(f32::NAN), Just(f32::INFINITY), Just(0.0f32), Just(1.0f32), Just(-1.0f32),
            -2000.0f32..2000.0, -1.5f32..1.5,
        ], 13 * 8),
        kinds in proptest::collection::vec(0u8..3, 8),
        flags in proptest::collection::vec(any::<u32>(), 8),
    ) {
        let mut asm = Assembler::new(BridgeConfig::default());
        let mut f = TrackerFrame::default();
        for (k, ((v, kind), flags)) in vals.chunks(13).zip(&kinds).zip(&flags).enumerate() {
            let rotation = match kind {
                0 => Rotation::Quat([v[0], v[1], v[2], v[3]]),
                1 => Rotation::Matrix([[v[0], v[1], v[2]], [v[3], v[4], v[5]], [v[6], v[7], v[8]]]),
                _ => Rotation::None,
            };
            let s = Sample {
                rotation,
                rms_error_mm: Some(v[12]),
                device_flags: *flags,
                device_frame: Some(k as u64),
                ..Sample::quat(k as u64, ToolName::new(if k % 2 == 0 { "Patient" } else { "HMD" }).unwrap(), [0.0; 4], [v[9], v[10], v[11]])
            };
            asm.ingest(&s);
            asm.frame(k as u64 + 1, &mut f);
            for t in &f.tools {
                prop_assert!(t.pose.is_finite() && t.rms_error_mm.is_finite());
                if t.is_valid() {
                    let n: f32 = t.pose.quat.iter().map(|q| q * q).sum();
                    prop_assert!((n - 1.0).abs() < 1e-4, "valid pose with |q|² = {}", n);
                }
            }
        }
    }
}
