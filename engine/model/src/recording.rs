//! Ventilator recordings: reading them, cutting them into breaths and integrating each breath's
//! volume (the input of `lungdyn pv recording` and of waveform-driven scenes).
//!
//! Two formats are read:
//! * a generic CSV with a header row naming each column *with its unit*: time (`time_s`, `t_ms`),
//!   flow (`flow_L/min`, `flow (L/s)`, `flow_ml_s`, + = inspiration) and airway pressure
//!   (`paw_cmH2O`, `pressure (kPa)`, `Paw mbar`); optionally volume (`volume_ml`) and oesophageal
//!   pressure (`pes_cmH2O`). A column whose unit is not recognised is refused: a flow in L/s read as
//!   L/min is a tidal volume 60 times too small.
//! * the Puritan-Bennett 840 raw export: optional time-stamp lines, then per ventilator breath a line
//!   `BS, S:<breath number>,`, one line `flow, pressure` per sample (L/min, cmH2O, 50 Hz) and `BE`.
//!
//! Breaths are cut at flow crossings with hysteresis and minimum durations ([`segment`]): an
//! inspiration starts where the flow rises above `+threshold` and stays above it on average for the
//! minimum inspiration time; it ends where the flow falls below `−threshold` and stays below it on
//! average for the minimum expiration time. Each start and end is moved back to where the flow
//! left the noise band (a quarter of the threshold) before it. Volume is the trapezoidal integral of flow from each breath's start, drift-corrected
//! per breath ([`breath_volume`]): the net volume at the breath's end (leak, sensor offset, bias flow)
//! is removed linearly over the breath, so every breath starts and ends at 0 ml.

use std::path::{Path, PathBuf};

pub mod checks;
pub mod classify;

use crate::input::{read_bounded, InputError, ReadLimits};
use crate::plausible::{FLOW_LPS, PRESSURE_CMH2O};
use crate::units::{flow_unit, header_unit, time_unit, PRESSURE_UNITS, VOLUME_UNITS};

/// Sample interval of the Puritan-Bennett 840 raw export, s (50 Hz).
pub const PB840_SAMPLE_S: f64 = 0.02;

/// Largest gap between two samples, s: a longer one is a recording stitched together (or a time
/// column in the wrong unit), across which flow cannot be integrated.
pub const MAX_SAMPLE_GAP_S: f64 = 1.0;

/// Errors reading a recording.
#[derive(Debug, thiserror::Error)]
pub enum RecordingError {
    /// The file could not be read within the limits.
    #[error(transparent)]
    Input(#[from] InputError),
    /// Malformed or implausible content (line 0: the file as a whole).
    #[error("{}{}: {message}", path.display(), if *line > 0 { format!(": line {line}") } else { String::new() })]
    Parse {
        /// Path.
        path: PathBuf,
        /// 1-based line.
        line: u64,
        /// What is wrong.
        message: String,
    },
}

/// The format a recording was read in.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
#[serde(rename_all = "snake_case")]
pub enum Format {
    /// A CSV with a header naming columns and units.
    GenericCsv,
    /// The Puritan-Bennett 840 raw export (`BS` … `BE`).
    Pb840,
}

impl Format {
    /// Human-readable name.
    pub fn describe(self) -> &'static str {
        match self {
            Format::GenericCsv => "CSV with named columns",
            Format::Pb840 => {
                "Puritan-Bennett 840 raw export (BS/BE, flow L/min, pressure cmH2O, 50 Hz)"
            }
        }
    }
}

/// One column read and the unit it was converted from.
#[derive(Debug, Clone, PartialEq, serde::Serialize)]
pub struct ColumnNote {
    /// "time", "flow", "pressure", "volume" or "oesophageal pressure".
    pub quantity: &'static str,
    /// The column's header (or the format's field).
    pub column: String,
    /// The unit recognised.
    pub unit: &'static str,
    /// Factor to lungdyn's unit (s, L/s, cmH2O, ml).
    pub factor: f64,
}

/// A recording in lungdyn's units.
#[derive(Debug, Clone, PartialEq)]
pub struct Recording {
    /// Format read.
    pub format: Format,
    /// Sample times, s, strictly increasing.
    pub t_s: Vec<f64>,
    /// Flow at the airway opening, L/s, + = inspiration.
    pub flow_lps: Vec<f64>,
    /// Airway pressure, cmH2O.
    pub paw_cmh2o: Vec<f64>,
    /// A recorded volume column, ml (the analysis integrates flow; this is reported beside it).
    pub volume_ml: Option<Vec<f64>>,
    /// Oesophageal pressure, cmH2O.
    pub pes_cmh2o: Option<Vec<f64>>,
    /// Columns and units read.
    pub columns: Vec<ColumnNote>,
    /// PB-840: the first sample index and the ventilator's number of each breath (`BS, S:<n>`).
    pub vent_breaths: Vec<(usize, u64)>,
}

/// Read a recording within `limits` (the table limits: [`ReadLimits::TABLE`]).
pub fn read_recording(path: &Path, limits: ReadLimits) -> Result<Recording, RecordingError> {
    let bytes = read_bounded(path, limits)?;
    parse_recording(&bytes).map_err(|(line, message)| RecordingError::Parse {
        path: path.to_path_buf(),
        line,
        message,
    })
}

/// Whether a line is a PB-840 time stamp (`2016-05-05-13-25-36.944930`).
fn is_timestamp(line: &str) -> bool {
    line.len() >= 8
        && line.bytes().any(|b| b == b'-')
        && line
            .bytes()
            .all(|b| b.is_ascii_digit() || matches!(b, b'-' | b'.' | b':' | b' ' | b'_' | b'T'))
}

/// Parse recording bytes; errors carry the 1-based line (0: the file as a whole).
pub fn parse_recording(bytes: &[u8]) -> Result<Recording, (u64, String)> {
    if crate::input::looks_binary(bytes) {
        return Err((0, "this is binary data, not a ventilator recording".into()));
    }
    let text = std::str::from_utf8(bytes)
        .map_err(|e| (0, format!("not UTF-8 text (byte {})", e.valid_up_to())))?;
    let first = text
        .lines()
        .map(|l| l.trim_start_matches('\u{feff}').trim())
        .find(|l| !l.is_empty() && !is_timestamp(l));
    let rec = match first {
        None => return Err((0, "the file is empty: no samples".into())),
        Some(l) if l.starts_with("BS") || l == "BE" => parse_pb840(text)?,
        Some(_) => parse_csv(bytes)?,
    };
    check_samples(&rec)?;
    Ok(rec)
}

fn parse_pb840(text: &str) -> Result<Recording, (u64, String)> {
    let mut flow = Vec::new();
    let mut paw = Vec::new();
    let mut vent_breaths = Vec::new();
    let mut open: Option<u64> = None; // line of the open BS
    let mut seen_bs = false;
    for (i, raw) in text.lines().enumerate() {
        let line_no = i as u64 + 1;
        let line = raw.trim_start_matches('\u{feff}').trim();
        if line.is_empty() {
            continue;
        }
        if line.starts_with("BS") {
            if let Some(at) = open {
                return Err((
                    line_no,
                    format!("a breath starts (BS) while the breath begun on line {at} has no BE"),
                ));
            }
            let number = line
                .split(',')
                .map(str::trim)
                .find_map(|f| f.strip_prefix("S:"))
                .and_then(|n| n.trim().parse::<u64>().ok())
                .ok_or_else(|| {
                    (
                        line_no,
                        format!("{line:?}: a breath start must read `BS, S:<breath number>,`"),
                    )
                })?;
            vent_breaths.push((flow.len(), number));
            open = Some(line_no);
            seen_bs = true;
            continue;
        }
        if line == "BE" {
            if open.take().is_none() {
                return Err((
                    line_no,
                    "BE (breath end) without a BS (breath start)".into(),
                ));
            }
            continue;
        }
        if !seen_bs && is_timestamp(line) {
            continue;
        }
        let fields: Vec<&str> = line.split(',').map(str::trim).collect();
        let fields: &[&str] = match fields.as_slice() {
            [a, b, ""] => &[a, b],
            f => f,
        };
        let [f, p] = fields else {
            return Err((
                line_no,
                format!(
                    "{line:?}: a PB-840 sample line holds two values, `flow, pressure` ({} found)",
                    fields.len()
                ),
            ));
        };
        if open.is_none() {
            return Err((
                line_no,
                "a sample outside a breath (between BE and the next BS)".into(),
            ));
        }
        let num = |s: &str, what: &str| -> Result<f64, (u64, String)> {
            let v: f64 = s
                .parse()
                .map_err(|_| (line_no, format!("{what} {s:?} is not a number")))?;
            if v.is_finite() {
                Ok(v)
            } else {
                Err((
                    line_no,
                    format!("{what} is {s}: every sample must be a finite number"),
                ))
            }
        };
        let fl = num(f, "flow")? / 60.0;
        let pr = num(p, "pressure")?;
        check_value(line_no, fl, pr)?;
        flow.push(fl);
        paw.push(pr);
    }
    let n = flow.len();
    Ok(Recording {
        format: Format::Pb840,
        t_s: (0..n).map(|i| i as f64 * PB840_SAMPLE_S).collect(),
        flow_lps: flow,
        paw_cmh2o: paw,
        volume_ml: None,
        pes_cmh2o: None,
        columns: vec![
            ColumnNote {
                quantity: "time",
                column: "sample index".into(),
                unit: "0.02 s",
                factor: PB840_SAMPLE_S,
            },
            ColumnNote {
                quantity: "flow",
                column: "field 1".into(),
                unit: "L/min",
                factor: 1.0 / 60.0,
            },
            ColumnNote {
                quantity: "pressure",
                column: "field 2".into(),
                unit: "cmH2O",
                factor: 1.0,
            },
        ],
        vent_breaths,
    })
}

/// Flow and pressure of one sample against their plausible ranges.
fn check_value(line: u64, flow_lps: f64, paw: f64) -> Result<(), (u64, String)> {
    FLOW_LPS
        .check(flow_lps, None)
        .map_err(|e| (line, e.to_string()))?;
    PRESSURE_CMH2O
        .check(paw, None)
        .map_err(|e| (line, e.to_string()))
}

/// Which quantity a generic CSV header names.
fn quantity_of(header: &str) -> Option<&'static str> {
    let lower = header.to_ascii_lowercase();
    let has = |keys: &[&str]| keys.iter().any(|k| lower.contains(k));
    if has(&["pes", "oes", "eso", "pleural"]) {
        Some("oesophageal pressure")
    } else if has(&["flow"]) {
        Some("flow")
    } else if has(&["paw", "pressure", "airway", "pao"]) {
        Some("pressure")
    } else if has(&["vol"]) {
        Some("volume")
    } else if lower == "t" || has(&["time"]) || lower.starts_with("t_") || lower.starts_with("t ") {
        Some("time")
    } else {
        None
    }
}

fn parse_csv(bytes: &[u8]) -> Result<Recording, (u64, String)> {
    let mut reader = csv::ReaderBuilder::new()
        .flexible(true)
        .trim(csv::Trim::All)
        .comment(Some(b'#'))
        .from_reader(bytes);
    let headers = reader
        .headers()
        .map_err(|e| (1, format!("cannot read the header row: {e}")))?
        .clone();
    let columns = csv_columns(&headers)?;
    let col = |q: &str| {
        columns
            .iter()
            .find(|(_, c)| c.quantity == q)
            .map(|(i, c)| (*i, c.factor))
    };
    let cols = RowColumns {
        time: col("time").expect("checked"),
        flow: col("flow").expect("checked"),
        pressure: col("pressure").expect("checked"),
        volume: col("volume"),
        pes: col("oesophageal pressure"),
    };
    let mut rec = Recording {
        format: Format::GenericCsv,
        t_s: Vec::new(),
        flow_lps: Vec::new(),
        paw_cmh2o: Vec::new(),
        volume_ml: cols.volume.map(|_| Vec::new()),
        pes_cmh2o: cols.pes.map(|_| Vec::new()),
        columns: columns.into_iter().map(|(_, c)| c).collect(),
        vent_breaths: Vec::new(),
    };
    for (i, r) in reader.records().enumerate() {
        let r = r.map_err(|e| (i as u64 + 2, e.to_string()))?;
        let line = r.position().map(|p| p.line()).unwrap_or(i as u64 + 2);
        if r.iter().all(|f| f.is_empty()) {
            continue;
        }
        push_row(&mut rec, line, &r, &cols)?;
    }
    Ok(rec)
}

/// A generic recording's columns: each quantity's (index, factor to lungdyn's unit).
struct RowColumns {
    time: (usize, f64),
    flow: (usize, f64),
    pressure: (usize, f64),
    volume: Option<(usize, f64)>,
    pes: Option<(usize, f64)>,
}

/// The header's columns: each quantity's column exactly once with a recognised unit, and time,
/// flow and airway pressure there (a semicolon or tab table, or a PV curve, refused naming what it
/// is).
fn csv_columns(headers: &csv::StringRecord) -> Result<Vec<(usize, ColumnNote)>, (u64, String)> {
    let headers: Vec<String> = headers
        .iter()
        .map(|h| h.trim_start_matches('\u{feff}').to_string())
        .collect();
    if headers.len() == 1 && headers[0].contains(';') {
        return Err((
            1,
            "the columns are separated by semicolons: lungdyn reads comma-separated values with \
             decimal points"
                .into(),
        ));
    }
    if headers.len() == 1 && headers[0].contains('\t') {
        return Err((
            1,
            "the columns are separated by tabs: lungdyn reads comma-separated values".into(),
        ));
    }
    // A PV curve (pressure and volume, no flow) given here is meant for `pv fit`.
    let quantities: Vec<Option<&str>> = headers.iter().map(|h| quantity_of(h)).collect();
    if !quantities.contains(&Some("flow")) && quantities.contains(&Some("volume")) {
        return Err((
            1,
            format!(
                "no flow column ({}): this looks like a PV curve (pressure against volume); fit one with \
                 `lungdyn pv fit --input FILE`, or give a recording with time, flow and airway pressure \
                 columns named with their units (time_s,flow_L/min,paw_cmH2O)",
                headers.join(",")
            ),
        ));
    }
    // Each quantity's column: exactly one, with a recognised unit.
    let mut columns: Vec<(usize, ColumnNote)> = Vec::new();
    for (i, h) in headers.iter().enumerate() {
        let Some(q) = quantity_of(h) else { continue };
        if let Some((j, _)) = columns.iter().find(|(_, c)| c.quantity == q) {
            return Err((
                1,
                format!(
                    "two columns look like {q}: {:?} (column {}) and {h:?} (column {}); keep one",
                    headers[*j],
                    j + 1,
                    i + 1
                ),
            ));
        }
        let (unit, expected) = match q {
            "time" => (time_unit(h), "s, ms or min (time_s)"),
            "flow" => (flow_unit(h), "L/min, L/s, ml/s or ml/min (flow_L/min)"),
            "volume" => (header_unit(h, VOLUME_UNITS), "ml or L (volume_ml)"),
            _ => (
                header_unit(h, PRESSURE_UNITS),
                "cmH2O, mbar, hPa, kPa, mmHg (paw_cmH2O)",
            ),
        };
        let Some((unit, factor)) = unit else {
            return Err((
                1,
                format!(
                    "the {q} column {h:?} names no unit lungdyn recognises: name it in the header, \
                     in {expected} (every input states its units; a guessed unit is a silently wrong \
                     volume)"
                ),
            ));
        };
        columns.push((
            i,
            ColumnNote {
                quantity: q,
                column: h.clone(),
                unit,
                factor,
            },
        ));
    }
    let col = |q: &str| {
        columns
            .iter()
            .find(|(_, c)| c.quantity == q)
            .map(|(i, c)| (*i, c.factor))
    };
    let mut missing: Vec<&str> = ["time", "flow", "pressure"]
        .into_iter()
        .filter(|q| col(q).is_none())
        .collect();
    if !missing.is_empty() {
        missing.sort();
        return Err((
            1,
            format!(
                "no {} column: a recording needs time, flow and airway pressure columns named with \
                 their units, e.g. time_s,flow_L/min,paw_cmH2O (header read: {})",
                missing.join(" or "),
                headers.join(",")
            ),
        ));
    }
    Ok(columns)
}

/// Row `r` (at `line`) checked and appended: time increasing without a gap, flow and pressure in
/// range, the volume no larger than a lung, the oesophageal pressure in range.
fn push_row(
    rec: &mut Recording,
    line: u64,
    r: &csv::StringRecord,
    cols: &RowColumns,
) -> Result<(), (u64, String)> {
    let ((tc, tf), (fc, ff), (pc, pf)) = (cols.time, cols.flow, cols.pressure);
    let (vcol, ecol) = (cols.volume, cols.pes);
    let value = |c: usize, what: &str| -> Result<f64, (u64, String)> {
        let field = r.get(c).unwrap_or("");
        let v: f64 = field.parse().map_err(|_| {
            (
                line,
                format!("{what} {field:?} (column {}) is not a number", c + 1),
            )
        })?;
        if v.is_finite() {
            Ok(v)
        } else {
            Err((
                line,
                format!("{what} is {field}: every sample must be a finite number"),
            ))
        }
    };
    let t = value(tc, "time")? * tf;
    let fl = value(fc, "flow")? * ff;
    let pr = value(pc, "pressure")? * pf;
    check_value(line, fl, pr)?;
    if let Some(&last) = rec.t_s.last() {
        if t <= last {
            return Err((
                line,
                format!("time {t} s does not increase (the previous sample is at {last} s)"),
            ));
        }
        if t - last > MAX_SAMPLE_GAP_S {
            return Err((
                line,
                format!(
                    "a gap of {} s between samples (more than {MAX_SAMPLE_GAP_S} s): flow cannot be \
                     integrated across it; check the time column's unit or split the recording",
                    crate::plausible::compact(t - last)
                ),
            ));
        }
    }
    rec.t_s.push(t);
    rec.flow_lps.push(fl);
    rec.paw_cmh2o.push(pr);
    if let (Some((c, f)), Some(v)) = (vcol, rec.volume_ml.as_mut()) {
        let ml = value(c, "volume")? * f;
        // Ventilators record volume above the breath's start (or above FRC): any sign, but
        // never more than a whole lung.
        let most = crate::plausible::LUNGS_VOLUME_ML.hi;
        if ml.abs() > most {
            return Err((
                line,
                format!(
                    "volume {} ml is larger than any lung ({most} ml): check the volume column's unit",
                    crate::plausible::compact(ml)
                ),
            ));
        }
        v.push(ml);
    }
    if let (Some((c, f)), Some(v)) = (ecol, rec.pes_cmh2o.as_mut()) {
        let p = value(c, "oesophageal pressure")? * f;
        PRESSURE_CMH2O
            .check(p, None)
            .map_err(|e| (line, e.to_string()))?;
        v.push(p);
    }
    Ok(())
}

/// Minimum number of samples in a recording.
pub const MIN_SAMPLES: usize = 10;

fn check_samples(rec: &Recording) -> Result<(), (u64, String)> {
    if rec.t_s.len() < MIN_SAMPLES {
        return Err((
            0,
            format!(
                "{} samples: a recording needs at least {MIN_SAMPLES} to hold a breath",
                rec.t_s.len()
            ),
        ));
    }
    let dt = (rec.t_s[rec.t_s.len() - 1] - rec.t_s[0]) / (rec.t_s.len() - 1) as f64;
    if !(1e-4..=0.5).contains(&dt) {
        return Err((
            0,
            format!(
                "mean sample interval {} s: a ventilator samples at 2–10000 Hz; check the time \
                 column's unit",
                crate::plausible::compact(dt)
            ),
        ));
    }
    Ok(())
}

/// Options of [`segment`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct SegmentOptions {
    /// Hysteresis threshold, L/s: inspiration above `+threshold`, expiration below `−threshold`.
    pub threshold_lps: f64,
    /// Minimum inspiration time, s (a shorter rise is noise or a cardiac oscillation).
    pub min_inspiration_s: f64,
    /// Minimum expiration time, s.
    pub min_expiration_s: f64,
}

impl Default for SegmentOptions {
    /// 3 L/min, 0.1 s, 0.2 s: above a ventilator's bias-flow drift (≈ 2 L/min in the PB-840
    /// exports) and below the shortest neonatal inspiration (≈ 0.25 s).
    fn default() -> Self {
        Self {
            threshold_lps: 0.05,
            min_inspiration_s: 0.1,
            min_expiration_s: 0.2,
        }
    }
}

/// One breath's sample indices.
#[derive(Debug, Clone, Copy, PartialEq, Eq, serde::Serialize)]
pub struct BreathSpan {
    /// First sample (inspiration start: the zero crossing before the flow rose).
    pub start: usize,
    /// First sample of expiration (the zero crossing before the flow fell); `end` when none.
    pub expiration: usize,
    /// Last sample (the next breath's start, shared; or the recording's last sample).
    pub end: usize,
    /// Whether the recording holds all of it (it ends after the expiration).
    pub complete: bool,
    /// Whether the recording starts inside this breath's inspiration.
    pub starts_cut: bool,
}

/// Whether `flow` beyond `sign·threshold` is sustained over `window` samples from `i`: the first
/// sample and at least 80 % of the window beyond it, and the window's mean too (a brief flicker or
/// a dip of a few samples is no phase change).
fn sustained(flow: &[f64], i: usize, window: usize, sign: f64, threshold: f64) -> bool {
    let w = &flow[i..(i + window.max(1)).min(flow.len())];
    let beyond = w.iter().filter(|&&f| sign * f > threshold).count();
    sign * flow[i] > threshold
        && beyond * 5 >= w.len() * 4
        && sign * w.iter().sum::<f64>() / w.len() as f64 > threshold
}

/// Move `i` back to where the flow left the noise band: over the samples before it (not before
/// `floor`) whose flow has the sign of `flow[i]` and at least a quarter of the threshold. A plain
/// zero crossing would walk back through seconds of bias flow (the PB-840 exports hold
/// +0.1…0.3 L/min for the whole expiratory pause).
fn back_to_crossing(flow: &[f64], mut i: usize, floor: usize, sign: f64, threshold: f64) -> usize {
    while i > floor && sign * flow[i - 1] >= 0.25 * threshold {
        i -= 1;
    }
    i
}

/// Cut a recording into breaths (see the module's description).
pub fn segment(rec: &Recording, opts: &SegmentOptions) -> Vec<BreathSpan> {
    let flow = &rec.flow_lps;
    let n = flow.len();
    if n < 2 {
        return Vec::new();
    }
    let dt = (rec.t_s[n - 1] - rec.t_s[0]) / (n - 1) as f64;
    let w_in = (opts.min_inspiration_s / dt).round().max(1.0) as usize;
    let w_ex = (opts.min_expiration_s / dt).round().max(1.0) as usize;
    let thr = opts.threshold_lps;
    // (inspiration onset, expiration onset) pairs.
    let mut onsets: Vec<(usize, Option<usize>)> = Vec::new();
    let mut inspiring = false;
    let mut last_exp: Option<usize> = None;
    let mut i = 0;
    while i < n {
        if !inspiring {
            let rested = last_exp.is_none_or(|e| i >= e + w_ex);
            if rested && sustained(flow, i, w_in, 1.0, thr) {
                let floor = last_exp.unwrap_or(0);
                onsets.push((back_to_crossing(flow, i, floor, 1.0, thr), None));
                inspiring = true;
            }
        } else if sustained(flow, i, w_ex, -1.0, thr) {
            let start = onsets.last().expect("inspiring").0;
            let e = back_to_crossing(flow, i, start + 1, -1.0, thr);
            onsets.last_mut().expect("inspiring").1 = Some(e);
            last_exp = Some(e);
            inspiring = false;
        }
        i += 1;
    }
    let mut spans = Vec::with_capacity(onsets.len());
    for (k, &(start, exp)) in onsets.iter().enumerate() {
        let next = onsets.get(k + 1).map(|o| o.0);
        let end = next.unwrap_or(n - 1);
        let complete = match exp {
            None => false,
            // The last breath: complete when its expiration lasted the minimum time and the flow
            // has come back near zero (not cut off mid-exhalation).
            Some(e) if next.is_none() => end >= e + w_ex && flow[end] > -thr,
            Some(_) => true,
        };
        spans.push(BreathSpan {
            start,
            expiration: exp.unwrap_or(end),
            end,
            complete,
            // The recording starts inside an inspiration when its first flow is already a good part
            // of the breath's peak, unless the ventilator marked a breath start there (PB-840 BS).
            starts_cut: start == 0
                && rec.vent_breaths.first().is_none_or(|b| b.0 != 0)
                && flow[0] > thr
                && flow[0]
                    > 0.25
                        * flow[..=exp.unwrap_or(end)]
                            .iter()
                            .copied()
                            .fold(0.0, f64::max),
        });
    }
    spans
}

/// The volume that flows from sample `i − 1` to sample `i`, ml: the flow of sample `i − 1` held
/// over the interval (each sample is the flow of the interval it starts, as the PB-840 documents
/// its export: ml = Σ flow · 1000 / 60 · 0.02). A trapezoid would lose half a sample at each step
/// of a square-wave (volume-controlled) flow.
fn step_ml(rec: &Recording, i: usize) -> f64 {
    rec.flow_lps[i - 1] * (rec.t_s[i] - rec.t_s[i - 1]) * 1000.0
}

/// One breath's volume above its start, ml, per sample `start..=end`, and the net volume removed
/// (ml, inspired − expired before the correction).
pub fn breath_volume(rec: &Recording, span: &BreathSpan) -> (Vec<f64>, f64) {
    let idx = span.start..=span.end;
    let mut v = Vec::with_capacity(span.end - span.start + 1);
    let mut acc = 0.0;
    for i in idx {
        if i > span.start {
            acc += step_ml(rec, i);
        }
        v.push(acc);
    }
    let net = acc;
    let (t0, t1) = (rec.t_s[span.start], rec.t_s[span.end]);
    if t1 > t0 && span.complete {
        for (j, i) in (span.start..=span.end).enumerate() {
            v[j] -= net * (rec.t_s[i] - t0) / (t1 - t0);
        }
    }
    (v, net)
}

/// One breath's timing and volumes (what a waveform scene and `pv recording` both need).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct BreathTiming {
    /// Start time, s.
    pub start_s: f64,
    /// Duration, s (start to the next breath's start).
    pub duration_s: f64,
    /// Inspiration time, s.
    pub inspiration_s: f64,
    /// Expiration time, s.
    pub expiration_s: f64,
    /// Tidal volume: the largest drift-corrected volume above the start, ml.
    pub tidal_volume_ml: f64,
    /// Volume inspired (integral of flow over the inspiration), ml.
    pub inspired_ml: f64,
    /// Net volume at the end before the drift correction (inspired − expired), ml.
    pub net_ml: f64,
    /// Breaths per minute, 60 / duration.
    pub rate_per_min: f64,
}

/// [`BreathTiming`] of one span from its volume (from [`breath_volume`]).
pub fn timing(rec: &Recording, span: &BreathSpan, volume: &[f64], net_ml: f64) -> BreathTiming {
    let t = |i: usize| rec.t_s[i];
    let duration = t(span.end) - t(span.start);
    let inspired = {
        let mut acc = 0.0;
        for i in span.start + 1..=span.expiration.max(span.start) {
            acc += step_ml(rec, i);
        }
        acc
    };
    BreathTiming {
        start_s: t(span.start),
        duration_s: duration,
        inspiration_s: t(span.expiration) - t(span.start),
        expiration_s: t(span.end) - t(span.expiration),
        tidal_volume_ml: volume.iter().copied().fold(0.0, f64::max),
        inspired_ml: inspired,
        net_ml,
        rate_per_min: if duration > 0.0 {
            60.0 / duration
        } else {
            f64::INFINITY
        },
    }
}

/// Largest |inspired − expired| volume of a breath, as a fraction of the inspired volume, that is
/// still drift (bias flow, sensor offset) rather than a leak or an artefact.
pub const MAX_IMBALANCE: f64 = 0.25;

/// `Ok` for a whole, clean breath; else why it is an artefact: cut by the recording, a tidal volume
/// or rate outside the plausible ranges, or a volume that does not close (|inspired − expired| above
/// [`MAX_IMBALANCE`] of the inspired volume).
pub fn whole_breath(span: &BreathSpan, tm: &BreathTiming) -> Result<(), String> {
    use crate::plausible::{compact, BREATHS_PER_MIN, TIDAL_VOLUME_ML};
    if span.starts_cut {
        return Err("the recording starts inside this breath's inspiration".into());
    }
    if !span.complete {
        return Err("the recording ends before this breath's expiration is over".into());
    }
    if !TIDAL_VOLUME_ML.contains(tm.tidal_volume_ml) {
        return Err(format!(
            "tidal volume {} ml is outside {}–{} ml (a flicker of flow, not a breath)",
            compact(tm.tidal_volume_ml),
            TIDAL_VOLUME_ML.lo,
            TIDAL_VOLUME_ML.hi
        ));
    }
    if tm.net_ml.abs() > MAX_IMBALANCE * tm.inspired_ml.abs() {
        return Err(format!(
            "expired {} ml against {} ml inspired ({} % apart, more than {} %): a leak, a \
             flow-sensor artefact or a breath cut short",
            compact(tm.inspired_ml - tm.net_ml),
            compact(tm.inspired_ml),
            compact(100.0 * tm.net_ml.abs() / tm.inspired_ml.abs().max(1e-9)),
            MAX_IMBALANCE * 100.0
        ));
    }
    if !BREATHS_PER_MIN.contains(tm.rate_per_min) {
        return Err(format!(
            "rate {} /min is outside {}–{} /min",
            compact(tm.rate_per_min),
            BREATHS_PER_MIN.lo,
            BREATHS_PER_MIN.hi
        ));
    }
    Ok(())
}

/// A recording's breathing resampled to the engine's tick: one averaged breath (what a
/// `[pv] waveform` scene plays, looped), with the airway pressure and flow averaged the same way,
/// the equation of motion fitted to them and the ventilator's control mode the breaths show.
#[derive(Debug, Clone, PartialEq)]
pub struct Waveform {
    /// Volume above the breath's start, ml, at every tick of one cycle (starts at 0; the cycle's
    /// end meets its start, so the loop is seamless).
    pub volume_ml: Vec<f64>,
    /// Airway pressure, cmH2O, at the same ticks (the sample in force at each tick, averaged).
    pub paw_cmh2o: Vec<f64>,
    /// Flow, L/s, at the same ticks (likewise).
    pub flow_lps: Vec<f64>,
    /// Ticks of the inspiration.
    pub inhale_ticks: u32,
    /// Breaths averaged.
    pub breaths_used: usize,
    /// Breaths left out, with the reason (1-based index, why).
    pub breaths_skipped: Vec<(usize, String)>,
    /// Mean tidal volume of the breaths used, ml.
    pub tidal_volume_ml: f64,
    /// Mean rate of the breaths used (60 / mean duration), breaths/min.
    pub rate_per_min: f64,
    /// The classes of the recording's breaths and the control mode their majority shows.
    pub control: classify::ControlSummary,
    /// The equation of motion fitted to the averaged breath (volume, flow, pressure per tick);
    /// `None` when it cannot be determined.
    pub eom: Option<classify::EquationOfMotion>,
}

/// Linear interpolation of `v` (samples at `t`, increasing) at time `x`, clamped to the ends.
fn interpolate(t: &[f64], v: &[f64], x: f64) -> f64 {
    let k = t.partition_point(|&ti| ti <= x);
    if k == 0 {
        return v[0];
    }
    if k >= t.len() {
        return v[v.len() - 1];
    }
    let (t0, t1) = (t[k - 1], t[k]);
    let w = if t1 > t0 { (x - t0) / (t1 - t0) } else { 0.0 };
    v[k - 1] + w * (v[k] - v[k - 1])
}

/// The sample of `v` (samples at `t`, increasing) in force at time `x`: the last at or before it
/// (each sample holds over its interval, as the recording's volume integrates it, [`step_ml`]), so
/// a ventilator's step at the next breath's first sample does not leak into the end of this one.
fn held(t: &[f64], v: &[f64], x: f64) -> f64 {
    v[t.partition_point(|&ti| ti <= x).saturating_sub(1)]
}

/// The whole, clean breaths of `rec` ([`whole_breath`], with an inspiration), characterised, and
/// the breaths left out with the reason; with every breath's class summarised. A recording whose
/// breaths are not what its header says (a pressure unit, the flow's sign, a volume column:
/// [`checks::check_plausible`]) is refused.
#[allow(clippy::type_complexity)]
fn usable_breaths(
    rec: &Recording,
    opts: &SegmentOptions,
) -> Result<
    (
        Vec<classify::BreathCharacter>,
        Vec<(usize, String)>,
        classify::ControlSummary,
    ),
    String,
> {
    let all = classify::characterise_all(rec, opts);
    checks::check_plausible(rec, &all.iter().collect::<Vec<_>>())?;
    let summary = classify::ControlSummary::of(&all);
    let mut used = Vec::new();
    let mut skipped = Vec::new();
    for c in all {
        match whole_breath(&c.span, &c.timing) {
            Ok(()) if c.span.expiration > c.span.start => used.push(c),
            Ok(()) => skipped.push((c.index, "no inspiration".to_string())),
            Err(why) => skipped.push((c.index, why)),
        }
    }
    Ok((used, skipped, summary))
}

/// The refusal when no breath of a recording can be played.
fn none_usable(skipped: &[(usize, String)]) -> String {
    format!(
        "no whole, clean breath to play ({} found, all left out{})",
        skipped.len(),
        skipped
            .first()
            .map(|(k, why)| format!("; breath {k}: {why}"))
            .unwrap_or_default()
    )
}

/// Average the whole, clean breaths of `rec` ([`whole_breath`]) into one breath at `tick_hz`:
/// inspiration and expiration are each stretched to the mean inspiration and expiration time
/// (so every breath's end-inspiration lines up and the tidal volume is not smeared), the
/// drift-corrected volumes (and the airway pressure and flow) averaged at each tick. Allocates:
/// call at load time, never per tick.
pub fn average_breath(
    rec: &Recording,
    opts: &SegmentOptions,
    tick_hz: f64,
) -> Result<Waveform, String> {
    let (used, skipped, control) = usable_breaths(rec, opts)?;
    if used.is_empty() {
        return Err(none_usable(&skipped));
    }
    let n = used.len() as f64;
    let ti = used.iter().map(|u| u.timing.inspiration_s).sum::<f64>() / n;
    let te = used.iter().map(|u| u.timing.expiration_s).sum::<f64>() / n;
    let cycle = (tick_hz * (ti + te)).round();
    if !(2.0..=1.0e7).contains(&cycle) {
        return Err(format!(
            "a breath of {} s at {tick_hz} Hz is {cycle} ticks: at least 2 needed",
            ti + te
        ));
    }
    let cycle = cycle as u32;
    let inhale = ((tick_hz * ti).round() as u32).clamp(1, cycle - 1);
    let mut volume = vec![0.0; cycle as usize];
    let mut paw = vec![0.0; cycle as usize];
    let mut flow = vec![0.0; cycle as usize];
    for u in &used {
        let (span, tm) = (&u.span, &u.timing);
        let t = &rec.t_s[span.start..=span.end];
        let p = &rec.paw_cmh2o[span.start..=span.end];
        let q = &rec.flow_lps[span.start..=span.end];
        for k in 0..cycle as usize {
            let k32 = k as u32;
            let x = if k32 < inhale {
                tm.start_s + tm.inspiration_s * k as f64 / inhale as f64
            } else {
                rec.t_s[span.expiration]
                    + tm.expiration_s * (k32 - inhale) as f64 / (cycle - inhale) as f64
            };
            volume[k] += interpolate(t, &u.volume_ml, x) / n;
            paw[k] += held(t, p, x) / n;
            flow[k] += held(t, q, x) / n;
        }
    }
    let eom = classify::fit_equation_of_motion(&volume, &flow, &paw);
    Ok(Waveform {
        volume_ml: volume,
        paw_cmh2o: paw,
        flow_lps: flow,
        inhale_ticks: inhale,
        breaths_used: used.len(),
        breaths_skipped: skipped,
        tidal_volume_ml: used.iter().map(|u| u.timing.tidal_volume_ml).sum::<f64>() / n,
        rate_per_min: 60.0 / (ti + te),
        control,
        eom,
    })
}

/// Ventilation mode of [`Synthetic`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub enum SyntheticMode {
    /// Volume control: constant inspiratory flow, L/s.
    Volume {
        /// Inspiratory flow, L/s.
        flow_lps: f64,
    },
    /// Pressure control: airway pressure held this far above PEEP during inspiration, cmH2O.
    Pressure {
        /// Inspiratory pressure above PEEP, cmH2O.
        above_peep_cmh2o: f64,
    },
}

/// A passive lung ventilated by a ventilator, for tests and fixtures (the real recordings are
/// GPL-3.0 and stay outside the repository): the equation of motion `Paw = V/C + R·flow + PEEP`
/// solved exactly per breath (every breath starts from V = 0). Expiration is passive through the
/// ventilator's exhalation valve (resistance `r_valve`: `Paw = PEEP + R_valve·|flow|`, so
/// `V = V_end·e^(−t/((R + R_valve)·C))`).
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct Synthetic {
    /// Ventilation mode.
    pub mode: SyntheticMode,
    /// Compliance, ml/cmH2O.
    pub c_ml_per_cmh2o: f64,
    /// Airway resistance, cmH2O·s/L.
    pub r_cmh2o_s_per_l: f64,
    /// Exhalation valve resistance, cmH2O·s/L.
    pub r_valve_cmh2o_s_per_l: f64,
    /// PEEP, cmH2O.
    pub peep_cmh2o: f64,
    /// Breaths per minute.
    pub rate_per_min: f64,
    /// Inspiration time, s.
    pub ti_s: f64,
    /// Number of breaths.
    pub breaths: usize,
    /// Sample interval, s.
    pub dt_s: f64,
}

impl Default for Synthetic {
    /// 500 ml at 0.5 L/s, C = 50 ml/cmH2O, R = 10, valve 5 cmH2O·s/L, PEEP 5, 15 /min, Ti 1 s,
    /// three breaths at 50 Hz.
    fn default() -> Self {
        Self {
            mode: SyntheticMode::Volume { flow_lps: 0.5 },
            c_ml_per_cmh2o: 50.0,
            r_cmh2o_s_per_l: 10.0,
            r_valve_cmh2o_s_per_l: 5.0,
            peep_cmh2o: 5.0,
            rate_per_min: 15.0,
            ti_s: 1.0,
            breaths: 3,
            dt_s: 0.02,
        }
    }
}

impl Synthetic {
    /// The recording (generic format; `vent_breaths` numbered from 1).
    pub fn recording(&self) -> Recording {
        let (c, r, dt_s) = (self.c_ml_per_cmh2o, self.r_cmh2o_s_per_l, self.dt_s);
        let per = (60.0 / self.rate_per_min / dt_s).round() as usize;
        let breaths = self.breaths.max(1);
        let tau_in = r * c / 1000.0;
        let tau_ex = (r + self.r_valve_cmh2o_s_per_l) * c / 1000.0;
        // Sample 0 is the end of a previous expiration (at rest), so the first breath is whole; the
        // last sample is where the next breath would start.
        let n = per * breaths + 2;
        let (mut t_s, mut flow, mut paw) = (Vec::new(), Vec::new(), Vec::new());
        let mut vent_breaths = Vec::new();
        for i in 0..n {
            t_s.push(i as f64 * dt_s);
            if i == 0 {
                flow.push(0.0);
                paw.push(self.peep_cmh2o);
                continue;
            }
            let j = i - 1;
            let k = (j / per).min(breaths - 1);
            let tb = (j - k * per) as f64 * dt_s;
            if j % per == 0 && j / per < breaths {
                vent_breaths.push((i, k as u64 + 1));
            }
            // Volume above FRC at the end of inspiration, and (V, flow) now.
            let v_end = match self.mode {
                SyntheticMode::Volume { flow_lps } => flow_lps * self.ti_s * 1000.0,
                SyntheticMode::Pressure { above_peep_cmh2o } => {
                    c * above_peep_cmh2o * (1.0 - (-self.ti_s / tau_in).exp())
                }
            };
            let (v, q) = if tb < self.ti_s {
                match self.mode {
                    SyntheticMode::Volume { flow_lps } => (flow_lps * tb * 1000.0, flow_lps),
                    SyntheticMode::Pressure { above_peep_cmh2o } => {
                        let vmax = c * above_peep_cmh2o;
                        let v = vmax * (1.0 - (-tb / tau_in).exp());
                        (v, (vmax - v) / 1000.0 / tau_in)
                    }
                }
            } else {
                let v = v_end * (-(tb - self.ti_s) / tau_ex).exp();
                (v, -v / 1000.0 / tau_ex)
            };
            flow.push(q);
            paw.push(self.peep_cmh2o + v / c + r * q);
        }
        Recording {
            format: Format::GenericCsv,
            t_s,
            flow_lps: flow,
            paw_cmh2o: paw,
            volume_ml: None,
            pes_cmh2o: None,
            columns: Vec::new(),
            vent_breaths,
        }
    }
}

#[cfg(test)]
mod tests;
