//! The `[processes]` table: where the three run-time processes run, how they wait and what each may
//! spend of the 16.7 ms frame. The launcher reads it to pin and start them; the engine and the
//! renderer read their wake strategy from it.

use serde::{Deserialize, Serialize};

use crate::wake::WakeMode;
use crate::TableError;

/// The frame deadline the budgets share, ms (60 Hz).
pub const FRAME_DEADLINE_MS: f64 = 1000.0 / 60.0;

/// `[processes]` table: the cores of the three processes and each one's share of the 16.7 ms frame.
#[derive(Debug, Clone, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ProcessesScene {
    /// Cores for tracker-bridge, engine and renderer, in that order (`lungdyn demo --cpus`
    /// overrides); empty: not pinned.
    pub cpus: Vec<usize>,
    /// Per-sample time budgets, ms.
    pub budget_ms: ProcessBudgets,
    /// Run the three processes SCHED_FIFO with locked memory where permitted (`--realtime`); each
    /// says once which capability or limit is missing where not.
    pub realtime: bool,
    /// How the engine waits for tracker frames and the renderer for engine frames: one strategy for
    /// both (`wake = "event"`) or each its own (`wake = { engine = "busy-poll", renderer = "event" }`).
    pub wake: ProcessWake,
    /// The spin window of `spin-then-park` around the moment the next sample is due, µs.
    pub spin_us: u32,
}

impl Default for ProcessesScene {
    fn default() -> Self {
        Self {
            cpus: Vec::new(),
            budget_ms: ProcessBudgets::default(),
            realtime: false,
            wake: ProcessWake::default(),
            spin_us: DEFAULT_SPIN_US,
        }
    }
}

/// The default `[processes] spin_us`: 200 µs around the due time covers a 60 Hz tracker's usual
/// jitter and the timer's slack at 1.2 % of a core.
pub const DEFAULT_SPIN_US: u32 = 200;
/// The largest `[processes] spin_us`: 2 ms, an eighth of the 60 Hz period (a longer spin is
/// busy-polling by another name).
pub const MAX_SPIN_US: u32 = 2_000;

/// The processes in `[processes] cpus` order.
pub const PROCESS_ORDER: [&str; 3] = ["tracker-bridge", "engine", "renderer"];
/// The engine's index in [`PROCESS_ORDER`].
pub const ENGINE: usize = 1;
/// The renderer's index in [`PROCESS_ORDER`].
pub const RENDERER: usize = 2;

impl ProcessesScene {
    /// The core `[processes] cpus` gives process `index` (see [`PROCESS_ORDER`]) for itself alone:
    /// `None` when no cores are given or another of the three shares it.
    pub fn reserved_core(&self, index: usize) -> Option<usize> {
        let core = *self.cpus.get(index)?;
        let shared = self
            .cpus
            .iter()
            .enumerate()
            .any(|(i, &c)| i != index && c == core);
        (!shared).then_some(core)
    }

    /// Why `busy-poll` cannot run for process `index` under these cpus, if it cannot.
    fn busy_poll_refusal(&self, index: usize) -> Option<String> {
        let name = PROCESS_ORDER[index];
        if self.cpus.is_empty() {
            return Some(format!(
                "wake: {name} = \"busy-poll\" spins a whole core: it needs a core of its own, and \
                 [processes] cpus gives none; reserve one (e.g. cpus = [0, 1, 2]) or use \
                 \"spin-then-park\""
            ));
        }
        if self.reserved_core(index).is_none() {
            let core = self.cpus[index];
            let others: Vec<&str> = (0..3)
                .filter(|&i| i != index && self.cpus.get(i) == Some(&core))
                .map(|i| PROCESS_ORDER[i])
                .collect();
            return Some(format!(
                "wake: {name} = \"busy-poll\" spins a whole core, but [processes] cpus = {:?} gives the \
                 {name} core {core}, shared with the {}; give it a core no other lungdyn process \
                 uses, or use \"spin-then-park\"",
                self.cpus,
                others.join(" and ")
            ));
        }
        None
    }
}

/// `[processes] wake`: the engine's and the renderer's wake strategies (the tracker-bridge waits on
/// its source and its own clock, not on a stream). A string sets both; a table sets each.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default, Serialize)]
pub struct ProcessWake {
    /// How the engine waits for tracker frames.
    pub engine: WakeMode,
    /// How the renderer waits for engine frames.
    pub renderer: WakeMode,
}

impl ProcessWake {
    /// The same strategy for both receivers.
    pub fn both(mode: WakeMode) -> Self {
        Self {
            engine: mode,
            renderer: mode,
        }
    }
}

impl<'de> Deserialize<'de> for ProcessWake {
    fn deserialize<D: serde::Deserializer<'de>>(d: D) -> Result<Self, D::Error> {
        #[derive(Deserialize)]
        #[serde(deny_unknown_fields, default)]
        struct Each {
            engine: WakeMode,
            renderer: WakeMode,
        }
        impl Default for Each {
            fn default() -> Self {
                let w = ProcessWake::default();
                Self {
                    engine: w.engine,
                    renderer: w.renderer,
                }
            }
        }
        struct V;
        impl<'de> serde::de::Visitor<'de> for V {
            type Value = ProcessWake;
            fn expecting(&self, f: &mut std::fmt::Formatter) -> std::fmt::Result {
                f.write_str(
                    "a wake strategy (\"auto\", \"event\", \"spin-then-park\", \"busy-poll\") or a \
                     table { engine = ..., renderer = ... }",
                )
            }
            fn visit_str<E: serde::de::Error>(self, v: &str) -> Result<ProcessWake, E> {
                WakeMode::parse(v).map(ProcessWake::both).map_err(E::custom)
            }
            fn visit_map<A: serde::de::MapAccess<'de>>(
                self,
                map: A,
            ) -> Result<ProcessWake, A::Error> {
                let e = Each::deserialize(serde::de::value::MapAccessDeserializer::new(map))?;
                Ok(ProcessWake {
                    engine: e.engine,
                    renderer: e.renderer,
                })
            }
        }
        d.deserialize_any(V)
    }
}

/// Per-sample time each process may spend, ms: the bridge from a sample's capture to its publish,
/// the engine from receiving it to publishing the tick's frame, the renderer from receiving the
/// frame to submitting it. Together with the transport they must fit the 16.7 ms frame deadline;
/// `lungdyn demo` reports each process's p99 and the samples over its budget.
#[derive(Debug, Clone, Copy, PartialEq, Serialize, Deserialize)]
#[serde(deny_unknown_fields, default)]
pub struct ProcessBudgets {
    /// tracker-bridge, ms.
    pub tracker_bridge: f64,
    /// engine, ms.
    pub engine: f64,
    /// renderer, ms.
    pub renderer: f64,
}

impl Default for ProcessBudgets {
    fn default() -> Self {
        Self {
            tracker_bridge: 1.0,
            engine: 2.0,
            renderer: 10.0,
        }
    }
}

impl ProcessesScene {
    /// Range checks serde cannot express: three cores or none, the spin window, a busy-poll only on
    /// a core of its own, each budget within the frame and their sum too.
    pub fn validate(&self) -> Result<(), TableError> {
        let p = self;
        if !(p.cpus.is_empty() || p.cpus.len() == 3) {
            return Err(TableError::ProcessCpus(p.cpus.clone()));
        }
        if !(1..=MAX_SPIN_US).contains(&p.spin_us) {
            return Err(TableError::ProcessWake(format!(
                "spin_us = {} must be within 1..{MAX_SPIN_US} µs (a spin-then-park's window around \
                 the due sample; use \"event\" for none, \"busy-poll\" for a whole core)",
                p.spin_us
            )));
        }
        for (index, mode) in [(ENGINE, p.wake.engine), (RENDERER, p.wake.renderer)] {
            if mode == WakeMode::BusyPoll {
                if let Some(why) = p.busy_poll_refusal(index) {
                    return Err(TableError::ProcessWake(why));
                }
            }
        }
        let b = p.budget_ms;
        for (name, v) in [
            ("tracker_bridge", b.tracker_bridge),
            ("engine", b.engine),
            ("renderer", b.renderer),
        ] {
            if !(v.is_finite() && v > 0.0 && v <= FRAME_DEADLINE_MS) {
                return Err(TableError::ProcessBudget(format!(
                    "{name} = {} must be within (0, {FRAME_DEADLINE_MS:.1}] ms",
                    crate::compact(v)
                )));
            }
        }
        let sum = b.tracker_bridge + b.engine + b.renderer;
        if sum > FRAME_DEADLINE_MS {
            return Err(TableError::ProcessBudget(format!(
                "the three budgets sum to {sum:.2} ms, more than the {FRAME_DEADLINE_MS:.1} ms frame \
                 deadline they share"
            )));
        }
        Ok(())
    }
}
