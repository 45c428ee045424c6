//! Geometry: Blender-compatible cameras, scene meshes in world space, and the
//! triangle BVH that finds the first surface along each view ray.

pub mod bvh;
pub mod camera;

use crate::scene::Mesh;
use bvh::Triangle;
use glam::DVec3;

/// World-space triangles of all meshes, in order, with the mesh index of each.
pub fn world_triangles(meshes: &[Mesh]) -> (Vec<Triangle>, Vec<u32>) {
    let mut tris = Vec::new();
    let mut owner = Vec::new();
    for (mi, m) in meshes.iter().enumerate() {
        let mat = m.transform.to_matrix();
        let world: Vec<DVec3> = m.positions.iter().map(|p| mat.transform_point3(DVec3::from(*p))).collect();
        for t in &m.triangles {
            tris.push(Triangle {
                v: [world[t[0] as usize], world[t[1] as usize], world[t[2] as usize]],
            });
            owner.push(mi as u32);
        }
    }
    (tris, owner)
}

/// The 12 outward-facing triangles of a box whose 8 corners are numbered by
/// bits (bit 0: +x, bit 1: +y, bit 2: +z), as vertex indices.
pub const CUBE_TRIANGLES: [[u32; 3]; 12] = [
    [0, 2, 1],
    [1, 2, 3],
    [4, 5, 6],
    [5, 7, 6],
    [0, 1, 4],
    [1, 5, 4],
    [2, 6, 3],
    [3, 6, 7],
    [0, 4, 2],
    [2, 4, 6],
    [1, 3, 5],
    [3, 7, 5],
];

/// Tests: the 8 corners (numbered as for [`CUBE_TRIANGLES`]) and the 12
/// triangles of the axis-aligned cube of centre `c` and half-side `h`.
#[cfg(test)]
pub(crate) fn cube(c: DVec3, h: f64) -> (Vec<DVec3>, Vec<[u32; 3]>) {
    let p = (0..8)
        .map(|i| {
            c + DVec3::new(
                if i & 1 == 0 { -h } else { h },
                if i & 2 == 0 { -h } else { h },
                if i & 4 == 0 { -h } else { h },
            )
        })
        .collect();
    (p, CUBE_TRIANGLES.to_vec())
}
