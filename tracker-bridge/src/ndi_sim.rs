//! A simulated NDI tracker that speaks the combined API: bytes in (commands), bytes out (replies).
//! The NDI tests put it behind a pseudo-terminal (as a serial Polaris) or a TCP socket (as a Vega);
//! the benchmarks measure the bridge's jitter against it. No I/O here.
//!
//! It answers `INIT`, `COMM`, `PHSR`, `PHRQ`, `PVWR`, `PINIT`, `PENA`, `PHF`, `TSTART`, `TSTOP`,
//! `BEEP`, `BX` (binary, option 0x0801 layout) and `TX` (ASCII), checks the CRC of every command
//! sent in the `NAME:` form (`ERROR04` when it is wrong), and replies `ERROR0C` to tracking
//! commands outside tracking mode, as a tracker does. Each tracking reply advances the frame
//! counter. Tests change tools between polls (missing, out of volume, a pose) and queue
//! [`Fault`]s for the next tracking replies.

use std::collections::VecDeque;

use crate::ndi::crc16;

/// One simulated tool.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SimTool {
    /// Port handle.
    pub handle: u8,
    /// Quaternion `[q0 (w), qx, qy, qz]`.
    pub quat_wxyz: [f32; 4],
    /// Position, mm.
    pub translation_mm: [f32; 3],
    /// RMS error, mm.
    pub rms_mm: f32,
    /// Extra port-status bits (out of volume 0x40, partially 0x80, faults ...); occupied,
    /// initialised and enabled are added from the tool's state.
    pub port_bits: u32,
    /// Not seen by the camera.
    pub missing: bool,
    /// `PINIT` done.
    pub initialized: bool,
    /// `PENA` done.
    pub enabled: bool,
}

impl SimTool {
    /// A wired tool in its port, not yet initialised, at `translation_mm` with no rotation.
    pub fn at(handle: u8, translation_mm: [f32; 3]) -> Self {
        SimTool {
            handle,
            quat_wxyz: [1.0, 0.0, 0.0, 0.0],
            translation_mm,
            rms_mm: 0.2,
            port_bits: 0,
            missing: false,
            initialized: false,
            enabled: false,
        }
    }

    fn port_status(&self) -> u32 {
        0x01 | if self.initialized { 0x10 } else { 0 }
            | if self.enabled { 0x20 } else { 0 }
            | self.port_bits
    }
}

/// Something wrong with the next tracking reply.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Fault {
    /// The reply's (body) CRC is wrong.
    BadCrc,
    /// Seven garbage bytes come before the reply.
    Garbage,
    /// No reply at all.
    Silence,
    /// `ERRORxx` instead of the data.
    Error(u8),
}

/// The simulated tracker.
#[derive(Debug, Clone)]
pub struct SimDevice {
    /// The tools, in port order.
    pub tools: Vec<SimTool>,
    /// Frame counter (advanced by each tracking reply).
    pub frame: u32,
    /// In tracking mode (`TSTART` .. `TSTOP`).
    pub tracking: bool,
    /// False: answer `ERROR01` to `BX` (a tracker that only knows `TX`).
    pub bx_supported: bool,
    /// Faults applied to the next tracking replies, one each.
    pub faults: VecDeque<Fault>,
    /// Every command text received (before its CRC), in order.
    pub commands: Vec<String>,
    /// Baud rate set by the last `COMM` (9600 at power-up).
    pub baud: u32,
    line: Vec<u8>,
}

impl SimDevice {
    /// A tracker with these tools plugged in.
    pub fn new(tools: Vec<SimTool>) -> Self {
        SimDevice {
            tools,
            frame: 1000,
            tracking: false,
            bx_supported: true,
            faults: VecDeque::new(),
            commands: Vec::new(),
            baud: 9600,
            line: Vec::new(),
        }
    }

    /// The tool with `handle`.
    pub fn tool_mut(&mut self, handle: u8) -> Option<&mut SimTool> {
        self.tools.iter_mut().find(|t| t.handle == handle)
    }

    /// Take received bytes; return the replies to every command they complete.
    pub fn receive(&mut self, bytes: &[u8]) -> Vec<u8> {
        let mut out = Vec::new();
        for &b in bytes {
            if b == b'\r' {
                let line = std::mem::take(&mut self.line);
                self.command(&line, &mut out);
            } else if self.line.len() < 4096 {
                self.line.push(b);
            }
        }
        out
    }

    fn ascii(text: &str, out: &mut Vec<u8>) {
        out.extend_from_slice(text.as_bytes());
        out.extend_from_slice(format!("{:04X}", crc16(text.as_bytes())).as_bytes());
        out.push(b'\r');
    }

    fn command(&mut self, raw: &[u8], out: &mut Vec<u8>) {
        let Ok(text) = std::str::from_utf8(raw) else {
            return Self::ascii("ERROR01", out);
        };
        let (name, params) = if let Some((name, rest)) = text.split_once(':') {
            if rest.len() < 4 {
                return Self::ascii("ERROR04", out);
            }
            let (params, crc) = rest.split_at(rest.len() - 4);
            let body = &text[..name.len() + 1 + params.len()];
            if u16::from_str_radix(crc, 16).ok() != Some(crc16(body.as_bytes())) {
                return Self::ascii("ERROR04", out);
            }
            (name, params)
        } else {
            text.split_once(' ').unwrap_or((text, ""))
        };
        self.commands.push(format!("{name}:{params}"));
        let handle = || u8::from_str_radix(params.get(..2).unwrap_or(""), 16).ok();
        match name {
            "INIT" => {
                self.tracking = false;
                Self::ascii("OKAY", out)
            }
            "COMM" => {
                self.baud = match params.chars().next() {
                    Some('5') => 115_200,
                    Some('0') => 9600,
                    Some('4') => 57_600,
                    _ => self.baud,
                };
                Self::ascii("OKAY", out)
            }
            "PHSR" => {
                let keep = |t: &SimTool| match params {
                    "01" => false,
                    "02" => !t.initialized,
                    "03" => t.initialized && !t.enabled,
                    "04" => t.enabled,
                    _ => true,
                };
                let list: Vec<&SimTool> = self.tools.iter().filter(|t| keep(t)).collect();
                let mut s = format!("{:02X}", list.len());
                for t in list {
                    s += &format!("{:02X}{:03X}", t.handle, t.port_status() & 0xFFF);
                }
                Self::ascii(&s, out)
            }
            "PHRQ" => {
                let h = self
                    .tools
                    .iter()
                    .map(|t| t.handle)
                    .max()
                    .unwrap_or(0)
                    .saturating_add(1)
                    .max(0x0A);
                self.tools.push(SimTool::at(h, [0.0, 0.0, -1000.0]));
                Self::ascii(&format!("{h:02X}"), out)
            }
            "PVWR" | "PHF" => Self::ascii("OKAY", out),
            "PINIT" | "PENA" => match handle().and_then(|h| self.tool_mut(h)) {
                Some(t) => {
                    if name == "PINIT" {
                        t.initialized = true;
                    } else {
                        t.enabled = true;
                    }
                    Self::ascii("OKAY", out)
                }
                None => Self::ascii("ERROR08", out),
            },
            "TSTART" => {
                self.tracking = true;
                Self::ascii("OKAY", out)
            }
            "TSTOP" => {
                self.tracking = false;
                Self::ascii("OKAY", out)
            }
            "BEEP" => Self::ascii("1", out),
            "BX" | "TX" => {
                if name == "BX" && !self.bx_supported {
                    return Self::ascii("ERROR01", out);
                }
                if !self.tracking {
                    return Self::ascii("ERROR0C", out);
                }
                self.frame = self.frame.wrapping_add(1);
                match self.faults.pop_front() {
                    Some(Fault::Silence) => {}
                    Some(Fault::Error(code)) => Self::ascii(&format!("ERROR{code:02X}"), out),
                    Some(Fault::Garbage) => {
                        out.extend_from_slice(&[0x00, 0xFF, 0x13, 0xC4, 0x00, 0x7F, 0x80]);
                        self.tracking_reply(name == "BX", out);
                    }
                    Some(Fault::BadCrc) => {
                        let start = out.len();
                        self.tracking_reply(name == "BX", out);
                        // The binary body CRC is the last two bytes; an ASCII CRC the 4 digits before CR.
                        let i = if name == "BX" {
                            out.len() - 1
                        } else {
                            out.len() - 2
                        };
                        if i >= start {
                            out[i] = if out[i] == b'0' {
                                b'1'
                            } else if name == "BX" {
                                out[i] ^ 0x5A
                            } else {
                                b'0'
                            };
                        }
                    }
                    None => self.tracking_reply(name == "BX", out),
                }
            }
            _ => Self::ascii("ERROR01", out),
        }
    }

    fn tracking_reply(&self, binary: bool, out: &mut Vec<u8>) {
        let tools: Vec<&SimTool> = self.tools.iter().filter(|t| t.enabled).collect();
        if binary {
            let mut body = vec![tools.len() as u8];
            for t in &tools {
                body.push(t.handle);
                body.push(if t.missing { 0x02 } else { 0x01 });
                if !t.missing {
                    for v in t
                        .quat_wxyz
                        .iter()
                        .chain(&t.translation_mm)
                        .chain([&t.rms_mm])
                    {
                        body.extend_from_slice(&v.to_le_bytes());
                    }
                }
                body.extend_from_slice(&t.port_status().to_le_bytes());
                body.extend_from_slice(&self.frame.to_le_bytes());
            }
            body.extend_from_slice(&0u16.to_le_bytes());
            let mut head = vec![0xC4, 0xA5];
            head.extend_from_slice(&(body.len() as u16).to_le_bytes());
            let hcrc = crc16(&head);
            head.extend_from_slice(&hcrc.to_le_bytes());
            out.extend_from_slice(&head);
            out.extend_from_slice(&body);
            out.extend_from_slice(&crc16(&body).to_le_bytes());
        } else {
            let fixed = |v: f32, scale: f32, digits: usize| {
                let n = (v * scale).round() as i64;
                format!(
                    "{}{:0digits$}",
                    if n < 0 { '-' } else { '+' },
                    n.unsigned_abs()
                )
            };
            let mut s = format!("{:02X}", tools.len());
            for t in &tools {
                s += &format!("{:02X}", t.handle);
                if t.missing {
                    s += "MISSING";
                } else {
                    for q in t.quat_wxyz {
                        s += &fixed(q, 1e4, 5);
                    }
                    for x in t.translation_mm {
                        s += &fixed(x, 1e2, 6);
                    }
                    s += &fixed(t.rms_mm, 1e4, 5);
                }
                s += &format!("{:08X}{:08X}\n", t.port_status(), self.frame);
            }
            s += "0000";
            Self::ascii(&s, out);
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::ndi::{self, Command, HandleStatus};

    fn run(dev: &mut SimDevice, cmd: Command) -> Vec<u8> {
        dev.receive(&cmd.encode().unwrap())
    }

    #[test]
    fn the_simulator_speaks_what_the_codec_parses() {
        let mut dev = SimDevice::new(vec![
            SimTool::at(0x0A, [10.5, -20.25, -1500.0]),
            SimTool::at(0x0B, [0.0, 0.0, -900.0]),
        ]);
        assert_eq!(run(&mut dev, Command::Init), b"OKAYA896\r");
        assert_eq!(
            run(&mut dev, Command::Bx(0x0801)),
            dev_error(0x0C),
            "no data before TSTART"
        );
        let need_init =
            ndi::parse_phsr_reply(&run(&mut dev, Command::Phsr(ndi::PhsrFilter::NeedInit)))
                .unwrap();
        assert_eq!(need_init.len(), 2);
        for h in [0x0A, 0x0B] {
            run(&mut dev, Command::Pinit(h));
            run(
                &mut dev,
                Command::Pena {
                    handle: h,
                    priority: ndi::TrackingPriority::Dynamic,
                },
            );
        }
        run(&mut dev, Command::Tstart);
        dev.tool_mut(0x0B).unwrap().missing = true;
        dev.tool_mut(0x0A).unwrap().port_bits = 0x40;
        let r = ndi::parse_bx_reply(&run(&mut dev, Command::Bx(0x0801)), 0x0801).unwrap();
        assert_eq!(r.tools[0].translation_mm, [10.5, -20.25, -1500.0]);
        assert!(r.tools[0].port_status.out_of_volume);
        assert_eq!(r.tools[1].status, HandleStatus::Missing);
        let t = ndi::parse_tx_reply(&run(&mut dev, Command::Tx(0x0801)), 0x0801).unwrap();
        assert_eq!(t.tools[0].translation_mm, [10.5, -20.25, -1500.0]);
        assert_eq!(t.tools[0].frame, r.tools[0].frame + 1);
        dev.faults.push_back(Fault::BadCrc);
        assert!(matches!(
            ndi::parse_bx_reply(&run(&mut dev, Command::Bx(0x0801)), 0x0801),
            Err(ndi::NdiError::Crc { .. })
        ));
        assert_eq!(dev.receive(b"INIT:0000\r"), dev_error(0x04));
    }

    fn dev_error(code: u8) -> Vec<u8> {
        let mut out = Vec::new();
        SimDevice::ascii(&format!("ERROR{code:02X}"), &mut out);
        out
    }
}
