#!/usr/bin/env python3
"""Independent check of a lung surface mesh against the label image it came from.

Written for `lungdyn mesh from-mask`, but shares no code with lungdyn.  It reads the mask
(NIfTI .nii/.nii.gz via nibabel, NRRD .nrrd/.seg.nrrd via pynrrd, MetaImage .mha/.mhd via
SimpleITK), maps voxels to lungdyn's BODY frame in mm (+X patient left, +Y anterior,
+Z superior: body = (-x, y, z) from RAS world, (x, -y, z) from LPS world) and prints ONE JSON
object with:
  mask   labelled-voxel volume (ml), spacing, world frame / affine used, axis codes, centroid;
  mesh   vertex/face counts, watertight, winding, Euler number, bodies, and when watertight
         genus = (2*bodies - euler)/2 (summed over bodies) and volume (ml; negative = faces wound
         inward, e.g. a mirroring transform that kept the triangle order);
  vertex_to_staircase   exact distance (mm and mean-voxel units) from every mesh vertex to the
         nearest voxel FACE between a labelled and an unlabelled voxel (KD-tree of face centres,
         exact point-to-rectangle distance, k grown until provably nearest);
  mc_surface   symmetric surface distance between the mask's own marching-cubes surface
         (skimage, level 0.5) and the mesh: points sampled uniformly by area on each surface,
         EXACT point-to-triangle distance to the other (centroid KD-tree + trimesh
         closest_point, k grown until provably nearest).  Both: `far_upper_bound` counts points
         over 32 voxels from the surface (only an upper bound, from every 64th primitive);
         `bound_only` points left open at k=256 may be up to `bound_error_mm` too large;
  lobes  (PLY `lobe` property and --lobe-labels) share of vertices whose lobe code equals the
         code of the nearest labelled voxel.

  python3 bench/mask_check.py --mask lungs.nrrd --mesh left.ply --label 3 [--keep-component
      largest|all|left|right]
      [--lobe-labels 5:4,6:5] [--samples 100000]
Everything heavy runs on the labelled bounding box + 2 voxels (handles 512x512x630 masks).
"""
import argparse, json, os, sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from pyneeds import need  # noqa: E402
need(["numpy", "scipy", "trimesh", "nibabel", "skimage"], __file__)

import numpy as np
from scipy import ndimage
from scipy.spatial import cKDTree
import trimesh

RAS_TO_BODY = np.diag([-1.0, 1.0, 1.0])
LPS_TO_BODY = np.diag([1.0, -1.0, 1.0])


def load_mask(path):
    """-> (array indexed [i,j,k], 4x4 voxel->BODY affine, info dict)."""
    low = path.lower()
    info = {"file": path}
    if low.endswith((".nii", ".nii.gz")):
        import nibabel as nib
        img = nib.load(path)
        hdr = img.header
        sf, sc = hdr.get_sform(coded=True)
        qf, qc = hdr.get_qform(coded=True)
        if sf is not None and int(sc) > 0:
            aff, used = sf, f"sform (code {int(sc)})"
        elif qf is not None and int(qc) > 0:
            aff, used = qf, f"qform (code {int(qc)})"
        else:
            aff, used = np.diag(list(hdr.get_zooms()[:3]) + [1.0]), "none coded: pixdim only"
        info.update(world="RAS (NIfTI)", affine_used=used, sform_code=int(hdr["sform_code"]),
                    qform_code=int(hdr["qform_code"]))
        data = np.asanyarray(img.dataobj)
        while data.ndim > 3 and data.shape[-1] == 1:
            data = data[..., 0]
        world_to_body = RAS_TO_BODY
    elif low.endswith(".nrrd"):
        need(["nrrd"], __file__)
        import nrrd
        data, hdr = nrrd.read(path)  # index order 'F': data[i, j, k] with i fastest in file
        space = str(hdr.get("space", "")).lower()
        dirs = hdr["space directions"]
        keep = [a for a, d in enumerate(dirs) if d is not None and np.all(np.isfinite(np.asarray(d, float)))]
        lists = [a for a in range(data.ndim) if a not in keep]
        if lists:  # .seg.nrrd layers / list axis: handled by the caller via any-over-axis
            info["non_spatial_axes"] = lists
        D = np.array([np.asarray(dirs[a], float) for a in keep]).T  # columns = axis vectors
        aff = np.eye(4)
        aff[:3, :3] = D
        aff[:3, 3] = np.asarray(hdr.get("space origin", np.zeros(3)), float)
        if space in ("left-posterior-superior", "lps"):
            world_to_body, w = LPS_TO_BODY, "LPS"
        elif space in ("right-anterior-superior", "ras"):
            world_to_body, w = RAS_TO_BODY, "RAS"
        else:
            sys.exit(f"NRRD space {space!r} is not RAS or LPS")
        info.update(world=f"{w} (NRRD space {hdr.get('space')})", affine_used="space directions + space origin")
        if lists:
            data = np.moveaxis(data, lists, list(range(len(lists))))
            data = data.reshape((-1,) + data.shape[len(lists):])
    else:
        need(["SimpleITK"], __file__)
        import SimpleITK as sitk
        img = sitk.ReadImage(path)
        data = sitk.GetArrayFromImage(img).transpose(2, 1, 0)  # (z,y,x) -> [i,j,k]
        D = np.array(img.GetDirection(), float).reshape(3, 3)  # row-major, columns = axes
        aff = np.eye(4)
        aff[:3, :3] = D @ np.diag(img.GetSpacing())
        aff[:3, 3] = img.GetOrigin()
        world_to_body = LPS_TO_BODY
        info.update(world="LPS (ITK)", affine_used="SimpleITK direction*spacing + origin")
    aff = np.asarray(aff, float)
    import nibabel as nib
    ras = np.diag([*np.diag(world_to_body @ RAS_TO_BODY), 1.0]) @ aff  # world -> RAS for axcodes
    info["axcodes_ras"] = "".join(nib.aff2axcodes(ras))
    info["affine_world"] = np.round(aff, 6).tolist()
    body = np.eye(4)
    body[:3, :3] = world_to_body
    return data, body @ aff, info


def exact_nearest(tree, pts, radius, dist_fn, far, k=8, kmax=256, pairs=2_000_000):
    """Nearest-primitive distance: tree holds primitive centres, every point of a primitive lies
    within `radius` of its centre; dist_fn(pts (m,3), idx (m,k)) -> (m,k).  k grows until the
    k-th centre is provably too far to matter.  Points with no centre within `far` mm (a mesh
    far off the mask; k-NN is slow there) get the distance to the primitive of the nearest of
    every 64th centre, an upper bound.  -> (dist, n_far, n_open: points still open at kmax whose
    value may be up to `radius` too large)"""
    out = np.empty(len(pts))
    d1 = tree.query(pts, k=1, distance_upper_bound=far)[0]
    faridx = np.flatnonzero(~np.isfinite(d1))
    if len(faridx):
        sel = np.arange(0, tree.n, 64)
        near = sel[cKDTree(tree.data[sel]).query(pts[faridx], k=1)[1]]
        out[faridx] = dist_fn(pts[faridx], near[:, None])[:, 0]
    todo, kk, n_open = np.flatnonzero(np.isfinite(d1)), k, 0
    while len(todo):
        kk = min(kk, tree.n)
        still = []
        for s in range(0, len(todo), max(1, pairs // kk)):
            t = todo[s:s + max(1, pairs // kk)]
            dc, ic = tree.query(pts[t], k=kk)
            dc, ic = dc.reshape(len(t), -1), ic.reshape(len(t), -1)
            dmin = dist_fn(pts[t], ic).min(axis=1)
            out[t] = dmin
            still.append(t[~((kk == tree.n) | (dc[:, -1] - radius >= dmin))])
        todo = np.concatenate(still)
        if kk >= kmax:
            n_open = len(todo)
            break
        kk *= 4
    return out, len(faridx), n_open


def staircase_faces(m, aff):
    """Centres (body mm) and normal axis of every voxel face between labelled and not."""
    cs, axes = [], []
    for a in range(3):
        d = np.diff(m.astype(np.int8), axis=a) != 0
        idx = np.argwhere(d).astype(float)
        idx[:, a] += 0.5
        cs.append(idx @ aff[:3, :3].T + aff[:3, 3])
        axes.append(np.full(len(idx), a, np.int8))
    return np.concatenate(cs), np.concatenate(axes)


def rect_dist_fn(centres, axes, aff):
    cols = aff[:3, :3]
    U, V, HU, HV = [], [], [], []
    for a in range(3):
        b, c = [x for x in range(3) if x != a]
        U.append(cols[:, b] / np.linalg.norm(cols[:, b])); HU.append(np.linalg.norm(cols[:, b]) / 2)
        V.append(cols[:, c] / np.linalg.norm(cols[:, c])); HV.append(np.linalg.norm(cols[:, c]) / 2)
    U, V, HU, HV = map(np.array, (U, V, HU, HV))

    def fn(p, idx):
        d = p[:, None, :] - centres[idx]
        ax = axes[idx]
        u, v = U[ax], V[ax]
        s = np.clip((d * u).sum(-1), -HU[ax], HU[ax])
        t = np.clip((d * v).sum(-1), -HV[ax], HV[ax])
        return np.linalg.norm(d - s[..., None] * u - t[..., None] * v, axis=-1)
    return fn, float(np.sqrt(HU ** 2 + HV ** 2).max())


def mesh_distance(points, mesh, far):
    """Exact distance from points to the triangles of mesh."""
    tri = mesh.triangles
    cen = tri.mean(axis=1)
    rad = float(np.linalg.norm(tri - cen[:, None], axis=-1).max())

    def fn(p, idx):
        m, k = idx.shape
        q = trimesh.triangles.closest_point(tri[idx.ravel()], np.repeat(p, k, axis=0))
        return np.linalg.norm(q - np.repeat(p, k, axis=0), axis=1).reshape(m, k)
    return exact_nearest(cKDTree(cen), points, rad, fn, max(far, 4 * rad), pairs=500_000) + (rad,)


def stats(d, unit=None):
    r = {"mean": float(d.mean()), "p95": float(np.percentile(d, 95)), "max": float(d.max())}
    if unit:
        r.update({f"{k}_vox": v / unit for k, v in list(r.items())})
    return {k: round(v, 4) for k, v in r.items()}


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--mask", required=True)
    ap.add_argument("--mesh", required=True)
    ap.add_argument("--label", help="comma-separated lung label values (default: any nonzero)")
    ap.add_argument("--keep-component", choices=["largest", "all", "left", "right"], default="all",
                    help="left/right: of the two largest 6-connected components, the one with larger/smaller body X")
    ap.add_argument("--lobe-labels", help="V1:code,V2:code,... label value -> lobe code 1..5")
    ap.add_argument("--samples", type=int, default=100000, help="points per surface for mc_surface")
    args = ap.parse_args()

    data, aff, info = load_mask(args.mask)
    labels = [float(v) for v in args.label.split(",")] if args.label else None
    sel = (lambda a: np.isin(a, labels)) if labels else (lambda a: a != 0)
    full = sel(data)
    if full.ndim == 4:  # NRRD list axis (segment layers) first
        full = full.any(axis=0)
        data = data.max(axis=0)
    if not full.any():
        sys.exit("no labelled voxels")
    bb = [np.flatnonzero(full.any(axis=tuple(x for x in range(3) if x != a))) for a in range(3)]
    lo = np.array([b[0] for b in bb]) - 2
    hi = np.array([b[-1] for b in bb]) + 3
    pad = [(max(0, -l), max(0, h - n)) for l, h, n in zip(lo, hi, full.shape)]
    sl = tuple(slice(max(0, l), min(h, n)) for l, h, n in zip(lo, hi, full.shape))
    m = np.pad(full[sl], pad)
    lab = np.pad(data[sl], pad)
    del full
    shift = np.eye(4)
    shift[:3, 3] = lo
    aff = aff @ shift  # voxel index in the crop -> body mm
    cc, ncc = ndimage.label(m)
    info["components_6conn"] = int(ncc)
    if args.keep_component != "all" and ncc > 1:
        sizes = np.bincount(cc.ravel())[1:]
        big = np.argsort(sizes)[::-1][:2] + 1
        keep = big[0]
        if args.keep_component in ("left", "right"):
            if sizes[big[1] - 1] < 0.1 * sizes[big[0] - 1]:
                sys.exit("left/right: the lungs are not two separate components (they touch)")
            x = [(np.argwhere(cc == c).mean(0) @ aff[:3, :3].T)[0] for c in big]
            keep = big[int(np.argmax(x) if args.keep_component == "left" else np.argmin(x))]
        m = cc == keep
        info["dropped_voxels"] = int(sizes.sum() - sizes[keep - 1])
    vox_ml = abs(np.linalg.det(aff[:3, :3])) / 1000.0
    spacing = np.linalg.norm(aff[:3, :3], axis=0)
    unit = float(spacing.mean())
    cols = aff[:3, :3] / spacing
    nz = np.argwhere(m)
    info.update(voxels=int(len(nz)), volume_ml=round(len(nz) * vox_ml, 3),
                spacing_mm=np.round(spacing, 6).tolist(), mean_spacing_mm=round(unit, 6),
                affine_orthogonal=bool(np.allclose(cols.T @ cols, np.eye(3), atol=1e-4)),
                centroid_body_mm=np.round(nz.mean(0) @ aff[:3, :3].T + aff[:3, 3], 2).tolist())
    out = {"mask": info}

    mesh = trimesh.load(args.mesh, process=False, force="mesh")
    bodies = mesh.split(only_watertight=False)
    euler = int(mesh.euler_number)
    mi = {"file": args.mesh, "vertices": len(mesh.vertices), "faces": len(mesh.faces),
          "watertight": bool(mesh.is_watertight), "is_winding_consistent": bool(mesh.is_winding_consistent),
          "euler_number": euler, "bodies": len(bodies),
          "genus": (2 * len(bodies) - euler) / 2 if mesh.is_watertight else None,
          "volume_ml": round(float(mesh.volume) / 1000.0, 3) if mesh.is_watertight else None,
          "centroid_mm": np.round(mesh.vertices.mean(0), 2).tolist()}
    if mi["volume_ml"] is not None:
        mi["volume_ratio_mesh_over_mask"] = round(mi["volume_ml"] / info["volume_ml"], 4)
    out["mesh"] = mi

    centres, axes = staircase_faces(m, aff)
    fn, rad = rect_dist_fn(centres, axes, aff)
    v = np.asarray(mesh.vertices, float)
    far = 32 * unit
    dv, nf, nb = exact_nearest(cKDTree(centres), v, rad, fn, far)
    ijk = np.rint((v - aff[:3, 3]) @ np.linalg.inv(aff[:3, :3]).T).astype(int)
    ok = np.all((ijk >= 0) & (ijk < m.shape), axis=1)
    inside = np.zeros(len(v), bool)
    inside[ok] = m[tuple(ijk[ok].T)]
    out["vertex_to_staircase"] = dict(stats(dv, unit), staircase_faces=len(centres), far_mm=round(far, 3), far_upper_bound=nf, bound_only=nb,
                                      bound_error_mm=round(rad, 4),
                                      share_vertices_in_labelled_voxel=round(float(inside.mean()), 4))

    from skimage.measure import marching_cubes
    verts, faces, _, _ = marching_cubes(m.astype(np.float32), 0.5)
    mc = trimesh.Trimesh(verts @ aff[:3, :3].T + aff[:3, 3], faces, process=False)
    pa = trimesh.sample.sample_surface(mc, args.samples, seed=1)[0]
    pb = trimesh.sample.sample_surface(mesh, args.samples, seed=2)[0]
    (dab, fab, nab, rab), (dba, fba, nba, rba) = mesh_distance(pa, mesh, far), mesh_distance(pb, mc, far)
    out["mc_surface"] = {"method": f"{args.samples} area-uniform samples per surface, exact point-to-triangle",
                         "mc_faces": len(faces), "far_upper_bound": fab + fba, "bound_only": nab + nba,
                         "bound_error_mm": round(max(rab, rba), 4), "mc_to_mesh": stats(dab, unit), "mesh_to_mc": stats(dba, unit),
                         "symmetric_mean_mm": round(float((dab.mean() + dba.mean()) / 2), 4),
                         "symmetric_mean_vox": round(float((dab.mean() + dba.mean()) / 2) / unit, 4)}

    raw = mesh.metadata.get("_ply_raw", {}).get("vertex", {}).get("data", {})
    lobe = raw["lobe"] if hasattr(raw, "dtype") and raw.dtype.names and "lobe" in raw.dtype.names else None
    if lobe is None and isinstance(raw, dict):
        lobe = raw.get("lobe")
    out["lobes"] = {"mesh_has_lobe_property": lobe is not None}
    if lobe is not None and args.lobe_labels:
        lut = {float(a): int(b) for a, b in (p.split(":") for p in args.lobe_labels.split(","))}
        lm = np.isin(lab, list(lut))
        border = lm & ~ndimage.binary_erosion(lm, border_value=0)
        bidx = np.argwhere(border)
        code = np.vectorize(lambda x: lut.get(float(x), 0))
        _, near = cKDTree(bidx @ aff[:3, :3].T + aff[:3, 3]).query(v)
        truth = code(lab[tuple(bidx[near].T)])
        own = np.zeros(len(v), bool)
        own[ok] = lm[tuple(ijk[ok].T)]
        truth[own] = code(lab[tuple(ijk[own].T)])
        lobe = np.asarray(lobe).ravel().astype(int)
        out["lobes"].update(share_agree=round(float((lobe == truth).mean()), 4),
                            mesh_codes=np.unique(lobe).tolist(), mask_codes=np.unique(truth).tolist())
    print(json.dumps(out))


if __name__ == "__main__":
    main()
