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

#[test]
fn every_mode_on_the_gpu_matches_the_cpu_reference_at_extreme_orientations() {
    let Some(gpu) = Gpu::for_tests() else { return };
    let base = lungdyn_tests::scene_with_kernels(scene(DeformMode::Basis), "modes-gpu");
    for mode in DeformMode::ALL {
        let mut scene = base.clone();
        scene.lungs.mode = mode;
        let kernels: Vec<_> = scene
            .lungs
            .sides
            .iter()
            .map(|&s| scene.lung_kernel(s).unwrap())
            .collect();
        let lungs: Vec<RenderLung> = kernels
            .iter()
            .map(|k| RenderLung::from_kernel(k, mode).unwrap())
            .collect();
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
        let geometry = kernels
            .iter()
            .map(|k| LungGeometry::from_kernel(k, mode, scene.engine.orientation).unwrap())
            .collect();
        let mut core = EngineCore::with_geometry(&scene, geometry).unwrap();
        let mut cpus: Vec<CpuLung> = lungs.iter().map(|l| l.lung.clone()).collect();
        let turns = [
            DQuat::IDENTITY,
            DQuat::from_rotation_x(std::f64::consts::FRAC_PI_2),
            DQuat::from_rotation_y(-std::f64::consts::FRAC_PI_2),
            DQuat::from_rotation_x(std::f64::consts::PI),
        ];
        let mut f = EngineFrame::default();
        for (k, turn) in turns.iter().enumerate() {
            let tick = 120 + 300 * k as u64;
            core.step(tick, Some(&posed(tick, *turn * supine())), &mut f);
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
            if k + 1 < turns.len() {
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
