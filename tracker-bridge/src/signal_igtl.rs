//! A respiratory amplitude over OpenIGTLink (`--breathing igtl:NAME`, issue 35 item 1): a belt,
//! a spirometer or a camera-based tracker's PC on the IGT link the bridge already reads poses from
//! (`--source igtl:` or `igtl-server:`), as messages from the device `NAME`:
//!
//! - **`SENSOR`**, the protocol's own one-dimensional type: one float64 value (`LARRAY` 1) with its
//!   unit in the message (`igtl_unit.h`: a prefix in the top 4 bits, then six SI units of 6 bits,
//!   each with a signed 4-bit exponent). A length (metres with any prefix: mm, cm, m) is read in mm,
//!   a volume (m³ with any prefix; the prefix scales the whole unit, so micro-m³ is 1 ml and milli-m³
//!   1 litre) in ml, no unit as arbitrary units. Any other unit (a force, a pressure, an
//!   acceleration) and any other count of values is refused and counted, never guessed.
//! - **`STRING`**, for senders that have no `SENSOR` (pyigtl, 3D Slicer's Python console): one
//!   `UNIT=VALUE` line as the UDP stream takes it ([`crate::signal_udp`]: `mm=12.5`, `ml=`, `au=3`),
//!   in US-ASCII or UTF-8.
//!
//! Each reading is stamped when the bridge's reader thread decoded it (the tracker's rule, so nothing
//! reads ahead of it), goes into the next frame's signal block, keeps the unit of the stream's first
//! (a reading in another unit is refused and counted), and a reading that is not a finite number is
//! sent on flagged invalid, never held. Readings of other devices are not the signal.

use ipc_types::{signal_status, signal_unit, SignalBlock, MAX_SIGNAL_SAMPLES};

use crate::igtl::Body;
use crate::sample::{NotAmplitude, Reading, ToolName};
use crate::signal_udp::{AmplitudeStream, StreamCounts};

/// Readings held between two frames (more are refused and counted as full blocks).
const QUEUE: usize = 32;

/// The SI units of `igtl_unit.h` this reads.
const METER: u8 = 0x01;

/// A decoded OpenIGTLink unit: the prefix's power of ten and up to six (unit, exponent) pairs.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub struct SensorUnit {
    /// Power of ten of the prefix (milli −3, micro −6); `None` for a prefix code the protocol
    /// does not define (8).
    pub prefix_exp: Option<i32>,
    /// (SI unit code, exponent −8..=7) for each of the six places; code 0 is no unit.
    pub units: [(u8, i8); 6],
}

impl SensorUnit {
    /// Unpack `igtl_unit` bits: prefix `pack >> 60`; place `i` (0..6) has its unit at bits
    /// `10·(5−i)+4 ..+6` and its exponent, a 4-bit two's complement, at `10·(5−i) ..+4`.
    pub fn unpack(pack: u64) -> Self {
        let prefix_exp = match pack >> 60 {
            0 => Some(0),
            1 => Some(1),
            2 => Some(2),
            3 => Some(3),
            4 => Some(6),
            5 => Some(9),
            6 => Some(12),
            7 => Some(15),
            9 => Some(-1),
            10 => Some(-2),
            11 => Some(-3),
            12 => Some(-6),
            13 => Some(-9),
            14 => Some(-12),
            15 => Some(-15),
            _ => None,
        };
        let mut units = [(0u8, 0i8); 6];
        for (i, u) in units.iter_mut().enumerate() {
            let shift = 10 * (5 - i as u32);
            let code = ((pack >> (shift + 4)) & 0x3F) as u8;
            let e = ((pack >> shift) & 0x0F) as i8;
            let exp = if e & 0x08 != 0 { e - 16 } else { e };
            *u = (code, exp);
        }
        Self { prefix_exp, units }
    }

    /// Pack (the inverse of [`Self::unpack`]; tests and senders).
    pub fn pack(prefix_code: u8, units: &[(u8, i8)]) -> u64 {
        let mut p = u64::from(prefix_code & 0x0F) << 60;
        for (i, &(code, exp)) in units.iter().take(6).enumerate() {
            let shift = 10 * (5 - i as u32);
            p |= u64::from(code & 0x3F) << (shift + 4);
            p |= u64::from((exp as u8) & 0x0F) << shift;
        }
        p
    }

    /// As a respiratory amplitude: the signal unit and the factor to it (m → mm, m³ → ml), or
    /// `None` for a unit that is neither a length, a volume nor none.
    pub fn amplitude(&self) -> Option<(u32, f64)> {
        let prefix = 10f64.powi(self.prefix_exp?);
        let mut used = self
            .units
            .iter()
            .filter(|(code, exp)| *code != 0 && *exp != 0);
        match (used.next(), used.next()) {
            (None, _) if self.prefix_exp == Some(0) => Some((signal_unit::ARBITRARY, 1.0)),
            (Some(&(METER, 1)), None) => Some((signal_unit::MM, prefix * 1e3)),
            (Some(&(METER, 3)), None) => Some((signal_unit::ML, prefix * 1e6)),
            _ => None,
        }
    }

    /// The unit in words, for messages (`m^1 (prefix 1e-3)`).
    pub fn describe(&self) -> String {
        let names = [
            "", "m", "g", "s", "A", "K", "mol", "cd", "rad", "sr", "Hz", "N", "Pa", "J", "W", "C",
            "V", "F", "ohm", "S", "Wb", "T", "H", "lm", "lx", "Bq", "Gy", "Sv",
        ];
        let mut parts: Vec<String> = self
            .units
            .iter()
            .filter(|(code, exp)| *code != 0 && *exp != 0)
            .map(|&(code, exp)| {
                let name = names
                    .get(usize::from(code))
                    .map_or_else(|| format!("unit#{code}"), |n| n.to_string());
                format!("{name}^{exp}")
            })
            .collect();
        if parts.is_empty() {
            parts.push("no unit".into());
        }
        match self.prefix_exp {
            Some(0) => parts.join(" "),
            Some(e) => format!("1e{e} {}", parts.join(" ")),
            None => format!("(undefined prefix) {}", parts.join(" ")),
        }
    }
}

/// The reading a message body is, if it is one (`SENSOR`, `STRING`); `None` for other bodies.
pub fn reading_of(body: &Body) -> Option<Result<(u32, Option<f64>), NotAmplitude>> {
    match body {
        Body::Sensor(s) => Some(match s.values.as_slice() {
            &[v] => match SensorUnit::unpack(s.unit).amplitude() {
                Some((unit, factor)) => {
                    let x = v * factor;
                    Ok((unit, x.is_finite().then_some(x)))
                }
                None => Err(NotAmplitude::Unit(s.unit)),
            },
            other => Err(NotAmplitude::Values(other.len())),
        }),
        Body::Text(t) if t.encoding == 3 || t.encoding == 106 => {
            Some(crate::signal_udp::parse_datagram(t.text.as_bytes()).ok_or(NotAmplitude::Text))
        }
        Body::Text(_) => Some(Err(NotAmplitude::Text)),
        _ => None,
    }
}

/// What an OpenIGTLink amplitude stream refused, beyond [`StreamCounts`].
#[derive(Debug, Clone, Copy, Default, PartialEq, Eq)]
pub struct IgtlCounts {
    /// `SENSOR` readings in a unit that is no length, volume or none.
    pub wrong_unit: u64,
    /// The last such unit, packed (0 when none).
    pub last_wrong_unit: u64,
    /// Readings of other devices (not the signal).
    pub other_devices: u64,
}

/// The respiratory amplitude from one OpenIGTLink device.
#[derive(Debug)]
pub struct IgtlSignal {
    name: ToolName,
    queue: [(u64, u32, Option<f64>); QUEUE],
    queued: usize,
    stream: AmplitudeStream,
    describe: String,
    /// What was sent and refused.
    pub counts: StreamCounts,
    /// What else was refused.
    pub refused: IgtlCounts,
}

impl IgtlSignal {
    /// Read the device `name`'s readings.
    pub fn new(name: ToolName) -> Self {
        Self {
            describe: format!(
                "OpenIGTLink amplitude from device \"{}\" (SENSOR with its unit: a length in mm, \
                 a volume in ml, none as arbitrary units; or STRING `mm=VALUE`, `ml=VALUE`, \
                 `au=VALUE`)",
                name.as_str()
            ),
            name,
            queue: [(0, 0, None); QUEUE],
            queued: 0,
            stream: AmplitudeStream::default(),
            counts: StreamCounts::default(),
            refused: IgtlCounts::default(),
        }
    }

    /// What it reads, for messages.
    pub fn describe(&self) -> &str {
        &self.describe
    }

    /// Take a reading the source decoded (the loop hands every one here); the device's own are
    /// queued for the next frame (or refused and counted): true; another device's are counted:
    /// false.
    pub fn take(&mut self, r: &Reading) -> bool {
        if r.name != self.name {
            self.refused.other_devices += 1;
            return false;
        }
        match r.value {
            Ok((unit, value)) if self.queued < QUEUE => {
                self.queue[self.queued] = (r.receive_ns, unit, value);
                self.queued += 1;
            }
            Ok(_) => self.counts.full_blocks += 1,
            Err(NotAmplitude::Unit(u)) => {
                self.refused.wrong_unit += 1;
                self.refused.last_wrong_unit = u;
                self.counts.malformed += 1;
            }
            Err(_) => self.counts.malformed += 1,
        }
        true
    }

    /// The readings queued since the last frame into `block` (at most [`MAX_SIGNAL_SAMPLES`]; the
    /// rest wait for the next frame), each stamped when it arrived.
    pub fn fill(&mut self, block: &mut SignalBlock) {
        *block = SignalBlock {
            status: signal_status::CONFIGURED,
            ..Default::default()
        };
        let mut taken = 0;
        while taken < self.queued && (block.count as usize) < MAX_SIGNAL_SAMPLES {
            let (t, unit, value) = self.queue[taken];
            self.stream.take(block, &mut self.counts, t, unit, value);
            taken += 1;
        }
        self.queue.copy_within(taken..self.queued, 0);
        self.queued -= taken;
        self.stream.finish(block, &mut self.counts);
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::igtl::{Message, Sensor, Text, Timestamp};

    fn mm_unit() -> u64 {
        SensorUnit::pack(0xB, &[(METER, 1)])
    }

    fn sensor(unit: u64, values: &[f64]) -> Body {
        Body::Sensor(Sensor {
            status: 0,
            unit,
            values: values.to_vec(),
        })
    }

    fn reading(name: &str, at: u64, body: &Body) -> Reading {
        Reading {
            receive_ns: at,
            name: ToolName::new(name).unwrap(),
            value: reading_of(body).unwrap(),
        }
    }

    /// The OpenIGTLink library's own SENSOR test message (`Testing/igtlutil/
    /// igtl_test_data_sensor.h`: device "DeviceName", timestamp 0x499602D4 s, six values, unit
    /// 0x00443E0000000000) encoded by this codec from its field values has the library's CRC-64,
    /// so the layout is the library's; its unit reads as m·s⁻² (an acceleration: no amplitude).
    #[test]
    fn the_libraries_sensor_message_is_ours_byte_for_byte_and_its_unit_is_read_as_it_says() {
        let values = [
            f64::from_bits(0x40fe_240c_7ae1_47ae),
            f64::from_bits(0x40c8_1cd6_c8b4_3958),
            f64::from_bits(0x4093_4a45_6d5c_faad),
            f64::from_bits(0x405e_dd3b_e22e_5de1),
            f64::from_bits(0x4028_b0fc_b4f1_e4b4),
            f64::from_bits(0x3ff3_c0ca_2a5b_1d5d),
        ];
        let body = sensor(0x0044_3E00_0000_0000, &values);
        let bytes = body.encode().unwrap();
        assert_eq!(bytes.len(), 58, "the library's body size 0x3a");
        assert_eq!(crate::igtl::crc64(&bytes), 0x637b_8008_6620_20e7);
        let parsed = Body::parse("SENSOR", &bytes, &crate::igtl::Limits::default()).unwrap();
        assert_eq!(parsed, body);
        let unit = SensorUnit::unpack(0x0044_3E00_0000_0000);
        assert_eq!(unit.prefix_exp, Some(0));
        assert_eq!(&unit.units[..2], &[(METER, 1), (0x03, -2)]);
        assert_eq!(unit.describe(), "m^1 s^-2");
        assert_eq!(unit.amplitude(), None);
        let m = Message::new("DeviceName", Timestamp::from_parts(0x4996_02d4, 0), body);
        assert_eq!(m.encode().unwrap().len(), 58 + 58);
    }

    #[test]
    fn lengths_volumes_and_no_unit_are_amplitudes_in_mm_ml_and_au_and_nothing_else_is() {
        let cases = [
            (
                SensorUnit::pack(0xB, &[(METER, 1)]),
                Some((signal_unit::MM, 1.0)),
            ),
            (
                SensorUnit::pack(0xA, &[(METER, 1)]),
                Some((signal_unit::MM, 10.0)),
            ),
            (
                SensorUnit::pack(0, &[(METER, 1)]),
                Some((signal_unit::MM, 1000.0)),
            ),
            (
                SensorUnit::pack(0xC, &[(METER, 3)]),
                Some((signal_unit::ML, 1.0)),
            ),
            (
                SensorUnit::pack(0xB, &[(METER, 3)]),
                Some((signal_unit::ML, 1000.0)),
            ),
            (0, Some((signal_unit::ARBITRARY, 1.0))),
            // A pressure, metres per second, mm² and an undefined prefix: refused.
            (SensorUnit::pack(0, &[(0x0C, 1)]), None),
            (SensorUnit::pack(0xB, &[(METER, 1), (0x03, -1)]), None),
            (SensorUnit::pack(0xB, &[(METER, 2)]), None),
            (SensorUnit::pack(8, &[(METER, 1)]), None),
            (SensorUnit::pack(0xB, &[]), None),
        ];
        for (pack, want) in cases {
            let got = SensorUnit::unpack(pack).amplitude();
            match (got, want) {
                (Some((u, f)), Some((wu, wf))) => {
                    assert_eq!(u, wu, "{pack:#x}");
                    assert!((f - wf).abs() < 1e-9 * wf, "{pack:#x}: {f} vs {wf}");
                }
                (g, w) => assert_eq!(g, w, "{pack:#x}"),
            }
        }
        // Every exponent survives a round trip (two's complement in 4 bits).
        for e in -8i8..=7 {
            let u = SensorUnit::unpack(SensorUnit::pack(0, &[(5, e), (METER, 1)]));
            assert_eq!(u.units[0], (5, e));
            assert_eq!(u.units[1], (METER, 1));
        }
    }

    #[test]
    fn readings_of_the_named_device_are_stamped_on_arrival_in_the_streams_unit() {
        let mut s = IgtlSignal::new(ToolName::new("Resp").unwrap());
        let text = |t: &str| {
            Body::Text(Text {
                encoding: 3,
                text: t.into(),
            })
        };
        s.take(&reading("Resp", 100, &sensor(mm_unit(), &[12.5])));
        s.take(&reading("Resp", 200, &sensor(mm_unit(), &[f64::NAN])));
        s.take(&reading("Resp", 300, &text("mm=3.5")));
        s.take(&reading("Resp", 400, &text("ml=400"))); // another unit: refused
        s.take(&reading("Resp", 500, &sensor(mm_unit(), &[1.0, 2.0]))); // two values
        s.take(&reading(
            "Resp",
            600,
            &sensor(SensorUnit::pack(0, &[(0x0C, 1)]), &[5.0]),
        ));
        s.take(&reading("Other", 700, &sensor(mm_unit(), &[9.0])));
        s.take(&reading(
            "Resp",
            800,
            &Body::Text(Text {
                encoding: 1000, // UTF-16: not read
                text: "mm=1".into(),
            }),
        ));
        let mut b = SignalBlock::default();
        s.fill(&mut b);
        assert_eq!(b.unit, signal_unit::MM);
        assert_eq!(b.status, signal_status::CONFIGURED);
        let got: Vec<(u64, f64, bool)> = (0..b.count as usize)
            .map(|i| {
                let (w, valid) = b.sample(i).unwrap();
                (w.t_ns, w.value, valid)
            })
            .collect();
        assert_eq!(
            got,
            [(100, 12.5, true), (200, 0.0, false), (300, 3.5, true)]
        );
        assert_eq!(s.counts.sent, 3);
        assert_eq!(s.counts.invalid, 1);
        assert_eq!(s.counts.malformed, 4, "ml, two values, a pressure, UTF-16");
        assert_eq!(s.refused.wrong_unit, 1);
        assert_eq!(s.refused.other_devices, 1);
        // Nothing queued: the next frame's block is empty but configured, in the stream's unit.
        s.fill(&mut b);
        assert_eq!((b.count, b.unit), (0, signal_unit::MM));
    }

    #[test]
    fn a_burst_longer_than_a_block_waits_for_the_next_frames_and_a_flood_is_counted() {
        let mut s = IgtlSignal::new(ToolName::new("Resp").unwrap());
        for k in 0..(QUEUE as u64 + 5) {
            s.take(&reading("Resp", k + 1, &sensor(mm_unit(), &[k as f64])));
        }
        assert_eq!(s.counts.full_blocks, 5, "the queue holds {QUEUE}");
        let mut seen = Vec::new();
        let mut b = SignalBlock::default();
        for _ in 0..QUEUE {
            s.fill(&mut b);
            seen.extend((0..b.count as usize).map(|i| b.sample(i).unwrap().0.value));
        }
        assert_eq!(seen, (0..QUEUE).map(|k| k as f64).collect::<Vec<_>>());
    }
}
