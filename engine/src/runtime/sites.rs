//! How a remote site follows a source's patient (issue 35): a source engine following a
//! respiratory signal, a site engine fed its control states a network delay late, and a second
//! site fed the same states without the patient's breath (what every site showed before format
//! v4: the model's own breath) — tick by tick, for `lungdyn breathing sites` and the tests.
//! Nothing here is on a real-time path.

use control_state::ControlState;
use ipc_types::{signal_status, EngineFrame, SignalWire, TrackerFrame, MAX_SIGNAL_SAMPLES};
use lung_model::breathing::SignalSample;

use super::remote::{BreathCache, Prepared, RemoteStateError, StateSchedule, StateStamp};
use super::{CoreError, EngineCore};

/// Why [`follow`] stopped.
#[derive(Debug, thiserror::Error)]
pub enum SitesError {
    /// A state could not be applied.
    #[error(transparent)]
    Remote(#[from] RemoteStateError),
    /// A state the source made cannot be sent (a value out of the packet's domain, or too large).
    #[error("the source's control state cannot be sent: {0}")]
    Encode(#[from] control_state::EncodeError),
    /// A disease cycle could not be prepared (as the engine process prepares one after each frame).
    #[error(transparent)]
    Core(#[from] CoreError),
}

/// One tick of a source and its sites: each one's volume above FRC (both lungs, ml) and state bits.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SiteTick {
    /// Seconds from the first tick.
    pub t_s: f64,
    /// The source's lungs.
    pub source_ml: f64,
    /// A site taking the patient's breath.
    pub site_ml: f64,
    /// A site without it (the states stripped of [`ControlState::live`]: the model's breath).
    pub model_site_ml: f64,
    /// The source's [`ipc_types::engine_state`] bits.
    pub source_state: u32,
    /// The site's.
    pub site_state: u32,
}

/// A run of [`follow`]: every tick, and the states the source sent.
#[derive(Debug, Clone)]
pub struct SiteRun {
    /// Per tick.
    pub ticks: Vec<SiteTick>,
    /// The states, in order (decoded from their wire bytes).
    pub states: Vec<ControlState>,
    /// How late the patient's turns reached the site (as `remote join` reports it).
    pub turn_lag: super::remote::TurnLag,
}

/// Run `source` over `ticks` ticks with `frame(tick)` as its input, publishing a control state when
/// the engine's process does ([`StateSchedule`]); `site` gets each state
/// `delay_ticks` after its tick (over the wire: encoded and decoded), and `model_site`, a copy of
/// `site`, gets it without the patient's breath. Both sites follow the source only
/// ([`EngineCore::follow_remote`]). Both engines tick at `tick_hz` (the scene's). After each tick
/// every engine prepares its disease state's next cycle, as the engine process does after each
/// frame (without it a disease scene's course never advanced).
pub fn follow(
    source: EngineCore,
    site: EngineCore,
    frame: &mut dyn FnMut(u64) -> TrackerFrame,
    ticks: u64,
    delay_ticks: u64,
    tick_hz: f64,
) -> Result<SiteRun, SitesError> {
    follow_joining(source, site, frame, ticks, delay_ticks, 0, tick_hz)
}

/// [`follow`] for sites that join at `join_tick`, as `lungdyn remote join` does late: until then
/// they hear nothing (their own model breathes), then the latest state the source sent that has
/// arrived, then every state after it.
pub fn follow_joining(
    mut source: EngineCore,
    site: EngineCore,
    frame: &mut dyn FnMut(u64) -> TrackerFrame,
    ticks: u64,
    delay_ticks: u64,
    join_tick: u64,
    tick_hz: f64,
) -> Result<SiteRun, SitesError> {
    let frc: f64 = source.geometry().map(|g| g.start_volume_ml).sum();
    let (mut site, mut model_site) = (site.clone(), site);
    site.follow_remote();
    model_site.follow_remote();
    let mut cache = BreathCache::default();
    let mut f = [EngineFrame::default(); 3];
    let mut states: Vec<ControlState> = Vec::new();
    let mut schedule = StateSchedule::default();
    let mut next = 0;
    let mut out = Vec::with_capacity(ticks as usize);
    let volume = |f: &EngineFrame| -> f64 {
        f.lungs
            .iter()
            .filter(|l| l.is_active())
            .map(|l| l.volume_ml as f64)
            .sum::<f64>()
            - frc
    };
    for tick in 0..ticks {
        source.step(tick, Some(&frame(tick)), &mut f[0]);
        if schedule.changed(&source) {
            let stamp = StateStamp {
                source: 1,
                epoch: 1,
                sequence: states.len() as u64,
                tick_hz,
                source_time_ns: (tick as f64 * 1e9 / tick_hz) as u64,
            };
            let s = source.control_state(tick, stamp, &[])?;
            let p = control_state::Packet::State(s);
            let wire = control_state::encode_to_vec(&p)?;
            if let Ok(control_state::Packet::State(s)) = control_state::decode(&wire) {
                states.push(s);
            }
        }
        if tick == join_tick {
            // A late joiner hears the latest state that has arrived, not the ones before it.
            let arrived = states
                .iter()
                .filter(|s| s.tick + delay_ticks <= tick)
                .count();
            next = next.max(arrived.saturating_sub(1));
        }
        // Until it joins, a site hears nothing (its own model breathes).
        while tick >= join_tick && next < states.len() && states[next].tick + delay_ticks <= tick {
            let s = states[next].clone();
            let mut stripped = s.clone();
            stripped.live = None;
            site.apply_prepared(Prepared::of(s, &mut cache)?, tick_hz)?;
            model_site.apply_prepared(Prepared::of(stripped, &mut cache)?, tick_hz)?;
            next += 1;
        }
        site.step(tick, None, &mut f[1]);
        model_site.step(tick, None, &mut f[2]);
        for e in [&mut source, &mut site, &mut model_site] {
            e.prepare_ahead()?;
        }
        out.push(SiteTick {
            t_s: tick as f64 / tick_hz,
            source_ml: volume(&f[0]),
            site_ml: volume(&f[1]),
            model_site_ml: volume(&f[2]),
            source_state: f[0].state,
            site_state: f[1].state,
        });
    }
    Ok(SiteRun {
        ticks: out,
        states,
        turn_lag: site.patient_turn_lag(),
    })
}

/// Replays `samples` (times from their first, ns) as a tracker bridge does: each tick's frame
/// carries the samples whose time fell since the previous tick's (at most
/// [`MAX_SIGNAL_SAMPLES`]; more wait for the next frame), never one ahead of its own time.
#[derive(Debug, Clone)]
pub struct SignalReplay<'a> {
    samples: &'a [SignalSample],
    next: usize,
    unit: u32,
    period_ns: u64,
    tick_ns: f64,
    /// The host clock at the first tick, ns (the recording's first sample falls there).
    t0_ns: u64,
}

impl<'a> SignalReplay<'a> {
    /// `samples` in `unit` ([`ipc_types::signal_unit`]) at `period_ns`, ticked at `tick_hz`.
    pub fn new(samples: &'a [SignalSample], unit: u32, period_ns: u64, tick_hz: f64) -> Self {
        Self {
            samples,
            next: 0,
            unit,
            period_ns,
            tick_ns: 1e9 / tick_hz,
            t0_ns: 1_000_000_000,
        }
    }

    /// The frame of `tick` (ticks in order).
    pub fn frame(&mut self, tick: u64) -> TrackerFrame {
        let now = self.t0_ns + (tick as f64 * self.tick_ns) as u64;
        let first = self.samples.first().map_or(0, |s| s.t_ns);
        let mut f = TrackerFrame {
            frame_number: tick,
            ..TrackerFrame::default()
        };
        f.stamps.capture_ns = now;
        f.stamps.bridge_publish_ns = now;
        f.signal.status = signal_status::CONFIGURED;
        f.signal.unit = self.unit;
        f.signal.period_ns = self.period_ns;
        f.signal.origin_ns = self.t0_ns;
        while let Some(s) = self.samples.get(self.next) {
            let t = self.t0_ns + (s.t_ns - first);
            if t > now || f.signal.count as usize == MAX_SIGNAL_SAMPLES {
                break;
            }
            let i = f.signal.count as usize;
            let valid = s.valid && s.value.is_finite();
            f.signal.samples[i] = SignalWire {
                t_ns: t,
                value: if valid { s.value } else { 0.0 },
            };
            if valid {
                f.signal.valid_mask |= 1 << i;
            }
            f.signal.count += 1;
            self.next += 1;
        }
        if self.next == self.samples.len() {
            f.signal.status |= signal_status::ENDED;
        }
        f
    }
}

/// What a [`SiteRun`] shows over the ticks the source's signal drove (from `from_s` on).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct SiteFigures {
    /// Ticks the source's lungs followed the signal.
    pub ticks: usize,
    /// Of those, the site breathing with the patient (the rest: its model, before the first whole
    /// breath reached it, or between the source's losses).
    pub site_following: usize,
    /// RMS of the site's volume against the source's over the ticks both followed the patient, ml.
    pub rms_ml: f64,
    /// The same ticks for a site without the patient's breath (the model's), ml.
    pub model_rms_ml: f64,
    /// RMS of the site's volume against the source's over every tick the source followed (the
    /// site's model before its first whole breath included), ml.
    pub rms_all_ml: f64,
    /// The shift of the site's breath against the source's that fits best over the ticks both
    /// followed (least RMS within ±1 s), ms, positive when the site is late (NaN when the site
    /// never followed).
    pub lag_ms: f64,
    /// The largest change of the site's volume from one tick to the next, ml.
    pub largest_step_ml: f64,
    /// The source's.
    pub source_largest_step_ml: f64,
}

/// [`SiteFigures`] of `run` over its ticks from `from_s` on at `tick_hz`.
pub fn figures(run: &SiteRun, from_s: f64, tick_hz: f64) -> SiteFigures {
    use ipc_types::engine_state::SIGNAL_FOLLOWING;
    let t = &run.ticks;
    let source: Vec<usize> = (0..t.len())
        .filter(|&k| t[k].t_s >= from_s && t[k].source_state & SIGNAL_FOLLOWING != 0)
        .collect();
    let both: Vec<usize> = source
        .iter()
        .copied()
        .filter(|&k| t[k].site_state & SIGNAL_FOLLOWING != 0)
        .collect();
    let rms = |over: &[usize], f: &dyn Fn(usize) -> f64| -> f64 {
        if over.is_empty() {
            return f64::NAN;
        }
        (over.iter().map(|&k| f(k).powi(2)).sum::<f64>() / over.len() as f64).sqrt()
    };
    let reach = tick_hz.round() as i64;
    let mut best = (f64::INFINITY, 0i64);
    for shift in -reach..=reach {
        let e = rms(&both, &|k| {
            let j = (k as i64 - shift).clamp(0, t.len() as i64 - 1) as usize;
            t[k].site_ml - t[j].source_ml
        });
        if e < best.0 {
            best = (e, shift);
        }
    }
    let step = |f: &dyn Fn(&SiteTick) -> f64| -> f64 {
        source
            .iter()
            .filter(|&&k| k > 0)
            .map(|&k| (f(&t[k]) - f(&t[k - 1])).abs())
            .fold(0.0, f64::max)
    };
    SiteFigures {
        ticks: source.len(),
        site_following: both.len(),
        rms_ml: rms(&both, &|k| t[k].site_ml - t[k].source_ml),
        model_rms_ml: rms(&both, &|k| t[k].model_site_ml - t[k].source_ml),
        rms_all_ml: rms(&source, &|k| t[k].site_ml - t[k].source_ml),
        // No lag without a tick to fit it on (NaN: `null` in a report's JSON, not 0 ms).
        lag_ms: if both.is_empty() {
            f64::NAN
        } else {
            best.1 as f64 * 1e3 / tick_hz
        },
        largest_step_ml: step(&|x| x.site_ml),
        source_largest_step_ml: step(&|x| x.source_ml),
    }
}
