//! The latency harness: per-hop and end-to-end histograms from the renderer's frame reports.

use hdrhistogram::Histogram;
use ipc_types::{report_flags, FrameReport};
use serde::Serialize;

/// The 16.7 ms frame deadline (60 Hz), ns.
pub const DEADLINE_NS: u64 = 16_666_667;

/// Hops reported, as (label, from-stamp index, to-stamp index) into [`ipc_types::HopStamps::as_array`].
pub const HOPS: [(&str, usize, usize); 6] = [
    ("tracker capture -> bridge publish", 0, 1),
    ("bridge publish -> engine receive", 1, 2),
    ("engine receive -> engine publish", 2, 3),
    ("engine publish -> renderer receive", 3, 4),
    ("renderer receive -> renderer submit", 4, 5),
    ("end to end: capture -> submit", 0, 5),
];

/// Accumulates frame reports. Recording never allocates (histograms are sized up front).
pub struct LatencyStats {
    hops: Vec<Histogram<u64>>,
    gpu: Histogram<u64>,
    /// Frames recorded.
    pub frames: u64,
    /// Frames whose end-to-end latency exceeded [`DEADLINE_NS`].
    pub deadline_misses: u64,
    /// Frames drawn on the deadline fallback (no fresh engine frame).
    pub stale_frames: u64,
    /// Reports missing from the stream (gaps in the renderer's frame counter).
    pub lost_reports: u64,
    /// Engine ticks never drawn (gaps in the drawn tick sequence).
    pub skipped_ticks: u64,
    /// Frames whose hop stamps were incomplete or out of order.
    pub bad_stamps: u64,
    /// Frames that were out of order against the previous one.
    pub out_of_order: u64,
    last_frame: Option<u64>,
    last_tick: Option<u64>,
    /// Volume range seen (min, max) of the summed lungs, ml.
    pub volume_range: (f32, f32),
}

impl Default for LatencyStats {
    fn default() -> Self {
        Self::new()
    }
}

fn histogram() -> Histogram<u64> {
    // 1 ns .. 60 s at 3 significant digits.
    Histogram::new_with_bounds(1, 60_000_000_000, 3).expect("static bounds are valid")
}

impl LatencyStats {
    /// Empty statistics.
    pub fn new() -> Self {
        Self {
            hops: HOPS.iter().map(|_| histogram()).collect(),
            gpu: histogram(),
            frames: 0,
            deadline_misses: 0,
            stale_frames: 0,
            lost_reports: 0,
            skipped_ticks: 0,
            bad_stamps: 0,
            out_of_order: 0,
            last_frame: None,
            last_tick: None,
            volume_range: (f32::INFINITY, f32::NEG_INFINITY),
        }
    }

    /// Record one report.
    pub fn record(&mut self, r: &FrameReport) {
        self.frames += 1;
        if let Some(prev) = self.last_frame {
            if r.frame <= prev {
                self.out_of_order += 1;
            } else {
                self.lost_reports += r.frame - prev - 1;
            }
        }
        self.last_frame = Some(r.frame);
        if r.flags & report_flags::STALE_ENGINE != 0 {
            self.stale_frames += 1;
        } else if let Some(prev) = self.last_tick {
            if r.engine_tick > prev {
                self.skipped_ticks += r.engine_tick - prev - 1;
            }
        }
        self.last_tick = Some(r.engine_tick);
        if !r.stamps.is_complete_and_ordered() {
            self.bad_stamps += 1;
            return;
        }
        let s = r.stamps.as_array();
        for (h, &(_, a, b)) in self.hops.iter_mut().zip(HOPS.iter()) {
            let _ = h.record((s[b] - s[a]).max(1));
        }
        if s[5] - s[0] > DEADLINE_NS {
            self.deadline_misses += 1;
        }
        if r.flags & report_flags::GPU_TIMED != 0 && r.gpu_frame_ns > 0 {
            let _ = self.gpu.record(r.gpu_frame_ns);
        }
        let v = r.volume_ml[0] + r.volume_ml[1];
        self.volume_range = (self.volume_range.0.min(v), self.volume_range.1.max(v));
    }

    /// Summary rows (ms).
    pub fn rows(&self) -> Vec<HopRow> {
        let mut rows: Vec<HopRow> = HOPS
            .iter()
            .zip(&self.hops)
            .map(|(&(name, _, _), h)| HopRow::from_histogram(name, h))
            .collect();
        if !self.gpu.is_empty() {
            rows.push(HopRow::from_histogram(
                "GPU time per frame (timestamp queries)",
                &self.gpu,
            ));
        }
        rows
    }

    /// The end-to-end row.
    pub fn end_to_end(&self) -> HopRow {
        HopRow::from_histogram(HOPS[5].0, &self.hops[5])
    }
}

/// One row of the latency table.
#[derive(Debug, Clone, Serialize)]
pub struct HopRow {
    /// Hop label.
    pub hop: String,
    /// Samples.
    pub count: u64,
    /// Median, ms.
    pub p50_ms: f64,
    /// 99th percentile, ms.
    pub p99_ms: f64,
    /// Maximum, ms.
    pub max_ms: f64,
}

impl HopRow {
    fn from_histogram(name: &str, h: &Histogram<u64>) -> Self {
        let ms = |ns: u64| ns as f64 / 1e6;
        if h.is_empty() {
            return Self {
                hop: name.to_string(),
                count: 0,
                p50_ms: 0.0,
                p99_ms: 0.0,
                max_ms: 0.0,
            };
        }
        Self {
            hop: name.to_string(),
            count: h.len(),
            p50_ms: ms(h.value_at_quantile(0.5)),
            p99_ms: ms(h.value_at_quantile(0.99)),
            max_ms: ms(h.max()),
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ipc_types::HopStamps;

    fn report(frame: u64, tick: u64, e2e_ns: u64) -> FrameReport {
        let base = 1_000_000;
        FrameReport {
            frame,
            engine_tick: tick,
            stamps: HopStamps {
                capture_ns: base,
                bridge_publish_ns: base + 10,
                engine_receive_ns: base + 20,
                engine_publish_ns: base + 30,
                renderer_receive_ns: base + 40,
                renderer_submit_ns: base + e2e_ns,
            },
            volume_ml: [1300.0, 1100.0],
            ..Default::default()
        }
    }

    #[test]
    fn misses_gaps_and_percentiles_are_counted() {
        let mut s = LatencyStats::new();
        for i in 1..=100 {
            s.record(&report(i, i, if i == 50 { 20_000_000 } else { 5_000_000 }));
        }
        s.record(&report(103, 105, 1_000_000));
        assert_eq!(s.frames, 101);
        assert_eq!(s.deadline_misses, 1);
        assert_eq!(s.lost_reports, 2);
        assert_eq!(s.skipped_ticks, 4);
        let e2e = s.end_to_end();
        assert!((e2e.p50_ms - 5.0).abs() < 0.01);
        assert!((e2e.max_ms - 20.0).abs() < 0.02);
        let mut bad = report(104, 106, 1000);
        bad.stamps.engine_receive_ns = 0;
        s.record(&bad);
        assert_eq!(s.bad_stamps, 1);
    }
}
