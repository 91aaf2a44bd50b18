//! The `[slicer]` table: the breathing lungs sent to 3D Slicer over OpenIGTLink while a demo runs
//! (issue 38; docs/SLICER.md). `lungdyn demo --igtl-serve [PORT]` turns it on from the command line.
//!
//! ```toml
//! [slicer]
//! serve = true        # lungdyn listens; Slicer's OpenIGTLinkIF connects as a client
//! port = 18945        # 18944 is the tracker's OpenIGTLink port
//! rate_hz = 30        # meshes sent per second (the engine's newest frame each time)
//! allow = []          # clients besides loopback: ["10.0.0.5", "192.168.1.0/24"]
//! # connect = "127.0.0.1:18944"  # instead of serving: connect to Slicer's server (its connector
//! #                              # of type Server, 18944 by default), retried every second
//! ```

use serde::{Deserialize, Serialize};

use crate::TableError;

/// The default port: the OpenIGTLink port (18944) is the tracker's.
pub const DEFAULT_PORT: u16 = 18945;
/// Meshes per second by default.
pub const DEFAULT_RATE_HZ: f64 = 30.0;
/// The fastest rate accepted: the engine's frame rate (a frame is never sent twice).
pub const MAX_RATE_HZ: f64 = 60.0;

/// `[slicer]` table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct SlicerScene {
    /// Serve the lungs over OpenIGTLink during `lungdyn demo` (off by default).
    pub serve: bool,
    /// TCP port (bound on loopback unless `allow` names more).
    pub port: u16,
    /// Meshes per second.
    pub rate_hz: f64,
    /// Clients besides loopback: addresses or networks; `--igtl-serve-allow` adds to them (checked
    /// when the demo starts, before anything is baked).
    pub allow: Vec<String>,
    /// Instead of serving, connect to Slicer's OpenIGTLink server at HOST:PORT (its connector's
    /// default type; `--igtl-connect` over it), retried every second.
    #[serde(skip_serializing_if = "Option::is_none")]
    pub connect: Option<String>,
}

impl Default for SlicerScene {
    fn default() -> Self {
        Self {
            serve: false,
            port: DEFAULT_PORT,
            rate_hz: DEFAULT_RATE_HZ,
            allow: Vec::new(),
            connect: None,
        }
    }
}

impl SlicerScene {
    /// Range checks (the allow-list's grammar is checked by the server that parses it).
    pub fn validate(&self) -> Result<(), TableError> {
        let bad = |why: String| Err(TableError::Slicer(why));
        if self.port == 0 {
            return bad("port = 0: name the port Slicer connects to (18945 by default)".into());
        }
        if let Some(c) = &self.connect {
            let port = c.rsplit_once(':').map(|(h, p)| (h, p.parse::<u16>()));
            if !matches!(port, Some((h, Ok(p))) if !h.is_empty() && p > 0) {
                return bad(format!(
                    "connect = {c:?}: give HOST:PORT of Slicer's OpenIGTLink server, e.g. \
                     \"127.0.0.1:18944\""
                ));
            }
            if self.serve {
                return bad(
                    "serve = true and connect both set: lungdyn either listens for Slicer or \
                     connects to it, give one"
                        .into(),
                );
            }
        }
        if !(self.rate_hz.is_finite() && (1.0..=MAX_RATE_HZ).contains(&self.rate_hz)) {
            return bad(format!(
                "rate_hz = {}: send 1 to {MAX_RATE_HZ} meshes per second (the engine draws 60; Slicer \
                 redraws comfortably at 30)",
                crate::compact(self.rate_hz)
            ));
        }
        Ok(())
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn off_by_default_and_values_out_of_range_are_named() {
        let d = SlicerScene::default();
        assert!(!d.serve);
        assert_eq!((d.port, d.rate_hz), (18945, 30.0));
        assert!(d.validate().is_ok());
        let t: SlicerScene = toml::from_str("serve = true\nport = 20000\nrate_hz = 10\n").unwrap();
        assert!(t.serve && t.port == 20000 && t.validate().is_ok());
        for (text, words) in [
            ("port = 0\n", "port = 0"),
            ("rate_hz = 0.5\n", "rate_hz = 0.5"),
            ("rate_hz = 120\n", "rate_hz = 120"),
            ("rate_hz = nan\n", "rate_hz = NaN"),
            ("connect = \"slicer-host\"\n", "HOST:PORT"),
            ("connect = \":18944\"\n", "HOST:PORT"),
            ("connect = \"127.0.0.1:0\"\n", "HOST:PORT"),
            ("connect = \"127.0.0.1:18944\"\nserve = true\n", "give one"),
        ] {
            let t: SlicerScene = toml::from_str(text).unwrap();
            let e = t.validate().unwrap_err().to_string();
            assert!(
                e.contains(words) && e.starts_with("[slicer]"),
                "{text}: {e}"
            );
        }
        let c: SlicerScene = toml::from_str("connect = \"10.0.0.5:18944\"\n").unwrap();
        assert!(c.validate().is_ok() && c.connect.as_deref() == Some("10.0.0.5:18944"));
        assert!(toml::from_str::<SlicerScene>("port = 70000\n").is_err());
        assert!(toml::from_str::<SlicerScene>("prot = 1\n").is_err());
    }
}
