//! # NDI Combined API: the pure protocol layer (Polaris Spectra/Vicra, Vega, Aurora)
//!
//! This module turns commands into the exact bytes an NDI tracker expects and turns the
//! tracker's replies back into typed values. It does no I/O: the serial port (Polaris/Aurora)
//! or TCP stream (Vega, port [`VEGA_TCP_PORT`]) lives elsewhere and feeds bytes in here.
//!
//! ## What is implemented
//! - [`crc16`]: the CRC NDI uses (CRC-16/ARC: reflected polynomial 0xA001, init 0, no final
//!   XOR), from a `const` table. ASCII text carries it as 4 uppercase hex digits, binary replies
//!   as a little-endian `u16`.
//! - [`Command`]: `INIT`, `COMM`, `PHSR`, `PINIT`, `PENA`, `PHF`, `TSTART`, `TSTOP`, `BX`, `TX`,
//!   `BEEP`, `RESET` and [`Command::Raw`] for everything else, always encoded in the CRC form
//!   `NAME:PARAMS` + CRC16 + CR. Out-of-range arguments are refused with
//!   [`NdiError::InvalidArgument`]; no malformed bytes are ever produced.
//! - ASCII replies ([`ascii_payload`], [`parse_ascii_reply`]): CRC stripped and checked; `OKAY`,
//!   `RESET`, `WARNING…`, data, and `ERRORxx` mapped to [`NdiError::Device`] with a description
//!   ([`error_description`]). `PHSR` replies: [`parse_phsr_reply`].
//! - Binary `BX` replies ([`parse_bx_reply`]): start sequence `C4 A5`, body length, header CRC,
//!   body, body CRC; the 0x0001 transformation block (valid / missing / disabled handles, port
//!   status, frame number) and the system status. Option 0x0800 (also report out-of-volume
//!   transforms) changes no layout and is accepted.
//! - ASCII `TX` replies ([`parse_tx_reply`]) with the fixed-width implied-decimal fields,
//!   `MISSING`, `DISABLED` and `UNOCCUPIED` records and the system status.
//! - [`ReplyReader`]: frames a byte stream into whole replies (ASCII up to CR, binary by its
//!   length field) with a bounded buffer and resynchronisation on garbage.
//!
//! ## Sources (public code; no NDI API guide was readable, see "Not verified" below)
//! - PlusToolkit/ndicapi `ndicapi.cxx` (`ndiCommandVA`, `CalcCRC16`, `ndiBXHelper`,
//!   `ndiTXHelper`, `ndiErrorString`, `ndiSerialProbe`) and `ndicapi.h` (command macros, error
//!   codes, reply-option, handle-status and port/system-status bits), revisions 026c0567 and
//!   c8ac18ad.
//! - PlusToolkit/PlusLib `src/PlusDataCollection/NDICAPITracking/vtkPlusNDITracker.cxx`
//!   (`BX:0801` polling, `COMM:%X%03d%d` so that 230400 baud is `A`, TCP port 8765).
//! - NDI's own sample code (2002-2003) as vendored in radtek/Panasee `TrackControl/`
//!   (`SystemCRC.cpp`, `Conversions.cpp`, `CommandHandling.cpp`): CRC table, BX framing,
//!   port-status bit names.
//! - jhu-saw/sawNDITracker `components/code/mtsNDISerial.cpp` (independent TX/PHSR parser).
//! - SciKit-Surgery/scikit-surgerynditracker `nditracker.py` (Vega over TCP).
//! - An Aurora ROS 2 driver `core/aurora_message_parser.cpp` (port-status bit names).
//! - Error codes 0x2E..0x42: ndicapi c8ac18ad `ndicapi.h` defines, agreeing with two
//!   independent driver tables; the older ndicapi string table (and the lungdyn research note
//!   that copied it) is shifted by one from 0x2E on and is not followed here.
//!
//! The byte-level facts and test vectors were collected in the lungdyn research note
//! `trackers_spec.md` (part B); the CRC vectors were checked against ndicapi's own parity
//! algorithm, the BX/TX/PHSR vectors are synthesised to the documented layout (no device
//! captures were available).
//!
//! ## Safety rules this module keeps
//! 1. std only, no `unsafe`, no I/O, no global state.
//! 2. Never emit malformed command bytes: every argument is range-checked, `Raw` text is
//!    restricted to printable ASCII in the `NAME:` form, and the CRC/CR are always appended here.
//! 3. Never trust a reply before its CRC is checked; binary header CRC before the length field is
//!    used, body CRC before the body is read.
//! 4. Never misparse: a layout this module does not know (unknown handle status, option blocks
//!    other than 0x0001/0x0800, length mismatches, stray bytes) is an error, not a guess.
//! 5. Memory is bounded: no allocation is sized from an untrusted length beyond
//!    [`ReplyReader::max_reply`] (64 KiB by default); per-reply vectors are bounded by a `u8`
//!    handle count.
//! 6. Never panic on any input (a deterministic fuzz test feeds 40,000 inputs to every parser).
//!
//! ## Not verified (treat as assumptions)
//! - `RESET:0` as a soft reset (NDI sample code sends `RESET 0` to wireless systems when it
//!   cannot send a serial break); the usual reset is a serial break, done by the transport.
//! - What follows `DISABLED` / `UNOCCUPIED` in a `TX` record (ndicapi and sawNDITracker disagree);
//!   this parser reads an 8-hex port status and 8-hex frame number there when present.
//! - `TX` with option 0x0800, the `WARNING` reply format, port-status bits 14-15 and system-status
//!   bits above 0x80.

#![forbid(unsafe_code)]
#![warn(missing_docs)]

use std::fmt;

// ---------------------------------------------------------------------------------------------
// Constants
// ---------------------------------------------------------------------------------------------

/// Default TCP port of an NDI Vega (PLUS `NetworkPort(8765)`, scikit-surgery default).
pub const VEGA_TCP_PORT: u16 = 8765;

/// First two bytes of every binary reply: the start sequence `0xA5C4` stored little-endian.
pub const BINARY_START: [u8; 2] = [0xC4, 0xA5];

/// Length of a binary reply header: start sequence, body length, header CRC (2 bytes each).
pub const BINARY_HEADER_LEN: usize = 6;

/// Bytes of a binary reply that are not body: the header plus the 2-byte body CRC.
pub const BINARY_OVERHEAD: usize = BINARY_HEADER_LEN + 2;

/// Default bound on one reply, in bytes, for [`ReplyReader`].
pub const DEFAULT_MAX_REPLY: usize = 64 * 1024;

/// Host-side bound on the text of one command (before CRC and CR). The API defines no number;
/// the longest command used in practice (`PVWR`) is 139 characters.
pub const MAX_COMMAND_TEXT: usize = 1024;

/// Shortest ASCII reply: an (empty) text, 4 CRC characters and CR.
const MIN_ASCII_REPLY: usize = 5;

/// Reply-option bits of `BX` and `TX` (`ndicapi.h`).
pub mod reply_options {
    /// Transformations, port status and frame number per handle, plus the system status.
    pub const TRANSFORMS: u16 = 0x0001;
    /// Tool and marker information per handle.
    pub const TOOL_MARKER_INFO: u16 = 0x0002;
    /// Position of a single stray active marker per handle.
    pub const ACTIVE_SINGLE_STRAY: u16 = 0x0004;
    /// `BX` only: 3-D positions of the markers of each tool.
    pub const MARKERS_3D: u16 = 0x0008;
    /// Also report transformations that are not normally reported (tools out of volume).
    pub const NOT_NORMALLY_REPORTED: u16 = 0x0800;
    /// Positions of stray passive markers.
    pub const PASSIVE_STRAYS: u16 = 0x1000;

    /// Bits a `BX` command may carry.
    pub const BX_ALLOWED: u16 = TRANSFORMS
        | TOOL_MARKER_INFO
        | ACTIVE_SINGLE_STRAY
        | MARKERS_3D
        | NOT_NORMALLY_REPORTED
        | PASSIVE_STRAYS;
    /// Bits a `TX` command may carry.
    pub const TX_ALLOWED: u16 = TRANSFORMS
        | TOOL_MARKER_INFO
        | ACTIVE_SINGLE_STRAY
        | NOT_NORMALLY_REPORTED
        | PASSIVE_STRAYS;
    /// Bits [`super::parse_bx_reply`] and [`super::parse_tx_reply`] decode (0x0001 required).
    pub const DECODED: u16 = TRANSFORMS | NOT_NORMALLY_REPORTED;
}

// ---------------------------------------------------------------------------------------------
// CRC-16
// ---------------------------------------------------------------------------------------------

/// CRC-16/ARC lookup table: entry `i` is `i` shifted right 8 times, XOR 0xA001 whenever the
/// bit shifted out is set (NDI sample `InitCrcTable`).
pub const CRC16_TABLE: [u16; 256] = make_crc16_table();

const fn make_crc16_table() -> [u16; 256] {
    let mut table = [0u16; 256];
    let mut i = 0;
    while i < 256 {
        let mut c = i as u16;
        let mut k = 0;
        while k < 8 {
            c = if c & 1 != 0 {
                (c >> 1) ^ 0xA001
            } else {
                c >> 1
            };
            k += 1;
        }
        table[i] = c;
        i += 1;
    }
    table
}

/// Continues a CRC-16/ARC over `data`, starting from `crc` (0 for a fresh CRC).
pub const fn crc16_update(mut crc: u16, data: &[u8]) -> u16 {
    let mut i = 0;
    while i < data.len() {
        crc = CRC16_TABLE[((crc ^ data[i] as u16) & 0xFF) as usize] ^ (crc >> 8);
        i += 1;
    }
    crc
}

/// The NDI CRC16 of `data` (CRC-16/ARC). `crc16(b"INIT:") == 0xE3A5`.
pub const fn crc16(data: &[u8]) -> u16 {
    crc16_update(0, data)
}

// ---------------------------------------------------------------------------------------------
// Errors
// ---------------------------------------------------------------------------------------------

/// Which CRC failed.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum CrcScope {
    /// The 4 hex digits at the end of an ASCII reply.
    AsciiReply,
    /// The header CRC of a binary reply (over its first 4 bytes).
    BinaryHeader,
    /// The body CRC of a binary reply.
    BinaryBody,
}

impl fmt::Display for CrcScope {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        f.write_str(match self {
            CrcScope::AsciiReply => "ASCII reply",
            CrcScope::BinaryHeader => "binary reply header",
            CrcScope::BinaryBody => "binary reply body",
        })
    }
}

/// Everything that can go wrong while encoding a command or decoding a reply.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum NdiError {
    /// A command argument is out of range; nothing was encoded.
    InvalidArgument {
        /// Command name (`"PINIT"`, `"raw"`, ...).
        command: &'static str,
        /// What is wrong with the argument.
        detail: String,
    },
    /// A CRC did not match: the bytes were corrupted or lost on the link.
    Crc {
        /// Which CRC.
        scope: CrcScope,
        /// The CRC the reply carries.
        expected: u16,
        /// The CRC computed over the bytes received.
        actual: u16,
    },
    /// The reply is incomplete.
    Truncated {
        /// Bytes needed at least.
        needed: usize,
        /// Bytes present.
        got: usize,
    },
    /// A binary reply is longer than its length field says.
    TrailingBytes {
        /// Length implied by the header.
        expected: usize,
        /// Length given.
        got: usize,
    },
    /// The tracker answered `ERRORxx`.
    Device {
        /// The error code (`xx`).
        code: u8,
        /// Short description, or a note that the code is unknown.
        description: &'static str,
    },
    /// A field is not in the expected format.
    BadField {
        /// Which field.
        field: &'static str,
        /// The offending text (escaped, shortened).
        text: String,
    },
    /// A CRC-valid reply does not have the layout its option word implies.
    Layout {
        /// Byte offset in the frame (binary) or reply text (ASCII).
        offset: usize,
        /// What did not fit.
        detail: String,
    },
    /// Reply options this module does not decode.
    UnsupportedOption {
        /// The option word given.
        options: u16,
        /// The bits that are not decoded (0 when only 0x0001 is missing).
        unsupported: u16,
    },
    /// A valid reply of another kind than the one expected.
    UnexpectedReply {
        /// What was expected.
        expected: &'static str,
        /// What came (escaped, shortened).
        got: String,
    },
}

impl fmt::Display for NdiError {
    fn fmt(&self, f: &mut fmt::Formatter<'_>) -> fmt::Result {
        match self {
            NdiError::InvalidArgument { command, detail } => {
                write!(
                    f,
                    "cannot encode NDI command {command}: {detail}; nothing was sent"
                )
            }
            NdiError::Crc {
                scope,
                expected,
                actual,
            } => write!(
                f,
                "CRC mismatch in {scope}: the reply carries {expected:04X} but the bytes received \
                 compute to {actual:04X}; bytes were corrupted or lost on the link (check the \
                 cable, that host and tracker use the same baud rate/COMM settings, and that no \
                 other program talks to the tracker)"
            ),
            NdiError::Truncated { needed, got } => write!(
                f,
                "reply incomplete: needs at least {needed} bytes, got {got} (keep reading until \
                 CR or the binary length is complete, or frame the stream with ReplyReader)"
            ),
            NdiError::TrailingBytes { expected, got } => write!(
                f,
                "binary reply has {got} bytes but its length field implies {expected}; the extra \
                 bytes belong to another reply (frame the stream with ReplyReader)"
            ),
            NdiError::Device { code, description } => {
                write!(f, "tracker answered ERROR{code:02X}: {description}")
            }
            NdiError::BadField { field, text } => write!(
                f,
                "malformed {field}: {text} (not the NDI Combined API layout this decoder \
                 implements)"
            ),
            NdiError::Layout { offset, detail } => {
                write!(f, "reply layout mismatch at byte {offset}: {detail}")
            }
            NdiError::UnsupportedOption {
                options,
                unsupported,
            } => {
                if *unsupported == 0 {
                    write!(
                        f,
                        "reply option word {options:04X} lacks 0x0001 (transforms); this decoder \
                         needs it: send BX:0001/BX:0801 or TX:0001/TX:0801"
                    )
                } else {
                    write!(
                        f,
                        "reply option bits {unsupported:04X} (of {options:04X}) are not decoded \
                         here; only 0x0001 (transforms) and 0x0800 (out-of-volume transforms) \
                         are: send BX:0801 or TX:0801 instead"
                    )
                }
            }
            NdiError::UnexpectedReply { expected, got } => {
                write!(f, "expected {expected}, but the tracker answered {got}")
            }
        }
    }
}

impl std::error::Error for NdiError {}

/// Escaped, shortened rendering of reply bytes for error messages.
fn show(bytes: &[u8]) -> String {
    const MAX: usize = 48;
    let mut s = String::from("\"");
    for &b in bytes.iter().take(MAX) {
        s.extend(std::ascii::escape_default(b).map(char::from));
    }
    s.push('"');
    if bytes.len() > MAX {
        use fmt::Write as _;
        let _ = write!(s, " (+{} more bytes)", bytes.len() - MAX);
    }
    s
}

fn bad(field: &'static str, bytes: &[u8]) -> NdiError {
    NdiError::BadField {
        field,
        text: show(bytes),
    }
}

/// Describes a device error code of an `ERRORxx` reply. Unknown codes get a generic text; the
/// number itself is kept in [`NdiError::Device::code`].
pub fn error_description(code: u8) -> &'static str {
    match code {
        0x01 => "invalid command",
        0x02 => "command too long",
        0x03 => "command too short",
        0x04 => "invalid CRC calculated for command",
        0x05 => "time-out on command execution",
        0x06 => "unable to set up new communication parameters",
        0x07 => "incorrect number of command parameters",
        0x08 => "invalid port handle selected",
        0x09 => "invalid tracking priority selected (must be S, D or B)",
        0x0A => "invalid LED selected",
        0x0B => "invalid LED state selected",
        0x0C => "command is invalid while in the current mode (e.g. tracking: send TSTOP first)",
        0x0D => "no tool assigned to the selected port handle",
        0x0E => "selected port handle not initialized (send PINIT)",
        0x0F => "selected port handle not enabled (send PENA)",
        0x10 => "system not initialized (send INIT)",
        0x11 => "unable to stop tracking",
        0x12 => "unable to start tracking",
        0x13 => "unable to initialize tool-in-port",
        0x14 => "invalid position sensor or field generator characterization parameters",
        0x15 => "unable to initialize the measurement system",
        0x16 => "unable to start diagnostic mode",
        0x17 => "unable to stop diagnostic mode",
        0x18 => "unable to determine environmental infrared or magnetic interference",
        0x19 => "unable to read the device's firmware version information",
        0x1A => "internal measurement system error",
        0x1B => "unable to initialize for environmental infrared diagnostics",
        0x1C => "unable to set marker firing signature",
        0x1D => "unable to search for SROM device IDs",
        0x1E => "unable to read SROM device data",
        0x1F => "unable to write SROM device data",
        0x20 => "unable to select SROM device",
        0x21 => "unable to perform tool current test",
        0x22 => {
            "enabled tools not supported by the selected volume (no camera parameters for \
                 this wavelength)"
        }
        0x23 => "command parameter out of range",
        0x24 => "unable to select parameters by volume",
        0x25 => "unable to determine the system's supported features list",
        0x28 => "too many tools enabled (older firmware: SCU hardware changed state)",
        0x29 => "main processor firmware corrupt",
        0x2A => "no memory available for dynamic allocation (heap full)",
        0x2B => "requested port handle has not been allocated",
        0x2C => "requested port handle has become unoccupied",
        0x2D => "all port handles have been allocated",
        0x2E => "incompatible firmware versions",
        0x2F => "invalid port description",
        0x30 => "requested port already assigned to a port handle",
        0x31 => "invalid input or output state",
        0x32 => "invalid operation for the device associated with the port handle",
        0x33 => "feature not available",
        0x34 => "user parameter does not exist",
        0x35 => "invalid value type",
        0x36 => "user parameter value out of valid range",
        0x37 => "user parameter array index out of valid range",
        0x38 => "user parameter size incorrect",
        0x39 => "permission denied (read-only, or a master-mode command on a monitor connection)",
        0x3B => "file not found",
        0x3C => "error writing to file",
        0x3D => "error reading from file",
        0x40 => "tool definition file error (CRC failed or invalid format)",
        0x41 => "tool characteristics not supported",
        0x42 => "device not present",
        0xF1 => "too much environmental infrared",
        0xF4..=0xF6 => "flash EPROM erase/write/read failure",
        _ => "unknown error code (not in ndicapi's table; see the tracker's API guide)",
    }
}

// ---------------------------------------------------------------------------------------------
// Commands
// ---------------------------------------------------------------------------------------------

/// Baud rate field of `COMM` (`ndicapi.h` `NDI_9600`..; 230400 is `A` as PLUS sends it).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Baud {
    /// 9600 baud (`0`), the power-up default.
    B9600,
    /// 14400 baud (`1`).
    B14400,
    /// 19200 baud (`2`).
    B19200,
    /// 38400 baud (`3`).
    B38400,
    /// 57600 baud (`4`).
    B57600,
    /// 115200 baud (`5`).
    B115200,
    /// 921600 baud (`6`).
    B921600,
    /// 1228739 baud (`7`).
    B1228739,
    /// 230400 baud (`A`).
    B230400,
}

impl Baud {
    /// The character sent in `COMM`.
    pub const fn code(self) -> char {
        match self {
            Baud::B9600 => '0',
            Baud::B14400 => '1',
            Baud::B19200 => '2',
            Baud::B38400 => '3',
            Baud::B57600 => '4',
            Baud::B115200 => '5',
            Baud::B921600 => '6',
            Baud::B1228739 => '7',
            Baud::B230400 => 'A',
        }
    }

    /// The rate in bits per second, for configuring the host port after `OKAY`.
    pub const fn bits_per_second(self) -> u32 {
        match self {
            Baud::B9600 => 9600,
            Baud::B14400 => 14400,
            Baud::B19200 => 19200,
            Baud::B38400 => 38400,
            Baud::B57600 => 57600,
            Baud::B115200 => 115_200,
            Baud::B921600 => 921_600,
            Baud::B1228739 => 1_228_739,
            Baud::B230400 => 230_400,
        }
    }
}

/// Data bits field of `COMM`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum DataBits {
    /// 8 data bits (`0`).
    Eight,
    /// 7 data bits (`1`).
    Seven,
}

/// Parity field of `COMM`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Parity {
    /// No parity (`0`).
    None,
    /// Odd parity (`1`).
    Odd,
    /// Even parity (`2`).
    Even,
}

/// Stop bits field of `COMM`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum StopBits {
    /// 1 stop bit (`0`).
    One,
    /// 2 stop bits (`1`).
    Two,
}

/// Handshake field of `COMM`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum Handshake {
    /// No hardware handshake (`0`).
    None,
    /// RTS/CTS hardware handshake (`1`).
    RtsCts,
}

/// Serial settings of a `COMM` command (`COMM:BDPSH`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct CommSettings {
    /// Baud rate.
    pub baud: Baud,
    /// Data bits.
    pub data_bits: DataBits,
    /// Parity.
    pub parity: Parity,
    /// Stop bits.
    pub stop_bits: StopBits,
    /// Hardware handshake.
    pub handshake: Handshake,
}

impl CommSettings {
    /// 9600 baud 8N1, no handshake: the settings after power-up, reset or `COMM:00000`.
    pub const POWER_ON: CommSettings = CommSettings::new_8n1(Baud::B9600);

    /// `baud` with 8 data bits, no parity, 1 stop bit, no handshake.
    pub const fn new_8n1(baud: Baud) -> Self {
        CommSettings {
            baud,
            data_bits: DataBits::Eight,
            parity: Parity::None,
            stop_bits: StopBits::One,
            handshake: Handshake::None,
        }
    }

    fn params(self) -> String {
        let d = match self.data_bits {
            DataBits::Eight => '0',
            DataBits::Seven => '1',
        };
        let p = match self.parity {
            Parity::None => '0',
            Parity::Odd => '1',
            Parity::Even => '2',
        };
        let s = match self.stop_bits {
            StopBits::One => '0',
            StopBits::Two => '1',
        };
        let h = match self.handshake {
            Handshake::None => '0',
            Handshake::RtsCts => '1',
        };
        [self.baud.code(), d, p, s, h].iter().collect()
    }
}

/// Which port handles a `PHSR` lists.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum PhsrFilter {
    /// `00`: all allocated handles.
    All,
    /// `01`: handles waiting to be freed (send `PHF`).
    ToBeFreed,
    /// `02`: handles needing initialization (send `PINIT`).
    NeedInit,
    /// `03`: handles needing enabling (send `PENA`).
    NeedEnable,
    /// `04`: enabled handles.
    Enabled,
}

impl PhsrFilter {
    /// The 2-digit option sent.
    pub const fn code(self) -> u8 {
        match self {
            PhsrFilter::All => 0,
            PhsrFilter::ToBeFreed => 1,
            PhsrFilter::NeedInit => 2,
            PhsrFilter::NeedEnable => 3,
            PhsrFilter::Enabled => 4,
        }
    }
}

/// Tracking priority of `PENA`.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum TrackingPriority {
    /// `S`: static tool (e.g. a reference frame).
    Static,
    /// `D`: dynamic tool (e.g. a pointer).
    Dynamic,
    /// `B`: button box (tool without markers).
    ButtonBox,
}

impl TrackingPriority {
    /// The character sent.
    pub const fn code(self) -> char {
        match self {
            TrackingPriority::Static => 'S',
            TrackingPriority::Dynamic => 'D',
            TrackingPriority::ButtonBox => 'B',
        }
    }
}

/// A host-to-tracker command. [`Command::encode`] gives the exact bytes to write.
#[derive(Debug, Clone, PartialEq, Eq, Hash)]
pub enum Command {
    /// `INIT:` initialise the system; expect `OKAY` (the first one may take seconds).
    Init,
    /// `COMM:BDPSH` change the serial settings; after `OKAY`, switch the host port (serial only).
    Comm(CommSettings),
    /// `PHSR:nn` list port handles.
    Phsr(PhsrFilter),
    /// `PINIT:hh` initialise a port handle (1..=0xFF).
    Pinit(u8),
    /// `PENA:hhP` enable tracking of a port handle (1..=0xFF).
    Pena {
        /// Port handle, 1..=0xFF.
        handle: u8,
        /// Tracking priority.
        priority: TrackingPriority,
    },
    /// `PHF:hh` free a port handle (1..=0xFF).
    Phf(u8),
    /// `TSTART:` enter tracking mode.
    Tstart,
    /// `TSTOP:` leave tracking mode.
    Tstop,
    /// `BX:oooo` binary tracking data; options from [`reply_options::BX_ALLOWED`], non-zero.
    Bx(u16),
    /// `TX:oooo` ASCII tracking data; options from [`reply_options::TX_ALLOWED`], non-zero.
    Tx(u16),
    /// `BEEP:n` beep 1..=9 times; the reply is `1` (beeped) or `0` (busy, retry).
    Beep(u8),
    /// `RESET:0` soft reset (unverified, see the module doc); a serial break is the usual reset.
    Reset,
    /// Any other command as its text before the CRC, in the `NAME:PARAMS` form, e.g. `VER:4`,
    /// `APIREV:` or `PHRQ:*********1****`. The name must be uppercase letters/digits, the
    /// parameters printable ASCII, the whole at most [`MAX_COMMAND_TEXT`] bytes.
    Raw(String),
}

fn check_handle(command: &'static str, handle: u8) -> Result<u8, NdiError> {
    if handle == 0 {
        return Err(NdiError::InvalidArgument {
            command,
            detail: "port handle 0x00 is not valid (handles are 0x01..=0xFF, as PHSR/PHRQ \
                     report them)"
                .to_string(),
        });
    }
    Ok(handle)
}

fn check_options(command: &'static str, options: u16, allowed: u16) -> Result<u16, NdiError> {
    if options == 0 || options & !allowed != 0 {
        return Err(NdiError::InvalidArgument {
            command,
            detail: format!(
                "reply option word {options:04X} must be non-zero and use only bits \
                 {allowed:04X}"
            ),
        });
    }
    Ok(options)
}

fn check_raw(text: &str) -> Result<(), NdiError> {
    let err = |detail: String| NdiError::InvalidArgument {
        command: "raw",
        detail,
    };
    let b = text.as_bytes();
    if b.len() > MAX_COMMAND_TEXT {
        return Err(err(format!(
            "text is {} bytes, more than the {MAX_COMMAND_TEXT}-byte bound",
            b.len()
        )));
    }
    let Some(colon) = b.iter().position(|&c| c == b':') else {
        return Err(err(format!(
            "{} is not in the CRC form NAME:PARAMS (e.g. \"VER:4\", \"APIREV:\")",
            show(b)
        )));
    };
    let name = &b[..colon];
    if name.is_empty()
        || name.len() > 16
        || !name
            .iter()
            .all(|c| c.is_ascii_uppercase() || c.is_ascii_digit())
    {
        return Err(err(format!(
            "command name {} must be 1..=16 uppercase letters or digits",
            show(name)
        )));
    }
    if let Some(&c) = b[colon + 1..]
        .iter()
        .find(|&&c| !(0x20..=0x7E).contains(&c))
    {
        return Err(err(format!(
            "parameters contain byte 0x{c:02X}; only printable ASCII is allowed (CR, LF or \
             binary bytes would break the framing)"
        )));
    }
    Ok(())
}

fn push_hex4(out: &mut Vec<u8>, v: u16) {
    const HEX: &[u8; 16] = b"0123456789ABCDEF";
    for shift in [12u16, 8, 4, 0] {
        out.push(HEX[((v >> shift) & 0xF) as usize]);
    }
}

impl Command {
    /// The command name (`"INIT"`, `"BX"`, ...; for `Raw`, the text before `:`).
    pub fn name(&self) -> &str {
        match self {
            Command::Init => "INIT",
            Command::Comm(_) => "COMM",
            Command::Phsr(_) => "PHSR",
            Command::Pinit(_) => "PINIT",
            Command::Pena { .. } => "PENA",
            Command::Phf(_) => "PHF",
            Command::Tstart => "TSTART",
            Command::Tstop => "TSTOP",
            Command::Bx(_) => "BX",
            Command::Tx(_) => "TX",
            Command::Beep(_) => "BEEP",
            Command::Reset => "RESET",
            Command::Raw(s) => s.split(':').next().unwrap_or(""),
        }
    }

    /// The checked command text the CRC covers (`"PINIT:0A"`), without CRC and CR.
    ///
    /// # Errors
    /// [`NdiError::InvalidArgument`] when an argument is out of range.
    pub fn payload(&self) -> Result<String, NdiError> {
        Ok(match self {
            Command::Init => "INIT:".to_string(),
            Command::Comm(c) => format!("COMM:{}", c.params()),
            Command::Phsr(f) => format!("PHSR:{:02X}", f.code()),
            Command::Pinit(h) => format!("PINIT:{:02X}", check_handle("PINIT", *h)?),
            Command::Pena { handle, priority } => {
                format!(
                    "PENA:{:02X}{}",
                    check_handle("PENA", *handle)?,
                    priority.code()
                )
            }
            Command::Phf(h) => format!("PHF:{:02X}", check_handle("PHF", *h)?),
            Command::Tstart => "TSTART:".to_string(),
            Command::Tstop => "TSTOP:".to_string(),
            Command::Bx(o) => {
                format!(
                    "BX:{:04X}",
                    check_options("BX", *o, reply_options::BX_ALLOWED)?
                )
            }
            Command::Tx(o) => {
                format!(
                    "TX:{:04X}",
                    check_options("TX", *o, reply_options::TX_ALLOWED)?
                )
            }
            Command::Beep(n) => {
                if !(1..=9).contains(n) {
                    return Err(NdiError::InvalidArgument {
                        command: "BEEP",
                        detail: format!("beep count {n} must be 1..=9"),
                    });
                }
                format!("BEEP:{n}")
            }
            Command::Reset => "RESET:0".to_string(),
            Command::Raw(s) => {
                check_raw(s)?;
                s.clone()
            }
        })
    }

    /// The exact bytes to write: payload, CRC16 as 4 uppercase hex digits, CR.
    ///
    /// # Errors
    /// [`NdiError::InvalidArgument`] when an argument is out of range.
    pub fn encode(&self) -> Result<Vec<u8>, NdiError> {
        let text = self.payload()?;
        let mut out = Vec::with_capacity(text.len() + 5);
        out.extend_from_slice(text.as_bytes());
        push_hex4(&mut out, crc16(text.as_bytes()));
        out.push(b'\r');
        Ok(out)
    }
}

// ---------------------------------------------------------------------------------------------
// Field helpers
// ---------------------------------------------------------------------------------------------

fn hex_digit(b: u8) -> Option<u32> {
    match b {
        b'0'..=b'9' => Some(u32::from(b - b'0')),
        b'A'..=b'F' => Some(u32::from(b - b'A' + 10)),
        _ => None,
    }
}

/// Uppercase hex, 1..=8 digits (the device sends uppercase; lowercase is refused).
fn parse_hex(field: &'static str, s: &[u8]) -> Result<u32, NdiError> {
    if s.is_empty() || s.len() > 8 {
        return Err(bad(field, s));
    }
    let mut v = 0u32;
    for &b in s {
        v = (v << 4) | hex_digit(b).ok_or_else(|| bad(field, s))?;
    }
    Ok(v)
}

fn all_hex(s: &[u8]) -> bool {
    s.iter().all(|&b| hex_digit(b).is_some())
}

/// Signed fixed-point field: `+`/`-` then only digits, value = integer / `scale`.
fn parse_fixed(field: &'static str, s: &[u8], scale: f64) -> Result<f32, NdiError> {
    let (sign, digits) = match s.split_first() {
        Some((b'+', d)) => (1i64, d),
        Some((b'-', d)) => (-1i64, d),
        _ => return Err(bad(field, s)),
    };
    if digits.is_empty() || digits.len() > 9 || !digits.iter().all(u8::is_ascii_digit) {
        return Err(bad(field, s));
    }
    let mut v = 0i64;
    for &d in digits {
        v = v * 10 + i64::from(d - b'0');
    }
    Ok(((sign * v) as f64 / scale) as f32)
}

// ---------------------------------------------------------------------------------------------
// ASCII replies
// ---------------------------------------------------------------------------------------------

/// A CRC-valid ASCII reply that is not an error.
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum AsciiReply {
    /// `OKAY`: the command succeeded.
    Okay,
    /// `RESET`: the tracker reset (after a serial break it is back at 9600 8N1).
    Reset,
    /// `WARNING…`: success with a warning (NDI's sample treats it as success); the text after
    /// `WARNING` is kept, usually a 2-hex code.
    Warning(String),
    /// Any other reply text (CRC removed), e.g. the answer to `VER`, `BEEP` or `GETINFO`.
    Data(String),
}

impl AsciiReply {
    /// True for `OKAY` and `WARNING…`.
    pub fn is_success(&self) -> bool {
        matches!(self, AsciiReply::Okay | AsciiReply::Warning(_))
    }

    fn summary(&self) -> String {
        match self {
            AsciiReply::Okay => "OKAY".to_string(),
            AsciiReply::Reset => "RESET".to_string(),
            AsciiReply::Warning(w) => format!("WARNING{}", show(w.as_bytes())),
            AsciiReply::Data(d) => show(d.as_bytes()),
        }
    }
}

/// Checks an ASCII reply frame (`text` + 4 uppercase hex CRC + CR, as [`ReplyReader`] yields
/// it) and returns `text`. The text may hold LF (multi-line replies) and printable ASCII only.
///
/// # Errors
/// [`NdiError::Truncated`] without CR or CRC, [`NdiError::Crc`], or [`NdiError::BadField`] for a
/// malformed CRC or a non-text byte.
pub fn ascii_payload(frame: &[u8]) -> Result<&str, NdiError> {
    let Some((b'\r', body)) = frame.split_last() else {
        return Err(NdiError::Truncated {
            needed: (frame.len() + 1).max(MIN_ASCII_REPLY),
            got: frame.len(),
        });
    };
    if body.len() < 4 {
        return Err(NdiError::Truncated {
            needed: MIN_ASCII_REPLY,
            got: frame.len(),
        });
    }
    let (text, crc_text) = body.split_at(body.len() - 4);
    let expected = parse_hex("reply CRC (4 uppercase hex digits before CR)", crc_text)? as u16;
    let actual = crc16(text);
    if expected != actual {
        return Err(NdiError::Crc {
            scope: CrcScope::AsciiReply,
            expected,
            actual,
        });
    }
    if text
        .iter()
        .any(|&b| !(b == b'\n' || (0x20..=0x7E).contains(&b)))
    {
        return Err(bad(
            "reply text (only printable ASCII and LF expected)",
            text,
        ));
    }
    std::str::from_utf8(text).map_err(|_| bad("reply text", text))
}

fn classify(text: &str) -> Result<AsciiReply, NdiError> {
    if text == "OKAY" {
        return Ok(AsciiReply::Okay);
    }
    if text == "RESET" {
        return Ok(AsciiReply::Reset);
    }
    if let Some(code) = text.strip_prefix("ERROR") {
        if code.len() != 2 {
            return Err(bad("ERROR code (2 hex digits)", text.as_bytes()));
        }
        let code = parse_hex("ERROR code (2 hex digits)", code.as_bytes())? as u8;
        return Err(NdiError::Device {
            code,
            description: error_description(code),
        });
    }
    if let Some(rest) = text.strip_prefix("WARNING") {
        return Ok(AsciiReply::Warning(rest.to_string()));
    }
    Ok(AsciiReply::Data(text.to_string()))
}

/// Parses an ASCII reply frame: `OKAY`, `RESET`, `WARNING…` or data; `ERRORxx` becomes
/// [`NdiError::Device`].
///
/// # Errors
/// As [`ascii_payload`], plus [`NdiError::Device`] for `ERRORxx`.
pub fn parse_ascii_reply(frame: &[u8]) -> Result<AsciiReply, NdiError> {
    classify(ascii_payload(frame)?)
}

/// Text of a data reply; `ERRORxx` and the non-data replies are errors.
fn data_text<'a>(frame: &'a [u8], expected: &'static str) -> Result<&'a str, NdiError> {
    let text = ascii_payload(frame)?;
    match classify(text)? {
        AsciiReply::Data(_) => Ok(text),
        other => Err(NdiError::UnexpectedReply {
            expected,
            got: other.summary(),
        }),
    }
}

/// One entry of a `PHSR` reply: a port handle and its 3-hex-digit status.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub struct PhsrEntry {
    /// Port handle.
    pub handle: u8,
    /// Status bits (12 bits used): see the methods.
    pub status: u16,
}

impl PhsrEntry {
    /// 0x001: a tool is in the port (occupied).
    pub fn occupied(&self) -> bool {
        self.status & 0x001 != 0
    }
    /// 0x002/0x004/0x008: switch 1, 2, 3 on.
    pub fn switches(&self) -> [bool; 3] {
        [
            self.status & 0x002 != 0,
            self.status & 0x004 != 0,
            self.status & 0x008 != 0,
        ]
    }
    /// 0x010: initialised (`PINIT` done).
    pub fn initialized(&self) -> bool {
        self.status & 0x010 != 0
    }
    /// 0x020: enabled (`PENA` done).
    pub fn enabled(&self) -> bool {
        self.status & 0x020 != 0
    }
    /// 0x080: tool sensed through current detection.
    pub fn current_detect(&self) -> bool {
        self.status & 0x080 != 0
    }
}

/// Parses the reply to `PHSR`: 2-hex count, then per handle 2-hex handle and 3-hex status.
///
/// # Errors
/// As [`parse_ascii_reply`]; [`NdiError::UnexpectedReply`] for `OKAY`/`RESET`/`WARNING`;
/// [`NdiError::Layout`] or [`NdiError::BadField`] when the text is not a handle list.
pub fn parse_phsr_reply(frame: &[u8]) -> Result<Vec<PhsrEntry>, NdiError> {
    let t = data_text(frame, "a PHSR reply (handle list)")?.as_bytes();
    if t.len() < 2 {
        return Err(bad("PHSR handle count", t));
    }
    let n = parse_hex("PHSR handle count", &t[..2])? as usize;
    if t.len() != 2 + 5 * n {
        return Err(NdiError::Layout {
            offset: 2,
            detail: format!(
                "PHSR reply announces {n} handles ({} characters) but has {} characters",
                2 + 5 * n,
                t.len()
            ),
        });
    }
    t[2..]
        .chunks_exact(5)
        .map(|c| {
            Ok(PhsrEntry {
                handle: parse_hex("PHSR handle", &c[..2])? as u8,
                status: parse_hex("PHSR handle status", &c[2..])? as u16,
            })
        })
        .collect()
}

// ---------------------------------------------------------------------------------------------
// Tracking data types
// ---------------------------------------------------------------------------------------------

/// Status of one port handle in a `BX`/`TX` reply.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash)]
pub enum HandleStatus {
    /// Transformation present (BX 0x01).
    Valid,
    /// Tool not seen (BX 0x02, TX `MISSING`): port status and frame present, no pose.
    Missing,
    /// Handle not enabled (BX 0x04, TX `DISABLED`): BX carries nothing more.
    Disabled,
    /// TX only (`UNOCCUPIED`): the tool was unplugged.
    Unoccupied,
}

/// Decoded port status (32 bits; BX `u32`, TX 8 hex digits). `raw` is authoritative; the
/// named flags are derived from it by [`PortStatus::from_raw`].
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct PortStatus {
    /// The raw bits.
    pub raw: u32,
    /// 0x0001: occupied / tool in port.
    pub occupied: bool,
    /// 0x0002: switch 1 closed (GPIO line 1 active on Aurora).
    pub switch1_closed: bool,
    /// 0x0004: switch 2 closed (GPIO line 2).
    pub switch2_closed: bool,
    /// 0x0008: switch 3 closed (GPIO line 3).
    pub switch3_closed: bool,
    /// 0x0010: initialised.
    pub initialized: bool,
    /// 0x0020: enabled.
    pub enabled: bool,
    /// 0x0040: out of the characterised volume.
    pub out_of_volume: bool,
    /// 0x0080: partially out of volume.
    pub partially_out_of_volume: bool,
    /// 0x0100: broken sensor (Aurora sensor coil).
    pub sensor_broken: bool,
    /// 0x0200: disturbance detected (IR interference on Polaris).
    pub disturbance_detected: bool,
    /// 0x0400: signal too small.
    pub signal_too_small: bool,
    /// 0x0800: signal too big.
    pub signal_too_big: bool,
    /// 0x1000: processing exception.
    pub processing_exception: bool,
    /// 0x2000: hardware failure.
    pub hardware_failure: bool,
}

impl PortStatus {
    /// Decodes the raw bits (bits 14..31 are kept in `raw` only; their meaning is unverified).
    pub const fn from_raw(raw: u32) -> Self {
        PortStatus {
            raw,
            occupied: raw & 0x0001 != 0,
            switch1_closed: raw & 0x0002 != 0,
            switch2_closed: raw & 0x0004 != 0,
            switch3_closed: raw & 0x0008 != 0,
            initialized: raw & 0x0010 != 0,
            enabled: raw & 0x0020 != 0,
            out_of_volume: raw & 0x0040 != 0,
            partially_out_of_volume: raw & 0x0080 != 0,
            sensor_broken: raw & 0x0100 != 0,
            disturbance_detected: raw & 0x0200 != 0,
            signal_too_small: raw & 0x0400 != 0,
            signal_too_big: raw & 0x0800 != 0,
            processing_exception: raw & 0x1000 != 0,
            hardware_failure: raw & 0x2000 != 0,
        }
    }
}

/// Decoded system status (BX `u16`, TX 4 hex digits). `raw` is authoritative.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Hash, Default)]
pub struct SystemStatus {
    /// The raw bits.
    pub raw: u16,
    /// 0x0001: communication synchronisation error.
    pub comm_sync_error: bool,
    /// 0x0002: too much external infrared / interference.
    pub too_much_interference: bool,
    /// 0x0004: system CRC error.
    pub system_crc_error: bool,
    /// 0x0008: recoverable system processing exception.
    pub recoverable_exception: bool,
    /// 0x0010: hardware failure.
    pub hardware_failure: bool,
    /// 0x0020: hardware configuration changed.
    pub hardware_change: bool,
    /// 0x0040: a port became occupied (re-run PHSR/PINIT/PENA, as PLUS does).
    pub port_occupied: bool,
    /// 0x0080: a port became unoccupied.
    pub port_unoccupied: bool,
}

impl SystemStatus {
    /// Decodes the raw bits.
    pub const fn from_raw(raw: u16) -> Self {
        SystemStatus {
            raw,
            comm_sync_error: raw & 0x0001 != 0,
            too_much_interference: raw & 0x0002 != 0,
            system_crc_error: raw & 0x0004 != 0,
            recoverable_exception: raw & 0x0008 != 0,
            hardware_failure: raw & 0x0010 != 0,
            hardware_change: raw & 0x0020 != 0,
            port_occupied: raw & 0x0040 != 0,
            port_unoccupied: raw & 0x0080 != 0,
        }
    }
}

/// One tool in a `BX`/`TX` reply.
///
/// Pose fields hold data only when `status` is [`HandleStatus::Valid`]; otherwise they are NaN
/// so that a forgotten status check cannot pass for a pose. `port_status` and `frame` are zero
/// when the reply carries none (BX disabled handles; TX `DISABLED`/`UNOCCUPIED` without them).
/// Equality compares the pose fields only when both samples have a pose, so samples without
/// one compare equal despite their NaNs (parsed poses are always finite).
#[derive(Debug, Clone, Copy)]
pub struct ToolSample {
    /// Port handle.
    pub handle: u8,
    /// Handle status.
    pub status: HandleStatus,
    /// Rotation quaternion as NDI gives it: `[q0 (scalar w), qx, qy, qz]`.
    pub quat: [f32; 4],
    /// Translation, millimetres, in the tracker's frame.
    pub translation_mm: [f32; 3],
    /// RMS fit error reported by the tracker, millimetres.
    pub rms_error_mm: f32,
    /// Port status.
    pub port_status: PortStatus,
    /// Camera frame number.
    pub frame: u32,
}

impl PartialEq for ToolSample {
    fn eq(&self, other: &Self) -> bool {
        self.handle == other.handle
            && self.status == other.status
            && self.port_status == other.port_status
            && self.frame == other.frame
            && (!self.has_pose()
                || (self.quat == other.quat
                    && self.translation_mm == other.translation_mm
                    && self.rms_error_mm == other.rms_error_mm))
    }
}

impl ToolSample {
    fn without_pose(handle: u8, status: HandleStatus) -> Self {
        ToolSample {
            handle,
            status,
            quat: [f32::NAN; 4],
            translation_mm: [f32::NAN; 3],
            rms_error_mm: f32::NAN,
            port_status: PortStatus::default(),
            frame: 0,
        }
    }

    /// True when the pose fields hold data.
    pub fn has_pose(&self) -> bool {
        self.status == HandleStatus::Valid
    }

    /// Pose usable for navigation: valid, tool in port, initialised, enabled (the PLUS rule
    /// `(status & 0x31) == 0x31`), and, stricter than PLUS, not out of volume.
    pub fn is_usable(&self) -> bool {
        let p = &self.port_status;
        self.has_pose() && p.occupied && p.initialized && p.enabled && !p.out_of_volume
    }
}

/// A decoded `BX` or `TX` reply.
#[derive(Debug, Clone, PartialEq)]
pub struct TrackingReply {
    /// Tools in reply order.
    pub tools: Vec<ToolSample>,
    /// System status.
    pub system_status: SystemStatus,
}

impl TrackingReply {
    /// The tool with `handle`, if reported.
    pub fn tool(&self, handle: u8) -> Option<&ToolSample> {
        self.tools.iter().find(|t| t.handle == handle)
    }
}

fn check_decode_options(options: u16) -> Result<(), NdiError> {
    let unsupported = options & !reply_options::DECODED;
    if options & reply_options::TRANSFORMS == 0 || unsupported != 0 {
        return Err(NdiError::UnsupportedOption {
            options,
            unsupported,
        });
    }
    Ok(())
}

// ---------------------------------------------------------------------------------------------
// Binary replies (BX)
// ---------------------------------------------------------------------------------------------

/// Checks a binary reply frame (start sequence, header CRC, exact length, body CRC) and returns
/// its body. An ASCII frame in its place (a tracker answers `ERRORxx` to a bad `BX`) gives that
/// error, or [`NdiError::UnexpectedReply`].
///
/// # Errors
/// [`NdiError::Truncated`], [`NdiError::TrailingBytes`], [`NdiError::Crc`] (header or body),
/// [`NdiError::BadField`] for a wrong start sequence, or the ASCII reply's error.
pub fn binary_body(frame: &[u8]) -> Result<&[u8], NdiError> {
    if frame.len() < 2 {
        if frame.first().is_none_or(|&b| b == BINARY_START[0]) {
            return Err(NdiError::Truncated {
                needed: BINARY_HEADER_LEN,
                got: frame.len(),
            });
        }
        return Err(bad("binary start sequence (C4 A5)", frame));
    }
    if frame[..2] != BINARY_START {
        if frame.last() == Some(&b'\r') {
            let reply = parse_ascii_reply(frame)?;
            return Err(NdiError::UnexpectedReply {
                expected: "a binary reply (C4 A5 ...)",
                got: reply.summary(),
            });
        }
        return Err(bad("binary start sequence (C4 A5)", &frame[..2]));
    }
    if frame.len() < BINARY_HEADER_LEN {
        return Err(NdiError::Truncated {
            needed: BINARY_HEADER_LEN,
            got: frame.len(),
        });
    }
    let expected = u16::from_le_bytes([frame[4], frame[5]]);
    let actual = crc16(&frame[..4]);
    if expected != actual {
        return Err(NdiError::Crc {
            scope: CrcScope::BinaryHeader,
            expected,
            actual,
        });
    }
    let len = usize::from(u16::from_le_bytes([frame[2], frame[3]]));
    let total = len + BINARY_OVERHEAD;
    if frame.len() < total {
        return Err(NdiError::Truncated {
            needed: total,
            got: frame.len(),
        });
    }
    if frame.len() > total {
        return Err(NdiError::TrailingBytes {
            expected: total,
            got: frame.len(),
        });
    }
    let body = &frame[BINARY_HEADER_LEN..BINARY_HEADER_LEN + len];
    let expected = u16::from_le_bytes([frame[total - 2], frame[total - 1]]);
    let actual = crc16(body);
    if expected != actual {
        return Err(NdiError::Crc {
            scope: CrcScope::BinaryBody,
            expected,
            actual,
        });
    }
    Ok(body)
}

/// Little-endian reader over a CRC-checked body; running past the end is a layout error.
struct Cursor<'a> {
    buf: &'a [u8],
    pos: usize,
    base: usize,
}

impl<'a> Cursor<'a> {
    fn take(&mut self, n: usize, what: &str) -> Result<&'a [u8], NdiError> {
        match self.pos.checked_add(n).filter(|&end| end <= self.buf.len()) {
            Some(end) => {
                let s = &self.buf[self.pos..end];
                self.pos = end;
                Ok(s)
            }
            None => Err(NdiError::Layout {
                offset: self.base + self.pos,
                detail: format!(
                    "the body ends after {} bytes but {what} needs {n} more; the reply does not \
                     match the option word given to the parser (pass the one sent with BX)",
                    self.buf.len()
                ),
            }),
        }
    }
    fn u8(&mut self, what: &str) -> Result<u8, NdiError> {
        Ok(self.take(1, what)?[0])
    }
    fn u16(&mut self, what: &str) -> Result<u16, NdiError> {
        let b = self.take(2, what)?;
        Ok(u16::from_le_bytes([b[0], b[1]]))
    }
    fn u32(&mut self, what: &str) -> Result<u32, NdiError> {
        let b = self.take(4, what)?;
        Ok(u32::from_le_bytes([b[0], b[1], b[2], b[3]]))
    }
    fn f32(&mut self, what: &str) -> Result<f32, NdiError> {
        Ok(f32::from_bits(self.u32(what)?))
    }
}

/// Parses a `BX` reply frame sent for the option word `options` (0x0001, optionally | 0x0800;
/// other blocks give [`NdiError::UnsupportedOption`]).
///
/// # Errors
/// [`NdiError::UnsupportedOption`], the errors of [`binary_body`], and [`NdiError::Layout`] /
/// [`NdiError::BadField`] when a CRC-valid body does not have the 0x0001 layout (unknown handle
/// status, non-finite transformation, bytes missing or left over).
pub fn parse_bx_reply(frame: &[u8], options: u16) -> Result<TrackingReply, NdiError> {
    check_decode_options(options)?;
    let body = binary_body(frame)?;
    let mut c = Cursor {
        buf: body,
        pos: 0,
        base: BINARY_HEADER_LEN,
    };
    let count = c.u8("the handle count")?;
    let mut tools = Vec::with_capacity(usize::from(count));
    for _ in 0..count {
        let handle = c.u8("a port handle")?;
        let status = match c.u8("a handle status")? {
            0x01 => HandleStatus::Valid,
            0x02 => HandleStatus::Missing,
            0x04 => HandleStatus::Disabled,
            other => {
                return Err(NdiError::BadField {
                    field: "BX handle status (0x01 valid, 0x02 missing, 0x04 disabled)",
                    text: format!("0x{other:02X} for handle 0x{handle:02X}"),
                })
            }
        };
        let mut tool = ToolSample::without_pose(handle, status);
        if status == HandleStatus::Valid {
            let mut v = [0f32; 8];
            for x in &mut v {
                *x = c.f32("a transformation")?;
            }
            if v.iter().any(|x| !x.is_finite()) {
                return Err(NdiError::BadField {
                    field: "BX transformation (non-finite value)",
                    text: format!("handle 0x{handle:02X}: {v:?}"),
                });
            }
            tool.quat = [v[0], v[1], v[2], v[3]];
            tool.translation_mm = [v[4], v[5], v[6]];
            tool.rms_error_mm = v[7];
        }
        if status != HandleStatus::Disabled {
            tool.port_status = PortStatus::from_raw(c.u32("a port status")?);
            tool.frame = c.u32("a frame number")?;
        }
        tools.push(tool);
    }
    let system_status = SystemStatus::from_raw(c.u16("the system status")?);
    if c.pos != body.len() {
        return Err(NdiError::Layout {
            offset: BINARY_HEADER_LEN + c.pos,
            detail: format!(
                "{} unparsed bytes after the system status; the reply carries blocks the option \
                 word given to the parser ({options:04X}) does not announce",
                body.len() - c.pos
            ),
        });
    }
    Ok(TrackingReply {
        tools,
        system_status,
    })
}

// ---------------------------------------------------------------------------------------------
// ASCII tracking replies (TX)
// ---------------------------------------------------------------------------------------------

const TX_QUAT_W: usize = 6;
const TX_TRANS_W: usize = 7;
const TX_ERR_W: usize = 6;
const TX_POSE_W: usize = 4 * TX_QUAT_W + 3 * TX_TRANS_W + TX_ERR_W; // 51
const TX_STATUS_W: usize = 8 + 8; // port status, frame number

/// Port status and frame number at the start of `rest` (8 hex digits each).
fn tx_status(rest: &[u8], handle: u8) -> Result<(PortStatus, u32), NdiError> {
    if rest.len() < TX_STATUS_W {
        return Err(NdiError::BadField {
            field: "TX port status + frame number (16 hex digits)",
            text: format!("{} for handle 0x{handle:02X}", show(rest)),
        });
    }
    let port = parse_hex("TX port status (8 hex digits)", &rest[..8])?;
    let frame = parse_hex("TX frame number (8 hex digits)", &rest[8..16])?;
    Ok((PortStatus::from_raw(port), frame))
}

fn parse_tx_record(rec: &[u8]) -> Result<ToolSample, NdiError> {
    if rec.len() < 2 {
        return Err(bad("TX record", rec));
    }
    let handle = parse_hex("TX port handle", &rec[..2])? as u8;
    let r = &rec[2..];
    // Characters after the known fields of a record are ignored (unknown extra fields).
    if let Some(rest) = r.strip_prefix(b"MISSING") {
        let mut t = ToolSample::without_pose(handle, HandleStatus::Missing);
        (t.port_status, t.frame) = tx_status(rest, handle)?;
        return Ok(t);
    }
    for (word, status) in [
        (&b"DISABLED"[..], HandleStatus::Disabled),
        (&b"UNOCCUPIED"[..], HandleStatus::Unoccupied),
    ] {
        if let Some(rest) = r.strip_prefix(word) {
            let mut t = ToolSample::without_pose(handle, status);
            if rest.len() >= TX_STATUS_W && all_hex(&rest[..TX_STATUS_W]) {
                (t.port_status, t.frame) = tx_status(rest, handle)?;
            }
            return Ok(t);
        }
    }
    if r.len() < TX_POSE_W + TX_STATUS_W {
        return Err(NdiError::BadField {
            field: "TX transformation record (51 characters + 16 hex digits)",
            text: format!("{} for handle 0x{handle:02X}", show(r)),
        });
    }
    let mut t = ToolSample::without_pose(handle, HandleStatus::Valid);
    let mut pos = 0;
    for q in &mut t.quat {
        *q = parse_fixed(
            "TX quaternion component (sign + 5 digits)",
            &r[pos..pos + TX_QUAT_W],
            1e4,
        )?;
        pos += TX_QUAT_W;
    }
    for x in &mut t.translation_mm {
        *x = parse_fixed(
            "TX translation (sign + 6 digits)",
            &r[pos..pos + TX_TRANS_W],
            1e2,
        )?;
        pos += TX_TRANS_W;
    }
    t.rms_error_mm = parse_fixed("TX error (sign + 5 digits)", &r[pos..pos + TX_ERR_W], 1e4)?;
    pos += TX_ERR_W;
    (t.port_status, t.frame) = tx_status(&r[pos..], handle)?;
    Ok(t)
}

/// Parses a `TX` reply frame sent for the option word `options` (0x0001, optionally | 0x0800;
/// other blocks give [`NdiError::UnsupportedOption`]).
///
/// # Errors
/// [`NdiError::UnsupportedOption`], the errors of [`parse_ascii_reply`],
/// [`NdiError::UnexpectedReply`] for `OKAY`/`RESET`/`WARNING`, and [`NdiError::Layout`] /
/// [`NdiError::BadField`] for records or fields not in the documented widths.
pub fn parse_tx_reply(frame: &[u8], options: u16) -> Result<TrackingReply, NdiError> {
    check_decode_options(options)?;
    let t = data_text(frame, "a TX reply (tracking data)")?.as_bytes();
    if t.len() < 2 {
        return Err(bad("TX handle count", t));
    }
    let count = parse_hex("TX handle count", &t[..2])? as usize;
    let mut tools = Vec::with_capacity(count);
    let mut pos = 2;
    for i in 0..count {
        let rest = &t[pos..];
        let lf = rest
            .iter()
            .position(|&b| b == b'\n')
            .ok_or_else(|| NdiError::Layout {
                offset: pos,
                detail: format!(
                    "TX record {} of {count} has no LF terminator (reply text {})",
                    i + 1,
                    show(rest)
                ),
            })?;
        tools.push(parse_tx_record(&rest[..lf])?);
        pos += lf + 1;
    }
    let tail = &t[pos..];
    if tail.len() != 4 {
        return Err(NdiError::Layout {
            offset: pos,
            detail: format!(
                "expected the 4-hex-digit system status after {count} records, found {}",
                show(tail)
            ),
        });
    }
    let system_status = SystemStatus::from_raw(parse_hex("TX system status", tail)? as u16);
    Ok(TrackingReply {
        tools,
        system_status,
    })
}

// ---------------------------------------------------------------------------------------------
// Stream framing
// ---------------------------------------------------------------------------------------------

/// One framed reply, bytes as received (CRCs not yet checked, except the binary header CRC).
#[derive(Debug, Clone, PartialEq, Eq)]
pub enum RawReply {
    /// Printable ASCII/LF text ending in CR; check with [`ascii_payload`] or a `parse_*`.
    Ascii(Vec<u8>),
    /// `C4 A5` + length + valid header CRC + body + body CRC; check with [`binary_body`] or
    /// [`parse_bx_reply`].
    Binary(Vec<u8>),
}

impl RawReply {
    /// The frame bytes.
    pub fn bytes(&self) -> &[u8] {
        match self {
            RawReply::Ascii(b) | RawReply::Binary(b) => b,
        }
    }
}

fn is_ascii_start(b: u8) -> bool {
    (0x21..=0x7E).contains(&b)
}

fn is_ascii_text(b: u8) -> bool {
    b == b'\n' || (0x20..=0x7E).contains(&b)
}

/// Splits a byte stream from the tracker into whole replies.
///
/// Feed it whatever each read returned ([`ReplyReader::push`]); it returns the replies completed
/// by those bytes. An ASCII reply starts with a printable character and runs to CR; a binary
/// reply starts with `C4 A5` and is framed by its length field once its header CRC checks out
/// (never by CR: bodies may contain 0x0D). Anything else is garbage: it is skipped (counted in
/// [`ReplyReader::skipped_bytes`]) until a plausible start. Also skipped: an ASCII run that
/// meets a non-text byte before its CR or outgrows the bound, a binary header with a bad CRC or
/// a length beyond the bound (one byte at a time, so a real reply inside is still found).
///
/// At most [`ReplyReader::max_reply`] bytes are buffered, whatever the chunk sizes or length
/// fields. Printable garbage directly before an ASCII reply cannot be told apart from it; the
/// joined frame then fails its CRC in the parser. After a serial break, call
/// [`ReplyReader::clear`].
#[derive(Debug, Clone)]
pub struct ReplyReader {
    buf: Vec<u8>,
    head: usize,
    scan: usize,
    max_reply: usize,
    skipped: u64,
}

impl Default for ReplyReader {
    fn default() -> Self {
        Self::new()
    }
}

impl ReplyReader {
    /// Smallest accepted bound (bytes).
    pub const MIN_MAX_REPLY: usize = 64;

    /// A reader bounded by [`DEFAULT_MAX_REPLY`] (64 KiB).
    pub fn new() -> Self {
        Self::with_max_reply(DEFAULT_MAX_REPLY)
    }

    /// A reader whose replies (and buffer) are at most `max_reply` bytes (raised to
    /// [`ReplyReader::MIN_MAX_REPLY`]). A binary reply needs `length + 8` bytes.
    pub fn with_max_reply(max_reply: usize) -> Self {
        ReplyReader {
            buf: Vec::new(),
            head: 0,
            scan: 0,
            max_reply: max_reply.max(Self::MIN_MAX_REPLY),
            skipped: 0,
        }
    }

    /// The bound on one reply and on the buffer, bytes.
    pub fn max_reply(&self) -> usize {
        self.max_reply
    }

    /// Bytes skipped as garbage since creation.
    pub fn skipped_bytes(&self) -> u64 {
        self.skipped
    }

    /// Bytes held for an incomplete reply.
    pub fn buffered_len(&self) -> usize {
        self.buf.len() - self.head
    }

    /// Drops any partial reply (not counted as skipped), e.g. after a serial break or reconnect.
    pub fn clear(&mut self) {
        self.buf.clear();
        self.head = 0;
        self.scan = 0;
    }

    /// Adds received bytes; returns the replies they complete, in stream order.
    pub fn push(&mut self, mut data: &[u8]) -> Vec<RawReply> {
        let mut out = Vec::new();
        loop {
            self.compact();
            let take = (self.max_reply - self.buf.len()).min(data.len());
            if take > 0 {
                self.reserve_bounded(take);
                self.buf.extend_from_slice(&data[..take]);
                data = &data[take..];
            }
            self.drain(&mut out);
            if self.buffered_len() >= self.max_reply {
                // Unreachable by construction (drain leaves less than a full buffer); kept as a
                // guard so that a full buffer can never stall the loop.
                let n = self.buffered_len();
                self.skip(n);
            }
            if data.is_empty() {
                break;
            }
        }
        self.compact();
        out
    }

    fn compact(&mut self) {
        if self.head > 0 {
            self.buf.drain(..self.head);
            self.head = 0;
        }
    }

    fn reserve_bounded(&mut self, extra: usize) {
        let need = self.buf.len() + extra;
        if need > self.buf.capacity() {
            let target = (self.buf.capacity() * 2)
                .max(need)
                .max(256)
                .min(self.max_reply);
            self.buf.reserve_exact(target - self.buf.len());
        }
    }

    fn skip(&mut self, n: usize) {
        self.head += n;
        self.skipped = self.skipped.saturating_add(n as u64);
        self.scan = 0;
    }

    fn consume(&mut self, n: usize) {
        self.head += n;
        self.scan = 0;
    }

    fn drain(&mut self, out: &mut Vec<RawReply>) {
        loop {
            let p = &self.buf[self.head..];
            let Some(&b0) = p.first() else { return };
            if b0 == BINARY_START[0] {
                if p.len() < 2 {
                    return;
                }
                if p[1] != BINARY_START[1] {
                    self.skip(1);
                    continue;
                }
                if p.len() < BINARY_HEADER_LEN {
                    return;
                }
                let len = usize::from(u16::from_le_bytes([p[2], p[3]]));
                let header_ok = crc16(&p[..4]) == u16::from_le_bytes([p[4], p[5]]);
                let total = len + BINARY_OVERHEAD;
                if !header_ok || total > self.max_reply {
                    self.skip(1);
                    continue;
                }
                if p.len() < total {
                    return;
                }
                out.push(RawReply::Binary(p[..total].to_vec()));
                self.consume(total);
            } else if is_ascii_start(b0) {
                let from = self.scan.max(1);
                let stop = p[from..]
                    .iter()
                    .position(|&b| b == b'\r' || !is_ascii_text(b));
                match stop.map(|i| (from + i, p[from + i])) {
                    Some((i, b'\r')) => {
                        if i + 1 >= MIN_ASCII_REPLY {
                            out.push(RawReply::Ascii(p[..=i].to_vec()));
                            self.consume(i + 1);
                        } else {
                            self.skip(i + 1);
                        }
                    }
                    Some((i, _)) => self.skip(i),
                    None => {
                        let n = p.len();
                        if n >= self.max_reply {
                            self.skip(n);
                        } else {
                            self.scan = n;
                        }
                        return;
                    }
                }
            } else {
                let n = p
                    .iter()
                    .position(|&b| b == BINARY_START[0] || is_ascii_start(b))
                    .unwrap_or(p.len());
                self.skip(n);
            }
        }
    }
}

// ---------------------------------------------------------------------------------------------
// Tests
// ---------------------------------------------------------------------------------------------

#[cfg(test)]
mod tests {
    use super::*;

    // ---- helpers -----------------------------------------------------------------------------

    fn unhex(s: &str) -> Vec<u8> {
        let s: Vec<u8> = s.bytes().filter(|b| !b.is_ascii_whitespace()).collect();
        s.chunks(2)
            .map(|c| u8::from_str_radix(std::str::from_utf8(c).unwrap(), 16).unwrap())
            .collect()
    }

    /// ASCII reply frame for `text` (test-side encoder).
    fn ascii_frame(text: &str) -> Vec<u8> {
        let mut v = text.as_bytes().to_vec();
        push_hex4(&mut v, crc16(text.as_bytes()));
        v.push(b'\r');
        v
    }

    /// Binary reply frame around `body` (test-side encoder).
    fn bx_frame(body: &[u8]) -> Vec<u8> {
        let mut v = BINARY_START.to_vec();
        v.extend_from_slice(&(body.len() as u16).to_le_bytes());
        let h = crc16(&v);
        v.extend_from_slice(&h.to_le_bytes());
        v.extend_from_slice(body);
        v.extend_from_slice(&crc16(body).to_le_bytes());
        v
    }

    /// Parity-form CRC exactly as ndicapi's CalcCRC16 macro (independent of the table).
    fn crc16_parity(data: &[u8]) -> u16 {
        const ODD: [u16; 16] = [0, 1, 1, 0, 1, 0, 0, 1, 1, 0, 0, 1, 0, 1, 1, 0];
        let mut crc: u16 = 0;
        for &b in data {
            let mut d = (u16::from(b) ^ crc) & 0xFF;
            crc >>= 8;
            if ODD[(d & 0xF) as usize] ^ ODD[(d >> 4) as usize] != 0 {
                crc ^= 0xC001;
            }
            d <<= 6;
            crc ^= d;
            d <<= 1;
            crc ^= d;
        }
        crc
    }

    /// Deterministic pseudo-random numbers for the fuzz loops: the workspace's xorshift
    /// (`rand_xorshift`), seeded.
    struct XorShift(rand_xorshift::XorShiftRng);
    impl XorShift {
        fn new(seed: u64) -> Self {
            Self(rand::SeedableRng::seed_from_u64(seed))
        }
        fn next(&mut self) -> u64 {
            rand::Rng::next_u64(&mut self.0)
        }
        fn below(&mut self, n: usize) -> usize {
            rand::RngExt::random_range(&mut self.0, 0..n.max(1))
        }
        fn byte(&mut self) -> u8 {
            self.next() as u8
        }
    }

    const SPEC_BX: &str =
        "c4a539003f43030a010000803f000000000000000000000000000028410000a2c10080bb\
                           c40000003e31000000341200000b0271000000341200000c040000ab69";
    /// 4 handles: valid in volume, valid out of volume (0x0801), missing + partially out of
    /// volume, disabled; system status 0x0040 (computed with the research Python CRC).
    const BX4: &str = "c4a5630005e30401010000003f0000003f000000bf0000003f0000a03f0000204000007\
                       0c00000803d31000000070000000201000000000000803f00000000000000000000c8c20000\
                       4843000816c50000003f71000000070000000302b100000007000000040440005f62";
    const BX0: &str = "c4a503002de30081006050";
    const SPEC_TX: &str = "020A+10000+00000+00000+00000+001050-002025-150000+01250000000310000123\
                           4\n0BMISSING0000007100001234\n00006938\r";
    const TX5: &str = "0501+05000+05000-05000+05000+000125+000250-000375+00625000000310000ABCD\n\
                       02DISABLED\n03DISABLED000000110000ABCD\n04UNOCCUPIED\n\
                       05MISSING000000B10000ABCD\n0041FF7E\r";
    const SPEC_PHSR: &str = "030A0310B0310C0115662\r";

    fn all_valid_frames() -> Vec<Vec<u8>> {
        vec![
            unhex(SPEC_BX),
            unhex(BX4),
            unhex(BX0),
            SPEC_TX.as_bytes().to_vec(),
            TX5.as_bytes().to_vec(),
            SPEC_PHSR.as_bytes().to_vec(),
            b"OKAYA896\r".to_vec(),
            b"RESETBE6F\r".to_vec(),
            b"ERROR0D8C03\r".to_vec(),
            b"WARNING02C28C\r".to_vec(),
            b"Features.Firmware.Version=007.000.012;3;1;0;12;;Current firmware revision \
              number99A8\r"
                .to_vec(),
        ]
    }

    /// Runs every parser on `bytes`; only checks that nothing panics.
    fn run_all_parsers(bytes: &[u8]) {
        let _ = ascii_payload(bytes);
        let _ = parse_ascii_reply(bytes);
        let _ = parse_phsr_reply(bytes);
        let _ = binary_body(bytes);
        for o in [0x0001, 0x0801, 0x0003, 0] {
            let _ = parse_bx_reply(bytes, o);
            let _ = parse_tx_reply(bytes, o);
        }
    }

    // ---- CRC ---------------------------------------------------------------------------------

    #[test]
    fn crc_spec_vectors() {
        assert_eq!(crc16(b"123456789"), 0xBB3D);
        assert_eq!(crc16(b"INIT:"), 0xE3A5);
        assert_eq!(crc16(b"OKAY"), 0xA896);
        assert_eq!(crc16(b"RESET"), 0xBE6F);
        assert_eq!(crc16(b"GETINFO:Features.Firmware.Version"), 0x0492);
        assert_eq!(
            crc16(
                b"Features.Firmware.Version=007.000.012;3;1;0;12;;Current firmware revision number"
            ),
            0x99A8
        );
        assert_eq!(crc16(b""), 0);
        const AT_COMPILE_TIME: u16 = crc16(b"INIT:");
        assert_eq!(AT_COMPILE_TIME, 0xE3A5);
    }

    #[test]
    fn crc_table_matches_spec_and_parity_form() {
        let first = [
            0x0000, 0xC0C1, 0xC181, 0x0140, 0xC301, 0x03C0, 0x0280, 0xC241, 0xC601, 0x06C0, 0x0780,
            0xC741, 0x0500, 0xC5C1, 0xC481, 0x0440,
        ];
        assert_eq!(CRC16_TABLE[..16], first);
        assert_eq!(CRC16_TABLE[128], 0xA001);
        assert_eq!(CRC16_TABLE[255], 0x4040);
        let mut rng = XorShift::new(0x1234_5678_9ABC_DEF1);
        for _ in 0..500 {
            let data: Vec<u8> = (0..rng.below(64)).map(|_| rng.byte()).collect();
            assert_eq!(crc16(&data), crc16_parity(&data));
            // Reflected CRC, init 0: data followed by its little-endian CRC has CRC 0.
            let mut with = data.clone();
            with.extend_from_slice(&crc16(&data).to_le_bytes());
            assert_eq!(crc16(&with), 0);
            let cut = rng.below(data.len() + 1);
            assert_eq!(
                crc16_update(crc16(&data[..cut]), &data[cut..]),
                crc16(&data)
            );
        }
    }

    // ---- commands ----------------------------------------------------------------------------

    #[test]
    fn every_command_exact_bytes() {
        use Command as C;
        let fast = CommSettings::new_8n1(Baud::B115200);
        let odd = CommSettings {
            baud: Baud::B921600,
            data_bits: DataBits::Seven,
            parity: Parity::Even,
            stop_bits: StopBits::Two,
            handshake: Handshake::RtsCts,
        };
        // Expected bytes: spec B.1 list, the rest computed with the research Python CRC.
        let cases: Vec<(Command, &str)> = vec![
            (C::Init, "INIT:E3A5\r"),
            (C::Comm(CommSettings::POWER_ON), "COMM:000000084\r"),
            (C::Comm(fast), "COMM:500000048\r"),
            (
                C::Comm(CommSettings::new_8n1(Baud::B230400)),
                "COMM:A00000BF8\r",
            ),
            (
                C::Comm(CommSettings::new_8n1(Baud::B1228739)),
                "COMM:70000C031\r",
            ),
            (C::Comm(odd), "COMM:612116C6C\r"),
            (C::Phsr(PhsrFilter::All), "PHSR:0020FF\r"),
            (C::Phsr(PhsrFilter::ToBeFreed), "PHSR:01E03E\r"),
            (C::Phsr(PhsrFilter::NeedInit), "PHSR:02E17E\r"),
            (C::Phsr(PhsrFilter::NeedEnable), "PHSR:0321BF\r"),
            (C::Phsr(PhsrFilter::Enabled), "PHSR:04E3FE\r"),
            (C::Pinit(0x0A), "PINIT:0AD5EB\r"),
            (C::Pinit(0x01), "PINIT:0131EA\r"),
            (
                C::Pena {
                    handle: 0x0A,
                    priority: TrackingPriority::Dynamic,
                },
                "PENA:0ADAD1E\r",
            ),
            (
                C::Pena {
                    handle: 0x0A,
                    priority: TrackingPriority::Static,
                },
                "PENA:0ASA35E\r",
            ),
            (
                C::Pena {
                    handle: 0xFF,
                    priority: TrackingPriority::ButtonBox,
                },
                "PENA:FFB457D\r",
            ),
            (C::Phf(0x0A), "PHF:0A2B0D\r"),
            (C::Phf(0xFF), "PHF:FF896A\r"),
            (C::Tstart, "TSTART:5423\r"),
            (C::Tstop, "TSTOP:2C14\r"),
            (C::Bx(0x0801), "BX:080100EC\r"),
            (C::Bx(0x0001), "BX:0001C26D\r"),
            (C::Bx(0x1000), "BX:1000FEAD\r"),
            (C::Tx(0x0001), "TX:0001031A\r"),
            (C::Tx(0x0801), "TX:0801C19B\r"),
            (C::Beep(1), "BEEP:18404\r"),
            (C::Beep(9), "BEEP:94205\r"),
            (C::Reset, "RESET:034BF\r"),
            (C::Raw("VER:4".into()), "VER:4A6EF\r"),
            (C::Raw("APIREV:".into()), "APIREV:443E\r"),
            (
                C::Raw("PHRQ:*********1****".into()),
                "PHRQ:*********1****A4C1\r",
            ),
            (
                C::Raw("GETINFO:Features.Firmware.Version".into()),
                "GETINFO:Features.Firmware.Version0492\r",
            ),
            (C::Raw("BX2:--6d=tools".into()), "BX2:--6d=tools36F8\r"),
        ];
        for (cmd, want) in cases {
            assert_eq!(
                String::from_utf8(cmd.encode().unwrap()).unwrap(),
                want,
                "{cmd:?}"
            );
            assert_eq!(cmd.payload().unwrap(), &want[..want.len() - 5]);
            assert!(want.starts_with(cmd.name()), "{cmd:?}");
        }
        assert_eq!(Baud::B230400.bits_per_second(), 230_400);
    }

    #[test]
    fn out_of_range_commands_are_refused() {
        use Command as C;
        let bad = vec![
            C::Pinit(0),
            C::Phf(0),
            C::Pena {
                handle: 0,
                priority: TrackingPriority::Dynamic,
            },
            C::Beep(0),
            C::Beep(10),
            C::Bx(0),
            C::Bx(0x0010),
            C::Bx(0x8001),
            C::Tx(0),
            C::Tx(0x0008),
            C::Tx(0x2001),
            C::Raw(String::new()),
            C::Raw("VER 4".into()),
            C::Raw(":4".into()),
            C::Raw("ver:4".into()),
            C::Raw("VER:4\r".into()),
            C::Raw("VER:4\nINIT:".into()),
            C::Raw("VER:\u{e9}".into()),
            C::Raw("V\u{c9}R:4".into()),
            C::Raw("ABCDEFGHIJKLMNOPQ:".into()),
            C::Raw(format!("PVWR:{}", "0".repeat(MAX_COMMAND_TEXT))),
        ];
        for cmd in bad {
            match cmd.encode() {
                Err(e @ NdiError::InvalidArgument { .. }) => assert!(!e.to_string().is_empty()),
                other => panic!("{cmd:?} gave {other:?}"),
            }
        }
        assert!(C::Raw(format!("PVWR:0A0000{}", "0".repeat(128)))
            .encode()
            .is_ok());
    }

    // ---- ASCII replies -----------------------------------------------------------------------

    #[test]
    fn ascii_replies_and_error_mapping() {
        assert_eq!(parse_ascii_reply(b"OKAYA896\r"), Ok(AsciiReply::Okay));
        assert_eq!(parse_ascii_reply(b"RESETBE6F\r"), Ok(AsciiReply::Reset));
        assert_eq!(
            parse_ascii_reply(b"WARNING02C28C\r"),
            Ok(AsciiReply::Warning("02".into()))
        );
        assert!(parse_ascii_reply(b"WARNING02C28C\r").unwrap().is_success());
        let info = b"Features.Firmware.Version=007.000.012;3;1;0;12;;Current firmware revision \
                     number99A8\r";
        assert_eq!(
            parse_ascii_reply(info),
            Ok(AsciiReply::Data(
                "Features.Firmware.Version=007.000.012;3;1;0;12;;Current firmware revision number"
                    .into()
            ))
        );
        let e = parse_ascii_reply(b"ERROR016BC2\r").unwrap_err();
        assert_eq!(
            e,
            NdiError::Device {
                code: 0x01,
                description: "invalid command"
            }
        );
        assert_eq!(e.to_string(), "tracker answered ERROR01: invalid command");
        match parse_ascii_reply(b"ERROR0D8C03\r") {
            Err(NdiError::Device {
                code: 0x0D,
                description,
            }) => {
                assert!(description.contains("no tool assigned"))
            }
            other => panic!("{other:?}"),
        }
        match parse_ascii_reply(b"ERROR2E2CC3\r") {
            Err(NdiError::Device {
                code: 0x2E,
                description,
            }) => {
                assert_eq!(description, "incompatible firmware versions")
            }
            other => panic!("{other:?}"),
        }
        let e = parse_ascii_reply(b"ERRORE03B25\r").unwrap_err();
        assert!(matches!(e, NdiError::Device { code: 0xE0, .. }));
        assert!(e.to_string().contains("ERRORE0") && e.to_string().contains("unknown"));
        for code in 0..=255u8 {
            let e = parse_ascii_reply(&ascii_frame(&format!("ERROR{code:02X}"))).unwrap_err();
            assert_eq!(
                e,
                NdiError::Device {
                    code,
                    description: error_description(code)
                }
            );
        }
        assert!(matches!(
            parse_ascii_reply(&ascii_frame("ERROR1")),
            Err(NdiError::BadField { .. })
        ));
        assert!(matches!(
            parse_ascii_reply(&ascii_frame("ERROR0d")),
            Err(NdiError::BadField { .. })
        ));
        // Multi-line text with LF is fine; empty text is legal framing.
        assert_eq!(
            parse_ascii_reply(&ascii_frame("A\nB")),
            Ok(AsciiReply::Data("A\nB".into()))
        );
        assert_eq!(ascii_payload(b"0000\r"), Ok(""));
    }

    #[test]
    fn ascii_framing_errors() {
        assert_eq!(
            parse_ascii_reply(b"OKAYA897\r"),
            Err(NdiError::Crc {
                scope: CrcScope::AsciiReply,
                expected: 0xA897,
                actual: 0xA896
            })
        );
        assert!(parse_ascii_reply(b"OKAYA897\r")
            .unwrap_err()
            .to_string()
            .contains("CRC"));
        assert!(matches!(
            parse_ascii_reply(b"OKAYa896\r"),
            Err(NdiError::BadField { .. })
        ));
        assert!(matches!(
            parse_ascii_reply(b"OKAYA896"),
            Err(NdiError::Truncated { .. })
        ));
        assert!(matches!(
            parse_ascii_reply(b"A96\r"),
            Err(NdiError::Truncated { .. })
        ));
        assert!(matches!(
            parse_ascii_reply(b""),
            Err(NdiError::Truncated { .. })
        ));
        let with_tab = ascii_frame("OK\tAY");
        assert!(matches!(
            parse_ascii_reply(&with_tab),
            Err(NdiError::BadField { .. })
        ));
        let valid = b"OKAYA896\r";
        for cut in 0..valid.len() {
            assert!(parse_ascii_reply(&valid[..cut]).is_err(), "cut {cut}");
        }
    }

    #[test]
    fn phsr_reply() {
        let v = parse_phsr_reply(SPEC_PHSR.as_bytes()).unwrap();
        assert_eq!(
            v,
            vec![
                PhsrEntry {
                    handle: 0x0A,
                    status: 0x031
                },
                PhsrEntry {
                    handle: 0x0B,
                    status: 0x031
                },
                PhsrEntry {
                    handle: 0x0C,
                    status: 0x011
                },
            ]
        );
        assert!(v[0].occupied() && v[0].initialized() && v[0].enabled());
        assert!(v[2].occupied() && v[2].initialized() && !v[2].enabled());
        assert_eq!(v[0].switches(), [false; 3]);
        assert!(!v[0].current_detect());
        assert_eq!(parse_phsr_reply(&ascii_frame("00")), Ok(vec![]));
        let e = PhsrEntry {
            handle: 1,
            status: 0x08E,
        };
        assert_eq!(e.switches(), [true, true, true]);
        assert!(e.current_detect() && !e.occupied());
        assert!(matches!(
            parse_phsr_reply(&ascii_frame("020A031")),
            Err(NdiError::Layout { .. })
        ));
        assert!(matches!(
            parse_phsr_reply(&ascii_frame("010A0310")),
            Err(NdiError::Layout { .. })
        ));
        assert!(matches!(
            parse_phsr_reply(&ascii_frame("010AX31")),
            Err(NdiError::BadField { .. })
        ));
        assert!(matches!(
            parse_phsr_reply(&ascii_frame("0")),
            Err(NdiError::BadField { .. })
        ));
        assert!(matches!(
            parse_phsr_reply(b"ERROR0D8C03\r"),
            Err(NdiError::Device { code: 0x0D, .. })
        ));
        assert!(matches!(
            parse_phsr_reply(b"OKAYA896\r"),
            Err(NdiError::UnexpectedReply { .. })
        ));
    }

    // ---- BX ------------------------------------------------------------------------------------

    #[test]
    fn bx_spec_vector() {
        let frame = unhex(SPEC_BX);
        assert_eq!(frame.len(), 65);
        let r = parse_bx_reply(&frame, 0x0001).unwrap();
        assert_eq!(r, parse_bx_reply(&frame, 0x0801).unwrap());
        assert_eq!(r.tools.len(), 3);
        assert_eq!(r.system_status, SystemStatus::from_raw(0));
        let a = r.tools[0];
        assert_eq!(a.handle, 0x0A);
        assert_eq!(a.status, HandleStatus::Valid);
        assert_eq!(a.quat, [1.0, 0.0, 0.0, 0.0]);
        assert_eq!(a.translation_mm, [10.5, -20.25, -1500.0]);
        assert_eq!(a.rms_error_mm, 0.125);
        assert_eq!(a.port_status.raw, 0x31);
        assert!(a.port_status.occupied && a.port_status.initialized && a.port_status.enabled);
        assert_eq!(a.frame, 0x1234);
        assert!(a.is_usable());
        let b = r.tool(0x0B).unwrap();
        assert_eq!(b.status, HandleStatus::Missing);
        assert!(b.quat.iter().all(|x| x.is_nan()) && b.rms_error_mm.is_nan());
        assert_eq!(b.port_status.raw, 0x71);
        assert!(b.port_status.out_of_volume);
        assert_eq!(b.frame, 0x1234);
        assert!(!b.is_usable() && !b.has_pose());
        let c = r.tool(0x0C).unwrap();
        assert_eq!(c.status, HandleStatus::Disabled);
        assert_eq!(c.port_status, PortStatus::default());
        assert_eq!(c.frame, 0);
        assert!(r.tool(0x0D).is_none());
        // Samples without a pose compare equal despite their NaN pose fields.
        assert_eq!(r, parse_bx_reply(&frame, 1).unwrap());
        let mut moved = r.clone();
        moved.tools[0].translation_mm[2] += 1.0;
        assert_ne!(r, moved);
    }

    #[test]
    fn bx_valid_missing_disabled_out_of_volume() {
        let r = parse_bx_reply(&unhex(BX4), 0x0801).unwrap();
        assert_eq!(r.tools.len(), 4);
        assert_eq!(r.system_status.raw, 0x0040);
        assert!(r.system_status.port_occupied && !r.system_status.port_unoccupied);
        let t = &r.tools;
        assert_eq!((t[0].handle, t[0].status), (1, HandleStatus::Valid));
        assert_eq!(t[0].quat, [0.5, 0.5, -0.5, 0.5]);
        assert_eq!(t[0].translation_mm, [1.25, 2.5, -3.75]);
        assert_eq!(t[0].rms_error_mm, 0.0625);
        assert_eq!(t[0].frame, 7);
        assert!(t[0].is_usable());
        // Valid but out of volume (reported because of 0x0800): pose present, not usable.
        assert_eq!((t[1].handle, t[1].status), (2, HandleStatus::Valid));
        assert_eq!(t[1].quat, [0.0, 1.0, 0.0, 0.0]);
        assert_eq!(t[1].translation_mm, [-100.0, 200.0, -2400.5]);
        assert!(t[1].port_status.out_of_volume && t[1].has_pose() && !t[1].is_usable());
        // Missing, partially out of volume.
        assert_eq!((t[2].handle, t[2].status), (3, HandleStatus::Missing));
        assert_eq!(t[2].port_status.raw, 0xB1);
        assert!(t[2].port_status.partially_out_of_volume && !t[2].port_status.out_of_volume);
        assert_eq!((t[3].handle, t[3].status), (4, HandleStatus::Disabled));
        let r0 = parse_bx_reply(&unhex(BX0), 0x0001).unwrap();
        assert!(r0.tools.is_empty());
        assert_eq!(r0.system_status.raw, 0x0081);
        assert!(r0.system_status.comm_sync_error && r0.system_status.port_unoccupied);
    }

    #[test]
    fn bx_crc_errors() {
        let good = unhex(SPEC_BX);
        let mut h = good.clone();
        h[4] ^= 0x01;
        assert_eq!(
            parse_bx_reply(&h, 1),
            Err(NdiError::Crc {
                scope: CrcScope::BinaryHeader,
                expected: 0x433E,
                actual: 0x433F
            })
        );
        let mut l = good.clone();
        l[2] = 0x38; // length changed, header CRC no longer matches
        assert!(matches!(
            parse_bx_reply(&l, 1),
            Err(NdiError::Crc {
                scope: CrcScope::BinaryHeader,
                ..
            })
        ));
        let mut b = good.clone();
        b[20] ^= 0x80;
        assert!(matches!(
            parse_bx_reply(&b, 1),
            Err(NdiError::Crc {
                scope: CrcScope::BinaryBody,
                expected: 0x69AB,
                ..
            })
        ));
        let mut c = good.clone();
        let n = c.len();
        c[n - 1] ^= 0xFF;
        assert!(matches!(
            parse_bx_reply(&c, 1),
            Err(NdiError::Crc {
                scope: CrcScope::BinaryBody,
                actual: 0x69AB,
                ..
            })
        ));
    }

    #[test]
    fn bx_truncated_at_every_length_and_trailing() {
        for hex in [SPEC_BX, BX4, BX0] {
            let good = unhex(hex);
            for cut in 0..good.len() {
                match parse_bx_reply(&good[..cut], 0x0801) {
                    Err(NdiError::Truncated { needed, got }) => {
                        assert_eq!(got, cut);
                        assert!(needed > cut && needed <= good.len());
                    }
                    other => panic!("cut {cut}: {other:?}"),
                }
            }
            let mut long = good.clone();
            long.push(0);
            assert_eq!(
                parse_bx_reply(&long, 1),
                Err(NdiError::TrailingBytes {
                    expected: good.len(),
                    got: good.len() + 1
                })
            );
        }
    }

    #[test]
    fn bx_layout_and_option_errors() {
        // ASCII error in place of a binary reply.
        assert!(matches!(
            parse_bx_reply(b"ERROR0D8C03\r", 0x0801),
            Err(NdiError::Device { code: 0x0D, .. })
        ));
        assert!(matches!(
            parse_bx_reply(b"OKAYA896\r", 0x0801),
            Err(NdiError::UnexpectedReply { .. })
        ));
        assert!(matches!(
            parse_bx_reply(b"\x00\x01\x02", 1),
            Err(NdiError::BadField { .. })
        ));
        assert!(matches!(
            parse_bx_reply(b"Z", 1),
            Err(NdiError::BadField { .. })
        ));
        // Unknown handle status with valid CRCs.
        assert!(matches!(
            parse_bx_reply(&bx_frame(&[1, 0x0A, 0x03, 0, 0]), 1),
            Err(NdiError::BadField { .. })
        ));
        // Count says 2 handles, only one present.
        let mut body = vec![2, 0x0B, 0x02];
        body.extend_from_slice(&[0; 8]);
        assert!(matches!(
            parse_bx_reply(&bx_frame(&body), 1),
            Err(NdiError::Layout { .. })
        ));
        // Extra bytes after the system status (e.g. a block the options did not announce).
        assert!(matches!(
            parse_bx_reply(&bx_frame(&[0, 0, 0, 0xAA]), 1),
            Err(NdiError::Layout { offset: 9, .. })
        ));
        assert!(matches!(
            parse_bx_reply(&bx_frame(&[]), 1),
            Err(NdiError::Layout { .. })
        ));
        // Non-finite transformation.
        let mut body = vec![1, 0x0A, 0x01];
        for v in [f32::NAN, 0.0, 0.0, 0.0, 1.0, 2.0, 3.0, 0.1] {
            body.extend_from_slice(&v.to_le_bytes());
        }
        body.extend_from_slice(&[0; 10]);
        assert!(matches!(
            parse_bx_reply(&bx_frame(&body), 1),
            Err(NdiError::BadField { .. })
        ));
        // Options not decoded.
        let good = unhex(SPEC_BX);
        for o in [
            0x0000, 0x0800, 0x0002, 0x0003, 0x0005, 0x0009, 0x1001, 0x0803,
        ] {
            match parse_bx_reply(&good, o) {
                Err(e @ NdiError::UnsupportedOption { .. }) => {
                    assert!(e.to_string().contains("0801"), "{e}")
                }
                other => panic!("{o:04X}: {other:?}"),
            }
            assert!(matches!(
                parse_tx_reply(SPEC_TX.as_bytes(), o),
                Err(NdiError::UnsupportedOption { .. })
            ));
        }
    }

    #[test]
    fn bx_round_trip_random_tools() {
        let mut rng = XorShift::new(77);
        for _ in 0..300 {
            let n = rng.below(12);
            let mut body = vec![n as u8];
            let mut want = Vec::new();
            for i in 0..n {
                let handle = (i + 1) as u8;
                let status = [
                    HandleStatus::Valid,
                    HandleStatus::Missing,
                    HandleStatus::Disabled,
                ][rng.below(3)];
                body.push(handle);
                let mut t = ToolSample::without_pose(handle, status);
                match status {
                    HandleStatus::Valid => body.push(1),
                    HandleStatus::Missing => body.push(2),
                    _ => body.push(4),
                }
                if status == HandleStatus::Valid {
                    let v: Vec<f32> = (0..8)
                        .map(|_| (rng.next() % 2_000_001) as f32 / 1000.0 - 1000.0)
                        .collect();
                    for x in &v {
                        body.extend_from_slice(&x.to_le_bytes());
                    }
                    t.quat = [v[0], v[1], v[2], v[3]];
                    t.translation_mm = [v[4], v[5], v[6]];
                    t.rms_error_mm = v[7];
                }
                if status != HandleStatus::Disabled {
                    let (p, f) = (rng.next() as u32, rng.next() as u32);
                    body.extend_from_slice(&p.to_le_bytes());
                    body.extend_from_slice(&f.to_le_bytes());
                    t.port_status = PortStatus::from_raw(p);
                    t.frame = f;
                }
                want.push(t);
            }
            let sys = rng.next() as u16;
            body.extend_from_slice(&sys.to_le_bytes());
            let got = parse_bx_reply(&bx_frame(&body), 0x0801).unwrap();
            assert_eq!(got.system_status, SystemStatus::from_raw(sys));
            assert_eq!(got.tools, want);
        }
    }

    #[test]
    fn port_status_bits() {
        let names = |p: PortStatus| {
            [
                p.occupied,
                p.switch1_closed,
                p.switch2_closed,
                p.switch3_closed,
                p.initialized,
                p.enabled,
                p.out_of_volume,
                p.partially_out_of_volume,
                p.sensor_broken,
                p.disturbance_detected,
                p.signal_too_small,
                p.signal_too_big,
                p.processing_exception,
                p.hardware_failure,
            ]
        };
        for bit in 0..32 {
            let p = PortStatus::from_raw(1 << bit);
            let set: Vec<usize> = names(p)
                .iter()
                .enumerate()
                .filter(|(_, &b)| b)
                .map(|(i, _)| i)
                .collect();
            if bit < 14 {
                assert_eq!(set, vec![bit]);
            } else {
                assert!(set.is_empty());
                assert_eq!(p.raw, 1 << bit);
            }
        }
        for bit in 0..16 {
            let s = SystemStatus::from_raw(1 << bit);
            let flags = [
                s.comm_sync_error,
                s.too_much_interference,
                s.system_crc_error,
                s.recoverable_exception,
                s.hardware_failure,
                s.hardware_change,
                s.port_occupied,
                s.port_unoccupied,
            ];
            assert_eq!(flags.iter().filter(|&&b| b).count(), usize::from(bit < 8));
            if bit < 8 {
                assert!(flags[bit]);
            }
        }
    }

    // ---- TX ------------------------------------------------------------------------------------

    #[test]
    fn tx_spec_vector() {
        let r = parse_tx_reply(SPEC_TX.as_bytes(), 0x0001).unwrap();
        assert_eq!(r.tools.len(), 2);
        assert_eq!(r.system_status.raw, 0);
        let a = r.tools[0];
        assert_eq!((a.handle, a.status), (0x0A, HandleStatus::Valid));
        assert_eq!(a.quat, [1.0, 0.0, 0.0, 0.0]);
        assert_eq!(a.translation_mm, [10.5, -20.25, -1500.0]);
        assert_eq!(a.rms_error_mm, 0.125);
        assert_eq!((a.port_status.raw, a.frame), (0x31, 0x1234));
        let b = r.tools[1];
        assert_eq!((b.handle, b.status), (0x0B, HandleStatus::Missing));
        assert_eq!((b.port_status.raw, b.frame), (0x71, 0x1234));
        // Same content as the BX spec vector, apart from the disabled handle 0x0C.
        let bx = parse_bx_reply(&unhex(SPEC_BX), 1).unwrap();
        assert_eq!(bx.tools[0], a);
        assert_eq!(
            (bx.tools[1].port_status, bx.tools[1].frame),
            (b.port_status, b.frame)
        );
    }

    #[test]
    fn tx_missing_disabled_unoccupied() {
        let r = parse_tx_reply(TX5.as_bytes(), 0x0801).unwrap();
        assert_eq!(r.system_status.raw, 0x0041);
        let t = &r.tools;
        assert_eq!(t.len(), 5);
        assert_eq!(t[0].quat, [0.5, 0.5, -0.5, 0.5]);
        assert_eq!(t[0].translation_mm, [1.25, 2.5, -3.75]);
        assert_eq!(t[0].rms_error_mm, 0.0625);
        assert_eq!(t[0].frame, 0xABCD);
        assert_eq!(
            (t[1].handle, t[1].status, t[1].port_status.raw, t[1].frame),
            (2, HandleStatus::Disabled, 0, 0)
        );
        assert_eq!(
            (t[2].handle, t[2].status, t[2].port_status.raw, t[2].frame),
            (3, HandleStatus::Disabled, 0x11, 0xABCD)
        );
        assert_eq!((t[3].handle, t[3].status), (4, HandleStatus::Unoccupied));
        assert_eq!(
            (t[4].handle, t[4].status, t[4].port_status.raw),
            (5, HandleStatus::Missing, 0xB1)
        );
        assert!(t[1..].iter().all(|x| !x.has_pose() && x.quat[0].is_nan()));
        // Zero handles.
        let r = parse_tx_reply(b"000000EF5E\r", 1).unwrap();
        assert!(r.tools.is_empty() && r.system_status.raw == 0);
        // Extra trailing characters inside a record are ignored (unknown extra fields).
        let r = parse_tx_reply(&ascii_frame("010AMISSING000000710000000AXYZ\n0000"), 1).unwrap();
        assert_eq!(r.tools[0].frame, 10);
    }

    #[test]
    fn tx_malformed() {
        let cases = [
            "00",                                                                          // no status
            "01",                                 // no record
            "010AMISSING00000071\n0000",          // short
            "010AMISSING0000007100001234\n000",   // status width
            "010AMISSING0000007100001234\n00000", // status width
            "010AMISSING0000007100001234\n000g",  // hex
            "010A+10000+00000+00000+00000+001050-002025-150000+0125000000031000012\n0000", // short
            "010A 10000+00000+00000+00000+001050-002025-150000+01250000000310000123 4\n0000",
            "010A+1000x+00000+00000+00000+001050-002025-150000+012500000003100001234\n0000",
            "010A+10000+00000+00000+00000+001050-002025-150000+01250000000310000123g\n0000",
            "010a+10000+00000+00000+00000+001050-002025-150000+012500000003100001234\n0000",
            "0ZMISSING0000007100001234\n0000",
            "X",
        ];
        for text in cases {
            match parse_tx_reply(&ascii_frame(text), 1) {
                Err(NdiError::BadField { .. } | NdiError::Layout { .. }) => {}
                other => panic!("{text:?}: {other:?}"),
            }
        }
        assert!(matches!(
            parse_tx_reply(b"ERROR0D8C03\r", 1),
            Err(NdiError::Device { code: 0x0D, .. })
        ));
        let good = SPEC_TX.as_bytes();
        for cut in 0..good.len() {
            assert!(parse_tx_reply(&good[..cut], 1).is_err(), "cut {cut}");
        }
        let mut bad_crc = good.to_vec();
        bad_crc[5] = b'9';
        assert!(matches!(
            parse_tx_reply(&bad_crc, 1),
            Err(NdiError::Crc { .. })
        ));
    }

    // ---- ReplyReader ---------------------------------------------------------------------------

    fn stream() -> (Vec<u8>, Vec<RawReply>) {
        let parts = vec![
            RawReply::Ascii(b"OKAYA896\r".to_vec()),
            RawReply::Binary(unhex(SPEC_BX)),
            RawReply::Ascii(SPEC_TX.as_bytes().to_vec()),
            RawReply::Binary(unhex(BX4)),
            RawReply::Ascii(b"ERROR0D8C03\r".to_vec()),
            RawReply::Binary(unhex(BX0)),
            RawReply::Ascii(SPEC_PHSR.as_bytes().to_vec()),
            // Handle 0x0D missing, port status 0x0D, frame 0x0D0D0D0D, system status 0x000D:
            // CR bytes inside a binary body.
            RawReply::Binary(bx_frame(&[
                1, 0x0D, 0x02, 0x0D, 0, 0, 0, 0x0D, 0x0D, 0x0D, 0x0D, 0x0D, 0,
            ])),
        ];
        let bytes = parts.iter().flat_map(|p| p.bytes().to_vec()).collect();
        (bytes, parts)
    }

    #[test]
    fn reader_every_split_point() {
        let (bytes, want) = stream();
        // One binary reply has CR bytes inside its body: framing must use the length field.
        assert!(want
            .iter()
            .any(|f| matches!(f, RawReply::Binary(b) if b[6..].contains(&b'\r'))));
        for a in 0..=bytes.len() {
            let mut r = ReplyReader::new();
            let mut got = r.push(&bytes[..a]);
            got.extend(r.push(&bytes[a..]));
            assert_eq!(got, want, "split at {a}");
            assert_eq!((r.skipped_bytes(), r.buffered_len()), (0, 0));
        }
        for step in [1, 2, 3, 7] {
            let mut r = ReplyReader::new();
            let got: Vec<RawReply> = bytes.chunks(step).flat_map(|c| r.push(c)).collect();
            assert_eq!(got, want, "step {step}");
        }
        // Two split points.
        let mut rng = XorShift::new(99);
        for _ in 0..2000 {
            let mut cuts = [rng.below(bytes.len() + 1), rng.below(bytes.len() + 1)];
            cuts.sort_unstable();
            let mut r = ReplyReader::new();
            let mut got = r.push(&bytes[..cuts[0]]);
            got.extend(r.push(&bytes[cuts[0]..cuts[1]]));
            got.extend(r.push(&bytes[cuts[1]..]));
            assert_eq!(got, want);
        }
        // Every frame parses.
        for f in &want {
            match f {
                RawReply::Binary(b) => assert!(parse_bx_reply(b, 0x0801).is_ok()),
                RawReply::Ascii(a) => assert!(ascii_payload(a).is_ok()),
            }
        }
    }

    #[test]
    fn reader_resynchronises_on_garbage() {
        let (bytes, want) = stream();
        let fake_header = {
            // C4 A5 with a length but a wrong header CRC.
            vec![0xC4, 0xA5, 0x10, 0x00, 0x00, 0x00]
        };
        let huge_header = {
            // Valid header CRC, length 0xFFFF: beyond the 64 KiB bound, so skipped.
            let mut h = vec![0xC4, 0xA5, 0xFF, 0xFF];
            let c = crc16(&h);
            h.extend_from_slice(&c.to_le_bytes());
            h
        };
        let garbages: Vec<Vec<u8>> = vec![
            vec![0x00],
            vec![0xFF; 100],
            vec![b'\r', b'\n', b' ', b'\r'],
            vec![0xC4],
            vec![0xC4, 0x00, 0xC4],
            vec![0xC4, 0xA5, 0xC4],
            fake_header,
            huge_header,
            b"OK\x00".to_vec(),
            b"ab\r".to_vec(),             // shorter than any reply: skipped
            b"\x80partial text".to_vec(), // text cut by the binary start of... nothing: see below
        ];
        for g in garbages {
            let mut input = g.clone();
            // A text run that is not CR-terminated must be ended by a non-text byte.
            if g.last().is_some_and(|&b| is_ascii_text(b)) && g.last() != Some(&b'\r') {
                input.push(0x00);
            }
            let glen = input.len() as u64;
            input.extend_from_slice(&bytes);
            for a in [0, 1, input.len() / 2, input.len()] {
                let mut r = ReplyReader::new();
                let mut got = r.push(&input[..a]);
                got.extend(r.push(&input[a..]));
                assert_eq!(got, want, "garbage {g:02X?} split {a}");
                assert_eq!(r.skipped_bytes(), glen, "garbage {g:02X?}");
            }
        }
        // Garbage between replies as well.
        let mut input = Vec::new();
        for f in &want {
            input.extend_from_slice(&[0xFF, 0x00, 0xC4]);
            input.extend_from_slice(f.bytes());
        }
        let mut r = ReplyReader::new();
        assert_eq!(r.push(&input), want);
        assert_eq!(r.skipped_bytes(), 3 * want.len() as u64);
        // Printable garbage glued to an ASCII reply: one frame that fails its CRC, then in sync.
        let mut r = ReplyReader::new();
        let mut input = b"xyz".to_vec();
        input.extend_from_slice(&bytes);
        let got = r.push(&input);
        assert_eq!(got.len(), want.len());
        assert!(matches!(
            parse_ascii_reply(got[0].bytes()),
            Err(NdiError::Crc { .. })
        ));
        assert_eq!(got[1..], want[1..]);
    }

    #[test]
    fn reader_bounds() {
        // A text line longer than the bound is dropped, the reader recovers.
        let mut r = ReplyReader::with_max_reply(100);
        assert_eq!(r.max_reply(), 100);
        let mut input = vec![b'A'; 1000];
        input.extend_from_slice(b"\x00OKAYA896\r");
        assert_eq!(
            r.push(&input),
            vec![RawReply::Ascii(b"OKAYA896\r".to_vec())]
        );
        assert_eq!(r.skipped_bytes(), 1001);
        assert!(r.buf.capacity() <= 2 * r.max_reply());
        // A binary reply larger than the bound is skipped; smaller ones pass.
        let big = bx_frame(&[0u8; 200]);
        let mut r = ReplyReader::with_max_reply(100);
        let mut input = big.clone();
        input.extend_from_slice(&unhex(BX0));
        let got = r.push(&input);
        assert_eq!(got.last(), Some(&RawReply::Binary(unhex(BX0))));
        assert!(r.skipped_bytes() >= 1);
        let mut r = ReplyReader::with_max_reply(208);
        assert_eq!(r.push(&big), vec![RawReply::Binary(big.clone())]);
        // Minimum bound and clear().
        let mut r = ReplyReader::with_max_reply(0);
        assert_eq!(r.max_reply(), ReplyReader::MIN_MAX_REPLY);
        assert!(r.push(b"OKAY").is_empty());
        assert_eq!(r.buffered_len(), 4);
        r.clear();
        assert_eq!(r.buffered_len(), 0);
        assert_eq!(r.push(b"OKAYA896\r").len(), 1);
        // A huge chunk is processed with the buffer bounded.
        let (bytes, want) = stream();
        let mut input = Vec::new();
        for _ in 0..2000 {
            input.extend_from_slice(&bytes);
        }
        let mut r = ReplyReader::with_max_reply(128);
        let got = r.push(&input);
        assert_eq!(got.len(), 2000 * want.len());
        assert!(r.buf.capacity() <= 256);
        assert_eq!(ReplyReader::default().max_reply(), DEFAULT_MAX_REPLY);
    }

    // ---- fuzz ----------------------------------------------------------------------------------

    fn mutate(rng: &mut XorShift, src: &[u8]) -> Vec<u8> {
        let mut v = src.to_vec();
        for _ in 0..1 + rng.below(3) {
            match rng.below(6) {
                0 if !v.is_empty() => {
                    let i = rng.below(v.len());
                    v[i] ^= 1 << rng.below(8);
                }
                1 if !v.is_empty() => {
                    let i = rng.below(v.len());
                    v[i] = rng.byte();
                }
                2 => {
                    let i = rng.below(v.len() + 1);
                    v.insert(i, rng.byte());
                }
                3 if !v.is_empty() => {
                    let i = rng.below(v.len());
                    v.remove(i);
                }
                4 => v.truncate(rng.below(v.len() + 1)),
                _ => {
                    // Splice a chunk of another frame.
                    let i = rng.below(v.len() + 1);
                    let junk: Vec<u8> = (0..rng.below(16)).map(|_| rng.byte()).collect();
                    v.splice(i..i, junk);
                }
            }
        }
        v
    }

    #[test]
    fn fuzz_never_panics_and_stays_bounded() {
        let mut rng = XorShift::new(0xDEAD_BEEF_CAFE_F00D);
        let valid = all_valid_frames();
        let mut reader = ReplyReader::with_max_reply(512);
        let mut fed = 0usize;
        let mut framed = 0usize;
        // 20,000 random byte strings.
        for _ in 0..20_000 {
            let cap = if rng.below(10) == 0 { 2000 } else { 80 };
            let len = rng.below(cap);
            let mut v: Vec<u8> = (0..len).map(|_| rng.byte()).collect();
            if len > 0 && rng.below(4) == 0 {
                v[0] = 0xC4;
            }
            if len > 1 && rng.below(4) == 0 {
                v[1] = 0xA5;
            }
            run_all_parsers(&v);
            fed += v.len();
            for f in reader.push(&v) {
                framed += f.bytes().len();
                run_all_parsers(f.bytes());
            }
            assert!(reader.buffered_len() < reader.max_reply());
            assert!(reader.buf.capacity() <= 2 * reader.max_reply());
        }
        // 20,000 mutations of valid replies.
        for i in 0..20_000 {
            let src = &valid[i % valid.len()];
            let v = mutate(&mut rng, src);
            run_all_parsers(&v);
            fed += v.len();
            for f in reader.push(&v) {
                framed += f.bytes().len();
                run_all_parsers(f.bytes());
            }
            assert!(reader.buffered_len() < reader.max_reply());
            assert!(reader.buf.capacity() <= 2 * reader.max_reply());
        }
        assert!(framed + reader.buffered_len() + reader.skipped_bytes() as usize == fed);
    }

    #[test]
    fn fuzz_single_byte_substitution_is_always_detected() {
        // CRC-16 catches every burst of at most 16 bits, so no one-byte change of a valid
        // reply may parse as a reply.
        for src in all_valid_frames() {
            for i in 0..src.len() {
                for x in [0x01u8, 0x20, 0x80, 0xFF, 0x5A] {
                    let mut v = src.clone();
                    v[i] ^= x;
                    assert!(ascii_payload(&v).is_err(), "{i} {x:02X} {v:02X?}");
                    assert!(binary_body(&v).is_err(), "{i} {x:02X}");
                }
            }
        }
    }

    #[test]
    fn fuzz_structured_payloads_with_valid_crc() {
        // Bodies with correct CRCs reach the field parsers: they must never panic, and whatever
        // they accept must satisfy the layout invariants.
        let mut rng = XorShift::new(0x0BAD_5EED);
        let alphabet = b"0123456789ABCDEF+-MISSINGDISABLEDUNOCCUPIED\n\n\nERRORWARNINGOKAYx ";
        for _ in 0..20_000 {
            let len = rng.below(120);
            let text: String = (0..len)
                .map(|_| alphabet[rng.below(alphabet.len())] as char)
                .collect();
            let f = ascii_frame(&text);
            run_all_parsers(&f);
            if let Ok(r) = parse_tx_reply(&f, 1) {
                assert!(r.tools.iter().all(|t| t.has_pose() || t.quat[0].is_nan()));
            }
            if let Ok(v) = parse_phsr_reply(&f) {
                assert_eq!(text.len(), 2 + 5 * v.len());
            }
        }
        for _ in 0..20_000 {
            let n = rng.below(4);
            let mut body = vec![n as u8];
            for _ in 0..n {
                body.push(rng.byte());
                body.push([1, 2, 4, rng.byte()][rng.below(4)]);
                let extra = [0, 8, 40][rng.below(3)];
                body.extend((0..extra).map(|_| rng.byte()));
            }
            body.extend((0..rng.below(4)).map(|_| rng.byte()));
            let f = bx_frame(&body);
            run_all_parsers(&f);
            if let Ok(r) = parse_bx_reply(&f, 0x0801) {
                let want: usize = 3 + r
                    .tools
                    .iter()
                    .map(|t| match t.status {
                        HandleStatus::Valid => 42,
                        HandleStatus::Missing => 10,
                        _ => 2,
                    })
                    .sum::<usize>();
                assert_eq!(want, body.len());
            }
        }
    }

    #[test]
    fn error_messages_are_helpful() {
        let msgs = [
            NdiError::Crc {
                scope: CrcScope::BinaryBody,
                expected: 1,
                actual: 2,
            }
            .to_string(),
            NdiError::Truncated { needed: 9, got: 3 }.to_string(),
            NdiError::TrailingBytes {
                expected: 9,
                got: 10,
            }
            .to_string(),
            NdiError::UnsupportedOption {
                options: 0x0800,
                unsupported: 0,
            }
            .to_string(),
            NdiError::UnsupportedOption {
                options: 0x0003,
                unsupported: 2,
            }
            .to_string(),
            NdiError::Layout {
                offset: 3,
                detail: "x".into(),
            }
            .to_string(),
            NdiError::UnexpectedReply {
                expected: "a",
                got: "b".into(),
            }
            .to_string(),
            Command::Beep(0).encode().unwrap_err().to_string(),
        ];
        assert!(msgs[0].contains("0001") && msgs[0].contains("0002") && msgs[0].contains("baud"));
        assert!(msgs[1].contains('9') && msgs[1].contains('3'));
        assert!(msgs[3].contains("0x0001"));
        assert!(msgs[4].contains("0002"));
        assert!(msgs[7].contains("1..=9"));
        let long = show(&[0u8; 100]);
        assert!(long.contains("\\x00") && long.contains("+52 more bytes"));
        let e: Box<dyn std::error::Error> = Box::new(NdiError::Truncated { needed: 1, got: 0 });
        assert!(!e.to_string().is_empty());
    }
}
