//! The synthetic source: each tick, one sample of the patient reference (`Patient`) and one of the
//! HMD (`HMD`) from [`crate::synthetic::Synthetic`], numbered by the tick, received "now". Its
//! frames are those the bridge published before sources existed (same poses, ids, RMS, numbers).

use ipc_types::tool_status;

use crate::sample::{Input, Rotation, Sample, ToolName};
use crate::source::{Poll, Source, SourceError};
use crate::synthetic::Synthetic;

/// The synthetic patient and HMD as a [`Source`].
#[derive(Debug)]
pub struct SyntheticSource {
    scene: Synthetic,
    n: u64,
    patient: ToolName,
    hmd: ToolName,
}

impl SyntheticSource {
    /// A source over `scene`.
    pub fn new(scene: Synthetic) -> Self {
        SyntheticSource {
            scene,
            n: 0,
            patient: ToolName::new("Patient").expect("static name"),
            hmd: ToolName::new("HMD").expect("static name"),
        }
    }
}

impl Source for SyntheticSource {
    fn describe(&self) -> String {
        // The posture named (the scene's [tracker] posture or --posture): a run that should show a
        // sitting patient says so at start, and a recording keeps it in its header.
        format!(
            "synthetic source ({} patient, HMD walking round the bed)",
            self.scene.posture.name()
        )
    }

    fn poll(&mut self, now_ns: u64, sink: &mut dyn FnMut(&Input)) -> Result<Poll, SourceError> {
        self.n += 1;
        let frame = self.scene.frame(self.n, now_ns);
        for (tool, name) in frame.tools.iter().zip([self.patient, self.hmd]) {
            sink(&Input::Sample(Sample {
                receive_ns: now_ns,
                device_time_ns: 0,
                device_frame: Some(self.n),
                name,
                tool_id: tool.tool_id,
                rotation: Rotation::Quat(tool.pose.quat),
                translation_mm: tool.pose.translation_mm,
                rms_error_mm: Some(tool.rms_error_mm),
                device_flags: tool.status & !tool_status::VALID,
            }));
        }
        Ok(Poll::Tick { at_ns: now_ns })
    }
}
