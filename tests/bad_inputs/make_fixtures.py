#!/usr/bin/env python3
"""Regenerates the fixtures of the bad-input battery (tests/bad_inputs/) from the lungdyn binary.

    python3 tests/bad_inputs/make_fixtures.py [path/to/lungdyn]     (default: target/release/lungdyn)

Needs only the binary and the Python standard library. `LUNGDYN_FIXTURES_ONLY=recordings` remakes
only the ventilator recordings (rec_*.csv, made here without the binary) and removes nothing. The good base files come from the binary
(`mesh generate`, `bake`, `kernel export`, `pv simulate`, `pv fit`, `fit-motion`); every bad file is
derived from them here, one defect each, so a refusal can only be for that defect. Large inputs
(3 GiB sparse files, /dev/zero, /dev/urandom, a FIFO) are not files here: the harness makes them from
the placeholders of cases.toml. `LUNGDYN_FIXTURES_ONLY=render-files` remakes only the calibration,
fiducial and HMD optics files (and the scenes naming them) and removes nothing;
`LUNGDYN_FIXTURES_ONLY=signal-traces` remakes only the respiratory traces that are not breathing.
"""
import math, os, random, shutil, struct, subprocess, sys, tempfile, zlib

HERE = os.path.dirname(os.path.abspath(__file__))
ROOT = os.path.dirname(os.path.dirname(HERE))
BIN = sys.argv[1] if len(sys.argv) > 1 else os.path.join(ROOT, "target", "release", "lungdyn")
RNG = random.Random(20240611)


def without_section(kernel, kind, reseal):
    """`kernel` with section `kind` left out of its table (its bytes stay, unreferenced): a kernel
    written before that optional section existed (unchanged if it has none)."""
    b = bytearray(kernel)
    count = struct.unpack_from("<I", b, 16)[0]
    entries = [bytes(b[64 + 32 * j:96 + 32 * j]) for j in range(count)]
    kept = [e for e in entries if struct.unpack_from("<I", e, 0)[0] != kind]
    assert len(kept) >= count - 1, "at most one section of that kind"
    b[64:64 + 32 * count] = b"".join(kept) + bytes(32 * (count - len(kept)))
    struct.pack_into("<I", b, 16, len(kept))
    return reseal(b)


def run(*args):
    subprocess.run([BIN, *args], check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)


def out(name, data):
    mode = "wb" if isinstance(data, (bytes, bytearray)) else "w"
    with open(os.path.join(HERE, name), mode, **({} if mode == "wb" else {"newline": ""})) as f:
        f.write(data)


# ---------------------------------------------------------------- meshes
def read_obj(path):
    v, f = [], []
    for line in open(path):
        s = line.split()
        if not s:
            continue
        if s[0] == "v":
            v.append(tuple(float(x) for x in s[1:4]))
        elif s[0] == "f":
            f.append(tuple(int(x.split("/")[0]) - 1 for x in s[1:]))
    return v, f


def obj(v, f, head="# lungdyn bad-input fixture\n", fmt="%.7g"):
    fv = "v " + " ".join([fmt] * 3) + "\n"
    return head + "".join(fv % tuple(p) for p in v) + "".join(
        "f " + " ".join(str(i + 1) for i in t) + "\n" for t in f)


def ply_ascii(v, f, extra_header=""):
    return ("ply\nformat ascii 1.0\n%selement vertex %d\nproperty float x\nproperty float y\n"
            "property float z\nelement face %d\nproperty list uchar int vertex_indices\nend_header\n"
            % (extra_header, len(v), len(f))
            + "".join("%.7g %.7g %.7g\n" % tuple(p) for p in v)
            + "".join("%d %s\n" % (len(t), " ".join(map(str, t))) for t in f))


def ply_binary(v, f, endian="<", nv=None, nf=None):
    fmt = {"<": "binary_little_endian", ">": "binary_big_endian"}[endian]
    head = ("ply\nformat %s 1.0\nelement vertex %d\nproperty float x\nproperty float y\nproperty float z\n"
            "element face %d\nproperty list uchar uint vertex_indices\nend_header\n"
            % (fmt, len(v) if nv is None else nv, len(f) if nf is None else nf)).encode()
    body = b"".join(struct.pack(endian + "3f", *p) for p in v)
    body += b"".join(struct.pack(endian + "B3I", 3, *t) for t in f)
    return head + body


def normal(a, b, c):
    u = [b[i] - a[i] for i in range(3)]; w = [c[i] - a[i] for i in range(3)]
    n = [u[1] * w[2] - u[2] * w[1], u[2] * w[0] - u[0] * w[2], u[0] * w[1] - u[1] * w[0]]
    l = math.sqrt(sum(x * x for x in n)) or 1.0
    return [x / l for x in n]


def stl_ascii(v, f, name="lung", normals=True):
    s = ["solid %s\n" % name]
    for t in f:
        a, b, c = (v[i] for i in t)
        s.append(" facet normal %.4g %.4g %.4g\n  outer loop\n" % tuple(normal(a, b, c) if normals else (0, 0, 0)))
        for p in (a, b, c):
            s.append("   vertex %.7g %.7g %.7g\n" % tuple(p))
        s.append("  endloop\n endfacet\n")
    s.append("endsolid %s\n" % name)
    return "".join(s)


def stl_binary(v, f, header=b"lungdyn bad-input fixture", count=None):
    h = header.ljust(80, b" ")[:80]
    body = b"".join(struct.pack("<12fH", *normal(*(v[i] for i in t)), *v[t[0]], *v[t[1]], *v[t[2]], 0)
                    for t in f)
    return h + struct.pack("<I", len(f) if count is None else count) + body


def scaled(v, s):
    return [tuple(c * s for c in p) for p in v]


def moved(v, dx=0.0, dy=0.0, dz=0.0):
    return [(p[0] + dx, p[1] + dy, p[2] + dz) for p in v]


def make_meshes(tmp):
    run("mesh", "generate", "--lung", "left", "--vertices", "100", "--out", os.path.join(tmp, "l.obj"))
    run("mesh", "generate", "--lung", "right", "--vertices", "100", "--out", os.path.join(tmp, "r.obj"))
    run("mesh", "generate", "--lung", "left", "--vertices", "1900", "--out", os.path.join(HERE, "lung_left_1946.ply"))
    shutil.copy(os.path.join(tmp, "l.obj"), os.path.join(HERE, "lung_left.obj"))
    shutil.copy(os.path.join(tmp, "r.obj"), os.path.join(HERE, "lung_right.obj"))
    v, f = read_obj(os.path.join(tmp, "l.obj"))
    rv, rf = read_obj(os.path.join(tmp, "r.obj"))
    n = len(v)
    # the same lung in every format the importer reads
    out("lung_left_ascii.ply", ply_ascii(v, f))
    out("lung_left_be.ply", ply_binary(v, f, ">"))
    out("lung_left_ascii.stl", stl_ascii(v, f))
    out("lung_left_binary.stl", stl_binary(v, f))
    out("lung_left_solid_header_binary.stl", stl_binary(v, f, header=b"solid exported by a segmentation tool"))
    out("lung_left_crlf.obj", obj(v, f).replace("\n", "\r\n"))
    out("lung_left_negative_index.obj", "# relative (negative) face indices\n" + "".join(
        "v %.7g %.7g %.7g\n" % p for p in v) + "".join("f %d %d %d\n" % tuple(i - n for i in t) for t in f))
    out("lung_left_uppercase.OBJ", obj(v, f))
    out("lung_left.txt", obj(v, f))
    out("lung_left_noext", obj(v, f))
    # units
    out("mesh_metres.obj", obj(scaled(v, 1e-3), f))
    out("mesh_cm.obj", obj(scaled(v, 0.1), f))
    out("mesh_metres_binary.ply", ply_binary(scaled(v, 1e-3), f))
    out("mesh_x1e35.obj", obj(scaled(v, 1e35), f))
    out("mesh_x1e35.stl", stl_binary(scaled(v, 1e35), f))
    out("mesh_tiny_2mm.obj", obj(scaled(v, 0.01), f))
    out("mesh_huge_2400mm.obj", obj(scaled(v, 10.0), f))
    # one bad vertex
    for tag, val in (("nan", float("nan")), ("inf", float("inf")), ("1e308", 1e308)):
        w = list(v); w[7] = (val, w[7][1], w[7][2])
        out("mesh_%s_vertex.obj" % tag, obj(w, f))
    w = list(v); w[7] = (float("nan"),) * 3
    out("mesh_nan_vertex.ply", ply_binary(w, f))
    out("mesh_nan_vertex.stl", stl_binary(w, f))
    out("mesh_unused_far_vertex.obj", obj(v + [(1e35, 1e35, 1e35)], f))
    # topology
    out("mesh_two_shells.obj", obj(v + moved(v, dx=300.0), f + [tuple(i + n for i in t) for t in f]))
    out("mesh_two_shells_unequal.obj", obj(v + scaled(moved(v, dx=200.0), 0.8),
                                            f + [tuple(i + n for i in t) for t in f]))
    out("mesh_overlapping_copies.obj", obj(v + moved(v, dx=5.0), f + [tuple(i + n for i in t) for t in f]))
    out("mesh_identical_copies.obj", obj(v + v, f + [tuple(i + n for i in t) for t in f]))
    cx = sum(p[0] for p in v) / n; cy = sum(p[1] for p in v) / n; cz = sum(p[2] for p in v) / n
    inner = [(cx + (p[0] - cx) * 0.5, cy + (p[1] - cy) * 0.5, cz + (p[2] - cz) * 0.5) for p in v]
    out("mesh_hollow_inner_shell.obj", obj(v + inner, f + [(t[0] + n, t[2] + n, t[1] + n) for t in f]))
    xs = [p[0] for p in v]
    i_max = xs.index(max(xs))
    w = list(v); w[i_max] = (min(xs) - 60.0, w[i_max][1], w[i_max][2])
    out("mesh_self_intersecting.obj", obj(w, f))
    zs = [p[2] for p in v]; zm = (min(zs) + max(zs)) / 2
    out("mesh_folded.obj", obj([(p[0], p[1], 2 * zm - p[2] - 20.0) if p[2] > zm else p for p in v], f))
    out("mesh_open.obj", obj(v, f[:-3]))
    out("mesh_one_hole.obj", obj(v, f[:-1]))
    out("mesh_inside_out.obj", obj(v, [(t[0], t[2], t[1]) for t in f]))
    out("mesh_inconsistent_winding.obj", obj(v, [(t[0], t[2], t[1]) if k % 17 == 0 else t for k, t in enumerate(f)]))
    a, b = f[0][0], f[0][1]
    out("mesh_nonmanifold_fin.obj", obj(v + [(v[a][0] + 40, v[a][1] + 40, v[a][2])], f + [(a, b, n)]))
    out("mesh_degenerate_faces.obj", obj(v, f + [(0, 0, 1), (2, 3, 3), (5, 5, 5)]))
    out("mesh_duplicate_faces.obj", obj(v, f + f[:10]))
    sv, sf = [], []
    for t in f:
        sf.append(tuple(range(len(sv), len(sv) + 3))); sv.extend(v[i] for i in t)
    out("mesh_unwelded.obj", obj(sv, sf))
    out("mesh_unwelded.stl", stl_binary(v, f))  # STL is unwelded by nature: same as lung_left_binary
    # contents
    out("mesh_points_only.obj", obj(v, []))
    out("mesh_faces_only.obj", "".join("f %d %d %d\n" % tuple(i + 1 for i in t) for t in f))
    out("mesh_index_out_of_range.obj", obj(v, f[:-1] + [(0, 1, 99999)]))
    out("mesh_index_zero.obj", obj(v, f).replace("f 1 ", "f 0 ", 1))
    out("mesh_index_huge.obj", obj(v, f) + "f 1 2 99999999999999999999999\n")
    out("mesh_two_vertex_face.obj", obj(v, f) + "f 1 2\n")
    out("mesh_text_in_vertex.obj", obj(v, f).replace("v ", "v abc ", 1))
    out("mesh_empty.obj", "")
    out("mesh_comments_only.obj", "# nothing but a comment\n# and another\n")
    out("mesh_text.obj", "this is not a mesh, it is a sentence.\n")
    out("mesh_binary_junk.obj", bytes(RNG.getrandbits(8) for _ in range(4096)))
    out("mesh_binary_junk.stl", bytes(RNG.getrandbits(8) for _ in range(4096)))
    out("mesh_binary_junk.ply", b"ply\n" + bytes(RNG.getrandbits(8) for _ in range(4096)))
    out("mesh_nul_bytes.obj", b"\0" * 2048)
    out("mesh_non_utf8_comment.obj", ("# Lunge links, Gr\xf6\xdfe in mm\n".encode("latin-1") + obj(v, f).encode()))
    out("mesh_non_utf8_vertex.obj", obj(v, f).encode().replace(b"v ", b"v \xff\xfe", 1))
    out("mesh_long_vertex_line.obj", obj(v, f).replace("v ", "v " + "1.0 " * 17500, 1))
    # PLY specifics
    out("ply_header_only.ply", ply_ascii([], []))
    out("ply_truncated.ply", ply_binary(v, f)[:-700])
    out("ply_vertex_count_4e9.ply", ply_binary(v, f, nv=4000000000))
    out("ply_face_count_4e9.ply", ply_binary(v, f, nf=4000000000))
    out("ply_no_end_header.ply", ply_ascii(v, f).replace("end_header\n", ""))
    out("ply_bad_format.ply", ply_ascii(v, f).replace("format ascii 1.0", "format binary_middle_endian 1.0"))
    out("ply_index_out_of_range.ply", ply_ascii(v, f[:-1] + [(0, 1, 99999)]))
    out("ply_negative_index.ply", ply_ascii(v, f[:-1] + [(0, 1, -5)]))
    out("ply_no_faces.ply", ply_ascii(v, [])[:0] + ply_ascii(v, []))
    bad = bytearray(ply_binary(v, f)); p = bad.index(b"end_header\n") + 11 + 12 * n
    bad[p] = 255  # first face says 255 vertices
    out("ply_face_list_255.ply", bytes(bad))
    out("ply_text_in_vertex.ply", ply_ascii(v, f).replace("\n%r" % v[3][0], "\nbanana", 1))
    out("ply_double_props.ply", ply_ascii(v, f).replace("property float", "property double"))
    # STL specifics
    out("stl_count_4e9.stl", stl_binary(v, f, count=0xFFFFFFFF))
    out("stl_truncated.stl", stl_binary(v, f)[:-25])
    out("stl_zero_triangles.stl", stl_binary(v, [], count=0))
    out("stl_ascii_garbage.stl", "solid lung\n facet normal banana 0 0\n  outer loop\nendsolid\n")
    out("stl_ascii_truncated.stl", stl_ascii(v, f)[:len(stl_ascii(v, f)) // 2])
    out("stl_ascii_nan.stl", stl_ascii(v, f, normals=False).replace("vertex ", "vertex nan ", 1))
    # the other lung: the generated right lung, and the left mirrored (x -> -x, winding flipped)
    out("lung_right_as_left.obj", obj(rv, rf))
    out("lung_left_mirrored.obj", obj([(-p[0], p[1], p[2]) for p in v], [(t[0], t[2], t[1]) for t in f]))
    # the anatomical left lung (its base is lowest posteriorly) written in DICOM LPS (y -> -y,
    # winding flipped): read as the body frame, anterior and posterior are swapped
    run("mesh", "generate", "--lung", "left", "--vertices", "2000", "--out", os.path.join(tmp, "a.obj"))
    av, af = read_obj(os.path.join(tmp, "a.obj"))
    out("lung_left_lps.obj", obj([(p[0], -p[1], p[2]) for p in av], [(t[0], t[2], t[1]) for t in af]))
    return v, f, rv, rf


# ---------------------------------------------------------------- PV curves
def make_pv(tmp):
    c = os.path.join(tmp, "c.csv")
    run("pv", "simulate", "--preset", "venegas-human", "--samples", "50", "--out", c)
    rows = [l.rstrip("\n").split(",") for l in open(c)]
    shutil.copy(c, os.path.join(HERE, "pv_good.csv"))
    d = [(r[0], float(r[2]), float(r[3])) for r in rows[1:]]   # phase, p cmH2O, v ml
    def csv(header, fn, data=d):
        return header + "\n" + "".join(fn(ph, p, vol) + "\n" for ph, p, vol in data)
    out("pv_two_columns.csv", csv("pressure_cmH2O,volume_ml", lambda ph, p, vol: "%r,%r" % (p, vol)))
    out("pv_unnamed.csv", csv("a,b", lambda ph, p, vol: "%r,%r" % (p, vol)))
    out("pv_kpa.csv", csv("pressure_kPa,volume_ml", lambda ph, p, vol: "%r,%r" % (p * 0.0980665, vol)))
    out("pv_pa.csv", csv("pressure_Pa,volume_ml", lambda ph, p, vol: "%r,%r" % (p * 98.0665, vol)))
    out("pv_mmhg.csv", csv("Paw (mmHg),volume_ml", lambda ph, p, vol: "%r,%r" % (p * 0.735559, vol)))
    out("pv_hpa.csv", csv("pressure_hPa,volume_ml", lambda ph, p, vol: "%r,%r" % (p * 0.980665, vol)))
    out("pv_mbar.csv", csv("pressure_mbar,volume_ml", lambda ph, p, vol: "%r,%r" % (p * 0.980665, vol)))
    out("pv_psi.csv", csv("pressure_psi,volume_ml", lambda ph, p, vol: "%r,%r" % (p * 0.0142233, vol)))
    out("pv_litres_header.csv", csv("pressure_cmH2O,volume (L)", lambda ph, p, vol: "%r,%r" % (p, vol / 1000)))
    out("pv_dl_header.csv", csv("pressure_cmH2O,volume_dL", lambda ph, p, vol: "%r,%r" % (p, vol / 100)))
    out("pv_litres_unnamed.csv", csv("pressure,volume", lambda ph, p, vol: "%r,%r" % (p, vol / 1000)))
    out("pv_ml_unnamed.csv", csv("pressure,volume", lambda ph, p, vol: "%r,%r" % (p, vol)))
    out("pv_swapped_unnamed.csv", csv("a,b", lambda ph, p, vol: "%r,%r" % (vol, p)))
    out("pv_swapped_named.csv", csv("volume_ml,pressure_cmH2O", lambda ph, p, vol: "%r,%r" % (vol, p)))
    out("pv_changes_above_frc.csv", csv("pressure,volume", lambda ph, p, vol: "%r,%r" % (p, vol - 2400)))
    out("pv_shifted_negative.csv", csv("pressure,volume", lambda ph, p, vol: "%r,%r" % (p, vol - 3000)))
    out("pv_oesophageal_from_zero.csv", csv("pes_cmH2O,volume_ml", lambda ph, p, vol: "%r,%r" % (-p, vol)))
    out("pv_oesophageal_falling.csv", csv("pes_cmH2O,volume_ml", lambda ph, p, vol: "%r,%r" % (-5 - p, vol)))
    out("pv_with_phase.csv", csv("phase,pressure_cmH2O,volume_ml", lambda ph, p, vol: "%s,%r,%r" % (ph, p, vol)))
    out("pv_bad_phase.csv", csv("phase,pressure_cmH2O,volume_ml",
                                lambda ph, p, vol: "%s,%r,%r" % ("sideways" if ph == "exhale" else ph, p, vol)))
    out("pv_only_inhale.csv", csv("phase,pressure_cmH2O,volume_ml", lambda ph, p, vol: "inhale,%r,%r" % (p, vol)))
    def one_bad(name, k, col, val):
        lines = csv("pressure_cmH2O,volume_ml", lambda ph, p, vol: "%r,%r" % (p, vol)).split("\n")
        cells = lines[k].split(","); cells[col] = val; lines[k] = ",".join(cells)
        out(name, "\n".join(lines))
    one_bad("pv_volume_1e308.csv", 51, 1, "1e308")      # file line 52
    one_bad("pv_volume_nan.csv", 77, 1, "NaN")
    one_bad("pv_volume_inf.csv", 77, 1, "inf")
    one_bad("pv_volume_overflow.csv", 77, 1, "1e999")
    one_bad("pv_volume_subnormal.csv", 77, 1, "4e-320")
    one_bad("pv_volume_text.csv", 77, 1, "abc")
    one_bad("pv_volume_empty_cell.csv", 77, 1, "")
    one_bad("pv_volume_hex.csv", 77, 1, "0x960")
    one_bad("pv_pressure_minus_1e308.csv", 30, 0, "-1e308")
    one_bad("pv_pressure_nan.csv", 30, 0, "nan")
    one_bad("pv_volume_negative.csv", 80, 1, "-2400")
    lines = csv("pressure_cmH2O,volume_ml", lambda ph, p, vol: "%r,%r" % (p, vol)).split("\n")
    out("pv_short_row.csv", "\n".join(lines[:60] + ["1.5"] + lines[60:]))
    out("pv_long_row.csv", "\n".join(lines[:60] + [lines[60] + ",7,8,9"] + lines[60:]))
    out("pv_70kB_line.csv", "\n".join(lines[:60] + ["1.0," + "9" * 70000] + lines[61:]))
    out("pv_crlf.csv", "\r\n".join(lines))
    out("pv_bom.csv", "\ufeff" + "\n".join(lines))
    out("pv_quoted_header.csv", '"pressure_cmH2O","volume_ml"\n' + "\n".join(lines[1:]))
    out("pv_semicolon_decimal_comma.csv", "pressure_cmH2O;volume_ml\n" + "".join(
        ("%.4f;%.2f\n" % (p, vol)).replace(".", ",") for ph, p, vol in d))
    out("pv_tab_separated.csv", "pressure_cmH2O\tvolume_ml\n" + "".join("%r\t%r\n" % (p, vol) for ph, p, vol in d))
    out("pv_empty.csv", "")
    out("pv_header_only.csv", "pressure_cmH2O,volume_ml\n")
    out("pv_no_header.csv", "\n".join(lines[1:]))
    out("pv_one_row.csv", "\n".join(lines[:2]) + "\n")
    out("pv_three_rows.csv", "\n".join(lines[:4]) + "\n")
    out("pv_constant_volume.csv", csv("pressure_cmH2O,volume_ml", lambda ph, p, vol: "%r,2400" % p))
    out("pv_constant_pressure.csv", csv("pressure_cmH2O,volume_ml", lambda ph, p, vol: "5,%r" % vol))
    sh = list(d); RNG.shuffle(sh)
    out("pv_shuffled_rows.csv", csv("pressure_cmH2O,volume_ml", lambda ph, p, vol: "%r,%r" % (p, vol), sh))
    out("pv_binary_junk.csv", bytes(RNG.getrandbits(8) for _ in range(4096)))
    out("pv_nul_bytes.csv", b"pressure_cmH2O,volume_ml\n" + b"\0" * 4096)
    out("pv_non_utf8_header.csv", "Druck_cmH2O,Volumen_ml_\xe4\n".encode("latin-1") + "\n".join(lines[1:]).encode())
    out("pv_non_utf8_value.csv", "\n".join(lines[:40]).encode() + b"\n1.0,24\xff0\n" + "\n".join(lines[41:]).encode())
    out("pv_one_column.csv", "volume_ml\n" + "".join("%r\n" % vol for ph, p, vol in d))
    out("pv_three_numeric_unnamed.csv", csv("x,y,z", lambda ph, p, vol: "%r,%r,%r" % (p, vol, p * 2)))
    out("pv_duplicate_columns.csv", csv("pressure_cmH2O,volume_ml,volume_ml", lambda ph, p, vol: "%r,%r,%r" % (p, vol, vol + 100)))
    out("pv_huge_count_of_columns.csv", ",".join("c%d" % i for i in range(200)) + "\n" + "\n".join(
        ",".join(["%r,%r" % (p, vol)] + ["0"] * 198) for ph, p, vol in d[:20]) + "\n")
    return c


def make_constants(tmp, c):
    k = os.path.join(tmp, "k.toml")
    run("pv", "fit", "--input", c, "--q", "2", "--c", "1", "--out", k)
    good = open(k).read().replace(tmp + os.sep, "")        # no temporary paths: regenerates byte for byte
    out("constants_good.toml", good)
    def sub(name, old, new, count=1):
        assert old in good, old
        out(name, good.replace(old, new, count))
    sub("constants_frc_minus200.toml", "frc_ml = 2400.0", "frc_ml = -200.0")
    sub("constants_tv_1e308.toml", "tv_ml = 500.0", "tv_ml = 1e308")
    sub("constants_tp_equals_rp.toml", "tp_cmh2o = 10.0", "tp_cmh2o = 0.0")
    sub("constants_tp_below_rp.toml", "tp_cmh2o = 10.0", "tp_cmh2o = -10.0")
    sub("constants_frc_nan.toml", "frc_ml = 2400.0", "frc_ml = nan")
    sub("constants_tv_inf.toml", "tv_ml = 500.0", "tv_ml = inf")
    sub("constants_chi_nan.toml", "chi = [\n", "chi = [\n    nan,\n    0.0,\n")
    sub("constants_chi_even.toml", "chi = [\n", "chi = [\n    0.1,\n")
    sub("constants_chi_empty.toml", good[good.index("chi = ["):good.index("]", good.index("chi = [")) + 1], "chi = []")
    sub("constants_chi_1e308.toml", "chi = [\n", "chi = [\n    1e308,\n    1e308,\n")
    sub("constants_q_zero.toml", "q = 2.0", "q = 0.0")
    sub("constants_q_1e308.toml", "q = 2.0", "q = 1e308")
    sub("constants_c_negative.toml", "c = 1.0", "c = -1.0")
    sub("constants_t_steps_zero.toml", "t_steps = 100.0", "t_steps = 0.0")
    sub("constants_t_steps_1e12.toml", "t_steps = 100.0", "t_steps = 1e12")
    sub("constants_beta_inf.toml", "beta0 = ", "beta0 = inf # ")
    sub("constants_format_99.toml", "format = 1", "format = 99")
    sub("constants_unknown_key.toml", "[boundary]\n", "[boundary]\nfrc_litres = 2.4\n")
    sub("constants_missing_exhale.toml", good[good.index("[exhale]"):], "")
    sub("constants_frc_string.toml", "frc_ml = 2400.0", 'frc_ml = "2400"')
    out("constants_empty.toml", "")
    out("constants_binary.toml", bytes(RNG.getrandbits(8) for _ in range(1024)))
    out("constants_syntax_error.toml", good.replace("[boundary]", "[boundary", 1))


# ---------------------------------------------------------------- kernels
def make_kernels(tmp):
    from_here = lambda n: os.path.join(HERE, n)
    run("bake", "--mesh", from_here("lung_left.obj"), "--lung", "left", "--out", from_here("kernel_left.kernel"), "--tolerance", "1e-3")
    run("bake", "--mesh", from_here("lung_right.obj"), "--lung", "right", "--out", from_here("kernel_right.kernel"), "--tolerance", "1e-3")
    # a left lung baked as the right one (the bake warns; the kernel then claims the wrong side)
    run("bake", "--mesh", from_here("lung_left.obj"), "--lung", "right", "--out", from_here("kernel_left_baked_as_right.kernel"),
        "--tolerance", "1e-3")
    good = open(from_here("kernel_left.kernel"), "rb").read()
    sys.path.insert(0, HERE)
    from xxh3 import xxh3_64
    count = struct.unpack_from("<I", good, 16)[0]
    table = {}
    for i in range(count):
        kind, es, off, ln, h = struct.unpack_from("<IIQQQ", good, 64 + 32 * i)
        table[kind] = (i, es, off, ln)

    def reseal(b, sections=True):
        """Recompute every checksum, so only the deliberate defect is wrong."""
        b = bytearray(b)
        cnt = min(struct.unpack_from("<I", b, 16)[0], 64)
        if sections:
            for i in range(cnt):
                kind, es, off, ln, h = struct.unpack_from("<IIQQQ", b, 64 + 32 * i)
                if off + ln <= len(b):
                    struct.pack_into("<Q", b, 64 + 32 * i + 24, xxh3_64(bytes(b[off:off + ln])))
        struct.pack_into("<Q", b, 32, xxh3_64(bytes(b[64:64 + 32 * cnt])))
        struct.pack_into("<Q", b, 40, xxh3_64(bytes(b[:40])))
        return bytes(b)

    assert reseal(good) == good
    def sec(kind):
        i, es, off, ln = table[kind]; return off, ln
    out("kernel_empty.kernel", b"")
    out("kernel_truncated_half.kernel", good[:len(good) // 2])
    out("kernel_truncated_header.kernel", good[:40])
    out("kernel_truncated_last_byte.kernel", good[:-1])
    out("kernel_trailing_garbage.kernel", good + b"garbage")
    off, ln = sec(2); b = bytearray(good); b[off + 101] ^= 0x04; out("kernel_bitflip_positions.kernel", bytes(b))
    b = bytearray(good); b[0:8] = b"LUNGDYNX"; out("kernel_bad_magic.kernel", reseal(b))
    b = bytearray(good); struct.pack_into("<I", b, 8, 2); out("kernel_version_2.kernel", reseal(b))
    b = bytearray(good); struct.pack_into("<I", b, 8, 2); out("kernel_version_2_unsealed.kernel", bytes(b))
    b = bytearray(good); struct.pack_into(">I", b, 12, 0x01020304); out("kernel_big_endian_bom.kernel", reseal(b))
    b = bytearray(good); struct.pack_into("<I", b, 16, 65); out("kernel_section_count_65.kernel", reseal(b))
    b = bytearray(good); struct.pack_into("<I", b, 16, 0xFFFFFFFF); out("kernel_section_count_4e9.kernel", reseal(b))
    b = bytearray(good); struct.pack_into("<Q", b, 24, len(good) * 1000); out("kernel_length_lie.kernel", reseal(b))
    i, es, off, ln = table[10]; b = bytearray(good)
    struct.pack_into("<Q", b, 64 + 32 * i + 16, 1 << 62); out("kernel_section_length_2e18.kernel", reseal(b))
    i, es, off, ln = table[2]; b = bytearray(good)
    struct.pack_into("<Q", b, 64 + 32 * i + 8, len(good) + 64); out("kernel_section_offset_past_end.kernel", reseal(b))
    i, es, off, ln = table[2]; b = bytearray(good)
    struct.pack_into("<Q", b, 64 + 32 * i + 8, off + 4); out("kernel_section_misaligned.kernel", reseal(b))
    b = bytearray(good); i = table[3][0]
    off, ln = sec(2); b = bytearray(good); struct.pack_into("<f", b, off + 12 * 5, float("nan"))
    out("kernel_nan_position.kernel", reseal(b))
    off, ln = sec(2); b = bytearray(good); struct.pack_into("<f", b, off + 12 * 5 + 4, 3e38)
    out("kernel_3e38_position.kernel", reseal(b))
    out("kernel_left_no_lobes.kernel", without_section(good, 13, reseal))
    off, ln = sec(7); b = bytearray(good); struct.pack_into("<f", b, off + 12 * 9, float("inf"))
    out("kernel_inf_unit_displacement.kernel", reseal(b))
    off, ln = sec(10); b = bytearray(good); struct.pack_into("<f", b, off + 4 * 17, float("nan"))
    out("kernel_nan_transfer_value.kernel", reseal(b))
    off, ln = sec(4); b = bytearray(good); struct.pack_into("<3f", b, off + 12 * 3, 0.0, 0.0, 0.0)
    off, ln = sec(3); b = bytearray(good); struct.pack_into("<I", b, off + 12 * 4 + 8, 1000000)
    out("kernel_triangle_index_out_of_range.kernel", reseal(b))
    off, ln = sec(9); b = bytearray(good); struct.pack_into("<I", b, off + 4 * 33, 0xFFFFFFF0)
    out("kernel_column_out_of_range.kernel", reseal(b))
    off, ln = sec(8); b = bytearray(good); struct.pack_into("<Q", b, off + 8 * 10, 1 << 40)
    out("kernel_row_offsets_not_monotone.kernel", reseal(b))
    off, ln = sec(1)
    meta = good[off:off + ln].decode()
    def meta_variant(name, old, new):
        assert old in meta, old
        m = meta.replace(old, new, 1)
        if len(m.encode()) > ln:             # keep the section length: drop indentation, pad with spaces
            m = "\n".join(l.strip() for l in m.split("\n"))
        m = m.encode()
        assert len(m) <= ln
        m = m.ljust(ln, b" ")
        b = bytearray(good); b[off:off + ln] = m; out(name, reseal(b))
    meta_variant("kernel_meta_side_middle.kernel", '"side": "left"', '"side": "middle"')
    meta_variant("kernel_meta_vertices_lie.kernel", '"vertices": 152', '"vertices": 153')
    import re
    uv = re.search(r'"unit_volume_ml": [0-9.e+-]+', meta).group(0)
    meta_variant("kernel_meta_unit_volume_zero.kernel", uv, '"unit_volume_ml": 0.0')
    meta_variant("kernel_meta_not_json.kernel", "{", "<")
    out("kernel_is_a_mesh.kernel", open(from_here("lung_left.obj"), "rb").read())
    out("kernel_text.kernel", "LUNGDYNK but then just text\n")
    out("kernel_zeros.kernel", b"\0" * 4096)


# ---------------------------------------------------------------- points (landmarks)
def make_points(tmp):
    from_here = lambda n: os.path.join(HERE, n)
    for side in ("left", "right"):
        for ml in (250, 500):
            run("kernel", "export", from_here("kernel_%s.kernel" % side), "--delta-ml", str(ml),
                "--out", os.path.join(tmp, "%s_%d.obj" % (side, ml)))
    L0, _ = read_obj(from_here("lung_left.obj")); R0, _ = read_obj(from_here("lung_right.obj"))
    L1, _ = read_obj(os.path.join(tmp, "left_250.obj")); R1, _ = read_obj(os.path.join(tmp, "right_250.obj"))
    L2, _ = read_obj(os.path.join(tmp, "left_500.obj")); R2, _ = read_obj(os.path.join(tmp, "right_500.obj"))
    shutil.copy(os.path.join(tmp, "left_250.obj"), from_here("lung_left_plus250.obj"))
    idx = range(0, len(L0), 4)
    def pts(P, head="# x y z, mm, body frame\n", fmt="%.4f %.4f %.4f\n"):
        return head + "".join(fmt % tuple(p) for p in P)
    F = [L0[i] for i in idx] + [R0[i] for i in idx]
    T = [L1[i] for i in idx] + [R1[i] for i in idx]
    T2 = [L2[i] for i in idx] + [R2[i] for i in idx]
    out("pts_exhale.txt", pts(F)); out("pts_inhale.txt", pts(T)); out("pts_inhale_500.txt", pts(T2))
    out("pts_left_exhale.txt", pts([L0[i] for i in idx])); out("pts_left_inhale.txt", pts([L1[i] for i in idx]))
    out("pts_exhale_metres.txt", pts(scaled(F, 1e-3), fmt="%.7f %.7f %.7f\n"))
    out("pts_inhale_metres.txt", pts(scaled(T, 1e-3), fmt="%.7f %.7f %.7f\n"))
    sp = (0.97, 0.97, 2.5); org = (-250.0, -200.0, -300.0)   # a CT grid: indices from its corner
    vox = lambda P: [tuple(round((p[k] - org[k]) / sp[k]) for k in range(3)) for p in P]
    out("pts_exhale_voxels.txt", pts(vox(F), head="# voxel indices i j k\n", fmt="%d %d %d\n"))
    out("pts_inhale_voxels.txt", pts(vox(T), head="# voxel indices i j k\n", fmt="%d %d %d\n"))
    out("pts_inhale_one_fewer.txt", pts(T[:-1]))
    out("pts_inhale_moved_500mm.txt", pts(moved(T, dz=500.0)))
    out("pts_inhale_shuffled.txt", pts(RNG.sample(T, len(T))))
    out("pts_inhale_same_as_exhale.txt", pts(F))
    def bad(name, k, line):
        L = pts(T).split("\n"); L[k] = line; out(name, "\n".join(L))
    bad("pts_inhale_nan.txt", 10, "nan 1.0 2.0")
    bad("pts_inhale_inf.txt", 10, "1.0 inf 2.0")
    bad("pts_inhale_1e308.txt", 10, "1e308 1.0 2.0")
    bad("pts_inhale_text.txt", 10, "left apex 12.5")
    bad("pts_inhale_two_columns.txt", 10, "12.5 13.5")
    bad("pts_inhale_four_columns.txt", 10, "12.5 13.5 14.5 15.5")
    bad("pts_inhale_70kB_line.txt", 10, " ".join(["1.0"] * 17500))
    out("pts_inhale_crlf.txt", pts(T).replace("\n", "\r\n"))
    out("pts_inhale_commas.txt", pts(T, fmt="%.4f,%.4f,%.4f\n"))
    out("pts_empty.txt", "")
    out("pts_comments_only.txt", "# no points\n\n# at all\n")
    out("pts_one_point.txt", pts(F[:1])); out("pts_one_point_to.txt", pts(T[:1]))
    out("pts_three_points.txt", pts(F[:3])); out("pts_three_points_to.txt", pts(T[:3]))
    out("pts_all_identical.txt", pts([F[0]] * len(F)))
    out("pts_binary_junk.txt", bytes(RNG.getrandbits(8) for _ in range(4096)))
    out("pts_non_utf8.txt", pts(T).encode().replace(b"\n", b"\n# \xe9chantillon\xff\n", 1))
    out("pts_non_utf8_value.txt", pts(T).encode().replace(b"\n", b"\n1.0 2.\xff 3.0\n", 2).replace(b"\n1.0 2.\xff 3.0\n", b"\n", 1))
    out("pts_exhale.csv", "x,y,z\n" + "".join("%.4f,%.4f,%.4f\n" % p for p in F))


# ---------------------------------------------------------------- motion and scenes
def make_motion(tmp):
    from_here = lambda n: os.path.join(HERE, n)
    m = os.path.join(tmp, "m.toml")
    run("fit-motion", "--from", from_here("pts_exhale.txt"), "--to", from_here("pts_inhale.txt"), "--out", m)
    good = open(m).read().replace(HERE + os.sep, "")
    out("motion_good.toml", good)
    import re
    first = re.search(r"c = \[([^\]]*)\]", good)
    def c_variant(name, values):
        out(name, good[:first.start()] + "c = [%s]" % values + good[first.end():])
    c_variant("motion_c_nan.toml", "nan, 0.2, 20.0, 0.9, 2.7, 1.4, 0.01, 0.95, 0.07")
    c_variant("motion_c_inf.toml", "inf, 0.2, 20.0, 0.9, 2.7, 1.4, 0.01, 0.95, 0.07")
    c_variant("motion_c_1e308.toml", "1e308, 1e308, 1e308, 1e308, 1e308, 1e308, 0.01, 0.95, 0.07")
    c_variant("motion_c_five_values.toml", "3.3, 0.2, 20.0, 0.9, 2.7")
    c_variant("motion_c_twenty_values.toml", ", ".join(["1.0"] * 20))
    c_variant("motion_c_negative.toml", "-3.3, -0.2, -20.0, -0.9, -2.7, -1.4, -0.01, -0.95, -0.07")
    c_variant("motion_c_strings.toml", '"a", "b", "c", "d", "e", "f", "g", "h", "i"')
    out("motion_format_2.toml", good.replace("format = 1", "format = 2"))
    out("motion_unknown_section.toml", good.replace("[left]", "[middle]"))
    out("motion_unknown_key.toml", good.replace("[left]\n", "[left]\nc10 = 1.0\n"))
    out("motion_empty.toml", "")
    out("motion_binary.toml", bytes(RNG.getrandbits(8) for _ in range(1024)))


SCENE_BASE = "[lungs]\nvertices = 100\n"


def make_scenes(tmp):
    s = lambda name, text: out("scene_" + name + ".toml", text)
    s("small", SCENE_BASE)
    s("kernels", '[lungs.kernels]\nleft = "kernel_left.kernel"\nright = "kernel_right.kernel"\n')
    s("kernel_other_side", '[lungs.kernels]\nleft = "kernel_right.kernel"\nright = "kernel_right.kernel"\n')
    s("kernel_other_side_only", SCENE_BASE + '\n[lungs.kernels]\nleft = "kernel_right.kernel"\n')
    s("kernels_swapped", '[lungs.kernels]\nleft = "kernel_right.kernel"\nright = "kernel_left.kernel"\n')
    s("render_color_lobes_no_lobe_section", '[lungs.kernels]\nleft = "kernel_left_no_lobes.kernel"\n'
      'right = "kernel_right.kernel"\n[render]\ncolor = "lobes"\n')
    s("kernel_missing", '[lungs.kernels]\nleft = "no_such.kernel"\nright = "kernel_right.kernel"\n')
    s("kernel_truncated", '[lungs.kernels]\nleft = "kernel_truncated_half.kernel"\nright = "kernel_right.kernel"\n')
    s("kernel_bitflip", '[lungs.kernels]\nleft = "kernel_bitflip_positions.kernel"\nright = "kernel_right.kernel"\n')
    s("kernel_is_mesh", '[lungs.kernels]\nleft = "lung_left.obj"\nright = "kernel_right.kernel"\n')
    s("kernel_middle", SCENE_BASE + '\n[lungs.kernels]\nmiddle = "kernel_left.kernel"\n')
    s("kernel_dev_zero", '[lungs.kernels]\nleft = "/dev/zero"\nright = "kernel_right.kernel"\n')
    s("unknown_top_key", SCENE_BASE + "colour = \"pink\"\n")
    s("unknown_section", SCENE_BASE + "[physics]\ngravity = 9.81\n")
    s("unknown_pv_key", "[pv]\nbreaths_per_minute = 12.0\n" + SCENE_BASE)
    s("unknown_render_key", SCENE_BASE + "[render]\nwidht = 800\n")
    s("unknown_lungs_key", "[lungs]\nvertices = 100\nvertex = 100\n")
    s("unknown_elasticity_key", SCENE_BASE + "[lungs.elasticity]\nmiddle = 2.0\n")
    for tag, val in (("0", "0.0"), ("1e9", "1e9"), ("nan", "nan"), ("inf", "inf"), ("negative", "-12.0"),
                     ("string", '"twelve"')):
        s("breaths_per_min_" + tag, "[pv]\nbreaths_per_min = %s\n" % val + SCENE_BASE)
    for tag, val in (("0", "0.0"), ("nan", "nan"), ("1e9", "1e9"), ("negative", "-60.0"), ("inf", "inf")):
        s("tick_hz_" + tag, "[engine]\ntick_hz = %s\n" % val + SCENE_BASE)
    s("pose_staleness_negative", "[engine]\npose_staleness_ticks = -1\n" + SCENE_BASE)
    s("pose_staleness_huge", "[engine]\npose_staleness_ticks = 9223372036854775807\n" + SCENE_BASE)
    for tag, val in (("zero", "[0.0, 1.0]"), ("one_value", "[1.0]"), ("negative", "[-1.0, 1.0]"),
                     ("nan", "[nan, 1.0]"), ("1e308", "[1e308, 1e-308]")):
        s("ie_ratio_" + tag, "[pv]\nie_ratio = %s\n" % val + SCENE_BASE)
    s("preset_unknown", "[pv]\npreset = \"venegas-horse\"\n" + SCENE_BASE)
    s("constants_missing", "[pv]\nconstants = \"no_such_constants.toml\"\n" + SCENE_BASE)
    s("constants_frc_minus200", "[pv]\nconstants = \"constants_frc_minus200.toml\"\n" + SCENE_BASE)
    s("constants_tv_1e308", "[pv]\nconstants = \"constants_tv_1e308.toml\"\n" + SCENE_BASE)
    s("constants_tp_equals_rp", "[pv]\nconstants = \"constants_tp_equals_rp.toml\"\n" + SCENE_BASE)
    s("constants_good", "[pv]\nconstants = \"constants_good.toml\"\n" + SCENE_BASE)
    for tag, val in (("0", "0"), ("99", "99"), ("4000001", "4000001"), ("negative", "-100"),
                     ("1e12", "1000000000000"), ("float", "100.5"), ("string", '"many"')):
        s("vertices_" + tag, "[lungs]\nvertices = %s\n" % val)
    for tag, val in (("0", "0.0"), ("nan", "nan"), ("negative", "-1e-5"), ("one", "1.0"), ("1e-300", "1e-300")):
        s("tolerance_" + tag, SCENE_BASE + "transfer_tolerance = %s\n" % val)
    for tag, val in (("empty", "[]"), ("twice_left", '["left", "left"]'), ("middle", '["middle"]'),
                     ("three", '["right", "left", "left"]')):
        s("sides_" + tag, "[lungs]\nvertices = 100\nsides = %s\n" % val)
    s("sides_left_only", "[lungs]\nvertices = 100\nsides = [\"left\"]\n")
    for tag, body in (("apex_0", "apex = 0.0"), ("apex_negative", "apex = -4.0"), ("base_nan", "base = nan"),
                      ("dependent_1.5", "dependent = 1.5"), ("dependent_negative", "dependent = -0.1"),
                      ("apex_1e308", "apex = 1e308")):
        s("elasticity_" + tag, SCENE_BASE + "[lungs.elasticity]\n%s\n" % body)
    s("lungs_shape_pear", SCENE_BASE + "shape = \"pear\"\n")
    s("lungs_shape_number", SCENE_BASE + "shape = 3\n")
    s("motion_missing", SCENE_BASE + "motion = \"no_such_motion.toml\"\n")
    s("motion_nan", SCENE_BASE + "motion = \"motion_c_nan.toml\"\n")
    s("motion_five_values", SCENE_BASE + "motion = \"motion_c_five_values.toml\"\n")
    s("motion_good", SCENE_BASE + "motion = \"motion_good.toml\"\n")
    for tag, body in (("width_0", "width = 0"), ("width_100000", "width = 100000"), ("height_negative", "height = -600"),
                      ("fov_0", "fov_y_deg = 0.0"), ("fov_180", "fov_y_deg = 180.0"), ("fov_nan", "fov_y_deg = nan"),
                      ("ipd_nan", "ipd_mm = nan"), ("ipd_negative", "ipd_mm = -63.0"), ("splat_negative", "splat_mm = -1.0"),
                      ("mode_wireframe", "mode = \"wireframe\""), ("stereo_string", "stereo = \"yes\""),
                      ("look_glass", "look = \"glass\""), ("color_lobe", "color = \"lobe\""),
                      ("color_lobes", "color = \"lobes\""),
                      ("msaa_8", "msaa = 8"), ("msaa_negative", "msaa = -4"),
                      ("lod_fast", "lod = \"fast\""), ("lod_9", "lod = 9"), ("lod_negative", "lod = -1"),
                      ("lod_fraction", "lod = 1.5"), ("governor_fast", "governor = \"fast\""),
                      ("governor_bool", "governor = true"), ("least_bands_zero", "governor_least_bands = 0"),
                      ("governor_start_last", "governor_start = \"last\"")):
        s("render_" + tag, SCENE_BASE + "[render]\n%s\n" % body)
    s("syntax_error", SCENE_BASE + "[render\nwidth = 800\n")
    s("duplicate_key", "[lungs]\nvertices = 100\nvertices = 200\n")
    s("binary", bytes(RNG.getrandbits(8) for _ in range(2048)))
    s("non_utf8", b"# Lunge \xfc\xe4\n" + SCENE_BASE.encode())
    s("empty_vertices_only", "[lungs]\nvertices = 100\n")
    s("tracker_posture_standing", SCENE_BASE + "[tracker]\nposture = \"standing\"\n")
    s("tracker_unknown_key", SCENE_BASE + "[tracker]\nwobble = 1\n")
    s("tracker_source_bogus", SCENE_BASE + "[tracker]\nsource = \"bogus:1\"\n")
    s("disease_index_1_5", "[disease]\nkind = \"closed-pneumothorax\"\nside = \"left\"\nindex = 1.5\n")
    s("disease_tumour_outside", "[disease]\nkind = \"tumour\"\nside = \"right\"\n[disease.tumour]\ncentre = [0.0, 0.0, 0.0]\nradii_mm = [15.0, 15.0, 15.0]\n")
    s("disease_tumour_unknown_lobe", "[disease]\nkind = \"tumour\"\nside = \"right\"\n[disease.tumour]\nlobe = \"right lingula\"\nradii_mm = [15.0, 15.0, 15.0]\n")
    s("disease_tumour_wrong_lobe", "[disease]\nkind = \"tumour\"\nside = \"right\"\n[disease.tumour]\nlobe = \"right upper\"\ncentre = [0.6, 0.3, 0.8]\nradii_mm = [15.0, 15.0, 15.0]\n")
    s("processes_cpus_4096", SCENE_BASE + "[processes]\ncpus = [4096, 0, 0]\n")
    s("processes_cpus_two", SCENE_BASE + "[processes]\ncpus = [0, 1]\n")
    s("processes_budget_over", SCENE_BASE + "[processes.budget_ms]\nrenderer = 16.0\n")
    s("remote_role_teacher", SCENE_BASE + "[remote]\nrole = \"teacher\"\n")
    s("remote_site_no_connect", SCENE_BASE + "[remote]\nrole = \"site\"\n")
    s("remote_udp_endpoint", SCENE_BASE + "[remote]\nrole = \"source\"\nlisten = [\"udp/0.0.0.0:7447\"]\n")
    s("remote_plain_on_network", SCENE_BASE + "[remote]\nrole = \"source\"\nlisten = [\"tcp/0.0.0.0:7447\"]\n")
    s("remote_lab_network_yes", SCENE_BASE + "[remote]\nrole = \"source\"\ninsecure_lab_network = \"yes\"\n")
    s("remote_no_port", SCENE_BASE + "[remote]\nrole = \"site\"\nconnect = [\"tcp/10.0.0.2\"]\n")
    s("remote_mode_mesh", SCENE_BASE + "[remote]\nrole = \"source\"\nmode = \"mesh\"\n")
    s("remote_client_no_connect", SCENE_BASE + "[remote]\nrole = \"source\"\nmode = \"client\"\n")
    s("remote_router_no_listen", SCENE_BASE + "[remote]\nrole = \"source\"\nmode = \"router\"\nlisten = []\n")
    s("remote_lease_5", SCENE_BASE + "[remote]\nrole = \"source\"\nlease_ms = 5\n")
    s("remote_room_slash", SCENE_BASE + "[remote]\nrole = \"source\"\nroom = \"ward/3\"\n")
    s("remote_site_id_bad", SCENE_BASE + "[remote]\nrole = \"source\"\nsite_id = \"xyz\"\n")
    s("remote_unknown_key", SCENE_BASE + "[remote]\nrole = \"source\"\nport = 7447\n")
    s("remote_site", SCENE_BASE + "[remote]\nrole = \"site\"\nconnect = [\"tcp/127.0.0.1:7447\"]\n")
    s("remote_clock_ntp", SCENE_BASE + "[remote]\nrole = \"site\"\nmode = \"client\"\nconnect = [\"tcp/127.0.0.1:7447\"]\nclock = \"ntp\"\n")
    s("remote_clock_relay_peer", SCENE_BASE + "[remote]\nrole = \"observer\"\nconnect = [\"tcp/127.0.0.1:7447\"]\nclock = \"relay\"\n")
    s("remote_clock_on_source", SCENE_BASE + "[remote]\nrole = \"source\"\nclock = \"source\"\n")
    out("scene_not_toml.json", '{"lungs": {"vertices": 100}}\n')


# ---------------------------------------------------------------- calibration and HMD optics

HMD_GOOD = ("format = 1\n[display]\nwidth_px = 160\nheight_px = 120\nhorizontal_fov_deg = 70.0\n"
            "[eyes]\nipd_mm = 64.0\n[eyes.left]\noffset_mm = [-32.0, 0.0, 0.0]\nfrustum_deg = [36.0, 34.0, 27.0, 28.0]\n"
            "[eyes.right]\noffset_mm = [32.0, 0.0, 0.0]\nfrustum_deg = [34.0, 36.0, 27.0, 28.0]\n")


def make_render_files(tmp):
    """The renderer's files ([render] calibration / hmd, --calibration / --hmd): a calibration from
    `lungdyn register` (five fiducials, the model 80 mm posterior of the reference) and an optics file
    (the binary writes none: this text), then one defect each, and scenes naming them."""
    rng = random.Random(20250612)  # its own stream: the fixtures above do not change with this section
    model = [(0, 0, 0), (100, 0, 0), (0, 120, 0), (0, 0, 90), (60, 40, 30)]
    out("fid_model.txt", "".join("%g %g %g\n" % p for p in model))
    # The model points are in the body frame (+X patient left), the tool's frame is right-handed
    # (RAS-aligned here): a real patient's tracked fiducials are the body points with X negated
    # (lung_model::frame::body_to_ras), then moved. Issue 19: before, the body points themselves were
    # taken for tracked ones, a mirror-image patient; that list is now fid_tracker_mirrored.txt.
    tracker = [(-x + 0.0, y - 80, z) for x, y, z in model]
    out("fid_tracker.txt", "".join("%g %g %g\n" % p for p in tracker))
    # One defect each (issue 18's probe): every one was once written with exit 0.
    fid = lambda name, pts: out("fid_tracker_" + name + ".txt", "".join("%.6g %.6g %.6g\n" % tuple(p) for p in pts))
    fid("identical", [(10, 20, 30)] * 5)
    fid("cm", [[v / 10 for v in p] for p in tracker])
    fid("m", [[v / 1000 for v in p] for p in tracker])
    fid("collinear", [(0, 40 * i - 80, 7) for i in range(5)])
    fid("mirrored", [(-x, y, z) for x, y, z in tracker])
    fid("swapped", [tracker[2], tracker[1], tracker[0], tracker[3], tracker[4]])
    fid("scaled_3pct", [[v * 1.03 for v in p] for p in tracker])
    fid("two", tracker[:2])
    fid("near_duplicate", tracker[:4] + [(tracker[0][0] + 0.4, tracker[0][1], tracker[0][2])])
    subprocess.run([BIN, "register", "--model-points", "fid_model.txt", "--tracker-points",
                    "fid_tracker.txt", "--out", os.path.join(HERE, "calib_good.toml")],
                   cwd=HERE, check=True, stdout=subprocess.DEVNULL, stderr=subprocess.DEVNULL)
    out("calib_garbage.toml", bytes(rng.getrandbits(8) for _ in range(512)))
    out("hmd_good.toml", HMD_GOOD)
    out("hmd_ipd_500.toml", HMD_GOOD.replace("ipd_mm = 64.0", "ipd_mm = 500.0"))
    s = lambda name, text: out("scene_" + name + ".toml", text)
    s("render_files_good", SCENE_BASE + '[render]\ncalibration = "calib_good.toml"\nhmd = "hmd_good.toml"\n')
    s("calibration_missing", SCENE_BASE + '[render]\ncalibration = "no_such_calibration.toml"\n')
    s("calibration_garbage", SCENE_BASE + '[render]\ncalibration = "calib_garbage.toml"\n')
    s("hmd_ipd_500", SCENE_BASE + '[render]\nhmd = "hmd_ipd_500.toml"\n')
    s("hmd_directory", SCENE_BASE + '[render]\nhmd = "."  # this folder\n')
    # Issue 18's probe: each was accepted by `hmd check`, `demo` or the renderer.
    for tag, old_text, new_text in (
            ("near_1e-6", "horizontal_fov_deg = 70.0\n", "horizontal_fov_deg = 70.0\nnear_mm = 1e-6\n"),
            ("near_5e-324", "horizontal_fov_deg = 70.0\n", "horizontal_fov_deg = 70.0\nnear_mm = 5e-324\n"),
            ("far_over_near", "horizontal_fov_deg = 70.0\n", "horizontal_fov_deg = 70.0\nnear_mm = 1.0\nfar_mm = 100000.0\n"),
            ("frustum_0.001deg", "frustum_deg = [36.0, 34.0, 27.0, 28.0]", "frustum_deg = [0.0005, 0.0005, 27.0, 28.0]"),
            ("frustum_nan", "frustum_deg = [36.0, 34.0, 27.0, 28.0]", "frustum_deg = [36.0, nan, 27.0, 28.0]"),
            ("width_16384", "width_px = 160", "width_px = 16384"),
            ("width_8", "width_px = 160", "width_px = 8"),
            ("offset_inf", "offset_mm = [-32.0, 0.0, 0.0]", "offset_mm = [-inf, 0.0, 0.0]")):
        assert old_text in HMD_GOOD
        out("hmd_%s.toml" % tag, HMD_GOOD.replace(old_text, new_text))
    with open(os.path.join(HERE, "calib_good.toml")) as f:
        calib = f.read()
    for tag, old_text, new_text in (
            ("matrix_nan", "rotation_matrix = [[1.0,", "rotation_matrix = [[nan,"),
            ("matrix_reflection", "1.0]]", "-1.0]]"),
            ("matrix_not_orthonormal", "rotation_matrix = [[1.0,", "rotation_matrix = [[1.01,"),
            ("quaternion_nan", "rotation_xyzw = [", "rotation_xyzw = [nan, "),
            ("translation_2500", "-79.99999999999999", "-2500.0"),
            ("translation_inf", "-79.99999999999999", "-inf"),
            # Issue 19: a calibration written before the body frame's reflection was named.
            ("format_1", "format = 2", "format = 1")):
        assert old_text in calib
        text = calib.replace(old_text, new_text, 1)
        if tag == "quaternion_nan":  # keep four components: drop the first one written
            head, rest = text.split("rotation_xyzw = [nan, ", 1)
            text = head + "rotation_xyzw = [nan, " + rest.split(", ", 1)[1]
        out("calib_%s.toml" % tag, text)
    s("hmd_near_1e-6", SCENE_BASE + '[render]\nhmd = "hmd_near_1e-6.toml"\n')
    s("calibration_matrix_nan", SCENE_BASE + '[render]\ncalibration = "calib_matrix_nan.toml"\n')


# ---------------------------------------------------------------- ventilator recordings
def passive_breaths(mode="vc", c=50.0, r=10.0, r_valve=5.0, peep=5.0, rate=15.0, ti=1.0, breaths=3,
                    dt=0.02, flow_lps=0.5, above_peep=15.0):
    """A passive lung on a ventilator (as lung_model::recording::Synthetic): Paw = V/C + R*flow + PEEP,
    expiration through the exhalation valve. Returns [(t_s, flow_lps, paw_cmh2o, breath_no_or_None)]:
    the first sample is at rest, each breath start carries its number. The real PB-840 recordings are
    GPL-3.0 and stay outside the repository; these stand in for them."""
    per = int(round(60.0 / rate / dt))
    tau_in, tau_ex = r * c / 1000.0, (r + r_valve) * c / 1000.0
    rows = [(0.0, 0.0, peep, None)]
    for i in range(1, per * breaths + 2):
        j = i - 1
        k = min(j // per, breaths - 1)
        tb = (j - k * per) * dt
        if mode == "vc":
            v_end = flow_lps * ti * 1000.0
        else:
            v_end = c * above_peep * (1 - math.exp(-ti / tau_in))
        if tb < ti:
            if mode == "vc":
                v, q = flow_lps * tb * 1000.0, flow_lps
            else:
                vmax = c * above_peep
                v = vmax * (1 - math.exp(-tb / tau_in))
                q = (vmax - v) / 1000.0 / tau_in
        else:
            v = v_end * math.exp(-(tb - ti) / tau_ex)
            q = -v / 1000.0 / tau_ex
        start = k + 1 if j % per == 0 and j // per < breaths else None
        rows.append((i * dt, q, peep + v / c + r * q, start))
    return rows


def pb840(rows, stamp="2016-05-05-13-25-36.944930"):
    """PB-840 raw export text: BS, S:<n>, / flow (L/min), pressure (cmH2O) / BE."""
    lines, open_ = [stamp], False
    first = next(i for i, row in enumerate(rows) if row[3] is not None)
    for t, q, p, start in rows[first:]:
        if start is not None:
            if open_:
                lines.append("BE")
            lines.append("BS, S:%d," % (400 + start))
            open_ = True
        lines.append("%.2f, %.2f" % (q * 60.0, p))
    lines.append("BE")
    return "\n".join(lines) + "\n"


def generic(rows, header="time_s,flow_L/min,paw_cmH2O", f=lambda t, q, p: "%.3f,%.3f,%.3f" % (t, q * 60, p)):
    return header + "\n" + "".join(f(t, q, p) + "\n" for t, q, p, _ in rows)


def make_recordings():
    vc, pc = passive_breaths("vc"), passive_breaths("pc", c=30.0, r=8.0, peep=10.0, rate=20.0)
    out("rec_pb840_vc.csv", pb840(vc))
    out("rec_pc.csv", generic(pc))
    out("rec_kpa_ls_ms.csv", generic(vc, "time (ms),Flow [L/s],Paw (kPa)",
                                     lambda t, q, p: "%.0f,%.5f,%.5f" % (t * 1000, q, p * 0.0980665)))
    out("rec_with_volume_pes.csv", generic(vc, "time_s,flow_L/s,paw_cmH2O,volume_ml,pes_cmH2O",
                                           lambda t, q, p: "%.3f,%.5f,%.3f,0,%.3f" % (t, q, p, 2 + 0.1 * p)))
    out("rec_flow_no_unit.csv", generic(vc, "time_s,flow,paw_cmH2O"))
    out("rec_pressure_unknown_unit.csv", generic(vc, "time_s,flow_L/min,paw_furlongs"))
    out("rec_time_no_unit.csv", generic(vc, "time,flow_L/min,paw_cmH2O"))
    out("rec_no_flow.csv", "time_s,paw_cmH2O\n" + "".join("%.3f,%.3f\n" % (t, p) for t, q, p, _ in vc))
    out("rec_two_flows.csv", generic(vc, "time_s,flow_L/min,paw_cmH2O,flow_L/s",
                                     lambda t, q, p: "%.3f,%.3f,%.3f,%.5f" % (t, q * 60, p, q)))
    # Flow in ml/s written under an L/s header: 500 L/s, beyond any airflow.
    out("rec_ml_as_litres.csv", generic(vc, "time_s,flow_L/s,paw_cmH2O", lambda t, q, p: "%.3f,%.1f,%.3f" % (t, q * 1000, p)))
    # Time in ms under an s header: a gap of 20 s between samples.
    out("rec_ms_as_seconds.csv", generic(vc, "time_s,flow_L/min,paw_cmH2O",
                                         lambda t, q, p: "%.0f,%.3f,%.3f" % (t * 1000, q * 60, p)))
    back = generic(vc).split("\n")
    back[40], back[41] = back[41], back[40]
    out("rec_time_backwards.csv", "\n".join(back))
    nan = generic(vc).split("\n")
    nan[30] = nan[30].rsplit(",", 1)[0] + ",NaN"
    out("rec_pressure_nan.csv", "\n".join(nan))
    out("rec_flat_flow.csv", generic([(t, 0.0, 5.0, None) for t, _, _, _ in vc]))
    text = pb840(vc)
    out("rec_pb840_bs_without_be.csv", text.replace("BE\nBS, S:402,", "BS, S:402,", 1))
    out("rec_pb840_three_fields.csv", text.replace("\n", "\n1.0, 5.0, 7.0\n", 3).split("\n", 1)[0] + "\n"
        + "BS, S:401,\n1.00, 5.00, 7.00\n" + text.split("BS, S:401,\n", 1)[1])
    out("rec_pb840_sample_outside.csv", text.replace("BE\nBS, S:402,", "BE\n1.00, 5.00\nBS, S:402,", 1))
    out("rec_pb840_bad_number.csv", text.replace("BS, S:402,", "BS, S:4x2,", 1))
    out("rec_semicolons.csv", "time_s;flow_L/min;paw_cmH2O\n0;1,5;5\n")
    out("rec_short.csv", generic(vc[:5]))
    # A leak: expiratory flow halved (every breath is an artefact, said so; accepted).
    out("rec_leak.csv", generic([(t, q * (0.5 if q < 0 else 1), p, s) for t, q, p, s in vc]))
    # PV loops given as volume above FRC (as ventilators and Guyton's curve give them): the simulated
    # loop less 2397.75 ml, so it starts at 2.25 ml.
    rows = [l.split(",") for l in open(os.path.join(HERE, "pv_good.csv")).read().split("\n")[1:] if l]
    rel = lambda header: header + "\n" + "".join("%s,%s,%r\n" % (r[0], r[2], float(r[3]) - 2397.75) for r in rows)
    out("pv_relative_2ml.csv", rel("phase,pressure_cmH2O,volume_ml"))
    out("pv_relative_header.csv", rel("phase,pressure_cmH2O,volume_above_frc_ml"))
    # Scenes that breathe from a recording ([pv] waveform).
    w = lambda name, text: out("scene_waveform_" + name + ".toml", text)
    w("good", '[pv]\nwaveform = "rec_pb840_vc.csv"\n')
    w("missing", '[pv]\nwaveform = "no_such_recording.csv"\n')
    w("not_a_recording", '[pv]\nwaveform = "rec_flow_no_unit.csv"\n')
    w("only_artefacts", '[pv]\nwaveform = "rec_leak.csv"\n')
    w("with_constants", '[pv]\nwaveform = "rec_pb840_vc.csv"\nconstants = "constants_good.toml"\n')
    w("with_disease", '[pv]\nwaveform = "rec_pb840_vc.csv"\n\n[disease]\nkind = "closed-pneumothorax"\n'
      'side = "left"\nindex = 0.1\nalpha_ml = 100.0\nphi = 0.1\n')
    # A disease on a recorded breath (EQUATIONS §4.7): accepted; what shapes a spontaneous breath
    # (phi) and a collapse of every lung are refused.
    w("closed_pneumothorax", '[pv]\nwaveform = "rec_pb840_vc.csv"\n\n[disease]\nkind = "closed-pneumothorax"\n'
      'side = "left"\nindex = 0.3\n')
    w("tension", '[pv]\nwaveform = "rec_pb840_vc.csv"\n\n[disease]\nkind = "tension-pneumothorax"\n'
      'side = "left"\nv_p_ml = 40.0\n')
    w("with_phi", '[pv]\nwaveform = "rec_pb840_vc.csv"\n\n[disease]\nkind = "tension-pneumothorax"\n'
      'side = "left"\nphi = 0.1\n')
    w("every_lung_collapsed", '[pv]\nwaveform = "rec_pb840_vc.csv"\n\n[disease]\n'
      'kind = "bilateral-pneumothorax"\nindex_left = 1.0\nindex_right = 1.0\n')
    # What the ventilator holds fixed (EQUATIONS §4.7): the recording's classes decide, or
    # [pv] waveform_control overrides them (warned about when it contradicts them).
    w("pc_closed_pneumothorax", '[pv]\nwaveform = "rec_pc.csv"\n\n[disease]\nkind = "closed-pneumothorax"\n'
      'side = "left"\nindex = 0.3\n')
    w("control_contradicts", '[pv]\nwaveform = "rec_pb840_vc.csv"\nwaveform_control = "pressure"\n\n'
      '[disease]\nkind = "closed-pneumothorax"\nside = "left"\nindex = 0.3\n')
    w("control_unknown", '[pv]\nwaveform = "rec_pc.csv"\nwaveform_control = "sideways"\n')
    w("control_not_a_string", '[pv]\nwaveform = "rec_pc.csv"\nwaveform_control = 1\n')
    out("scene_waveform_control_without_waveform.toml", '[pv]\nwaveform_control = "pressure"\n')


def make_signal_traces():
    """Respiratory traces that are not breathing, or not as labelled (issue 35): a 3 Hz vibration,
    a volume_L column holding ml, two time columns that disagree, 10 s too short to calibrate on."""
    def w(name, header, rows):
        out(name, header + "\n" + "\n".join(rows) + "\n")
    breath = lambda k, depth: depth * (1 - math.cos(2 * math.pi * k * 0.04 / 4))
    w("trace_csv_vibration_3hz.csv", "time_s,amplitude_mm",
      ["%.3f,%.4f" % (k * 0.04, 2 * (1 - math.cos(2 * math.pi * 3 * k * 0.04))) for k in range(300)])
    w("trace_csv_volume_l_holding_ml.csv", "time_s,volume_L",
      ["%.3f,%.2f" % (k * 0.04, breath(k, 250)) for k in range(400)])
    w("trace_csv_two_time_columns.csv", "time_s,time_ms,amplitude_mm",
      ["%.3f,%d,%.4f" % (k * 0.04, k * 10, breath(k, 4)) for k in range(400)])
    w("trace_csv_10s_too_few_breaths.csv", "time_s,amplitude_mm",
      ["%.3f,%.4f" % (k * 0.04, breath(k, 4)) for k in range(251)])


def make_tracker_recordings():
    """Tracker recordings (`--record`), 0.2 s of the synthetic tools: one made without a
    respiratory signal, one with a 12 s amplitude trace (a sine, 4 s breaths) as its signal."""
    rows = ["time_s,amplitude_mm"] + ["%.3f,%.4f" % (k * 0.04, 5 * (1 - math.cos(2 * math.pi * k * 0.04 / 4)))
                                      for k in range(300)]
    out("trace_sine_12s.csv", "\n".join(rows) + "\n")
    for name, extra in [("tracker_recording_no_signal.ldtr", []),
                        ("tracker_recording_with_signal.ldtr",
                         ["--breathing", "trace:" + os.path.join(HERE, "trace_sine_12s.csv")])]:
        path = os.path.join(HERE, name)
        if os.path.exists(path):
            os.remove(path)
        run("tracker", "listen", "--seconds", "0.2", "--record", path, *extra)
    derive_latency_out_of_range()


def derive_latency_out_of_range():
    """The recording with a signal, with a signal-latency record (kind 6, layout v8) of 5 s after
    its first signal record, its CRC right: a latency no frame has (1 ns ... 1 s)."""
    data = open(os.path.join(HERE, "tracker_recording_with_signal.ldtr"), "rb").read()
    config_len, = struct.unpack_from("<I", data, 12)
    description_len, = struct.unpack_from("<I", data, 24)
    at = 32 + config_len + description_len
    while data[at] != 5:
        at += 2 + data[at + 1] + 4
    at += 2 + data[at + 1] + 4
    record = bytes([6, 8]) + struct.pack("<Q", 5_000_000_000)
    record += struct.pack("<I", zlib.crc32(record) & 0xFFFFFFFF)
    with open(os.path.join(HERE, "tracker_recording_latency_out_of_range.ldtr"), "wb") as f:
        f.write(data[:at] + record + data[at:])


def main():
    if not os.path.exists(BIN):
        sys.exit("lungdyn binary not found: %s (pass its path)" % BIN)
    # Kept as they are: the respiratory traces written by hand before this script made any (their
    # recipes are in the issue-35 commits that added them); the ones made here are remade.
    hand_made = {"trace_good.csv", "trace_good.vxp", "trace_good_v15.vxp", "trace_csv_decimal_comma.csv",
                 "trace_csv_flat.csv", "trace_csv_gap.csv", "trace_csv_nan.csv", "trace_csv_no_unit.csv",
                 "trace_vxp_constant_time.vxp", "trace_vxp_no_data.vxp", "trace_vxp_no_scale.vxp",
                 "trace_vxp_seconds.vxp", "trace_vxp_short.vxp"}
    keep = {"cases.toml", "README.md", "make_fixtures.py", "xxh3.py"} | hand_made
    for n in [] if os.environ.get("LUNGDYN_FIXTURES_ONLY") else os.listdir(HERE):
        if n not in keep and os.path.isfile(os.path.join(HERE, n)):
            os.remove(os.path.join(HERE, n))
    if os.environ.get("LUNGDYN_FIXTURES_ONLY") == "recordings":
        make_recordings()
        return
    if os.environ.get("LUNGDYN_FIXTURES_ONLY") == "tracker-recordings":
        make_tracker_recordings()
        return
    if os.environ.get("LUNGDYN_FIXTURES_ONLY") == "signal-traces":
        make_signal_traces()
        return
    if os.environ.get("LUNGDYN_FIXTURES_ONLY") == "render-files":
        with tempfile.TemporaryDirectory() as tmp:
            make_render_files(tmp)
        return
    with tempfile.TemporaryDirectory() as tmp:
        make_recordings()
        make_tracker_recordings()
        make_signal_traces()
        make_meshes(tmp)
        c = make_pv(tmp); make_constants(tmp, c)
        make_kernels(tmp); make_points(tmp); make_motion(tmp); make_scenes(tmp)
        make_render_files(tmp)
    total = sum(os.path.getsize(os.path.join(HERE, n)) for n in os.listdir(HERE))
    print("%d files, %.0f KiB in %s" % (len(os.listdir(HERE)), total / 1024, HERE))


if __name__ == "__main__":
    main()
