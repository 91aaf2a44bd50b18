use super::*;
use ipc_types::{tool_status, ToolPose, LUNG_LEFT, LUNG_RIGHT};
use lung_model::mesh::generate;
use lung_model::orientation::OrientationMethod;

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
            quat: unit_quat([0.0, 0.0, (n as f32 * 0.01).sin(), 1.0]),
            translation_mm: [n as f32, 0.0, 900.0],
            _pad: 0,
        },
        rms_error_mm: 0.2,
        _pad: 0,
    };
    f
}

/// `q / |q|` in f32 (tracker quaternions are unit rotations).
fn unit_quat(q: [f32; 4]) -> [f32; 4] {
    let n = q.iter().map(|v| v * v).sum::<f32>().sqrt();
    q.map(|v| v / n)
}

/// Both default lungs at 1000 vertices, baked in memory exactly as the launcher bakes them.
fn baked_geometry() -> Vec<LungGeometry> {
    [Side::Right, Side::Left]
        .into_iter()
        .map(|side| {
            // The seed's Table 6.1 directions, as every bake had before the population preset
            // became the default: the digests below pin the engine's tick, and a kernel baked
            // the same way keeps them comparable across that change.
            let mut settings = lung_bake::kernel::BakeSettings::default_for(side);
            settings.motion = lung_model::deform::MotionConstants::table_6_1(side);
            // ... and the seed's unsmoothed catch factors (amplitude_smoothing_mm = 0).
            settings.amplitude_smoothing_mm = 0.0;
            let k = lung_bake::kernel::bake(
                side,
                generate::lung(side, 1000).unwrap(),
                &settings,
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
    // Every byte of every frame as layout v2 had it (v3 only appended each lung's collapse and
    // hilum, zero for a healthy lung), pinned across builds and machines.
    let digest = fnv(a
        .iter()
        .flat_map(|f| v2_bytes(f).into_iter().map(|b| b as u64)));
    assert_eq!(
        digest, REFERENCE_DIGEST_V2,
        "reference run changed: digest {digest:#018x}"
    );
    for f in &a {
        for l in &f.lungs {
            assert_eq!((l.collapse, l.hilum_mm), (0.0, [0.0; 3]));
        }
    }
}

/// The bytes of `f` in layout v2: the header (with version 2) and each lung without the v3 fields.
fn v2_bytes(f: &EngineFrame) -> Vec<u8> {
    let mut v2 = *f;
    v2.layout_version = 2;
    let bytes = bytemuck::bytes_of(&v2);
    let header = core::mem::offset_of!(EngineFrame, lungs);
    let lung = core::mem::size_of::<LungFrame>();
    let v2_lung = core::mem::offset_of!(LungFrame, collapse);
    let mut out = bytes[..header].to_vec();
    for k in 0..NUM_LUNGS {
        let at = header + k * lung;
        out.extend_from_slice(&bytes[at..at + v2_lung]);
    }
    out
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
/// by the v1 engine (one shared breathing state): 0xd9cf7a77d6c0942c with the replay's original,
/// not-quite-unit quaternions. The orientation modes refuse a pose that is not a rotation, so the
/// replay now feeds unit quaternions; both digests were re-pinned by running the engine *before*
/// the orientation change (commit 1508ae7) on the new replay, so they prove the precomputed mode
/// unchanged by it. Issue 19 made the anatomical lungs the generated default: the replay's lungs
/// changed shape (each lung's volume cubic, hence `deform_scale`, and every displacement), so both
/// digests were re-pinned (teardrop: 0x79219bf4fc346d87 and 0xf5880a7e074aa73e) after two runs of
/// the replay — one and several test threads — gave the same new digests. Issue 25 made the
/// scene's default I:E 1:2 (quiet breathing; EQUATIONS §1.1) instead of the seed's 1:1: the replay's
/// breath changed shape in time (a 100-tick inhalation and 200-tick exhalation instead of 150 + 150),
/// so both digests were re-pinned (1:1: 0xbda578dfd1470065 and 0x064f9f6ef8aa5d4f) after the replay
/// gave equal frames twice in one run and the same digests with one and with four test threads.
/// Issue 34 rounded the anatomical lungs' inferior border (a crease drawn as a saw-tooth): the
/// replay's lungs changed shape there (volume and every displacement), so both digests were
/// re-pinned (sharp border: 0xbfd9db59148f44f9 and 0x1a1bb03e53268759) after runs with one and
/// with two test threads gave the same new digests. Issue 34 widened the anterior border of the
/// coarsest lungs to two columns of vertices (the 1178-vertex right lung crossed itself): the
/// replay's 1000-vertex lungs changed shape there, so both digests were re-pinned (0.2 rad ridge:
/// 0x392793cbbee04863 and 0xe537b5d560e94cd9) after runs with one and with two test threads gave
/// the same new digests.
const REFERENCE_DIGEST_V1: u64 = 0xe1f226c798b5b285;
/// FNV-1a over every byte of every v2 frame of the same replay (precomputed mode).
const REFERENCE_DIGEST_V2: u64 = 0x77c48fba36fe987b;

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

/// A lung drawn outside the volume range its kernel was checked free of folds carries
/// `PAST_FOLD_FREE` in exactly those frames (the HUD and the run's report say so); the range comes
/// from the kernel's metadata, and a lung within its range is never marked.
#[test]
fn frames_drawing_a_lung_past_its_fold_free_range_say_so() {
    let files: Vec<KernelFile> = kernels_of(0, lung_model::deform::DirectionPreset::default())
        .iter()
        .map(|p| KernelFile::open_lazy(p).unwrap())
        .collect();
    let mut geometry: Vec<LungGeometry> = files
        .iter()
        .map(|k| {
            let g = LungGeometry::from_kernel(
                k,
                DeformMode::Precomputed,
                OrientationMethod::Exact,
                lung_model::orientation::DEFAULT_MIN_SLOPE_RATIO,
            )
            .unwrap();
            let measured = k.meta().fold_free.expect("the bake measures the range");
            assert_eq!(g.fold_free, Some(measured));
            assert!(measured.above_ml > 0.0 && measured.below_ml > 0.0);
            g
        })
        .collect();
    // The right lung's range made narrower than its breath: above +60 ml or below −5 ml is past it.
    let narrow = lung_model::kernel::FoldFreeMeta {
        above_ml: 60.0,
        below_ml: 5.0,
        searched_above_ml: 60.0,
        searched_below_ml: 5.0,
    };
    geometry[0].fold_free = Some(narrow);
    let start = geometry[0].start_volume_ml;
    let mut core = EngineCore::with_geometry(&Scene::default(), geometry).unwrap();
    let mut f = EngineFrame::default();
    let (mut past, mut within) = (0, 0);
    for tick in 0..600 {
        core.step(tick, None, &mut f);
        let r = &f.lungs[LUNG_RIGHT];
        let delta = r.volume_ml as f64 - start;
        let flagged = r.flags & lung_flags::PAST_FOLD_FREE != 0;
        assert_eq!(
            flagged,
            !narrow.contains(delta),
            "tick {tick}: {delta:+.1} ml"
        );
        if flagged {
            past += 1;
        } else {
            within += 1;
        }
        assert_eq!(
            f.lungs[LUNG_LEFT].flags & lung_flags::PAST_FOLD_FREE,
            0,
            "tick {tick}: the left lung breathes within its measured range"
        );
    }
    assert!(
        past > 100 && within > 100,
        "{past} frames past, {within} within"
    );
    // Below the start volume too (a lung held 20 ml under it is past the −5 ml, 3 ml under is not).
    for (tick, under, past) in [(600, 20.0, true), (601, 3.0, false)] {
        core.lung_mut(Side::Right)
            .unwrap()
            .hold(Some(start - under));
        core.step(tick, None, &mut f);
        let flags = f.lungs[LUNG_RIGHT].flags;
        assert_ne!(flags & lung_flags::HELD, 0);
        assert_eq!(
            flags & lung_flags::PAST_FOLD_FREE != 0,
            past,
            "{under} ml under"
        );
    }
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

/// Both default lungs at 1000 vertices baked with `bands` SH bands into kernel files (the engine
/// reads the orientation data from a kernel's metadata), once per process.
/// Both generated lungs at 1000 vertices with `bands` SH bands and the motion of `preset`, baked
/// once per test process.
fn kernels_of(bands: u32, preset: lung_model::deform::DirectionPreset) -> Vec<std::path::PathBuf> {
    let dir = std::env::temp_dir().join(format!(
        "lungdyn-engine-{}-{bands}-{}",
        std::process::id(),
        preset.name()
    ));
    std::fs::create_dir_all(&dir).unwrap();
    [Side::Right, Side::Left]
        .into_iter()
        .map(|side| {
            let path = dir.join(format!("{}.kernel", side.name()));
            if !path.exists() {
                let mut s = lung_bake::kernel::BakeSettings::for_preset(preset, side);
                s.sh_bands = bands;
                lung_bake::kernel::bake(side, generate::lung(side, 1000).unwrap(), &s, &|_| {})
                    .unwrap()
                    .write(&path)
                    .unwrap();
            }
            path
        })
        .collect()
}

fn core_in(mode: DeformMode, method: OrientationMethod) -> (EngineCore, Vec<KernelFile>) {
    core_of(mode, method, lung_model::deform::DirectionPreset::default())
}

/// [`core_in`] with kernels of `preset`'s motion.
fn core_of(
    mode: DeformMode,
    method: OrientationMethod,
    preset: lung_model::deform::DirectionPreset,
) -> (EngineCore, Vec<KernelFile>) {
    let files: Vec<KernelFile> = kernels_of(4, preset)
        .iter()
        .map(|p| KernelFile::open_lazy(p).unwrap())
        .collect();
    let geometry = files
        .iter()
        .map(|k| {
            LungGeometry::from_kernel(
                k,
                mode,
                method,
                lung_model::orientation::DEFAULT_MIN_SLOPE_RATIO,
            )
            .unwrap()
        })
        .collect();
    let mut scene = Scene::default();
    scene.lungs.mode = mode;
    scene.engine.orientation = method;
    (EngineCore::with_geometry(&scene, geometry).unwrap(), files)
}

/// A tracker frame whose patient reference has rotation `q` (body → room).
fn posed(n: u64, q: glam::DQuat) -> TrackerFrame {
    let mut f = frame(n, true);
    f.tools[TOOL_PATIENT].pose.quat = q.to_array().map(|v| v as f32);
    f
}

/// Supine in the synthetic tracker's room (+Z up): body X → room Y, Y → Z, Z → X.
fn supine() -> glam::DQuat {
    glam::DQuat::from_mat3(&glam::DMat3::from_cols(
        glam::DVec3::Y,
        glam::DVec3::Z,
        glam::DVec3::X,
    ))
}

/// Turns of the supine patient: supine, rolled 90° onto each side, pitched ±90° (sitting up, head
/// down), prone, and a gimbal-lock-like compound turn.
fn patient_turns() -> [glam::DQuat; 7] {
    [
        glam::DQuat::IDENTITY,
        glam::DQuat::from_rotation_x(std::f64::consts::FRAC_PI_2),
        glam::DQuat::from_rotation_x(-std::f64::consts::FRAC_PI_2),
        glam::DQuat::from_rotation_y(std::f64::consts::FRAC_PI_2),
        glam::DQuat::from_rotation_y(-std::f64::consts::FRAC_PI_2),
        glam::DQuat::from_rotation_x(std::f64::consts::PI),
        glam::DQuat::from_euler(glam::EulerRot::XYZ, 0.4, std::f64::consts::FRAC_PI_2, -1.2),
    ]
}

/// Folded surfaces in every orientation-following mode for each volume change in `wholes` (ml of
/// both lungs, each lung its share), at the engine's own coefficients for every turn of
/// [`patient_turns`] (supine, lying on either side, pitched 90°, prone, a compound turn): neither
/// lung's drawn surface intersects itself (the exact test of `lung_bake::surface_checks`). The
/// precomputed field is held to the same range at 10k vertices by `lung_bake`'s
/// `the_default_lungs_do_not_fold_over_the_whole_range`, and the basis field in every posture of the
/// bake's orientation set by `the_default_lungs_do_not_fold_in_any_posture`; these kernels are the
/// default bake at 1000 vertices with 4 SH bands (the SH mode's own approximation included).
fn folds_in_every_following_mode(wholes: &[f64]) -> Vec<String> {
    use lung_model::deform::modes::CpuLung;
    let mut folds = Vec::new();
    for mode in [DeformMode::Basis, DeformMode::Sh, DeformMode::Direct] {
        let (mut core, files) = core_in(mode, OrientationMethod::Exact);
        let mut lungs: Vec<CpuLung> = files
            .iter()
            .map(|k| CpuLung::from_kernel(k, mode).unwrap())
            .collect();
        let volume_of = |cpu: &CpuLung, positions: &[[f32; 3]]| {
            lung_model::mesh::TriMesh {
                positions: positions.to_vec(),
                triangles: cpu.triangles.clone(),
            }
            .enclosed_volume_ml()
        };
        let starts: Vec<f64> = lungs.iter().map(|c| volume_of(c, &c.positions)).collect();
        let total: f64 = starts.iter().sum();
        let turns = patient_turns();
        let mut f = EngineFrame::default();
        for (k, turn) in turns.iter().enumerate() {
            let tick = 150 + 300 * k as u64;
            core.step(tick, Some(&posed(tick, *turn * supine())), &mut f);
            for (i, ((lung, cpu), start)) in f.lungs.iter().zip(&mut lungs).zip(&starts).enumerate()
            {
                let side = ["right", "left"][i];
                let coeffs = lung.coeffs[..lung.coeff_count as usize].to_vec();
                let mut out = vec![[0.0f32; 3]; cpu.len()];
                for &whole in wholes {
                    let target = start + whole * start / total;
                    // The scale that makes the drawn surface enclose the target: walk out from 0
                    // in small steps until the volume passes it (monotonic near 0; far beyond, a
                    // surface turned inside out would enclose a large volume again), then bisect.
                    let dir = whole.signum() as f32;
                    let step = lung.deform_scale.abs().max(1.0) * 0.05;
                    let mut at = |s: f32, out: &mut Vec<[f32; 3]>| {
                        cpu.deform_into(s, &coeffs, [0.0; 3], out).unwrap();
                        volume_of(cpu, out)
                    };
                    let mut reach = 0.0f32;
                    for _ in 0..2000 {
                        if (at(reach, &mut out) - target) * whole >= 0.0 {
                            break;
                        }
                        reach += dir * step;
                    }
                    let (mut lo, mut hi) = (reach - dir * step, reach);
                    for _ in 0..40 {
                        let mid = 0.5 * (lo + hi);
                        if (at(mid, &mut out) - target) * whole >= 0.0 {
                            hi = mid;
                        } else {
                            lo = mid;
                        }
                    }
                    let v = at(hi, &mut out);
                    assert!(
                        (v - target).abs() < 1.0,
                        "{mode} turn {k}: reached {v:.1} of {target:.1} ml"
                    );
                    let m = lung_model::mesh::TriMesh {
                        positions: out.clone(),
                        triangles: cpu.triangles.clone(),
                    };
                    let si = lung_bake::surface_checks::self_intersections(&m, 64);
                    if si.count > 0 {
                        folds.push(format!(
                            "{mode} turn {k}, {side} lung, at {whole:+} ml of both lungs ({v:.0} ml): {} crossing pairs",
                            si.count
                        ));
                    }
                }
            }
        }
    }
    folds
}

/// Fails listing every folded surface of [`folds_in_every_following_mode`].
fn assert_no_folds(wholes: &[f64]) {
    let folds = folds_in_every_following_mode(wholes);
    assert!(
        folds.is_empty(),
        "{} folded surfaces:\n{}",
        folds.len(),
        folds.join("\n")
    );
}

/// The normal range, FRC − 500 to FRC + 500 ml of both lungs: no mode folds either lung in any of
/// the postures.
#[test]
fn no_mode_folds_the_surface_from_frc_minus_500_to_plus_500_ml_in_any_posture() {
    assert_no_folds(&[-500.0, 500.0]);
}

/// Issue 19's whole range, to FRC + 1500 ml, in every mode and every turn. With the orientation
/// limit at lungdyn's earlier ratio 0.5 the turned postures folded from between +500 and +1000 ml
/// (left lung on its side: 5 crossing pairs at +1000, 52 at +1500 ml; basis and direct identical,
/// SH a little worse; prone 11–17 pairs from +1000 ml): the turned force put the breath where the
/// supine directions run along or into the surface, the volume slope fell to about half the supine
/// one and the breath moved the surface up to 2.8× as far (EQUATIONS.md §3.3). At the default
/// ratio 0.8 none folds.
#[test]
fn no_mode_folds_the_surface_from_frc_minus_500_to_plus_1500_ml() {
    assert_no_folds(&[-500.0, 500.0, 1000.0, 1500.0]);
}

#[test]
fn turning_the_patient_changes_the_breath_but_never_its_volume() {
    use lung_model::deform::modes::CpuLung;
    for mode in [DeformMode::Basis, DeformMode::Sh, DeformMode::Direct] {
        let (mut core, files) = core_in(mode, OrientationMethod::Exact);
        let mut lungs: Vec<CpuLung> = files
            .iter()
            .map(|k| CpuLung::from_kernel(k, mode).unwrap())
            .collect();
        let turns = patient_turns();
        let mut shapes = Vec::new();
        let mut f = EngineFrame::default();
        for (k, turn) in turns.iter().enumerate() {
            // Tick 150: end of inspiration of the 300-tick cycle.
            let tick = 150 + 300 * k as u64;
            core.step(tick, Some(&posed(tick, *turn * supine())), &mut f);
            assert_eq!(f.state & engine_state::POSE_INVALID, 0);
            for (lung, cpu) in f.lungs.iter().zip(&mut lungs) {
                assert_eq!(lung.coeff_kind, mode.coeff_kind());
                assert!(lung.deform_scale.is_finite() && lung.volume_ml.is_finite());
                let coeffs = &lung.coeffs[..lung.coeff_count as usize];
                assert!(coeffs.iter().all(|c| c.is_finite()));
                let mut out = vec![[0.0f32; 3]; cpu.len()];
                cpu.deform_into(lung.deform_scale, coeffs, [0.0; 3], &mut out)
                    .unwrap();
                let v = lung_model::mesh::TriMesh {
                    positions: out.clone(),
                    triangles: cpu.triangles.clone(),
                }
                .enclosed_volume_ml();
                // The mode's own volume forms make the drawn mesh enclose the PV volume.
                assert!(
                    (v - lung.volume_ml as f64).abs() < 0.05,
                    "{mode} turn {k}: drawn {v} ml, PV {} ml",
                    lung.volume_ml
                );
                shapes.push(out);
            }
        }
        // The breath's shape differs between supine and a turned patient (same volume).
        let n = lungs[0].len();
        let moved = |a: &Vec<[f32; 3]>, b: &Vec<[f32; 3]>| {
            a.iter()
                .zip(b)
                .map(|(p, q)| glam::Vec3::from(*p).distance(glam::Vec3::from(*q)))
                .fold(0.0f32, f32::max)
        };
        assert_eq!(shapes[0].len(), n);
        assert!(
            moved(&shapes[0], &shapes[2]) > 1.0,
            "{mode}: turning changed nothing"
        );
    }
}

#[test]
fn a_pose_that_is_not_a_rotation_is_refused_and_the_last_gravity_kept() {
    let (mut core, _files) = core_in(DeformMode::Basis, OrientationMethod::Exact);
    let mut f = EngineFrame::default();
    core.step(0, Some(&posed(0, supine())), &mut f);
    let good = f;
    for (k, quat) in [
        [0.0, 0.0, 0.0, 0.0],
        [0.0, 0.0, 0.0, 3.0],
        [1.0, 1.0, 1.0, 1.0],
    ]
    .into_iter()
    .enumerate()
    {
        let tick = 300 * (k as u64 + 1);
        let mut bad = frame(tick, true);
        bad.tools[TOOL_PATIENT].pose.quat = quat;
        core.step(tick, Some(&bad), &mut f);
        assert_ne!(f.state & engine_state::POSE_INVALID, 0, "{quat:?}");
        assert_ne!(f.state & engine_state::PATIENT_POSE_HELD, 0);
        assert_eq!(f.patient_pose, good.patient_pose);
        // Same phase, same gravity: the same coefficients and scale as the good frame.
        assert_eq!(f.lungs[LUNG_LEFT].coeffs, good.lungs[LUNG_LEFT].coeffs);
        assert_eq!(
            f.lungs[LUNG_LEFT].deform_scale,
            good.lungs[LUNG_LEFT].deform_scale
        );
    }
    core.step(1200, Some(&posed(1200, supine())), &mut f);
    assert_eq!(f.state & engine_state::POSE_INVALID, 0);
}

#[test]
fn every_orientation_method_stays_finite_at_the_extremes_and_replays_bitwise() {
    for method in [
        OrientationMethod::Exact,
        OrientationMethod::Seed,
        OrientationMethod::Fixed,
    ] {
        for mode in [DeformMode::Basis, DeformMode::Sh] {
            let run = || {
                let (mut core, _files) = core_in(mode, method);
                let mut out = Vec::new();
                let mut f = EngineFrame::default();
                // A slow tumble through every orientation, including exactly ±90° pitch.
                for tick in 0..720u64 {
                    let a = tick as f64 * std::f64::consts::TAU / 360.0;
                    let q = glam::DQuat::from_euler(
                        glam::EulerRot::XYZ,
                        a,
                        (a * 0.5).sin() * std::f64::consts::FRAC_PI_2,
                        0.3 * a,
                    );
                    core.step(tick, Some(&posed(tick, q * supine())), &mut f);
                    for l in &f.lungs {
                        assert!(
                            l.deform_scale.is_finite() && l.coeffs.iter().all(|c| c.is_finite())
                        );
                        assert!(
                            l.deform_scale.abs() < 1e4,
                            "{method:?} {mode}: scale {}",
                            l.deform_scale
                        );
                    }
                    out.push(f);
                }
                out
            };
            let (a, b) = (run(), run());
            for (x, y) in a.iter().zip(&b) {
                assert_eq!(bytemuck::bytes_of(x), bytemuck::bytes_of(y));
            }
            if method == OrientationMethod::Fixed {
                // Fixed: the coefficients never move.
                assert!(a
                    .windows(2)
                    .all(|w| w[0].lungs[LUNG_LEFT].coeffs == w[1].lungs[LUNG_LEFT].coeffs));
            }
        }
    }
}

/// A scene with a `[disease]` table over the two baked test lungs (their meshes for the hilum).
fn disease_core(disease: &str) -> EngineCore {
    diseased_core(&format!(
        "[lungs]\nsides = [\"right\", \"left\"]\n[disease]\n{disease}"
    ))
}

/// The scene `text` over the two baked test lungs with its disease state started.
fn diseased_core(text: &str) -> EngineCore {
    let scene = Scene::parse(text, "test").unwrap();
    let meshes: Vec<_> = [Side::Right, Side::Left]
        .into_iter()
        .map(|side| generate::lung(side, 1000).unwrap())
        .collect();
    let mut core = EngineCore::with_geometry(&scene, baked_geometry()).unwrap();
    core.start_disease(&scene, &meshes).unwrap();
    core
}

#[test]
fn a_closed_pneumothorax_collapses_the_affected_lung_by_eq_8_1_and_drops_it_by_eq_8_2() {
    let mut c = disease_core("kind = \"closed-pneumothorax\"\nside = \"left\"\nindex = 0.1\n");
    let healthy = core();
    let start = healthy
        .geometry()
        .map(|g| g.start_volume_ml)
        .collect::<Vec<_>>();
    let mut f = EngineFrame::default();
    let mut min_left = f32::MAX;
    for tick in 0..600 {
        c.step(tick, None, &mut f);
        let l = &f.lungs[LUNG_LEFT];
        let r = &f.lungs[LUNG_RIGHT];
        assert!(l.volume_ml.is_finite() && l.deform_scale.is_finite() && l.deform_scale >= 0.0);
        // eq. 8.1: dV = 0.1^0.33 of the left lung's volume is lost: c = 1 − (1 − dV)^(1/3).
        let dv = 0.1f64.powf(0.33);
        let expect_c = 1.0 - (1.0 - dv).cbrt();
        assert!(
            (l.collapse as f64 - expect_c).abs() < 1e-6,
            "{}",
            l.collapse
        );
        assert!(l.hilum_mm.iter().all(|v| v.is_finite()) && l.hilum_mm != [0.0; 3]);
        // eq. 8.2: A = (100·0.1 − 4.2)/(4.7·2) cm = 6.17 mm downwards.
        assert!((l.offset_mm[2] + 6.170).abs() < 0.01, "{:?}", l.offset_mm);
        assert_eq!(r.collapse, 0.0);
        min_left = min_left.min(l.volume_ml);
    }
    // The collapsed lung breathes from (1 − dV) of its volume.
    let dv = 0.1f64.powf(0.33);
    let base = start[1] * (1.0 - dv);
    assert!((min_left as f64 - base).abs() < 0.5, "{min_left} vs {base}");
}

/// Step `c` over `ticks` as the process loop does (the tick, then the next cycle prepared), with
/// live actions at their ticks; returns every frame's FNV digest and whether the left lung was
/// ever held (arrest).
fn run_disease(
    c: &mut EngineCore,
    ticks: u64,
    actions: &[(u64, lung_model::disease::tension::Intervention)],
) -> (Vec<u64>, bool, f32, f32) {
    let mut f = EngineFrame::default();
    let (mut digests, mut held, mut max_c, mut last_c) = (Vec::new(), false, 0.0f32, 0.0f32);
    for tick in 0..ticks {
        let input = (tick % 3 != 0).then(|| frame(tick, true));
        c.step(tick, input.as_ref(), &mut f);
        for l in &f.lungs {
            assert!(
                l.volume_ml.is_finite() && l.deform_scale.is_finite(),
                "tick {tick}"
            );
            assert!((0.0..=1.0).contains(&l.collapse), "tick {tick}");
        }
        held |= f.lungs[LUNG_LEFT].flags & lung_flags::HELD != 0;
        last_c = f.lungs[LUNG_LEFT].collapse;
        max_c = max_c.max(last_c);
        digests.push(fnv(bytemuck::bytes_of(&f).iter().map(|&b| b as u64)));
        for &(at, kind) in actions {
            if at == tick {
                assert_eq!(c.intervene(tick, kind, Side::Left), LiveAction::Queued);
            }
        }
        c.prepare_ahead().unwrap();
    }
    (digests, held, max_c, last_c)
}

#[test]
fn a_tension_pneumothorax_runs_to_arrest_and_a_needle_stops_it() {
    use lung_model::disease::tension::Intervention;
    let untreated = "kind = \"tension-pneumothorax\"\nside = \"left\"\n";
    // Untreated: the course ends in arrest (both lungs held) within the hour.
    let mut c = disease_core(untreated);
    let (_, held, _, _) = run_disease(&mut c, 216_000, &[]);
    assert!(
        held,
        "the untreated course ends with the lungs held (arrest)"
    );
    let Some(disease::DiseaseRun::Tension(run)) = c.disease() else {
        panic!("tension")
    };
    assert!(run.first_arrest.is_some());
    // A timed needle decompression under tension (a faster leak, 40 ml a cycle: the shift is near
    // β at 80 s; EQUATIONS §4.6): no arrest, and the left lung re-expands as the tension vents.
    let fast = "kind = \"tension-pneumothorax\"\nside = \"left\"\nv_p_ml = 40.0\n";
    let needle =
        "[[disease.events]]\nat_s = 80.0\nkind = \"needle-decompression\"\nside = \"left\"\n";
    let mut c = disease_core(&format!("{fast}{needle}"));
    let (b, held, max_c, last_c) = run_disease(&mut c, 12_000, &[]);
    assert!(!held);
    assert!(max_c > 0.0 && last_c < 0.9 * max_c, "{max_c} {last_c}");
    let Some(disease::DiseaseRun::Tension(run)) = c.disease() else {
        panic!("tension")
    };
    assert_eq!(run.events.len(), 1);
    assert_eq!(run.events[0].tick, 4800);
    assert!(run.first_arrest.is_none());
    // Without the needle the same course arrests within the run.
    let (_, held, _, _) = run_disease(&mut disease_core(fast), 12_000, &[]);
    assert!(held);
    // The same needle as a trainee's live action at tick 4800: the same frames bit for bit (both
    // are applied when the cycle after their arrival is prepared).
    let mut live = disease_core(fast);
    let (a, ..) = run_disease(
        &mut live,
        12_000,
        &[(4800, Intervention::NeedleDecompression)],
    );
    assert_eq!(a, b);
}

#[test]
fn a_disease_run_replays_bitwise() {
    use lung_model::disease::tension::Intervention;
    let scene = "kind = \"tension-pneumothorax\"\nside = \"left\"\n[[disease.events]]\nat_s = 40.0\nkind = \"chest-tube\"\nside = \"left\"\n";
    let actions = [(2500, Intervention::NeedleDecompression)];
    let (a, ..) = run_disease(&mut disease_core(scene), 20_000, &actions);
    let (b, ..) = run_disease(&mut disease_core(scene), 20_000, &actions);
    assert_eq!(a, b);
}

#[test]
fn live_actions_without_a_tension_pneumothorax_are_refused() {
    use lung_model::disease::tension::Intervention;
    let mut c = core();
    assert_eq!(
        c.intervene(10, Intervention::ChestTube, Side::Left),
        LiveAction::NoTension
    );
    let mut c = disease_core("kind = \"tension-pneumothorax\"\nside = \"left\"\n");
    for k in 0..disease::MAX_QUEUED_ACTIONS {
        assert_eq!(
            c.intervene(k as u64, Intervention::ChestTube, Side::Left),
            LiveAction::Queued
        );
    }
    assert_eq!(
        c.intervene(99, Intervention::ChestTube, Side::Left),
        LiveAction::QueueFull
    );
}

#[test]
fn a_tumour_raises_the_affected_lungs_resistance_and_leaves_the_other_lung_alone() {
    // A large tumour (60 mm radii, 905 ml) so eq. 8.9's x = φ·min(1, V_t/V_lung) is not tiny.
    let scene = "kind = \"tumour\"\nside = \"right\"\n[disease.tumour]\ncentre = [0.5, 0.5, 0.5]\nradii_mm = [60.0, 60.0, 60.0]\n";
    let mut c = disease_core(scene);
    let Some(disease::DiseaseRun::Tumour(run)) = c.disease() else {
        panic!("not a tumour run");
    };
    assert_eq!(run.side, Side::Right);
    assert!(run.resistance.iter().all(|r| r.x > 0.01 && !r.identity));
    let mut healthy = core();
    let (mut f, mut g) = (EngineFrame::default(), EngineFrame::default());
    let (mut differs, mut range_t, mut range_h) = (
        false,
        (f32::INFINITY, f32::NEG_INFINITY),
        (f32::INFINITY, f32::NEG_INFINITY),
    );
    let ticks = 60 * 60; // one simulated minute
    for tick in 0..ticks {
        let input = frame(tick, true);
        c.step(tick, Some(&input), &mut f);
        healthy.step(tick, Some(&input), &mut g);
        // The other lung breathes exactly as in a healthy patient.
        assert_eq!(
            bytemuck::bytes_of(&f.lungs[LUNG_LEFT]),
            bytemuck::bytes_of(&g.lungs[LUNG_LEFT]),
            "tick {tick}"
        );
        let (t, h) = (f.lungs[LUNG_RIGHT], g.lungs[LUNG_RIGHT]);
        assert!(t.volume_ml.is_finite() && t.deform_scale.is_finite());
        assert_eq!(t.cycle, h.cycle, "the rate is unchanged (tick {tick})");
        differs |= t.volume_ml != h.volume_ml;
        range_t = (range_t.0.min(t.volume_ml), range_t.1.max(t.volume_ml));
        range_h = (range_h.0.min(h.volume_ml), range_h.1.max(h.volume_ml));
        c.prepare_ahead().unwrap();
    }
    // The raised resistance reshapes the breath within the cycle; the PV boundary values (FRC and
    // tidal volume) still bound it.
    assert!(differs, "the resistance changed nothing");
    assert!(
        (range_t.0 - range_h.0).abs() < 1.0,
        "{range_t:?} {range_h:?}"
    );
    assert!(
        (range_t.1 - range_h.1).abs() < 1.0,
        "{range_t:?} {range_h:?}"
    );
    // And the run replays bit for bit.
    let (a, ..) = run_disease(&mut disease_core(scene), 5_000, &[]);
    let (b, ..) = run_disease(&mut disease_core(scene), 5_000, &[]);
    assert_eq!(a, b);
}

#[test]
fn every_live_action_is_answered_once_received_then_applied_in_order_or_ignored_or_refused() {
    use ipc_types::{
        ControlPacket, ControlReply, Intervention, OUTCOME_APPLIED, OUTCOME_NO_EFFECT,
        REPLY_APPLIED, REPLY_IGNORED, REPLY_RECEIVED, REPLY_REFUSED,
    };
    use process::{run_loop, ActionCounts, Controls};
    use transport::memory::{Recorder, Scripted};
    use transport::pacer::PacerConfig;
    use transport::{Clock, FakeClock};
    const P: u64 = 16_666_667;
    let packet = |kind: u32, lung: u32, sequence: u64| ControlPacket {
        layout_version: LAYOUT_VERSION,
        kind,
        lung,
        _pad: 0,
        sequence,
        origin: ipc_types::ORIGIN_LOCAL,
    };
    let needle = Intervention::NeedleDecompression.code();
    let dressing = Intervention::OcclusiveDressing.code();
    // All in one tick: a needle (and the same packet again), an unknown kind, then dressings on
    // "the affected side" until the queue overflows by one.
    let mut arrivals = vec![
        (10 * P, packet(needle, LUNG_LEFT as u32, 1)),
        (10 * P, packet(needle, LUNG_LEFT as u32, 1)),
        (10 * P, packet(99, LUNG_LEFT as u32, 2)),
    ];
    for k in 0..disease::MAX_QUEUED_ACTIONS as u64 {
        arrivals.push((10 * P, packet(dressing, ipc_types::LUNG_AFFECTED, 100 + k)));
    }
    let clock = FakeClock::at(0);
    let mut inlet = Scripted::new(&clock, arrivals, 256);
    let mut replies = Recorder::<ControlReply>::new(&clock);
    let record = replies.clone();
    let mut tracker = Scripted::<TrackerFrame>::new(&clock, vec![], 4);
    let mut frames = Recorder::new(&clock);
    let c = clock.clone();
    let stats = run_loop(
        &mut disease_core("kind = \"tension-pneumothorax\"\nside = \"left\"\n"),
        &mut tracker,
        &mut frames,
        Some(Controls {
            inlet: &mut inlet,
            replies: &mut replies,
            state: None,
        }),
        &clock,
        PacerConfig::for_period(P),
        &mut || c.now_ns() >= 1200 * P,
        None,
        0,
    )
    .unwrap();
    let n = disease::MAX_QUEUED_ACTIONS as u64;
    assert_eq!(
        stats.actions,
        ActionCounts {
            received: n,
            applied: n,
            ignored: 1,
            refused: 1,
            repeated: 1,
        }
    );
    let r = record.values();
    let with =
        |status: u32| -> Vec<&ControlReply> { r.iter().filter(|x| x.status == status).collect() };
    let received: Vec<u64> = with(REPLY_RECEIVED).iter().map(|x| x.sequence).collect();
    let applied: Vec<u64> = with(REPLY_APPLIED).iter().map(|x| x.sequence).collect();
    // Each queued action answered twice, applied in the order it was received.
    let expected: Vec<u64> = std::iter::once(1).chain(100..100 + n - 1).collect();
    assert_eq!(received, expected);
    assert_eq!(applied, expected);
    let first = with(REPLY_APPLIED)[0];
    assert_eq!(
        (first.outcome, first.lung),
        (OUTCOME_APPLIED, LUNG_LEFT as u32)
    );
    // The tick after the packets' arrival at 10 periods (the first deadline tick is at 1.25).
    assert!((8..=10).contains(&first.tick), "{}", first.tick);
    assert_eq!(first.text(), "air venting");
    assert!(first.cycle >= 1);
    // The dressing went to the affected (left) side and did nothing to a leak from the lung.
    let d = with(REPLY_APPLIED)[1];
    assert_eq!((d.outcome, d.lung), (OUTCOME_NO_EFFECT, LUNG_LEFT as u32));
    assert!(d.text().contains("leaks from the lung"), "{}", d.text());
    let ignored = with(REPLY_IGNORED);
    assert_eq!(ignored.len(), 1);
    assert_eq!(ignored[0].sequence, 2);
    assert!(ignored[0]
        .text()
        .starts_with("ignored: not an intervention"));
    let refused = with(REPLY_REFUSED);
    assert_eq!(refused.len(), 1);
    assert_eq!(refused[0].sequence, 100 + n - 1);
    assert!(refused[0].text().starts_with("refused: "));
    // Nothing else was said.
    assert_eq!(r.len() as u64, 2 * n + 2);
}

#[test]
fn a_live_action_without_a_tension_pneumothorax_is_answered_ignored() {
    use ipc_types::{ControlPacket, ControlReply, Intervention, REPLY_IGNORED};
    use process::{run_loop, Controls};
    use transport::memory::{Recorder, Scripted};
    use transport::pacer::PacerConfig;
    use transport::{Clock, FakeClock};
    const P: u64 = 16_666_667;
    let clock = FakeClock::at(0);
    let p = ControlPacket {
        layout_version: LAYOUT_VERSION,
        kind: Intervention::ChestTube.code(),
        lung: ipc_types::LUNG_AFFECTED,
        _pad: 0,
        sequence: 7,
        origin: ipc_types::ORIGIN_LOCAL,
    };
    let mut inlet = Scripted::new(&clock, vec![(3 * P, p)], 8);
    let mut replies = Recorder::<ControlReply>::new(&clock);
    let record = replies.clone();
    let mut tracker = Scripted::<TrackerFrame>::new(&clock, vec![], 4);
    let mut frames = Recorder::new(&clock);
    let c = clock.clone();
    run_loop(
        &mut core(),
        &mut tracker,
        &mut frames,
        Some(Controls {
            inlet: &mut inlet,
            replies: &mut replies,
            state: None,
        }),
        &clock,
        PacerConfig::for_period(P),
        &mut || c.now_ns() >= 10 * P,
        None,
        0,
    )
    .unwrap();
    let r = record.values();
    assert_eq!(r.len(), 1);
    assert_eq!((r[0].status, r[0].sequence), (REPLY_IGNORED, 7));
    assert!(r[0]
        .text()
        .starts_with("ignored: the scene has no tension pneumothorax"));
}

/// The shipped waveform scene (a synthetic PB-840 recording: 500 ml at 15 breaths/min).
fn waveform_scene() -> Scene {
    let path = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scenes/ventilated_recording.toml");
    Scene::load(&path).unwrap()
}

#[test]
fn a_waveform_scene_breathes_the_recording_without_a_pv_model() {
    let scene = waveform_scene();
    let w = scene.pv_waveform().unwrap().expect("a waveform scene");
    let mut core = EngineCore::with_geometry(&scene, baked_geometry()).unwrap();
    assert_eq!(core.stage_counts().pv_models_built, 0, "no PV model built");
    assert_eq!(
        EngineCore::with_geometry(&Scene::default(), baked_geometry())
            .unwrap()
            .stage_counts()
            .pv_models_built,
        1
    );
    // Both lungs' volumes over four cycles: the summed swing is the recorded tidal volume and the
    // period the recorded rate, each within 2 %.
    let hz = scene.engine.tick_hz;
    let mut total = Vec::new();
    for tick in 0..(4.0 * hz * 60.0 / 15.0) as u64 {
        let mut f = EngineFrame::default();
        core.step(tick, Some(&frame(tick, true)), &mut f);
        total.push(f.lungs.iter().map(|l| l.volume_ml as f64).sum::<f64>());
        assert!(f.lungs.iter().all(|l| l.volume_ml.is_finite()));
    }
    let (lo, hi) = total
        .iter()
        .fold((f64::MAX, f64::MIN), |(l, h), &v| (l.min(v), h.max(v)));
    assert!(
        ((hi - lo) / 500.0 - 1.0).abs() < 0.02,
        "tidal volume {} ml against the recorded 500 ml (waveform mean {} ml)",
        hi - lo,
        w.tidal_volume_ml
    );
    // Period: ticks between successive starts of inspiration (the minima).
    let starts: Vec<usize> = (1..total.len() - 1)
        .filter(|&i| total[i] <= total[i - 1] && total[i] < total[i + 1] && total[i] < lo + 1.0)
        .collect();
    assert!(starts.len() >= 3, "{starts:?}");
    let period = (starts[starts.len() - 1] - starts[0]) as f64 / (starts.len() - 1) as f64;
    let rate = 60.0 * hz / period;
    assert!((rate / 15.0 - 1.0).abs() < 0.02, "rate {rate}/min");
    // Seamless: the step across the loop point is no larger than the largest step within a cycle.
    let steps: Vec<f64> = total.windows(2).map(|p| (p[1] - p[0]).abs()).collect();
    let cycle = (hz * 60.0 / w.rate_per_min).round() as usize;
    let within = steps[1..cycle - 1].iter().copied().fold(0.0, f64::max);
    assert!(
        steps[cycle - 1] <= within,
        "{} > {within}",
        steps[cycle - 1]
    );
}

#[test]
fn a_waveform_scene_replays_bitwise_identically() {
    let scene = waveform_scene();
    let a = replay(&mut EngineCore::with_geometry(&scene, baked_geometry()).unwrap());
    let b = replay(&mut EngineCore::with_geometry(&scene, baked_geometry()).unwrap());
    for (x, y) in a.iter().zip(&b) {
        assert_eq!(
            bytemuck::bytes_of(x),
            bytemuck::bytes_of(y),
            "tick {}",
            x.tick
        );
    }
}

/// The frames of ticks `from..to` of `core` stepped without tracker input (after `resume_at(from)`
/// when `resume`), as bytes.
fn frames_from(mut core: EngineCore, from: u64, to: u64, resume: bool) -> Vec<Vec<u8>> {
    let mut f = EngineFrame::default();
    let start = if resume {
        core.resume_at(from).unwrap();
        from
    } else {
        0
    };
    let mut out = Vec::new();
    for tick in start..to {
        core.step(tick, None, &mut f);
        core.prepare_ahead().unwrap();
        if tick >= from {
            out.push(bytemuck::bytes_of(&f).to_vec());
        }
    }
    out
}

/// A restarted engine resumes where the stream expects: its frames from the resume tick on are
/// those of an uninterrupted run, bit for bit (phase, cycle, volumes, scales), healthy or diseased,
/// mid-breath or on a cycle boundary.
#[test]
fn an_engine_resumed_at_a_tick_equals_an_uninterrupted_run_from_there() {
    for from in [0, 1, 137, 300, 301, 4321] {
        let a = frames_from(core(), from, from + 400, false);
        let b = frames_from(core(), from, from + 400, true);
        assert_eq!(a, b, "healthy, resumed at {from}");
    }
    let tension = "kind = \"tension-pneumothorax\"\nside = \"left\"\nonset_s = 2.0\n";
    for from in [0, 250, 1999] {
        let a = frames_from(disease_core(tension), from, from + 700, false);
        let b = frames_from(disease_core(tension), from, from + 700, true);
        assert_eq!(a, b, "tension pneumothorax, resumed at {from}");
    }
    // The check can fail: a fresh core stepped at the tick without the replay differs.
    let a = frames_from(disease_core(tension), 1999, 2100, false);
    let mut fresh = disease_core(tension);
    let mut f = EngineFrame::default();
    fresh.step(1999, None, &mut f);
    assert_ne!(a[0], bytemuck::bytes_of(&f).to_vec(), "the replay matters");
}

/// A frame outlet that takes a millisecond of real time per tick, so the disease worker builds
/// each cycle well inside a breath of the fake clock (as it does at the engine's real rate).
struct Paced(Vec<EngineFrame>);

impl transport::Publish<EngineFrame> for Paced {
    fn publish(&mut self, f: &EngineFrame) -> Result<(), transport::PortError> {
        self.0.push(*f);
        std::thread::sleep(std::time::Duration::from_millis(1));
        Ok(())
    }
}

/// Remote sites (seed §8.3): twelve actions from twelve origins in one tick (plus a repeat) are
/// each announced once — eight in one state, the rest in the next, none dropped — with the tick
/// they show from, ahead of it; a site that gets every state half a second late and puts the
/// announced cycles in at their ticks breathes the source's breath bit for bit, and the same site
/// fed states without the announcement does not.
#[test]
fn actions_are_announced_with_their_tick_ahead_and_a_late_site_applies_them_at_that_tick() {
    use control_state::{decode, Packet};
    use ipc_types::{ControlPacket, ControlReply, Intervention};
    use transport::memory::{Recorder, Scripted};
    use transport::FakeClock;
    const P: u64 = 16_666_667;
    const DELAY: u64 = 30;
    let tension = "kind = \"tension-pneumothorax\"\nside = \"left\"\n";
    let packet = |origin: u64| ControlPacket {
        layout_version: LAYOUT_VERSION,
        kind: Intervention::NeedleDecompression.code(),
        lung: ipc_types::LUNG_AFFECTED,
        _pad: 0,
        sequence: 1,
        origin,
    };
    let mut arrivals: Vec<_> = (1..=12u64).map(|o| (400 * P, packet(o))).collect();
    arrivals.push((400 * P, packet(3)));
    let clock = FakeClock::at(0);
    let mut inlet = Scripted::new(&clock, arrivals, 256);
    let mut replies = Recorder::<ControlReply>::new(&clock);
    let mut frames = Paced(Vec::new());
    let (stats, published) = run_publishing_state(
        &mut disease_core(tension),
        &mut inlet,
        &mut replies,
        &mut frames,
        &clock,
        P,
        77,
        1500 * P,
    );
    assert_eq!(stats.actions.repeated, 1);
    assert_eq!(stats.actions.applied, 12);
    assert_eq!((stats.events_announced, stats.events_unannounced), (12, 0));
    let states: Vec<_> = published
        .values()
        .iter()
        .map(|f| match decode(f.encoded()).unwrap() {
            Packet::State(s) => s,
            p => panic!("{p:?}"),
        })
        .collect();
    // Every action once, with its origin, all showing from one cycle start after their arrival,
    // announced before it.
    let mut events = Vec::new();
    for s in &states {
        for e in s.events.iter() {
            assert!(
                e.apply_tick > s.tick + DELAY,
                "{e:?} announced at {}",
                s.tick
            );
            events.push(*e);
        }
    }
    let mut origins: Vec<u64> = events.iter().map(|e| e.origin).collect();
    origins.sort();
    assert_eq!(origins, (1..=12).collect::<Vec<_>>());
    assert!(events.iter().all(|e| e.apply_tick == events[0].apply_tick
        && e.apply_cycle == events[0].apply_cycle
        && e.sequence == 1));
    let counts: Vec<usize> = states
        .iter()
        .map(|s| s.events.len())
        .filter(|&n| n > 0)
        .collect();
    assert_eq!(counts, vec![8, 4]);
    let start = states
        .iter()
        .find(|s| s.tick == events[0].apply_tick)
        .expect("a state at the cycle start the actions show from");
    assert_eq!(start.cycle, events[0].apply_cycle);
    // Two counts, both named: the engine's applied replies give the disease course's cycle, each
    // announced event carries that same course cycle beside the breathing cycle, and the state
    // that announced the cycle maps the one to the other.
    let applied: Vec<u64> = replies
        .values()
        .iter()
        .filter(|r| r.status == ipc_types::REPLY_APPLIED)
        .map(|r| r.cycle)
        .collect();
    assert_eq!(applied.len(), 12);
    let course = events[0].course_cycle;
    assert!(
        applied.iter().all(|&c| c == course),
        "{applied:?} vs {course}"
    );
    assert!(events.iter().all(|e| e.course_cycle == course));
    let announced = states
        .iter()
        .find_map(|s| {
            s.pending
                .as_ref()
                .filter(|p| p.apply_tick == events[0].apply_tick)
        })
        .expect("the cycle the actions show from was announced");
    assert_eq!(
        (announced.course_cycle, announced.apply_cycle),
        (course, events[0].apply_cycle)
    );
    eprintln!(
        "actions show from disease cycle {course}, breathing cycle {}",
        events[0].apply_cycle
    );
    let ahead = states
        .iter()
        .filter(|s| {
            s.pending
                .as_ref()
                .is_some_and(|p| p.apply_tick > s.tick + DELAY)
        })
        .count();
    assert!(ahead >= 3, "{ahead} cycles announced ahead");
    // A site getting every state DELAY ticks late.
    let site = |announce: bool| -> usize {
        let mut site = disease_core(tension);
        site.follow_remote();
        let mut cache = remote::BreathCache::default();
        let mut f = EngineFrame::default();
        let mut next = 0;
        let mut differing = 0;
        for (tick, source) in frames.0.iter().enumerate().skip(DELAY as usize) {
            let tick = tick as u64;
            while next < states.len() && states[next].tick + DELAY <= tick {
                let mut s = states[next].clone();
                if !announce {
                    s.pending = None;
                }
                site.apply_prepared(remote::Prepared::of(s, &mut cache).unwrap(), 60.0)
                    .unwrap();
                next += 1;
            }
            site.step(tick, None, &mut f);
            if (0..2).any(|k| f.lungs[k].volume_ml.to_bits() != source.lungs[k].volume_ml.to_bits())
            {
                differing += 1;
            }
        }
        differing
    };
    assert_eq!(site(true), 0);
    assert!(site(false) >= 2 * DELAY as usize, "{}", site(false));
}

/// A waveform scene (the shipped synthetic recording) with `disease` over the two baked test lungs.
fn ventilated_core(disease: &str) -> EngineCore {
    recording_core("ventilated_vc_synthetic.csv", "", disease)
}

/// A waveform scene playing `scenes/recordings/<file>` (with more `[pv]` keys `pv`) and `disease`
/// over the two baked test lungs.
fn recording_core(file: &str, pv: &str, disease: &str) -> EngineCore {
    let recording = std::path::Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../scenes/recordings")
        .join(file);
    diseased_core(&format!(
        "[pv]\npreset = \"venegas-human\"\nwaveform = {:?}\n{pv}[lungs]\nsides = [\"right\", \"left\"]\n\
         {disease}",
        recording.display().to_string()
    ))
}

/// EQUATIONS §4.7, pressure control: on the shipped pressure-controlled recording (a passive lung,
/// C = 30 ml/cmH2O, R = 8 cmH2O·s/L, 15 cmH2O above PEEP for 1 s at 20 /min) a pneumothorax lowers
/// the delivered volume with the compliance, where volume control (`waveform_control = "volume"`)
/// delivers the recorded volume; index 0 is the recording bit for bit in both modes.
#[test]
fn a_pressure_controlled_recording_delivers_less_under_a_pneumothorax() {
    const PC: &str = "ventilated_pc_synthetic.csv";
    let cycle = 180; // 20 breaths/min at 60 Hz
    let healthy = ventilated_frames(&mut recording_core(PC, "", ""), 3 * cycle);
    let (healthy_each, healthy_total) = swings(&healthy);
    let closed = |index: f64| {
        format!("[disease]\nkind = \"closed-pneumothorax\"\nside = \"left\"\nindex = {index}\n")
    };
    let volume = "waveform_control = \"volume\"\n";
    for pv in ["", volume] {
        let mut core = recording_core(PC, pv, &closed(0.0));
        assert_same_frames(&healthy, &ventilated_frames(&mut core, 3 * cycle));
        let d = core
            .disease()
            .unwrap()
            .delivery()
            .expect("a ventilated course");
        assert_eq!(d.last.unwrap().fraction, 1.0);
    }
    let mut last = healthy_total;
    for index in [0.1, 0.3, 1.0] {
        let mut pc = recording_core(PC, "", &closed(index));
        let (each, total) = swings(&ventilated_frames(&mut pc, 3 * cycle));
        let d = pc.disease().unwrap().delivery().unwrap().last.unwrap();
        assert_eq!(
            d.control,
            lung_model::recording::classify::ControlMode::Pressure
        );
        // Less than the recording, as much as the engine says it delivered, and less with more
        // collapse; at least the compliance's share (the stiffer lungs fill faster).
        assert!(
            total < healthy_total - 1.0 && total < last,
            "I = {index}: {total} ml"
        );
        assert!(
            (total - d.fraction * healthy_total).abs() < 0.5,
            "I = {index}: {total} ml against {} of {healthy_total} ml",
            d.fraction
        );
        assert!(
            d.fraction >= d.compliance_ratio * 0.99 && !d.pressure_capped,
            "{d:?}"
        );
        last = total;
        // The other lung takes no more than its own compliance allows (its τ is the system's).
        assert!(
            each[LUNG_RIGHT] < healthy_each[LUNG_RIGHT] * 1.05,
            "I = {index}: {each:?}"
        );
        // Volume control on the same recording: the recorded volume, the collapsing lung's share
        // moved to the other lung.
        let mut vc = recording_core(PC, volume, &closed(index));
        let (_, vc_total) = swings(&ventilated_frames(&mut vc, 3 * cycle));
        assert!(
            (vc_total - healthy_total).abs() < 0.1,
            "I = {index}: {vc_total} ml against {healthy_total} ml"
        );
    }
}

/// Every frame of `ticks` ticks of `core` (stepped and prepared as the process loop does).
fn ventilated_frames(core: &mut EngineCore, ticks: u64) -> Vec<EngineFrame> {
    let mut out = Vec::new();
    for tick in 0..ticks {
        let mut f = EngineFrame::default();
        core.step(tick, None, &mut f);
        core.prepare_ahead().unwrap();
        for l in &f.lungs {
            assert!(
                l.volume_ml.is_finite() && l.deform_scale.is_finite(),
                "tick {tick}: {l:?}"
            );
        }
        out.push(f);
    }
    out
}

/// Two runs' frames are the same, byte for byte.
fn assert_same_frames(a: &[EngineFrame], b: &[EngineFrame]) {
    assert_eq!(a.len(), b.len());
    for (x, y) in a.iter().zip(b) {
        assert_eq!(
            bytemuck::bytes_of(x),
            bytemuck::bytes_of(y),
            "tick {}",
            x.tick
        );
    }
}

/// Each lung's swing (max − min volume) over `frames`, and the swing of the two together.
fn swings(frames: &[EngineFrame]) -> ([f64; 2], f64) {
    let mut lo = [f64::MAX; 3];
    let mut hi = [f64::MIN; 3];
    for f in frames {
        let v = [
            f.lungs[0].volume_ml as f64,
            f.lungs[1].volume_ml as f64,
            f.lungs[0].volume_ml as f64 + f.lungs[1].volume_ml as f64,
        ];
        for k in 0..3 {
            lo[k] = lo[k].min(v[k]);
            hi[k] = hi[k].max(v[k]);
        }
    }
    ([hi[0] - lo[0], hi[1] - lo[1]], hi[2] - lo[2])
}

/// EQUATIONS §4.7: on a ventilator's recorded breath a closed pneumothorax moves the collapsing
/// lung's share to the other lung and the two together still take the recorded volume; index 0 is
/// the healthy waveform scene bit for bit; complete collapse holds the lung and the other takes it
/// all; no PV model is built.
#[test]
fn a_pneumothorax_on_a_recorded_breath_conserves_the_delivered_volume() {
    let scene = waveform_scene();
    let cycle = (scene.engine.tick_hz * 4.0) as u64; // 15 breaths/min
    let healthy = ventilated_frames(
        &mut EngineCore::with_geometry(&scene, baked_geometry()).unwrap(),
        3 * cycle,
    );
    let (healthy_each, healthy_total) = swings(&healthy);
    let closed = |index: f64| {
        format!("[disease]\nkind = \"closed-pneumothorax\"\nside = \"left\"\nindex = {index}\n")
    };
    let zero = ventilated_frames(&mut ventilated_core(&closed(0.0)), 3 * cycle);
    assert_same_frames(&healthy, &zero);
    let mut last_right = healthy_each[LUNG_RIGHT];
    for index in [1e-9, 0.1, 0.5, 1.0] {
        let mut core = ventilated_core(&closed(index));
        assert_eq!(core.stage_counts().pv_models_built, 0);
        let frames = ventilated_frames(&mut core, 3 * cycle);
        let (each, total) = swings(&frames);
        // The delivered volume is conserved (f32 frames: within 0.1 ml).
        assert!(
            (total - healthy_total).abs() < 0.1,
            "I = {index}: {total} ml against {healthy_total} ml"
        );
        // The left lung takes (1 − dV) of its weight, the right lung the rest.
        let dv = index.powf(0.33);
        assert!(each[LUNG_RIGHT] >= last_right - 1e-3, "I = {index}");
        last_right = each[LUNG_RIGHT];
        let (sl, sr) = (healthy_each[LUNG_LEFT], healthy_each[LUNG_RIGHT]);
        let want_left = healthy_total * sl * (1.0 - dv) / (sl * (1.0 - dv) + sr);
        assert!(
            (each[LUNG_LEFT] - want_left).abs() < 0.1,
            "I = {index}: left {} ml, expected {want_left} ml",
            each[LUNG_LEFT]
        );
        // The recorded rate: the period is the recording's.
        assert_eq!(core.cycle_ticks() as u64, cycle);
        if index == 1.0 {
            assert!(frames
                .iter()
                .all(|f| f.lungs[LUNG_LEFT].flags & lung_flags::HELD != 0));
        }
    }
}

/// A tension pneumothorax on a recorded breath runs its course at the ventilator's rate: the two
/// lungs share the delivered volume until the SVC closes, nothing is NaN through arrest and a
/// needle, and the run replays bit for bit.
#[test]
fn a_tension_pneumothorax_on_a_recorded_breath_replays_bitwise() {
    let tension = "[disease]\nkind = \"tension-pneumothorax\"\nside = \"left\"\nv_p_ml = 40.0\n\
                   [[disease.events]]\nat_s = 80.0\nkind = \"needle-decompression\"\nside = \"left\"\n";
    let mut core = ventilated_core(tension);
    let a = ventilated_frames(&mut core, 9000);
    assert_eq!(core.stage_counts().pv_models_built, 0);
    let b = ventilated_frames(&mut ventilated_core(tension), 9000);
    assert_same_frames(&a, &b);
    // Cycle by cycle (240 ticks at 15/min), while neither lung is held, the two lungs' swing is
    // the recorded one.
    let healthy_total = swings(&ventilated_frames(
        &mut EngineCore::with_geometry(&waveform_scene(), baked_geometry()).unwrap(),
        240,
    ))
    .1;
    let mut checked = 0;
    for c in a.chunks(240) {
        let held = c
            .iter()
            .any(|f| f.lungs.iter().any(|l| l.flags & lung_flags::HELD != 0));
        let changed = c[1..].iter().any(|f| {
            f.lungs
                .iter()
                .any(|l| l.flags & lung_flags::CYCLE_CHANGED != 0)
        });
        if !held && !changed && c.len() == 240 {
            let total = swings(c).1;
            // Pleural air changes the affected lung's base between cycles; within one cycle the
            // two lungs together take the recorded volume.
            assert!(
                (total - healthy_total).abs() < 0.5,
                "{total} ml against {healthy_total} ml at tick {}",
                c[0].tick
            );
            checked += 1;
        }
    }
    assert!(checked >= 10, "{checked} cycles checked");
    let Some(disease::DiseaseRun::Tension(run)) = core.disease() else {
        panic!("tension")
    };
    assert_eq!(run.events.len(), 1);
}

/// EQUATIONS §1.1 "I:E": a scene breathes 1:2 by default (quiet breathing), `[pv] ie_ratio = [1, 1]`
/// gives the seed's 2.5 s + 2.5 s, and a disease course keeps the scene's I:E (the clinical model).
#[test]
fn the_default_breath_is_one_to_two_and_the_seeds_one_to_one_stays_reachable() {
    let inhaling = |core: &mut EngineCore, side: usize| {
        let mut f = EngineFrame::default();
        let mut n = 0;
        let mut ticks = (0, 0);
        for tick in 0..300 {
            core.step(tick, None, &mut f);
            n += (f.lungs[side].flags & lung_flags::INHALING != 0) as u32;
            ticks = (f.lungs[side].inhale_ticks, f.lungs[side].cycle_ticks);
        }
        (n, ticks)
    };
    assert_eq!(
        Scene::default().pv.ie_ratio,
        lung_model::pv::DEFAULT_IE_RATIO
    );
    assert_eq!(inhaling(&mut core(), LUNG_LEFT), (100, (100, 300)));
    let mut seed = Scene::default();
    seed.pv.ie_ratio = lung_model::pv::SEED_IE_RATIO;
    let mut c = EngineCore::with_geometry(&seed, baked_geometry()).unwrap();
    assert_eq!(inhaling(&mut c, LUNG_LEFT), (150, (150, 300)));
    // A closed pneumothorax quickens the breath and keeps 1:2 (to the tick).
    let mut c = disease_core("kind = \"closed-pneumothorax\"\nside = \"left\"\nindex = 0.1\n");
    let (_, (ti, ct)) = inhaling(&mut c, LUNG_RIGHT);
    assert!(
        ct < 300 && (3 * ti as i64 - ct as i64).abs() <= 2,
        "{ti} of {ct}"
    );
}

/// Frames recorded; at tick 30 the loop stalls for ten periods (the clock jumps), past the
/// pacer's catch-up allowance.
struct Stalls(Vec<EngineFrame>, transport::FakeClock, u64);

impl transport::Publish<EngineFrame> for Stalls {
    fn publish(&mut self, f: &EngineFrame) -> Result<(), transport::PortError> {
        self.0.push(*f);
        if f.tick == 30 {
            self.1.advance(10 * self.2);
        }
        Ok(())
    }
}

/// Remote sites schedule the source's tick k at the last state's time plus (k − its tick)
/// periods. When the source's pacer skips deadlines, its ticks from then on fall whole periods
/// later than that: it publishes a state at the first tick after the skip, with that tick's due
/// time, so the sites re-anchor one path delay later instead of a breathing cycle later (the
/// classroom harness's 33 ms phase errors on a loaded machine).
#[test]
fn a_skipped_deadline_publishes_a_state_with_the_new_schedule() {
    use control_state::{decode, Packet};
    use ipc_types::{ControlPacket, ControlReply};
    use transport::memory::{Recorder, Scripted};
    use transport::FakeClock;
    const P: u64 = 16_666_667;
    let clock = FakeClock::at(0);
    let mut inlet = Scripted::<ControlPacket>::new(&clock, vec![], 4);
    let mut replies = Recorder::<ControlReply>::new(&clock);
    let mut frames = Stalls(Vec::new(), clock.clone(), P);
    let (stats, published) = run_publishing_state(
        &mut core(),
        &mut inlet,
        &mut replies,
        &mut frames,
        &clock,
        P,
        7,
        120 * P,
    );
    assert!(stats.pacer.skipped_deadlines > 0, "{:?}", stats.pacer);
    let states: Vec<_> = published
        .values()
        .iter()
        .map(|f| match decode(f.encoded()).unwrap() {
            Packet::State(s) => (s.tick, s.source_time_ns),
            p => panic!("{p:?}"),
        })
        .collect();
    // The first state (tick 0) and one at tick 31, the first after the stall; no cycle starts
    // between (the default scene breathes 12 a minute: 300 ticks a cycle).
    assert_eq!(states.len(), 2, "{states:?}");
    assert_eq!(states[1].0, 31);
    // Its time is the schedule the ticks now follow: tick 32 ran one period after it.
    let due_31 = states[1].1;
    assert!(due_31 > states[0].1 + 31 * P, "{states:?}");
    let t = |k: u64| {
        frames
            .0
            .iter()
            .find(|f| f.tick == k)
            .unwrap()
            .stamps
            .engine_receive_ns
    };
    assert!(t(32) >= due_31 + P && t(32) < due_31 + 2 * P, "{states:?}");
}

/// [`process::run_loop`] without tracker frames, taking actions from `inlet` (replies to `replies`,
/// engine frames to `frames`) and publishing its
/// control state as source `source` (epoch 1, 60 Hz), paced at `period` ns on the fake `clock`
/// until it reads `until_ns`: the loop's stats and what it published (the two remote-state tests'
/// common set-up).
fn run_publishing_state(
    core: &mut EngineCore,
    inlet: &mut dyn transport::Receive<ipc_types::ControlPacket>,
    replies: &mut dyn transport::Publish<ipc_types::ControlReply>,
    frames: &mut dyn transport::Publish<EngineFrame>,
    clock: &transport::FakeClock,
    period: u64,
    source: u64,
    until_ns: u64,
) -> (
    process::LoopStats,
    transport::memory::Recorder<control_state::ControlStateFrame>,
) {
    use transport::memory::{Recorder, Scripted};
    use transport::Clock;
    let mut tracker = Scripted::<TrackerFrame>::new(clock, vec![], 4);
    let mut outlet = Recorder::<control_state::ControlStateFrame>::new(clock);
    let published = outlet.clone();
    let c = clock.clone();
    let stats = process::run_loop(
        core,
        &mut tracker,
        frames,
        Some(process::Controls {
            inlet,
            replies,
            state: Some(process::StateOut {
                outlet: &mut outlet,
                source,
                epoch: 1,
                tick_hz: 60.0,
            }),
        }),
        clock,
        transport::pacer::PacerConfig::for_period(period),
        &mut || c.now_ns() >= until_ns,
        None,
        0,
    )
    .unwrap();
    (stats, published)
}

/// The headless runner (`lungdyn scene run`) is the engine's tick function: its frames are those of
/// the same core stepped by hand, bit for bit, and its per-lung summary is the frames' own (the
/// default scene's 12 breaths a minute, the tidal swing of the last whole breath).
#[test]
fn the_headless_run_is_the_tick_function_and_summarises_its_frames() {
    let ticks = 60 * 20;
    let mut seen = Vec::new();
    let run = crate::headless::run_core(core(), ticks, &mut |t| frame(t, true), &mut |_, f| {
        seen.push(*f)
    })
    .unwrap();
    let mut by_hand = core();
    let mut f = EngineFrame::default();
    for (tick, s) in (0..ticks).zip(&seen) {
        by_hand.step(tick, Some(&frame(tick, true)), &mut f);
        assert_eq!(bytemuck::bytes_of(&f), bytemuck::bytes_of(s), "tick {tick}");
        by_hand.prepare_ahead().unwrap();
    }
    assert_eq!(seen.len() as u64, ticks);
    assert_eq!(bytemuck::bytes_of(&run.last), bytemuck::bytes_of(&f));
    assert_eq!(run.non_finite_frames, 0);
    for k in [LUNG_LEFT, LUNG_RIGHT] {
        let vols: Vec<f64> = seen.iter().map(|f| f.lungs[k].volume_ml as f64).collect();
        let lo = vols.iter().copied().fold(f64::INFINITY, f64::min);
        let hi = vols.iter().copied().fold(f64::NEG_INFINITY, f64::max);
        assert_eq!(run.lungs[k].volume_range_ml, (lo, hi));
        let (tidal, rate) = run.lungs[k].tidal_and_rate(60.0);
        let rate = rate.expect("whole breaths in 20 s");
        assert!((rate - 12.0).abs() < 0.1, "lung {k}: {rate} breaths/min");
        assert!(
            tidal > 0.0 && tidal <= hi - lo + 1e-9,
            "lung {k}: {tidal} ml"
        );
    }
}

// ---- Breathing with the patient's signal (issue 35; runtime::signal) ----

const TICK_NS: u64 = 16_666_667;
const T0_NS: u64 = 1_000_000_000;

fn signal_core(latency_ms: f64) -> EngineCore {
    let mut scene = Scene::default();
    scene.breathing.source = lung_model::scene::BreathSource::Signal;
    scene.breathing.signal = "trace:unused-by-the-engine".into();
    scene.breathing.latency_ms = latency_ms;
    scene.validate().unwrap();
    EngineCore::with_geometry(&scene, baked_geometry()).unwrap()
}

/// A chest marker's excursion, mm: a breath every 4.7 s (not a whole number of 25 Hz samples),
/// inspiration the shorter part, each breath's depth 10 mm ± 10 % (so no breath is the last one's
/// copy and the calibration is a median).
fn chest_mm(t_s: f64) -> f64 {
    let cycles = t_s / 4.7;
    let depth = 10.0 * (1.0 + 0.1 * (cycles.floor() * 1.3).sin());
    let phase = cycles.fract();
    if phase < 0.4 {
        depth * (0.5 - 0.5 * (std::f64::consts::PI * phase / 0.4).cos())
    } else {
        depth * (0.5 + 0.5 * (std::f64::consts::PI * (phase - 0.4) / 0.6).cos())
    }
}

/// The tracker frame of `tick` (60 Hz) carrying the 25 Hz samples of `signal` due since the
/// previous tick's, those in `cut` (seconds) withheld; `value` may spoil a sample.
fn signal_frame(
    tick: u64,
    cut: Option<(f64, f64)>,
    value: &dyn Fn(u64, f64) -> (f64, bool),
) -> TrackerFrame {
    let mut f = frame(tick, true);
    let now = T0_NS + tick * TICK_NS;
    f.stamps.capture_ns = now;
    f.stamps.bridge_publish_ns = now;
    f.signal.status = ipc_types::signal_status::CONFIGURED;
    f.signal.unit = ipc_types::signal_unit::MM;
    f.signal.period_ns = 40_000_000;
    let prev = now.saturating_sub(TICK_NS);
    let first = (prev.saturating_sub(T0_NS)) / 40_000_000;
    for k in first..=(now - T0_NS) / 40_000_000 {
        let t = T0_NS + k * 40_000_000;
        let t_s = (t - T0_NS) as f64 * 1e-9;
        if t <= prev && tick > 0 || t > now || cut.is_some_and(|(a, b)| t_s >= a && t_s < b) {
            continue;
        }
        let i = f.signal.count as usize;
        let (v, valid) = value(k, t_s);
        f.signal.samples[i] = ipc_types::SignalWire { t_ns: t, value: v };
        if valid {
            f.signal.valid_mask |= 1 << i;
        }
        f.signal.count += 1;
    }
    f
}

/// Run `seconds` of ticks: (time s, both lungs' volume above FRC ml, state bits) per tick.
fn follow_run(
    core: &mut EngineCore,
    seconds: f64,
    cut: Option<(f64, f64)>,
    value: &dyn Fn(u64, f64) -> (f64, bool),
) -> Vec<(f64, f64, u32)> {
    run_inputs(core, seconds, &|tick| signal_frame(tick, cut, value))
}

/// [`follow_run`] with each tick's tracker frame from `input`.
fn run_inputs(
    core: &mut EngineCore,
    seconds: f64,
    input: &dyn Fn(u64) -> TrackerFrame,
) -> Vec<(f64, f64, u32)> {
    let frc: f64 = core.geometry().map(|g| g.start_volume_ml).sum();
    let ticks = (seconds * 60.0) as u64;
    let mut out = Vec::new();
    let mut f = EngineFrame::default();
    for tick in 0..ticks {
        core.step(tick, Some(&input(tick)), &mut f);
        let v: f64 = f
            .lungs
            .iter()
            .filter(|l| l.is_active())
            .map(|l| l.volume_ml as f64)
            .sum();
        out.push((tick as f64 / 60.0, v - frc, f.state));
    }
    out
}

/// The index of the first tick of `run` the signal drove.
fn first_following(run: &[(f64, f64, u32)]) -> usize {
    run.iter()
        .position(|r| r.2 & ipc_types::engine_state::SIGNAL_FOLLOWING != 0)
        .expect("follows")
}

fn clean(_: u64, t_s: f64) -> (f64, bool) {
    (chest_mm(t_s), true)
}

/// A spirometer's volume in ml (50 ml per mm of [`chest_mm`]: 500 ml breaths from an
/// end-expiration at 0 s) drives the lungs from its first samples when its block states its rate;
/// a source whose rate is not known yet (period 0, learnt by the bridge after its first samples, as
/// a UDP or OpenIGTLink stream's) waits for its first end-expiration instead — restarted on the
/// learnt rate mid-breath, it would take wherever it restarted as its baseline — and the takeover
/// then blends from the model without a step.
#[test]
fn a_volume_drives_from_its_first_samples_once_its_rate_is_known() {
    use ipc_types::engine_state as e;
    let run = |unknown_until_s: f64| {
        run_inputs(&mut signal_core(50.0), 12.0, &|tick| {
            let mut input = signal_frame(tick, None, &|_, t_s| (50.0 * chest_mm(t_s), true));
            input.signal.unit = ipc_types::signal_unit::ML;
            if (tick as f64 / 60.0) < unknown_until_s {
                input.signal.period_ns = 0;
            }
            input
        })
    };
    let first_following = |r: &[(f64, f64, u32)]| r[first_following(r)].0;
    let known = run(0.0);
    assert!(
        first_following(&known) < 0.5,
        "from {:.2} s",
        first_following(&known)
    );
    let learnt = run(0.5);
    let from = first_following(&learnt);
    // The first end-expiration is at 4.7 s, confirmed once the next breath has risen past the
    // hysteresis.
    assert!(from > 4.7 && from < 6.5, "from {from:.2} s");
    assert!(learnt
        .iter()
        .filter(|x| x.0 >= from)
        .all(|x| x.2 & e::SIGNAL_FOLLOWING != 0));
    let worst = learnt
        .windows(2)
        .map(|w| (w[1].1 - w[0].1).abs())
        .fold(0.0, f64::max);
    // 500 ml breaths at 60 Hz move at most about 12 ml a tick.
    assert!(
        worst < 25.0,
        "the drawn volume stepped {worst:.1} ml in a tick"
    );
}

/// A belt's breaths of depths 6-14 mm (4.7 s each), cut at `ceiling` mm by its sensor's range.
fn belt(ceiling: f64) -> impl Fn(u64, f64) -> (f64, bool) {
    move |_: u64, t_s: f64| {
        let c = (t_s / 4.7).floor();
        let depth = 10.0 * (0.6 + 0.8 * (c * 0.618_034).fract());
        let v = depth * 0.5 * (1.0 - (std::f64::consts::TAU * t_s / 4.7).cos());
        (v.min(ceiling), true)
    }
}

/// A belt whose deeper breaths are cut by its sensor's range (depths 6-14 mm, cut at 12): the
/// frames say so (`SIGNAL_CLIPPED`, the HUD's "SIGNAL LOOKS CLIPPED") while the lungs follow it; the
/// same breaths uncut never do.
#[test]
fn a_signal_cut_by_its_sensors_range_is_flagged_on_the_frames() {
    use ipc_types::engine_state as e;
    let run = |ceiling: f64| {
        let mut core = signal_core(50.0);
        follow_run(&mut core, 120.0, None, &belt(ceiling))
    };
    let cut = run(12.0);
    let flagged: Vec<_> = cut
        .iter()
        .filter(|r| r.2 & e::SIGNAL_CLIPPED != 0)
        .collect();
    assert!(
        flagged.len() > 60 * 30,
        "{} of {} frames flagged",
        flagged.len(),
        cut.len()
    );
    assert!(flagged.iter().all(|r| r.2 & e::SIGNAL_FOLLOWING != 0));
    // Once seen (three cut breaths), it stays while the last 16 breaths show it.
    let first = cut
        .iter()
        .position(|r| r.2 & e::SIGNAL_CLIPPED != 0)
        .unwrap();
    assert!(cut[first..].iter().all(|r| r.2 & e::SIGNAL_CLIPPED != 0));
    let uncut = run(f64::INFINITY);
    assert!(uncut.iter().all(|r| r.2 & e::SIGNAL_CLIPPED == 0));
    assert!(uncut.iter().any(|r| r.2 & e::SIGNAL_FOLLOWING != 0));
}

#[test]
fn the_lungs_follow_the_patients_signal_once_calibrated() {
    use ipc_types::engine_state as e;
    let mut core = signal_core(50.0);
    let tidal = core.lung(Side::Right).unwrap().breathing().boundary().tv_ml;
    let run = follow_run(&mut core, 60.0, None, &clean);
    // First the model breathes while the signal calibrates; following within three breaths.
    assert!(run[0].2 & e::SIGNAL_CALIBRATING != 0, "{:b}", run[0].2);
    let following = first_following(&run);
    assert!(
        run[following].0 < 16.0,
        "following from {} s",
        run[following].0
    );
    assert!(run[following..]
        .iter()
        .all(|r| r.2 & e::SIGNAL_FOLLOWING != 0));
    // Over the last 30 s the drawn volume is the signal at the display time (50 ms after the
    // frame's stamp) calibrated to the model's tidal volume (10 mm, the median depth): within 5 %
    // of it, RMS.
    let mut sq = 0.0;
    let mut n = 0.0;
    for &(t, v, _) in run.iter().filter(|r| r.0 >= 30.0) {
        let want = tidal * chest_mm(t + 0.05) / 10.0;
        sq += (v - want).powi(2);
        n += 1.0;
    }
    let rms = (sq / n).sqrt();
    eprintln!(
        "following from {:.2} s; RMS {rms:.1} ml of a {tidal:.0} ml tidal volume over 30-60 s",
        run[following].0
    );
    assert!(
        rms < 0.05 * tidal,
        "RMS {rms:.1} ml of a {tidal:.0} ml tidal volume"
    );
    assert!(core.signal().unwrap().follower().counts().breaths >= 10);
    let t = core.signal().unwrap().ticks();
    assert_eq!(t.following + t.calibrating + t.lost, run.len() as u64);
    assert_eq!(t.following, (run.len() - following) as u64);
}

/// `[breathing] ml_per_unit` (a spirometry calibration): the amplitude drives the lungs from its
/// first samples (its baseline the lowest value so far until the first end-expiration), not after
/// two regular breaths, and at the spirometer's gain — the patient's own tidal volume (here
/// 70 ml/mm × 10 mm = 700 ml), not the scene's.
#[test]
fn a_spirometry_calibration_drives_from_the_first_samples_at_its_own_gain() {
    use ipc_types::engine_state as e;
    let mut auto = signal_core(50.0);
    let tidal = auto.lung(Side::Right).unwrap().breathing().boundary().tv_ml;
    let auto_run = follow_run(&mut auto, 40.0, None, &clean);
    let mut scene = Scene::default();
    scene.breathing.source = lung_model::scene::BreathSource::Signal;
    scene.breathing.signal = "trace:unused-by-the-engine".into();
    scene.breathing.latency_ms = 50.0;
    scene.breathing.ml_per_unit = Some(70.0);
    scene.validate().unwrap();
    let mut spiro = EngineCore::with_geometry(&scene, baked_geometry()).unwrap();
    let run = follow_run(&mut spiro, 40.0, None, &clean);
    let (from, auto_from) = (first_following(&run), first_following(&auto_run));
    // The trace starts at its trough (no turn: the first end-expiration found is at 4.7 s), so
    // the lowest value so far is the baseline from the first samples.
    assert!(
        run[from].0 < 0.5 && run[from].0 + 4.0 < auto_run[auto_from].0,
        "following from {:.2} s with the calibration, {:.2} s without",
        run[from].0,
        auto_run[auto_from].0
    );
    assert!(run[from..].iter().all(|r| r.2 & e::SIGNAL_FOLLOWING != 0));
    // The volume is the spirometer's: 70 ml per mm, at the display time, past the takeover.
    let (mut sq, mut n) = (0.0, 0.0);
    for &(t, v, _) in run.iter().filter(|r| r.0 >= run[from].0 + 1.0) {
        sq += (v - 70.0 * chest_mm(t + 0.05)).powi(2);
        n += 1.0;
    }
    let rms = (sq / n).sqrt();
    eprintln!(
        "spirometry calibration: following from {:.2} s (without: {:.2} s), RMS {rms:.1} ml against 70 ml/mm",
        run[from].0, auto_run[auto_from].0
    );
    assert!(rms < 0.05 * 700.0, "RMS {rms:.1} ml against 70 ml/mm");
    assert!(
        (tidal - 700.0).abs() > 100.0,
        "the scene's tidal volume is another"
    );
    let spiro_peak = run.iter().map(|r| r.1).fold(f64::MIN, f64::max);
    assert!(
        spiro_peak > 700.0 && spiro_peak < 1.2 * 770.0,
        "the deepest breath drawn: {spiro_peak:.0} ml (11 mm at most)"
    );
}

/// The engine frame says what the engine followed (layout v7, `lungdyn breathing follow` reads it):
/// the display time it predicted for — the newest input's stamp plus `latency_ms` — and the volume
/// above FRC with and without the prediction, of which the lungs draw a fixed share once the
/// takeover's blend is over; a scene that breathes with the model says nothing.
#[test]
fn the_engine_frame_carries_what_it_followed_of_the_signal() {
    use ipc_types::engine_state as e;
    let mut eng = signal_core(50.0);
    let frc: f64 = eng.geometry().map(|g| g.start_volume_ml).sum();
    let mut f = EngineFrame::default();
    let (mut newest, mut since, mut ratios) = (0u64, None, Vec::new());
    for tick in 0..40 * 60 {
        let input = signal_frame(tick, None, &clean);
        newest = newest.max(input.stamps.bridge_publish_ns.max(input.stamps.capture_ns));
        eng.step(tick, Some(&input), &mut f);
        let s = f.signal;
        assert!(s.volume_ml.is_finite() && s.unpredicted_ml.is_finite());
        if s.display_ns != 0 {
            assert_eq!(s.display_ns, newest + 50_000_000, "tick {tick}");
        }
        if f.state & e::SIGNAL_FOLLOWING == 0 {
            continue;
        }
        let from = *since.get_or_insert(tick);
        if tick >= from + super::signal::TAKEOVER_TICKS && s.volume_ml.abs() > 50.0 {
            let drawn: f64 = f
                .lungs
                .iter()
                .filter(|l| l.is_active())
                .map(|l| l.volume_ml as f64)
                .sum::<f64>()
                - frc;
            ratios.push(drawn / s.volume_ml as f64);
        }
    }
    assert!(ratios.len() > 300, "{} frames compared", ratios.len());
    let (lo, hi) = ratios
        .iter()
        .fold((f64::MAX, f64::MIN), |a, &r| (a.0.min(r), a.1.max(r)));
    assert!(
        hi - lo < 1e-3,
        "the lungs' share of the followed volume: {lo}..{hi}"
    );
    // The patient's typical breath for the heads-up display (layout v9): a breath every 4.7 s,
    // and (an amplitude calibrated to the scene's tidal volume) the model's tidal volume.
    let model_tv: f32 = f
        .lungs
        .iter()
        .filter(|l| l.is_active())
        .map(|l| l.tidal_ml)
        .sum();
    assert!((f.signal.period_s - 4.7).abs() < 0.05, "{:?}", f.signal);
    assert!(
        (f.signal.tidal_ml - model_tv).abs() < 1.0,
        "{:?} against {model_tv}",
        f.signal
    );
    // …and where the breath is: inspiration 40 % of each breath (chest_mm), the phase the time
    // since the last end-expiration (the breath starts at multiples of 4.7 s; the display time is
    // the newest input's plus 50 ms).
    assert!(
        (f.signal.inhale_fraction - 0.4).abs() < 0.05,
        "{:?}",
        f.signal
    );
    let display_s = (f.signal.display_ns - T0_NS) as f64 * 1e-9;
    let expected = (display_s / 4.7).fract();
    assert!(
        (f64::from(f.signal.phase) - expected).abs() < 0.03,
        "{:?} at {display_s} s: {expected}",
        f.signal
    );
    // With the model breathing there is nothing to say.
    let mut model = core();
    for tick in 0..120 {
        model.step(tick, Some(&signal_frame(tick, None, &clean)), &mut f);
        assert_eq!(f.signal, ipc_types::SignalFollowed::default());
    }
}

/// `latency = "measured"` (the default): the engine predicts across the pipeline's latency that
/// each frame carries (measured by the bridge from the renderer's reports) plus the source's own
/// delay, `latency_ms` until one comes; a latency past 1 s is bounded; `latency = "fixed"` keeps
/// `latency_ms` whatever the frames say. What is predicted follows the horizon, and the same frames
/// give the same engine frames bit for bit.
#[test]
fn the_breath_is_predicted_across_the_latency_the_renderer_measured() {
    use lung_model::scene::LatencyChoice;
    let run = |choice: LatencyChoice, sensor_ms: f64, measured: &dyn Fn(u64) -> u64| {
        let mut scene = Scene::default();
        scene.breathing.source = lung_model::scene::BreathSource::Signal;
        scene.breathing.signal = "trace:unused-by-the-engine".into();
        scene.breathing.latency_ms = 50.0;
        scene.breathing.latency = choice;
        scene.breathing.sensor_latency_ms = sensor_ms;
        scene.validate().unwrap();
        let mut eng = EngineCore::with_geometry(&scene, baked_geometry()).unwrap();
        let mut f = EngineFrame::default();
        let mut out = Vec::new();
        for tick in 0..30 * 60 {
            let mut input = signal_frame(tick, None, &clean);
            input.signal.pipeline_latency_ns = measured(tick);
            eng.step(tick, Some(&input), &mut f);
            let horizon = (f.signal.display_ns != 0).then(|| {
                assert_eq!(
                    f.signal.display_ns - input.stamps.bridge_publish_ns,
                    f.signal.latency_ns,
                    "the frame says the latency it predicted across"
                );
                f.signal.latency_ns
            });
            out.push((horizon, f));
        }
        out
    };
    let ramp = |tick: u64| match tick {
        0..600 => 0,
        600..1200 => 12_000_000,
        _ => 5_000_000_000,
    };
    let measured = run(LatencyChoice::Measured, 5.0, &ramp);
    let horizons: Vec<Option<u64>> = measured.iter().map(|r| r.0).collect();
    assert!(horizons[..600].iter().flatten().all(|&h| h == 50_000_000));
    assert!(horizons[..600].iter().flatten().count() > 500);
    assert!(horizons[600..1200].iter().all(|&h| h == Some(17_000_000)));
    assert!(horizons[1200..].iter().all(|&h| h == Some(1_005_000_000)));
    let fixed = run(LatencyChoice::Fixed, 5.0, &ramp);
    assert!(fixed.iter().filter_map(|r| r.0).all(|h| h == 50_000_000));
    // What is predicted follows the horizon: the volumes differ while following with 17 ms.
    let following =
        |r: &(Option<u64>, EngineFrame)| r.1.state & ipc_types::engine_state::SIGNAL_FOLLOWING != 0;
    let differ = (600..1200)
        .filter(|&t| following(&measured[t]) && following(&fixed[t]))
        .filter(|&t| measured[t].1.signal.volume_ml != fixed[t].1.signal.volume_ml)
        .count();
    assert!(differ > 300, "{differ} ticks predicted differently");
    // A pure function of the frames.
    let again = run(LatencyChoice::Measured, 5.0, &ramp);
    assert!(measured
        .iter()
        .zip(&again)
        .all(|(a, b)| bytemuck::bytes_of(&a.1) == bytemuck::bytes_of(&b.1)));
}

#[test]
fn a_lost_signal_is_flagged_within_100_ms_and_the_model_carries_on_without_a_jump() {
    use ipc_types::engine_state as e;
    let core = signal_core(50.0);
    let tidal = core.lung(Side::Right).unwrap().breathing().boundary().tv_ml;
    // Cut mid-inspiration and mid-expiration in two runs.
    for cut_at in [41.0, 43.5] {
        let mut core = signal_core(50.0);
        let run = follow_run(&mut core, 60.0, Some((cut_at, cut_at + 5.0)), &clean);
        let last_sample = run.iter().rposition(|r| r.0 < cut_at).unwrap();
        let lost = run
            .iter()
            .position(|r| r.0 >= cut_at && r.2 & e::SIGNAL_LOST != 0)
            .expect("the loss is flagged");
        let after_ms = (run[lost].0 - run[last_sample].0) * 1000.0;
        assert!(
            after_ms <= 100.0 + 17.0,
            "lost said {after_ms:.0} ms after the last sample"
        );
        // Phase-continuous: the step at the handover is no larger than the breath's own steps.
        let step = (run[lost].1 - run[lost - 1].1).abs();
        let own = run[lost - 30..lost - 1]
            .windows(2)
            .map(|w| (w[1].1 - w[0].1).abs())
            .fold(0.0, f64::max);
        assert!(
            step <= own.max(0.02 * tidal) * 1.5,
            "cut at {cut_at} s: a {step:.1} ml jump at the handover (the breath's own steps up to {own:.1} ml)"
        );
        // The model breathes during the loss (its volume moves), and the signal takes over again.
        let during: Vec<f64> = run
            .iter()
            .filter(|r| r.0 > cut_at + 0.5 && r.0 < cut_at + 4.5)
            .map(|r| r.1)
            .collect();
        let swing = during.iter().cloned().fold(f64::MIN, f64::max)
            - during.iter().cloned().fold(f64::MAX, f64::min);
        assert!(
            swing > 0.5 * tidal,
            "the model breathes while the signal is lost: {swing:.0} ml"
        );
        let back = run
            .iter()
            .position(|r| r.0 > cut_at + 5.0 && r.2 & e::SIGNAL_FOLLOWING != 0)
            .expect("following again after the loss");
        assert!(
            run[back].0 < cut_at + 5.0 + 1.0,
            "cut at {cut_at} s: following again {:.2} s after the samples came back",
            run[back].0 - cut_at - 5.0
        );
        eprintln!(
            "cut at {cut_at} s: lost said after {after_ms:.0} ms, handover step {step:.1} ml (own steps up to {own:.1} ml), model swing {swing:.0} ml"
        );
        // The signal takes over blended in from the model's breath: no jump either.
        let step = (run[back].1 - run[back - 1].1).abs();
        eprintln!(
            "cut at {cut_at} s: following again after {:.2} s, takeover step {step:.1} ml",
            run[back].0 - cut_at - 5.0
        );
        assert!(
            step <= own * 1.5 + tidal / signal::TAKEOVER_TICKS as f64 + 0.02 * tidal,
            "cut at {cut_at} s: a {step:.1} ml jump when the signal took over again"
        );
        assert!(run.last().unwrap().2 & e::SIGNAL_FOLLOWING != 0);
    }
    drop(core);
}

#[test]
fn a_signal_run_replays_bitwise_and_bad_samples_never_reach_a_frame() {
    // Every fifth sample flagged invalid with a NaN or a huge value behind it; every 37th a
    // valid absurdity.
    let spoilt = |k: u64, t_s: f64| match k % 37 {
        0 => (1e300, true),
        _ if k % 5 == 4 => (if k % 2 == 0 { f64::NAN } else { -1e12 }, false),
        _ => (chest_mm(t_s), true),
    };
    let frames = |core: &mut EngineCore| {
        let mut out = Vec::new();
        let mut f = EngineFrame::default();
        for tick in 0..3600u64 {
            let mut input = signal_frame(tick, Some((30.0, 33.0)), &spoilt);
            if tick % 13 == 7 {
                // A foreign frame's block: more samples claimed than it holds, all "valid".
                input.signal.count = u32::MAX;
                input.signal.valid_mask = u32::MAX;
            }
            if tick % 17 == 3 {
                // ... and a unit and a period no source has.
                input.signal.unit = 99;
                input.signal.period_ns = u64::MAX;
            }
            // Every 11th tick without a frame (the deadline fallback).
            core.step(tick, (tick % 11 != 5).then_some(&input), &mut f);
            out.push(f);
        }
        out
    };
    let a = frames(&mut signal_core(80.0));
    let b = frames(&mut signal_core(80.0));
    assert!(a == b, "the same inputs, the same frames");
    for f in &a {
        for l in f.lungs.iter().filter(|l| l.is_active()) {
            assert!(
                l.volume_ml.is_finite() && l.deform_scale.is_finite(),
                "{l:?}"
            );
            assert!(l.volume_ml > 0.0 && l.volume_ml < 8000.0, "{}", l.volume_ml);
        }
        assert_eq!(f.fault, fault::NONE);
    }
    let c = signal_core(80.0);
    assert!(c.signal().is_some());
    assert!(
        core().signal().is_none(),
        "a model scene has no signal drive"
    );
}

/// The surfaces the engine's frame draws in `mode` for the patient turned by `turn` from supine, at
/// tick 150 (mid-inhalation), with kernels of `preset`: one position list per lung.
fn drawn_in(
    mode: DeformMode,
    preset: lung_model::deform::DirectionPreset,
    turn: glam::DQuat,
) -> Vec<Vec<[f32; 3]>> {
    use lung_model::deform::modes::CpuLung;
    let (mut core, files) = core_of(mode, OrientationMethod::Exact, preset);
    let mut f = EngineFrame::default();
    core.step(150, Some(&posed(150, turn * supine())), &mut f);
    files
        .iter()
        .zip(&f.lungs)
        .map(|(k, lung)| {
            let mut cpu = CpuLung::from_kernel(k, mode).unwrap();
            let mut out = vec![[0.0f32; 3]; cpu.len()];
            cpu.deform_into(
                lung.deform_scale,
                &lung.coeffs[..lung.coeff_count as usize],
                [0.0; 3],
                &mut out,
            )
            .unwrap();
            out
        })
        .collect()
}

/// A kernel whose motion is a fitted force field (the breath-hold population, as a breath-hold
/// pair's `fit-motion` writes) is drawn supine by every orientation-following mode as its
/// precomputed field: the fitted supine force is the first basis function (EQUATIONS.md §3.3, "A
/// fitted supine force"). Before, the basis, SH and direct modes drew eq. 6.18's linear force with
/// Table 6.1's constants and the fitted directions: 7.1 mm (mean) from the fitted motion on the
/// left lung at +250 ml, where the motion itself is 8.8 mm. Turned onto its side the lung moves
/// otherwise (the posture still counts), with no NaN, and basis and direct agree.
#[test]
fn a_fitted_force_is_drawn_supine_by_every_mode_as_its_precomputed_field() {
    use lung_model::deform::DirectionPreset;
    let preset = DirectionPreset::BreathHold;
    let supine_turn = glam::DQuat::IDENTITY;
    let reference = drawn_in(DeformMode::Precomputed, preset, supine_turn);
    let files: Vec<KernelFile> = kernels_of(4, preset)
        .iter()
        .map(|p| KernelFile::open_lazy(p).unwrap())
        .collect();
    let rest: Vec<Vec<[f32; 3]>> = files.iter().map(|k| k.mesh().positions).collect();
    let distance = |a: &[f32; 3], b: &[f32; 3]| {
        ((a[0] - b[0]).powi(2) + (a[1] - b[1]).powi(2) + (a[2] - b[2]).powi(2)).sqrt() as f64
    };
    let mean = |a: &[[f32; 3]], b: &[[f32; 3]]| {
        a.iter().zip(b).map(|(a, b)| distance(a, b)).sum::<f64>() / a.len() as f64
    };
    for (k, (lung, start)) in files.iter().zip(reference.iter().zip(&rest)) {
        assert!(k.meta().orientation.as_ref().unwrap().fitted_supine_force);
        let moved = mean(lung, start);
        assert!(
            moved > 1.0,
            "{:?}: the breath moves {moved} mm",
            k.meta().side
        );
    }
    for (mode, tolerance_mm) in [
        (DeformMode::Basis, 0.01),
        (DeformMode::Direct, 0.01),
        // Four bands: the projection's own error (its RMS against eq. 7.1 is in the kernel).
        (DeformMode::Sh, 0.0),
    ] {
        let drawn = drawn_in(mode, preset, supine_turn);
        for (k, (d, r)) in files.iter().zip(drawn.iter().zip(&reference)) {
            let worst = d
                .iter()
                .zip(r)
                .map(|(a, b)| distance(a, b))
                .fold(0.0, f64::max);
            let rms = (d
                .iter()
                .zip(r)
                .map(|(a, b)| distance(a, b).powi(2))
                .sum::<f64>()
                / d.len() as f64)
                .sqrt();
            let allowed = if mode == DeformMode::Sh {
                // The SH error is measured at the reference volume (250 ml or less) over the
                // orientation set; mid-inhalation is within it.
                3.0 * k.meta().sh.as_ref().unwrap().rms_mm + 0.05
            } else {
                tolerance_mm
            };
            let measured = if mode == DeformMode::Sh { rms } else { worst };
            assert!(
                measured <= allowed,
                "{mode} {:?}: {measured} mm from the precomputed field (allowed {allowed})",
                k.meta().side
            );
        }
    }
    let turned = glam::DQuat::from_rotation_y(std::f64::consts::FRAC_PI_2);
    let basis = drawn_in(DeformMode::Basis, preset, turned);
    let direct = drawn_in(DeformMode::Direct, preset, turned);
    for ((b, d), r) in basis.iter().zip(&direct).zip(&reference) {
        assert!(b.iter().flatten().all(|v| v.is_finite()));
        assert!(mean(b, r) > 0.1, "the turned lung moves as the supine one");
        let worst = b
            .iter()
            .zip(d)
            .map(|(a, c)| distance(a, c))
            .fold(0.0, f64::max);
        assert!(worst < 0.01, "basis and direct differ by {worst} mm turned");
    }
}

/// A kernel with a fitted force baked before the orientation modes drew it (its metadata lacks
/// `fitted_supine_force`) is refused by every orientation-following mode, naming what to do, and
/// still drawn by the precomputed mode (whose field was always the fit).
#[test]
fn a_fitted_force_baked_before_the_orientation_modes_drew_it_is_refused_by_them() {
    use lung_model::deform::modes::CpuLung;
    use lung_model::deform::DirectionPreset;
    let side = Side::Left;
    let mut k = lung_bake::kernel::bake(
        side,
        generate::lung(side, 300).unwrap(),
        &lung_bake::kernel::BakeSettings::for_preset(DirectionPreset::BreathHold, side),
        &|_| {},
    )
    .unwrap();
    k.meta.orientation.as_mut().unwrap().fitted_supine_force = false;
    let dir = std::env::temp_dir().join(format!("lungdyn-stale-fit-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    let path = dir.join("left.kernel");
    k.write(&path).unwrap();
    let file = KernelFile::open_lazy(&path).unwrap();
    assert!(file.meta().orientation_predates_fitted_force());
    for mode in [DeformMode::Basis, DeformMode::Sh, DeformMode::Direct] {
        let err = LungGeometry::from_kernel(
            &file,
            mode,
            OrientationMethod::Exact,
            lung_model::orientation::DEFAULT_MIN_SLOPE_RATIO,
        )
        .err()
        .unwrap()
        .to_string();
        assert!(err.contains("bake it again"), "{mode}: {err}");
        let err = CpuLung::from_kernel(&file, mode).err().unwrap().to_string();
        assert!(err.contains("bake it again"), "{mode}: {err}");
    }
    assert!(LungGeometry::from_kernel(
        &file,
        DeformMode::Precomputed,
        OrientationMethod::Exact,
        lung_model::orientation::DEFAULT_MIN_SLOPE_RATIO,
    )
    .is_ok());
    let _ = std::fs::remove_dir_all(&dir);
}

// ---- A remote site breathing with the source's patient (issue 35; remote::RemoteLive) ----

/// The tidal volume the signal scenes' sites are measured against, ml (the default PV model's).
fn signal_tidal_ml() -> f64 {
    signal_core(50.0)
        .lung(Side::Right)
        .unwrap()
        .breathing()
        .boundary()
        .tv_ml
}

/// A source following `chest_mm` (cut over `cut`) for `seconds` and a site that gets each of its
/// states `delay` ticks late ([`super::sites::follow`]).
fn remote_follow(seconds: f64, delay: u64, cut: Option<(f64, f64)>) -> super::sites::SiteRun {
    let site = EngineCore::with_geometry(&Scene::default(), baked_geometry()).unwrap();
    super::sites::follow(
        signal_core(50.0),
        site,
        &mut |tick| signal_frame(tick, cut, &clean),
        (seconds * 60.0) as u64,
        delay,
        60.0,
    )
    .unwrap()
}

/// A source that follows the patient's live signal tells its sites the patient's breath: each site
/// plays the previous breath from the start of the one in progress and re-aligns at every breath,
/// so it breathes with the patient, not with the model; without it (the v3 states) a site breathed
/// the model's own clock while the source followed the patient. A loss at the source hands the
/// sites back to the model in step with the source's, bit for bit.
#[test]
fn a_site_breathes_with_the_sources_patient() {
    use super::sites::SiteRun;
    use ipc_types::engine_state as e;
    const DELAY: u64 = 6; // 100 ms: a slow network
    let run = remote_follow(75.0, DELAY, Some((50.0, 56.0)));
    let tidal = signal_tidal_ml();
    let live = run.states.iter().filter(|s| s.live.is_some()).count();
    assert!(live >= 8, "{live} states carried the patient's breath");
    let t = &run.ticks;
    let first = t
        .iter()
        .position(|r| r.site_state & e::SIGNAL_FOLLOWING != 0)
        .expect("the site follows the patient");
    // Over 30-50 s (the site follows from the first whole breath the source followed).
    let window = SiteRun {
        ticks: t[..50 * 60].to_vec(),
        states: Vec::new(),
        turn_lag: run.turn_lag,
    };
    // Each turn reached the site at least the delay after it happened, and within half a breath
    // (the follower's confirmation of the turn, then the delay).
    let lag = run.turn_lag;
    let mean = lag.mean_ms(60.0).unwrap();
    eprintln!(
        "turns heard {mean:.0} ms late on average, at most {} ticks ({lag:?})",
        lag.max_ticks
    );
    assert!(lag.turns >= 16, "{lag:?}");
    assert!(mean >= 100.0 && lag.max_ticks < 2 * 60, "{lag:?}");
    let f = super::sites::figures(&window, 30.0, 60.0);
    eprintln!(
        "site following from {:.1} s; 30-50 s: {f:?} ({:.1} % of {tidal:.0} ml against {:.1} % \
         without the patient's breath); {live} of {} states carried the breath",
        t[first].t_s,
        100.0 * f.rms_ml / tidal,
        100.0 * f.model_rms_ml / tidal,
        run.states.len()
    );
    // Measured (2026-12-07, each breath started on the patient's rhythm): following from 24.3 s;
    // RMS 26.0 ml (5.2 % of tidal) against 320 ml for the model's breath; lag 17 ms; largest step
    // 7.7 ml against the breath's own 7.1 ml; turns heard 641 ms late on average (the follower
    // confirms a smooth breath's turns late), 46 ticks at most. (2026-12-06, holding each breath's
    // end until the next start was heard: 44.8 ml, 9.0 %; lag 83 ms; largest step 23 ml, the
    // re-alignments faded over REALIGN_TICKS.)
    assert!(t[first].t_s < 25.0, "{}", t[first].t_s);
    assert_eq!(f.site_following, f.ticks);
    assert!(f.rms_ml < 0.15 * tidal, "RMS {:.1} ml", f.rms_ml);
    assert!(f.rms_ml * 3.0 < f.model_rms_ml, "{f:?}");
    assert!(f.lag_ms.abs() <= 150.0, "{f:?}");
    assert!(f.largest_step_ml < 5.0 * f.source_largest_step_ml, "{f:?}");
    // The loss at 50 s: the source's model carries on and so does the site's, the same volumes
    // once the state arrived (the loss is seen within 100 ms, then the delay).
    let lost: Vec<_> = t
        .iter()
        .filter(|r| r.t_s >= 50.0 + (12 + DELAY) as f64 / 60.0 && r.t_s < 56.0)
        .collect();
    assert!(lost.iter().all(|r| r.site_state & e::SIGNAL_FOLLOWING == 0));
    assert!(
        lost.iter()
            .all(|r| r.site_ml.to_bits() == r.source_ml.to_bits()),
        "the site's model is the source's during the loss"
    );
    // And it follows the patient again after.
    assert!(t.last().unwrap().site_state & e::SIGNAL_FOLLOWING != 0);
}

/// A site a second behind its source (a continent away, or a slow relay) hears each of the
/// patient's turns over a second late: it keeps the patient's rhythm by starting each breath when
/// the previous one has played out, instead of holding the breath's end until the next start is
/// heard (which made every breath start a second late there, and the site no closer to the patient
/// than the model's own breath on short breaths).
#[test]
fn a_site_a_second_behind_keeps_the_patients_rhythm() {
    const DELAY: u64 = 60; // 1 s
    let run = remote_follow(50.0, DELAY, None);
    let tidal = signal_tidal_ml();
    let window = super::sites::SiteRun {
        ticks: run.ticks.clone(),
        states: Vec::new(),
        turn_lag: run.turn_lag,
    };
    let f = super::sites::figures(&window, 30.0, 60.0);
    let mean = run.turn_lag.mean_ms(60.0).unwrap();
    eprintln!(
        "30-50 s, the site 1 s behind: {f:?} ({:.1} % of {tidal:.0} ml against {:.1} % without the \
         patient's breath); turns heard {mean:.0} ms late",
        100.0 * f.rms_ml / tidal,
        100.0 * f.model_rms_ml / tidal,
    );
    // Measured (2026-12-07): 29.4 ml (5.9 % of 500 ml) against 320 ml for the model's breath,
    // lag 0 ms; turns heard 1527 ms late. Holding each breath's end until the next start was
    // heard instead: 159.8 ml (32.0 %), lag 550 ms.
    assert!(mean >= 1000.0, "turns heard {mean:.0} ms late");
    assert_eq!(f.site_following, f.ticks);
    assert!(f.rms_ml * 3.0 < f.model_rms_ml, "{f:?}");
    assert!(f.rms_ml < 0.15 * tidal, "RMS {:.1} ml", f.rms_ml);
    assert!(f.lag_ms.abs() <= 150.0, "{f:?}");
}

/// When the patient stops breathing (an apnoea from an end-expiration), a site predicting the
/// next breath on the rhythm must not draw a breath the patient never took: a breath started on
/// rhythm would have been heard within the site's usual lag, so the prediction is taken back
/// within that lag and 200 ms, and the site holds at the breath's end as the source does.
#[test]
fn a_site_takes_back_a_breath_the_patient_did_not_start() {
    const DELAY: u64 = 6; // 100 ms
    let apnoea_s = 9.0 * 4.7; // an end-expiration of `chest_mm`
    let apnoea = move |_: u64, t_s: f64| (if t_s < apnoea_s { chest_mm(t_s) } else { 0.0 }, true);
    let site = EngineCore::with_geometry(&Scene::default(), baked_geometry()).unwrap();
    let run = super::sites::follow(
        signal_core(50.0),
        site,
        &mut |tick| signal_frame(tick, None, &apnoea),
        (55.0 * 60.0) as u64,
        DELAY,
        60.0,
    )
    .unwrap();
    let tidal = signal_tidal_ml();
    let slowest = run.turn_lag.max_ticks as f64 / 60.0;
    // The breath predicted from the rhythm starts near the apnoea's start (the last breath's
    // length after the last start) and is taken back once the slowest lag and 200 ms have passed
    // without it heard, over 200 ms more (measured 2026-12-07: up to 311 ml at 43.5 s, back at the
    // breath's end, 22 ml above the source's, from 43.8 s; turns heard up to 0.73 s late). Without
    // the taking back the site drew the whole breath, to 47 s.
    let back_s = apnoea_s + slowest + 1.0;
    let after: Vec<_> = run.ticks.iter().filter(|r| r.t_s >= back_s).collect();
    assert!(
        after
            .iter()
            .all(|r| r.site_state & ipc_types::engine_state::SIGNAL_FOLLOWING != 0),
        "the site follows the patient's breath through the apnoea (not its model)"
    );
    assert!(slowest < 1.5, "turns heard up to {slowest:.2} s late");
    assert!(after.len() > 60 * 8);
    let worst = after
        .iter()
        .map(|r| (r.site_ml - r.source_ml).abs())
        .fold(0.0, f64::max);
    eprintln!(
        "apnoea from {apnoea_s:.1} s: after {back_s:.1} s the site within {worst:.1} ml of the \
         source (tidal {tidal:.0} ml); turns heard up to {slowest:.2} s late"
    );
    assert!(
        worst < 0.05 * tidal,
        "the site {worst:.1} ml from the source"
    );
}

/// A site that joins late, mid-breath (a colleague opening `lungdyn remote join` well into a
/// session), first hears the breath in progress, whose turns are long past: it follows the patient
/// from the tick it joins, and that breath's lag is no measure of how late turns arrive — an apnoea
/// from the second breath start after it joined (6.9 s later) is taken back as promptly as at a
/// site that was there from the start.
#[test]
fn a_site_joining_late_follows_at_once_and_keeps_its_patience() {
    use ipc_types::engine_state::SIGNAL_FOLLOWING;
    const DELAY: u64 = 6; // 100 ms
    let apnoea_s = 9.0 * 4.7; // an end-expiration of `chest_mm`
    let join_s = 7.0 * 4.7 + 2.5; // 2.5 s into a breath, 7 s before the apnoea
    let apnoea = move |_: u64, t_s: f64| (if t_s < apnoea_s { chest_mm(t_s) } else { 0.0 }, true);
    let run = |join_tick: u64| {
        let site = EngineCore::with_geometry(&Scene::default(), baked_geometry()).unwrap();
        super::sites::follow_joining(
            signal_core(50.0),
            site,
            &mut |tick| signal_frame(tick, None, &apnoea),
            (55.0 * 60.0) as u64,
            DELAY,
            join_tick,
            60.0,
        )
        .unwrap()
    };
    let (early, late) = (run(0), run((join_s * 60.0) as u64));
    let tidal = signal_tidal_ml();
    let following = |r: &super::sites::SiteTick| r.site_state & SIGNAL_FOLLOWING != 0;
    let joined_at = late
        .ticks
        .iter()
        .find(|r| r.t_s >= join_s && following(r))
        .expect("the late site follows the patient")
        .t_s;
    // Until the apnoea, from a breath after joining: as close to the source as the early site.
    let rms = |run: &super::sites::SiteRun| {
        let w: Vec<_> = run
            .ticks
            .iter()
            .filter(|r| r.t_s >= join_s + 4.7 && r.t_s < apnoea_s)
            .map(|r| (r.site_ml - r.source_ml).powi(2))
            .collect();
        (w.iter().sum::<f64>() / w.len() as f64).sqrt()
    };
    // After the apnoea: both back at the breath's end by the time the early site is.
    let back_s = apnoea_s + early.turn_lag.max_ticks as f64 / 60.0 + 1.0;
    let worst = |run: &super::sites::SiteRun| {
        run.ticks
            .iter()
            .filter(|r| r.t_s >= back_s)
            .map(|r| (r.site_ml - r.source_ml).abs())
            .fold(0.0, f64::max)
    };
    eprintln!(
        "joined at {join_s:.1} s, following from {joined_at:.2} s; RMS to the apnoea {:.1} ml late, \
         {:.1} ml early; after {back_s:.1} s within {:.1} ml late, {:.1} ml early (tidal \
         {tidal:.0} ml)",
        rms(&late),
        rms(&early),
        worst(&late),
        worst(&early)
    );
    assert!(
        joined_at - join_s < 0.5,
        "following {:.2} s after joining",
        joined_at - join_s
    );
    assert!(rms(&late) < 0.15 * tidal && rms(&late) < 1.5 * rms(&early) + 5.0);
    assert!(
        worst(&late) < 0.05 * tidal,
        "the late site {:.1} ml from the source",
        worst(&late)
    );
}

/// A source whose signal looks clipped tells its sites (control-state v5): their frames say so
/// as the source's do, from the next state it sends, and stop saying so when the source does (the
/// sensor's range widened: the cut ends at 130 s); sites of the same breaths uncut never do.
#[test]
fn a_site_says_so_when_the_sources_signal_looks_clipped() {
    use ipc_types::engine_state::{SIGNAL_CLIPPED, SIGNAL_FOLLOWING};
    const DELAY: u64 = 6; // 100 ms
    let run = |ceiling: f64| {
        let site = EngineCore::with_geometry(&Scene::default(), baked_geometry()).unwrap();
        let (cut, free) = (belt(ceiling), belt(f64::INFINITY));
        let b = move |tick: u64, t_s: f64| {
            if t_s < 130.0 {
                cut(tick, t_s)
            } else {
                free(tick, t_s)
            }
        };
        super::sites::follow(
            signal_core(50.0),
            site,
            &mut |tick| signal_frame(tick, None, &b),
            220 * 60,
            DELAY,
            60.0,
        )
        .unwrap()
    };
    let cut = run(12.0);
    let flagged = |bits: &dyn Fn(&super::sites::SiteTick) -> u32| {
        let on = |r: &&super::sites::SiteTick| bits(r) & SIGNAL_CLIPPED != 0;
        let t = &cut.ticks;
        (
            t.iter().position(|r| on(&r)),
            t.iter().rposition(|r| on(&r)),
        )
    };
    let (Some(source), Some(source_end)) = flagged(&|r| r.source_state) else {
        panic!("the source sees the clipping")
    };
    let (Some(site), Some(site_end)) = flagged(&|r| r.site_state) else {
        panic!("the site is told")
    };
    eprintln!(
        "the source says clipped from {:.1} to {:.1} s, the site from {:.1} to {:.1} s",
        source as f64 / 60.0,
        source_end as f64 / 60.0,
        site as f64 / 60.0,
        site_end as f64 / 60.0
    );
    // With the next state: at the patient's next turn (half a breath at most), then the delay.
    let told = |from: usize, to: usize| to >= from + DELAY as usize && to - from <= 3 * 60;
    assert!(told(source, site), "from {source} {site}");
    assert!(told(source_end, site_end), "to {source_end} {site_end}");
    assert!(cut.ticks[site..=site_end]
        .iter()
        .all(|r| r.site_state & SIGNAL_CLIPPED != 0 && r.site_state & SIGNAL_FOLLOWING != 0));
    assert!(site_end < cut.ticks.len() - 60 * 10, "cleared at the end");
    let uncut = run(f64::INFINITY);
    assert!(uncut
        .ticks
        .iter()
        .all(|r| r.site_state & SIGNAL_CLIPPED == 0));
    assert!(uncut
        .ticks
        .iter()
        .any(|r| r.site_state & SIGNAL_FOLLOWING != 0));
}

/// The site's breath is a pure function of the states and the ticks they arrive at: twice the same.
#[test]
fn a_sites_live_breath_replays_bitwise() {
    let (a, b) = (remote_follow(30.0, 3, None), remote_follow(30.0, 3, None));
    assert!(a.ticks.iter().zip(&b.ticks).all(|(x, y)| {
        x.site_ml.to_bits() == y.site_ml.to_bits() && x.site_state == y.site_state
    }));
}

/// While the bridge learns a chest tool's axis (`tool:NAME:auto`) it sends no samples and says it
/// learns: the engine shows the model "learning", counted as calibrating, never as a loss (no veil);
/// once samples come, it follows as any signal.
#[test]
fn a_chest_axis_being_learnt_is_shown_as_learning_not_as_a_loss() {
    use ipc_types::engine_state as e;
    let mut core = signal_core(50.0);
    let mut f = EngineFrame::default();
    let learn_ticks = 12 * 60;
    for tick in 0..learn_ticks {
        let mut input = signal_frame(tick, None, &clean);
        input.signal.count = 0;
        input.signal.valid_mask = 0;
        input.signal.status |= ipc_types::signal_status::LEARNING;
        core.step(tick, Some(&input), &mut f);
        assert_eq!(
            f.state & (e::SIGNAL_CALIBRATING | e::SIGNAL_LEARNING | e::SIGNAL_LOST),
            e::SIGNAL_CALIBRATING | e::SIGNAL_LEARNING,
            "tick {tick}"
        );
    }
    let t = core.signal().unwrap().ticks();
    assert_eq!((t.calibrating, t.lost), (learn_ticks, 0));
    // Then the samples come: no longer learning, and following within three breaths.
    let mut following = None;
    for tick in learn_ticks..learn_ticks + 30 * 60 {
        core.step(tick, Some(&signal_frame(tick, None, &clean)), &mut f);
        assert_eq!(f.state & e::SIGNAL_LEARNING, 0);
        if f.state & e::SIGNAL_FOLLOWING != 0 && following.is_none() {
            following = Some(tick);
        }
    }
    assert!(following.is_some());
}

/// A disease course acts on the patient's own breaths (issue 35 item 4, EQUATIONS.md §4.7's
/// reading): with the signal driving both lungs of a tension pneumothorax, the lungs share the
/// patient's volume change by their cycles' tidal volumes — tick by tick the two lungs' changes
/// stand as their tidal volumes do (as their shares before the course takes anything) — and
/// together still take the whole of it. Checked to fail with the signal shared by the shares alone.
#[test]
fn a_pneumothorax_shares_the_patients_signal_by_the_lungs_tidal_volumes() {
    let text = "[lungs]\nsides = [\"right\", \"left\"]\n[breathing]\nsource = \"signal\"\n\
                signal = \"trace:unused-by-the-engine\"\n[disease]\nkind = \"tension-pneumothorax\"\n\
                side = \"left\"\nonset_s = 2.0\nv_p_ml = 40.0\n";
    let mut core = diseased_core(text);
    let shares: Vec<f64> = {
        let frc: f64 = core.geometry().map(|g| g.start_volume_ml).sum();
        [Side::Right, Side::Left]
            .iter()
            .map(|&s| {
                core.geometry()
                    .find(|g| g.side == s)
                    .unwrap()
                    .start_volume_ml
                    / frc
            })
            .collect()
    };
    let mut f = EngineFrame::default();
    let mut last: Option<(f32, f32, f32)> = None;
    let (mut checked, mut reduced, mut run) = (0, 0, 0u64);
    for tick in 0..(90 * 60) {
        core.step(tick, Some(&signal_frame(tick, None, &clean)), &mut f);
        core.prepare_ahead().unwrap();
        let (r, l) = (&f.lungs[ipc_types::LUNG_RIGHT], &f.lungs[LUNG_LEFT]);
        assert!(r.volume_ml.is_finite() && l.volume_ml.is_finite());
        // Past the takeover's blend from the model's breath (half a second).
        run = if f.state & ipc_types::engine_state::SIGNAL_FOLLOWING != 0 {
            run + 1
        } else {
            0
        };
        let following = run > 60;
        let changed = (r.flags | l.flags) & (lung_flags::CYCLE_CHANGED | lung_flags::HELD) != 0;
        if let (Some((r0, l0, s0)), true, false) = (last, following, changed) {
            let (dr, dl) = (f64::from(r.volume_ml - r0), f64::from(l.volume_ml - l0));
            // Past the takeover's blend, the lungs together take the signal's whole change.
            let ds = f64::from(f.signal.volume_ml - s0);
            if ds.abs() > 0.5 {
                assert!(
                    (dr + dl - ds).abs() < 0.01 * ds.abs() + 0.01,
                    "tick {tick}: the lungs moved {:.3} ml together, the signal {ds:.3} ml",
                    dr + dl
                );
            }
            if dr.abs() > 0.5 {
                let want = f64::from(l.tidal_ml) / f64::from(r.tidal_ml);
                assert!(
                    (dl / dr - want).abs() < 0.01 * want,
                    "tick {tick}: the lungs moved {dl:.3} / {dr:.3} ml (tidal {} / {}), their tidal volumes \
                     stand at {want:.4}", l.tidal_ml, r.tidal_ml
                );
                checked += 1;
                if want < 0.9 * shares[1] / shares[0] {
                    reduced += 1;
                }
            }
        }
        last = Some((r.volume_ml, l.volume_ml, f.signal.volume_ml));
    }
    assert!(checked > 1000, "{checked} ticks compared");
    assert!(
        reduced > 500,
        "the course reduced the left lung's breath on {reduced} ticks"
    );
}
