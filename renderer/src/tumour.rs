//! The tumour drawn where the radiotherapy planner needs to see it: an ellipsoid of the tumour's
//! radii at its centre's position this frame, in a colour that contrasts with the lungs, drawn
//! through the opaque lung surface (the overlay phase: the tumour lies inside the lung), or as a
//! solid body inside the translucent and see-through looks' lungs.
//!
//! The centre moves as the kernel's [`TumourMeta`] says for the lung's mode and the frame's
//! coefficients (the mean-value interpolation of the surface's displacement, seed §8.2 and
//! `lung_model::disease::tumour`), with the lung's collapse and rigid offset (EQUATIONS.md §4.1).
//! Per frame: one small vertex write from a stack array (no allocation).

use lung_model::deform::modes::DeformMode;
use lung_model::kernel::TumourMeta;
use wgpu::util::DeviceExt;

/// Rings between the poles of the ellipsoid mesh.
const RINGS: usize = 12;
/// Segments around.
const SEGMENTS: usize = 24;
/// Vertices of the ellipsoid mesh.
pub const VERTICES: usize = (RINGS - 1) * SEGMENTS + 2;

/// A unit sphere as (positions, triangles), outward wound (counter-clockwise seen from outside):
/// the tumour's ellipsoid here and in `lungdyn export gltf`.
pub fn unit_sphere() -> (Vec<[f32; 3]>, Vec<[u32; 3]>) {
    let mut p = Vec::with_capacity(VERTICES);
    p.push([0.0, 0.0, 1.0]);
    for r in 1..RINGS {
        let theta = std::f32::consts::PI * r as f32 / RINGS as f32;
        for s in 0..SEGMENTS {
            let phi = std::f32::consts::TAU * s as f32 / SEGMENTS as f32;
            p.push([
                theta.sin() * phi.cos(),
                theta.sin() * phi.sin(),
                theta.cos(),
            ]);
        }
    }
    p.push([0.0, 0.0, -1.0]);
    let ring = |r: usize, s: usize| (1 + (r - 1) * SEGMENTS + s % SEGMENTS) as u32;
    let south = (VERTICES - 1) as u32;
    let mut t = Vec::new();
    for s in 0..SEGMENTS {
        t.push([0, ring(1, s), ring(1, s + 1)]);
        for r in 1..RINGS - 1 {
            let (a, b, c, d) = (
                ring(r, s),
                ring(r + 1, s),
                ring(r + 1, s + 1),
                ring(r, s + 1),
            );
            t.push([a, b, c]);
            t.push([a, c, d]);
        }
        t.push([ring(RINGS - 1, s), south, ring(RINGS - 1, s + 1)]);
    }
    (p, t)
}

/// One lung's tumour on the GPU.
pub struct TumourDraw {
    /// Lung slot (0 right, 1 left).
    pub slot: usize,
    meta: TumourMeta,
    mode: DeformMode,
    /// Ellipsoid vertices relative to the centre, mm.
    local: Vec<[f32; 3]>,
    /// Deformed positions (xyz mm, w 1).
    pub positions: wgpu::Buffer,
    /// Normals (w 0: no colour field).
    pub normals: wgpu::Buffer,
    /// Surface attributes: every vertex [`crate::draw::Material::Tumour`].
    pub surface: wgpu::Buffer,
    /// Triangles.
    pub index: wgpu::Buffer,
    /// Index count.
    pub index_count: u32,
}

impl TumourDraw {
    /// The tumour of lung `slot` in `mode`.
    pub fn new(device: &wgpu::Device, slot: usize, meta: &TumourMeta, mode: DeformMode) -> Self {
        let (unit, triangles) = unit_sphere();
        let r = meta.tumour.radii_mm;
        let local: Vec<[f32; 3]> = unit
            .iter()
            .map(|u| [u[0] * r[0] as f32, u[1] * r[1] as f32, u[2] * r[2] as f32])
            .collect();
        // Ellipsoid normals: the gradient of Σ (x_a / r_a)², per vertex.
        let normals: Vec<[f32; 4]> = unit
            .iter()
            .map(|u| {
                let g = glam::Vec3::new(u[0] / r[0] as f32, u[1] / r[1] as f32, u[2] / r[2] as f32)
                    .normalize_or_zero();
                [g.x, g.y, g.z, 0.0]
            })
            .collect();
        let rest = Self::place(&local, meta.centre_mm);
        let usage = wgpu::BufferUsages::VERTEX | wgpu::BufferUsages::COPY_DST;
        let positions = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lungdyn tumour positions"),
            contents: bytemuck::cast_slice(&rest),
            usage,
        });
        let normals = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lungdyn tumour normals"),
            contents: bytemuck::cast_slice(&normals),
            usage: wgpu::BufferUsages::VERTEX,
        });
        let surface = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lungdyn tumour surface"),
            contents: bytemuck::cast_slice(
                &[crate::draw::surface(crate::draw::Material::Tumour, 0, false); VERTICES],
            ),
            usage: wgpu::BufferUsages::VERTEX,
        });
        let index = device.create_buffer_init(&wgpu::util::BufferInitDescriptor {
            label: Some("lungdyn tumour indices"),
            contents: bytemuck::cast_slice(&triangles),
            usage: wgpu::BufferUsages::INDEX,
        });
        Self {
            slot,
            meta: meta.clone(),
            mode,
            local,
            positions,
            normals,
            surface,
            index,
            index_count: triangles.len() as u32 * 3,
        }
    }

    fn place(local: &[[f32; 3]], centre: [f64; 3]) -> [[f32; 4]; VERTICES] {
        let mut out = [[0.0f32; 4]; VERTICES];
        for (o, l) in out.iter_mut().zip(local) {
            *o = [
                (centre[0] + l[0] as f64) as f32,
                (centre[1] + l[1] as f64) as f32,
                (centre[2] + l[2] as f64) as f32,
                1.0,
            ];
        }
        out
    }

    /// The centre's position this frame, mm (body frame), from the lung slot's scale,
    /// coefficients, collapse, hilum and offset; the rest position when the coefficients do not
    /// fit the mode or the result is not finite (never a NaN on screen).
    pub fn centre_mm(
        &self,
        scale: f32,
        coeffs: &[f32],
        collapse: f32,
        hilum: [f32; 3],
        offset: [f32; 3],
    ) -> [f64; 3] {
        let n = match self.mode {
            DeformMode::Precomputed => 0,
            DeformMode::Basis | DeformMode::Direct => 4,
            DeformMode::Sh => self.meta.sh_mm.len(),
        };
        let Some(d) = coeffs
            .get(..n)
            .and_then(|c| self.meta.displacement_mm(self.mode, c))
        else {
            return self.meta.centre_mm;
        };
        let p = self.meta.position_mm(
            d,
            scale as f64,
            collapse as f64,
            hilum.map(|v| v as f64),
            offset.map(|v| v as f64),
        );
        if p.iter().all(|v| v.is_finite()) {
            p
        } else {
            self.meta.centre_mm
        }
    }

    /// Write this frame's ellipsoid (no allocation: a stack array through `write_buffer`).
    pub fn update(&self, queue: &wgpu::Queue, centre_mm: [f64; 3]) {
        let v = Self::place(&self.local, centre_mm);
        queue.write_buffer(&self.positions, 0, bytemuck::cast_slice(&v));
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn the_sphere_is_closed_and_outward() {
        let (p, t) = unit_sphere();
        assert_eq!(p.len(), VERTICES);
        let mesh = lung_model::mesh::TriMesh {
            positions: p.iter().map(|v| v.map(|c| c * 10.0)).collect(),
            triangles: t,
        };
        // Outward winding gives a positive enclosed volume close to 4/3·π·10³ mm³ (a polyhedron
        // inscribed in the sphere: a little less).
        let v = mesh.enclosed_volume_ml() * 1000.0;
        let sphere = 4.0 / 3.0 * std::f64::consts::PI * 1000.0;
        assert!(v > 0.9 * sphere && v < sphere, "{v} vs {sphere}");
        lung_model::mesh::check(&mesh).unwrap();
    }
}
