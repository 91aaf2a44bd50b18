//! Respiratory traces read from files: Varian RPM exports (`.vxp`) and a plain CSV of one
//! signal — what a replayed source plays and `lungdyn breathing check` measures.
//!
//! **`.vxp`** (RPM 1.5 and 1.6; no Varian specification is public — the layout below is what six
//! open readers and a real export agree on: plastimatch's `readrpm.m`, the UKE IPMI group's
//! `read_vxp`, SIRO-RPM-Peak-Correction's `vxp2csv.py` among them). A `[Header]` of `key=value`
//! lines up to `[Data]` (`Data_layout`, `Samples_per_second` — nominal, may be 12.5 —,
//! `Scale_factor`), then one line per sample: `amplitude,phase,timestamp,validflag,ttlin,mark[,ttlout]`
//! with the amplitude in cm (× `Scale_factor` = mm), the timestamp in ms from an arbitrary origin
//! (jittered: the spacing is read, not assumed), `validflag` ≥ 0 valid, −1 the marker block lost
//! (no sample), −2 "non-periodic breathing" (a real position, kept and counted). The raw amplitude
//! *falls* on inspiration (the readers of the UKE group and FL0WNAWAY negate it; on the real export
//! we checked the signal falls for 44 % of the samples and rises for 56 %: the shorter phase is the
//! inspiration), so it is negated here: + = inspiration, as every lungdyn signal. The columns are
//! found through `Data_layout` when present. CRLF line ends are accepted.
//!
//! **CSV**: a header naming a time column (`time_s`, `t_ms`, `time (s)`) and one signal column with
//! its unit (`amplitude_mm`, `amplitude (cm)`, `volume_ml`, `volume_L`, or `amplitude_au` for a
//! device's own unit), optionally `valid` (1/0, true/false). `#` lines are comments.
//!
//! Every file is checked: times strictly increasing and finite (a repeated or all-equal time column
//! is refused: it cannot be replayed at its own rate), no gap over 5 s, a rate of 1–1000 Hz, values
//! finite, at least 10 s of valid signal.

use std::path::Path;

use super::SignalSample;
use crate::input::{read_bounded, ReadLimits};
use crate::units;

/// Longest gap between two samples, s (a loss longer than this is two recordings).
pub const MAX_TRACE_GAP_S: f64 = 5.0;
/// Shortest trace with valid signal, s (two or three breaths).
pub const MIN_TRACE_S: f64 = 10.0;

/// Errors reading a trace: the same as a ventilator recording's (both are tables read within the
/// input limits; a parse error names the line).
pub use crate::recording::RecordingError as TraceError;

/// A trace's format.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum TraceFormat {
    /// Varian RPM export.
    Vxp,
    /// CSV with a time and a signal column.
    Csv,
}

/// The signal's unit as read.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum SignalUnit {
    /// Excursion, mm (a chest marker).
    Mm,
    /// Volume, ml.
    Ml,
    /// A device's own unit.
    Arbitrary,
}

impl SignalUnit {
    /// The unit's symbol.
    pub fn symbol(self) -> &'static str {
        match self {
            SignalUnit::Mm => "mm",
            SignalUnit::Ml => "ml",
            SignalUnit::Arbitrary => "a.u.",
        }
    }
}

/// A trace as read.
#[derive(Debug, Clone, PartialEq)]
pub struct SignalTrace {
    /// Format.
    pub format: TraceFormat,
    /// Unit of the values (after conversion).
    pub unit: SignalUnit,
    /// Samples, times from the file on the replay clock (the first at 1 s), + = inspiration.
    pub samples: Vec<SignalSample>,
    /// The rate the file states (`Samples_per_second`), Hz.
    pub stated_rate_hz: Option<f64>,
    /// The rate its times show (samples over duration), Hz.
    pub rate_hz: f64,
    /// Samples flagged invalid (RPM −1, `valid` 0).
    pub invalid: usize,
    /// Samples RPM flagged non-periodic (−2; kept).
    pub non_periodic: usize,
}

/// Read a trace, by its content: `[Header]` first is RPM, anything else CSV.
pub fn read_trace(path: &Path, limits: ReadLimits) -> Result<SignalTrace, TraceError> {
    let bytes = read_bounded(path, limits)?;
    parse_trace(&bytes).map_err(|(line, message)| TraceError::Parse {
        path: path.to_path_buf(),
        line,
        message,
    })
}

/// Whether bytes look like a respiratory trace this module reads (an RPM header, or a CSV header
/// with a time column and an amplitude or a volume column but no flow).
pub fn looks_like_trace(bytes: &[u8]) -> bool {
    let head = String::from_utf8_lossy(&bytes[..bytes.len().min(4096)]).to_ascii_lowercase();
    let first = head
        .lines()
        .find(|l| !l.trim().is_empty() && !l.starts_with('#'));
    match first {
        Some(l) if l.trim() == "[header]" => true,
        Some(l) => l.contains("amplitude") || (l.contains("vol") && !l.contains("flow")),
        None => false,
    }
}

/// Parse trace bytes; errors carry the 1-based line (0: the file as a whole).
pub fn parse_trace(bytes: &[u8]) -> Result<SignalTrace, (u64, String)> {
    let text = std::str::from_utf8(bytes)
        .map_err(|e| (0, format!("not UTF-8 text ({e}): a trace is a text file")))?;
    let first = text
        .lines()
        .map(str::trim)
        .find(|l| !l.is_empty())
        .unwrap_or("");
    let mut trace = if first.eq_ignore_ascii_case("[header]") {
        parse_vxp(text)?
    } else {
        parse_csv(text)?
    };
    check(&mut trace)?;
    Ok(trace)
}

fn parse_vxp(text: &str) -> Result<SignalTrace, (u64, String)> {
    let mut lines = text
        .lines()
        .enumerate()
        .map(|(i, l)| (i as u64 + 1, l.trim_end_matches('\r')));
    let mut layout: Option<Vec<String>> = None;
    let mut rate = None;
    let mut scale = None;
    let mut data_at = None;
    for (n, line) in lines.by_ref() {
        let line = line.trim();
        if line.eq_ignore_ascii_case("[data]") {
            data_at = Some(n);
            break;
        }
        if line.is_empty() || line.eq_ignore_ascii_case("[header]") {
            continue;
        }
        let Some((key, value)) = line.split_once('=') else {
            return Err((
                n,
                format!("{line:?} is not key=value (an RPM header ends with [Data])"),
            ));
        };
        let number = || -> Result<f64, (u64, String)> {
            value
                .trim()
                .parse::<f64>()
                .ok()
                .filter(|v| v.is_finite() && *v > 0.0)
                .ok_or_else(|| {
                    (
                        n,
                        format!("{}={value:?} is not a positive number", key.trim()),
                    )
                })
        };
        match key.trim().to_ascii_lowercase().as_str() {
            "data_layout" => {
                layout = Some(
                    value
                        .split(',')
                        .map(|c| c.trim().to_ascii_lowercase())
                        .collect(),
                )
            }
            "samples_per_second" => rate = Some(number()?),
            "scale_factor" => scale = Some(number()?),
            _ => {}
        }
    }
    let data_at = data_at.ok_or((0, "no [Data] line: the RPM header never ends".to_string()))?;
    let scale = scale.ok_or((
        data_at,
        "the header has no Scale_factor: the amplitude's unit is unknown (RPM writes 10: cm → mm)"
            .to_string(),
    ))?;
    let col = |name: &str, default: usize| {
        layout
            .as_ref()
            .map_or(Some(default), |l| l.iter().position(|c| c == name))
    };
    let (Some(ia), Some(it), Some(iv)) = (
        col("amplitude", 0),
        col("timestamp", 2),
        col("validflag", 3),
    ) else {
        return Err((
            0,
            "Data_layout names no amplitude, timestamp or validflag column".to_string(),
        ));
    };
    let mut trace = SignalTrace {
        format: TraceFormat::Vxp,
        unit: SignalUnit::Mm,
        samples: Vec::new(),
        stated_rate_hz: rate,
        rate_hz: 0.0,
        invalid: 0,
        non_periodic: 0,
    };
    let mut times_ms: Vec<f64> = Vec::new();
    for (n, line) in lines {
        if line.trim().is_empty() {
            continue;
        }
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        let field = |i: usize, what: &str| -> Result<f64, (u64, String)> {
            let f = fields
                .get(i)
                .ok_or_else(|| (n, format!("{} fields: no {what}", fields.len())))?;
            f.parse::<f64>()
                .map_err(|_| (n, format!("{what} {f:?} is not a number")))
        };
        let amp = field(ia, "amplitude")?;
        let t = field(it, "timestamp")?;
        let flag = field(iv, "validflag")?;
        if !t.is_finite() {
            return Err((n, format!("timestamp {t} is not finite")));
        }
        // −2 is RPM's "non-periodic breathing": the marker block's position is real (a cough, an
        // irregular breath is exactly what should be drawn); −1 (track lost) and below are not.
        let valid = (flag >= 0.0 || flag == -2.0) && amp.is_finite();
        if flag == -2.0 {
            trace.non_periodic += 1;
        }
        if !valid {
            trace.invalid += 1;
        }
        times_ms.push(t);
        trace.samples.push(SignalSample {
            t_ns: 0,
            // cm × Scale_factor = mm; negated: + = inspiration (see the module's description).
            value: -amp * scale,
            valid,
        });
    }
    stamp(&mut trace, &times_ms, 1e-3)?;
    Ok(trace)
}

/// Set the samples' stamps from times in seconds × `to_s`, first sample at 1 s.
fn stamp(trace: &mut SignalTrace, times: &[f64], to_s: f64) -> Result<(), (u64, String)> {
    let Some(&t0) = times.first() else {
        return Err((0, "no sample".to_string()));
    };
    for (i, (&t, s)) in times.iter().zip(trace.samples.iter_mut()).enumerate() {
        let since = (t - t0) * to_s;
        if i > 0 && !(t > times[i - 1]) {
            return Err((
                0,
                format!(
                    "sample {}: time {t} is not after the previous {}: the times must increase \
                     (a repeated or constant time column cannot be replayed at its own rate)",
                    i + 1,
                    times[i - 1]
                ),
            ));
        }
        if i > 0 && (t - times[i - 1]) * to_s > MAX_TRACE_GAP_S {
            return Err((
                0,
                format!(
                    "sample {}: a gap of {:.1} s (over {MAX_TRACE_GAP_S} s): two recordings, or a \
                     time column in the wrong unit",
                    i + 1,
                    (t - times[i - 1]) * to_s
                ),
            ));
        }
        s.t_ns = super::TRACE_START_NS + (since * 1e9).round() as u64;
    }
    Ok(())
}

/// A CSV header's quantity and factor to lungdyn's unit (the units every table reader knows:
/// [`crate::units`]).
fn csv_column(header: &str) -> Option<(&'static str, f64, Option<SignalUnit>)> {
    let name = units::tokens(header).next()?;
    let arbitrary = || {
        let t: Vec<String> = units::tokens(header).collect();
        (t.iter().any(|t| t == "au") || t.windows(2).any(|w| w[0] == "a" && w[1] == "u"))
            .then_some(("signal", 1.0, Some(SignalUnit::Arbitrary)))
    };
    match name.as_str() {
        "time" | "t" => units::time_unit(header).map(|(_, f)| ("time", f, None)),
        "valid" => Some(("valid", 1.0, None)),
        "amplitude" | "signal" | "excursion" | "displacement" => {
            units::header_unit(header, units::LENGTH_UNITS)
                .map(|(_, f)| ("signal", f, Some(SignalUnit::Mm)))
                .or_else(arbitrary)
        }
        "volume" => units::header_unit(header, units::VOLUME_UNITS)
            .map(|(_, f)| ("signal", f, Some(SignalUnit::Ml))),
        _ => None,
    }
}

fn parse_csv(text: &str) -> Result<SignalTrace, (u64, String)> {
    let mut reader = csv::ReaderBuilder::new()
        .flexible(true)
        .trim(csv::Trim::All)
        .comment(Some(b'#'))
        .from_reader(text.as_bytes());
    let headers = reader
        .headers()
        .map_err(|e| (1, format!("cannot read the header row: {e}")))?
        .clone();
    if let [only] = headers.iter().collect::<Vec<_>>()[..] {
        if let Some(sep) = [';', '\t'].into_iter().find(|c| only.contains(*c)) {
            return Err((
                1,
                format!(
                    "one column {only:?}: its columns are separated by {sep:?}, not commas —                      write a comma-separated file with decimal points (time_s,amplitude_mm)"
                ),
            ));
        }
    }
    let (mut time, mut signal, mut valid) = (None, None, None);
    for (i, h) in headers.iter().enumerate() {
        match csv_column(h) {
            Some(("time", f, _)) => {
                if time.is_some() {
                    return Err((1, format!("two time columns (the second: {h:?}): keep one")));
                }
                time = Some((i, f))
            }
            Some(("signal", f, Some(u))) => {
                if signal.is_some() {
                    return Err((
                        1,
                        format!("two signal columns (the second: {h:?}): keep one"),
                    ));
                }
                signal = Some((i, f, u))
            }
            Some(("valid", _, _)) => valid = Some(i),
            _ => {}
        }
    }
    let Some((it, tf)) = time else {
        return Err((
            1,
            format!(
                "no time column with a unit in {:?}: name it time_s or time_ms",
                headers.iter().collect::<Vec<_>>()
            ),
        ));
    };
    let Some((is, sf, unit)) = signal else {
        return Err((
            1,
            format!(
                "no signal column with a unit in {:?}: amplitude_mm, amplitude_cm, amplitude_au, \
                 volume_ml or volume_L (+ = inspiration)",
                headers.iter().collect::<Vec<_>>()
            ),
        ));
    };
    let mut trace = SignalTrace {
        format: TraceFormat::Csv,
        unit,
        samples: Vec::new(),
        stated_rate_hz: None,
        rate_hz: 0.0,
        invalid: 0,
        non_periodic: 0,
    };
    let mut times = Vec::new();
    for row in reader.records() {
        let row = row.map_err(|e| (e.position().map_or(0, |p| p.line()), e.to_string()))?;
        let n = row.position().map_or(0, |p| p.line());
        let num = |i: usize, what: &str| -> Result<f64, (u64, String)> {
            let f = row.get(i).ok_or_else(|| (n, format!("no {what} field")))?;
            f.parse::<f64>().map_err(|_| {
                (
                    n,
                    format!("{what} {f:?} is not a number (a decimal comma?)"),
                )
            })
        };
        let t = num(it, "time")?;
        if !t.is_finite() {
            return Err((n, format!("time {t} is not finite")));
        }
        let v = num(is, "signal")?;
        let ok = match valid.and_then(|i| row.get(i)) {
            None => true,
            Some(f) => match f.to_ascii_lowercase().as_str() {
                "1" | "true" | "yes" => true,
                "0" | "false" | "no" => false,
                other => return Err((n, format!("valid {other:?} is not 1/0 or true/false"))),
            },
        };
        let ok = ok && v.is_finite();
        trace.invalid += usize::from(!ok);
        times.push(t);
        trace.samples.push(SignalSample {
            t_ns: 0,
            value: v * sf,
            valid: ok,
        });
    }
    stamp(&mut trace, &times, tf)?;
    Ok(trace)
}

fn check(trace: &mut SignalTrace) -> Result<(), (u64, String)> {
    let n = trace.samples.len();
    if n < 2 {
        return Err((
            0,
            format!("{n} sample(s): a trace needs at least {MIN_TRACE_S} s"),
        ));
    }
    let span_s = (trace.samples[n - 1].t_ns - trace.samples[0].t_ns) as f64 * 1e-9;
    trace.rate_hz = (n - 1) as f64 / span_s;
    if !(1.0..=1000.0).contains(&trace.rate_hz) {
        return Err((
            0,
            format!(
                "{:.3} samples per second from the times: a respiratory signal is sampled at \
                 1–1000 Hz (a time column in the wrong unit?)",
                trace.rate_hz
            ),
        ));
    }
    let valid = trace.samples.iter().filter(|s| s.valid).count();
    if (valid as f64) < MIN_TRACE_S * trace.rate_hz {
        return Err((
            0,
            format!(
                "{valid} valid samples at {:.1} Hz: under {MIN_TRACE_S} s of signal",
                trace.rate_hz
            ),
        ));
    }
    if let Some(stated) = trace.stated_rate_hz {
        if (stated - trace.rate_hz).abs() > 0.2 * stated {
            return Err((
                0,
                format!(
                    "the header says {stated} samples per second, the timestamps {:.2}: the \
                     timestamps are not in ms, or samples are missing",
                    trace.rate_hz
                ),
            ));
        }
    }
    Ok(())
}
