//! Realistic head motion for evaluating pose prediction: a clinician wearing the HMD at the
//! bedside, written as a recording (`lungdyn tracker simulate`), so `lungdyn tracker predict` can
//! be measured on motion with the speeds and spectra of real heads without a tracker at hand.
//!
//! The model (room frame of [`crate::synthetic`]: bed along X, patient reference on the sternum):
//! - **standing and walking**: the wearer stands at a point of an ellipse round the bed for 2–6 s,
//!   then walks 20–70° of it at about 0.6 m/s (minimum-jerk profile); while walking the head bobs
//!   15 mm vertically at the 2 Hz step rate and sways 10 mm sideways at the 1 Hz stride rate
//!   (head displacement in gait is a few centimetres peak to peak, e.g. Hirasaki et al. 1999);
//!   while standing, postural sway of a few millimetres below 0.5 Hz;
//! - **gaze shifts**: every 0.8–3 s the head turns to a new target around the chest (yaw within
//!   ±25°, pitch ±15°; one in six a large 40–60° look away, e.g. at a monitor) with a
//!   minimum-jerk rotation lasting 0.2 s + 8 ms per degree, so a 20° shift peaks near 110°/s and a
//!   50° one near 155°/s, within measured head-movement peak speeds of 100–300°/s (Grossman et al.
//!   1988; Zangemeister & Stark 1982);
//! - **small rotations**: ±0.3° of physiological tremor and drift at 0.5–3 Hz on every axis;
//! - **tracker noise**: Gaussian, 0.05 mm per axis and 0.02° per axis by default (an optical
//!   tracker's jitter is of that order; its RMS accuracy of 0.1–0.25 mm is mostly bias).
//!
//! The patient reference rises and falls 2 mm with breathing at 0.25 Hz. Deterministic for a seed.

use std::f64::consts::TAU;

use glam::{DQuat, DVec3};

use crate::assemble::BridgeConfig;
use crate::record::{RecordError, RecordWriter};
use crate::sample::{Rotation, Sample, ToolName};
use crate::synthetic::{HEAD_HEIGHT_MM, STERNUM_MM};
use crate::validate::{Validation, Volume};

/// Parameters of a generated session.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct HeadMotion {
    /// Length, s.
    pub seconds: f64,
    /// Sample rate, Hz.
    pub rate_hz: f64,
    /// Random seed.
    pub seed: u64,
    /// Position noise per axis (1 σ), mm.
    pub noise_mm: f64,
    /// Rotation noise per axis (1 σ), degrees.
    pub noise_deg: f64,
}

impl Default for HeadMotion {
    fn default() -> Self {
        HeadMotion {
            seconds: 60.0,
            rate_hz: 60.0,
            seed: 1,
            noise_mm: 0.05,
            noise_deg: 0.02,
        }
    }
}

/// SplitMix64: small, fast, reproducible everywhere.
#[derive(Debug, Clone)]
struct Rng(u64);

impl Rng {
    fn next(&mut self) -> u64 {
        self.0 = self.0.wrapping_add(0x9E37_79B9_7F4A_7C15);
        let mut z = self.0;
        z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
        z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
        z ^ (z >> 31)
    }
    fn uniform(&mut self, lo: f64, hi: f64) -> f64 {
        lo + (hi - lo) * ((self.next() >> 11) as f64 / (1u64 << 53) as f64)
    }
    fn gauss(&mut self) -> f64 {
        let u = self.uniform(f64::MIN_POSITIVE, 1.0);
        let v = self.uniform(0.0, 1.0);
        (-2.0 * u.ln()).sqrt() * (TAU * v).cos()
    }
}

/// Minimum-jerk blend 0 → 1 over s ∈ [0, 1].
fn min_jerk(s: f64) -> f64 {
    let s = s.clamp(0.0, 1.0);
    s * s * s * (10.0 - 15.0 * s + 6.0 * s * s)
}

/// A piecewise minimum-jerk trajectory of one value: holds, then moves to the next value.
#[derive(Debug, Clone)]
struct Moves {
    /// (start time, duration, from, to).
    segments: Vec<(f64, f64, f64, f64)>,
}

impl Moves {
    fn at(&self, t: f64) -> f64 {
        let i = self.segments.partition_point(|s| s.0 <= t);
        match i.checked_sub(1).and_then(|i| self.segments.get(i)) {
            None => self.segments.first().map_or(0.0, |s| s.2),
            Some(&(start, dur, from, to)) => from + (to - from) * min_jerk((t - start) / dur),
        }
    }
    /// Fraction of the way through a movement at `t` (0 when holding), for gait.
    fn moving(&self, t: f64) -> f64 {
        let i = self.segments.partition_point(|s| s.0 <= t);
        match i.checked_sub(1).and_then(|i| self.segments.get(i)) {
            Some(&(start, dur, _, _)) if t < start + dur => {
                let s = (t - start) / dur;
                // Speed profile of a minimum-jerk move, normalised to 1 at its peak.
                (30.0 * s * s * (1.0 - s) * (1.0 - s)) / 1.875
            }
            _ => 0.0,
        }
    }
}

/// The poses of one session: `(t seconds, patient pose, HMD pose)` per sample, noise included.
pub fn session(m: &HeadMotion) -> Vec<(f64, (DQuat, DVec3), (DQuat, DVec3))> {
    let mut rng = Rng(m.seed ^ 0x6C75_6E67_6479_6E00);
    let n = (m.seconds * m.rate_hz).round().max(1.0) as usize;
    // Walking: station angle along the ellipse.
    let mut station = Moves {
        segments: Vec::new(),
    };
    let (mut t, mut angle) = (0.0, rng.uniform(0.0, TAU));
    while t < m.seconds + 10.0 {
        let hold = rng.uniform(2.0, 6.0);
        let step = rng.uniform(20f64.to_radians(), 70f64.to_radians())
            * if rng.uniform(0.0, 1.0) < 0.5 {
                -1.0
            } else {
                1.0
            };
        let dur = (step.abs() * 875.0 / 600.0).max(1.0); // arc on a ~875 mm mean radius at 0.6 m/s
        station.segments.push((t + hold, dur, angle, angle + step));
        angle += step;
        t += hold + dur;
    }
    // Gaze shifts: yaw and pitch offsets from the direction of the chest.
    let (mut yaw, mut pitch) = (
        Moves {
            segments: Vec::new(),
        },
        Moves {
            segments: Vec::new(),
        },
    );
    let (mut t, mut y0, mut p0) = (0.0, 0.0, 0.0);
    while t < m.seconds + 10.0 {
        t += rng.uniform(0.8, 3.0);
        let far = rng.uniform(0.0, 1.0) < 1.0 / 6.0;
        let y1 = if far {
            rng.uniform(40.0, 60.0)
                * if rng.uniform(0.0, 1.0) < 0.5 {
                    -1.0
                } else {
                    1.0
                }
        } else {
            rng.uniform(-25.0, 25.0)
        };
        let p1 = rng.uniform(-15.0, 15.0);
        let amplitude = ((y1 - y0) * (y1 - y0) + (p1 - p0) * (p1 - p0)) as f64;
        let dur = 0.2 + 0.008 * amplitude.sqrt();
        yaw.segments.push((t, dur, y0, y1));
        pitch.segments.push((t, dur, p0, p1));
        (y0, p0) = (y1, p1);
        t += dur;
    }
    // Tremor and sway: a few sinusoids with random phases.
    let waves: Vec<(f64, f64, f64)> = (0..12)
        .map(|_| {
            (
                rng.uniform(0.5, 3.0),
                rng.uniform(0.05, 0.15),
                rng.uniform(0.0, TAU),
            )
        })
        .collect();
    let sway: Vec<(f64, f64)> = (0..4)
        .map(|_| (rng.uniform(0.1, 0.5), rng.uniform(0.0, TAU)))
        .collect();
    let chest = DVec3::new(
        f64::from(STERNUM_MM.x),
        f64::from(STERNUM_MM.y),
        f64::from(STERNUM_MM.z) - 80.0,
    );
    let supine = {
        let q = crate::synthetic::supine();
        DQuat::from_xyzw(
            f64::from(q.x),
            f64::from(q.y),
            f64::from(q.z),
            f64::from(q.w),
        )
    };
    let noise_rad = m.noise_deg.to_radians();
    (0..n)
        .map(|k| {
            let t = k as f64 / m.rate_hz;
            let a = station.at(t);
            let walking = station.moving(t);
            let forward = DVec3::new(-a.sin(), a.cos() * 0.75, 0.0).normalize_or_zero();
            let side = DVec3::new(forward.y, -forward.x, 0.0);
            let standing = 1.0 - walking;
            let sway_v: f64 = sway
                .iter()
                .map(|(f, ph)| (TAU * f * t + ph).sin())
                .sum::<f64>();
            let mut head = DVec3::new(1000.0 * a.cos(), 750.0 * a.sin(), f64::from(HEAD_HEIGHT_MM))
                + DVec3::Z * (15.0 * walking * (TAU * 2.0 * t).sin())
                + side * (10.0 * walking * (TAU * 1.0 * t).sin() + 2.0 * standing * sway_v);
            head += forward * (1.5 * standing * sway_v);
            // Look at the chest, then turn by the gaze offsets (yaw about room Z, pitch about the
            // head's right axis), then tremor on every axis.
            let look = {
                let f = (chest - head).normalize();
                let r = f.cross(DVec3::Z).normalize();
                let u = r.cross(f);
                DQuat::from_mat3(&glam::DMat3::from_cols(r, u, -f))
            };
            let tremor = |i: usize| -> f64 {
                waves[i * 4..i * 4 + 4]
                    .iter()
                    .map(|(f, amp, ph)| amp * (TAU * f * t + ph).sin())
                    .sum::<f64>()
                    .to_radians()
            };
            let q = DQuat::from_rotation_z(yaw.at(t).to_radians())
                * look
                * DQuat::from_rotation_x(pitch.at(t).to_radians())
                * DQuat::from_euler(glam::EulerRot::XYZ, tremor(0), tremor(1), tremor(2));
            let jitter = |rng: &mut Rng, s: f64| {
                DVec3::new(rng.gauss() * s, rng.gauss() * s, rng.gauss() * s)
            };
            let hq = DQuat::from_scaled_axis(jitter(&mut rng, noise_rad)) * q;
            let hp = head + jitter(&mut rng, m.noise_mm);
            let breath = DVec3::Z * (2.0 * (TAU * 0.25 * t).sin());
            let pq = DQuat::from_scaled_axis(jitter(&mut rng, noise_rad)) * supine;
            let pp = DVec3::new(
                f64::from(STERNUM_MM.x),
                f64::from(STERNUM_MM.y),
                f64::from(STERNUM_MM.z),
            ) + breath
                + jitter(&mut rng, m.noise_mm);
            (t, (pq.normalize(), pp), (hq.normalize(), hp))
        })
        .collect()
}

/// The configuration a generated recording carries: the usual tool names, no volume (room frame).
pub fn config(rate_hz: f64) -> BridgeConfig {
    BridgeConfig {
        rate_hz,
        validation: Validation {
            volume: Volume::Unbounded,
            ..Validation::default()
        },
        ..BridgeConfig::default()
    }
}

/// Write a session to `path` as a recording (one tick per sample); returns the samples per tool.
pub fn write(path: &std::path::Path, m: &HeadMotion) -> Result<usize, RecordError> {
    let poses = session(m);
    let config = config(m.rate_hz);
    let mut w = RecordWriter::create(
        path,
        &config,
        &format!("lungdyn tracker simulate (head motion, seed {})", m.seed),
    )?;
    let io = |source| RecordError::Io {
        path: path.to_path_buf(),
        source,
    };
    let names = [
        ToolName::new("Patient").expect("static"),
        ToolName::new("HMD").expect("static"),
    ];
    let t0: u64 = 1_000_000_000;
    for (k, (t, patient, hmd)) in poses.iter().enumerate() {
        let ns = t0 + (t * 1e9).round() as u64;
        for (i, (q, p)) in [patient, hmd].into_iter().enumerate() {
            w.sample(&Sample {
                receive_ns: ns,
                device_time_ns: 0,
                device_frame: Some(k as u64 + 1),
                name: names[i],
                tool_id: i as u32 + 1,
                rotation: Rotation::Quat([q.x as f32, q.y as f32, q.z as f32, q.w as f32]),
                translation_mm: [p.x as f32, p.y as f32, p.z as f32],
                rms_error_mm: Some(0.25),
                device_flags: 0,
            })
            .map_err(io)?;
        }
        w.tick(ns, k as u64 + 1).map_err(io)?;
    }
    w.finish()?;
    Ok(poses.len())
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn head_motion_has_the_speeds_of_real_heads_and_is_reproducible() {
        let m = HeadMotion {
            seconds: 120.0,
            noise_mm: 0.0,
            noise_deg: 0.0,
            ..Default::default()
        };
        let s = session(&m);
        assert_eq!(s, session(&m), "same seed, same motion");
        let dt = 1.0 / m.rate_hz;
        let speeds: Vec<f64> = s
            .windows(2)
            .map(|w| w[1].2 .0.angle_between(w[0].2 .0).to_degrees() / dt)
            .collect();
        let peak = speeds.iter().cloned().fold(0.0, f64::max);
        let mean = speeds.iter().sum::<f64>() / speeds.len() as f64;
        assert!(
            (80.0..300.0).contains(&peak),
            "peak head speed {peak} deg/s"
        );
        assert!((5.0..60.0).contains(&mean), "mean head speed {mean} deg/s");
        let lin: Vec<f64> = s
            .windows(2)
            .map(|w| (w[1].2 .1 - w[0].2 .1).length() / dt)
            .collect();
        let lpeak = lin.iter().cloned().fold(0.0, f64::max);
        assert!(
            (300.0..1500.0).contains(&lpeak),
            "peak walking speed {lpeak} mm/s"
        );
        for (_, _, (_, p)) in &s {
            assert!((p.z - 1600.0).abs() < 40.0 && p.truncate().length() > 650.0);
        }
    }
}
