//! How a receiving process waits for its next sample: the names scenes use (`[processes] wake`) and
//! the transport acts on (`transport::wake`).

/// A receiver's wake strategy as a scene asks for it.
#[derive(
    Debug, Clone, Copy, PartialEq, Eq, Hash, Default, serde::Serialize, serde::Deserialize,
)]
#[serde(rename_all = "kebab-case")]
pub enum WakeMode {
    /// Chosen at start-up from the cores: busy-poll on a core the scene reserves for the process,
    /// spin-then-park on a machine with cores to spare, the event otherwise.
    #[default]
    Auto,
    /// Sleep on the stream's iceoryx2 event until the producer signals (no CPU while waiting; the
    /// kernel's wake-up is the hop's latency).
    Event,
    /// Park on the event until the next sample is due, spin a bounded window around it, then park
    /// again (near busy-poll latency for a periodic stream at a small share of a core).
    SpinThenPark,
    /// Spin on the stream without sleeping (lowest latency; a whole core): only on a core the scene
    /// reserves for the process.
    BusyPoll,
}

impl WakeMode {
    /// Every mode, in the order the documentation lists them.
    pub const ALL: [WakeMode; 4] = [
        WakeMode::Auto,
        WakeMode::Event,
        WakeMode::SpinThenPark,
        WakeMode::BusyPoll,
    ];

    /// Name as in scenes (the serde name too).
    pub const fn name(self) -> &'static str {
        match self {
            WakeMode::Auto => "auto",
            WakeMode::Event => "event",
            WakeMode::SpinThenPark => "spin-then-park",
            WakeMode::BusyPoll => "busy-poll",
        }
    }

    /// The mode of a scene name.
    pub fn parse(name: &str) -> Result<WakeMode, UnknownWakeMode> {
        WakeMode::ALL
            .into_iter()
            .find(|m| m.name() == name)
            .ok_or_else(|| UnknownWakeMode(name.to_string()))
    }
}

impl core::fmt::Display for WakeMode {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        f.write_str(self.name())
    }
}

/// A name that is not a [`WakeMode`].
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct UnknownWakeMode(pub String);

impl core::fmt::Display for UnknownWakeMode {
    fn fmt(&self, f: &mut core::fmt::Formatter<'_>) -> core::fmt::Result {
        write!(
            f,
            "{:?} is not a wake strategy: give \"auto\", \"event\", \"spin-then-park\" or \"busy-poll\"",
            self.0
        )
    }
}

impl std::error::Error for UnknownWakeMode {}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn names_round_trip() {
        for m in WakeMode::ALL {
            assert_eq!(WakeMode::parse(m.name()), Ok(m));
            assert_eq!(m.to_string(), m.name());
        }
        let e = WakeMode::parse("busy_poll").unwrap_err().to_string();
        assert!(e.contains("\"busy_poll\" is not a wake strategy"), "{e}");
        assert!(e.contains("spin-then-park"), "{e}");
    }
}
