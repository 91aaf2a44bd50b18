//! Replay of a recording ([`crate::record`]): each poll hands over the samples and events recorded
//! before the next tick and returns that tick's recorded time, so the assembler sees exactly what
//! it saw when the recording was made (the grouping of samples into frames and the staleness times
//! included) and builds the same frames. Paced, one recorded tick per bridge period (the recorded
//! rate); with `--as-fast-as-possible`, without waiting. A recording cut short plays up to its last
//! complete tick and says so. A sample stamped after its tick by more than the staleness bound
//! (a damaged clock: the assembler shows its tool stale) is named once, so the replay says why.
//! A recording made with a respiratory signal plays it back: each tick publishes the block it
//! recorded, its times moved to this run's clock as the samples' are.

use std::fs::File;
use std::io::BufReader;
use std::path::{Path, PathBuf};

use crate::assemble::BridgeConfig;
use crate::record::{Record, RecordError, RecordReader};
use crate::sample::{Event, EventKind, Input};
use crate::source::{Poll, Source, SourceError};

/// The replay source.
#[derive(Debug)]
pub struct Replay {
    reader: RecordReader<BufReader<File>>,
    path: PathBuf,
    paced: bool,
    config: BridgeConfig,
    ended: bool,
    /// The latest receive time of the samples handed over since the last tick, ns.
    latest_ns: u64,
    /// A sample stamped far after its tick has been named (once per replay: not a flood).
    told_future: bool,
    /// The signal block recorded for the tick being returned.
    signal: Option<ipc_types::SignalBlock>,
}

impl Replay {
    /// Open `path`; `paced`: one tick per period (else as fast as possible).
    pub fn open(path: &Path, paced: bool) -> Result<Self, SourceError> {
        let reader = RecordReader::open(path)?;
        let config = reader.header.config.clone();
        Ok(Replay {
            reader,
            path: path.to_path_buf(),
            paced,
            config,
            ended: false,
            latest_ns: 0,
            told_future: false,
            signal: None,
        })
    }

    /// The recorded source's description.
    pub fn recorded_source(&self) -> &str {
        &self.reader.header.source
    }
}

impl Source for Replay {
    fn describe(&self) -> String {
        format!(
            "replay of {} ({}){}",
            self.path.display(),
            self.reader.header.source,
            if self.paced {
                ""
            } else {
                ", as fast as possible"
            }
        )
    }

    fn poll(&mut self, _now_ns: u64, sink: &mut dyn FnMut(&Input)) -> Result<Poll, SourceError> {
        if self.ended {
            return Ok(Poll::End);
        }
        loop {
            match self.reader.next_record() {
                Ok(Some(Record::Sample(s))) => {
                    self.latest_ns = self.latest_ns.max(s.receive_ns);
                    sink(&Input::Sample(s));
                }
                Ok(Some(Record::Event(e))) => sink(&Input::Event(e)),
                Ok(Some(Record::Signal(b))) => self.signal = Some(b),
                // The latency the block just read carried (recorded right after it).
                Ok(Some(Record::SignalLatency(ns))) => {
                    if let Some(b) = self.signal.as_mut() {
                        b.pipeline_latency_ns = ns;
                    }
                }
                Ok(Some(Record::Tick { at_ns, .. })) => {
                    let ahead = self.latest_ns.saturating_sub(at_ns);
                    if !self.told_future && ahead > self.config.stale_ns {
                        self.told_future = true;
                        sink(&Input::Event(Event::new(
                            EventKind::Note,
                            0,
                            format!(
                                "a sample is stamped {:.3} s after its tick: the recording's clock is damaged, its tool is shown stale",
                                ahead as f64 / 1e9
                            ),
                        )));
                    }
                    self.latest_ns = 0;
                    return Ok(Poll::Tick { at_ns });
                }
                Ok(Some(Record::End { .. })) | Ok(None) => {
                    self.ended = true;
                    return Ok(Poll::End);
                }
                Err(e @ RecordError::Truncated { .. }) => {
                    self.ended = true;
                    sink(&Input::Event(Event::new(
                        EventKind::Note,
                        0,
                        format!("{e}; played up to its last complete tick"),
                    )));
                    return Ok(Poll::End);
                }
                Err(e) => return Err(e.into()),
            }
        }
    }

    fn paced(&self) -> bool {
        self.paced
    }

    fn recorded_config(&self) -> Option<&BridgeConfig> {
        Some(&self.config)
    }

    fn recorded_signal(&mut self) -> Option<ipc_types::SignalBlock> {
        self.signal.take()
    }
}
