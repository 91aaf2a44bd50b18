#!/usr/bin/env python3
"""A population motion from the shared breath-hold pairs, judged leave-one-patient-out (issue 34
item 4: built in as `directions = "breath-hold"`, the motion `lungdyn patient` bakes into a patient's
lung without a fit it can draw, where it draws the lung's tidal share without a fold; the generated
lungs keep the built-in motion).

Each patient's fitted motion (`fit-motion --exhale/--inhale`: a direction field and an applied force
field, polynomials in the lung's box coordinates) is made scale-free (each field divided by its RMS
over the box), and the population motion of a side is the mean of the OTHER five patients' fields.
It is baked on the held-out patient's exhale surface (`lungdyn bake --motion`), driven to that
patient's inhale volume (`lungdyn kernel export --delta-ml`) and measured against the aligned inhale
surface with trimesh (area-weighted vertex means of exact point-to-triangle distances, both ways —
lungdyn's definition, bench/pair_check.py checks it agrees), beside no motion and uniform scaling.
Each drawn surface is checked for folds (`lungdyn mesh check`) at the inhale volume and at the lung's
share of a tidal breath (--tidal-ml shared by the two lungs' exhale volumes).

Inputs: per case and lung, a fit's JSON (with the fields, from bench/patient_motion.py's
--json-dir, run with --force-centres 0: the population averages the polynomial fields, and a fit's
local force terms sit on that patient's own surface) and a --surfaces-out folder of the same case
(exhale surface and aligned inhale).

    python3 bench/population_motion.py --fits /tmp/lungdyn-patient-motion --surfaces /tmp/popsurf \
        [--lungdyn target/release/lungdyn] [--out docs/masks/population_motion.md]
"""
import argparse, json, os, subprocess, sys, tempfile, time

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from pyneeds import need  # noqa: E402
need(["numpy", "trimesh", "rtree", "scipy"], __file__)

import numpy as np
import trimesh

ROOT = os.path.dirname(os.path.dirname(os.path.abspath(__file__)))
CASES = ["05", "06", "07", "08", "09", "10"]


def monomials(degree):
    out = []
    for t in range(degree + 1):
        for i in range(t, -1, -1):
            for j in range(t - i, -1, -1):
                out.append((i, j, t - i - j))
    return out


GRID = np.stack(np.meshgrid(*[np.linspace(-1, 1, 7)] * 3, indexing="ij"), -1).reshape(-1, 3)


def basis(degree):
    return np.stack([GRID[:, 0] ** a * GRID[:, 1] ** b * GRID[:, 2] ** c for a, b, c in monomials(degree)], 1)


def normalised(fit):
    """The fit's direction coefficients (m×3) and force coefficients (m), each over its RMS on the box."""
    if fit["force"].get("centres"):
        # Local terms sit on that patient's own surface: they have no place on another lung's.
        sys.exit("population_motion.py: a fit has local force terms (fit-motion --force-centres); "
                 "the population averages polynomial fits: run bench/patient_motion.py --force-centres 0")
    d = np.array(fit["direction"]["coeffs"], float)
    f = np.array(fit["force"]["coeffs"], float)
    dv = basis(fit["direction"]["degree"]) @ d
    fv = basis(fit["force"]["degree"]) @ f
    # u = F·d is unchanged when both change sign: make the force positive on average, so that
    # patients' fits do not cancel in the mean.
    sign = 1.0 if fv.mean() >= 0 else -1.0
    return sign * d / np.sqrt((dv ** 2).sum(1).mean()), sign * f / np.sqrt((fv ** 2).mean())


def toml_field(name, degree, coeffs, vector):
    rows = ", ".join("[" + ", ".join(f"{v:.12g}" for v in c) + "]" for c in coeffs) if vector else \
        ", ".join(f"{v:.12g}" for v in coeffs)
    model = 'model = "poly"\n' if vector else ""
    return f"[{name}]\n{model}lo = [-1.0, -1.0, -1.0]\nhi = [1.0, 1.0, 1.0]\ndegree = {degree}\ncoeffs = [{rows}]\n\n"


def mssd(a, b):
    def directed(x, y):
        _, dist, _ = trimesh.proximity.closest_point(y, x.vertices)
        area = np.zeros(len(x.vertices))
        for k in range(3):
            np.add.at(area, x.faces[:, k], x.area_faces / 3.0)
        return (area * dist).sum() / area.sum()
    return 0.5 * (directed(a, b) + directed(b, a))


def run(cmd):
    p = subprocess.run(cmd, capture_output=True, text=True)
    if p.returncode != 0:
        raise SystemExit(f"{' '.join(cmd)}: exit {p.returncode}: {p.stderr[-400:]}")
    return p.stdout


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--fits", required=True)
    ap.add_argument("--surfaces", required=True)
    ap.add_argument("--lungdyn", default=os.path.join(ROOT, "target", "release", "lungdyn"))
    ap.add_argument("--out", default=os.path.join(ROOT, "docs", "masks", "population_motion_table.md"))
    ap.add_argument("--tidal-ml", type=float, default=500.0,
                    help="the tidal breath shared by both lungs in proportion to their exhale volumes "
                         "(the default scene's, 500 ml): the share each lung must draw without a fold")
    ap.add_argument("--write-population", metavar="TOML",
                    help="also write the population motion of all six patients (both lungs) there")
    a = ap.parse_args()
    fits = {(c, s): json.load(open(os.path.join(a.fits, f"case_{c}_{s}.json")))["lungs"][0]
            for c in CASES for s in ["right", "left"]}
    rows, t0 = [], time.time()
    tmp = tempfile.mkdtemp(prefix="lungdyn-population-")
    for c in CASES:
        for s in ["right", "left"]:
            others = [normalised(fits[(o, s)]) for o in CASES if o != c]
            d = np.mean([x[0] for x in others], 0)
            f = np.mean([x[1] for x in others], 0)
            fit = fits[(c, s)]
            motion = os.path.join(tmp, f"pop_{c}_{s}.toml")
            open(motion, "w").write(
                'format = 2\nframe = "body (box coordinates)"\nchosen = "population, leave-one-out"\n\n'
                + toml_field(f"{s}_field", fit["direction"]["degree"], d, True)
                + toml_field(f"{s}_force", fit["force"]["degree"], f, False))
            surf = os.path.join(a.surfaces, f"case_{c}")
            exhale = os.path.join(surf, f"{s}_exhale.ply")
            kernel = os.path.join(tmp, f"pop_{c}_{s}.kernel")
            # --frame body: these surfaces are in the body frame by construction (mesh from-mask); the
            # surface-only orientation check misreads case 06 left's flat diaphragm without it.
            run([a.lungdyn, "bake", "--mesh", exhale, "--frame", "body", "--lung", s, "--motion", motion,
                 "--out", kernel])
            drawn = os.path.join(tmp, f"pop_{c}_{s}.ply")
            dv = fit["inhale_ml"] - fit["exhale_ml"]
            run([a.lungdyn, "kernel", "export", kernel, "--delta-ml", f"{dv}", "--out", drawn])
            target = trimesh.load(os.path.join(surf, f"{s}_inhale_aligned.ply"), process=False)
            m = mssd(trimesh.load(drawn, process=False), target)
            # lungdyn's own check of the drawn surface: refused when it crosses itself (a fold).
            chk = subprocess.run([a.lungdyn, "mesh", "check", "--mesh", drawn, "--frame", "body"],
                                 capture_output=True, text=True)
            folds = "intersects itself" in chk.stderr
            # The same at the lung's share of a tidal breath (what `lungdyn patient` asks of it).
            both = fits[(c, "right")]["exhale_ml"] + fits[(c, "left")]["exhale_ml"]
            share = a.tidal_ml * fit["exhale_ml"] / both
            tidal = os.path.join(tmp, f"pop_{c}_{s}_tidal.ply")
            run([a.lungdyn, "kernel", "export", kernel, "--delta-ml", f"{share}", "--out", tidal])
            chk = subprocess.run([a.lungdyn, "mesh", "check", "--mesh", tidal, "--frame", "body"],
                                 capture_output=True, text=True)
            tidal_folds = (share, "intersects itself" in chk.stderr)
            rows.append((c, s, dv, fit["no_motion"]["mssd_mm"], fit["uniform_scaling"]["mssd_mm"], m,
                         fit["cross_validated"]["mssd_mm"], folds, tidal_folds))
            print(f"case {c} {s}: population (others) {m:.2f} mm; no motion {rows[-1][3]:.2f}, "
                  f"scaling {rows[-1][4]:.2f}, own fit held out {rows[-1][6]:.2f}", file=sys.stderr)
    lines = ["| case | lung | ΔV ml | no motion | uniform scaling | **population of the other 5 patients** | folds at inhale | folds at its tidal share (ml) | own fit, held out |",
             "|---|---|---|---|---|---|---|---|---|"]
    for c, s, dv, n, u, m, cv, folds, (share, tfolds) in rows:
        best = m < min(n, u)
        lines.append(f"| {c} | {s} | {dv:+.0f} | {n:.2f} | {u:.2f} | {'**' if best else ''}{m:.2f}{'**' if best else ''} "
                     f"| {'yes' if folds else 'no'} | {'yes' if tfolds else 'no'} (+{share:.0f}) | {cv:.2f} |")
    wins = sum(1 for r in rows if r[5] < min(r[3], r[4]))
    mean = lambda k: np.mean([r[k] for r in rows])
    lines += ["", f"Means (MSSD, mm): no motion {mean(3):.2f}, uniform scaling {mean(4):.2f}, population "
              f"(leave-one-patient-out) {mean(5):.2f}, each patient's own fit held out {mean(6):.2f}. The "
              f"population beats both baselines on {wins} of {len(rows)} lungs (bold); it draws its lung's "
              f"share of a {a.tidal_ml:.0f} ml tidal breath without a fold on "
              f"{sum(1 for r in rows if not r[8][1])} of {len(rows)}.",
              "", f"Measured {time.strftime('%Y-%m-%d %H:%M UTC', time.gmtime())}, {os.cpu_count()} CPUs, "
              f"{time.time() - t0:.0f} s, with `python3 bench/population_motion.py --fits DIR --surfaces DIR`."]
    if a.write_population:
        text = ('# lungdyn motion: the population of the six shared COPDgene breath-hold pairs (DIR-Lab cases\n'
                '# 05-10), each fitted by `fit-motion --exhale/--inhale`, made scale-free and averaged per lung\n'
                '# (bench/population_motion.py; docs/masks/population_motion.md). Fields in box coordinates.\n'
                'format = 2\nframe = "body (box coordinates)"\nchosen = "population of six breath-hold pairs"\n\n')
        for s in ["right", "left"]:
            allf = [normalised(fits[(o, s)]) for o in CASES]
            ref = fits[(CASES[0], s)]
            text += toml_field(f"{s}_field", ref["direction"]["degree"], np.mean([x[0] for x in allf], 0), True)
            text += toml_field(f"{s}_force", ref["force"]["degree"], np.mean([x[1] for x in allf], 0), False)
        open(a.write_population, "w").write(text)
        lines.append(f"The population of all six (both lungs) written to `{os.path.relpath(a.write_population, ROOT)}`.")
    print("\n".join(lines))
    if a.out:
        open(a.out, "w").write("\n".join(lines) + "\n")


if __name__ == "__main__":
    main()
