//! Writing meshes: Wavefront OBJ (text) and PLY (binary little-endian), chosen by file extension.
//!
//! Files are written through [`outfile::write_atomically`]: a target that is not a regular file is
//! refused, and a temporary sibling is flushed, synced and renamed over the target, so an interrupted
//! run never leaves a half-written mesh where a good one was.
//! (Import, with tobj/ply-rs/stl_io, belongs to issue #4.)

use std::io::Write;
use std::path::{Path, PathBuf};

use super::TriMesh;

/// Mesh file formats lungdyn writes.
#[derive(Debug, Clone, Copy, PartialEq, Eq)]
pub enum MeshFormat {
    /// Wavefront OBJ.
    Obj,
    /// Binary little-endian PLY.
    Ply,
}

impl MeshFormat {
    /// Format from the path's extension (`.obj` or `.ply`, any case).
    pub fn from_path(path: &Path) -> Result<Self, WriteError> {
        match path
            .extension()
            .and_then(|e| e.to_str())
            .map(|e| e.to_ascii_lowercase())
            .as_deref()
        {
            Some("obj") => Ok(MeshFormat::Obj),
            Some("ply") => Ok(MeshFormat::Ply),
            _ => Err(WriteError::UnknownFormat {
                path: path.to_path_buf(),
            }),
        }
    }
}

/// Errors writing a mesh.
#[derive(Debug, thiserror::Error)]
pub enum WriteError {
    /// The extension names no supported format.
    #[error("{}: unknown mesh format: the file name must end in .obj or .ply", path.display())]
    UnknownFormat {
        /// The path given.
        path: PathBuf,
    },
    /// The target is not a regular file, or the OS refused (see [`outfile`]).
    #[error(transparent)]
    File(#[from] outfile::WriteError),
}

/// Check an output path before any work: its extension names a mesh format and it is not an
/// existing device, FIFO, socket or folder ([`outfile::check`]). Returns the format.
pub fn check_out(path: &Path) -> Result<MeshFormat, WriteError> {
    let format = MeshFormat::from_path(path)?;
    outfile::check(path)?;
    Ok(format)
}

/// Write `mesh` to `path` in the format its extension names, atomically.
pub fn write_mesh(mesh: &TriMesh, path: &Path) -> Result<MeshFormat, WriteError> {
    write(mesh, None, path)
}

/// Write `mesh` with its per-vertex lobe codes ([`super::lobes`]), atomically: an OBJ gets each
/// lobe's colour after the vertex (`v x y z r g b`, 0..1, as MeshLab and Blender read it), a PLY
/// `red green blue` and a `lobe` (uchar code) vertex property.
///
/// # Panics
/// If `lobes` does not hold one code per vertex (a caller's bug).
pub fn write_mesh_with_lobes(
    mesh: &TriMesh,
    lobes: &[u8],
    path: &Path,
) -> Result<MeshFormat, WriteError> {
    assert_eq!(
        lobes.len(),
        mesh.positions.len(),
        "one lobe code per vertex"
    );
    write(mesh, Some(lobes), path)
}

fn write(mesh: &TriMesh, lobes: Option<&[u8]>, path: &Path) -> Result<MeshFormat, WriteError> {
    let format = MeshFormat::from_path(path)?;
    outfile::write_atomically(path, |w| match format {
        MeshFormat::Obj => write_obj(mesh, lobes, w),
        MeshFormat::Ply => write_ply(mesh, lobes, w),
    })?;
    Ok(format)
}

fn lobe_colour(code: u8) -> [u8; 3] {
    super::lobes::Lobe::from_code(code)
        .unwrap_or(super::lobes::Lobe::Unknown)
        .colour()
}

fn write_obj(mesh: &TriMesh, lobes: Option<&[u8]>, w: &mut impl Write) -> std::io::Result<()> {
    writeln!(
        w,
        "# lungdyn mesh, millimetres, body frame (+X left, +Y anterior, +Z superior)"
    )?;
    for (i, p) in mesh.positions.iter().enumerate() {
        match lobes {
            None => writeln!(w, "v {} {} {}", p[0], p[1], p[2])?,
            Some(l) => {
                let [r, g, b] = lobe_colour(l[i]).map(|c| c as f32 / 255.0);
                writeln!(w, "v {} {} {} {r:.4} {g:.4} {b:.4}", p[0], p[1], p[2])?
            }
        }
    }
    for t in &mesh.triangles {
        writeln!(w, "f {} {} {}", t[0] + 1, t[1] + 1, t[2] + 1)?;
    }
    Ok(())
}

fn write_ply(mesh: &TriMesh, lobes: Option<&[u8]>, w: &mut impl Write) -> std::io::Result<()> {
    let extra = if lobes.is_some() {
        "property uchar red\nproperty uchar green\nproperty uchar blue\nproperty uchar lobe\n"
    } else {
        ""
    };
    write!(
        w,
        "ply\nformat binary_little_endian 1.0\ncomment lungdyn mesh, millimetres, body frame\n\
         element vertex {}\nproperty float x\nproperty float y\nproperty float z\n{extra}\
         element face {}\nproperty list uchar uint vertex_indices\nend_header\n",
        mesh.positions.len(),
        mesh.triangles.len()
    )?;
    for (i, p) in mesh.positions.iter().enumerate() {
        for v in p {
            w.write_all(&v.to_le_bytes())?;
        }
        if let Some(l) = lobes {
            w.write_all(&lobe_colour(l[i]))?;
            w.write_all(&[l[i]])?;
        }
    }
    for t in &mesh.triangles {
        w.write_all(&[3u8])?;
        for i in t {
            w.write_all(&i.to_le_bytes())?;
        }
    }
    Ok(())
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::mesh::{generate, Side};

    #[test]
    fn obj_and_ply_files_have_the_right_counts() {
        let dir = std::env::temp_dir().join(format!("lungdyn-io-{}", std::process::id()));
        std::fs::create_dir_all(&dir).unwrap();
        let mesh = generate::lung(Side::Left, 1000).unwrap();
        let obj = dir.join("l.obj");
        write_mesh(&mesh, &obj).unwrap();
        let text = std::fs::read_to_string(&obj).unwrap();
        assert_eq!(
            text.lines().filter(|l| l.starts_with("v ")).count(),
            mesh.positions.len()
        );
        assert_eq!(
            text.lines().filter(|l| l.starts_with("f ")).count(),
            mesh.triangles.len()
        );
        let ply = dir.join("l.PLY");
        write_mesh(&mesh, &ply).unwrap();
        let bytes = std::fs::read(&ply).unwrap();
        let header_end = bytes
            .windows(11)
            .position(|w| w == b"end_header\n")
            .unwrap()
            + 11;
        assert_eq!(
            bytes.len() - header_end,
            mesh.positions.len() * 12 + mesh.triangles.len() * 13
        );
        assert!(matches!(
            write_mesh(&mesh, &dir.join("l.stl")),
            Err(WriteError::UnknownFormat { .. })
        ));
        // With lobes: colours on every OBJ vertex, four more bytes per PLY vertex.
        let lobes = crate::mesh::lobes::classify(Side::Left, &mesh);
        write_mesh_with_lobes(&mesh, &lobes, &obj).unwrap();
        let text = std::fs::read_to_string(&obj).unwrap();
        assert!(text
            .lines()
            .filter(|l| l.starts_with("v "))
            .all(|l| l.split(' ').count() == 7));
        write_mesh_with_lobes(&mesh, &lobes, &ply).unwrap();
        let bytes = std::fs::read(&ply).unwrap();
        let header_end = bytes
            .windows(11)
            .position(|w| w == b"end_header\n")
            .unwrap()
            + 11;
        assert!(std::str::from_utf8(&bytes[..header_end])
            .unwrap()
            .contains("property uchar lobe"));
        assert_eq!(
            bytes.len() - header_end,
            mesh.positions.len() * 16 + mesh.triangles.len() * 13
        );
        // An unwritable target fails cleanly and leaves no temporary behind.
        let err = write_mesh(&mesh, &dir.join("missing-dir").join("x.obj")).unwrap_err();
        assert!(err.to_string().contains("missing-dir"));
        std::fs::remove_dir_all(&dir).unwrap();
    }
}
