//! The `[tracker]` table: where the patient's and the HMD's poses come from. The tracker-bridge reads
//! it itself (`tracker-bridge --scene FILE`), and `lungdyn scene run` takes the posture from it.

use serde::{Deserialize, Serialize};

/// `[tracker]` table.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct TrackerScene {
    /// The bridge's source (`lungdyn demo --tracker` overrides it): `synthetic`,
    /// `igtl-client:HOST[:PORT]`, `igtl-server[:BIND[:PORT]]`, `ndi-serial:DEVICE`,
    /// `ndi-tcp:HOST[:PORT]`, `replay:FILE`.
    pub source: String,
    /// The synthetic patient's posture (`lungdyn scene run` uses it too): the breath follows gravity
    /// in the orientation modes.
    pub posture: Posture,
    /// The OpenIGTLink server's senders besides loopback: addresses or networks
    /// (`["10.0.0.5", "192.168.1.0/24"]`); the bridge's `--igtl-allow` adds to them.
    pub allow: Vec<String>,
}

impl Default for TrackerScene {
    fn default() -> Self {
        Self {
            source: "synthetic".into(),
            posture: Posture::Supine,
            allow: Vec::new(),
        }
    }
}

/// A patient's posture on the bed (the synthetic source's fixed orientation; the bridge's
/// `--posture` takes the same names).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize, Deserialize)]
#[cfg_attr(feature = "clap", derive(clap::ValueEnum))]
#[serde(rename_all = "kebab-case")]
pub enum Posture {
    /// On the back (the seed's and the default).
    #[default]
    Supine,
    /// Sitting upright (head up, gravity from head to feet).
    Sitting,
    /// On the front.
    Prone,
    /// On the left side.
    LeftLateral,
    /// On the right side.
    RightLateral,
}

impl Posture {
    /// Every posture, in the order `--help` lists them.
    pub const ALL: [Posture; 5] = [
        Posture::Supine,
        Posture::Sitting,
        Posture::Prone,
        Posture::LeftLateral,
        Posture::RightLateral,
    ];

    /// Name as in scenes and on the bridge's `--posture`.
    pub fn name(self) -> &'static str {
        match self {
            Posture::Supine => "supine",
            Posture::Sitting => "sitting",
            Posture::Prone => "prone",
            Posture::LeftLateral => "left-lateral",
            Posture::RightLateral => "right-lateral",
        }
    }
}
