//! The latency harness: per-hop and end-to-end histograms from the renderer's frame reports, and the
//! latency of every tracker sample on the schedule.
//!
//! Measuring only the frames that were drawn hides a stall (coordinated omission): a renderer frozen
//! for two seconds draws no frame, so no frame reports a large latency, and the first frame after the
//! freeze shows fresh data with a small one. The schedule view fixes that: the tracker samples at a
//! fixed rate, and every sample — drawn or not — has a latency: the time from its capture until the
//! first frame showing it *or newer data* was submitted. A report covering tracker frames
//! `last+1 ..= n` settles all of them at once (the earlier ones' capture times follow from the
//! schedule), so a 2-second freeze shows as ~120 samples over the deadline and a 2-second worst case.

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
    present: Histogram<u64>,
    /// How the last presented frame was presented ([`ipc_types::present_mode`] code, and the
    /// surface's frame latency); `None` when no frame was presented (headless).
    pub present_mode: Option<(u32, u32)>,
    /// Frames that reached a display (`present` returned).
    pub presented_frames: u64,
    samples: Histogram<u64>,
    period_ns: u64,
    last_tracker: Option<(u64, u64)>,
    last_submit: Option<u64>,
    /// Tracker samples settled (each with its latency against the schedule).
    pub tracker_samples: u64,
    /// Tracker samples first shown more than [`DEADLINE_NS`] after their capture, drawn or not.
    pub sample_deadline_misses: u64,
    /// Display slots (one per period) in which no frame was submitted at all.
    pub missed_frame_slots: u64,
    /// Frames recorded.
    pub frames: u64,
    /// Frames whose end-to-end latency exceeded [`DEADLINE_NS`].
    pub deadline_misses: u64,
    /// Frames drawn on the deadline fallback (no fresh engine frame).
    pub stale_frames: u64,
    /// Frames drawn with the patient pose held by the engine (samples missing or rejected).
    pub pose_held_frames: u64,
    /// Of those, frames whose held pose was stale (past the limit, or none ever arrived).
    pub pose_stale_frames: u64,
    /// Frames whose lungs the patient's respiratory signal drove.
    pub signal_following_frames: u64,
    /// Frames drawn while a followed signal was lost (the model breathed, under the blue veil).
    pub signal_lost_frames: u64,
    /// Frames whose driving signal looked clipped by its sensor's range.
    pub signal_clipped_frames: u64,
    /// Frames that drew a lung outside its kernel's fold-free volume range.
    pub past_fold_free_frames: u64,
    /// Frames drawn with every governor step given up and still over its target.
    pub governor_floor_frames: u64,
    /// Times the drawn quality changed from one frame to the next.
    pub quality_changes: u64,
    /// The quality bits of the last frame (`report_flags::QUALITY_LOWERED`), and per quality seen,
    /// its frames (a handful of distinct qualities at most; those not 0 are the frames the governor
    /// drew below the scene's quality).
    pub last_quality: u32,
    pub quality_frames: Vec<(u32, u64)>,
    /// The quality bits of the first frame (not 0 where the governor started where an earlier
    /// run settled: `[render] governor_start`).
    pub first_quality: u32,
    /// Reports missing from the stream (gaps in the renderer's frame counter).
    pub lost_reports: u64,
    /// Engine ticks never drawn (gaps in the drawn tick sequence).
    pub skipped_ticks: u64,
    /// Frames whose hop stamps were incomplete or out of order.
    pub bad_stamps: u64,
    /// Frames drawn before any tracker sample reached the engine (no capture stamp: the lungs
    /// breathe before the tracker connects); not latency samples, not bad stamps.
    pub untracked_frames: u64,
    /// Frames that were out of order against the previous one.
    pub out_of_order: u64,
    /// Frames whose tracker sample number jumped further ahead than the clock allows (a corrupted
    /// or foreign tracker frame): not settled on the schedule, which they would stretch to
    /// billions of samples.
    pub implausible_samples: u64,
    last_frame: Option<u64>,
    last_tick: Option<u64>,
    bridge_restarted: bool,
    /// Volume range seen (min, max) of the summed lungs, ml.
    pub volume_range: (f32, f32),
}

impl Default for LatencyStats {
    fn default() -> Self {
        Self::new()
    }
}

/// The tracker's sample period the schedule assumes (60 Hz).
pub const SCHEDULE_PERIOD_NS: u64 = DEADLINE_NS;

const NS_PER_S: u64 = 1_000_000_000;

fn histogram() -> Histogram<u64> {
    // 1 ns .. 60 s at 3 significant digits.
    Histogram::new_with_bounds(1, 60_000_000_000, 3).expect("static bounds are valid")
}

impl LatencyStats {
    /// Empty statistics, on the 60 Hz schedule.
    pub fn new() -> Self {
        Self::with_period(SCHEDULE_PERIOD_NS)
    }

    /// Empty statistics for a tracker sampling every `period_ns`.
    pub fn with_period(period_ns: u64) -> Self {
        Self {
            hops: HOPS.iter().map(|_| histogram()).collect(),
            gpu: histogram(),
            present: histogram(),
            present_mode: None,
            presented_frames: 0,
            samples: histogram(),
            period_ns: period_ns.max(1),
            last_tracker: None,
            last_submit: None,
            tracker_samples: 0,
            sample_deadline_misses: 0,
            missed_frame_slots: 0,
            frames: 0,
            deadline_misses: 0,
            stale_frames: 0,
            pose_held_frames: 0,
            pose_stale_frames: 0,
            signal_following_frames: 0,
            signal_lost_frames: 0,
            signal_clipped_frames: 0,
            past_fold_free_frames: 0,
            governor_floor_frames: 0,
            quality_changes: 0,
            last_quality: 0,
            quality_frames: Vec::with_capacity(16),
            first_quality: 0,
            lost_reports: 0,
            skipped_ticks: 0,
            bad_stamps: 0,
            untracked_frames: 0,
            out_of_order: 0,
            implausible_samples: 0,
            last_frame: None,
            last_tick: None,
            bridge_restarted: false,
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
        if r.flags & report_flags::PATIENT_POSE_HELD != 0 {
            self.pose_held_frames += 1;
        }
        if r.flags & report_flags::PATIENT_POSE_STALE != 0 {
            self.pose_stale_frames += 1;
        }
        if r.flags & report_flags::SIGNAL_FOLLOWING != 0 {
            self.signal_following_frames += 1;
        }
        if r.flags & report_flags::SIGNAL_LOST != 0 {
            self.signal_lost_frames += 1;
        }
        if r.flags & report_flags::SIGNAL_CLIPPED != 0 {
            self.signal_clipped_frames += 1;
        }
        if r.flags & report_flags::PAST_FOLD_FREE != 0 {
            self.past_fold_free_frames += 1;
        }
        self.record_quality(r.flags);
        if r.flags & report_flags::STALE_ENGINE != 0 {
            self.stale_frames += 1;
        } else if let Some(prev) = self.last_tick {
            if r.engine_tick > prev {
                self.skipped_ticks += r.engine_tick - prev - 1;
            }
        }
        self.last_tick = Some(r.engine_tick);
        if r.present_ns != 0 {
            self.presented_frames += 1;
            self.present_mode = Some((r.present_mode, r.frame_latency));
            if r.stamps.renderer_submit_ns != 0 && r.present_ns >= r.stamps.renderer_submit_ns {
                let _ = self
                    .present
                    .record((r.present_ns - r.stamps.renderer_submit_ns).max(1));
            }
        }
        let v = r.volume_ml[0] + r.volume_ml[1];
        self.volume_range = (self.volume_range.0.min(v), self.volume_range.1.max(v));
        if r.stamps.capture_ns == 0 && r.stamps.bridge_publish_ns == 0 && r.tracker_frame == 0 {
            self.untracked_frames += 1;
            return;
        }
        if !r.stamps.is_complete_and_ordered() {
            self.bad_stamps += 1;
            return;
        }
        let s = r.stamps.as_array();
        for (h, &(_, a, b)) in self.hops.iter_mut().zip(HOPS.iter()) {
            let _ = h.record((s[b] - s[a]).max(1));
        }
        self.settle_samples(
            r.tracker_frame,
            r.stamps.capture_ns,
            r.stamps.renderer_submit_ns,
        );
        if s[5] - s[0] > DEADLINE_NS {
            self.deadline_misses += 1;
        }
        if r.flags & report_flags::GPU_TIMED != 0 && r.gpu_frame_ns > 0 {
            let _ = self.gpu.record(r.gpu_frame_ns);
        }
    }

    /// The governor's part of a report: what it gave up for the frame and whether at its floor.
    fn record_quality(&mut self, flags: u32) {
        let quality = flags & report_flags::QUALITY_LOWERED;
        if flags & report_flags::GOVERNOR_FLOOR != 0 {
            self.governor_floor_frames += 1;
        }
        if self.frames > 1 && quality != self.last_quality {
            self.quality_changes += 1;
        }
        if self.frames <= 1 {
            self.first_quality = quality;
        }
        self.last_quality = quality;
        match self.quality_frames.iter_mut().find(|(q, _)| *q == quality) {
            Some((_, n)) => *n += 1,
            // Bounded: 3 bits of draw levels, MSAA, the look (at most 32 distinct).
            None => self.quality_frames.push((quality, 1)),
        }
    }

    /// A process of the run was restarted: its counters start again, which must not read as
    /// reports out of order (a new renderer numbers its frames from 1) or as samples already
    /// settled (a new tracker-bridge numbers its samples from the start). The outage itself shows
    /// on the schedule: the display slots without a frame, the samples shown late.
    pub fn restarted(&mut self, role: &str) {
        match role {
            "renderer" => self.last_frame = None,
            // Reports of the old bridge's samples may still arrive (the engine holds its last
            // one): the numbering restarts at the first report whose sample number goes back.
            "tracker-bridge" => self.bridge_restarted = true,
            _ => {}
        }
    }

    /// The run ended at `end_ns`: tracker samples on the schedule after the last one shown were
    /// never shown — each is settled as missed, as are the display slots since the last frame (a
    /// renderer stopped for good reports nothing, and would otherwise look punctual).
    pub fn finish(&mut self, end_ns: u64) {
        let Some(submit) = self.last_submit else {
            return;
        };
        let gap = end_ns.saturating_sub(submit);
        if gap > self.period_ns + self.period_ns / 2 {
            self.missed_frame_slots += (gap - self.period_ns / 2) / self.period_ns;
        }
        self.last_submit = Some(end_ns);
        if let Some((frame, capture)) = self.last_tracker {
            // Samples captured after the last one shown and more than a deadline before the end.
            let mut n = frame + 1;
            loop {
                let captured = capture.saturating_add((n - frame).saturating_mul(self.period_ns));
                if captured.saturating_add(DEADLINE_NS) >= end_ns {
                    break;
                }
                let _ = self.samples.record(end_ns - captured);
                self.tracker_samples += 1;
                self.sample_deadline_misses += 1;
                n += 1;
            }
            self.last_tracker = Some((
                n - 1,
                capture.saturating_add((n - 1 - frame) * self.period_ns),
            ));
        }
    }

    /// The schedule view: tracker samples `last+1 ..= frame` are first shown by this submit.
    fn settle_samples(&mut self, frame: u64, capture_ns: u64, submit_ns: u64) {
        if let Some(prev) = self.last_submit {
            // Display slots that passed without any frame.
            let gap = submit_ns.saturating_sub(prev);
            if gap > self.period_ns + self.period_ns / 2 {
                self.missed_frame_slots += (gap - self.period_ns / 2) / self.period_ns;
            }
        }
        self.last_submit = Some(self.last_submit.map_or(submit_ns, |p| p.max(submit_ns)));
        if self.bridge_restarted && self.last_tracker.is_some_and(|(last, _)| frame < last) {
            self.bridge_restarted = false;
            self.last_tracker = None;
        }
        let first_new = match self.last_tracker {
            Some((last, _)) if frame <= last => return,
            Some((last, last_capture)) => {
                // At most one sample per period since the last one, and a second's slack.
                let possible = capture_ns.saturating_sub(last_capture) / self.period_ns
                    + NS_PER_S / self.period_ns;
                if frame - last > possible {
                    self.implausible_samples += 1;
                    return;
                }
                last + 1
            }
            None => frame,
        };
        for n in first_new..=frame {
            let captured = capture_ns.saturating_sub((frame - n).saturating_mul(self.period_ns));
            let latency = submit_ns.saturating_sub(captured).max(1);
            let _ = self.samples.record(latency);
            self.tracker_samples += 1;
            if latency > DEADLINE_NS {
                self.sample_deadline_misses += 1;
            }
        }
        self.last_tracker = Some((frame, capture_ns));
    }

    /// Latency of every tracker sample against the schedule (drawn or not).
    pub fn sample_latency(&self) -> HopRow {
        HopRow::from_histogram(
            "tracker sample -> first frame showing it (schedule, drawn or not)",
            &self.samples,
        )
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
        if !self.present.is_empty() {
            rows.push(self.submit_to_present());
        }
        if !self.samples.is_empty() {
            rows.push(self.sample_latency());
        }
        rows
    }

    /// Per presented frame: renderer submit → `present` returned (CLOCK_MONOTONIC).
    pub fn submit_to_present(&self) -> HopRow {
        HopRow::from_histogram("renderer submit -> present returned", &self.present)
    }

    /// The end-to-end row.
    pub fn end_to_end(&self) -> HopRow {
        HopRow::from_histogram(HOPS[5].0, &self.hops[5])
    }

    /// One process's per-sample time against its budget: `hop` indexes [`HOPS`] (0 bridge, 2 engine,
    /// 4 renderer).
    pub fn budget_row(&self, process: &str, hop: usize, budget_ms: f64) -> BudgetRow {
        let h = &self.hops[hop];
        let row = HopRow::from_histogram(HOPS[hop].0, h);
        let limit = (budget_ms * 1e6) as u64;
        BudgetRow {
            process: process.to_string(),
            budget_ms,
            samples: h.len(),
            p99_ms: row.p99_ms,
            max_ms: row.max_ms,
            over_budget: if h.is_empty() || h.max() <= limit {
                0
            } else {
                h.count_between(limit + 1, h.max())
            },
        }
    }
}

/// One process's per-sample time against its `[processes] budget_ms`.
#[derive(Debug, Clone, Serialize)]
pub struct BudgetRow {
    /// Process.
    pub process: String,
    /// Budget, ms.
    pub budget_ms: f64,
    /// Samples measured.
    pub samples: u64,
    /// 99th percentile, ms.
    pub p99_ms: f64,
    /// Maximum, ms.
    pub max_ms: f64,
    /// Samples over the budget (at the histogram's 3 significant digits).
    pub over_budget: u64,
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

    /// Frames whose signal looked clipped are counted apart from those it drove.
    #[test]
    fn frames_with_a_clipped_signal_are_counted() {
        let mut s = LatencyStats::new();
        for i in 1..=10 {
            let mut r = report(i, i, 5_000_000);
            r.flags = report_flags::SIGNAL_FOLLOWING;
            if i > 6 {
                r.flags |= report_flags::SIGNAL_CLIPPED;
            }
            s.record(&r);
        }
        assert_eq!(
            (s.signal_following_frames, s.signal_clipped_frames),
            (10, 4)
        );
    }

    /// Frames that drew a lung past its kernel's fold-free range are counted.
    #[test]
    fn frames_past_the_fold_free_range_are_counted() {
        let mut s = LatencyStats::new();
        for i in 1..=10 {
            let mut r = report(i, i, 5_000_000);
            if i % 3 == 0 {
                r.flags = report_flags::PAST_FOLD_FREE;
            }
            s.record(&r);
        }
        assert_eq!(s.past_fold_free_frames, 3);
    }

    #[test]
    fn submit_to_present_is_measured_on_presented_frames_only() {
        let mut s = LatencyStats::new();
        // Headless frames: nothing presented, no row, no mode.
        s.record(&report(1, 1, 5_000_000));
        assert_eq!(s.presented_frames, 0);
        assert_eq!(s.present_mode, None);
        assert!(!s.rows().iter().any(|r| r.hop.contains("present")));
        for i in 2..=11 {
            let mut r = report(i, i, 5_000_000);
            r.present_ns = r.stamps.renderer_submit_ns + i * 100_000;
            r.present_mode = ipc_types::present_mode::MAILBOX;
            r.frame_latency = 1;
            s.record(&r);
        }
        // A present stamp before the submit is a broken clock: counted presented, not timed.
        let mut r = report(12, 12, 5_000_000);
        r.present_ns = r.stamps.renderer_submit_ns - 1;
        r.present_mode = ipc_types::present_mode::MAILBOX;
        r.frame_latency = 1;
        s.record(&r);
        assert_eq!(s.presented_frames, 11);
        assert_eq!(s.present_mode, Some((ipc_types::present_mode::MAILBOX, 1)));
        let p = s.submit_to_present();
        assert_eq!(p.count, 10);
        assert!((p.max_ms - 1.1).abs() < 0.01, "{p:?}");
        assert!((p.p50_ms - 0.6).abs() < 0.01, "{p:?}");
        assert!(s.rows().iter().any(|r| r.hop == p.hop));
    }

    /// A report of tracker sample `n` captured at `n·P`, drawn `e2e` later.
    fn on_schedule(frame: u64, n: u64, e2e: u64) -> FrameReport {
        let p = SCHEDULE_PERIOD_NS;
        let c = 1_000_000_000 + n * p;
        FrameReport {
            frame,
            engine_tick: n,
            tracker_frame: n,
            stamps: HopStamps {
                capture_ns: c,
                bridge_publish_ns: c + 10,
                engine_receive_ns: c + 20,
                engine_publish_ns: c + 30,
                renderer_receive_ns: c + 40,
                renderer_submit_ns: c + e2e,
            },
            volume_ml: [1300.0, 1100.0],
            ..Default::default()
        }
    }

    /// A renderer frozen for two seconds draws nothing and then fresh data: per drawn frame nothing
    /// looks wrong, against the schedule ~120 samples are late and the worst waited ~2 s.
    #[test]
    fn a_two_second_stall_shows_as_missed_deadlines_and_a_two_second_worst_case() {
        let mut s = LatencyStats::new();
        let mut frame = 0;
        for n in 1..=60 {
            frame += 1;
            s.record(&on_schedule(frame, n, 1_000_000));
        }
        // Frozen: samples 61..=180 are never drawn; the next frame shows sample 181, 1 ms old.
        for n in 181..=240 {
            frame += 1;
            s.record(&on_schedule(frame, n, 1_000_000));
        }
        assert_eq!(s.deadline_misses, 0, "every drawn frame was on time");
        assert!((s.end_to_end().max_ms - 1.0).abs() < 0.01);
        assert_eq!(s.tracker_samples, 240);
        assert_eq!(
            s.sample_deadline_misses, 120,
            "samples 61..=180 waited > 16.7 ms"
        );
        let worst = s.sample_latency().max_ms;
        assert!((1990.0..=2010.0).contains(&worst), "{worst}");
        assert_eq!(s.missed_frame_slots, 120);
    }

    #[test]
    fn on_schedule_nothing_is_missed() {
        let mut s = LatencyStats::new();
        for n in 1..=600 {
            s.record(&on_schedule(n, n, 3_000_000));
        }
        assert_eq!((s.sample_deadline_misses, s.missed_frame_slots), (0, 0));
        assert_eq!(s.tracker_samples, 600);
        assert!((s.sample_latency().max_ms - 3.0).abs() < 0.01);
    }

    /// A renderer stopped for good reports nothing more: without `finish` the run looks punctual;
    /// with it every sample and display slot since its last frame is missed.
    #[test]
    fn a_renderer_that_never_comes_back_shows_as_missed_deadlines_to_the_end() {
        let p = SCHEDULE_PERIOD_NS;
        let mut s = LatencyStats::new();
        for n in 1..=60 {
            s.record(&on_schedule(n, n, 1_000_000));
        }
        assert_eq!(s.sample_deadline_misses, 0);
        // Stopped after sample 60; the run ends 3 s later.
        let last_capture = 1_000_000_000 + 60 * p;
        s.finish(last_capture + 3_000_000_000);
        assert!(
            (178..=180).contains(&s.sample_deadline_misses),
            "{}",
            s.sample_deadline_misses
        );
        assert!(
            (178..=180).contains(&s.missed_frame_slots),
            "{}",
            s.missed_frame_slots
        );
        assert!(s.sample_latency().max_ms > 2_900.0);
        // A run that ended on time adds nothing.
        let mut t = LatencyStats::new();
        for n in 1..=60 {
            t.record(&on_schedule(n, n, 1_000_000));
        }
        t.finish(last_capture + 5_000_000);
        assert_eq!((t.sample_deadline_misses, t.missed_frame_slots), (0, 0));
    }

    /// Restarted processes number from the start again: no report reads as out of order and the
    /// new bridge's samples are settled, not ignored as already shown.
    #[test]
    fn a_sample_number_beyond_the_clock_is_set_aside_not_settled() {
        let mut s = LatencyStats::new();
        for n in 1..=30 {
            s.record(&on_schedule(n, n, 1_000_000));
        }
        // A corrupted tracker frame's number: settling up to it looped for hours.
        let mut garbage = on_schedule(31, 31, 1_000_000);
        garbage.tracker_frame = u64::MAX - 3;
        s.record(&garbage);
        assert_eq!(s.implausible_samples, 1);
        assert_eq!(s.tracker_samples, 30);
        // The real sequence goes on being settled.
        for n in 32..=40 {
            s.record(&on_schedule(n, n, 1_000_000));
        }
        assert_eq!(s.tracker_samples, 40, "31 settled with 32");
        assert_eq!(s.implausible_samples, 1);
    }

    #[test]
    fn a_restarted_renderer_or_bridge_is_counted_from_its_new_numbers() {
        let mut s = LatencyStats::new();
        for n in 1..=60 {
            s.record(&on_schedule(n, n, 1_000_000));
        }
        s.restarted("renderer");
        s.restarted("tracker-bridge");
        // The engine still shows the old bridge's last sample for a while.
        s.record(&on_schedule(1, 60, 1_000_000));
        let before = s.tracker_samples;
        for n in 1..=10 {
            let mut r = on_schedule(n + 1, 60 + n, 1_000_000);
            r.tracker_frame = n;
            s.record(&r);
        }
        assert_eq!(s.out_of_order, 0);
        assert_eq!(s.lost_reports, 0);
        assert_eq!(s.tracker_samples, before + 10);
    }
}
