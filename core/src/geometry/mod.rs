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
