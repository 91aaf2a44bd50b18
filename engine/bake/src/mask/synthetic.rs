//! Label images made here, for tests and benchmarks (the `testing` feature): the built-in lungs
//! voxelised at a CT spacing and written as NIfTI-1, NRRD and MetaImage with their headers' frames.
//! One copy, used by lung-bake's own mask tests and by the workspace's CLI tests of
//! `mesh from-mask`, `patient` and `fit-motion`.

use std::io::Write;

use glam::DVec3;
use lung_model::mesh::{anatomy, Side, TriMesh};

use super::volume::Axes;

/// A label volume in the body frame: `labels[i + nx (j + ny k)]` at body position
/// `origin + (i sx, j sy, k sz)`.
#[derive(Clone)]
pub struct Body {
    /// Voxels along x, y, z.
    pub dims: [usize; 3],
    /// Voxel size, mm.
    pub spacing: [f64; 3],
    /// Body position of voxel (0, 0, 0), mm.
    pub origin: DVec3,
    /// The labels, x fastest.
    pub labels: Vec<u16>,
}

/// Inside test by ray parity along +X for every voxel row (triangles binned by their Y–Z box).
pub fn voxelise(mesh: &TriMesh, body: &mut Body, value: impl Fn(DVec3) -> u16) {
    let [nx, ny, nz] = body.dims;
    let p = |i: u32| DVec3::from(mesh.positions[i as usize].map(|v| v as f64));
    for k in 0..nz {
        let z = body.origin.z + k as f64 * body.spacing[2];
        // Triangles spanning this z.
        let tris: Vec<[DVec3; 3]> = mesh
            .triangles
            .iter()
            .map(|t| t.map(p))
            .filter(|c| {
                let lo = c.iter().map(|v| v.z).fold(f64::INFINITY, f64::min);
                let hi = c.iter().map(|v| v.z).fold(f64::NEG_INFINITY, f64::max);
                lo <= z && z < hi
            })
            .collect();
        for j in 0..ny {
            let y = body.origin.y + j as f64 * body.spacing[1] + 1e-7;
            let mut xs: Vec<f64> = Vec::new();
            for c in &tris {
                // Intersection of the line (·, y, z) with the triangle's plane, inside the triangle.
                let e1 = c[1] - c[0];
                let e2 = c[2] - c[0];
                let n = e1.cross(e2);
                if n.x.abs() < 1e-12 {
                    continue;
                }
                let x = c[0].x - (n.y * (y - c[0].y) + n.z * (z - c[0].z)) / n.x;
                let q = DVec3::new(x, y, z);
                let w0 = (c[1] - c[0]).cross(q - c[0]).dot(n);
                let w1 = (c[2] - c[1]).cross(q - c[1]).dot(n);
                let w2 = (c[0] - c[2]).cross(q - c[2]).dot(n);
                if (w0 >= 0.0 && w1 >= 0.0 && w2 >= 0.0) || (w0 <= 0.0 && w1 <= 0.0 && w2 <= 0.0) {
                    xs.push(x);
                }
            }
            xs.sort_by(|a, b| a.total_cmp(b));
            for pair in xs.chunks_exact(2) {
                for i in 0..nx {
                    let x = body.origin.x + i as f64 * body.spacing[0];
                    if x >= pair[0] && x < pair[1] {
                        body.labels[i + nx * (j + ny * k)] = value(DVec3::new(x, y, z));
                    }
                }
            }
        }
    }
}

/// An empty label volume at `spacing` holding `meshes` with a 10 mm margin.
pub fn empty_body_around(meshes: &[&TriMesh], spacing: [f64; 3]) -> Body {
    let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
    for m in meshes {
        for q in &m.positions {
            let v = DVec3::from(q.map(|v| v as f64));
            lo = lo.min(v);
            hi = hi.max(v);
        }
    }
    let dims = [0, 1, 2].map(|a| ((hi[a] - lo[a] + 20.0) / spacing[a]).ceil() as usize + 1);
    Body {
        dims,
        spacing,
        origin: lo - DVec3::splat(10.0),
        labels: vec![0; dims[0] * dims[1] * dims[2]],
    }
}

/// Both built-in lungs (4k vertices each) at `spacing`, right = `right`, left = `left` (a closure
/// may give lobes), on a grid that holds both with a margin.
pub fn both_lungs(
    spacing: [f64; 3],
    right: impl Fn(DVec3) -> u16,
    left: impl Fn(DVec3) -> u16,
) -> (Body, [TriMesh; 2]) {
    let r = anatomy::lung(Side::Right, 4000).expect("the built-in lung");
    let l = anatomy::lung(Side::Left, 4000).expect("the built-in lung");
    let mut body = empty_body_around(&[&r, &l], spacing);
    voxelise(&r, &mut body, &right);
    voxelise(&l, &mut body, &left);
    (body, [r, l])
}

/// Write `v` little-endian at byte `at` (a NIfTI header field).
pub fn put_f32(b: &mut [u8], at: usize, v: f32) {
    b[at..at + 4].copy_from_slice(&v.to_le_bytes());
}
/// Write `v` little-endian at byte `at` (a NIfTI header field).
pub fn put_i16(b: &mut [u8], at: usize, v: i16) {
    b[at..at + 2].copy_from_slice(&v.to_le_bytes());
}

/// The voxel grid written with voxel axes `axes` (each voxel axis's body direction), as a world
/// frame `world` (RAS or LPS) affine: the voxel order is reversed along every axis whose direction
/// is opposite the body's. Returns the voxel data in file order and the voxel → world matrix rows.
pub fn in_file_order(body: &Body, axes: Axes, world: Axes) -> (Vec<u16>, [[f64; 4]; 3]) {
    let [nx, ny, nz] = body.dims;
    // axes must be a sign change of (L, A, S) per axis (no permutation) for this helper.
    let sign: [f64; 3] = [0, 1, 2].map(|a| {
        let d = axes.0[a].body();
        if d[a] > 0.0 {
            1.0
        } else {
            -1.0
        }
    });
    let mut data = vec![0u16; body.labels.len()];
    for k in 0..nz {
        for j in 0..ny {
            for i in 0..nx {
                let src = [i, j, k];
                let dst: [usize; 3] = [0, 1, 2].map(|a| {
                    if sign[a] > 0.0 {
                        src[a]
                    } else {
                        body.dims[a] - 1 - src[a]
                    }
                });
                data[dst[0] + nx * (dst[1] + ny * dst[2])] = body.labels[i + nx * (j + ny * k)];
            }
        }
    }
    // Voxel (0,0,0) of the file is at the body position of the source's far end on flipped axes.
    let first = DVec3::new(
        body.origin.x
            + if sign[0] > 0.0 {
                0.0
            } else {
                (nx - 1) as f64 * body.spacing[0]
            },
        body.origin.y
            + if sign[1] > 0.0 {
                0.0
            } else {
                (ny - 1) as f64 * body.spacing[1]
            },
        body.origin.z
            + if sign[2] > 0.0 {
                0.0
            } else {
                (nz - 1) as f64 * body.spacing[2]
            },
    );
    let to_world = world.to_body().transpose(); // orthogonal sign matrix: its own inverse transpose
    let mut rows = [[0.0; 4]; 3];
    for a in 0..3 {
        let step_body = axes.0[a].body() * body.spacing[a];
        let w = to_world * step_body;
        for r in 0..3 {
            rows[r][a] = w[r];
        }
    }
    let o = to_world * first;
    for r in 0..3 {
        rows[r][3] = o[r];
    }
    (data, rows)
}

/// A NIfTI-1 file (int16 data) with the given sform rows (RAS), or no sform/qform when `None`.
pub fn nifti(body: &Body, rows: Option<[[f64; 4]; 3]>, data: &[u16]) -> Vec<u8> {
    let mut h = vec![0u8; 352];
    h[0..4].copy_from_slice(&348i32.to_le_bytes());
    put_i16(&mut h, 40, 3);
    for a in 0..3 {
        put_i16(&mut h, 42 + 2 * a, body.dims[a] as i16);
    }
    for a in 3..8 {
        put_i16(&mut h, 42 + 2 * a, 1);
    }
    put_i16(&mut h, 70, 4); // int16
    put_i16(&mut h, 72, 16);
    put_f32(&mut h, 76, 1.0);
    for a in 0..3 {
        put_f32(&mut h, 80 + 4 * a, body.spacing[a] as f32);
    }
    put_f32(&mut h, 108, 352.0);
    put_f32(&mut h, 112, 1.0);
    h[123] = 2; // mm
    if let Some(rows) = rows {
        put_i16(&mut h, 254, 2);
        for (r, row) in rows.iter().enumerate() {
            for c in 0..4 {
                put_f32(&mut h, 280 + 16 * r + 4 * c, row[c] as f32);
            }
        }
    }
    h[344..348].copy_from_slice(b"n+1\0");
    for &v in data {
        h.extend_from_slice(&(v as i16).to_le_bytes());
    }
    h
}

/// `bytes` gzipped (a `.nii.gz`).
pub fn gzip(bytes: &[u8]) -> Vec<u8> {
    let mut e = flate2::write::GzEncoder::new(Vec::new(), flate2::Compression::fast());
    e.write_all(bytes).expect("in memory");
    e.finish().expect("in memory")
}

/// An NRRD file (gzip-encoded unsigned shorts) with `rows` as its space directions and origin in
/// `space` ("right-anterior-superior" or "left-posterior-superior").
pub fn nrrd(body: &Body, rows: [[f64; 4]; 3], space: &str, data: &[u16]) -> Vec<u8> {
    let dir = |a: usize| format!("({},{},{})", rows[0][a], rows[1][a], rows[2][a]);
    let mut out = format!(
        "NRRD0004\n# made by lungdyn's tests\ntype: unsigned short\ndimension: 3\nspace: {space}\n\
         sizes: {} {} {}\nspace directions: {} {} {}\nkinds: domain domain domain\nendian: little\n\
         encoding: gzip\nspace origin: ({},{},{})\n\n",
        body.dims[0],
        body.dims[1],
        body.dims[2],
        dir(0),
        dir(1),
        dir(2),
        rows[0][3],
        rows[1][3],
        rows[2][3]
    )
    .into_bytes();
    let raw: Vec<u8> = data.iter().flat_map(|v| v.to_le_bytes()).collect();
    out.extend(gzip(&raw));
    out
}

/// A MetaImage file (zlib-compressed bytes) with `rows` as its direction and offset (LPS).
pub fn mha(body: &Body, rows: [[f64; 4]; 3], data: &[u16]) -> Vec<u8> {
    // ITK's TransformMatrix: the direction matrix's columns one after another.
    let s = body.spacing;
    let m: Vec<String> = (0..3)
        .flat_map(|a| (0..3).map(move |r| rows[r][a] / s[a]))
        .map(|v| v.to_string())
        .collect();
    let raw: Vec<u8> = data.iter().flat_map(|v| (*v as u8).to_le_bytes()).collect();
    let mut z = flate2::write::ZlibEncoder::new(Vec::new(), flate2::Compression::fast());
    z.write_all(&raw).expect("in memory");
    let packed = z.finish().expect("in memory");
    let mut out = format!(
        "ObjectType = Image\nNDims = 3\nBinaryData = True\nBinaryDataByteOrderMSB = False\n\
         CompressedData = True\nCompressedDataSize = {}\nTransformMatrix = {}\nOffset = {} {} {}\n\
         AnatomicalOrientation = RAI\nElementSpacing = {} {} {}\nDimSize = {} {} {}\n\
         ElementType = MET_UCHAR\nElementDataFile = LOCAL\n",
        packed.len(),
        m.join(" "),
        rows[0][3],
        rows[1][3],
        rows[2][3],
        s[0],
        s[1],
        s[2],
        body.dims[0],
        body.dims[1],
        body.dims[2]
    )
    .into_bytes();
    out.extend(packed);
    out
}
