#!/usr/bin/env python3
"""bench/mask_check.py on ONE lung of a one-label mask whose two lungs touch (one 6-connected
component, where --keep-component left|right silently keeps both lungs).

The sides are separated here, independently of lungdyn: the mask is eroded (6-connectivity) until its
two largest components each hold >= 10 % of the larger, and these two cores are grown back over the
mask by a watershed on the negated distance transform (mm), so the cut falls on the narrowest neck.
--side left|right means what the checker's --keep-component left|right means: the part with the
larger|smaller body X in the frame the checker reads from the HEADER (body: +X patient left).  For the
COPDgene masks, whose headers turn the patient half a turn about the long axis, the anatomical right
lung is --side left (and the mesh must be turned back into the header's frame first).
Nothing is written but the checker's JSON on stdout.

  python3 docs/masks/split_check.py --side left|right --mask M --mesh MESH   (run from the repo root)
"""
import sys, numpy as np
from scipy import ndimage
from skimage.segmentation import watershed
sys.path.insert(0, "bench")
import mask_check

side = sys.argv[sys.argv.index("--side") + 1]
i = sys.argv.index("--side"); del sys.argv[i:i + 2]
orig = mask_check.load_mask


def load(path):
    data, aff, info = orig(path)
    m = data != 0
    cur, it = m.copy(), 0
    while True:
        lab, n = ndimage.label(cur)
        sizes = np.bincount(lab.ravel())[1:]
        if n >= 2 and np.sort(sizes)[-2] >= 0.1 * sizes.max():
            break
        cur, it = ndimage.binary_erosion(cur), it + 1
        if it > 40 or not cur.any():
            sys.exit("split_check: no two cores after 40 erosions")
    big = np.argsort(sizes)[::-1][:2] + 1
    x = [(np.argwhere(lab == c).mean(0) @ aff[:3, :3].T)[0] for c in big]
    markers = np.zeros(m.shape, np.int32)
    markers[lab == big[int(np.argmin(x))]] = 1   # --side right: smaller body X
    markers[lab == big[int(np.argmax(x))]] = 2   # --side left: larger body X
    sp = np.linalg.norm(aff[:3, :3], axis=0)
    ws = watershed(-ndimage.distance_transform_edt(m, sampling=sp), markers, mask=m)
    info["split"] = {"side": side, "erosions": it, "smaller_x_voxels": int((ws == 1).sum()), "larger_x_voxels": int((ws == 2).sum()),
                     "unreached_voxels": int((m & (ws == 0)).sum()),
                     "method": "erode (6-conn) to two cores >= 10 %, watershed on -EDT(mm) within the mask"}
    return ws.astype(np.int16), aff, info


mask_check.load_mask = load
sys.argv += ["--label", "1" if side == "right" else "2", "--keep-component", "largest"]
mask_check.main()
