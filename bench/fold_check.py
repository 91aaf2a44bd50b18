#!/usr/bin/env python3
"""Independent check of a kernel's recorded fold-free range (`KernelMeta::fold_free`) with MeshLab.

lungdyn's bake records how far from its start volume a lung is drawn before its surface crosses
itself (`lungdyn kernel inspect K --json`: meta.fold_free). This script exports the kernel's surface
at volumes around each recorded end (`lungdyn kernel export K --delta-ml D`) and counts the
self-intersecting faces of each with MeshLab's own test (pymeshlab,
`compute_selection_by_self_intersections_per_face`), beside lungdyn's count of crossing pairs
(`kernel export`'s `self_intersections`, capped at 16). It shares no geometry code with lungdyn.

    python3 bench/fold_check.py --kernel right.kernel [--lungdyn target/release/lungdyn]
        [--extra=-20,-25] [--json out.json]

Each end is checked just inside it (must be clean) and one refinement step past it (must cross, when
the search found a fold there; the step is 1/768 of the span searched). `--extra` adds volumes (ml
from the start volume) to check, e.g. a crossing that comes and goes (write `--extra=-20`: a bare
leading minus reads as an option). Exits 1 when MeshLab disagrees with the recorded range, 2 when a
package, the binary or an argument is wrong, 3 when lungdyn refuses the kernel or has no range.
"""
import argparse
import importlib.metadata
import json
import os
import subprocess
import sys
import tempfile

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from pyneeds import need  # noqa: E402

need(["pymeshlab"], __file__)

import pymeshlab  # noqa: E402

STEP = 1.0 / 768.0  # the bake's refinement: 1/24 of the span, then 5 bisection steps


def run(cmd):
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        print(f"{' '.join(cmd)} failed ({p.returncode}): {p.stderr.strip()}", file=sys.stderr)
        sys.exit(3)
    return p.stdout


def meshlab_faces(path):
    ms = pymeshlab.MeshSet()
    ms.load_new_mesh(path)
    ms.apply_filter("compute_selection_by_self_intersections_per_face")
    return ms.current_mesh().selected_face_number()


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--kernel", required=True)
    ap.add_argument("--lungdyn", default=os.path.join(os.path.dirname(os.path.dirname(
        os.path.abspath(__file__))), "target", "release", "lungdyn"))
    ap.add_argument("--extra", default="",
                    help="comma-separated further volume changes, ml (--extra=-20,-25)")
    ap.add_argument("--json", help="write the rows here too")
    a = ap.parse_args()
    if not os.path.exists(a.lungdyn):
        print(f"{a.lungdyn}: no lungdyn binary (cargo build --release -p lungdyn)", file=sys.stderr)
        sys.exit(2)
    meta = json.loads(run([a.lungdyn, "kernel", "inspect", a.kernel, "--json"]))["meta"]
    ff = meta.get("fold_free")
    if ff is None:
        print(f"{a.kernel}: no fold-free range recorded (baked by an older lungdyn)", file=sys.stderr)
        sys.exit(3)
    checks = []  # (delta ml, expected to cross: True, False or None)
    for sign, end, span in [(1, ff["above_ml"], ff["searched_above_ml"]),
                            (-1, ff["below_ml"], ff["searched_below_ml"])]:
        checks.append((sign * end * (1 - 1e-6), False))
        if end < span:
            checks.append((sign * (end + STEP * span * 1.0001), True))
    for d in filter(None, a.extra.split(",")):
        try:
            checks.append((float(d), None))
        except ValueError:
            ap.error(f"--extra: {d!r} is not a volume change in ml")
    rows, bad = [], 0
    with tempfile.TemporaryDirectory() as tmp:
        for delta, crosses in checks:
            out = os.path.join(tmp, "d.ply")
            e = json.loads(run([a.lungdyn, "kernel", "export", a.kernel, "--delta-ml",
                                f"{delta:.6f}", "--out", out, "--json"]))
            faces = meshlab_faces(out)
            ok = crosses is None or (faces > 0) == crosses
            bad += not ok
            rows.append({"delta_ml": round(delta, 3), "lungdyn_pairs": e["self_intersections"],
                         "meshlab_faces": faces, "expected": crosses, "agrees": ok})
            print(f"{delta:+10.2f} ml  lungdyn pairs {e['self_intersections']:2d}  MeshLab faces "
                  f"{faces:3d}  {'' if crosses is None else ('crosses' if crosses else 'clean')}"
                  f"{'' if ok else '  DISAGREES'}")
    print(f"{a.kernel}: recorded {ff['above_ml']:+.1f} / -{ff['below_ml']:.1f} ml; "
          f"{'MeshLab agrees' if not bad else f'{bad} check(s) disagree'}")
    if a.json:
        with open(a.json, "w") as w:
            json.dump({"kernel": a.kernel, "fold_free": ff,
                       "pymeshlab": importlib.metadata.version("pymeshlab"), "rows": rows}, w, indent=1)
    sys.exit(1 if bad else 0)


if __name__ == "__main__":
    main()
