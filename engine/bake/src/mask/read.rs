//! Reading label images: NIfTI-1 (`.nii`, `.nii.gz`, through the `nifti` crate), NRRD (`.nrrd`,
//! `.seg.nrrd`: raw or gzip, attached data) and MetaImage (`.mha`: raw or zlib). NRRD and
//! MetaImage have no well-kept Rust reader (issue 34's survey: none on crates.io but a GPL
//! microscopy crate), so their small text headers are read here; the voxel data is checked against
//! the size the header claims before anything is allocated from it.
//!
//! Every reader gives the voxel → body-frame transform from the file's own header, or refuses:
//! * NIfTI: the sform when its code is set, else the qform (quaternion, `qfac` = pixdim[0]), in RAS
//!   mm (`xyzt_units` metres and micrometres scaled; unset taken as mm and noted). Neither set: the
//!   file says nothing about the patient's axes and is refused unless `--axes` states them.
//! * NRRD: `space directions` (one column per axis) and `space origin` in the `space` it names
//!   (LPS, RAS, LAS, ...); a `space` without anatomical meaning (scanner-xyz) is refused likewise.
//! * MetaImage: `TransformMatrix` (ITK writes the direction matrix's columns one after another),
//!   `Offset`, `ElementSpacing`, in ITK's LPS world.

use std::io::Read;
use std::path::Path;

use glam::{DMat3, DQuat, DVec3};

use super::volume::{check_grid, Axes, FrameSource, LabelVolume, VoxelToBody};
use super::MaskError;
use lung_model::input::{read_bounded, ReadLimits};

/// Largest label file read (compressed size), and largest decompressed voxel data.
pub const MASK_LIMITS: ReadLimits = ReadLimits {
    max_bytes: 2 << 30,
    max_line_bytes: 0,
    allow_special: false,
};
const MAX_VOXEL_BYTES: u64 = 4 << 30;

/// The image formats read.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum Format {
    /// NIfTI-1, optionally gzipped.
    Nifti,
    /// NRRD.
    Nrrd,
    /// MetaImage, header and data in one file.
    Mha,
}

impl Format {
    /// The format a path names by its extension.
    pub fn of(path: &Path) -> Option<Format> {
        let name = path.file_name()?.to_str()?.to_ascii_lowercase();
        if name.ends_with(".nii") || name.ends_with(".nii.gz") {
            Some(Format::Nifti)
        } else if name.ends_with(".nrrd") {
            Some(Format::Nrrd)
        } else if name.ends_with(".mha") {
            Some(Format::Mha)
        } else {
            None
        }
    }
}

/// Read the label image at `path`; `axes` (when given) replaces the header's voxel axis directions.
pub fn read_labels(
    path: &Path,
    limits: ReadLimits,
    axes: Option<Axes>,
) -> Result<LabelVolume, MaskError> {
    let format = Format::of(path).ok_or_else(|| MaskError::Format {
        path: path.to_path_buf(),
        message: "unknown label image format: use NIfTI (.nii, .nii.gz), NRRD (.nrrd, .seg.nrrd) \
                  or MetaImage (.mha); DICOM SEG: convert it first (e.g. 3D Slicer, dcmqi's \
                  segimage2itkimage)"
            .into(),
    })?;
    let bytes = read_bounded(path, limits)?;
    let bad = |message: String| MaskError::Format {
        path: path.to_path_buf(),
        message,
    };
    let mut volume = match format {
        Format::Nifti => read_nifti(&bytes, axes.is_some()).map_err(bad)?,
        Format::Nrrd => read_nrrd(&bytes, axes.is_some()).map_err(bad)?,
        Format::Mha => read_mha(&bytes).map_err(bad)?,
    };
    if let Some(axes) = axes {
        volume.frame.axes_override = Some(axes.code());
        volume.to_body = volume.to_body.with_axes(axes);
    }
    check_grid(volume.dims, &volume.to_body).map_err(bad)?;
    Ok(volume)
}

/// Decompress a gzip or zlib stream, refusing more than `limit` bytes out.
fn inflate(data: &[u8], gzip: bool, limit: u64) -> Result<Vec<u8>, String> {
    let mut out = Vec::new();
    let r: Box<dyn Read> = if gzip {
        Box::new(flate2::read::MultiGzDecoder::new(data))
    } else {
        Box::new(flate2::read::ZlibDecoder::new(data))
    };
    r.take(limit + 1)
        .read_to_end(&mut out)
        .map_err(|e| format!("its compressed data does not decompress: {e}"))?;
    if out.len() as u64 > limit {
        return Err(format!(
            "its data decompresses to more than {limit} bytes: not a lung label image"
        ));
    }
    Ok(out)
}

/// Scalar voxel types of the three formats.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
enum Scalar {
    U8,
    I8,
    U16,
    I16,
    U32,
    I32,
    F32,
    F64,
}

impl Scalar {
    fn bytes(self) -> usize {
        match self {
            Scalar::U8 | Scalar::I8 => 1,
            Scalar::U16 | Scalar::I16 => 2,
            Scalar::U32 | Scalar::I32 | Scalar::F32 => 4,
            Scalar::F64 => 8,
        }
    }
}

/// Convert raw voxel data to label values (0..=65535, whole numbers), scaled by `slope`/`inter`.
fn to_labels(
    raw: &[u8],
    scalar: Scalar,
    big_endian: bool,
    count: usize,
    slope: f64,
    inter: f64,
) -> Result<Vec<u16>, String> {
    let n = scalar.bytes();
    if raw.len() < count * n {
        return Err(format!(
            "its voxel data is {} bytes where the header's sizes need {} ({} voxels of {n} bytes): \
             the file is cut short or its header is wrong",
            raw.len(),
            count * n,
            count
        ));
    }
    let word = |c: &[u8]| -> f64 {
        let mut b = [0u8; 8];
        b[..n].copy_from_slice(c);
        if big_endian {
            b[..n].reverse();
        }
        match scalar {
            Scalar::U8 => b[0] as f64,
            Scalar::I8 => b[0] as i8 as f64,
            Scalar::U16 => u16::from_le_bytes([b[0], b[1]]) as f64,
            Scalar::I16 => i16::from_le_bytes([b[0], b[1]]) as f64,
            Scalar::U32 => u32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Scalar::I32 => i32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Scalar::F32 => f32::from_le_bytes([b[0], b[1], b[2], b[3]]) as f64,
            Scalar::F64 => f64::from_le_bytes(b),
        }
    };
    let mut out = Vec::with_capacity(count);
    for (idx, c) in raw.chunks_exact(n).take(count).enumerate() {
        let v = word(c) * slope + inter;
        if !((0.0..=65535.0).contains(&v) && v.fract() == 0.0) {
            return Err(format!(
                "voxel {idx} holds {v}: a label image holds whole numbers 0..65535 (is this a CT \
                 image or a probability map rather than a segmentation?)"
            ));
        }
        out.push(v as u16);
    }
    Ok(out)
}

// ----------------------------------------------------------------------------------------------
// NIfTI-1
// ----------------------------------------------------------------------------------------------

fn read_nifti(bytes: &[u8], axes_given: bool) -> Result<LabelVolume, String> {
    use nifti::{InMemNiftiObject, NiftiHeader, NiftiObject, NiftiType};
    let gz = bytes.starts_with(&[0x1f, 0x8b]);
    let data = if gz {
        inflate(bytes, true, MAX_VOXEL_BYTES)?
    } else {
        bytes.to_vec()
    };
    if data.len() < 348 {
        return Err(format!(
            "{} bytes: shorter than a NIfTI-1 header (348)",
            data.len()
        ));
    }
    let header =
        NiftiHeader::from_reader(&data[..]).map_err(|e| format!("not a NIfTI-1 file: {e}"))?;
    let dim = header.dim;
    if !(3..=5).contains(&dim[0]) || dim[1..=3].contains(&0) {
        return Err(format!(
            "dim {:?}: a label image is a 3D volume (dim[0] = 3, or 4–5 with one time point)",
            &dim[..(dim[0].min(7) as usize + 1)]
        ));
    }
    if dim[4..=(dim[0] as usize)].iter().any(|&d| d > 1) {
        return Err(format!(
            "dim {:?}: it holds several volumes (a time series or a 4D stack); give one 3D label \
             image",
            &dim[..(dim[0] as usize + 1)]
        ));
    }
    let dims = [dim[1] as usize, dim[2] as usize, dim[3] as usize];
    let count = dims.iter().product::<usize>();
    let scalar = match header
        .data_type()
        .map_err(|e| format!("unknown datatype {}: {e}", header.datatype))?
    {
        NiftiType::Uint8 => Scalar::U8,
        NiftiType::Int8 => Scalar::I8,
        NiftiType::Uint16 => Scalar::U16,
        NiftiType::Int16 => Scalar::I16,
        NiftiType::Uint32 => Scalar::U32,
        NiftiType::Int32 => Scalar::I32,
        NiftiType::Float32 => Scalar::F32,
        NiftiType::Float64 => Scalar::F64,
        other => {
            return Err(format!(
                "datatype {other:?}: a label image is stored as integers (or floats holding them)"
            ))
        }
    };
    let need = header.vox_offset.max(348.0) as u64 + (count * scalar.bytes()) as u64;
    if (data.len() as u64) < need {
        return Err(format!(
            "{} bytes where its header ({}×{}×{} voxels of {} bytes from offset {}) needs {need}: \
             cut short or a wrong header",
            data.len(),
            dims[0],
            dims[1],
            dims[2],
            scalar.bytes(),
            header.vox_offset
        ));
    }
    let obj = InMemNiftiObject::from_reader(&data[..])
        .map_err(|e| format!("its volume could not be read: {e}"))?;
    let raw = obj.volume().raw_data();
    let big = matches!(header.endianness, nifti::Endianness::Big);
    let (slope, inter) = if header.scl_slope == 0.0 || !header.scl_slope.is_finite() {
        (1.0, 0.0)
    } else {
        (header.scl_slope as f64, header.scl_inter as f64)
    };
    let labels = to_labels(raw, scalar, big, count, slope, inter)?;

    let mut notes = Vec::new();
    let (to_body, from) = nifti_frame(&header, axes_given, &mut notes)?;
    if header.intent_code != 0 && header.intent_code != 1002 {
        notes.push(format!(
            "the NIfTI intent code is {} (a label image has 0 or 1002, NIFTI_INTENT_LABEL)",
            header.intent_code
        ));
    }
    Ok(LabelVolume {
        dims,
        labels,
        frame: FrameSource {
            format: "NIfTI-1",
            from,
            world: "RAS".into(),
            spacing_mm: to_body.spacing(),
            voxel_axes: to_body.voxel_axes().code(),
            axes_override: None,
        },
        to_body,
        names: Vec::new(),
        notes,
    })
}

/// The voxel → body transform a NIfTI-1 header states (sform, else qform, else — with `--axes` —
/// pixdim alone), and which fields gave it.
fn nifti_frame(
    header: &nifti::NiftiHeader,
    axes_given: bool,
    notes: &mut Vec<String>,
) -> Result<(VoxelToBody, String), String> {
    let unit = match header.xyzt_units & 0o7 {
        1 => 1000.0,
        2 => 1.0,
        3 => 0.001,
        _ => {
            notes.push(
                "the NIfTI header does not state its length unit (xyzt_units 0): read as mm".into(),
            );
            1.0
        }
    };
    let (ras, from) = if header.sform_code > 0 {
        let r = |row: [f32; 4]| row.map(|v| v as f64);
        let (x, y, z) = (r(header.srow_x), r(header.srow_y), r(header.srow_z));
        let linear = DMat3::from_cols(
            DVec3::new(x[0], y[0], z[0]),
            DVec3::new(x[1], y[1], z[1]),
            DVec3::new(x[2], y[2], z[2]),
        );
        (
            (linear, DVec3::new(x[3], y[3], z[3])),
            format!("sform (code {})", header.sform_code),
        )
    } else if header.qform_code > 0 {
        let (b, c, d) = (
            header.quatern_b as f64,
            header.quatern_c as f64,
            header.quatern_d as f64,
        );
        let a = (1.0 - (b * b + c * c + d * d)).max(0.0).sqrt();
        let rot = DMat3::from_quat(DQuat::from_xyzw(b, c, d, a).normalize());
        let qfac = if header.pixdim[0] < 0.0 { -1.0 } else { 1.0 };
        let p = header.pixdim.map(|v| (v as f64).abs());
        let linear = DMat3::from_cols(
            rot.x_axis * p[1],
            rot.y_axis * p[2],
            rot.z_axis * (p[3] * qfac),
        );
        (
            (
                linear,
                DVec3::new(
                    header.quatern_x as f64,
                    header.quatern_y as f64,
                    header.quatern_z as f64,
                ),
            ),
            format!("qform (code {}, qfac {qfac})", header.qform_code),
        )
    } else if axes_given {
        let p = header.pixdim.map(|v| (v as f64).abs());
        notes.push(
            "the NIfTI header sets neither sform nor qform: the voxel axes come from --axes and the \
             spacing from pixdim"
                .into(),
        );
        (
            (
                DMat3::from_diagonal(DVec3::new(p[1], p[2], p[3])),
                DVec3::ZERO,
            ),
            "pixdim only (no sform or qform)".into(),
        )
    } else {
        return Err(
            "its header sets neither an sform nor a qform (both codes 0): it does not say where the \
             patient's left, anterior and superior are, and lungdyn does not guess. Pass --axes \
             with the voxel axes' directions (e.g. --axes LPS) if you know them"
                .into(),
        );
    };
    let to_body = VoxelToBody {
        linear: Axes::RAS.to_body() * ras.0 * unit,
        origin: Axes::RAS.to_body() * ras.1 * unit,
    };
    Ok((to_body, from))
}

// ----------------------------------------------------------------------------------------------
// NRRD
// ----------------------------------------------------------------------------------------------

/// The header lines of an NRRD or MetaImage file up to where its data begins: `(fields, offset)`.
fn header_lines(bytes: &[u8], nrrd: bool) -> Result<(Vec<(String, String)>, usize), String> {
    let mut fields = Vec::new();
    let mut pos = 0usize;
    let limit = bytes.len().min(1 << 20);
    let mut first = true;
    while pos < limit {
        let end = bytes[pos..limit]
            .iter()
            .position(|&b| b == b'\n')
            .map(|e| pos + e)
            .ok_or("its header does not end (no blank line or ElementDataFile within 1 MiB)")?;
        let line = std::str::from_utf8(&bytes[pos..end])
            .map_err(|_| "its header is not text".to_string())?
            .trim_end_matches('\r');
        pos = end + 1;
        if first && nrrd {
            first = false;
            if !line.starts_with("NRRD000") {
                return Err(
                    "it does not begin with the NRRD magic line (NRRD0001…NRRD0005)".into(),
                );
            }
            continue;
        }
        first = false;
        if nrrd {
            if line.is_empty() {
                return Ok((fields, pos));
            }
            if line.starts_with('#') {
                continue;
            }
            // "key:=value" key/value pairs (segment metadata) and "field: description".
            if let Some((k, v)) = line.split_once(":=") {
                fields.push((format!("kv:{}", k.trim()), v.trim().to_string()));
            } else if let Some((k, v)) = line.split_once(": ") {
                fields.push((k.trim().to_ascii_lowercase(), v.trim().to_string()));
            } else {
                return Err(format!(
                    "header line {line:?} is neither 'field: value' nor 'key:=value'"
                ));
            }
        } else {
            let (k, v) = line
                .split_once('=')
                .ok_or_else(|| format!("header line {line:?} is not 'Key = Value'"))?;
            let (k, v) = (k.trim().to_string(), v.trim().to_string());
            let done = k == "ElementDataFile";
            fields.push((k, v));
            if done {
                return Ok((fields, pos));
            }
        }
    }
    Err("its header does not end within the file".into())
}

fn field<'a>(fields: &'a [(String, String)], key: &str) -> Option<&'a str> {
    fields
        .iter()
        .find(|(k, _)| k == key)
        .map(|(_, v)| v.as_str())
}

fn numbers(s: &str, what: &str) -> Result<Vec<f64>, String> {
    s.split(|c: char| c.is_whitespace() || c == ',' || c == '(' || c == ')')
        .filter(|t| !t.is_empty())
        .map(|t| {
            t.parse::<f64>()
                .ok()
                .filter(|v| v.is_finite())
                .ok_or_else(|| format!("{what} {s:?}: {t:?} is not a finite number"))
        })
        .collect()
}

fn sizes3(s: &str, what: &str) -> Result<[usize; 3], String> {
    let v = numbers(s, what)?;
    if v.len() != 3 || v.iter().any(|&x| x < 1.0 || x.fract() != 0.0 || x > 1e6) {
        return Err(format!(
            "{what} {s:?}: a label image has three whole sizes ≥ 1"
        ));
    }
    Ok([v[0] as usize, v[1] as usize, v[2] as usize])
}

/// The world axes an NRRD `space` names.
fn nrrd_space(space: &str) -> Option<Axes> {
    let s = space.to_ascii_lowercase();
    let parts: Vec<&str> = s.split('-').collect();
    if parts.len() == 3 {
        let letters: String = parts
            .iter()
            .map(|p| match *p {
                "left" => 'L',
                "right" => 'R',
                "anterior" => 'A',
                "posterior" => 'P',
                "superior" => 'S',
                "inferior" => 'I',
                _ => '?',
            })
            .collect();
        return letters.parse().ok();
    }
    s.to_ascii_uppercase().parse().ok()
}

fn read_nrrd(bytes: &[u8], axes_given: bool) -> Result<LabelVolume, String> {
    let (fields, offset) = header_lines(bytes, true)?;
    let get = |k: &str| field(&fields, k);
    if get("data file").or(get("datafile")).is_some() {
        return Err(
            "its voxel data is in a separate file ('data file'): save it as one .nrrd \
                    (3D Slicer: Save, with the data attached)"
                .into(),
        );
    }
    let dimension = get("dimension").ok_or("its header has no 'dimension'")?;
    let sizes_field = get("sizes").ok_or("its header has no 'sizes'")?;
    let mut dir_field = get("space directions").map(str::to_string);
    let mut sizes_text = sizes_field.to_string();
    if dimension.trim() == "4" {
        // A 3D Slicer segmentation with layers: a 'list' axis first, its direction 'none'.
        let s = numbers(sizes_field, "sizes")?;
        if s.len() == 4 && s[0] == 1.0 {
            sizes_text = format!("{} {} {}", s[1], s[2], s[3]);
            dir_field = dir_field.map(|d| d.trim_start().trim_start_matches("none").to_string());
        } else {
            return Err(format!(
                "a 4D NRRD of sizes {sizes_field}: a segmentation with several layers (overlapping \
                 segments); export it as one labelmap (3D Slicer: Segmentations → Export to files, \
                 or merge the layers)"
            ));
        }
    } else if dimension.trim() != "3" {
        return Err(format!("dimension {dimension}: a label image is 3D"));
    }
    let dims = sizes3(&sizes_text, "sizes")?;
    let scalar = match get("type")
        .ok_or("its header has no 'type'")?
        .to_ascii_lowercase()
        .as_str()
    {
        "uchar" | "unsigned char" | "uint8" | "uint8_t" => Scalar::U8,
        "signed char" | "int8" | "int8_t" | "char" => Scalar::I8,
        "ushort" | "unsigned short" | "unsigned short int" | "uint16" | "uint16_t" => Scalar::U16,
        "short" | "short int" | "signed short" | "signed short int" | "int16" | "int16_t" => {
            Scalar::I16
        }
        "uint" | "unsigned int" | "uint32" | "uint32_t" => Scalar::U32,
        "int" | "signed int" | "int32" | "int32_t" => Scalar::I32,
        "float" => Scalar::F32,
        "double" => Scalar::F64,
        other => {
            return Err(format!(
                "type {other:?}: a label image is stored as integers"
            ))
        }
    };
    let big = match get("endian").map(str::to_ascii_lowercase).as_deref() {
        Some("big") => true,
        Some("little") | None => false,
        Some(other) => return Err(format!("endian {other:?}: use little or big")),
    };
    let body = &bytes[offset..];
    let count = dims.iter().product::<usize>();
    let raw = match get("encoding")
        .ok_or("its header has no 'encoding'")?
        .to_ascii_lowercase()
        .as_str()
    {
        "raw" => body.to_vec(),
        "gzip" | "gz" => inflate(
            body,
            true,
            MAX_VOXEL_BYTES.min((count * scalar.bytes()) as u64),
        )?,
        other => {
            return Err(format!(
                "encoding {other:?}: lungdyn reads raw and gzip NRRD (re-save with compression \
                 gzip or none)"
            ))
        }
    };
    let labels = to_labels(&raw, scalar, big, count, 1.0, 0.0)?;
    let mut notes = Vec::new();
    let (to_body, from, world_name) =
        nrrd_frame(&fields, dir_field.as_deref(), axes_given, &mut notes)?;
    // 3D Slicer segment names: SegmentN_Name and SegmentN_LabelValue.
    let mut names = Vec::new();
    for (k, v) in &fields {
        if let Some(n) = k
            .strip_prefix("kv:Segment")
            .and_then(|r| r.strip_suffix("_Name"))
        {
            let value = field(&fields, &format!("kv:Segment{n}_LabelValue"))
                .and_then(|s| s.parse::<u16>().ok());
            if let Some(value) = value {
                names.push((value, v.clone()));
            }
        }
    }
    Ok(LabelVolume {
        dims,
        labels,
        frame: FrameSource {
            format: "NRRD",
            from,
            world: world_name,
            spacing_mm: to_body.spacing(),
            voxel_axes: to_body.voxel_axes().code(),
            axes_override: None,
        },
        to_body,
        names,
        notes,
    })
}

/// The voxel → body transform an NRRD header states (`space directions` and `space origin` in
/// its `space`; with `--axes`, the spacing alone), which fields gave it, and its world's name.
fn nrrd_frame(
    fields: &[(String, String)],
    dir_field: Option<&str>,
    axes_given: bool,
    notes: &mut Vec<String>,
) -> Result<(VoxelToBody, String, String), String> {
    let get = |k: &str| field(fields, k);
    let space = get("space");
    let world = space.and_then(nrrd_space);
    let directions = match dir_field {
        Some(d) => {
            let v = numbers(d, "space directions")?;
            if v.len() != 9 {
                return Err(format!(
                    "space directions {d:?}: three vectors of three numbers expected"
                ));
            }
            Some(DMat3::from_cols(
                DVec3::new(v[0], v[1], v[2]),
                DVec3::new(v[3], v[4], v[5]),
                DVec3::new(v[6], v[7], v[8]),
            ))
        }
        None => None,
    };
    let origin = match get("space origin") {
        Some(o) => {
            let v = numbers(o, "space origin")?;
            if v.len() != 3 {
                return Err(format!("space origin {o:?}: three numbers expected"));
            }
            DVec3::new(v[0], v[1], v[2])
        }
        None => DVec3::ZERO,
    };
    if get("space units").is_some_and(|u| !u.contains("mm")) {
        return Err(format!(
            "space units {}: lungdyn reads NRRD in mm",
            get("space units").unwrap_or_default()
        ));
    }
    let (to_body, from, world_name) = match (world, directions) {
        (Some(w), Some(d)) => (
            VoxelToBody {
                linear: w.to_body() * d,
                origin: w.to_body() * origin,
            },
            format!(
                "space directions and space origin in {}",
                space.unwrap_or_default()
            ),
            w.code(),
        ),
        _ if axes_given => {
            let spacing = match (directions, get("spacings")) {
                (Some(d), _) => [d.x_axis.length(), d.y_axis.length(), d.z_axis.length()],
                (None, Some(s)) => {
                    let v = numbers(s, "spacings")?;
                    if v.len() != 3 {
                        return Err(format!("spacings {s:?}: three numbers expected"));
                    }
                    [v[0], v[1], v[2]]
                }
                (None, None) => return Err("its header gives no spacing".into()),
            };
            notes.push(
                "the NRRD header names no anatomical space: the voxel axes come from --axes".into(),
            );
            (
                VoxelToBody {
                    linear: DMat3::from_diagonal(DVec3::from(spacing)),
                    origin: DVec3::ZERO,
                },
                "spacing only (no anatomical space)".into(),
                "none".into(),
            )
        }
        _ => {
            return Err(format!(
            "its header names {} and {}: it does not say where the patient's left, anterior and \
                 superior are, and lungdyn does not guess. Pass --axes with the voxel axes' \
                 directions (e.g. --axes LPS) if you know them",
            space.map_or("no 'space'".to_string(), |s| format!("space {s:?}")),
            if directions.is_some() {
                "space directions"
            } else {
                "no space directions"
            }
        ))
        }
    };
    Ok((to_body, from, world_name))
}

// ----------------------------------------------------------------------------------------------
// MetaImage
// ----------------------------------------------------------------------------------------------

fn read_mha(bytes: &[u8]) -> Result<LabelVolume, String> {
    let (fields, offset) = header_lines(bytes, false)?;
    let get = |k: &str| field(&fields, k);
    if get("ObjectType").is_some_and(|t| t != "Image") {
        return Err(format!(
            "ObjectType {}: not an image",
            get("ObjectType").unwrap_or_default()
        ));
    }
    if get("NDims").map(str::trim) != Some("3") {
        return Err(format!("NDims {:?}: a label image is 3D", get("NDims")));
    }
    if get("ElementDataFile").map(str::trim) != Some("LOCAL") {
        return Err(
            "its data is in a separate file (ElementDataFile): give a .mha with LOCAL data".into(),
        );
    }
    if get("ElementNumberOfChannels").is_some_and(|c| c.trim() != "1") {
        return Err("it has several channels per voxel: a label image has one".into());
    }
    let dims = sizes3(
        get("DimSize").ok_or("its header has no DimSize")?,
        "DimSize",
    )?;
    let scalar = match get("ElementType").ok_or("its header has no ElementType")? {
        "MET_UCHAR" => Scalar::U8,
        "MET_CHAR" => Scalar::I8,
        "MET_USHORT" => Scalar::U16,
        "MET_SHORT" => Scalar::I16,
        "MET_UINT" => Scalar::U32,
        "MET_INT" => Scalar::I32,
        "MET_FLOAT" => Scalar::F32,
        "MET_DOUBLE" => Scalar::F64,
        other => {
            return Err(format!(
                "ElementType {other}: a label image is stored as integers"
            ))
        }
    };
    let truthy = |k: &str| get(k).is_some_and(|v| v.eq_ignore_ascii_case("true"));
    let big = truthy("BinaryDataByteOrderMSB") || truthy("ElementByteOrderMSB");
    let count = dims.iter().product::<usize>();
    let body = &bytes[offset..];
    let raw = if truthy("CompressedData") {
        inflate(body, false, (count * scalar.bytes()) as u64)?
    } else {
        body.to_vec()
    };
    let labels = to_labels(&raw, scalar, big, count, 1.0, 0.0)?;
    let spacing = numbers(
        get("ElementSpacing")
            .or(get("ElementSize"))
            .ok_or("its header has no ElementSpacing")?,
        "ElementSpacing",
    )?;
    let offset_v = numbers(
        get("Offset")
            .or(get("Position"))
            .or(get("Origin"))
            .unwrap_or("0 0 0"),
        "Offset",
    )?;
    let m = numbers(
        get("TransformMatrix")
            .or(get("Rotation"))
            .or(get("Orientation"))
            .unwrap_or("1 0 0 0 1 0 0 0 1"),
        "TransformMatrix",
    )?;
    if spacing.len() != 3 || offset_v.len() != 3 || m.len() != 9 {
        return Err("ElementSpacing, Offset and TransformMatrix need 3, 3 and 9 numbers".into());
    }
    // ITK writes the direction matrix column by column: the first three numbers are axis 0's
    // direction.
    let dirs = DMat3::from_cols(
        DVec3::new(m[0], m[1], m[2]) * spacing[0],
        DVec3::new(m[3], m[4], m[5]) * spacing[1],
        DVec3::new(m[6], m[7], m[8]) * spacing[2],
    );
    let to_body = VoxelToBody {
        linear: Axes::LPS.to_body() * dirs,
        origin: Axes::LPS.to_body() * DVec3::new(offset_v[0], offset_v[1], offset_v[2]),
    };
    let mut notes = Vec::new();
    if let Some(o) = get("AnatomicalOrientation") {
        notes.push(format!(
            "MetaImage AnatomicalOrientation {o} is informative only (ITK does not apply it); the \
             frame is TransformMatrix in LPS"
        ));
    }
    Ok(LabelVolume {
        dims,
        labels,
        frame: FrameSource {
            format: "MetaImage",
            from: "TransformMatrix, Offset and ElementSpacing (ITK's LPS world)".into(),
            world: "LPS".into(),
            spacing_mm: to_body.spacing(),
            voxel_axes: to_body.voxel_axes().code(),
            axes_override: None,
        },
        to_body,
        names: Vec::new(),
        notes,
    })
}
