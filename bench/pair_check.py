#!/usr/bin/env python3
"""Independent check of `lungdyn fit-motion --exhale/--inhale --surfaces-out DIR --json`.

fit-motion writes DIR/<lung>_exhale.ply (the exhale surface fitted on), <lung>_moved.ply (that
surface driven to the inhale volume by the fitted kernel) and <lung>_inhale_aligned.ply (the
inhale surface after the translation alignment: the target), and reports MSSD figures in JSON.
This script recomputes those figures from the PLY files alone and prints ONE JSON object:

  meshes   for each PLY: vertices, faces, watertight, winding-consistent, bodies, Euler number,
           volume (ml = mm^3/1000; must be > 0, i.e. outward normals); optionally (pymeshlab
           installed) the number of self-intersecting faces.  Checks: moved volume equals
           inhale_aligned volume within 0.1 %; exhale volume equals JSON exhale_ml (0.1 %);
           inhale_aligned volume vs JSON inhale_ml (reported); moved has exhale's faces.
  mssd     for in_sample (moved <-> inhale_aligned), no_motion (exhale <-> inhale_aligned) and
           uniform_scaling (exhale scaled about its own volume centroid by
           (V_inhale_aligned / V_exhale)^(1/3), <-> inhale_aligned), and the same scaling about
           the exhale's plain vertex mean (lungdyn's centre; uniform_scaling_vertex_mean_centre):
             sampled: N area-uniform random points on each surface (fixed seed), EXACT
               point-to-triangle distance to the other surface (trimesh.proximity.closest_point:
               nearest vertex by KD-tree bounds the search box, so the result is exact),
               the two directed means and their mean (MSSD), p95 and max of both pooled;
             vertex_weighted: the same distances from every VERTEX, each weighted by a third of
               the area of its faces -- lungdyn's own definition, for a tight comparison
             (p95/max here: unweighted, over both surfaces' vertices pooled, as lungdyn's).
           beside lungdyn's figure for each and the differences.

Independence: no lungdyn code or output other than the PLYs and the JSON figures is used; the
geometry is trimesh's (rtree + numpy), not lungdyn's parry3d point-to-triangle code.
Sampled means and lungdyn's area-weighted vertex means estimate the same surface integral but
differ slightly (sampling noise, vertex vs interior placement: ~1-2 % typically), hence the
tolerance.  Exit status 1 if any checker MSSD (sampled or vertex-weighted) differs from
lungdyn's by more than 0.1 mm + 5 % of lungdyn's, or a mesh check fails; 0 otherwise.

  python3 bench/pair_check.py --dir DIR --lung right --fit-json fit.json [--samples 200000]
      [--seed 46] [--out check.json]
"""
import argparse, json, os, sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from pyneeds import need  # noqa: E402
need(["numpy", "trimesh", "rtree", "scipy"], __file__)

import numpy as np
import trimesh

TOL_ABS_MM, TOL_REL = 0.1, 0.05
VOL_TOL = 1e-3


def mesh_report(m, self_intersections):
    r = {"vertices": len(m.vertices), "faces": len(m.faces), "watertight": bool(m.is_watertight),
         "winding_consistent": bool(m.is_winding_consistent),
         "bodies": int(len(m.split(only_watertight=False))), "euler": int(m.euler_number),
         "volume_ml": float(m.volume) / 1000.0, "area_mm2": float(m.area)}
    r["ok"] = r["watertight"] and r["winding_consistent"] and r["volume_ml"] > 0
    if self_intersections:
        r["self_intersecting_faces"] = count_self_intersections(m)
    return r


def count_self_intersections(m):
    try:
        import pymeshlab
    except ImportError:
        return None
    ms = pymeshlab.MeshSet()
    ms.add_mesh(pymeshlab.Mesh(vertex_matrix=np.asarray(m.vertices, float),
                               face_matrix=np.asarray(m.faces, np.int32)))
    ms.compute_selection_by_self_intersections_per_face()
    return int(ms.current_mesh().selected_face_number())


def distances(points, mesh, chunk=20000):
    """Exact distance from each point to the triangle mesh (trimesh, chunked for memory)."""
    out = np.empty(len(points))
    for i in range(0, len(points), chunk):
        _, d, _ = trimesh.proximity.closest_point(mesh, points[i:i + chunk])
        out[i:i + chunk] = d
    return out


def vertex_weights(m):
    w = np.zeros(len(m.vertices))
    for k in range(3):
        np.add.at(w, m.faces[:, k], m.area_faces / 3.0)
    return w


def mssd(a, b, n, seed):
    """a, b: trimesh meshes. Sampled and vertex-weighted symmetric surface distance."""
    pa, _ = trimesh.sample.sample_surface(a, n, seed=seed)
    pb, _ = trimesh.sample.sample_surface(b, n, seed=seed + 1)
    da, db = distances(pa, b), distances(pb, a)
    both = np.concatenate([da, db])
    s = {"mssd_mm": 0.5 * (da.mean() + db.mean()), "a_to_b_mm": da.mean(),
         "b_to_a_mm": db.mean(), "p95_mm": np.percentile(both, 95), "max_mm": both.max()}
    va, vb = distances(a.vertices, b), distances(b.vertices, a)
    wa, wb = vertex_weights(a), vertex_weights(b)
    ma, mb = (va * wa).sum() / wa.sum(), (vb * wb).sum() / wb.sum()
    bothv = np.concatenate([va, vb])
    v = {"mssd_mm": 0.5 * (ma + mb), "a_to_b_mm": ma, "b_to_a_mm": mb,
         "p95_mm": np.percentile(bothv, 95), "max_mm": bothv.max()}
    return ({k: float(x) for k, x in s.items()}, {k: float(x) for k, x in v.items()})


def compare(lungdyn, sampled, vertexw):
    ld = lungdyn["mssd_mm"]
    tol = TOL_ABS_MM + TOL_REL * ld
    out = {"lungdyn": {k: lungdyn.get(k) for k in
                       ("mssd_mm", "exhale_to_inhale_mm", "inhale_to_exhale_mm", "p95_mm", "max_mm")},
           "checker_sampled": sampled, "checker_vertex_weighted": vertexw,
           "tolerance_mm": tol,
           "diff_sampled_mm": sampled["mssd_mm"] - ld,
           "diff_vertex_weighted_mm": vertexw["mssd_mm"] - ld,
           "diff_directed_sampled_mm": [sampled["a_to_b_mm"] - lungdyn["exhale_to_inhale_mm"],
                                        sampled["b_to_a_mm"] - lungdyn["inhale_to_exhale_mm"]]}
    out["agrees"] = bool(abs(out["diff_sampled_mm"]) <= tol and
                         abs(out["diff_vertex_weighted_mm"]) <= tol)
    return out


def main():
    ap = argparse.ArgumentParser(description=__doc__.split("\n")[0])
    ap.add_argument("--dir", required=True, help="fit-motion --surfaces-out folder")
    ap.add_argument("--lung", required=True, choices=["right", "left"])
    ap.add_argument("--fit-json", required=True, help="fit-motion --json output (stdout) file")
    ap.add_argument("--samples", type=int, default=200000)
    ap.add_argument("--seed", type=int, default=46)
    ap.add_argument("--no-self-intersections", action="store_true")
    ap.add_argument("--out", help="also write the JSON here")
    a = ap.parse_args()

    fit = json.load(open(a.fit_json))
    lung = next(l for l in fit["lungs"] if l.get("side") == a.lung)
    names = ("exhale", "moved", "inhale_aligned")
    paths = {n: f"{a.dir}/{a.lung}_{n}.ply" for n in names}
    meshes = {n: trimesh.load(p, force="mesh", process=False) for n, p in paths.items()}
    # process=False: keep the file's own vertex indexing (no merging), so topology is as written.
    rep = {n: dict(file=paths[n], **mesh_report(meshes[n], not a.no_self_intersections))
           for n in names}
    failures = [f"{n}: not watertight / inconsistent winding / non-positive volume"
                for n in names if not rep[n]["ok"]]

    ve, vm, vi = (rep[n]["volume_ml"] for n in names)
    vol = {"exhale_ml": ve, "moved_ml": vm, "inhale_aligned_ml": vi,
           "json_exhale_ml": lung.get("exhale_ml"), "json_inhale_ml": lung.get("inhale_ml"),
           "moved_vs_inhale_rel": vm / vi - 1.0,
           "exhale_vs_json_rel": ve / lung["exhale_ml"] - 1.0,
           "inhale_aligned_vs_json_rel": vi / lung["inhale_ml"] - 1.0,
           "moved_same_faces_as_exhale": bool(
               np.array_equal(meshes["moved"].faces, meshes["exhale"].faces))}
    if abs(vol["moved_vs_inhale_rel"]) > VOL_TOL:
        failures.append(f"moved volume differs from inhale_aligned by "
                        f"{100 * vol['moved_vs_inhale_rel']:+.3f} %")
    if abs(vol["exhale_vs_json_rel"]) > VOL_TOL:
        failures.append(f"exhale volume differs from JSON exhale_ml by "
                        f"{100 * vol['exhale_vs_json_rel']:+.3f} %")
    if not vol["moved_same_faces_as_exhale"]:
        failures.append("moved surface does not have the exhale surface's faces")

    ex, mv, ia = meshes["exhale"], meshes["moved"], meshes["inhale_aligned"]
    c = np.asarray(ex.center_mass)
    s = (vi / ve) ** (1.0 / 3.0)
    scaled = trimesh.Trimesh(vertices=c + s * (np.asarray(ex.vertices) - c), faces=ex.faces,
                             process=False)
    cv = np.asarray(ex.vertices).mean(axis=0)  # lungdyn's centre: the plain vertex mean
    scaled_vm = trimesh.Trimesh(vertices=cv + s * (np.asarray(ex.vertices) - cv), faces=ex.faces,
                                process=False)
    pairs = {"in_sample": mv, "no_motion": ex, "uniform_scaling": scaled,
             "uniform_scaling_vertex_mean_centre": scaled_vm}
    out_mssd = {}
    for key, m in pairs.items():
        smp, vw = mssd(m, ia, a.samples, a.seed)
        out_mssd[key] = compare(lung[key.split("_vertex")[0]], smp, vw)
        if not out_mssd[key]["agrees"]:
            failures.append(f"{key}: checker MSSD {smp['mssd_mm']:.3f} (sampled) / "
                            f"{vw['mssd_mm']:.3f} (vertex-weighted) vs lungdyn "
                            f"{lung[key]['mssd_mm']:.3f} mm, tolerance "
                            f"{out_mssd[key]['tolerance_mm']:.3f}")
    out_mssd["uniform_scaling"]["scale"] = s
    out_mssd["uniform_scaling"]["centre_mm"] = c.tolist()
    out_mssd["uniform_scaling_vertex_mean_centre"]["centre_mm"] = cv.tolist()
    out_mssd["uniform_scaling_vertex_mean_centre"]["note"] = (
        "same scale about the exhale's vertex mean (what lungdyn's patient_motion.rs uses) "
        "instead of its volume centroid: separates a distance error from a centre choice")
    if "cross_validated" in lung:
        out_mssd["cross_validated_lungdyn_only"] = lung["cross_validated"]

    result = {
        "tool": "bench/pair_check.py (trimesh %s, numpy %s)" % (trimesh.__version__, np.__version__),
        "fit_json": a.fit_json, "dir": a.dir, "lung": a.lung,
        "exhale_input": fit.get("exhale"), "inhale_input": fit.get("inhale"),
        "alignment_translation_mm": lung.get("alignment", {}).get("translation_mm"),
        "samples_per_surface": a.samples, "seed": a.seed,
        "tolerance": f"|checker - lungdyn| <= {TOL_ABS_MM} mm + {100 * TOL_REL:.0f} % of lungdyn "
                     "(sampled vs area-weighted vertex means estimate the same integral but "
                     "differ slightly); volumes within 0.1 %",
        "meshes": rep, "volumes": vol, "mssd": out_mssd,
        "failures": failures, "ok": not failures,
        "directions": "a_to_b = the moved/exhale/scaled surface to inhale_aligned "
                      "(lungdyn's exhale_to_inhale), b_to_a = inhale_aligned to it",
    }
    text = json.dumps(result, indent=2)
    print(text)
    if a.out:
        with open(a.out, "w") as f:
            f.write(text + "\n")
    sys.exit(0 if not failures else 1)


if __name__ == "__main__":
    main()
