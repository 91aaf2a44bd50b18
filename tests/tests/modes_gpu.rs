//! The four deformation modes on the GPU against their CPU reference (lavapipe in CI): for coefficients
//! the engine produces at extreme patient orientations, the GPU's deformed positions and vertex
//! normals agree with `lung_model::deform::modes::CpuLung` within 1e-4 relative; and each mode loads
//! only the kernel sections it needs (a precomputed scene never reads the transfer rows).

use engine::runtime::{EngineCore, LungGeometry};
use glam::{DMat3, DQuat, DVec3};
use ipc_types::LUNG_LEFT;
use ipc_types::{EngineFrame, Pose, ToolPose, TrackerFrame, LAYOUT_VERSION, TOOL_PATIENT};
use lung_model::deform::modes::{CpuLung, DeformMode};
use lung_model::kernel::section;
use lung_model::scene::Scene;
use lung_model::scene::SceneExt;
use renderer::gpu::Gpu;
use renderer::{DrawState, LungRenderer, RenderLung};

fn supine() -> DQuat {
    DQuat::from_mat3(&DMat3::from_cols(DVec3::Y, DVec3::Z, DVec3::X))
}

fn posed(n: u64, q: DQuat) -> TrackerFrame {
    let mut f = TrackerFrame {
        layout_version: LAYOUT_VERSION,
        tool_count: 2,
        frame_number: n,
        ..Default::default()
    };
    f.tools[TOOL_PATIENT] = ToolPose {
        tool_id: 1,
        status: ipc_types::tool_status::VALID,
        pose: Pose {
            quat: q.to_array().map(|v| v as f32),
            translation_mm: [0.0, 0.0, 1120.0],
            _pad: 0,
        },
        rms_error_mm: 0.2,
        _pad: 0,
    };
    f
}

fn scene(mode: DeformMode) -> Scene {
    let mut s = Scene::default();
    s.lungs.vertices = 2500;
    s.lungs.mode = mode;
    s.render.width = 96;
    s.render.height = 72;
    s
}

/// An engine over `kernels` in `mode` (the scene's orientation settings).
fn engine_over(
    scene: &Scene,
    kernels: &[lung_model::kernel::KernelFile],
    mode: DeformMode,
) -> EngineCore {
    let geometry = kernels
        .iter()
        .map(|k| {
            LungGeometry::from_kernel(
                k,
                mode,
                scene.engine.orientation,
                scene.engine.min_slope_ratio,
            )
            .unwrap()
        })
        .collect();
    EngineCore::with_geometry(scene, geometry).unwrap()
}

/// The scene's kernels and the lungs the renderer loads from them in `mode`.
fn loaded(
    scene: &Scene,
    mode: DeformMode,
) -> (Vec<lung_model::kernel::KernelFile>, Vec<RenderLung>) {
    let kernels: Vec<_> = scene
        .lungs
        .sides
        .iter()
        .map(|&s| scene.lung_kernel(s).unwrap())
        .collect();
    let lungs = kernels
        .iter()
        .map(|k| RenderLung::from_kernel(k, mode).unwrap())
        .collect();
    (kernels, lungs)
}

/// The patient supine, turned 90° about two axes, and prone.
const TURNS: [fn() -> DQuat; 4] = [
    || DQuat::IDENTITY,
    || DQuat::from_rotation_x(std::f64::consts::FRAC_PI_2),
    || DQuat::from_rotation_y(-std::f64::consts::FRAC_PI_2),
    || DQuat::from_rotation_x(std::f64::consts::PI),
];

/// What the renderer draws for engine frame `f`: its scales and coefficients, no offset, no
/// collapse, the patient's pose for both poses.
fn drawn_from(f: &EngineFrame) -> DrawState {
    let mut state = DrawState {
        deform_scale: [0.0; 2],
        offset_mm: [[0.0; 3]; 2],
        collapse: [0.0; 2],
        hilum_mm: [[0.0; 3]; 2],
        coeffs: [[0.0; ipc_types::MAX_COEFFS]; 2],
        patient: f.patient_pose,
        hmd: f.patient_pose,
        pose_warning: Default::default(),
    };
    for slot in 0..2 {
        state.deform_scale[slot] = f.lungs[slot].deform_scale;
        state.coeffs[slot] = f.lungs[slot].coeffs;
    }
    state
}

#[test]
fn every_mode_on_the_gpu_matches_the_cpu_reference_at_extreme_orientations() {
    let Some(gpu) = Gpu::for_tests() else { return };
    let base = lungdyn_tests::scene_with_kernels(scene(DeformMode::Basis), "modes-gpu");
    for mode in DeformMode::ALL {
        let mut scene = base.clone();
        scene.lungs.mode = mode;
        let (kernels, lungs) = loaded(&scene, mode);
        // Only what the mode needs was read.
        for k in &kernels {
            let read = |kind| k.is_verified(kind);
            assert_eq!(
                read(section::VALS),
                mode == DeformMode::Direct,
                "{mode}: transfer rows"
            );
            assert_eq!(
                read(section::SH),
                mode == DeformMode::Sh,
                "{mode}: SH section"
            );
            assert_eq!(
                read(section::BASIS),
                mode == DeformMode::Basis,
                "{mode}: basis section"
            );
        }
        let r = LungRenderer::new(&gpu, &scene.render, &lungs).unwrap();
        let mut core = engine_over(&scene, &kernels, mode);
        let mut cpus: Vec<CpuLung> = lungs.iter().map(|l| l.lung.clone()).collect();
        let mut f = EngineFrame::default();
        for (k, turn) in TURNS.iter().enumerate() {
            let tick = 120 + 300 * k as u64;
            core.step(tick, Some(&posed(tick, turn() * supine())), &mut f);
            let mut state = drawn_from(&f);
            for slot in 0..2 {
                state.offset_mm[slot] = [1.5 * slot as f32, -2.0, 0.25];
            }
            r.render(&gpu, &state, false);
            let positions = r.read_deformed(&gpu).unwrap();
            let normals = r.read_normals(&gpu).unwrap();
            let mut at = 0;
            let (mut worst_p, mut worst_n) = (0.0f32, 0.0f32);
            for (lung, cpu) in lungs.iter().zip(&mut cpus) {
                let slot = lung.side.index();
                let l = &f.lungs[slot];
                let mut out = vec![[0.0f32; 3]; cpu.len()];
                cpu.deform_into(
                    l.deform_scale,
                    &l.coeffs[..l.coeff_count as usize],
                    state.offset_mm[slot],
                    &mut out,
                )
                .unwrap();
                let mut n = vec![[0.0f32; 3]; cpu.len()];
                cpu.normals_into(&out, &mut n);
                for i in 0..cpu.len() {
                    let g = positions[at + i];
                    assert!(g.iter().all(|v| v.is_finite()), "{mode}: NaN on the GPU");
                    for a in 0..3 {
                        let rel = (g[a] - out[i][a]).abs() / out[i][a].abs().max(1.0);
                        worst_p = worst_p.max(rel);
                        worst_n = worst_n.max((normals[at + i][a] - n[i][a]).abs());
                    }
                }
                at += cpu.len();
            }
            assert!(
                worst_p <= 1e-4,
                "{mode} turn {k}: positions differ by {worst_p:e} relative"
            );
            assert!(
                worst_n <= 1e-3,
                "{mode} turn {k}: normals differ by {worst_n:e}"
            );
            if k + 1 < TURNS.len() {
                continue;
            }
            // A pneumothorax's collapse towards the hilum (EQUATIONS.md §4.1), left lung only:
            // h + (1 − c)(p − h) + s·u + o = (drawn without collapse) + c·(h − p), p the rest
            // position (drawn at scale 0, offset 0); the right lung is untouched.
            let breathing = positions;
            let mut rest = state;
            rest.deform_scale = [0.0; 2];
            rest.offset_mm = [[0.0; 3]; 2];
            r.render(&gpu, &rest, false);
            let p = r.read_deformed(&gpu).unwrap();
            let (c, h) = (0.3f32, [-40.0f32, 10.0, 120.0]);
            let mut collapsed = state;
            collapsed.collapse[LUNG_LEFT] = c;
            collapsed.hilum_mm[LUNG_LEFT] = h;
            r.render(&gpu, &collapsed, false);
            let got = r.read_deformed(&gpu).unwrap();
            let mut at = 0;
            let mut worst = 0.0f32;
            for lung in &lungs {
                let n = lung.lung.len();
                for i in at..at + n {
                    for a in 0..3 {
                        let want = if lung.side.index() == LUNG_LEFT {
                            breathing[i][a] + c * (h[a] - p[i][a])
                        } else {
                            breathing[i][a]
                        };
                        worst = worst.max((got[i][a] - want).abs() / want.abs().max(1.0));
                    }
                }
                at += n;
            }
            assert!(
                worst <= 1e-5,
                "{mode}: collapse differs by {worst:e} relative"
            );
        }
    }
}

/// The SH mode's 16-bit coefficients on the GPU (`snorm16` pairs with a zero pad after an odd count)
/// against the CPU's blocks of eight, for 1, 9 and 49 coefficients per vertex and the two lungs at
/// different counts, with coefficients of both signs and a lung whose vertex count is not a
/// multiple of eight.
#[test]
fn sh_coefficients_held_in_16_bits_agree_on_gpu_and_cpu_at_odd_counts() {
    use lung_model::deform::modes::{ModeData, ShCoeffs};
    use lung_model::mesh::{generate, Side};
    let Some(gpu) = Gpu::for_tests() else { return };
    let values = |n: usize, seed: u64| -> Vec<f32> {
        use rand::{RngExt, SeedableRng};
        let mut r = rand_xorshift::XorShiftRng::seed_from_u64(seed);
        (0..n).map(|_| r.random_range(-1.0f32..1.0)).collect()
    };
    let render = scene(DeformMode::Sh).render;
    for (n_right, n_left) in [(1usize, 9usize), (9, 49), (49, 16)] {
        let lungs: Vec<RenderLung> = [(Side::Right, n_right, 1203), (Side::Left, n_left, 1100)]
            .into_iter()
            .map(|(side, n, vertices)| {
                let mesh = generate::lung(side, vertices).unwrap();
                let v = mesh.positions.len();
                let kd: Vec<[f32; 3]> = values(3 * v, 7 + n as u64)
                    .chunks_exact(3)
                    .map(|c| [c[0] * 0.01, c[1] * 0.01, c[2] * 0.01])
                    .collect();
                let t = values(n * v, 3 + n as u64);
                RenderLung {
                    side,
                    kernel_id: 0,
                    lung: CpuLung::new(
                        mesh,
                        kd,
                        ModeData::Sh {
                            t: ShCoeffs::quantise(n, &t).unwrap(),
                        },
                    ),
                    tumour: None,
                    lobes: None,
                }
            })
            .collect();
        assert!(
            lungs.iter().any(|l| l.lung.len() % 8 != 0),
            "a tail block is exercised"
        );
        let r = LungRenderer::new(&gpu, &render, &lungs).unwrap();
        let mut state = DrawState {
            deform_scale: [1.3, 0.7],
            offset_mm: [[0.5, -1.0, 2.0], [0.0; 3]],
            collapse: [0.0; 2],
            hilum_mm: [[0.0; 3]; 2],
            // Past each lung's count: NaN, which the host must not pass on (it zeroes those).
            coeffs: [[f32::NAN; ipc_types::MAX_COEFFS]; 2],
            patient: Default::default(),
            hmd: Default::default(),
            pose_warning: Default::default(),
        };
        for l in &lungs {
            let slot = l.side.index();
            let n = l.lung.coeff_count();
            state.coeffs[slot][..n].copy_from_slice(&values(n, 11 + slot as u64));
        }
        r.render(&gpu, &state, false);
        let positions = r.read_deformed(&gpu).unwrap();
        let mut at = 0;
        for l in &lungs {
            let slot = l.side.index();
            let n = l.lung.coeff_count();
            let mut cpu = l.lung.clone();
            let mut out = vec![[0.0f32; 3]; cpu.len()];
            cpu.deform_into(
                state.deform_scale[slot],
                &state.coeffs[slot][..n],
                state.offset_mm[slot],
                &mut out,
            )
            .unwrap();
            assert!(
                positions[at..at + cpu.len()]
                    .iter()
                    .flatten()
                    .all(|v| v.is_finite()),
                "{n} coefficients: NaN on the GPU"
            );
            let mut worst = 0.0f32;
            let mut moved = 0.0f32;
            for (i, o) in out.iter().enumerate() {
                let g = positions[at + i];
                for a in 0..3 {
                    worst = worst.max((g[a] - o[a]).abs() / o[a].abs().max(1.0));
                    moved = moved.max((o[a] - l.lung.positions[i][a]).abs());
                }
            }
            assert!(
                moved > 1e-3,
                "{n} coefficients: the lung moved ({moved} mm)"
            );
            assert!(
                worst <= 1e-5,
                "{n} coefficients ({:?}): GPU and CPU differ by {worst:e} relative",
                l.side
            );
            at += cpu.len();
        }
    }
}

/// The governor's "drawn vertices only" (`renderer::governor::Step::DrawnOnly`) in every mode:
/// each vertex of the level drawn lands where the full pass puts it, bit for bit; its normal (and
/// the ventilation colour's expansion) comes from that level's triangles; no other vertex is
/// touched; and the full quality moves every vertex again in its first frame.
#[test]
fn drawn_vertices_only_moves_the_drawn_levels_vertices_exactly_and_nothing_else() {
    use lung_model::scene::ColorMode;
    use renderer::deform::Incidence;
    use renderer::governor::{Quality, Step};
    use renderer::lod;
    let Some(gpu) = Gpu::for_tests() else { return };
    let base = lungdyn_tests::scene_with_kernels(scene(DeformMode::Basis), "modes-gpu-drawn");
    for mode in DeformMode::ALL {
        let mut scene = base.clone();
        scene.lungs.mode = mode;
        // One mode with the expansion field in each normal's w.
        if mode == DeformMode::Basis {
            scene.render.color = ColorMode::Ventilation;
        }
        let lungs: Vec<RenderLung> = scene
            .lungs
            .sides
            .iter()
            .map(|&s| RenderLung::from_kernel(&scene.lung_kernel(s).unwrap(), mode).unwrap())
            .collect();
        let mut r = LungRenderer::new(&gpu, &scene.render, &lungs).unwrap();
        assert!(
            r.governor_steps().contains(&Step::DrawnOnly),
            "{mode}: the ladder has the step"
        );
        let count = r.vertex_count() as usize;
        // At rest (scale 0), and a breath: scales, offsets, coefficients of both signs, the left
        // lung collapsing towards its hilum.
        let rest_state = DrawState {
            deform_scale: [0.0; 2],
            offset_mm: [[0.0; 3]; 2],
            collapse: [0.0, 0.2],
            hilum_mm: [[0.0; 3], [-40.0, 10.0, 120.0]],
            coeffs: [[0.0; ipc_types::MAX_COEFFS]; 2],
            patient: Default::default(),
            hmd: Default::default(),
            pose_warning: Default::default(),
        };
        let mut breath = rest_state;
        for l in &lungs {
            let s = l.side.index();
            breath.deform_scale[s] = 1.5 + 0.25 * s as f32;
            breath.offset_mm[s] = [1.0, -2.0, 0.5 * s as f32];
            for k in 0..l.lung.coeff_count().min(ipc_types::MAX_COEFFS) {
                breath.coeffs[s][k] = [0.9, -0.4, 0.3, 0.7][k % 4] / (1.0 + k as f32);
            }
        }
        r.render(&gpu, &rest_state, false);
        let rest = r.read_deformed(&gpu).unwrap();
        r.render(&gpu, &breath, false);
        let full = r.read_deformed(&gpu).unwrap();
        assert!(
            (0..count).any(|i| full[i] != rest[i]),
            "{mode}: the breath moves the lungs"
        );
        // Back to rest, then the breath with the drawn level's vertices only, at the coarsest.
        r.render(&gpu, &rest_state, false);
        r.set_quality(Quality {
            lod_bias: 7,
            drawn_only: true,
            ..Quality::FULL
        });
        r.render(&gpu, &breath, false);
        let level = r.lod_shown().level as usize;
        assert!(level >= 1, "{mode}: a coarser level is drawn");
        let listed = r.read_deformed(&gpu).unwrap();
        let normals = r.read_normals(&gpu).unwrap();
        // The level's triangles as the renderer builds them.
        let per_lung: Vec<_> = lungs
            .iter()
            .map(|l| {
                lod::lung_levels(
                    &l.lung.positions,
                    &l.lung.triangles,
                    lung_model::scene::MAX_LOD_LEVEL,
                )
                .levels
            })
            .collect();
        let counts: Vec<u32> = lungs.iter().map(|l| l.lung.len() as u32).collect();
        let levels = lod::Levels::join(&per_lung, &counts);
        let range = levels.ranges[level].clone();
        let indices = &levels.indices[range.start as usize..range.end as usize];
        // The rest areas are the FRC surface's (the lungs' own positions, no collapse).
        let rest_xyz: Vec<[f32; 3]> = lungs
            .iter()
            .flat_map(|l| l.lung.positions.iter().copied())
            .collect();
        let inc = Incidence::of_level(indices, &rest_xyz);
        assert_eq!(r.vertices_moved() as usize, inc.vertices.len(), "{mode}");
        assert!(
            inc.vertices.len() * 2 < count,
            "{mode}: level {level} uses {} of {count} vertices",
            inc.vertices.len()
        );
        let mut drawn = vec![false; count];
        for &v in &inc.vertices {
            drawn[v as usize] = true;
        }
        for i in 0..count {
            let want = if drawn[i] { full[i] } else { rest[i] };
            assert!(
                listed[i].map(f32::to_bits) == want.map(f32::to_bits),
                "{mode}: vertex {i} (drawn {}) at {:?}, want {want:?}",
                drawn[i],
                listed[i]
            );
        }
        let (mut worst_n, mut worst_field) = (0.0f32, 0.0f32);
        for (g, &v) in inc.vertices.iter().enumerate() {
            let (mut n, mut area2) = (glam::Vec3::ZERO, 0.0f32);
            for &t in &inc.tris[inc.ptr[g] as usize..inc.ptr[g + 1] as usize] {
                let c = &indices[3 * t as usize..3 * t as usize + 3];
                let [a, b, d] =
                    [c[0], c[1], c[2]].map(|i| glam::Vec4::from(full[i as usize]).truncate());
                let x = (b - a).cross(d - a);
                n += x;
                area2 += x.length();
            }
            let got = glam::Vec4::from(normals[v as usize]);
            worst_n = worst_n.max((got.truncate() - n.normalize()).abs().max_element());
            if mode == DeformMode::Basis {
                let want = (0.5 * area2 / inc.rest_area[g]).powf(1.5) - 1.0;
                worst_field = worst_field.max((got.w - want).abs() / want.abs().max(0.01));
            }
        }
        assert!(
            worst_n <= 1e-3,
            "{mode}: level normals differ by {worst_n:e}"
        );
        assert!(
            worst_field <= 1e-3,
            "{mode}: expansion differs by {worst_field:e}"
        );
        // Everything back: the first frame at full quality moves every vertex again.
        r.set_quality(Quality::FULL);
        r.render(&gpu, &breath, false);
        assert_eq!(r.vertices_moved() as usize, count);
        let again = r.read_deformed(&gpu).unwrap();
        for i in 0..count {
            assert!(
                again[i].map(f32::to_bits) == full[i].map(f32::to_bits),
                "{mode}: vertex {i} after the full quality came back"
            );
        }
    }
}

/// The governor's accuracy step (`renderer::governor::Step::ShBands`, where a scene sets
/// `[render] governor_least_bands`): with the spherical harmonics capped at b bands the GPU moves
/// every vertex exactly as the full pass does with the engine's force coefficients past b² dropped
/// (bit for bit), and not as the full pass does; with the cap lifted it is the full pass again.
/// Prints what each cap moves the vertices by, for engine frames at mid-inspiration and the peak
/// in four orientations (docs/LATENCY.md "The accuracy opt-in").
#[test]
fn capped_bands_deform_as_the_full_pass_with_the_higher_bands_force_dropped() {
    use renderer::governor::{Quality, Step};
    let Some(gpu) = Gpu::for_tests() else { return };
    let mut scene = scene(DeformMode::Sh);
    scene.lungs.bands = 8;
    let mut scene = lungdyn_tests::scene_with_kernels(scene, "modes-gpu-bands");
    scene.render.governor_least_bands = Some(1);
    let (kernels, lungs) = loaded(&scene, DeformMode::Sh);
    assert!(lungs.iter().all(|l| l.lung.coeff_count() == 64), "8 bands");
    let mut r = LungRenderer::new(&gpu, &scene.render, &lungs).unwrap();
    let caps: Vec<u8> = r
        .governor_steps()
        .iter()
        .filter_map(|s| match s {
            Step::ShBands(b) => Some(*b),
            _ => None,
        })
        .collect();
    assert_eq!(caps, [7, 6, 5, 4, 3, 2, 1], "the ladder's band steps");
    let mut core = engine_over(&scene, &kernels, DeformMode::Sh);
    let mut f = EngineFrame::default();
    // Per cap: the largest and the sum of squares of the move from the full pass, mm.
    let mut cost = [(0.0f64, 0.0f64, 0usize); 9];
    for (k, turn) in TURNS.iter().enumerate() {
        for tick in [60 + 300 * k as u64, 120 + 300 * k as u64] {
            core.step(tick, Some(&posed(tick, turn() * supine())), &mut f);
            let state = drawn_from(&f);
            r.set_quality(Quality::FULL);
            r.render(&gpu, &state, false);
            let full = r.read_deformed(&gpu).unwrap();
            for &b in &caps {
                r.set_quality(Quality {
                    sh_bands: b,
                    ..Quality::FULL
                });
                r.render(&gpu, &state, false);
                let capped = r.read_deformed(&gpu).unwrap();
                let mut dropped = state;
                for c in &mut dropped.coeffs {
                    c[usize::from(b) * usize::from(b)..].fill(0.0);
                }
                r.set_quality(Quality::FULL);
                r.render(&gpu, &dropped, false);
                let want = r.read_deformed(&gpu).unwrap();
                assert!(
                    capped == want,
                    "tick {tick}, {b} bands: the capped pass is not the full pass with the higher \
                     bands' force dropped"
                );
                let moved: Vec<f64> = capped
                    .iter()
                    .zip(&full)
                    .map(|(a, c)| {
                        (0..3)
                            .map(|i| (f64::from(a[i]) - f64::from(c[i])).powi(2))
                            .sum::<f64>()
                            .sqrt()
                    })
                    .collect();
                let e = &mut cost[usize::from(b)];
                e.0 = moved.iter().copied().fold(e.0, f64::max);
                e.1 += moved.iter().map(|m| m * m).sum::<f64>();
                e.2 += moved.len();
            }
            r.set_quality(Quality::FULL);
            r.render(&gpu, &state, false);
            assert!(
                r.read_deformed(&gpu).unwrap() == full,
                "tick {tick}: the cap lifted is the full pass again"
            );
        }
    }
    for &b in &caps {
        let (max, sum, n) = cost[usize::from(b)];
        let rms = (sum / n as f64).sqrt();
        eprintln!(
            "SH capped at {b} of 8 bands: vertices move {rms:.3} mm RMS, {max:.3} mm at most from \
             the full pass (2 × 2500 vertices, mid-inspiration and peak, four orientations)"
        );
        assert!(max > 0.0, "{b} bands: the cap changed nothing");
    }
    // Fewer bands, further from the full pass (the projection's higher bands add detail).
    assert!(cost[1].0 > cost[7].0, "{cost:?}");
}
