//! OpenIGTLink POLYDATA content: the first piece of lungdyn speaking to 3D Slicer (issue 38 item 1;
//! `lungdyn demo --igtl-serve` sends it, framed by `crate::igtl_send`). Layout as the OpenIGTLink library packs it
//! (`Source/igtlutil/igtl_polydata.c`, `igtlPolyDataMessage.cxx`), all big-endian, no padding
//! between sections:
//!
//! 1. ten `u32`: points, vertices and their bytes, lines and their bytes, polygons and their bytes,
//!    triangle strips and their bytes, attributes (40 bytes);
//! 2. the points, `f32` x, y, z each;
//! 3. the cells: each a `u32` count then that many `u32` point indices (lungdyn sends polygons only:
//!    Slicer's converter mishandles vertex cells);
//! 4. per attribute a 6-byte header: `u8` type, `u8` components, `u32` tuples (the library's order,
//!    which the protocol text gives the other way round);
//! 5. the attributes' names, each NUL-terminated, back to back, one zero byte more when their total
//!    is odd;
//! 6. each attribute's data, `f32`.
//!
//! Only point scalars (type 0) are written: the library sizes RGBA, texture-coordinate and every
//! cell attribute wrongly (OpenIGTLink issue #36), so a per-vertex lobe code goes as a 1-component
//! point scalar. Slicer builds a new mesh from every message, so the topology goes with each one:
//! [`Topology`] encodes its bytes once and each frame copies them ([`encode`] into a reused buffer,
//! no allocation once it has grown).

use thiserror::Error;

/// The message type.
pub const TYPE_NAME: &str = "POLYDATA";
/// Attribute type of point scalars.
pub const POINT_SCALAR: u8 = 0x00;
/// Longest attribute name the library accepts (bytes, without the NUL).
pub const MAX_NAME_BYTES: usize = 255;
/// Most components of a point scalar.
pub const MAX_COMPONENTS: u8 = 127;

/// Why a POLYDATA body cannot be made.
#[derive(Debug, Clone, PartialEq, Eq, Error)]
pub enum PolyDataError {
    /// A cell names a point that does not exist.
    #[error("cell {cell} names point {index}, but there are {points} points")]
    BadIndex {
        /// The cell.
        cell: usize,
        /// The index.
        index: u32,
        /// Points.
        points: usize,
    },
    /// A cell with fewer than 3 points is no polygon.
    #[error("cell {cell} has {count} points; a polygon needs at least 3")]
    TooFewPoints {
        /// The cell.
        cell: usize,
        /// Its points.
        count: usize,
    },
    /// A count does not fit the format's 32 bits.
    #[error("{what} ({count}) does not fit OpenIGTLink's 32-bit counts")]
    TooMany {
        /// What.
        what: &'static str,
        /// How many.
        count: u64,
    },
    /// The points given are not the ones the topology was made for.
    #[error("{got} points given for a topology of {expected}")]
    PointCount {
        /// Expected.
        expected: usize,
        /// Given.
        got: usize,
    },
    /// A point is NaN or infinite: it would reach Slicer as a broken mesh.
    #[error("point {index} is not finite")]
    NotFinite {
        /// The point.
        index: usize,
    },
    /// An attribute's name is empty, too long or holds a NUL.
    #[error("attribute name {name:?}: {reason}")]
    BadName {
        /// The name.
        name: String,
        /// Why.
        reason: &'static str,
    },
    /// An attribute does not have one tuple per point, or a bad component count.
    #[error(
        "attribute {name:?} has {values} values for {points} points of {components} components"
    )]
    AttributeLength {
        /// Its name.
        name: String,
        /// Values given.
        values: usize,
        /// Points.
        points: usize,
        /// Components per point.
        components: u8,
    },
}

/// Per-point values sent with the mesh (a point scalar of `components` values per point).
#[derive(Debug, Clone, Copy)]
pub struct PointScalars<'a> {
    /// Its name in Slicer's scalar list.
    pub name: &'a str,
    /// Components per point, 1..=127.
    pub components: u8,
    /// `points × components` values.
    pub values: &'a [f32],
}

/// The polygons of a mesh, encoded once.
#[derive(Debug, Clone, PartialEq, Eq)]
pub struct Topology {
    points: usize,
    polygons: u32,
    bytes: Vec<u8>,
}

fn count32(what: &'static str, n: usize) -> Result<u32, PolyDataError> {
    u32::try_from(n).map_err(|_| PolyDataError::TooMany {
        what,
        count: n as u64,
    })
}

impl Topology {
    /// Polygons (each at least 3 point indices) over `points` points.
    pub fn polygons<'a>(
        cells: impl IntoIterator<Item = &'a [u32]>,
        points: usize,
    ) -> Result<Self, PolyDataError> {
        count32("points", points)?;
        let mut bytes = Vec::new();
        let mut n = 0usize;
        for (cell, c) in cells.into_iter().enumerate() {
            if c.len() < 3 {
                return Err(PolyDataError::TooFewPoints {
                    cell,
                    count: c.len(),
                });
            }
            bytes.extend_from_slice(&count32("a polygon's points", c.len())?.to_be_bytes());
            for &index in c {
                if index as usize >= points {
                    return Err(PolyDataError::BadIndex {
                        cell,
                        index,
                        points,
                    });
                }
                bytes.extend_from_slice(&index.to_be_bytes());
            }
            n += 1;
        }
        count32("polygon bytes", bytes.len())?;
        Ok(Self {
            points,
            polygons: count32("polygons", n)?,
            bytes,
        })
    }

    /// Triangles over `points` points.
    pub fn triangles(triangles: &[[u32; 3]], points: usize) -> Result<Self, PolyDataError> {
        Self::polygons(triangles.iter().map(|t| t.as_slice()), points)
    }

    /// The points the topology was made for.
    pub fn points(&self) -> usize {
        self.points
    }

    /// Bytes of the polygon section.
    pub fn polygon_bytes(&self) -> usize {
        self.bytes.len()
    }
}

/// The POLYDATA content of `points` (mm, as given) over `topology` with `scalars`, into `out`
/// (cleared first; its capacity is kept, so a sender that reuses it allocates nothing per frame).
pub fn encode(
    points: &[[f32; 3]],
    topology: &Topology,
    scalars: &[PointScalars<'_>],
    out: &mut Vec<u8>,
) -> Result<(), PolyDataError> {
    out.clear();
    append(points, topology, scalars, out)
}

/// [`encode`] appending to `out` (behind a header the sender seals, `crate::igtl_send`); on an
/// error nothing is appended.
pub fn append(
    points: &[[f32; 3]],
    topology: &Topology,
    scalars: &[PointScalars<'_>],
    out: &mut Vec<u8>,
) -> Result<(), PolyDataError> {
    check_points(points, topology.points)?;
    check_scalars(scalars, points.len())?;
    out.extend_from_slice(&counts(topology, scalars)?);
    append_points(points, out);
    append_tail(topology, scalars, out);
    Ok(())
}

/// The points fit the topology and are finite.
fn check_points(points: &[[f32; 3]], expected: usize) -> Result<(), PolyDataError> {
    if points.len() != expected {
        return Err(PolyDataError::PointCount {
            expected,
            got: points.len(),
        });
    }
    if let Some(index) = points.iter().position(|p| !p.iter().all(|v| v.is_finite())) {
        return Err(PolyDataError::NotFinite { index });
    }
    Ok(())
}

/// Every attribute has a usable name and one value per point and component.
fn check_scalars(scalars: &[PointScalars<'_>], points: usize) -> Result<(), PolyDataError> {
    for s in scalars {
        if s.name.is_empty() || s.name.len() > MAX_NAME_BYTES || s.name.contains('\0') {
            return Err(PolyDataError::BadName {
                name: s.name.to_string(),
                reason: "must be 1 to 255 bytes without a NUL",
            });
        }
        if s.components == 0
            || s.components > MAX_COMPONENTS
            || s.values.len() != points * s.components as usize
        {
            return Err(PolyDataError::AttributeLength {
                name: s.name.to_string(),
                values: s.values.len(),
                points,
                components: s.components,
            });
        }
    }
    Ok(())
}

/// Bytes of the ten counts that open the content.
const COUNTS_BYTES: usize = 40;

/// The ten counts that open the content: points, vertices, lines, polygons, strips (each a count
/// and a byte size), attributes.
fn counts(
    topology: &Topology,
    scalars: &[PointScalars<'_>],
) -> Result<[u8; COUNTS_BYTES], PolyDataError> {
    let npoints = count32("points", topology.points)?;
    let nattr = count32("attributes", scalars.len())?;
    let mut out = [0u8; COUNTS_BYTES];
    let values = [
        npoints,
        0,
        0,
        0,
        0,
        topology.polygons,
        topology.bytes.len() as u32,
        0,
        0,
        nattr,
    ];
    for (chunk, v) in out.chunks_exact_mut(4).zip(values) {
        chunk.copy_from_slice(&v.to_be_bytes());
    }
    Ok(out)
}

/// The points, big-endian `f32`s.
fn append_points(points: &[[f32; 3]], out: &mut Vec<u8>) {
    let start = out.len();
    out.resize(start + points.len() * 12, 0);
    for (chunk, v) in out[start..]
        .chunks_exact_mut(4)
        .zip(points.iter().flatten())
    {
        chunk.copy_from_slice(&v.to_be_bytes());
    }
}

/// Everything after the points: the polygons, the attributes' headers, names and values (checked
/// by [`check_scalars`]).
fn append_tail(topology: &Topology, scalars: &[PointScalars<'_>], out: &mut Vec<u8>) {
    let npoints = topology.points as u32;
    out.extend_from_slice(&topology.bytes);
    for s in scalars {
        out.push(POINT_SCALAR);
        out.push(s.components);
        out.extend_from_slice(&npoints.to_be_bytes());
    }
    let mut names_len = 0usize;
    for s in scalars {
        out.extend_from_slice(s.name.as_bytes());
        out.push(0);
        names_len += s.name.len() + 1;
    }
    if names_len % 2 == 1 {
        out.push(0);
    }
    for s in scalars {
        for v in s.values {
            out.extend_from_slice(&v.to_be_bytes());
        }
    }
}

/// A mesh whose triangles and point scalars stay fixed while its points move (a breathing lung
/// with its lobe codes): everything but the points encoded and CRC'd once, so a frame costs the
/// points' bytes and their CRC-64 — about a quarter of the message for a triangle mesh with one
/// point scalar (12 of some 48 bytes per vertex) — not the whole
/// body (`crate::igtl::CrcShift`). [`FixedMesh::append`] gives the same bytes as [`append`].
#[derive(Debug, Clone)]
pub struct FixedMesh {
    points: usize,
    counts: [u8; COUNTS_BYTES],
    tail: Vec<u8>,
    tail_crc: u64,
    over_tail: crate::igtl::CrcShift,
}

impl FixedMesh {
    /// The fixed part of meshes over `topology` with `scalars`.
    pub fn new(topology: &Topology, scalars: &[PointScalars<'_>]) -> Result<Self, PolyDataError> {
        check_scalars(scalars, topology.points)?;
        let counts = counts(topology, scalars)?;
        let mut tail = Vec::new();
        append_tail(topology, scalars, &mut tail);
        Ok(Self {
            points: topology.points,
            counts,
            tail_crc: crate::igtl::crc64(&tail),
            over_tail: crate::igtl::CrcShift::zero_bytes(tail.len() as u64),
            tail,
        })
    }

    /// The content of the mesh at `points`, appended to `out`; returns its CRC-64 (on an error
    /// nothing is appended).
    pub fn append(&self, points: &[[f32; 3]], out: &mut Vec<u8>) -> Result<u64, PolyDataError> {
        check_points(points, self.points)?;
        let start = out.len();
        out.extend_from_slice(&self.counts);
        append_points(points, out);
        let front = crate::igtl::crc64(&out[start..]);
        out.extend_from_slice(&self.tail);
        Ok(self.over_tail.combine(front, self.tail_crc))
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    /// The OpenIGTLink library's own POLYDATA test message (`Testing/igtlutil/
    /// igtl_test_data_polydata.h`): a unit cube, 8 points, 6 quads, one point scalar "attr" = 0..7;
    /// its header gives a 300-byte body with CRC-64 0x73dddfc80c48c62b. Ours, made from the same
    /// cube, has that length and that CRC: the same bytes as the library's, without copying them.
    #[test]
    fn the_librarys_own_cube_encodes_to_its_bytes() {
        let points: Vec<[f32; 3]> = [
            [0, 0, 0],
            [1, 0, 0],
            [1, 1, 0],
            [0, 1, 0],
            [0, 0, 1],
            [1, 0, 1],
            [1, 1, 1],
            [0, 1, 1],
        ]
        .iter()
        .map(|p| p.map(|v| v as f32))
        .collect();
        let quads: [[u32; 4]; 6] = [
            [0, 1, 2, 3],
            [4, 5, 6, 7],
            [0, 1, 5, 4],
            [1, 2, 6, 5],
            [2, 3, 7, 6],
            [3, 0, 4, 7],
        ];
        let topology = Topology::polygons(quads.iter().map(|q| q.as_slice()), 8).unwrap();
        assert_eq!(topology.polygon_bytes(), 0x78);
        let attr: Vec<f32> = (0..8).map(|i| i as f32).collect();
        let mut body = Vec::new();
        encode(
            &points,
            &topology,
            &[PointScalars {
                name: "attr",
                components: 1,
                values: &attr,
            }],
            &mut body,
        )
        .unwrap();
        assert_eq!(body.len(), 300);
        assert_eq!(crate::igtl::crc64(&body), 0x73dd_dfc8_0c48_c62b);
    }

    #[test]
    fn a_reused_buffer_keeps_its_capacity_and_the_topology_is_copied_each_frame() {
        let points = vec![[0.0f32; 3], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]];
        let t = Topology::triangles(&[[0, 1, 2]], 3).unwrap();
        let mut out = Vec::new();
        encode(&points, &t, &[], &mut out).unwrap();
        let first = out.clone();
        let cap = out.capacity();
        encode(&points, &t, &[], &mut out).unwrap();
        assert_eq!(out, first);
        assert_eq!(out.capacity(), cap);
        assert_eq!(out.len(), 40 + 3 * 12 + 16);
    }

    #[test]
    fn bad_meshes_and_attributes_are_refused_by_name() {
        assert!(matches!(
            Topology::triangles(&[[0, 1, 3]], 3),
            Err(PolyDataError::BadIndex { index: 3, .. })
        ));
        assert!(matches!(
            Topology::polygons([[0u32, 1].as_slice()], 3),
            Err(PolyDataError::TooFewPoints { count: 2, .. })
        ));
        let t = Topology::triangles(&[[0, 1, 2]], 3).unwrap();
        let mut out = Vec::new();
        let p = [[0.0f32; 3], [1.0, 0.0, 0.0], [0.0, f32::NAN, 0.0]];
        assert_eq!(
            encode(&p, &t, &[], &mut out),
            Err(PolyDataError::NotFinite { index: 2 })
        );
        let p = [[0.0f32; 3]; 3];
        assert!(matches!(
            encode(&p[..2], &t, &[], &mut out),
            Err(PolyDataError::PointCount { .. })
        ));
        let long = "x".repeat(256);
        for (name, components, n) in [("", 1u8, 3usize), (long.as_str(), 1, 3), ("a\0b", 1, 3)] {
            let v = vec![0.0; n];
            let s = PointScalars {
                name,
                components,
                values: &v,
            };
            assert!(matches!(
                encode(&p, &t, &[s], &mut out),
                Err(PolyDataError::BadName { .. })
            ));
        }
        for (components, n) in [(1u8, 2usize), (0, 0), (128, 384), (3, 3)] {
            let v = vec![0.0; n];
            let s = PointScalars {
                name: "lobe",
                components,
                values: &v,
            };
            assert!(matches!(
                encode(&p, &t, &[s], &mut out),
                Err(PolyDataError::AttributeLength { .. })
            ));
        }
    }

    /// A fixed mesh gives the plain encoder's bytes and the CRC of those bytes, frame after frame,
    /// with one scalar, several, an odd name length (the pad) and none; bad points append nothing.
    #[test]
    fn a_fixed_mesh_gives_the_plain_encoders_bytes_and_their_crc() {
        let tris = [[0u32, 1, 2], [0, 2, 3], [0, 3, 1], [1, 3, 2]];
        let topology = Topology::triangles(&tris, 4).unwrap();
        let lobes = [1.0f32, 2.0, 3.0, 4.0];
        let pairs = [0.5f32, -1.0, 2.0, 3.0, 1e-3, 7.0, 8.0, 9.0];
        let sets: [&[PointScalars<'_>]; 3] = [
            &[],
            &[PointScalars {
                name: "Lobe",
                components: 1,
                values: &lobes,
            }],
            &[
                PointScalars {
                    name: "odd",
                    components: 1,
                    values: &lobes,
                },
                PointScalars {
                    name: "Pairs",
                    components: 2,
                    values: &pairs,
                },
            ],
        ];
        for scalars in sets {
            let mesh = FixedMesh::new(&topology, scalars).unwrap();
            for frame in 0..3 {
                let t = frame as f32;
                let points = [[t, 0.0, 0.0], [1.0, t, 0.0], [0.0, 1.0, t], [-t, 2.5, 1e-7]];
                let mut plain = vec![9u8];
                append(&points, &topology, scalars, &mut plain).unwrap();
                let mut fixed = vec![9u8];
                let crc = mesh.append(&points, &mut fixed).unwrap();
                assert_eq!(fixed, plain);
                assert_eq!(crc, crate::igtl::crc64(&fixed[1..]));
            }
            let mut out = vec![1u8, 2];
            let nan = [[f32::NAN, 0.0, 0.0], [0.0; 3], [0.0; 3], [0.0; 3]];
            assert!(matches!(
                mesh.append(&nan, &mut out),
                Err(PolyDataError::NotFinite { index: 0 })
            ));
            assert!(matches!(
                mesh.append(&[[0.0; 3]; 3], &mut out),
                Err(PolyDataError::PointCount {
                    expected: 4,
                    got: 3
                })
            ));
            assert_eq!(out, [1, 2]);
        }
        let short = [PointScalars {
            name: "Lobe",
            components: 1,
            values: &lobes[..3],
        }];
        assert!(matches!(
            FixedMesh::new(&topology, &short),
            Err(PolyDataError::AttributeLength { .. })
        ));
    }
}
