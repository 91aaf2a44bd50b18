//! `lung_bake::mask` end to end on masks made here: the built-in lungs voxelised at CT spacing and
//! written as NIfTI, NRRD and MetaImage with their headers' frames, then made into surfaces again.
//! What must hold: each side found (by label, by components, split where the lungs touch), the
//! frame honoured (the same lung from an RAS NIfTI, an LPS NRRD and an LPS MetaImage), tunnels
//! closed, the volume kept, the vertex count near the one asked, the surface within half a voxel
//! of the mask's boundary and near the lung it was voxelised from, lobes from lobe labels, a
//! header that contradicts the anatomy refused with the axes that fix it, and bad files refused
//! with a reason.

use std::path::{Path, PathBuf};

use glam::DVec3;
use lung_bake::mask::synthetic::{
    both_lungs, empty_body_around, gzip, in_file_order, mha, nifti, nrrd, put_f32, put_i16,
    voxelise, Body,
};
use lung_bake::mask::{self, labels::Convention, volume::Axes, MaskOptions};
use lung_model::mesh::{anatomy, lobes, Side, TriMesh};

fn tmp(name: &str) -> PathBuf {
    let dir = std::env::temp_dir().join(format!("lungdyn-mask-{}", std::process::id()));
    std::fs::create_dir_all(&dir).unwrap();
    dir.join(name)
}

fn write(name: &str, bytes: &[u8]) -> PathBuf {
    let p = tmp(name);
    std::fs::write(&p, bytes).unwrap();
    p
}

fn opts(side: Side, vertices: usize) -> MaskOptions {
    let mut o = MaskOptions::new(side);
    o.vertices = vertices;
    o
}

/// Mean distance from `a`'s vertices to `b`'s surface (point to triangle, through the surface
/// fit's BVH target).
fn mean_nearest(a: &TriMesh, b: &TriMesh) -> f64 {
    let target = lung_bake::surface_fit::Target::new(b, "reference").unwrap();
    let sum: f64 = a
        .positions
        .iter()
        .map(|q| {
            target
                .signed_distance(DVec3::from(q.map(|v| v as f64)))
                .abs()
        })
        .sum();
    sum / a.positions.len() as f64
}

#[test]
fn both_lungs_in_one_label_from_nifti_nrrd_and_metaimage_give_the_same_lungs() {
    let spacing = [2.0, 1.75, 2.5];
    // Right voxelised as 1 and left as 2 to count each, then written as one label.
    let (sides, lungs) = both_lungs(spacing, |_| 1, |_| 2);
    let mut body = sides.clone();
    body.labels.iter_mut().for_each(|l| *l = (*l != 0) as u16);
    let voxel_ml = spacing.iter().product::<f64>() / 1000.0;
    // RAS NIfTI with voxel axes RAS (x reversed against the body), gzipped.
    let (d_ras, rows_ras) = in_file_order(&body, Axes::RAS, Axes::RAS);
    let nii = write("lungs.nii.gz", &gzip(&nifti(&body, Some(rows_ras), &d_ras)));
    // LPS NRRD with voxel axes LPS.
    let (d_lps, rows_lps) = in_file_order(&body, Axes::LPS, Axes::LPS);
    let nrrd_path = write(
        "lungs.nrrd",
        &nrrd(&body, rows_lps, "left-posterior-superior", &d_lps),
    );
    // MetaImage (LPS world) with voxel axes LAS.
    let las: Axes = "LAS".parse().unwrap();
    let (d_las, rows_las) = in_file_order(&body, las, Axes::LPS);
    let mha_path = write("lungs.mha", &mha(&body, rows_las, &d_las));

    for (side, truth) in [(Side::Right, 0usize), (Side::Left, 1)] {
        let code = if side == Side::Right { 1 } else { 2 };
        let want_ml = sides.labels.iter().filter(|&&l| l == code).count() as f64 * voxel_ml;
        let mut made = Vec::new();
        for path in [&nii, &nrrd_path, &mha_path] {
            let m = mask::mesh_from_mask(&[path.clone()], &opts(side, 6000))
                .unwrap_or_else(|e| panic!("{}: {e}", path.display()));
            assert_eq!(m.convention, Convention::Single, "{}", path.display());
            assert_eq!(m.sides_from, "components");
            // Every voxel of this side is counted, or dropped as a stray piece (and said; a stray
            // piece is dropped from both sides' counts, whichever lung it came from).
            let dropped = m.voxels_dropped as f64 * voxel_ml;
            assert!(
                m.mask_volume_ml <= want_ml + 1e-9 && want_ml <= m.mask_volume_ml + dropped + 1e-9,
                "{} (+{dropped} dropped) vs {want_ml}",
                m.mask_volume_ml
            );
            assert!(m.voxels_dropped < 10, "{} voxels dropped", m.voxels_dropped);
            let v = m.mesh.enclosed_volume_ml();
            assert!(
                (v / m.closed_volume_ml - 1.0).abs() < 0.01,
                "{}: {v} ml vs mask {}",
                path.display(),
                m.closed_volume_ml
            );
            let n = m.mesh.positions.len();
            assert!((5000..=7000).contains(&n), "{n} vertices for 6000 asked");
            assert_eq!(m.genus_after, 0);
            let d = m.distance_to_mask;
            assert!(
                d.mean_voxels <= 0.5,
                "{}: mean distance {:.3} voxel",
                path.display(),
                d.mean_voxels
            );
            // Near the lung it was voxelised from (the voxelisation itself is ±half a voxel).
            let err = mean_nearest(&m.mesh, &lungs[truth]);
            assert!(
                err < 1.0,
                "{} {}: {err:.2} mm from the built-in lung",
                path.display(),
                side.name()
            );
            // Lobes from the planes (no lobe labels), all of this side.
            assert_eq!(m.lobes_from, "planes");
            assert!(m
                .lobes
                .iter()
                .all(|&c| lobes::Lobe::from_code(c).and_then(|l| l.side()) == Some(side)));
            made.push(m);
        }
        // The three files give the same surface (the same voxels in the same places).
        for other in &made[1..] {
            let e = mean_nearest(&made[0].mesh, &other.mesh);
            assert!(e < 0.25, "formats disagree by {e:.3} mm");
        }
    }
}

#[test]
fn touching_lungs_are_split_and_tunnels_closed() {
    let spacing = [2.0, 2.0, 2.0];
    let (mut body, _) = both_lungs(spacing, |_| 1, |_| 1);
    let [nx, ny, nz] = body.dims;
    let at = |body: &Body, p: DVec3| {
        let u = (p - body.origin) / DVec3::from(body.spacing);
        (
            u.x.round() as usize,
            u.y.round() as usize,
            u.z.round() as usize,
        )
    };
    // A bridge between the lungs at mid-height in front (an anterior junction line).
    let (_, _, kz) = at(&body, DVec3::new(0.0, 0.0, 40.0));
    let right_x: Vec<usize> = (0..nx).collect();
    let mut bridged = 0;
    for k in kz..kz + 6 {
        for j in 0..ny {
            // Only rows where both lungs are present: fill between them.
            let row: Vec<usize> = right_x
                .iter()
                .copied()
                .filter(|&i| body.labels[i + nx * (j + ny * k)] != 0)
                .collect();
            if let (Some(&a), Some(&b)) = (row.first(), row.last()) {
                let gap: Vec<usize> = (a..=b)
                    .filter(|&i| body.labels[i + nx * (j + ny * k)] == 0)
                    .collect();
                if !gap.is_empty() && gap.len() < 40 && j % 7 == 0 {
                    for i in gap {
                        body.labels[i + nx * (j + ny * k)] = 1;
                        bridged += 1;
                    }
                }
            }
        }
    }
    assert!(bridged > 0, "the bridge joins the lungs");
    // A tunnel (a vessel) through the right lung, front to back, at its centre.
    let (mut sum, mut count) = (DVec3::ZERO, 0.0);
    for (idx, &l) in body.labels.iter().enumerate() {
        let p = body.origin
            + DVec3::new(
                (idx % nx) as f64,
                ((idx / nx) % ny) as f64,
                (idx / (nx * ny)) as f64,
            ) * DVec3::from(body.spacing);
        if l != 0 && p.x < 0.0 {
            sum += p;
            count += 1.0;
        }
    }
    let (ti, _, tk) = at(&body, sum / count);
    for j in 0..ny {
        for (di, dk) in [(0, 0), (1, 0), (0, 1), (1, 1)] {
            body.labels[(ti + di) + nx * (j + ny * (tk + dk))] = 0;
        }
    }
    let _ = nz;
    let (d, rows) = in_file_order(&body, Axes::RAS, Axes::RAS);
    let path = write("touching.nii", &nifti(&body, Some(rows), &d));
    let right = mask::mesh_from_mask(&[path.clone()], &opts(Side::Right, 4000)).unwrap();
    assert_eq!(right.sides_from, "split at contact");
    assert!(
        right.genus_before >= 1,
        "the tunnel is seen: genus {}",
        right.genus_before
    );
    assert_eq!(right.genus_after, 0);
    assert!(right.closing_mm > 0.0);
    let left = mask::mesh_from_mask(&[path.clone()], &opts(Side::Left, 4000)).unwrap();
    assert_eq!(left.sides_from, "split at contact");
    // The right lung is to the patient's right (−X in the body frame) and the larger.
    assert!(right.mesh.aabb().max[0] < left.mesh.aabb().min[0] + 20.0);
    assert!(right.mask_volume_ml > left.mask_volume_ml);
    // Kept, the tunnel stays.
    let mut keep = opts(Side::Right, 4000);
    keep.keep_tunnels = true;
    let kept = mask::mesh_from_mask(&[path], &keep).unwrap();
    assert!(kept.genus_after >= 1, "genus {}", kept.genus_after);
}

#[test]
fn lobes_come_from_lobe_labels_and_a_lying_header_is_refused_with_the_fix() {
    let spacing = [1.75, 1.75, 2.0];
    // lungmask LTRCLobes: 1 LUL, 2 LLL, 3 RUL, 4 RML, 5 RLL — lobes from the fissure planes of the
    // built-in lungs' boxes.
    let r = anatomy::lung(Side::Right, 4000).unwrap();
    let l = anatomy::lung(Side::Left, 4000).unwrap();
    let fr = lobes::Fissures::adult(Side::Right);
    let fl = lobes::Fissures::adult(Side::Left);
    let (rb, lb) = (r.aabb(), l.aabb());
    let code = |side: Side, bb: &lung_model::mesh::Aabb, f: &lobes::Fissures, p: DVec3| -> u16 {
        match f.lobe_at(side, lobes::normalise(side, bb, p.to_array())) {
            lobes::Lobe::LeftUpper => 1,
            lobes::Lobe::LeftLower => 2,
            lobes::Lobe::RightUpper => 3,
            lobes::Lobe::RightMiddle => 4,
            _ => 5,
        }
    };
    let (body, _) = both_lungs(
        spacing,
        |p| code(Side::Right, &rb, &fr, p),
        |p| code(Side::Left, &lb, &fl, p),
    );
    let (d, rows) = in_file_order(&body, Axes::RAS, Axes::RAS);
    let path = write("lobes.nii.gz", &gzip(&nifti(&body, Some(rows), &d)));
    let m = mask::mesh_from_mask(&[path.clone()], &opts(Side::Right, 5000)).unwrap();
    assert_eq!(m.convention, Convention::LungmaskLobes);
    assert_eq!(m.labels_used, vec![3, 4, 5]);
    assert_eq!(m.lobes_from, "labels");
    let mut seen = [0usize; 6];
    for &c in &m.lobes {
        seen[c as usize] += 1;
    }
    assert!(seen[1] > 0 && seen[2] > 0 && seen[3] > 0, "{seen:?}");
    assert_eq!(seen[0] + seen[4] + seen[5], 0, "{seen:?}");
    // --label naming the other side's lobe is refused.
    let mut wrong = opts(Side::Right, 5000);
    wrong.labels = Some(vec![1]);
    let e = mask::mesh_from_mask(&[path.clone()], &wrong)
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("left upper") && e.contains("not a lobe of the right lung"),
        "{e}"
    );

    // The same voxels in LPS order under a header that calls them RAS (a classic writer's bug):
    // anterior–posterior and left–right both mirrored. Refused, naming the axes that fix it.
    let (d_lps, _) = in_file_order(&body, Axes::LPS, Axes::LPS);
    // The header claims voxel axes R, A, S (a diagonal sform, origin 0) with the data laid out
    // L, P, S.
    let mut lying = [[0.0; 4]; 3];
    for a in 0..3 {
        lying[a][a] = spacing[a];
    }
    let path = write("lying.nii", &nifti(&body, Some(lying), &d_lps));
    let e = mask::mesh_from_mask(&[path.clone()], &opts(Side::Left, 3000))
        .unwrap_err()
        .to_string();
    assert!(e.contains("--axes"), "{e}");
    let mut fixed = opts(Side::Left, 3000);
    fixed.axes = Some("LPS".parse().unwrap());
    let m = mask::mesh_from_mask(&[path], &fixed).unwrap();
    assert_eq!(m.frame.axes_override.as_deref(), Some("LPS"));
    assert_eq!(m.lobes_from, "labels");
}

#[test]
fn bad_label_images_are_refused_with_the_reason() {
    let spacing = [2.0, 2.0, 2.0];
    let (body, _) = both_lungs(spacing, |_| 1, |_| 1);
    let (d, rows) = in_file_order(&body, Axes::RAS, Axes::RAS);
    let good = nifti(&body, Some(rows), &d);
    let check = |name: &str, bytes: &[u8], o: MaskOptions, want: &[&str]| {
        let p = write(name, bytes);
        let e = mask::mesh_from_mask(&[p], &o).unwrap_err().to_string();
        for w in want {
            assert!(e.contains(w), "{name}: {e:?} lacks {w:?}");
        }
    };
    let right = || opts(Side::Right, 3000);
    check(
        "short.nii",
        &good[..200],
        right(),
        &["shorter than a NIfTI-1 header"],
    );
    check("cut.nii", &good[..good.len() / 2], right(), &["cut short"]);
    check("cut.nii.gz", &gzip(&good)[..1000], right(), &["decompress"]);
    check(
        "plain.nii",
        &nifti(&body, None, &d),
        right(),
        &["neither an sform nor a qform", "--axes"],
    );
    let mut four_d = good.clone();
    put_i16(&mut four_d, 40, 4);
    put_i16(&mut four_d, 48, 3);
    check("4d.nii", &four_d, right(), &["several volumes"]);
    let (_, mut small_rows) = in_file_order(&body, Axes::RAS, Axes::RAS);
    for row in &mut small_rows {
        for c in 0..3 {
            row[c] *= 0.001;
        }
    }
    check(
        "metres.nii",
        &nifti(&body, Some(small_rows), &d),
        right(),
        &["spacing", "unit"],
    );
    let mut float = good.clone();
    put_f32(&mut float, 112, 0.5);
    check("scaled.nii", &float, right(), &["whole numbers"]);
    check(
        "empty.nii",
        &nifti(&body, Some(rows), &vec![0u16; d.len()]),
        right(),
        &["no labelled voxel"],
    );
    let mut named = right();
    named.labels = Some(vec![7]);
    check(
        "missing.nii",
        &good,
        named,
        &["--label 7", "no voxel holds 7"],
    );
    check(
        "noise.txt",
        b"hello",
        right(),
        &["unknown label image format"],
    );
    check(
        "bad.nrrd",
        b"NRRD0004\ntype: float\ndimension: 3\n",
        right(),
        &["header"],
    );
    check(
        "nospace.nrrd",
        b"NRRD0004\ntype: uchar\ndimension: 3\nsizes: 2 2 2\nencoding: raw\n\n\0\0\0\0\0\0\0\0",
        right(),
        &["does not say where the patient", "--axes"],
    );
    check(
        "layers.seg.nrrd",
        b"NRRD0004\ntype: uchar\ndimension: 4\nsizes: 3 2 2 2\nencoding: raw\n\n",
        right(),
        &["several layers"],
    );
    check(
        "bad.mha",
        b"ObjectType = Image\nNDims = 2\nElementDataFile = LOCAL\n",
        right(),
        &["3D"],
    );
    // A path that is a folder is refused by the bounded reader.
    let dir = tmp("a-folder.nii");
    std::fs::create_dir_all(&dir).unwrap();
    let e = mask::mesh_from_mask(&[dir], &right())
        .unwrap_err()
        .to_string();
    assert!(e.contains("folder"), "{e}");
}

/// The shared COPDgene masks (../shared/data/lungs), when present: both lungs of an exhale scan
/// each become a checked lung; said aloud when the data is absent.
#[test]
fn a_real_copdgene_mask_gives_two_checked_lungs() {
    let path = Path::new(env!("CARGO_MANIFEST_DIR"))
        .join("../../../shared/data/lungs/copdgene_breath_hold_pairs/case_08_exp_mask.nii.gz");
    if !path.exists() {
        eprintln!(
            "SKIPPED (said aloud): {} is absent: the real-mask check did not run",
            path.display()
        );
        return;
    }
    for side in [Side::Right, Side::Left] {
        let mut o = opts(side, 20_000);
        // This file's header is known to lie (identity RAS on LPS-ordered data: the lungs' bases
        // come out anterior); the test states the real axes, as a user would after the error.
        o.axes = Some("LPS".parse().unwrap());
        let m = mask::mesh_from_mask(&[path.clone()], &o)
            .unwrap_or_else(|e| panic!("{}: {e}", side.name()));
        let v = m.mesh.enclosed_volume_ml();
        assert!((v / m.closed_volume_ml - 1.0).abs() < 0.01);
        assert!(
            m.distance_to_mask.mean_voxels <= 0.5,
            "{:?}",
            m.distance_to_mask
        );
        assert_eq!(m.genus_after, 0);
        eprintln!(
            "case 08 exp {}: {} vertices, {:.0} ml (mask {:.0} ml, closed {:.0} ml), genus {} → 0 (closing {} mm), \
             distance mean {:.2} mm, sides from {}, warnings {:?}",
            side.name(), m.mesh.positions.len(), v, m.mask_volume_ml, m.closed_volume_ml, m.genus_before,
            m.closing_mm, m.distance_to_mask.mean_mm, m.sides_from, m.warnings
        );
    }
}

/// An image holding one lung under one label: which lung it is comes from its shape, never from
/// what was asked — the other side is refused, naming the lung the image holds.
#[test]
fn one_lung_in_an_image_is_never_returned_as_the_other() {
    let spacing = [1.5, 1.5, 2.0];
    let r = anatomy::lung(Side::Right, 4000).unwrap();
    let mut body = empty_body_around(&[&r], spacing);
    voxelise(&r, &mut body, |_| 1);
    let (d, rows) = in_file_order(&body, Axes::RAS, Axes::RAS);
    let path = write(
        "one_right_lung.nii.gz",
        &gzip(&nifti(&body, Some(rows), &d)),
    );
    let m = mask::mesh_from_mask(&[path.clone()], &opts(Side::Right, 4000)).unwrap();
    assert_eq!(m.sides_from, "one lung in the image");
    let e = mask::mesh_from_mask(&[path], &opts(Side::Left, 4000))
        .unwrap_err()
        .to_string();
    assert!(
        e.contains("holds one lung")
            && e.contains("it is the right lung")
            && e.contains("--lung right"),
        "{e}"
    );
}

/// The shared masks (../shared/data/lungs), when present: the cases the first measurement found
/// wrong (docs/masks/README.md). Every COPDgene header lies (RAS over LPS-ordered voxels); the
/// frame is judged once per image, from both lungs, so each lung of each file is refused naming
/// `--axes LPS` (case_06_insp and case_10_insp right were accepted silently, writing the
/// anatomical left lung as the right); with `--axes LPS` they pass without a frame warning; a
/// one-lung image asked for the other lung is refused; case_09_exp left at 20k vertices (a false
/// tunnel through a thin sheet at the coarse grid) is made. Said aloud when the data is absent.
#[test]
fn the_shared_masks_that_were_wrong_are_refused_or_made() {
    let root = Path::new(env!("CARGO_MANIFEST_DIR")).join("../../../shared/data/lungs");
    if !root.exists() {
        eprintln!(
            "SKIPPED (said aloud): {} is absent: the real-mask frame checks did not run",
            root.display()
        );
        return;
    }
    let copd = |c: &str| root.join(format!("copdgene_breath_hold_pairs/case_{c}_mask.nii.gz"));
    for (case, side) in [
        ("06_insp", Side::Right),
        ("10_insp", Side::Right),
        ("06_exp", Side::Left),
    ] {
        let e = mask::mesh_from_mask(&[copd(case)], &opts(side, 3000))
            .map(|m| format!("accepted with warnings {:?}", m.warnings))
            .unwrap_or_else(|e| e.to_string());
        assert!(
            e.contains("pass --axes LPS") && !e.starts_with("accepted"),
            "case {case} {}: {e}",
            side.name()
        );
        let mut o = opts(side, 3000);
        o.axes = Some("LPS".parse().unwrap());
        let m = mask::mesh_from_mask(&[copd(case)], &o).unwrap();
        assert!(
            m.warnings.iter().all(|w| !w.contains("--axes")),
            "case {case} {} with --axes LPS: {:?}",
            side.name(),
            m.warnings
        );
    }
    let mut o = opts(Side::Left, 20_000);
    o.axes = Some("LPS".parse().unwrap());
    let m = mask::mesh_from_mask(&[copd("09_exp")], &o).unwrap();
    assert_eq!(m.genus_after, 0);
    let one = root.join("baseline_followup/CT_3D_lung_fixed_mask.mha");
    let e = mask::mesh_from_mask(&[one], &opts(Side::Left, 3000))
        .unwrap_err()
        .to_string();
    assert!(e.contains("it is the right lung"), "{e}");
}
