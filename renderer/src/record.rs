//! Snapshots of one whole breath, from one fixed viewpoint: what the demo's strip and its
//! `--record` animation are made of.
//!
//! A breath is the followed lung's own cycle as the engine runs it ([`BreathPlan`]): the frames are
//! planned when that lung starts a new cycle, spread over the cycle's length as the engine frame
//! states it (`cycle_ticks`), so a tension pneumothorax breathing at 40/min gives one breath, not
//! frames spaced for the scene's 12/min. The viewpoint is the front of the patient
//! ([`front_view`]): the same for every frame, whatever the walking HMD does.

use glam::{Mat3, Mat4, Vec3};
use ipc_types::{EngineFrame, Pose};

/// Plans `count` snapshots over the first whole breath that starts at or after a tick.
#[derive(Debug, Clone)]
pub struct BreathPlan {
    count: u32,
    after_tick: u64,
    seen_cycle: Option<u32>,
}

impl BreathPlan {
    /// `count` frames over the first breath starting at or after `after_tick`.
    pub fn new(count: u32, after_tick: u64) -> Self {
        Self {
            count,
            after_tick,
            seen_cycle: None,
        }
    }

    /// Watch `frame`; once the followed lung starts a new cycle at or after the start tick, the
    /// engine ticks to snapshot (the cycle's start, then evenly over its `cycle_ticks`).
    pub fn observe(&mut self, frame: &EngineFrame) -> Option<Vec<u64>> {
        let k = crate::hud::text::breathing_lung(frame)?;
        let l = &frame.lungs[k];
        let seen = self.seen_cycle.replace(l.cycle);
        if self.count == 0 || l.cycle_ticks == 0 || !l.phase.is_finite() {
            return None;
        }
        let ct = l.cycle_ticks as u64;
        let local = ((l.phase.clamp(0.0, 1.0) as f64 * ct as f64).round() as u64).min(ct - 1);
        let start = frame.tick.saturating_sub(local);
        // A cycle that began at or after the start tick, seen begin (a new cycle number), or the
        // very first frame when it is a cycle's first tick.
        let new_cycle = match seen {
            Some(c) => c != l.cycle,
            None => local == 0,
        };
        if !(new_cycle && start >= self.after_tick) {
            return None;
        }
        let n = self.count as u64;
        Some((0..n).map(|j| start + j * ct / n).collect())
    }
}

/// Most of the image's height (or width, whichever binds) the lungs' box fills in the
/// [`front_view`], at its anterior face.
pub const FRONT_VIEW_FILL: f32 = 0.55;
/// The band of the image (fractions of its height from the top) the [`front_view`] puts the lungs'
/// box in without a heads-up display to leave room for: below where a panel and PV loop end at
/// mid sizes (about a third of the way down). With a HUD, its own band is used
/// ([`crate::hud::Hud::lungs_band`]), which grows the top at small sizes.
pub const FRONT_VIEW_BAND: (f32, f32) = (0.34, 0.89);

/// The HMD pose that looks at the lungs from the front of the patient (from anterior, head up in
/// the image), far enough that the lungs' box fills [`FRONT_VIEW_FILL`] of the image's height (or
/// width), or less where `band` is narrower, centred in `band` (fractions of the image's height
/// from its top, e.g. [`FRONT_VIEW_BAND`]: what a HUD leaves clear): `model` is the body → room
/// matrix, `(lo, hi)` the lungs' box in the body frame (+Y anterior, +Z superior).
pub fn front_view(
    model: Mat4,
    (lo, hi): (Vec3, Vec3),
    fov_y_deg: f32,
    aspect: f32,
    band: (f32, f32),
) -> Pose {
    let centre = (lo + hi) * 0.5;
    let size = hi - lo;
    let t = (fov_y_deg.to_radians() * 0.5).tan().max(1e-3);
    let (top, bottom) = if band.0.is_finite() && band.1.is_finite() && band.1 > band.0 {
        (band.0.clamp(0.0, 1.0), band.1.clamp(0.0, 1.0))
    } else {
        FRONT_VIEW_BAND
    };
    // 6 % of the band spare: the box's corners behind its anterior face, seen from an eye aimed
    // above the centre, reach a little past the face's outline.
    let fill = FRONT_VIEW_FILL.min(0.94 * (bottom - top)).max(0.05);
    // Half the visible height at the box's anterior face, for the box's height (or width, by the
    // aspect) to fill `fill` of the image.
    let half_height = (size.z / (2.0 * fill)).max(size.x / (2.0 * fill * aspect.max(1e-3)));
    let distance = half_height / t + size.y * 0.5;
    let (distance, half_height) = if distance.is_finite() && distance > 0.0 {
        (distance, half_height)
    } else {
        (1000.0, 0.0)
    };
    // The box's top, as a fraction of the image's height from its top: the box centred in the
    // band (a box bound by its width is shorter than `fill`).
    let box_h = if half_height > 0.0 {
        size.z / (2.0 * half_height)
    } else {
        0.0
    };
    let box_top = top + (bottom - top - box_h).max(0.0) * 0.5;
    // Aim above the lungs' centre so that the box's top lands `box_top` of the way down: the
    // image centre is `size.z / 2 − (1 − 2·box_top)·half_height` above the centre.
    let above = size.z * 0.5 - (1.0 - 2.0 * box_top) * half_height;
    let target = model.transform_point3(centre + Vec3::Z * above);
    let eye = model.transform_point3(centre + Vec3::Y * distance);
    let up_room = model.transform_vector3(Vec3::Z).normalize_or(Vec3::Z);
    let forward = (target - eye).normalize_or(Vec3::NEG_Y);
    let right = forward.cross(up_room).normalize_or(Vec3::X);
    let up = right.cross(forward);
    let q = glam::Quat::from_mat3(&Mat3::from_cols(right, up, -forward)).normalize();
    Pose {
        quat: q.to_array(),
        translation_mm: eye.to_array(),
        _pad: 0,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use ipc_types::{lung_flags, LUNG_LEFT, LUNG_RIGHT};

    fn frame(tick: u64, cycle: u32, ct: u32, first_tick_of_cycle: u64) -> EngineFrame {
        let mut f = EngineFrame {
            tick,
            ..Default::default()
        };
        let l = &mut f.lungs[LUNG_LEFT];
        l.flags = lung_flags::ACTIVE;
        l.cycle = cycle;
        l.cycle_ticks = ct;
        l.phase = (tick - first_tick_of_cycle) as f32 / ct as f32;
        f
    }

    #[test]
    fn a_breath_is_planned_at_the_lungs_own_rate() {
        // A lung breathing at 40/min (90 ticks at 60 Hz) while the scene says 12/min (300).
        let mut p = BreathPlan::new(6, 100);
        for tick in 0..400u64 {
            let f = frame(tick, (tick / 90) as u32, 90, tick / 90 * 90);
            if let Some(ticks) = p.observe(&f) {
                assert_eq!(tick, 180, "the first cycle starting at or after tick 100");
                assert_eq!(ticks, vec![180, 195, 210, 225, 240, 255]);
                return;
            }
        }
        panic!("never planned");
    }

    #[test]
    fn a_skipped_start_tick_still_plans_from_the_cycles_start() {
        // The renderer saw tick 185 first in the new cycle (frames dropped): the breath still
        // starts at 180, and the past ticks are taken at once by the snapshot loop.
        let mut p = BreathPlan::new(3, 0);
        assert!(p.observe(&frame(170, 1, 90, 90)).is_none());
        assert_eq!(
            p.observe(&frame(185, 2, 90, 180)),
            Some(vec![180, 210, 240])
        );
    }

    #[test]
    fn a_rate_change_is_followed_and_a_held_lung_is_not_the_one_followed() {
        let mut p = BreathPlan::new(2, 0);
        let mut f = frame(299, 0, 300, 0);
        f.lungs[LUNG_RIGHT] = f.lungs[LUNG_LEFT];
        f.lungs[LUNG_RIGHT].flags |= lung_flags::HELD;
        f.lungs[LUNG_RIGHT].cycle_ticks = 1000;
        assert!(p.observe(&f).is_none());
        let mut g = frame(300, 1, 120, 300);
        g.lungs[LUNG_RIGHT] = f.lungs[LUNG_RIGHT];
        assert_eq!(p.observe(&g), Some(vec![300, 360]));
        // Nothing to plan: no count, or no lung.
        assert!(BreathPlan::new(0, 0).observe(&frame(0, 0, 90, 0)).is_none());
        assert!(BreathPlan::new(3, 0)
            .observe(&EngineFrame::default())
            .is_none());
    }

    /// Image-plane horizontal coordinate (mm, + to the viewer's right) of the generated `side`
    /// lung's centroid, seen from the front view of a supine patient.
    fn seen_from_the_front(side: lung_model::mesh::Side) -> f32 {
        use lung_model::mesh::{generate, Side};
        let lungs = [Side::Right, Side::Left].map(|s| generate::lung(s, 2_000).unwrap());
        let (mut lo, mut hi) = (Vec3::splat(f32::INFINITY), Vec3::splat(f32::NEG_INFINITY));
        for p in lungs.iter().flat_map(|m| &m.positions) {
            lo = lo.min(Vec3::from(*p));
            hi = hi.max(Vec3::from(*p));
        }
        let supine = glam::Quat::from_mat3(&Mat3::from_cols(Vec3::Y, Vec3::Z, Vec3::X));
        let patient = Pose {
            quat: supine.to_array(),
            translation_mm: [0.0, 0.0, 1000.0],
            _pad: 0,
        };
        let model = crate::camera::Rig::default().model(&patient);
        let pose = front_view(model, (lo, hi), 60.0, 4.0 / 3.0, FRONT_VIEW_BAND);
        let mesh = &lungs[if side == Side::Right { 0 } else { 1 }];
        let centroid = mesh.positions.iter().map(|p| Vec3::from(*p)).sum::<Vec3>()
            / mesh.positions.len() as f32;
        let q = glam::Quat::from_array(pose.quat);
        (q * Vec3::X).dot(model.transform_point3(centroid) - Vec3::from(pose.translation_mm))
    }

    /// Handedness (issue 19): seen from the front (anterior, head up) — as a clinician facing the
    /// patient sees them, and as radiology shows an anterior view — the patient's right lung is on
    /// the viewer's left. The body frame (+X patient left, +Y anterior, +Z superior) is physically
    /// left-handed (patient-left × anterior = inferior), while the renderer and the room are
    /// right-handed: with body → room taken as a rotation the front view showed a mirror-image
    /// patient (the right lung on the viewer's right, the cardiac notch on the viewer's left).
    /// The model matrix now reflects through `lung_model::frame::body_to_room`.
    #[test]
    fn the_patients_right_lung_is_on_the_viewers_left_from_the_front() {
        use lung_model::mesh::Side;
        let (right, left) = (
            seen_from_the_front(Side::Right),
            seen_from_the_front(Side::Left),
        );
        assert!(
            right < -20.0 && left > 20.0,
            "right lung at {right} mm, left at {left} mm"
        );
    }

    #[test]
    fn the_front_view_looks_at_the_lungs_from_anterior_with_the_head_up() {
        // Patient supine: body +Y (anterior) is room +Z (up), body +Z (superior) room +X.
        let supine = glam::Quat::from_mat3(&Mat3::from_cols(Vec3::Y, Vec3::Z, Vec3::X));
        let model = lung_model::frame::body_to_room(Mat4::from_rotation_translation(
            supine,
            Vec3::new(0.0, 0.0, 1000.0),
        ));
        let boxed = (
            Vec3::new(-150.0, -100.0, -120.0),
            Vec3::new(150.0, 100.0, 130.0),
        );
        let pose = front_view(model, boxed, 60.0, 16.0 / 9.0, FRONT_VIEW_BAND);
        let eye = Vec3::from(pose.translation_mm);
        // Above the patient (room up), looking down at the chest, the head at the image's top.
        assert!(eye.z > 1300.0, "{eye}");
        let q = glam::Quat::from_array(pose.quat);
        let forward = q * Vec3::NEG_Z;
        let up = q * Vec3::Y;
        assert!(forward.z < -0.95, "{forward}");
        assert!(up.x > 0.95, "head (room +X) is up: {up}");
        assert!((q.length() - 1.0).abs() < 1e-5);
        // A degenerate box still gives a finite pose.
        let p = front_view(model, (Vec3::ZERO, Vec3::ZERO), 60.0, 1.0, (f32::NAN, 0.5));
        assert!(p.is_finite());
    }
}
