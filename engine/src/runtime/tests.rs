use super::*;
use ipc_types::{tool_status, ToolPose, LUNG_LEFT, LUNG_RIGHT};
use lung_model::mesh::generate;

fn frame(n: u64, patient_valid: bool) -> TrackerFrame {
    let mut f = TrackerFrame {
        layout_version: LAYOUT_VERSION,
        tool_count: 2,
        frame_number: n,
        ..Default::default()
    };
    f.stamps.capture_ns = 1000 + n;
    f.tools[TOOL_PATIENT] = ToolPose {
        tool_id: 1,
        status: if patient_valid {
            tool_status::VALID
        } else {
            tool_status::MISSING
        },
        pose: Pose {
            quat: [0.0, 0.0, (n as f32 * 0.01).sin(), 1.0],
            translation_mm: [n as f32, 0.0, 900.0],
            _pad: 0,
        },
        rms_error_mm: 0.2,
        _pad: 0,
    };
    f
}

/// Both default lungs at 1000 vertices, baked in memory exactly as the launcher bakes them.
fn baked_geometry() -> Vec<LungGeometry> {
    [Side::Right, Side::Left]
        .into_iter()
        .map(|side| {
            let k = lung_bake::kernel::bake(
                side,
                generate::lung(side, 1000).unwrap(),
                &lung_bake::kernel::BakeSettings::default_for(side),
                &|_| {},
            )
            .unwrap();
            let mut m = LungModel::from_unit_displacement(side, k.mesh, k.unit_displacement);
            m.kernel_id = 0x1000 + side.index() as u64;
            LungGeometry::of(&m)
        })
        .collect()
}

fn core() -> EngineCore {
    EngineCore::with_geometry(&Scene::default(), baked_geometry()).unwrap()
}

/// A recorded input sequence with gaps (deadline-fallback ticks) and bad patient samples.
fn replay(core: &mut EngineCore) -> Vec<EngineFrame> {
    let mut out = Vec::new();
    for tick in 0..900u64 {
        let input = match tick % 37 {
            5 | 6 => None,
            9 => Some(frame(tick, false)),
            _ => Some(frame(tick, true)),
        };
        let mut f = EngineFrame::default();
        core.step(tick, input.as_ref(), &mut f);
        out.push(f);
    }
    out
}

fn fnv(words: impl Iterator<Item = u64>) -> u64 {
    words.fold(0xcbf2_9ce4_8422_2325_u64, |h, w| {
        (h ^ w).wrapping_mul(0x0000_0100_0000_01b3)
    })
}

/// The fields of the v1 frame, as the v1 reference digest saw them.
fn v1_words(f: &EngineFrame, cycle_ticks: u32) -> Vec<u64> {
    let mut v = vec![
        f.state as u64,
        f.fault as u64,
        cycle_ticks as u64,
        f.tick as u32 as u64,
        f.tracker_frame as u32 as u64,
    ];
    v.extend(
        f.patient_pose
            .quat
            .iter()
            .chain(&f.patient_pose.translation_mm)
            .map(|x| x.to_bits() as u64),
    );
    for l in &f.lungs {
        v.extend([
            l.volume_ml.to_bits() as u64,
            l.deform_scale.to_bits() as u64,
            (l.flags & lung_flags::ACTIVE) as u64,
        ]);
    }
    v
}

#[test]
fn same_inputs_replay_bitwise_identically() {
    let a = replay(&mut core());
    let b = replay(&mut core());
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(
            bytemuck::bytes_of(x),
            bytemuck::bytes_of(y),
            "tick {}",
            x.tick
        );
    }
    // Every byte of every frame, pinned across builds and machines.
    let digest = fnv(a
        .iter()
        .flat_map(|f| bytemuck::bytes_of(f).iter().map(|&b| b as u64)));
    assert_eq!(
        digest, REFERENCE_DIGEST_V2,
        "reference run changed: digest {digest:#018x}"
    );
}

/// Per-lung state (layout v2) changed nothing of what v1 computed: the v1 fields of the same
/// replay still give the digest pinned before the change.
#[test]
fn per_lung_state_reproduces_the_shared_cycle_exactly() {
    let mut c = core();
    let ct = c.cycle_ticks();
    let a = replay(&mut c);
    let digest = fnv(a.iter().flat_map(|f| v1_words(f, ct)));
    assert_eq!(digest, REFERENCE_DIGEST_V1, "digest {digest:#018x}");
}

/// FNV-1a over [`v1_words`] of the 900-tick reference replay at 1000 vertices per lung, as pinned
/// by the v1 engine (one shared breathing state).
const REFERENCE_DIGEST_V1: u64 = 0xd9cf7a77d6c0942c;
/// FNV-1a over every byte of every v2 frame of the same replay.
const REFERENCE_DIGEST_V2: u64 = 0x83ae09d79b4e1967;

#[test]
fn missing_samples_hold_the_pose_and_flag_it() {
    let mut core = core();
    let mut f = EngineFrame::default();
    core.step(0, None, &mut f);
    assert_ne!(f.state & engine_state::NO_TRACKER_YET, 0);
    core.step(1, Some(&frame(1, true)), &mut f);
    let good = f.patient_pose;
    assert_eq!(f.state & engine_state::PATIENT_POSE_HELD, 0);
    core.step(2, Some(&frame(2, false)), &mut f);
    assert_eq!(f.patient_pose, good);
    assert_ne!(f.state & engine_state::PATIENT_POSE_HELD, 0);
    for t in 3..40 {
        core.step(t, None, &mut f);
    }
    assert_ne!(f.state & engine_state::PATIENT_POSE_STALE, 0);
    assert_eq!(f.fault, fault::TRACKER_LOST);
    assert_eq!(f.patient_pose, good);
}

#[test]
fn lung_volumes_follow_the_pv_model_and_carry_their_kernel() {
    let mut core = core();
    let breathing = core.lung(Side::Left).unwrap().breathing().clone();
    let mut f = EngineFrame::default();
    for tick in 0..600 {
        core.step(tick, None, &mut f);
        let total: f32 = f.lungs.iter().map(|l| l.volume_ml).sum();
        let expect = breathing.volume_at(tick) as f32;
        assert!(
            (total - expect).abs() < 0.5,
            "tick {tick}: {total} vs {expect}"
        );
        for (i, l) in f.lungs.iter().enumerate() {
            assert!(l.volume_ml.is_finite() && l.deform_scale.is_finite() && l.deform_scale >= 0.0);
            assert_eq!(l.kernel_id, 0x1000 + i as u64);
            assert!(l.is_active());
            assert_eq!(l.cycle as u64, tick / 300);
            assert_eq!(l.phase, ((tick % 300) as f64 / 300.0) as f32);
        }
    }
}

#[test]
fn one_lung_can_stop_while_the_other_breathes() {
    let mut core = core();
    let mut f = EngineFrame::default();
    core.step(0, None, &mut f);
    let left_rest = f.lungs[LUNG_LEFT].volume_ml as f64;
    core.lung_mut(Side::Left)
        .unwrap()
        .hold(Some(left_rest - 200.0));
    core.lung_mut(Side::Left)
        .unwrap()
        .set_offset_mm([0.0, 0.0, -12.0]);
    let mut right = Vec::new();
    for tick in 1..300 {
        core.step(tick, None, &mut f);
        let l = &f.lungs[LUNG_LEFT];
        assert_eq!(l.volume_ml as f64, (left_rest - 200.0) as f32 as f64);
        assert_ne!(l.flags & lung_flags::HELD, 0);
        assert_eq!(l.offset_mm, [0.0, 0.0, -12.0]);
        assert!(
            l.deform_scale < 0.0,
            "a held, smaller lung shrinks along its field"
        );
        right.push(f.lungs[LUNG_RIGHT].volume_ml);
        assert_eq!(f.lungs[LUNG_RIGHT].flags & lung_flags::HELD, 0);
    }
    let (lo, hi) = right
        .iter()
        .fold((f32::MAX, f32::MIN), |(a, b), &v| (a.min(v), b.max(v)));
    assert!(hi - lo > 200.0, "the right lung still breathes: {lo}..{hi}");
    core.lung_mut(Side::Left).unwrap().hold(None);
    core.step(300, None, &mut f);
    assert_eq!(f.lungs[LUNG_LEFT].flags & lung_flags::HELD, 0);
}

#[test]
fn a_rate_change_takes_effect_at_the_next_cycle_start() {
    let mut core = core();
    let mut fast_scene = Scene::default();
    fast_scene.pv.breaths_per_min = 20.0;
    let (i, e, b) = fast_scene.pv_model().unwrap();
    let fast = Breathing::from_constants(&i, &e, b, &fast_scene.timing()).unwrap();
    assert_eq!(fast.cycle_ticks(), 180);
    let mut f = EngineFrame::default();
    core.step(0, None, &mut f);
    core.lung_mut(Side::Left)
        .unwrap()
        .set_breathing_from_next_cycle(fast);
    let mut cycle_starts = Vec::new();
    for tick in 1..1000u64 {
        core.step(tick, None, &mut f);
        let l = &f.lungs[LUNG_LEFT];
        if l.phase == 0.0 {
            cycle_starts.push((tick, l.cycle, l.flags & lung_flags::CYCLE_CHANGED != 0));
        }
        assert!(l.volume_ml.is_finite());
        // The right lung keeps the old rhythm.
        assert_eq!(
            f.lungs[LUNG_RIGHT].phase,
            ((tick % 300) as f64 / 300.0) as f32
        );
    }
    // The current breath finishes (300 ticks), then 180-tick cycles; the change is flagged once.
    assert_eq!(
        cycle_starts,
        vec![
            (300, 1, true),
            (480, 2, false),
            (660, 3, false),
            (840, 4, false)
        ]
    );
}

#[test]
fn hours_of_ticks_stay_finite_periodic_and_bounded() {
    let mut core = core();
    let mut f = EngineFrame::default();
    let mut first_cycle = Vec::new();
    for tick in 0..(60 * 60 * 60 * 2u64) {
        core.step(tick, None, &mut f);
        for l in &f.lungs {
            assert!(l.volume_ml.is_finite() && l.deform_scale.is_finite() && l.phase < 1.0);
        }
        let v = f.lungs[LUNG_LEFT].volume_ml.to_bits();
        if tick < 300 {
            first_cycle.push(v);
        } else {
            assert_eq!(v, first_cycle[(tick % 300) as usize], "tick {tick}");
        }
    }
    assert_eq!(f.lungs[LUNG_LEFT].cycle, (60 * 60 * 60 * 2 - 1) / 300);
}

#[test]
fn a_scene_without_kernels_is_refused_with_the_way_to_get_them() {
    let e = EngineCore::new(&Scene::default()).unwrap_err().to_string();
    assert!(e.contains("no kernel for the right lung"), "{e}");
    assert!(e.contains("lungdyn scene prepare"), "{e}");
}
