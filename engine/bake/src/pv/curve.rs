//! Measured PV curves (the input of `lungdyn pv fit`, the output of `lungdyn pv simulate`): a CSV
//! with a header row; the first two columns whose first data row is numeric are pressure (cmH2O)
//! and volume (ml, or litres with [`VolumeUnit::Litre`]); an optional `phase` column
//! (`inhale`/`exhale`). Samples in time order.

use std::path::{Path, PathBuf};

use lung_model::pv::Phase;

use super::fit::PvSample;

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
    /// Malformed CSV.
    #[error("{}: line {line}: {message}", path.display())]
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
}

/// Read a PV curve CSV.
pub fn read_curve(path: &Path, unit: VolumeUnit) -> Result<CurveFile, CurveError> {
    let bytes = std::fs::read(path).map_err(|source| CurveError::Io {
        path: path.to_path_buf(),
        source,
    })?;
    parse_curve(&bytes, unit).map_err(|(line, message)| CurveError::Csv {
        path: path.to_path_buf(),
        line,
        message,
    })
}

/// Parse PV curve CSV bytes; errors carry the 1-based line.
pub fn parse_curve(bytes: &[u8], unit: VolumeUnit) -> Result<CurveFile, (u64, String)> {
    let mut reader = csv::ReaderBuilder::new()
        .flexible(true)
        .trim(csv::Trim::All)
        .from_reader(bytes);
    let headers = reader
        .headers()
        .map_err(|e| (1, format!("cannot read the header row: {e}")))?
        .clone();
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
    let Some((first_line, first)) = records.first() else {
        return Err((2, "no data rows after the header".into()));
    };
    let phase_col = headers.iter().position(|h| h.eq_ignore_ascii_case("phase"));
    let numeric: Vec<usize> = (0..first.len())
        .filter(|&i| Some(i) != phase_col && first.get(i).is_some_and(|f| f.parse::<f64>().is_ok()))
        .collect();
    if numeric.len() < 2 {
        return Err((
            *first_line,
            "need two numeric columns (pressure in cmH2O, then volume) in the first data row"
                .into(),
        ));
    }
    // Columns named for what they hold win (a time column often comes first); else the first two.
    let named = |keys: &[&str]| {
        numeric.iter().copied().find(|&i| {
            let h = headers.get(i).unwrap_or("").to_ascii_lowercase();
            keys.iter().any(|k| h.contains(k))
        })
    };
    let pc = named(&["pressure", "cmh2o", "pes", "paw", "ptp"]).unwrap_or(numeric[0]);
    let vc = named(&["volume", "vol", "(ml)", "(l)", "_ml", "_l"])
        .filter(|&v| v != pc)
        .unwrap_or(
            *numeric
                .iter()
                .find(|&&i| i != pc)
                .expect("two numeric columns"),
        );
    let scale = match unit {
        VolumeUnit::Ml => 1.0,
        VolumeUnit::Litre => 1000.0,
    };
    let mut samples = Vec::with_capacity(records.len());
    for (line, rec) in &records {
        let value = |col: usize, what: &str| -> Result<f64, (u64, String)> {
            let field = rec.get(col).unwrap_or("");
            let v: f64 = field
                .parse()
                .map_err(|_| (*line, format!("{what} {field:?} is not a number")))?;
            if v.is_finite() {
                Ok(v)
            } else {
                Err((
                    *line,
                    format!("{what} is {field}: every sample must be a finite number"),
                ))
            }
        };
        let phase = match phase_col {
            None => None,
            Some(c) => match rec.get(c).unwrap_or("").to_ascii_lowercase().as_str() {
                "inhale" | "inhalation" | "inspiration" | "in" => Some(Phase::Inhale),
                "exhale" | "exhalation" | "expiration" | "ex" => Some(Phase::Exhale),
                other => return Err((*line, format!("phase {other:?}: use inhale or exhale"))),
            },
        };
        samples.push(PvSample {
            pressure: value(pc, "pressure")?,
            volume: value(vc, "volume")? * scale,
            phase,
        });
    }
    Ok(CurveFile {
        samples,
        pressure_column: headers.get(pc).unwrap_or("").to_string(),
        volume_column: headers.get(vc).unwrap_or("").to_string(),
        has_phase: phase_col.is_some(),
    })
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn curves_parse_with_units_phase_and_extra_columns() {
        let csv = b"time_s, pressure (cmH2O), volume (L), phase\n0, 0.0, 2.4, inhale\n0.1, 1.5, 2.5, inhale\n\n0.2, 3.0, 2.9, exhale\n";
        let c = parse_curve(csv, VolumeUnit::Litre).unwrap();
        // A time column comes first, but the named columns win.
        assert_eq!(c.pressure_column, "pressure (cmH2O)");
        assert_eq!(c.volume_column, "volume (L)");
        assert_eq!(c.samples[2].volume, 2900.0);
        // Unnamed columns: the first two numeric ones.
        let c = parse_curve(b"a,b,c\n1,2,3\n", VolumeUnit::Ml).unwrap();
        assert_eq!(
            (c.pressure_column.as_str(), c.volume_column.as_str()),
            ("a", "b")
        );
        let csv = b"pressure,volume,phase\n0,2400,inhale\n5,2900,exhale\n";
        let c = parse_curve(csv, VolumeUnit::Ml).unwrap();
        assert_eq!(c.samples.len(), 2);
        assert_eq!(c.samples[1].phase, Some(Phase::Exhale));
        assert!(c.has_phase);
    }

    #[test]
    fn bad_csv_is_refused_with_the_line() {
        let (line, msg) = parse_curve(b"p,v\n0,1\n1,nan\n", VolumeUnit::Ml).unwrap_err();
        assert_eq!(line, 3);
        assert!(msg.contains("finite"), "{msg}");
        let (line, msg) = parse_curve(b"p,v\n0,1\n1,abc\n", VolumeUnit::Ml).unwrap_err();
        assert_eq!((line, msg.contains("not a number")), (3, true));
        assert!(parse_curve(b"p,v\n", VolumeUnit::Ml)
            .unwrap_err()
            .1
            .contains("no data"));
        assert!(parse_curve(b"a,b\nx,y\n", VolumeUnit::Ml)
            .unwrap_err()
            .1
            .contains("two numeric"));
        assert!(parse_curve(b"p,v,phase\n0,1,sideways\n", VolumeUnit::Ml)
            .unwrap_err()
            .1
            .contains("inhale or exhale"));
        assert!(parse_curve(&[0xff, 0xfe, 0x00, 0x12], VolumeUnit::Ml).is_err());
    }
}
