//! PV constants files: what `lungdyn pv fit` writes and a scene loads (`[pv] constants =
//! "file.toml"`): boundary values and each phase's constants (eq. 5.11 and EQUATIONS §1.1),
//! versioned, validated on load. (Measured curves, the fit's input, are read at bake time:
//! `lung_bake::pv::curve`.)

use std::path::{Path, PathBuf};

use serde::{Deserialize, Serialize};

use super::{Boundary, PhaseConstants, PvError};

/// Errors reading or writing a PV constants file.
#[derive(Debug, thiserror::Error)]
pub enum PvFileError {
    /// The file could not be read or written.
    #[error("{}: {source}", path.display())]
    Io {
        /// Path.
        path: PathBuf,
        /// OS error.
        source: std::io::Error,
    },
    /// Writing refused or failed (a target that is not a regular file, an OS error).
    #[error(transparent)]
    Write(#[from] outfile::WriteError),
    /// Not TOML of the constants format (the parser's message names line and column).
    #[error("{}: {message}", path.display())]
    Toml {
        /// Path.
        path: PathBuf,
        /// Parser message.
        message: String,
    },
    /// Another format version.
    #[error("{}: format {found} is not supported (this build reads format {CONSTANTS_FORMAT})", path.display())]
    Format {
        /// Path.
        path: PathBuf,
        /// Format in the file.
        found: u32,
    },
    /// A phase's constants cannot produce a curve.
    #[error("{}: [{phase}]", path.display())]
    Constants {
        /// Path.
        path: PathBuf,
        /// "inhale" or "exhale".
        phase: &'static str,
        /// Why.
        source: PvError,
    },
    /// The boundary values are outside human ranges.
    #[error("{}: [boundary]: {source}", path.display())]
    Boundary {
        /// Path.
        path: PathBuf,
        /// The value out of range.
        source: crate::plausible::Implausible,
    },
    /// The file could not be read within the limits.
    #[error(transparent)]
    Input(#[from] crate::input::InputError),
}

/// Version of the constants file format.
pub const CONSTANTS_FORMAT: u32 = 1;

/// A patient's PV constants: what `lungdyn pv fit` writes and a scene can load.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields)]
pub struct PvConstantsFile {
    /// [`CONSTANTS_FORMAT`].
    pub format: u32,
    /// Where the constants came from (free text).
    pub source: String,
    /// Boundary values (Table 5.2 meaning).
    pub boundary: Boundary,
    /// Inhalation constants.
    pub inhale: PhaseConstants,
    /// Exhalation constants.
    pub exhale: PhaseConstants,
}

impl PvConstantsFile {
    /// Load and validate.
    pub fn load(path: &Path) -> Result<Self, PvFileError> {
        let text = crate::input::read_text_bounded(path, crate::input::ReadLimits::CONFIG)?;
        let path_buf = || path.to_path_buf();
        let file: Self = toml::from_str(&text).map_err(|e| PvFileError::Toml {
            path: path_buf(),
            message: e.to_string(),
        })?;
        if file.format != CONSTANTS_FORMAT {
            return Err(PvFileError::Format {
                path: path_buf(),
                found: file.format,
            });
        }
        for (phase, k) in [("inhale", &file.inhale), ("exhale", &file.exhale)] {
            k.validate()
                .and_then(|()| super::phase_curve(k, 100).map(|_| ()))
                .map_err(|source| PvFileError::Constants {
                    path: path_buf(),
                    phase,
                    source,
                })?;
        }
        file.boundary
            .check_plausible()
            .map_err(|source| PvFileError::Boundary {
                path: path_buf(),
                source,
            })?;
        Ok(file)
    }

    /// Write atomically, with a comment header.
    pub fn save(&self, path: &Path) -> Result<(), PvFileError> {
        let body = toml::to_string_pretty(self).map_err(|e| PvFileError::Toml {
            path: path.to_path_buf(),
            message: e.to_string(),
        })?;
        outfile::write_atomically(path, |w| {
            use std::io::Write;
            writeln!(w, "# lungdyn PV constants (EQUATIONS.md §1): use from a scene with [pv] constants = \"{}\"", path.file_name().map(|f| f.to_string_lossy()).unwrap_or_default())?;
            w.write_all(body.as_bytes())
        })
        .map_err(PvFileError::Write)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn constants_files_round_trip() {
        let p = super::super::preset("colebatch-human").unwrap();
        let file = PvConstantsFile {
            format: CONSTANTS_FORMAT,
            source: "test".into(),
            boundary: p.boundary,
            inhale: p.inhale.clone(),
            exhale: p.exhale.clone(),
        };
        let path = std::env::temp_dir().join(format!("lungdyn-pv-{}.toml", std::process::id()));
        file.save(&path).unwrap();
        assert_eq!(PvConstantsFile::load(&path).unwrap(), file);
        std::fs::write(&path, "format = 1\n").unwrap();
        assert!(PvConstantsFile::load(&path)
            .unwrap_err()
            .to_string()
            .contains("missing field"));
        std::fs::remove_file(&path).ok();
    }
}
