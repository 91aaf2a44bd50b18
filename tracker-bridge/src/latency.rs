//! The pipeline's latency as the renderer measures it (issue 35, item 3: the breath is predicted to
//! each frame's display time "from the measured latency"). The bridge reads the renderer's frame
//! reports ([`FrameReport`]); each gives how long after the bridge published a tracker frame the
//! frame drawn from it was shown ([`FrameReport::display_ns`] less the report's
//! `stamps.bridge_publish_ns`). The median of the latest [`WINDOW`] goes out in every tracker frame
//! that carries the respiratory signal ([`ipc_types::SignalBlock::pipeline_latency_ns`]), where the
//! engine takes it as an input — recorded with the signal and replayed as it was, so the engine stays
//! a pure function of its inputs. The bridge measures; the engine predicts; the renderer draws.
//!
//! Nothing here allocates: a fixed ring and a median by selection on a copy on the stack.

use ipc_types::FrameReport;

/// Reports the median is taken over (about a second at 60 Hz: follows a change of load within a
/// breath, and one slow frame moves it by one place).
pub const WINDOW: usize = 64;
/// Reports needed before a median is given (a quarter of a second at 60 Hz; before that the engine
/// predicts across the scene's `latency_ms`).
pub const MIN_REPORTS: usize = 16;
/// A latency longer than this is not a frame's (a report from a renderer that was paused, or a
/// clock that is not the bridge's): not taken, counted.
pub const MAX_LATENCY_NS: u64 = 1_000_000_000;

/// The latest latencies and their median.
#[derive(Debug, Clone)]
pub struct LatencyMeter {
    ring: [u64; WINDOW],
    len: usize,
    next: usize,
    median_ns: u64,
    taken: u64,
    refused: u64,
}

impl Default for LatencyMeter {
    fn default() -> Self {
        Self::new()
    }
}

impl LatencyMeter {
    /// Nothing measured yet.
    pub fn new() -> Self {
        Self {
            ring: [0; WINDOW],
            len: 0,
            next: 0,
            median_ns: 0,
            taken: 0,
            refused: 0,
        }
    }

    /// Take one report. A report with no bridge stamp (a frame drawn before any tracker frame), a
    /// display not after the publish, or a latency past [`MAX_LATENCY_NS`] is refused (counted).
    pub fn report(&mut self, r: &FrameReport) -> bool {
        let publish = r.stamps.bridge_publish_ns;
        let display = r.display_ns();
        if publish == 0 || display <= publish || display - publish > MAX_LATENCY_NS {
            self.refused += 1;
            return false;
        }
        self.ring[self.next] = display - publish;
        self.next = (self.next + 1) % WINDOW;
        self.len = (self.len + 1).min(WINDOW);
        self.taken += 1;
        if self.len >= MIN_REPORTS {
            let mut copy = self.ring;
            let window = &mut copy[..self.len];
            let mid = self.len / 2;
            self.median_ns = *window.select_nth_unstable(mid).1;
        }
        true
    }

    /// The median of the latest reports, ns; 0 until [`MIN_REPORTS`] were taken.
    pub fn median_ns(&self) -> u64 {
        self.median_ns
    }

    /// Reports taken and refused so far.
    pub fn counts(&self) -> (u64, u64) {
        (self.taken, self.refused)
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    fn report(publish: u64, latency: u64) -> FrameReport {
        let mut r = FrameReport::default();
        r.stamps.bridge_publish_ns = publish;
        r.stamps.renderer_submit_ns = publish + latency / 2;
        r.gpu_done_ns = publish + latency;
        r
    }

    #[test]
    fn the_median_of_the_latest_window_is_given_once_enough_reports_came() {
        let mut m = LatencyMeter::new();
        for i in 0..MIN_REPORTS as u64 - 1 {
            assert!(m.report(&report(1_000_000 + i, 9_000_000)));
            assert_eq!(m.median_ns(), 0, "no median before {MIN_REPORTS} reports");
        }
        assert!(m.report(&report(2_000_000, 9_000_000)));
        assert_eq!(m.median_ns(), 9_000_000);
        // One slow frame in the window moves the median by no more than a place.
        assert!(m.report(&report(3_000_000, 400_000_000)));
        assert_eq!(m.median_ns(), 9_000_000);
        // The window follows a change of load: after WINDOW reports at 20 ms, only they count.
        for i in 0..WINDOW as u64 {
            m.report(&report(4_000_000 + i, 20_000_000 + i));
        }
        assert_eq!(m.median_ns(), 20_000_000 + WINDOW as u64 / 2);
        assert_eq!(m.counts(), (MIN_REPORTS as u64 + 1 + WINDOW as u64, 0));
    }

    #[test]
    fn the_display_is_the_present_else_the_gpu_done_else_the_submit() {
        let mut m = LatencyMeter::new();
        let mut r = report(1_000, 0);
        r.stamps.renderer_submit_ns = 5_000_000;
        r.gpu_done_ns = 7_000_000;
        r.present_ns = 12_000_000;
        for _ in 0..MIN_REPORTS {
            m.report(&r);
        }
        assert_eq!(m.median_ns(), 12_000_000 - 1_000, "present");
        let mut m = LatencyMeter::new();
        r.present_ns = 0;
        for _ in 0..MIN_REPORTS {
            m.report(&r);
        }
        assert_eq!(m.median_ns(), 7_000_000 - 1_000, "GPU done");
        let mut m = LatencyMeter::new();
        r.gpu_done_ns = 0;
        for _ in 0..MIN_REPORTS {
            m.report(&r);
        }
        assert_eq!(m.median_ns(), 5_000_000 - 1_000, "submit");
    }

    #[test]
    fn reports_that_cannot_be_a_frames_latency_are_refused_and_counted() {
        let mut m = LatencyMeter::new();
        // No tracker frame behind it; shown before it was published; a paused renderer's.
        assert!(!m.report(&report(0, 9_000_000)));
        let mut before = report(10_000_000, 0);
        before.gpu_done_ns = 0;
        before.stamps.renderer_submit_ns = 5_000_000;
        assert!(!m.report(&before));
        assert!(!m.report(&report(1, MAX_LATENCY_NS + 1)));
        assert_eq!(m.counts(), (0, 3));
        assert_eq!(m.median_ns(), 0);
    }
}
