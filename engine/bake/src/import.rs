//! Reading patient lung surfaces: OBJ (tobj), PLY (ply-rs-bw), STL ASCII and binary (stl_io).
//!
//! After reading, vertices at identical positions are welded (STL stores every triangle's corners
//! separately), and what is safe to repair is repaired and reported: triangles that collapse after
//! welding, exact duplicate triangles, unused vertices, a surface wound inside out. Everything else
//! [`lung_model::mesh::check`] refuses (open edges, non-manifold edges, inconsistent winding, NaN) is an error
//! naming the file and the problem. Header claims are checked against the file size before any
//! reader allocates, so a file claiming 2^31 faces costs nothing.

use std::collections::HashMap;
use std::io::{BufRead, Cursor};
use std::path::{Path, PathBuf};

use lung_model::mesh::{check, MeshError, Topology, TriMesh};

/// Length unit of the coordinates in a file.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Units {
    /// Millimetres (lungdyn's unit).
    Mm,
    /// Centimetres.
    Cm,
    /// Metres.
    M,
}

impl Units {
    /// Factor to millimetres.
    pub fn to_mm(self) -> f32 {
        match self {
            Units::Mm => 1.0,
            Units::Cm => 10.0,
            Units::M => 1000.0,
        }
    }
}

impl std::str::FromStr for Units {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "mm" => Ok(Units::Mm),
            "cm" => Ok(Units::Cm),
            "m" => Ok(Units::M),
            other => Err(format!("unknown unit {other:?}: use mm, cm or m")),
        }
    }
}

/// The coordinate frame of a mesh file's coordinates (all in the file's length unit).
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum MeshFrame {
    /// lungdyn's body frame: +X patient left, +Y anterior, +Z superior.
    #[default]
    Body,
    /// DICOM/ITK patient coordinates: +X left, +Y **posterior**, +Z superior (ITK-SNAP, most
    /// DICOM-RT / segmentation exports, 3D Slicer's default model export since 4.11).
    Lps,
    /// 3D Slicer's internal frame, NIfTI: +X **right**, +Y anterior, +Z superior.
    Ras,
}

impl MeshFrame {
    /// The body-frame position of a vertex given in this frame (`lung_model::frame`).
    pub fn to_body(self, p: [f32; 3]) -> [f32; 3] {
        match self {
            MeshFrame::Body => p,
            MeshFrame::Lps => lung_model::frame::lps_to_body_f32(p),
            MeshFrame::Ras => lung_model::frame::ras_to_body_f32(p),
        }
    }

    /// The name on the command line.
    pub fn name(self) -> &'static str {
        match self {
            MeshFrame::Body => "body",
            MeshFrame::Lps => "lps",
            MeshFrame::Ras => "ras",
        }
    }
}

impl std::str::FromStr for MeshFrame {
    type Err = String;
    fn from_str(s: &str) -> Result<Self, String> {
        match s {
            "body" => Ok(MeshFrame::Body),
            "lps" => Ok(MeshFrame::Lps),
            "ras" => Ok(MeshFrame::Ras),
            other => Err(format!("unknown frame {other:?}: use body, lps or ras")),
        }
    }
}

/// What was repaired while importing.
#[derive(Debug, Clone, Default, PartialEq, Eq, serde::Serialize)]
pub struct Repairs {
    /// Vertices merged into an identical one.
    pub welded_vertices: usize,
    /// Triangles removed because two corners coincided.
    pub degenerate_triangles: usize,
    /// Exact duplicate triangles removed.
    pub duplicate_triangles: usize,
    /// Vertices no triangle used, removed.
    pub unused_vertices: usize,
    /// The whole surface was wound inside out and was flipped.
    pub flipped_inside_out: bool,
}

/// An imported mesh.
#[derive(Debug, Clone)]
pub struct Imported {
    /// The mesh in mm.
    pub mesh: TriMesh,
    /// Its topology.
    pub topology: Topology,
    /// What was repaired.
    pub repairs: Repairs,
    /// Connected shells in the file (before `--component` picked one).
    pub shells: usize,
    /// Self-intersecting triangle pairs found (at most 16 counted); refused for a single lung, only
    /// reported for point sets.
    pub self_intersections: usize,
    /// Which lung the geometry looks like (the medial surface is concave); set by [`import_with`].
    pub side: Option<crate::surface_checks::SideEvidence>,
    /// Whether anterior/posterior or superior/inferior look flipped (in the body frame, after the
    /// stated frame's conversion); set by [`import_with`].
    pub orientation: Option<crate::surface_checks::OrientationEvidence>,
    /// Each vertex's lobe code ([`lung_model::mesh::lobes`]), where the file carries them (a PLY
    /// `lobe` vertex property, as `mesh from-mask` and `mesh generate --lobe-colours` write it);
    /// `bake` keeps them instead of the fissure planes'.
    pub lobes: Option<Vec<u8>>,
}

/// Which connected shells of a file to keep.
#[derive(Debug, Clone, Copy, PartialEq, Eq, Default)]
pub enum Shells {
    /// Exactly one shell is expected: more is refused (two lungs, or two copies of one, in one file).
    #[default]
    One,
    /// Keep shell `n` (1 = the largest by volume), drop the others (`--component N`).
    Pick(usize),
    /// Keep every shell (point sets for fitting, where both lungs may be in one file).
    All,
}

/// How to import.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct ImportOptions {
    /// Unit of the file's coordinates.
    pub units: Units,
    /// Size and line limits of the file.
    pub limits: lung_model::input::ReadLimits,
    /// Which shells to keep.
    pub shells: Shells,
    /// Check the result is the size of one lung (a single-lung surface: mesh check, bake); else only
    /// that its size is that of lungs at all (point sets of both lungs).
    pub one_lung: bool,
    /// Frame of the file's coordinates, converted to the body frame on reading.
    pub frame: MeshFrame,
}

impl ImportOptions {
    /// A single-lung surface in `units` with the default limits.
    pub fn lung(units: Units) -> Self {
        Self {
            units,
            limits: lung_model::input::ReadLimits::MESH,
            shells: Shells::One,
            one_lung: true,
            frame: MeshFrame::Body,
        }
    }
}

/// Import errors: each names the file.
#[derive(Debug, thiserror::Error)]
pub enum ImportError {
    /// Unreadable file, or not within the input limits.
    #[error(transparent)]
    Input(#[from] lung_model::input::InputError),
    /// The size of the surface is not that of a lung in the stated unit.
    #[error("{}: {source}", path.display())]
    Implausible {
        /// Path.
        path: PathBuf,
        /// The value out of range, with the likely unit mistake.
        source: lung_model::plausible::Implausible,
    },
    /// `--component N` names a shell the file does not have.
    #[error("{}: --component {asked}: the file has {count} shell(s); 1 is the largest", path.display())]
    NoSuchComponent {
        /// Path.
        path: PathBuf,
        /// Shell asked for.
        asked: usize,
        /// Shells in the file.
        count: usize,
    },
    /// The surface checks refused it (shells, self-intersections).
    #[error("{}: {source}", path.display())]
    Surface {
        /// Path.
        path: PathBuf,
        /// What is wrong.
        source: crate::surface_checks::SurfaceProblem,
    },
    /// Unknown extension.
    #[error("{}: unknown mesh format: use .obj, .ply or .stl", path.display())]
    Format {
        /// Path.
        path: PathBuf,
    },
    /// The reader rejected the content.
    #[error("{}: not a valid {format} file: {message}", path.display())]
    Parse {
        /// Path.
        path: PathBuf,
        /// Format name.
        format: &'static str,
        /// Reader's message.
        message: String,
    },
    /// The surface cannot be used (after safe repairs).
    #[error("{}: {source}", path.display())]
    Mesh {
        /// Path.
        path: PathBuf,
        /// What is wrong.
        source: MeshError,
    },
}

/// Import a single-lung surface `path` (format by extension), coordinates in `units`, with the
/// default limits: [`import_with`] and [`ImportOptions::lung`].
pub fn import(path: &Path, units: Units) -> Result<Imported, ImportError> {
    import_with(path, &ImportOptions::lung(units))
}

/// Import `path` (format by extension) as `opts` says: bounded reading, parsing, welding and safe
/// repairs, topology, shells, self-intersections, and the size of a lung in the stated unit.
pub fn import_with(path: &Path, opts: &ImportOptions) -> Result<Imported, ImportError> {
    let units = opts.units;
    let ext = path
        .extension()
        .and_then(|e| e.to_str())
        .map(|e| e.to_ascii_lowercase());
    let format: Option<&'static str> = match ext.as_deref() {
        Some("obj") => Some("OBJ"),
        Some("ply") => Some("PLY"),
        Some("stl") => Some("STL"),
        _ => None,
    };
    // The first bytes must already look like the format: a 3 GiB sparse file of zeros named .stl
    // is refused by its header, not after reading it all. (The path itself — a folder, a device, a
    // file over the size limit — is judged first, whatever its name.)
    let bytes = lung_model::input::read_bounded_with(
        path,
        lung_model::input::ReadLimits {
            // Binary PLY and STL have no lines; OBJ and ASCII files are checked by their parsers.
            max_line_bytes: 0,
            ..opts.limits
        },
        |head, size| match format {
            Some(f) => sniff(f, head, size).map_err(|m| format!("not a valid {f} file: {m}")),
            None => Err(String::new()),
        },
    );
    let Some(format) = format else {
        return Err(match bytes {
            Err(lung_model::input::InputError::Format { .. }) | Ok(_) => ImportError::Format {
                path: path.to_path_buf(),
            },
            Err(e) => e.into(),
        });
    };
    let bytes = bytes?;
    let parse = |message: String| ImportError::Parse {
        path: path.to_path_buf(),
        format,
        message,
    };
    let mut file_lobes = None;
    let (mut positions, mut triangles, unused_in_file) = match format {
        "OBJ" => read_obj(&bytes).map_err(parse)?,
        "PLY" => {
            let ((p, t), lobes) = read_ply(&bytes).map_err(parse)?;
            file_lobes = lobes;
            (p, t, 0)
        }
        _ => read_stl(&bytes).map(|(p, t)| (p, t, 0)).map_err(parse)?,
    };
    if opts.frame != MeshFrame::Body {
        for p in &mut positions {
            *p = opts.frame.to_body(*p);
        }
        // LPS and RAS each mirror one axis of the body frame: keep the winding outward (so an
        // outward file is not reported as repaired inside out).
        for t in &mut triangles {
            t.swap(1, 2);
        }
    }
    let mut imported =
        repair_with_lobes(positions, triangles, file_lobes, units).map_err(|source| {
            ImportError::Mesh {
                path: path.to_path_buf(),
                source,
            }
        })?;
    // The OBJ reader already left out vertices no face uses: count them as removed too.
    imported.repairs.unused_vertices += unused_in_file;
    let surface = |source| ImportError::Surface {
        path: path.to_path_buf(),
        source,
    };
    let comps = crate::surface_checks::components(&imported.mesh);
    imported.shells = comps.count;
    match opts.shells {
        Shells::One if comps.count > 1 => {
            return Err(surface(
                crate::surface_checks::SurfaceProblem::MultipleComponents {
                    count: comps.count,
                    sizes_ml: comps.sizes.iter().map(|c| c.volume_ml).collect(),
                },
            ))
        }
        Shells::Pick(n) if n == 0 || n > comps.count => {
            return Err(ImportError::NoSuchComponent {
                path: path.to_path_buf(),
                asked: n,
                count: comps.count,
            })
        }
        Shells::Pick(n) if comps.count > 1 => {
            let mesh = crate::surface_checks::extract_component(&imported.mesh, &comps, n - 1);
            let topology = check(&mesh).map_err(|source| ImportError::Mesh {
                path: path.to_path_buf(),
                source,
            })?;
            imported.mesh = mesh;
            imported.topology = topology;
            // The picked shell's vertices are renumbered: its lobes are the fissure planes' again.
            imported.lobes = None;
        }
        _ => {}
    }
    let hits = crate::surface_checks::self_intersections(&imported.mesh, 16);
    imported.self_intersections = hits.count;
    if let (true, Some(first)) = (opts.one_lung, hits.first) {
        let t = imported.mesh.triangles[first.0 as usize];
        let p = |i: u32| imported.mesh.positions[i as usize];
        let at_mm = [0, 1, 2].map(|k| (p(t[0])[k] + p(t[1])[k] + p(t[2])[k]) / 3.0);
        return Err(surface(
            crate::surface_checks::SurfaceProblem::SelfIntersecting {
                count: hits.count,
                first,
                at_mm,
            },
        ));
    }
    check_size(&imported.mesh, units, opts.one_lung).map_err(|source| {
        ImportError::Implausible {
            path: path.to_path_buf(),
            source,
        }
    })?;
    imported.side = Some(crate::surface_checks::infer_side(&imported.mesh));
    imported.orientation = Some(crate::surface_checks::infer_orientation(&imported.mesh));
    Ok(imported)
}

/// Whether `mesh` (in mm, read in `units`) has the size of one lung (`one_lung`) or of lungs at all.
pub fn check_size(
    mesh: &TriMesh,
    units: Units,
    one_lung: bool,
) -> Result<(), lung_model::plausible::Implausible> {
    use lung_model::plausible::{
        length_unit_hint, LANDMARK_SPREAD_MM, LUNG_EXTENT_MM, LUNG_VOLUME_ML,
    };
    let given = match units {
        Units::Mm => "mm",
        Units::Cm => "cm",
        Units::M => "m",
    };
    let size = mesh.aabb().size();
    let extent = size.iter().fold(0.0f64, |m, &v| m.max(v as f64));
    let limit = if one_lung {
        LUNG_EXTENT_MM
    } else {
        LANDMARK_SPREAD_MM
    };
    limit.check(extent, length_unit_hint(extent, given))?;
    if one_lung {
        LUNG_VOLUME_ML.check(
            mesh.enclosed_volume_ml(),
            Some("a lung's volume: is this one lung, in the stated unit?".into()),
        )?;
    }
    Ok(())
}

type Raw = (Vec<[f32; 3]>, Vec<[u32; 3]>);

/// An ASCII STL begins with `solid` and has a line end within this many bytes.
const STL_ASCII_PROBE: usize = 1024;

/// What the first bytes of a mesh file (`head`, the whole file when `size` equals its length) say
/// before the rest is read: an `Err` is the reason it cannot be a file of `format`.
fn sniff(format: &str, head: &[u8], size: Option<u64>) -> Result<(), String> {
    match format {
        "OBJ" => obj_text(head, size == Some(head.len() as u64)),
        "PLY" => {
            if !head.is_empty() && !head.starts_with(b"ply") {
                return Err("it does not begin with the line \"ply\"".into());
            }
            let whole = size == Some(head.len() as u64);
            // The claims are checked here when the header is in the head (it always is, but for
            // a header longer than the head, which the full read checks).
            match size {
                Some(size) if whole || head.windows(10).any(|w| w == b"end_header") => {
                    ply_claims(head, size)
                }
                _ => Ok(()),
            }
        }
        _ => match size {
            Some(size) => stl_claims(head, size),
            None => Ok(()),
        },
    }
}

/// OBJ is UTF-8 text without NUL bytes: the reason `bytes` is not (`complete`: `bytes` is the whole
/// file, so a character cut at its end is an error too).
fn obj_text(bytes: &[u8], complete: bool) -> Result<(), String> {
    let line_of = |offset: usize| bytes[..offset].iter().filter(|&&b| b == b'\n').count() + 1;
    let nul = bytes.iter().position(|&b| b == 0);
    let bad_utf8 = match std::str::from_utf8(bytes) {
        Ok(_) => None,
        // A character cut at the end of a head is not an error yet.
        Err(e) if e.error_len().is_none() && !complete => None,
        Err(e) => Some(e.valid_up_to()),
    };
    match (nul, bad_utf8) {
        (Some(n), b) if b.is_none_or(|b| n < b) => Err(format!(
            "binary data (a NUL byte at byte {n}, line {}), not OBJ text (UTF-8): no triangles can be \
             read from it; is this the right file?",
            line_of(n)
        )),
        (_, Some(b)) => Err(format!(
            "line {} is not UTF-8 text (at byte {b}): an OBJ file is text; re-export it, or remove the \
             non-UTF-8 characters (often in a comment or a name)",
            line_of(b)
        )),
        _ => Ok(()),
    }
}

/// Read an OBJ file: (positions, triangles, vertices of the file no face uses, which the reader
/// leaves out).
fn read_obj(bytes: &[u8]) -> Result<(Vec<[f32; 3]>, Vec<[u32; 3]>, usize), String> {
    obj_text(bytes, true)?;
    let (models, _) = tobj::load_obj_buf(&mut Cursor::new(bytes), &tobj::GPU_LOAD_OPTIONS, |_| {
        Err(tobj::LoadError::OpenFileFailed)
    })
    .map_err(|e| e.to_string())?;
    let (mut positions, mut triangles) = (Vec::new(), Vec::new());
    for m in models {
        let base = positions.len() as u32;
        positions.extend(m.mesh.positions.chunks_exact(3).map(|p| [p[0], p[1], p[2]]));
        for t in m.mesh.indices.chunks_exact(3) {
            triangles.push([t[0] + base, t[1] + base, t[2] + base]);
        }
    }
    // tobj numbers vertices in the order faces first use them; restore the file's `v` order, which
    // is what ties two phases of one lung together (fit-motion's correspondences).
    if let Some(perm) = obj_file_order(bytes, &positions) {
        let mut ordered = vec![[0.0f32; 3]; positions.len()];
        for (t, &n) in perm.iter().enumerate() {
            ordered[n as usize] = positions[t];
        }
        positions = ordered;
        for t in &mut triangles {
            *t = t.map(|v| perm[v as usize]);
        }
    }
    let file_vertices = std::str::from_utf8(bytes)
        .map(|text| {
            text.lines()
                .filter(|l| {
                    let l = l.trim_start();
                    l.starts_with("v ") || l.starts_with("v\t")
                })
                .count()
        })
        .unwrap_or(0);
    let unused = file_vertices.saturating_sub(positions.len());
    Ok((positions, triangles, unused))
}

/// For each vertex tobj returned, its rank among the file's `v` lines, matched by the exact parsed
/// coordinates; `None` when the match is not one-to-one (duplicate coordinates), in which case
/// tobj's order is kept.
fn obj_file_order(bytes: &[u8], positions: &[[f32; 3]]) -> Option<Vec<u32>> {
    let key = |p: &[f32; 3]| p.map(f32::to_bits);
    let mut by_key: HashMap<[u32; 3], u32> = HashMap::with_capacity(positions.len());
    for (i, p) in positions.iter().enumerate() {
        if by_key.insert(key(p), i as u32).is_some() {
            return None;
        }
    }
    let text = std::str::from_utf8(bytes).ok()?;
    let mut perm = vec![u32::MAX; positions.len()];
    let mut next = 0u32;
    for line in text.lines() {
        let Some(rest) = line.strip_prefix("v ").or_else(|| line.strip_prefix("v\t")) else {
            continue;
        };
        let mut f = rest.split_whitespace().map(|v| v.parse::<f32>());
        let (Some(Ok(x)), Some(Ok(y)), Some(Ok(z))) = (f.next(), f.next(), f.next()) else {
            return None;
        };
        if let Some(&t) = by_key.get(&key(&[x, y, z])) {
            if perm[t as usize] == u32::MAX {
                perm[t as usize] = next;
                next += 1;
            }
        }
    }
    (next as usize == positions.len()).then_some(perm)
}

/// Element counts a PLY header claims, checked against the file size before anything is allocated.
fn ply_claims(bytes: &[u8], size: u64) -> Result<(), String> {
    let mut total: u64 = 0;
    for line in bytes.lines().take(1000) {
        let line = line.map_err(|_| "the header is not text".to_string())?;
        if line.trim() == "end_header" {
            // Every element takes at least one byte in any PLY encoding.
            return if total <= size {
                Ok(())
            } else {
                Err(format!(
                    "the header claims {total} elements, more than the file's {size} bytes can hold"
                ))
            };
        }
        let mut words = line.split_whitespace();
        if words.next() == Some("element") {
            let count: u64 = words
                .nth(1)
                .and_then(|c| c.parse().ok())
                .ok_or(format!("bad element line {line:?}"))?;
            total = total.saturating_add(count);
        }
    }
    Err("no end_header line".into())
}

/// A PLY's positions and triangles, and its vertices' `lobe` codes when it has that property.
fn read_ply(bytes: &[u8]) -> Result<(Raw, Option<Vec<u8>>), String> {
    use ply_rs_bw::ply::{DefaultElement, Property};
    ply_claims(bytes, bytes.len() as u64)?;
    let parser = ply_rs_bw::parser::Parser::<DefaultElement>::new();
    let ply = parser
        .read_ply(&mut Cursor::new(bytes))
        .map_err(|e| e.to_string())?;
    let scalar = |p: &Property| -> Option<f32> {
        Some(match *p {
            Property::Float(v) => v,
            Property::Double(v) => v as f32,
            Property::Int(v) => v as f32,
            Property::UInt(v) => v as f32,
            Property::Short(v) => v as f32,
            Property::UShort(v) => v as f32,
            Property::Char(v) => v as f32,
            Property::UChar(v) => v as f32,
            _ => return None,
        })
    };
    let vertices = ply.payload.get("vertex").ok_or("no vertex element")?;
    let mut positions = Vec::with_capacity(vertices.len());
    for (i, v) in vertices.iter().enumerate() {
        let get = |k: &str| {
            v.get(k)
                .and_then(scalar)
                .ok_or(format!("vertex {i} has no numeric {k}"))
        };
        positions.push([get("x")?, get("y")?, get("z")?]);
    }
    let lobes = if vertices.first().is_some_and(|v| v.contains_key("lobe")) {
        let mut codes = Vec::with_capacity(vertices.len());
        for (i, v) in vertices.iter().enumerate() {
            let code = v
                .get("lobe")
                .and_then(scalar)
                .filter(|&c| c.fract() == 0.0 && (0.0..=5.0).contains(&c))
                .ok_or(format!(
                    "vertex {i}'s lobe is not a lobe code 0..5 (0 unknown, 1–3 right upper/middle/lower, 4–5 left upper/lower)"
                ))?;
            codes.push(code as u8);
        }
        Some(codes)
    } else {
        None
    };
    let faces = ply.payload.get("face").ok_or("no face element")?;
    let mut triangles = Vec::with_capacity(faces.len());
    for (i, f) in faces.iter().enumerate() {
        let list = f
            .get("vertex_indices")
            .or_else(|| f.get("vertex_index"))
            .ok_or(format!("face {i} has no vertex_indices"))?;
        let idx: Vec<i64> = match list {
            Property::ListInt(v) => v.iter().map(|&x| x as i64).collect(),
            Property::ListUInt(v) => v.iter().map(|&x| x as i64).collect(),
            Property::ListShort(v) => v.iter().map(|&x| x as i64).collect(),
            Property::ListUShort(v) => v.iter().map(|&x| x as i64).collect(),
            Property::ListChar(v) => v.iter().map(|&x| x as i64).collect(),
            Property::ListUChar(v) => v.iter().map(|&x| x as i64).collect(),
            _ => return Err(format!("face {i}: vertex_indices is not an integer list")),
        };
        if idx.len() < 3 || idx.iter().any(|&x| x < 0 || x >= positions.len() as i64) {
            return Err(format!(
                "face {i} has fewer than 3 corners or an index outside 0..{}",
                positions.len()
            ));
        }
        // Polygons are fanned into triangles.
        for k in 1..idx.len() - 1 {
            triangles.push([idx[0] as u32, idx[k] as u32, idx[k + 1] as u32]);
        }
    }
    Ok(((positions, triangles), lobes))
}

/// A binary STL's header claim (80-byte header, u32 count, 50 bytes per triangle) against the file's
/// `size`, from its first bytes `head`; an ASCII STL (`solid` and a line end early) passes.
fn stl_claims(head: &[u8], size: u64) -> Result<(), String> {
    let ascii = head.starts_with(b"solid")
        && head.iter().take(STL_ASCII_PROBE).any(|&b| b == b'\n')
        && !looks_binary(head, size);
    if ascii {
        return Ok(());
    }
    if size < 84 || head.len() < 84 {
        return Err(format!(
            "{size} bytes is too short for a binary STL (84-byte header)"
        ));
    }
    let claimed = u32::from_le_bytes(head[80..84].try_into().unwrap()) as u64;
    let expected = 84 + 50 * claimed;
    if expected != size {
        return Err(format!(
            "the header claims {claimed} triangles ({expected} bytes) but the file has {size} bytes"
        ));
    }
    Ok(())
}

fn read_stl(bytes: &[u8]) -> Result<Raw, String> {
    // Check the claim before reading.
    stl_claims(bytes, bytes.len() as u64)?;
    let mesh = stl_io::read_stl(&mut Cursor::new(bytes)).map_err(|e| e.to_string())?;
    let positions = mesh.vertices.iter().map(|v| v.0).collect();
    let triangles = mesh
        .faces
        .iter()
        .map(|f| f.vertices.map(|i| i as u32))
        .collect();
    Ok((positions, triangles))
}

/// A binary STL may also begin with "solid": it is binary when its size matches the count.
fn looks_binary(head: &[u8], size: u64) -> bool {
    head.len() >= 84 && {
        let claimed = u32::from_le_bytes(head[80..84].try_into().unwrap()) as u64;
        84 + 50 * claimed == size
    }
}

/// Weld, repair what is safe, scale to mm, and check.
pub fn repair(
    positions: Vec<[f32; 3]>,
    triangles: Vec<[u32; 3]>,
    units: Units,
) -> Result<Imported, MeshError> {
    repair_with_lobes(positions, triangles, None, units)
}

/// [`repair`], carrying a lobe code per vertex through the welding and compaction (a welded
/// vertex keeps the first one's code).
pub fn repair_with_lobes(
    positions: Vec<[f32; 3]>,
    triangles: Vec<[u32; 3]>,
    lobes: Option<Vec<u8>>,
    units: Units,
) -> Result<Imported, MeshError> {
    let mut repairs = Repairs::default();
    if let Some(i) = positions
        .iter()
        .position(|p| p.iter().any(|v| !v.is_finite()))
    {
        return Err(MeshError::NonFinite { vertex: i });
    }
    if let Some(t) = triangles
        .iter()
        .position(|t| t.iter().any(|&i| i as usize >= positions.len()))
    {
        return Err(MeshError::IndexOutOfRange { triangle: t });
    }
    // Weld identical positions (−0.0 and 0.0 are the same point).
    let key = |p: &[f32; 3]| p.map(|v| if v == 0.0 { 0u32 } else { v.to_bits() });
    let mut first: HashMap<[u32; 3], u32> = HashMap::with_capacity(positions.len());
    let mut remap = Vec::with_capacity(positions.len());
    for (i, p) in positions.iter().enumerate() {
        let id = *first.entry(key(p)).or_insert(i as u32);
        if id != i as u32 {
            repairs.welded_vertices += 1;
        }
        remap.push(id);
    }
    let mut seen = std::collections::HashSet::with_capacity(triangles.len());
    let mut kept = Vec::with_capacity(triangles.len());
    for t in &triangles {
        let t = t.map(|i| remap[i as usize]);
        if t[0] == t[1] || t[1] == t[2] || t[0] == t[2] {
            repairs.degenerate_triangles += 1;
            continue;
        }
        // Same triangle, same winding, any rotation.
        let r = (0..3).min_by_key(|&k| t[k]).unwrap_or(0);
        if !seen.insert([t[r], t[(r + 1) % 3], t[(r + 2) % 3]]) {
            repairs.duplicate_triangles += 1;
            continue;
        }
        kept.push(t);
    }
    // Compact: drop unused vertices, keeping the file's vertex order (two phases of a lung
    // correspond by it).
    let mut used = vec![false; positions.len()];
    for t in &kept {
        for &i in t {
            used[i as usize] = true;
        }
    }
    let mut new_index = vec![u32::MAX; positions.len()];
    let mut out_positions = Vec::new();
    let mut out_lobes = lobes.as_ref().map(|_| Vec::new());
    let s = units.to_mm();
    for (i, p) in positions.iter().enumerate() {
        if used[i] {
            new_index[i] = out_positions.len() as u32;
            out_positions.push([p[0] * s, p[1] * s, p[2] * s]);
            if let (Some(out), Some(l)) = (out_lobes.as_mut(), lobes.as_ref()) {
                out.push(l[i]);
            }
        }
    }
    for t in &mut kept {
        *t = t.map(|i| new_index[i as usize]);
    }
    repairs.unused_vertices = positions.len() - repairs.welded_vertices - out_positions.len();
    let mut mesh = TriMesh {
        positions: out_positions,
        triangles: kept,
    };
    if !mesh.triangles.is_empty() && mesh.enclosed_volume_mm3() < 0.0 {
        for t in &mut mesh.triangles {
            t.swap(1, 2);
        }
        repairs.flipped_inside_out = true;
    }
    if let Some(i) = mesh
        .positions
        .iter()
        .position(|p| p.iter().any(|v| !v.is_finite()))
    {
        // Finite in the file, infinite once scaled to mm (coordinates near f32::MAX).
        return Err(MeshError::NonFinite { vertex: i });
    }
    let topology = check(&mesh)?;
    Ok(Imported {
        mesh,
        topology,
        repairs,
        shells: 1,
        self_intersections: 0,
        side: None,
        orientation: None,
        lobes: out_lobes,
    })
}

#[cfg(test)]
mod tests {
    use super::*;
    use lung_model::mesh::{generate, io, Side};
    use proptest::prelude::*;

    fn tmp(name: &str) -> PathBuf {
        let dir = std::env::temp_dir().join(format!("lungdyn-import-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        dir.join(name)
    }

    #[test]
    fn our_own_obj_and_ply_round_trip() {
        let mesh = generate::lung(Side::Left, 1000).unwrap();
        for name in ["rt.obj", "rt.ply"] {
            let p = tmp(name);
            io::write_mesh(&mesh, &p).unwrap();
            let back = import(&p, Units::Mm).unwrap();
            assert_eq!(back.mesh.triangles.len(), mesh.triangles.len());
            assert_eq!(back.repairs, Repairs::default(), "{name}");
            assert!((back.mesh.enclosed_volume_ml() - 1100.0).abs() < 0.01);
            // The file's vertex order survives (two phases of a lung correspond by it).
            let first = back
                .mesh
                .positions
                .iter()
                .zip(&mesh.positions)
                .position(|(a, b)| a != b);
            assert!(first.is_none(), "{name}: vertex order changed at {first:?}");
            assert!(
                back.mesh.triangles == mesh.triangles,
                "{name}: triangles changed"
            );
        }
        // A face order that first uses the last vertex still keeps the file order.
        let p = tmp("reordered.obj");
        std::fs::write(
            &p,
            "v 0 0 0\nv 100 0 0\nv 0 100 0\nv 0 0 100\nf 4 2 3\nf 1 3 2\nf 1 2 4\nf 1 4 3\n",
        )
        .unwrap();
        let back = import(&p, Units::Mm).unwrap();
        assert_eq!(back.mesh.positions[0], [0.0, 0.0, 0.0]);
        assert_eq!(back.mesh.positions[3], [0.0, 0.0, 100.0]);
        assert_eq!(back.mesh.triangles[0], [3, 1, 2]);
    }

    fn stl_binary(mesh: &TriMesh) -> Vec<u8> {
        let mut b = vec![0u8; 80];
        b.extend((mesh.triangles.len() as u32).to_le_bytes());
        for t in &mesh.triangles {
            b.extend([0u8; 12]);
            for &i in t {
                for v in mesh.positions[i as usize] {
                    b.extend(v.to_le_bytes());
                }
            }
            b.extend([0u8; 2]);
        }
        b
    }

    #[test]
    fn stl_is_welded_into_a_closed_surface_and_units_apply() {
        let mesh = generate::lung(Side::Right, 1000).unwrap();
        let p = tmp("lung.stl");
        // In centimetres: coordinates / 10, then --units cm brings them back.
        let cm = TriMesh {
            positions: mesh.positions.iter().map(|p| p.map(|v| v / 10.0)).collect(),
            ..mesh.clone()
        };
        std::fs::write(&p, stl_binary(&cm)).unwrap();
        let back = import(&p, Units::Cm).unwrap();
        // stl_io indexes identical corners itself; either way every corner is welded.
        assert_eq!(back.mesh.positions.len(), mesh.positions.len());
        assert!((back.mesh.enclosed_volume_ml() - 1300.0).abs() < 0.5);
    }

    #[test]
    fn inside_out_and_duplicates_are_repaired_and_reported() {
        let mut mesh = generate::lung(Side::Left, 200).unwrap();
        for t in &mut mesh.triangles {
            t.swap(1, 2);
        }
        mesh.triangles.push(mesh.triangles[0]);
        let r = repair(mesh.positions.clone(), mesh.triangles.clone(), Units::Mm).unwrap();
        assert!(r.repairs.flipped_inside_out);
        assert_eq!(r.repairs.duplicate_triangles, 1);
    }

    #[test]
    fn holes_and_garbage_are_refused_naming_file_and_problem() {
        let mut mesh = generate::lung(Side::Left, 200).unwrap();
        mesh.triangles.truncate(mesh.triangles.len() - 2);
        let p = tmp("open.obj");
        io::write_mesh(&mesh, &p).unwrap();
        let e = import(&p, Units::Mm).unwrap_err().to_string();
        assert!(
            e.contains("open.obj") && e.contains("open boundary edges"),
            "{e}"
        );
        let p = tmp("empty.stl");
        std::fs::write(&p, b"").unwrap();
        assert!(import(&p, Units::Mm)
            .unwrap_err()
            .to_string()
            .contains("too short"));
        let p = tmp("huge.stl");
        let mut b = vec![0u8; 80];
        b.extend((1u32 << 31).to_le_bytes());
        std::fs::write(&p, &b).unwrap();
        let e = import(&p, Units::Mm).unwrap_err().to_string();
        assert!(e.contains("claims 2147483648 triangles"), "{e}");
        let p = tmp("huge.ply");
        std::fs::write(&p, b"ply\nformat ascii 1.0\nelement vertex 3\nproperty float x\nproperty float y\nproperty float z\nelement face 2147483648\nproperty list uchar int vertex_indices\nend_header\n").unwrap();
        assert!(import(&p, Units::Mm)
            .unwrap_err()
            .to_string()
            .contains("claims"));
        let p = tmp("nan.obj");
        std::fs::write(&p, b"v 0 0 0\nv 1 0 0\nv 0 nan 0\nf 1 2 3\n").unwrap();
        assert!(import(&p, Units::Mm).is_err());
        let p = tmp("x.dae");
        std::fs::write(&p, b"").unwrap();
        assert!(matches!(
            import(&p, Units::Mm),
            Err(ImportError::Format { .. })
        ));
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(300))]
        #[test]
        fn arbitrary_bytes_never_panic_any_reader(bytes in proptest::collection::vec(any::<u8>(), 0..600), ext in 0usize..3) {
            let p = tmp(&format!("fuzz-{}.{}", std::process::id(), ["obj", "ply", "stl"][ext]));
            std::fs::write(&p, &bytes).unwrap();
            let _ = import(&p, Units::Mm);
        }

        #[test]
        fn mutated_valid_files_never_panic(flips in proptest::collection::vec((0usize..4000, any::<u8>()), 1..8), ext in 0usize..2) {
            let mesh = generate::lung(Side::Left, 100).unwrap();
            let p = tmp(&format!("mut-{}.{}", std::process::id(), ["ply", "stl"][ext]));
            if ext == 0 { io::write_mesh(&mesh, &p).unwrap(); } else { std::fs::write(&p, stl_binary(&mesh)).unwrap(); }
            let mut bytes = std::fs::read(&p).unwrap();
            for (at, v) in flips { let n = bytes.len(); bytes[at % n] = v; }
            std::fs::write(&p, &bytes).unwrap();
            let _ = import(&p, Units::Mm);
        }
    }
}
