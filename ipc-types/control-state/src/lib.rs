//! # control-state: the engine's control state as a stream (seed §8.3)
//!
//! The seed distributes a lung simulation by sending, once per breathing cycle or parameter
//! change, a *control packet object*: the PV boundary values (FRC, TV, pressures), the breathing
//! rate, the PV control constants and what the deformation needs; every site then drives its own
//! lung from it. [`ControlState`] is that packet for this engine: per lung its PV constants per
//! phase (eq. 5.11, EQUATIONS §1), boundary values and timing, the change pending from its next
//! cycle, its share of the volume change, held/base volume, collapse (§4.1) and rigid offset, and
//! its cycle bookkeeping; the source's cycle number and the source clock at the cycle's first
//! tick; the patient's gravity in the body frame (orientation); the disease state; and the events
//! (a trainee's interventions) with their origin site and sequence, each stamped with the cycle and
//! tick at which every site applies it; and the disease cycle the source has prepared and not yet
//! started ([`PendingCycle`]), announced before it starts so every site switches to it at the same
//! source tick as the source, however late the packet that announced it travelled.
//!
//! Version history: v1 had no pending cycle and events without their apply tick and outcome; v2
//! adds them; v3 gives each event the disease course's cycle it shows from as well as the
//! breathing cycle (the two counts a user sees: `lungdyn scene event` and the engine say the
//! course's, frames and states count breaths); v4 adds the patient's breath a source follows from
//! a live respiratory signal ([`LiveBreath`], issue 35), so the sites breathe with the patient too;
//! v5 adds whether that signal looks clipped by its sensor's range ([`LiveBreath::clipped`]), so the
//! sites say so as the source does.
//!
//! ## Encoding
//! [`encode`] writes `magic "LDCS" | version u16 | flags u16 | length u32 | xxh3-64 of the payload |
//! payload` (little-endian), the payload being [`Packet`] in postcard (serde). [`decode`] refuses,
//! each with its own [`DecodeError`]: short input, another magic, an unknown version (named with
//! ours), a length that is not the input's, a payload over [`MAX_PAYLOAD`], a checksum mismatch,
//! bytes postcard cannot read, trailing bytes, and values out of their domain
//! ([`Packet::check`]: non-finite numbers, unknown sides, ...). Nothing is allocated from a length
//! read off the wire beyond a fixed bound: sequences are [`Bounded`] (refused past their capacity,
//! preallocated at most to it) and the payload is at most [`MAX_PAYLOAD`] bytes. Decoding never
//! panics (proptest over random and truncated input).
//!
//! ## On iceoryx2
//! [`ControlStateFrame`] is the fixed-size `Pod` payload the engine publishes the encoded bytes in,
//! so the remote bridge forwards them unchanged (both ends check the checksum).

use bytemuck::{Pod, Zeroable};
use serde::{Deserialize, Serialize};
use thiserror::Error;

/// Magic bytes at the start of every encoded packet.
pub const MAGIC: [u8; 4] = *b"LDCS";
/// Version of the encoding (header and payload); a packet of another version is refused.
pub const FORMAT_VERSION: u16 = 5;
/// Header bytes: magic, version, flags, payload length, checksum.
pub const HEADER_BYTES: usize = 4 + 2 + 2 + 4 + 8;
/// Bytes a [`ControlStateFrame`] carries (the largest encoded packet).
pub const FRAME_BYTES: usize = 4096;
/// Largest payload accepted.
pub const MAX_PAYLOAD: usize = FRAME_BYTES - HEADER_BYTES;
/// Control constants per phase at most (lung-model's `MAX_CONTROL_CONSTANTS`).
pub const MAX_CHI: usize = 15;
/// Lungs per state.
pub const MAX_LUNGS: usize = 2;
/// Events carried in one state (the latest ones; each also travels on its own).
pub const MAX_EVENTS: usize = 8;
/// Samples of a [`LiveBreath`]'s previous breath (evenly over its ticks; a 4 s breath at 60 Hz is
/// one sample every 3.8 ticks, well under the breath's curvature).
pub const LIVE_SAMPLES: usize = 64;
/// Longest breath a [`LiveBreath`] describes, ticks (a minute at 60 Hz; the source describes none
/// longer: a pause that long is an apnoea, which the sites hold at its last volume).
pub const MAX_LIVE_TICKS: u32 = 3600;
/// Largest volume above FRC a [`LiveBreath`] carries, ml (whole patient; an adult's inspiratory
/// capacity is 2–4 l, and a signal's trough may sit below FRC).
pub const MAX_LIVE_ML: f32 = 8000.0;

/// A `Vec` of at most `N` elements: decoding refuses a longer sequence and never preallocates more
/// than `N` whatever length the input claims.
#[derive(Debug, Clone, PartialEq)]
pub struct Bounded<T, const N: usize>(Vec<T>);

impl<T, const N: usize> Default for Bounded<T, N> {
    fn default() -> Self {
        Self(Vec::new())
    }
}

impl<T, const N: usize> Bounded<T, N> {
    /// The elements, or `None` when there are more than `N`.
    pub fn new(items: Vec<T>) -> Option<Self> {
        (items.len() <= N).then_some(Self(items))
    }
    /// The elements.
    pub fn as_slice(&self) -> &[T] {
        &self.0
    }
    /// Add one; false (nothing added) when full.
    pub fn push(&mut self, item: T) -> bool {
        if self.0.len() >= N {
            return false;
        }
        self.0.push(item);
        true
    }
    /// Number of elements.
    pub fn len(&self) -> usize {
        self.0.len()
    }
    /// True when empty.
    pub fn is_empty(&self) -> bool {
        self.0.is_empty()
    }
}

impl<T, const N: usize> core::ops::Deref for Bounded<T, N> {
    type Target = [T];
    fn deref(&self) -> &[T] {
        &self.0
    }
}

impl<T: Serialize, const N: usize> Serialize for Bounded<T, N> {
    fn serialize<S: serde::Serializer>(&self, s: S) -> Result<S::Ok, S::Error> {
        self.0.serialize(s)
    }
}

impl<'de, T: Deserialize<'de>, const N: usize> Deserialize<'de> for Bounded<T, N> {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        struct V<T, const N: usize>(core::marker::PhantomData<T>);
        impl<'de, T: Deserialize<'de>, const N: usize> serde::de::Visitor<'de> for V<T, N> {
            type Value = Bounded<T, N>;
            fn expecting(&self, f: &mut core::fmt::Formatter) -> core::fmt::Result {
                write!(f, "a sequence of at most {N} elements")
            }
            fn visit_seq<A: serde::de::SeqAccess<'de>>(
                self,
                mut a: A,
            ) -> Result<Self::Value, A::Error> {
                let claimed = a.size_hint().unwrap_or(0);
                if claimed > N {
                    return Err(serde::de::Error::invalid_length(claimed, &self));
                }
                let mut v = Vec::with_capacity(claimed);
                while let Some(x) = a.next_element()? {
                    if v.len() == N {
                        return Err(serde::de::Error::invalid_length(N + 1, &self));
                    }
                    v.push(x);
                }
                Ok(Bounded(v))
            }
        }
        d.deserialize_seq(V::<T, N>(core::marker::PhantomData))
    }
}

/// One breathing phase's constants (eq. 5.11 and EQUATIONS §1.1), as lung-model's `PhaseConstants`.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PhaseState {
    /// Control constants `χ_1..χ_N`.
    pub chi: Bounded<f64, MAX_CHI>,
    /// Motor-drive exponent `q`.
    pub q: f64,
    /// Growth constant `c`.
    pub c: f64,
    /// Hysteresis constant `T_ext` (control steps).
    pub t_ext: f64,
    /// Control steps per phase `T`.
    pub t_steps: f64,
    /// Resistance offset `β0`.
    pub beta0: f64,
    /// Resistance slope `β1`.
    pub beta1: f64,
}

/// A lung's PV cycle: both phases, the boundary values (Table 5.2) and the timing.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PvState {
    /// Inhalation constants.
    pub inhale: PhaseState,
    /// Exhalation constants.
    pub exhale: PhaseState,
    /// Functional residual capacity, ml.
    pub frc_ml: f64,
    /// Tidal volume, ml.
    pub tv_ml: f64,
    /// Resting pressure, cmH2O.
    pub rp_cmh2o: f64,
    /// Top pressure ("PR" of the seed's packet), cmH2O.
    pub tp_cmh2o: f64,
    /// Breathing rate ("V" of the seed's packet), breaths per minute.
    pub breaths_per_min: f64,
    /// I of I:E.
    pub ie_inhale: f64,
    /// E of I:E.
    pub ie_exhale: f64,
}

/// The disease state the source runs (what a site shows in words; the lungs' states carry its
/// effect on the breath).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub enum Disease {
    /// Healthy lungs.
    None,
    /// A closed pneumothorax (eq. 8.1–8.9) on `side`.
    ClosedPneumothorax {
        /// 0 right, 1 left.
        side: u8,
    },
    /// A tension pneumothorax's course (eq. 8.10–8.13) on `side`, after `cycles_run` cycles.
    TensionPneumothorax {
        /// 0 right, 1 left.
        side: u8,
        /// Disease cycles run since onset.
        cycles_run: u64,
    },
    /// A tumour (eq. 8.14–8.22) in `side`.
    Tumour {
        /// 0 right, 1 left.
        side: u8,
    },
}

/// One lung's breathing state.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LungState {
    /// 0 right, 1 left.
    pub side: u8,
    /// The PV cycle in force.
    pub pv: PvState,
    /// The PV cycle from this lung's next cycle start, if a change is pending.
    pub next: Option<PvState>,
    /// Share of the volume change above FRC this lung takes.
    pub share: f64,
    /// Held volume (ml) when the lung does not breathe.
    pub held_ml: Option<f64>,
    /// Volume at the start of an inhalation (ml) when not the lung's own FRC volume.
    pub base_ml: Option<f64>,
    /// Collapse towards the hilum, 0..1 (EQUATIONS §4.1).
    pub collapse: f64,
    /// Rigid offset, body frame, mm.
    pub offset_mm: [f64; 3],
    /// Cycles this lung completed.
    pub cycle: u32,
    /// Source tick its current cycle started at.
    pub cycle_start_tick: u64,
}

/// A trainee's or instructor's intervention, with where it came from.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Serialize, Deserialize)]
pub struct RemoteEvent {
    /// Site id of the sender.
    pub origin: u64,
    /// The sender's sequence number (a repeated one is one event).
    pub sequence: u64,
    /// `ipc_types::Intervention` code.
    pub kind: u32,
    /// Lung slot, or `ipc_types::LUNG_AFFECTED`.
    pub lung: u32,
    /// The source's breathing cycle (as [`ControlState::cycle`] counts) from which its effect
    /// shows at every site (0 in a site's request: the source schedules it).
    pub apply_cycle: u64,
    /// The source tick that cycle starts at: every site and the source switch there.
    pub apply_tick: u64,
    /// The same cycle as the disease course counts it (from the onset; what the engine's reply
    /// [`ipc_types::ControlReply::cycle`] and `lungdyn scene event` call the "disease cycle"),
    /// stamped by the source's engine (0 in a site's request).
    pub course_cycle: u64,
    /// What it did, as the source's engine judged it (`ipc_types::OUTCOME_*`; 0 in a site's
    /// request).
    pub outcome: u32,
}

/// One lung's part of a [`PendingCycle`]: what the disease course puts into it at the cycle start
/// (EQUATIONS §4).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PendingLung {
    /// 0 right, 1 left.
    pub side: u8,
    /// The PV cycle it breathes from then (`None`: it keeps its breath, e.g. while held).
    pub pv: Option<PvState>,
    /// Collapse towards the hilum, 0..1.
    pub collapse: f64,
    /// Rigid offset, body frame, mm.
    pub offset_mm: [f64; 3],
    /// Volume at the start of an inhalation, ml.
    pub base_ml: f64,
    /// Held volume (ml) when the lung stops breathing.
    pub held_ml: Option<f64>,
}

/// A disease cycle the source has prepared (the interventions it takes already applied) and that
/// starts at `apply_tick`: sent ahead so every site switches at that tick, as the source does.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct PendingCycle {
    /// The source tick it starts at.
    pub apply_tick: u64,
    /// The source's breathing cycle (as [`ControlState::cycle`]) it starts.
    pub apply_cycle: u64,
    /// The disease course's own cycle number.
    pub course_cycle: u64,
    /// Each lung it changes.
    pub lungs: Bounded<PendingLung, MAX_LUNGS>,
}

/// The patient's breathing, as a source engine follows it from a live respiratory signal
/// (`[breathing] source = "signal"`, issue 35): sent with every state and at once at each of the
/// patient's turns — the start of a breath (an end-expiration) and the start of its expiration (an
/// end-inspiration) — so each site plays the previous breath from the last turn of the breath in
/// progress: from the breath's start, and once the patient's expiration is announced, its
/// expiration from there scaled to start at this breath's peak; then, until the next breath is
/// announced, the previous breath again on the patient's rhythm ([`LiveBreath::volume_on_rhythm`]:
/// a prediction at most a breath ahead; the sites need no sample stream). `None` in a state: the
/// source's model
/// breathes (its signal calibrating, lost or not yet a whole breath), and the lungs' PV states say
/// where, as for any source.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct LiveBreath {
    /// Source tick the patient's breath in progress started at (its end-expiration).
    pub start_tick: u64,
    /// Breaths the source has seen the patient complete while following (each new one a new
    /// number; a site re-aligns when it changes).
    pub breath: u64,
    /// Source tick the breath in progress reached its highest volume and began to expire, with that
    /// volume above FRC, ml (`None` while it inspires).
    pub peak: Option<(u64, f32)>,
    /// Ticks the previous breath lasted (its start to the current breath's start).
    pub last_ticks: u32,
    /// Ticks from the previous breath's start to its highest volume.
    pub last_peak: u32,
    /// The previous breath's whole-patient volume above FRC, ml (each lung takes its share, as of
    /// the model's breath), at [`LIVE_SAMPLES`] or fewer evenly spaced points from its first tick to
    /// its last.
    pub last_ml: Bounded<f32, LIVE_SAMPLES>,
    /// The source's signal looks clipped by its sensor's range (breaths of unequal depth ending at
    /// one value): the breaths may be deeper than drawn, and each site's frames say so too.
    pub clipped: bool,
}

impl LiveBreath {
    fn check(&self) -> Result<(), &'static str> {
        if !(2..=MAX_LIVE_TICKS).contains(&self.last_ticks) {
            return Err("a live breath lasts under 2 ticks or over a minute");
        }
        if self.last_peak >= self.last_ticks {
            return Err("a live breath's peak is not within it");
        }
        if self.last_ml.len() < 2 {
            return Err("a live breath has fewer than 2 samples");
        }
        let volume = |v: f32| v.is_finite() && v.abs() <= MAX_LIVE_ML;
        if !self.last_ml.iter().all(|&v| volume(v)) || !self.peak.is_none_or(|(_, v)| volume(v)) {
            return Err("a live breath's volume is not finite or beyond 8 l above or below FRC");
        }
        if self.peak.is_some_and(|(t, _)| t < self.start_tick) {
            return Err("a live breath's peak is before its start");
        }
        Ok(())
    }

    /// The previous breath's volume at sample position `x` (linear between samples, the last past
    /// the end), and whether it rises there.
    fn sample_at(&self, x: f64) -> (f64, bool) {
        let v = &self.last_ml;
        let n = v.len();
        if n < 2 || x >= (n - 1) as f64 {
            return (v.last().copied().unwrap_or(0.0) as f64, false);
        }
        let x = x.max(0.0);
        let k = x.floor() as usize;
        let (a, b) = (v[k] as f64, v[k + 1] as f64);
        (a + (b - a) * (x - k as f64), b > a)
    }

    /// The volume above FRC a site plays at source tick `tick`, ml, and whether it rises there:
    /// before the breath's peak is announced, the previous breath from the start; after, the
    /// previous breath's expiration from the peak's tick, scaled from this breath's peak to the
    /// previous breath's end; held at the end.
    pub fn volume_at(&self, tick: u64) -> (f64, bool) {
        let n = self.last_ml.len();
        if n < 2 || self.last_ticks < 2 {
            return self.sample_at(0.0);
        }
        let per_tick = (n - 1) as f64 / (self.last_ticks - 1) as f64;
        let peak_x = self.last_peak as f64 * per_tick;
        match self.peak {
            None => self.sample_at(tick.saturating_sub(self.start_tick) as f64 * per_tick),
            Some((at, peak_ml)) => {
                let x = peak_x + tick.saturating_sub(at) as f64 * per_tick;
                let (v, _) = self.sample_at(x);
                let end = self.last_ml[n - 1] as f64;
                let top = self.sample_at(peak_x).0;
                let v = if top - end > 1.0 {
                    end + (v - end) * (peak_ml as f64 - end) / (top - end)
                } else {
                    v
                };
                (v, false)
            }
        }
    }

    /// [`Self::volume_at`] until the breath in progress has played out as the previous breath did
    /// (to the end of its expiration), then the patient's next breath predicted on their rhythm:
    /// the previous breath again from its start, beginning and ending at this one's end — one
    /// breath ahead at most, replaced when the patient's next turn is announced. A site hears a
    /// breath the patient started on rhythm within its usual lag: if none is heard `patience_ticks`
    /// into the predicted breath, the patient has not started one (a longer pause, an apnoea), and
    /// the prediction fades back to the breath's end over [`RHYTHM_FADE_TICKS`] and holds there, as
    /// the source's lungs do. For a site that hears the patient's turns late: [`Self::volume_at`]
    /// holds each breath's end until the next breath's start is heard, so every breath starts that
    /// late there.
    pub fn volume_on_rhythm(&self, tick: u64, patience_ticks: u64) -> (f64, bool) {
        let n = self.last_ml.len();
        if n < 2 || self.last_ticks < 2 {
            return self.volume_at(tick);
        }
        // The tick the breath in progress plays its last sample at (the previous breath's end).
        let end_tick = match self.peak {
            None => self
                .start_tick
                .saturating_add(u64::from(self.last_ticks - 1)),
            Some((at, _)) => at.saturating_add(u64::from(
                (self.last_ticks - 1).saturating_sub(self.last_peak),
            )),
        };
        if tick <= end_tick {
            return self.volume_at(tick);
        }
        let into = tick - end_tick - 1;
        let per_tick = (n - 1) as f64 / (self.last_ticks - 1) as f64;
        let x = into as f64 * per_tick;
        let (first, end) = (self.last_ml[0] as f64, self.last_ml[n - 1] as f64);
        // The previous breath from its start, its own net change (end − first) taken out so the
        // prediction ends where it began: at this breath's end, where the source holds.
        let predicted = |x: f64| {
            end + (self.sample_at(x).0 - first) - (end - first) * (x / (n - 1) as f64).min(1.0)
        };
        let at = predicted(x);
        let rising = predicted(x + per_tick) > at;
        let fade =
            1.0 - (into.saturating_sub(patience_ticks) as f64 / RHYTHM_FADE_TICKS as f64).min(1.0);
        (end + (at - end) * fade, rising && fade == 1.0)
    }
}

/// Ticks over which a site's breath predicted on the patient's rhythm goes back to the previous
/// breath's end when the patient's next breath is not heard in time (200 ms at 60 Hz).
pub const RHYTHM_FADE_TICKS: u64 = 12;

/// The source engine's control state at the start of a breathing cycle (or a change).
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub struct ControlState {
    /// Site id of the source.
    pub source: u64,
    /// The source's session (its start time, ns): a restarted source has another.
    pub epoch: u64,
    /// Packet sequence within the session.
    pub sequence: u64,
    /// Source tick the state holds at (the first lung's cycle start, or the change).
    pub tick: u64,
    /// Engine ticks per second.
    pub tick_hz: f64,
    /// Source clock (ns) at `tick`.
    pub source_time_ns: u64,
    /// Cycles the first lung completed.
    pub cycle: u64,
    /// Gravity in the body frame (the patient's orientation).
    pub gravity_body: [f64; 3],
    /// The disease state.
    pub disease: Disease,
    /// Each simulated lung.
    pub lungs: Bounded<LungState, MAX_LUNGS>,
    /// Events announced with this state (at most [`MAX_EVENTS`]; more wait for the next state,
    /// which the source sends at once).
    pub events: Bounded<RemoteEvent, MAX_EVENTS>,
    /// The disease cycle prepared and not yet started, if any.
    pub pending: Option<PendingCycle>,
    /// The patient's breath the source follows from a live signal (`None`: its model breathes).
    pub live: Option<LiveBreath>,
}

/// Everything that travels between sites.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
pub enum Packet {
    /// The source's state.
    State(ControlState),
    /// An intervention sent by a site to the source.
    Event(RemoteEvent),
    /// A delay probe from `from` to `to`, sent at `t0_ns` (sender's clock).
    Probe {
        /// Sender.
        from: u64,
        /// Addressee.
        to: u64,
        /// Probe number.
        id: u64,
        /// Sender's clock at send.
        t0_ns: u64,
    },
    /// The answer: the probe's fields plus the answerer's clock at receive (`t1`) and send (`t2`).
    ProbeReply {
        /// Answerer.
        from: u64,
        /// The probe's sender.
        to: u64,
        /// Probe number.
        id: u64,
        /// The probe's `t0_ns`.
        t0_ns: u64,
        /// Answerer's clock at receive.
        t1_ns: u64,
        /// Answerer's clock at send.
        t2_ns: u64,
    },
}

/// Why bytes are not a packet.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum DecodeError {
    /// Fewer bytes than a header.
    #[error("a control packet needs at least {HEADER_BYTES} bytes, got {got}")]
    TooShort {
        /// Bytes received.
        got: usize,
    },
    /// Not a control packet.
    #[error("not a lungdyn control packet (magic {found:02x?}, expected \"LDCS\")")]
    BadMagic {
        /// The first four bytes.
        found: [u8; 4],
    },
    /// Another encoding version.
    #[error("control packet format v{theirs} is not understood by this build (v{ours}): run the same lungdyn release at every site")]
    UnknownVersion {
        /// The packet's version.
        theirs: u16,
        /// Ours.
        ours: u16,
    },
    /// The header's length is not what arrived.
    #[error("control packet says {claimed} payload bytes, {actual} arrived")]
    LengthMismatch {
        /// Header's length.
        claimed: usize,
        /// Bytes after the header.
        actual: usize,
    },
    /// Over the bound.
    #[error("control packet payload of {len} bytes exceeds the {MAX_PAYLOAD}-byte limit")]
    TooLong {
        /// Payload bytes.
        len: usize,
    },
    /// Corrupted on the way.
    #[error("control packet checksum mismatch (header {expected:016x}, payload {actual:016x}): corrupted")]
    Checksum {
        /// Header's checksum.
        expected: u64,
        /// The payload's.
        actual: u64,
    },
    /// The payload is not a packet.
    #[error("control packet payload is malformed: {0}")]
    Malformed(String),
    /// A value out of its domain.
    #[error("control packet value out of range: {0}")]
    Invalid(&'static str),
}

/// Why a packet could not be encoded.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum EncodeError {
    /// The packet does not fit the buffer (or [`MAX_PAYLOAD`]).
    #[error("the control packet does not fit {capacity} bytes")]
    TooLarge {
        /// Buffer bytes.
        capacity: usize,
    },
    /// A value out of its domain (the same checks as decoding).
    #[error("refusing to send a control packet with a value out of range: {0}")]
    Invalid(&'static str),
}

fn finite(v: &[f64], what: &'static str) -> Result<(), &'static str> {
    if v.iter().all(|x| x.is_finite()) {
        Ok(())
    } else {
        Err(what)
    }
}

impl PvState {
    fn check(&self) -> Result<(), &'static str> {
        for p in [&self.inhale, &self.exhale] {
            finite(&p.chi, "a control constant chi is not finite")?;
            finite(
                &[p.q, p.c, p.t_ext, p.t_steps, p.beta0, p.beta1],
                "a phase constant (q, c, T_ext, T, beta) is not finite",
            )?;
        }
        finite(
            &[
                self.frc_ml,
                self.tv_ml,
                self.rp_cmh2o,
                self.tp_cmh2o,
                self.breaths_per_min,
                self.ie_inhale,
                self.ie_exhale,
            ],
            "a boundary value or the timing is not finite",
        )?;
        if !(self.frc_ml > 0.0 && self.tv_ml > 0.0 && self.breaths_per_min > 0.0) {
            return Err("FRC, tidal volume and breathing rate must be positive");
        }
        Ok(())
    }
}

fn side(s: u8) -> Result<(), &'static str> {
    if (s as usize) < MAX_LUNGS {
        Ok(())
    } else {
        Err("a lung side is neither right (0) nor left (1)")
    }
}

impl Packet {
    /// Check every value's domain (finite numbers, known sides, distinct lungs, a positive tick
    /// rate). Physical plausibility is the engine's to judge when it builds the breath.
    pub fn check(&self) -> Result<(), &'static str> {
        let Packet::State(s) = self else {
            return Ok(());
        };
        if !(s.tick_hz.is_finite() && s.tick_hz > 0.0 && s.tick_hz <= 100_000.0) {
            return Err("the tick rate is not within 0–100 kHz");
        }
        finite(&s.gravity_body, "gravity is not finite")?;
        match s.disease {
            Disease::None => {}
            Disease::ClosedPneumothorax { side: d }
            | Disease::TensionPneumothorax { side: d, .. }
            | Disease::Tumour { side: d } => side(d)?,
        }
        for (k, l) in s.lungs.iter().enumerate() {
            side(l.side)?;
            if s.lungs[..k].iter().any(|o| o.side == l.side) {
                return Err("the same lung twice");
            }
            l.pv.check()?;
            if let Some(n) = &l.next {
                n.check()?;
            }
            finite(
                &[l.share, l.collapse],
                "a lung's share or collapse is not finite",
            )?;
            finite(&l.offset_mm, "a lung's offset is not finite")?;
            finite(
                &[l.held_ml.unwrap_or(0.0), l.base_ml.unwrap_or(0.0)],
                "a lung's held or base volume is not finite",
            )?;
            if !(0.0..=1.0).contains(&l.collapse) {
                return Err("a lung's collapse is outside 0..1");
            }
        }
        if let Some(p) = &s.pending {
            if p.apply_tick < s.tick {
                return Err("the pending cycle starts before the state's tick");
            }
            for (k, l) in p.lungs.iter().enumerate() {
                side(l.side)?;
                if p.lungs[..k].iter().any(|o| o.side == l.side) {
                    return Err("the same lung twice in the pending cycle");
                }
                if let Some(pv) = &l.pv {
                    pv.check()?;
                }
                finite(
                    &[l.collapse, l.base_ml, l.held_ml.unwrap_or(0.0)],
                    "a pending lung's collapse, base or held volume is not finite",
                )?;
                finite(&l.offset_mm, "a pending lung's offset is not finite")?;
                if !(0.0..=1.0).contains(&l.collapse) {
                    return Err("a pending lung's collapse is outside 0..1");
                }
            }
        }
        if let Some(live) = &s.live {
            live.check()?;
        }
        Ok(())
    }
}

/// Encode `packet` into `out`; the number of bytes written. No allocation.
pub fn encode(packet: &Packet, out: &mut [u8]) -> Result<usize, EncodeError> {
    packet.check().map_err(EncodeError::Invalid)?;
    let capacity = out.len();
    if capacity < HEADER_BYTES {
        return Err(EncodeError::TooLarge { capacity });
    }
    let (head, body) = out.split_at_mut(HEADER_BYTES);
    let room = body.len().min(MAX_PAYLOAD);
    let n = postcard::to_slice(packet, &mut body[..room])
        .map_err(|_| EncodeError::TooLarge { capacity })?
        .len();
    let sum = xxhash_rust::xxh3::xxh3_64(&body[..n]);
    head[0..4].copy_from_slice(&MAGIC);
    head[4..6].copy_from_slice(&FORMAT_VERSION.to_le_bytes());
    head[6..8].copy_from_slice(&0u16.to_le_bytes());
    head[8..12].copy_from_slice(&(n as u32).to_le_bytes());
    head[12..20].copy_from_slice(&sum.to_le_bytes());
    Ok(HEADER_BYTES + n)
}

/// Encode into a new buffer (off the tick: allocates).
pub fn encode_to_vec(packet: &Packet) -> Result<Vec<u8>, EncodeError> {
    let mut buf = vec![0u8; FRAME_BYTES];
    let n = encode(packet, &mut buf)?;
    buf.truncate(n);
    Ok(buf)
}

/// Decode one packet from exactly `bytes`. Never panics; allocates at most what the bounded
/// fields of a [`MAX_PAYLOAD`]-byte payload hold.
pub fn decode(bytes: &[u8]) -> Result<Packet, DecodeError> {
    if bytes.len() < HEADER_BYTES {
        return Err(DecodeError::TooShort { got: bytes.len() });
    }
    let (head, body) = bytes.split_at(HEADER_BYTES);
    let found: [u8; 4] = head[0..4].try_into().unwrap_or_default();
    if found != MAGIC {
        return Err(DecodeError::BadMagic { found });
    }
    let version = u16::from_le_bytes([head[4], head[5]]);
    if version != FORMAT_VERSION {
        return Err(DecodeError::UnknownVersion {
            theirs: version,
            ours: FORMAT_VERSION,
        });
    }
    let claimed = u32::from_le_bytes([head[8], head[9], head[10], head[11]]) as usize;
    if claimed > MAX_PAYLOAD {
        return Err(DecodeError::TooLong { len: claimed });
    }
    if claimed != body.len() {
        return Err(DecodeError::LengthMismatch {
            claimed,
            actual: body.len(),
        });
    }
    let mut sum = [0u8; 8];
    sum.copy_from_slice(&head[12..20]);
    let expected = u64::from_le_bytes(sum);
    let actual = xxhash_rust::xxh3::xxh3_64(body);
    if expected != actual {
        return Err(DecodeError::Checksum { expected, actual });
    }
    let (packet, rest): (Packet, &[u8]) =
        postcard::take_from_bytes(body).map_err(|e| DecodeError::Malformed(e.to_string()))?;
    if !rest.is_empty() {
        return Err(DecodeError::Malformed(format!(
            "{} bytes after the packet",
            rest.len()
        )));
    }
    packet.check().map_err(DecodeError::Invalid)?;
    Ok(packet)
}

/// The encoded control state as the engine publishes it on iceoryx2 (fixed size, `Pod`).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Pod, Zeroable)]
#[repr(C)]
pub struct ControlStateFrame {
    /// `ipc_types::LAYOUT_VERSION` of the publisher.
    pub layout_version: u32,
    /// Bytes of [`Self::bytes`] used.
    pub len: u32,
    /// One encoded [`Packet`] ([`encode`]).
    pub bytes: [u8; FRAME_BYTES],
}

const _: () = assert!(core::mem::size_of::<ControlStateFrame>() == 8 + FRAME_BYTES);

impl Default for ControlStateFrame {
    fn default() -> Self {
        Self {
            layout_version: ipc_types::LAYOUT_VERSION,
            ..Zeroable::zeroed()
        }
    }
}

impl ControlStateFrame {
    /// Encode `packet` into this frame. No allocation.
    pub fn set(&mut self, packet: &Packet) -> Result<(), EncodeError> {
        let n = encode(packet, &mut self.bytes)?;
        self.layout_version = ipc_types::LAYOUT_VERSION;
        self.len = n as u32;
        Ok(())
    }

    /// The encoded bytes (an impossible length from a faulty peer reads as the whole buffer, which
    /// [`decode`] then refuses).
    pub fn encoded(&self) -> &[u8] {
        &self.bytes[..(self.len as usize).min(FRAME_BYTES)]
    }
}

impl ipc_types::Message for ControlStateFrame {
    const NAME: &'static str = "ControlStateFrame";
    const TYPE_NAME: &'static str = "lungdyn.ControlStateFrame.v3";
    fn layout_version(&self) -> u32 {
        self.layout_version
    }
}

#[cfg(test)]
mod tests;
