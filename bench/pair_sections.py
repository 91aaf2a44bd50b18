#!/usr/bin/env python3
"""Sections through a breath-hold pair's fit, to look at rather than read: the exhale surface, the
fitted kernel at the inhale volume and the real (aligned) inhale surface, cut by the sagittal and
coronal planes through the exhale lung's centroid (trimesh sections, matplotlib).

    python3 bench/pair_sections.py --dir FIT_DIR --lung right --title "case 05" --out sections.png

FIT_DIR is a `lungdyn fit-motion --exhale/--inhale --surfaces-out FIT_DIR` folder.
"""
import argparse, os, sys

sys.path.insert(0, os.path.dirname(os.path.abspath(__file__)))
from pyneeds import need  # noqa: E402
need(["matplotlib", "numpy", "trimesh"], __file__)

import matplotlib
matplotlib.use("Agg")
import matplotlib.pyplot as plt
import numpy as np
import trimesh


def main():
    ap = argparse.ArgumentParser(description=__doc__, formatter_class=argparse.RawDescriptionHelpFormatter)
    ap.add_argument("--dir", required=True)
    ap.add_argument("--lung", required=True, choices=["right", "left"])
    ap.add_argument("--title", default="")
    ap.add_argument("--out", required=True)
    a = ap.parse_args()
    load = lambda w: trimesh.load(os.path.join(a.dir, f"{a.lung}_{w}.ply"), process=False)
    meshes = [("exhale", load("exhale"), "#7f7f7f", "--"),
              ("fitted kernel at the inhale volume", load("moved"), "#d62728", "-"),
              ("real inhale (aligned)", load("inhale_aligned"), "#1f77b4", "-")]
    c = meshes[0][1].center_mass
    # Body frame: +X patient left, +Y anterior, +Z superior.
    views = [("sagittal (x = centroid): anterior →", [1, 0, 0], (1, 2), "Y (anterior) mm"),
             ("coronal (y = centroid): patient's left →", [0, 1, 0], (0, 2), "X (patient's left) mm")]
    fig, axes = plt.subplots(1, 2, figsize=(11, 6.2))
    for ax, (name, normal, (u, v), xlabel) in zip(axes, views):
        for label, m, colour, style in meshes:
            s = m.section(plane_origin=c, plane_normal=normal)
            if s is None:
                continue
            first = True
            for seg in s.discrete:
                ax.plot(seg[:, u], seg[:, v], style, color=colour, lw=1.6, label=label if first else None)
                first = False
        ax.set_aspect("equal")
        ax.set_title(name, fontsize=10)
        ax.set_xlabel(xlabel)
        ax.set_ylabel("Z (superior) mm")
        ax.grid(alpha=0.3)
    axes[0].legend(loc="lower left", fontsize=8)
    fig.suptitle(f"{a.title} {a.lung} lung: exhale, the fitted kernel at the inhale volume, the real inhale", fontsize=11)
    fig.tight_layout()
    fig.savefig(a.out, dpi=110)
    print(f"wrote {a.out}")


if __name__ == "__main__":
    main()
