//! Measured PV curves (the input of `lungdyn pv fit`, the output of `lungdyn pv simulate`): a CSV
//! with a header row; the first two columns whose first data row is numeric are pressure (cmH2O)
//! and volume (ml, or litres with [`VolumeUnit::Litre`]); an optional `phase` column
//! (`inhale`/`exhale`). Samples in time order.

use std::path::{Path, PathBuf};

use lung_model::pv::{Boundary, Phase};

use super::fit::PvSample;
use lung_model::units::{header_unit, PRESSURE_UNITS, VOLUME_UNITS};

/// Errors reading a curve file.
#[derive(Debug, thiserror::Error)]
pub enum CurveError {
    /// The file could not be read.
    #[error("{}: {source}", path.display())]
    Io {
        /// Path.
        path: PathBuf,
        /// OS error.
        source: std::io::Error,
    },
    /// The file could not be read within the limits.
    #[error(transparent)]
    Input(#[from] lung_model::input::InputError),
    /// Malformed or implausible CSV (line 0: the file as a whole).
    #[error("{}{}: {message}", path.display(), if *line > 0 { format!(": line {line}") } else { String::new() })]
    Csv {
        /// Path.
        path: PathBuf,
        /// 1-based line.
        line: u64,
        /// What is wrong.
        message: String,
    },
}

/// Volume unit of a curve file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum VolumeUnit {
    /// Millilitres (the default).
    Ml,
    /// Litres.
    Litre,
}

impl std::str::FromStr for VolumeUnit {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s.to_ascii_lowercase().as_str() {
            "ml" => Ok(VolumeUnit::Ml),
            "l" | "litre" | "liter" => Ok(VolumeUnit::Litre),
            other => Err(format!("unknown volume unit {other:?}: use ml or l")),
        }
    }
}

/// What [`read_curve`] found.
#[derive(Debug, Clone)]
pub struct CurveFile {
    /// Samples in file order, volume in ml.
    pub samples: Vec<PvSample>,
    /// Header of the pressure column.
    pub pressure_column: String,
    /// Header of the volume column.
    pub volume_column: String,
    /// Whether a phase column was used.
    pub has_phase: bool,
    /// Unit of the pressure column, converted to cmH2O.
    pub pressure_unit: ColumnUnit,
    /// Unit of the volume column, converted to ml.
    pub volume_unit: ColumnUnit,
    /// FRC added to every volume (`--frc`: the column held changes above FRC).
    pub frc_added_ml: Option<f64>,
    /// Why the volumes were read as changes above FRC ("--frc", "--relative", "header"), and
    /// whether the FRC was assumed (Table 5.2) rather than given.
    pub relative: Option<(&'static str, bool)>,
}

/// A unit of a column and its factor to lungdyn's unit (cmH2O or ml).
#[derive(Debug, Clone, Copy, PartialEq, serde::Serialize)]
pub struct ColumnUnit {
    /// The unit as recognised ("kPa", "L", ...).
    pub name: &'static str,
    /// Multiply by this to get cmH2O (pressure) or ml (volume).
    pub factor: f64,
    /// Where the unit came from: "header", "flag" or "default".
    pub from: &'static str,
}

/// Options of [`read_curve`].
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct CurveOptions {
    /// The volume unit the user declared (`--volume-unit`); the header's unit otherwise, else ml.
    pub volume_unit: Option<VolumeUnit>,
    /// Volumes are changes above this FRC (ml): absolute volume = FRC + value (`--frc`).
    pub frc_ml: Option<f64>,
    /// Volumes are changes above FRC (`--relative`; also when the volume header says `delta` or
    /// `above_frc`): FRC is `frc_ml`, else Table 5.2's 2400 ml, said so.
    pub relative: bool,
    /// Size and line limits of the file.
    pub limits: lung_model::input::ReadLimits,
}

impl Default for CurveOptions {
    fn default() -> Self {
        Self {
            volume_unit: None,
            frc_ml: None,
            relative: false,
            limits: lung_model::input::ReadLimits::TABLE,
        }
    }
}

/// Read a PV curve CSV: bounded, units from the header (or the flag), every sample checked against
/// the plausible ranges of [`lung_model::plausible`].
pub fn read_curve(path: &Path, opts: &CurveOptions) -> Result<CurveFile, CurveError> {
    let bytes = lung_model::input::read_bounded(path, opts.limits)?;
    parse_curve(&bytes, opts).map_err(|(line, message)| CurveError::Csv {
        path: path.to_path_buf(),
        line,
        message,
    })
}

/// Parse PV curve CSV bytes; errors carry the 1-based line (0: the file as a whole).
pub fn parse_curve(bytes: &[u8], opts: &CurveOptions) -> Result<CurveFile, (u64, String)> {
    if lung_model::input::looks_binary(bytes) {
        return Err((0, "this is binary data, not a CSV table".into()));
    }
    check_separators(bytes)?;
    let (headers, records) = read_rows(bytes)?;
    let cols = Columns::choose(&headers, &records)?;
    let units = Units::of(&cols, opts)?;
    let mut samples = Vec::with_capacity(records.len());
    // The volume column as given, in ml, before --frc is added: (lowest, highest).
    let mut raw_ml = (f64::INFINITY, f64::NEG_INFINITY);
    for (line, rec) in &records {
        samples.push(sample_of(*line, rec, &cols, &units, &mut raw_ml)?);
    }
    if let (Some(frc), Some((why, _))) = (units.frc_add, units.relative) {
        check_relative(raw_ml, frc, &cols.v_header, why)?;
    }
    check_swings(&samples, &cols, &units)?;
    Ok(CurveFile {
        samples,
        pressure_column: cols.p_header,
        volume_column: cols.v_header,
        has_phase: cols.phase.is_some(),
        pressure_unit: units.pressure,
        volume_unit: units.volume,
        frc_added_ml: units.frc_add,
        relative: units.relative,
    })
}

/// The header and the data rows (blank rows dropped), each with its 1-based line.
type Rows = (csv::StringRecord, Vec<(u64, csv::StringRecord)>);

/// Read the header (checked) and the non-blank rows; at least one row.
fn read_rows(bytes: &[u8]) -> Result<Rows, (u64, String)> {
    let mut reader = csv::ReaderBuilder::new()
        .flexible(true)
        .trim(csv::Trim::All)
        .from_reader(bytes);
    let headers = reader
        .headers()
        .map_err(|e| (1, format!("cannot read the header row: {e}")))?
        .clone();
    check_header(&headers)?;
    let records: Vec<(u64, csv::StringRecord)> = reader
        .records()
        .enumerate()
        .map(|(i, r)| {
            r.map(|r| (r.position().map(|p| p.line()).unwrap_or(i as u64 + 2), r))
                .map_err(|e| (i as u64 + 2, e.to_string()))
        })
        .filter(|r| {
            r.as_ref()
                .map(|(_, rec)| !rec.iter().all(|f| f.is_empty()))
                .unwrap_or(true)
        })
        .collect::<Result<_, _>>()?;
    if records.is_empty() {
        return Err((2, "no data rows after the header".into()));
    }
    Ok((headers, records))
}

/// Which columns hold the pressure, the volume and (optionally) the phase, and their headers.
struct Columns {
    phase: Option<usize>,
    pressure: usize,
    volume: usize,
    p_header: String,
    v_header: String,
}

/// Header words that name a pressure column.
const PRESSURE_KEYS: &[&str] = &["pressure", "pes", "paw", "ptp", "pleural", "airway"];

impl Columns {
    /// Columns named for what they hold win (a time column often comes first); else the first two
    /// numeric ones. Two columns that both look like pressures (or volumes) are refused: which one
    /// is meant is a guess, and a wrong guess is a silently wrong fit.
    fn choose(
        headers: &csv::StringRecord,
        records: &[(u64, csv::StringRecord)],
    ) -> Result<Self, (u64, String)> {
        let (first_line, first) = &records[0];
        let phase = headers.iter().position(|h| h.eq_ignore_ascii_case("phase"));
        let numeric: Vec<usize> = (0..first.len())
            .filter(|&i| Some(i) != phase && first.get(i).is_some_and(|f| f.parse::<f64>().is_ok()))
            .collect();
        if numeric.len() < 2 {
            let tabs = headers.len() == 1 && headers.get(0).is_some_and(|h| h.contains('\t'));
            return Err((
                *first_line,
                format!(
                    "need two numeric columns (pressure, then volume) in the first data row{}",
                    if tabs {
                        "; the columns are separated by tabs: lungdyn reads comma-separated values \
                         (export as CSV with ',' between columns)"
                    } else {
                        ""
                    }
                ),
            ));
        }
        let header = |i: usize| headers.get(i).unwrap_or("");
        let looks_pressure = |i: usize| {
            let lower = header(i).to_ascii_lowercase();
            PRESSURE_KEYS.iter().any(|k| lower.contains(k))
                || header_unit(header(i), PRESSURE_UNITS).is_some()
        };
        let pressures: Vec<usize> = numeric
            .iter()
            .copied()
            .filter(|&i| looks_pressure(i))
            .collect();
        ambiguous(headers, &pressures, "pressures")?;
        let pc = numeric
            .iter()
            .copied()
            .find(|&i| looks_pressure(i))
            .unwrap_or(numeric[0]);
        let volumes: Vec<usize> = numeric
            .iter()
            .copied()
            .filter(|&i| i != pc && looks_volume(header(i)))
            .collect();
        ambiguous(headers, &volumes, "volumes")?;
        let vc = volumes.first().copied().unwrap_or(
            *numeric
                .iter()
                .find(|&&i| i != pc)
                .expect("two numeric columns"),
        );
        Ok(Self {
            phase,
            pressure: pc,
            volume: vc,
            p_header: header(pc).to_string(),
            v_header: header(vc).to_string(),
        })
    }
}

/// The columns' units, and whether the volumes are changes above FRC (and what is added).
struct Units {
    pressure: ColumnUnit,
    volume: ColumnUnit,
    /// Why the volumes are read as changes above FRC ("--frc", "--relative", "header"), and
    /// whether Table 5.2's FRC was assumed.
    relative: Option<(&'static str, bool)>,
    /// The FRC added to every volume, ml.
    frc_add: Option<f64>,
}

impl Units {
    /// From the headers and the options; a header and a flag that disagree are refused.
    fn of(cols: &Columns, opts: &CurveOptions) -> Result<Self, (u64, String)> {
        let v_header = &cols.v_header;
        let pressure = match header_unit(&cols.p_header, PRESSURE_UNITS) {
            Some((name, factor)) => ColumnUnit {
                name,
                factor,
                from: "header",
            },
            None => ColumnUnit {
                name: "cmH2O",
                factor: 1.0,
                from: "default",
            },
        };
        // Changes above FRC: declared by a flag, or by the header (`delta_volume_ml`, `volume
        // above FRC (L)`; `dV_ml` is not enough: it must say delta or above FRC).
        let header_relative = {
            let t: Vec<String> = lung_model::units::tokens(v_header).collect();
            t.iter().any(|w| w == "delta" || w == "abovefrc")
                || t.windows(2).any(|w| w[0] == "above" && w[1] == "frc")
        };
        let relative: Option<(&'static str, bool)> = if opts.frc_ml.is_some() {
            Some(("--frc", false))
        } else if opts.relative {
            Some(("--relative", true))
        } else if header_relative {
            Some(("header", true))
        } else {
            None
        };
        let frc_add = opts.frc_ml.or(relative.map(|_| Boundary::HUMAN.frc_ml));
        let unit = |name, factor, from| ColumnUnit { name, factor, from };
        let volume = match (header_unit(v_header, VOLUME_UNITS), opts.volume_unit) {
            (Some((name, _)), Some(flag)) if (flag == VolumeUnit::Litre) != (name == "L") => {
                return Err((
                    1,
                    format!(
                        "the volume column {v_header:?} says {name}, but --volume-unit says {}: drop \
                         the flag or fix the header",
                        if flag == VolumeUnit::Litre { "l" } else { "ml" }
                    ),
                ));
            }
            (Some((name, factor)), _) => unit(name, factor, "header"),
            (None, Some(VolumeUnit::Litre)) => unit("L", 1000.0, "flag"),
            (None, Some(VolumeUnit::Ml)) => unit("ml", 1.0, "flag"),
            (None, None) => unit("ml", 1.0, "default"),
        };
        Ok(Self {
            pressure,
            volume,
            relative,
            frc_add,
        })
    }
}

/// One row as a sample (cmH2O, ml), each value checked against the physical ranges with what
/// probably went wrong (swapped columns, a unit, changes above FRC); `raw_ml` gathers the volume
/// column's range as given.
fn sample_of(
    line: u64,
    rec: &csv::StringRecord,
    cols: &Columns,
    units: &Units,
    raw_ml: &mut (f64, f64),
) -> Result<PvSample, (u64, String)> {
    use lung_model::plausible::{volume_unit_hint, LUNGS_VOLUME_ML, PRESSURE_CMH2O};
    let (p_header, v_header) = (&cols.p_header, &cols.v_header);
    let value = |col: usize, what: &str| -> Result<f64, (u64, String)> {
        let field = rec.get(col).unwrap_or("");
        let v: f64 = field
            .parse()
            .map_err(|_| (line, format!("{what} {field:?} is not a number")))?;
        if v.is_finite() {
            Ok(v)
        } else {
            Err((
                line,
                format!("{what} is {field}: every sample must be a finite number"),
            ))
        }
    };
    let phase = match cols.phase {
        None => None,
        Some(c) => match rec.get(c).unwrap_or("").to_ascii_lowercase().as_str() {
            "inhale" | "inhalation" | "inspiration" | "in" => Some(Phase::Inhale),
            "exhale" | "exhalation" | "expiration" | "ex" => Some(Phase::Exhale),
            other => return Err((line, format!("phase {other:?}: use inhale or exhale"))),
        },
    };
    let pressure = value(cols.pressure, "pressure")? * units.pressure.factor;
    let raw_volume = value(cols.volume, "volume")?;
    let volume_factor = units.volume.factor;
    *raw_ml = (
        raw_ml.0.min(raw_volume * volume_factor),
        raw_ml.1.max(raw_volume * volume_factor),
    );
    let volume = raw_volume * volume_factor + units.frc_add.unwrap_or(0.0);
    if !PRESSURE_CMH2O.contains(pressure) {
        // Swapped columns: the "pressure" looks like lung volumes and the "volume" like pressures.
        let swapped = LUNGS_VOLUME_ML.contains(pressure)
            && PRESSURE_CMH2O.contains(raw_volume * volume_factor);
        return Err((
            line,
            format!(
                "{}{}",
                PRESSURE_CMH2O.check(pressure, None).unwrap_err(),
                if swapped {
                    format!(
                        ": column {p_header:?} (taken as pressure) holds lung volumes — are the columns \
                         swapped? Name them in the header (e.g. pressure_cmH2O, volume_ml)"
                    )
                } else if units.pressure.from == "default" {
                    format!(
                        ": column {p_header:?} states no unit and was read as cmH2O; name its unit in the \
                         header (pressure_kPa, pressure_mmHg, pressure_Pa, ...)"
                    )
                } else {
                    String::new()
                }
            ),
        ));
    }
    if !LUNGS_VOLUME_ML.contains(volume) {
        // A wrong unit, or (below the smallest lung, a neonate's FRC) changes above FRC as
        // ventilators and compliance curves give them: both said when both fit.
        let unit = if units.volume.from != "header" {
            volume_unit_hint(volume, if volume_factor == 1000.0 { "l" } else { "ml" })
        } else {
            None
        };
        let relative = (units.frc_add.is_none() && raw_volume * volume_factor < LUNGS_VOLUME_ML.lo)
            .then(|| {
                format!(
                    "a lung volume is absolute and at least {} ml; column {v_header:?} looks like \
                     changes above FRC: pass --relative (with --frc ML, else Table 5.2's {} ml is \
                     assumed) or name the column volume_above_frc_ml",
                    LUNGS_VOLUME_ML.lo,
                    Boundary::HUMAN.frc_ml
                )
            });
        let hint = match (unit, relative) {
            (Some(u), Some(r)) => Some(format!("{r}; or, {u}")),
            (u, r) => u.or(r),
        };
        return Err((
            line,
            LUNGS_VOLUME_ML.check(volume, hint).unwrap_err().to_string(),
        ));
    }
    Ok(PvSample {
        pressure,
        volume,
        phase,
    })
}

/// The loop's pressure and volume swings against human ranges: a loop with no change at all is the
/// fit's to refuse (with its own message); a change of the wrong size is a unit question.
fn check_swings(samples: &[PvSample], cols: &Columns, units: &Units) -> Result<(), (u64, String)> {
    use lung_model::plausible::{PRESSURE_SWING_CMH2O, TIDAL_VOLUME_ML};
    let span = |f: fn(&PvSample) -> f64| {
        samples
            .iter()
            .map(f)
            .fold((f64::MAX, f64::MIN), |(lo, hi), v| (lo.min(v), hi.max(v)))
    };
    let (p_lo, p_hi) = span(|s| s.pressure);
    let (v_lo, v_hi) = span(|s| s.volume);
    if samples.len() > 1 && p_hi > p_lo {
        PRESSURE_SWING_CMH2O
            .check(
                p_hi - p_lo,
                Some(format!(
                    "pressure column {:?} read in {} ({}); check its unit",
                    cols.p_header, units.pressure.name, units.pressure.from
                )),
            )
            .map_err(|e| (0, e.to_string()))?;
    }
    if samples.len() > 1 && v_hi > v_lo {
        TIDAL_VOLUME_ML
            .check(
                v_hi - v_lo,
                Some(format!(
                    "volume column {:?} read in {} ({}); check its unit",
                    cols.v_header, units.volume.name, units.volume.from
                )),
            )
            .map_err(|e| (0, e.to_string()))?;
    }
    Ok(())
}

/// Whether a volume column's header names a volume (and not a flow, which shares its units).
fn looks_volume(header: &str) -> bool {
    let lower = header.to_ascii_lowercase();
    !lower.contains("flow")
        && !lower.contains("/s")
        && !lower.contains("/min")
        && (lower.contains("vol") || header_unit(header, VOLUME_UNITS).is_some())
}

/// Refuse two or more candidate columns `cols` for one quantity (`what`: "pressures", "volumes").
fn ambiguous(headers: &csv::StringRecord, cols: &[usize], what: &str) -> Result<(), (u64, String)> {
    if cols.len() < 2 {
        return Ok(());
    }
    let list = cols
        .iter()
        .map(|&i| format!("{:?} (column {})", headers.get(i).unwrap_or(""), i + 1))
        .collect::<Vec<_>>()
        .join(", ");
    Err((
        1,
        format!(
            "{} columns look like {what}: {list}; which one to fit is ambiguous: keep one in the file \
             (or rename the others so their names do not say {what})",
            if cols.len() == 2 { "two".to_string() } else { cols.len().to_string() },
        ),
    ))
}

/// The first row must name the columns: a row of numbers there is data without a header (its
/// first sample would become the column names and be lost, and no unit would be stated).
fn check_header(headers: &csv::StringRecord) -> Result<(), (u64, String)> {
    let fields: Vec<&str> = headers
        .iter()
        .map(|h| h.trim_start_matches('\u{feff}'))
        .collect();
    if fields.len() >= 2
        && fields
            .iter()
            .all(|h| !h.is_empty() && h.parse::<f64>().is_ok())
    {
        return Err((
            1,
            format!(
                "the first row holds numbers ({}), not a header: the first row must name each column \
                 with its unit, e.g. pressure_cmH2O,volume_ml (every input states its units)",
                fields.join(", ")
            ),
        ));
    }
    Ok(())
}

/// Semicolon-separated tables (often with decimal commas, as spreadsheets in many locales write
/// them) would split into the wrong fields: refuse them naming the separator.
fn check_separators(bytes: &[u8]) -> Result<(), (u64, String)> {
    let text = String::from_utf8_lossy(&bytes[..bytes.len().min(64 << 10)]);
    let mut lines = text
        .lines()
        .map(|l| l.trim_start_matches('\u{feff}').trim())
        .filter(|l| !l.is_empty());
    let Some(header) = lines.next() else {
        return Ok(());
    };
    if !(header.contains(';') && header.split(';').count() > header.split(',').count()) {
        return Ok(());
    }
    let decimal_comma = lines.take(20).any(|l| {
        l.split(';').any(|f| {
            let f = f.trim().trim_start_matches(['-', '+']);
            f.split_once(',').is_some_and(|(a, b)| {
                !a.is_empty()
                    && !b.is_empty()
                    && a.bytes().all(|c| c.is_ascii_digit())
                    && b.bytes().all(|c| c.is_ascii_digit())
            })
        })
    });
    Err((
        1,
        format!(
            "the columns are separated by semicolons (;){}: lungdyn reads comma-separated values with \
             decimal points — export the table as CSV with ',' between columns and '.' in numbers \
             (e.g. 0.5,2400.0)",
            if decimal_comma {
                " and the numbers use a decimal comma (0,5)"
            } else {
                ""
            }
        ),
    ))
}

/// `why` (`--frc`, `--relative` or the header) declares the volume column as changes above FRC: a
/// column whose lowest value is itself a plausible FRC and larger than the loop's whole swing holds
/// absolute volumes already, and adding FRC would double it.
fn check_relative(
    raw_ml: (f64, f64),
    frc: f64,
    header: &str,
    why: &str,
) -> Result<(), (u64, String)> {
    use lung_model::plausible::{compact, FRC_ML};
    let (lo, hi) = raw_ml;
    if FRC_ML.contains(lo) && lo >= hi - lo {
        let (declares, drop) = match why {
            "header" => (
                format!("the header {header:?}"),
                "rename the column".to_string(),
            ),
            flag => (flag.to_string(), format!("drop {flag}")),
        };
        return Err((
            0,
            format!(
                "{declares} declares the volumes as changes above FRC ({} ml), but column {header:?} \
                 already looks absolute: its lowest value is {} ml (a plausible FRC) and the loop spans \
                 only {} ml; with --frc the FRC would be {} ml. For absolute volumes, {drop}",
                compact(frc),
                compact(lo),
                compact(hi - lo),
                compact(lo + frc)
            ),
        ));
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;

    fn with(unit: Option<VolumeUnit>) -> CurveOptions {
        CurveOptions {
            volume_unit: unit,
            ..Default::default()
        }
    }

    fn err(csv: &[u8], opts: &CurveOptions) -> (u64, String) {
        parse_curve(csv, opts).unwrap_err()
    }

    #[test]
    fn curves_parse_with_units_phase_and_extra_columns() {
        let csv = b"time_s, pressure (cmH2O), volume (L), phase\n0, 0.0, 2.4, inhale\n0.1, 1.5, 2.5, inhale\n\n0.2, 3.0, 2.9, exhale\n";
        let c = parse_curve(csv, &with(None)).unwrap();
        // A time column comes first, but the named columns win; the header's L is used.
        assert_eq!(c.pressure_column, "pressure (cmH2O)");
        assert_eq!(c.volume_column, "volume (L)");
        assert_eq!((c.volume_unit.name, c.volume_unit.from), ("L", "header"));
        assert_eq!(c.samples[2].volume, 2900.0);
        // Unnamed columns: the first two numeric ones.
        let c = parse_curve(b"a,b,c\n1,2400,3\n4,2900,1\n", &with(None)).unwrap();
        assert_eq!(
            (c.pressure_column.as_str(), c.volume_column.as_str()),
            ("a", "b")
        );
        let csv = b"pressure,volume,phase\n0,2400,inhale\n5,2900,exhale\n";
        let c = parse_curve(csv, &with(Some(VolumeUnit::Ml))).unwrap();
        assert_eq!(c.samples.len(), 2);
        assert_eq!(c.samples[1].phase, Some(Phase::Exhale));
        assert!(c.has_phase);
    }

    #[test]
    fn units_in_the_header_are_converted_and_reported() {
        let c = parse_curve(b"pressure_kPa,volume_ml\n0,2400\n1,2900\n", &with(None)).unwrap();
        assert_eq!(
            (c.pressure_unit.name, c.pressure_unit.from),
            ("kPa", "header")
        );
        assert!((c.samples[1].pressure - 10.197_162).abs() < 1e-9);
        let c = parse_curve(b"Paw [mmHg],vol_L\n0,2.4\n7.4,2.9\n", &with(None)).unwrap();
        assert_eq!(c.pressure_unit.name, "mmHg");
        assert!((c.samples[1].pressure - 10.06).abs() < 0.01);
        assert_eq!(c.samples[1].volume, 2900.0);
        // A header that contradicts the flag is refused.
        let (_, m) = err(
            b"pressure,volume_L\n0,2.4\n5,2.9\n",
            &with(Some(VolumeUnit::Ml)),
        );
        assert!(m.contains("says L") && m.contains("--volume-unit"), "{m}");
    }

    #[test]
    fn silent_unit_mistakes_are_refused_with_the_fix() {
        // Volume first in unnamed columns: the "pressure" is 2400.
        let (line, m) = err(b"a,b\n2400,0\n2900,10\n", &with(None));
        assert_eq!(line, 2);
        assert!(m.contains("swapped"), "{m}");
        // ml data declared as litres.
        let (_, m) = err(
            b"pressure,volume\n0,2400\n10,2900\n",
            &with(Some(VolumeUnit::Litre)),
        );
        assert!(m.contains("drop --volume-unit l"), "{m}");
        // Litres read as ml.
        let (_, m) = err(b"pressure,volume\n0,2.4\n10,2.9\n", &with(None));
        assert!(m.contains("--volume-unit l"), "{m}");
        // Volumes shifted below zero: relative volumes need --frc.
        let (_, m) = err(b"pressure,volume\n0,-200\n10,300\n", &with(None));
        assert!(m.contains("--frc"), "{m}");
        let c = parse_curve(
            b"pressure,volume\n0,-200\n10,300\n",
            &CurveOptions {
                frc_ml: Some(2400.0),
                ..Default::default()
            },
        )
        .unwrap();
        assert_eq!(c.samples[0].volume, 2200.0);
        // One absurd sample names its line.
        let (line, m) = err(b"pressure,volume\n0,2400\n5,1e308\n10,2900\n", &with(None));
        assert_eq!(line, 3, "{m}");
        // Pressure in Pa without a unit: far beyond any pressure.
        let (_, m) = err(b"pressure,volume\n0,2400\n980,2900\n", &with(None));
        assert!(m.contains("states no unit"), "{m}");
        // A loop with a pressure change far too small for cmH2O (kPa without a unit?).
        let (line, m) = err(b"pressure,volume\n1,2400\n1.1,2900\n", &with(None));
        assert_eq!(line, 0);
        assert!(m.contains("pressure range"), "{m}");
    }

    #[test]
    fn tables_that_would_be_misread_are_refused_with_the_reason() {
        let o = with(None);
        // No header: the first sample would become the column names.
        let (line, m) = err(b"0.0,2400.0\n5.0,2600.0\n10.0,2900.0\n", &o);
        assert_eq!(line, 1);
        assert!(
            m.contains("not a header") && m.contains("pressure_cmH2O,volume_ml"),
            "{m}"
        );
        // Two volume columns (the same name twice, or two names that both say volume).
        let (_, m) = err(
            b"pressure_cmH2O,volume_ml,volume_ml\n0,2400,2500\n10,2900,3000\n",
            &o,
        );
        assert!(
            m.contains("two columns look like volumes") && m.contains("column 3"),
            "{m}"
        );
        let (_, m) = err(
            b"paw_cmH2O,pes_cmH2O,volume_ml\n0,-5,2400\n10,-10,2900\n",
            &o,
        );
        assert!(m.contains("two columns look like pressures"), "{m}");
        // A flow column shares the volume units but is not a volume.
        let c = parse_curve(
            b"flow (L/s),pressure_cmH2O,volume_ml\n0.5,0,2400\n0.4,10,2900\n",
            &o,
        )
        .unwrap();
        assert_eq!(c.volume_column, "volume_ml");
        // Semicolons with decimal commas, said as such (not "lung volume = 0 ml").
        let (_, m) = err(b"pressure_cmH2O;volume_ml\n0,0;2400,00\n10,5;2900,0\n", &o);
        assert!(
            m.contains("semicolons") && m.contains("decimal comma"),
            "{m}"
        );
        let (_, m) = err(b"pressure_cmH2O\tvolume_ml\n0\t2400\n10\t2900\n", &o);
        assert!(
            m.contains("two numeric columns") && m.contains("tabs"),
            "{m}"
        );
        // --frc on volumes that are already absolute.
        let frc = CurveOptions {
            frc_ml: Some(2400.0),
            ..Default::default()
        };
        let (_, m) = err(b"pressure,volume\n0,2400\n5,2650\n10,2900\n", &frc);
        assert!(
            m.contains("--frc") && m.contains("already") && m.contains("4800"),
            "{m}"
        );
        // --relative, or a header that says so, on absolute volumes: the same refusal.
        let rel = CurveOptions {
            relative: true,
            ..Default::default()
        };
        let (_, m) = err(b"pressure,volume\n0,2400\n5,2650\n10,2900\n", &rel);
        assert!(m.contains("drop --relative"), "{m}");
        let (_, m) = err(b"pressure,delta_volume_ml\n0,2400\n10,2900\n", &o);
        assert!(m.contains("rename the column"), "{m}");
        // Changes above FRC, starting at 0 or a little off it, are what --frc is for.
        for csv in [
            &b"pressure,volume\n0,0\n10,500\n"[..],
            b"pressure,volume\n0,120\n10,620\n",
        ] {
            assert!(parse_curve(csv, &frc).is_ok());
        }
    }

    #[test]
    fn relative_volumes_are_accepted_when_declared_and_hinted_when_they_look_relative() {
        let o = with(None);
        // Volume above FRC from a ventilator or Guyton's curve: 2.25 ml, 17 ml, 0 ml first.
        for first in ["2.25", "17", "0"] {
            let csv = format!("pressure_cmH2O,volume_ml\n0,{first}\n5,250\n10,500\n");
            let (line, m) = err(csv.as_bytes(), &o);
            assert_eq!(line, 2);
            assert!(m.contains("--relative") && m.contains("--frc"), "{m}");
            // Declared by the flag: FRC is Table 5.2's, said so.
            let c = parse_curve(
                csv.as_bytes(),
                &CurveOptions {
                    relative: true,
                    ..Default::default()
                },
            )
            .unwrap();
            assert_eq!(c.relative, Some(("--relative", true)));
            assert_eq!(c.frc_added_ml, Some(2400.0));
            assert_eq!(c.samples[2].volume, 2900.0);
        }
        // Declared by the header; --frc gives the FRC.
        for header in [
            "delta_volume_ml",
            "volume above FRC (ml)",
            "Volume_above_FRC_L",
        ] {
            let scale = if header.ends_with('L') { 0.001 } else { 1.0 };
            let csv = format!(
                "pressure_cmH2O,{header}\n0,{}\n10,{}\n",
                2.25 * scale,
                500.0 * scale
            );
            let c = parse_curve(csv.as_bytes(), &o).unwrap();
            assert_eq!(c.relative, Some(("header", true)), "{header}");
            let c = parse_curve(
                csv.as_bytes(),
                &CurveOptions {
                    frc_ml: Some(3000.0),
                    ..Default::default()
                },
            )
            .unwrap();
            assert_eq!(c.relative, Some(("--frc", false)));
            assert!((c.samples[1].volume - 3500.0).abs() < 1e-9, "{header}");
        }
        // Absolute volumes are not relative: no hint needed, none given.
        let c = parse_curve(b"pressure_cmH2O,volume_ml\n0,2400\n10,2900\n", &o).unwrap();
        assert_eq!(c.relative, None);
    }

    #[test]
    fn bad_csv_is_refused_with_the_line() {
        let o = with(None);
        let (line, msg) = err(b"p,v\n0,1000\n1,nan\n", &o);
        assert_eq!(line, 3);
        assert!(msg.contains("finite"), "{msg}");
        let (line, msg) = err(b"p,v\n0,1000\n1,abc\n", &o);
        assert_eq!((line, msg.contains("not a number")), (3, true));
        assert!(err(b"p,v\n", &o).1.contains("no data"));
        assert!(err(b"a,b\nx,y\n", &o).1.contains("two numeric"));
        assert!(err(b"p,v,phase\n0,1000,sideways\n", &o)
            .1
            .contains("inhale or exhale"));
        assert!(err(&[0xff, 0xfe, 0x00, 0x12], &o).1.contains("binary"));
    }
}
