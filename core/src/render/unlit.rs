//! Tiles of the image whose view rays provably miss every light's
//! illumination volume. Their in-scatter is exactly 0; when no requested layer
//! needs the ray itself (transmittance, depth, …) they are not traced at all.
//!
//! **The test.** A point or spot light's illumination volume is the cone
//! `K = {P + s·v : s ≥ 0, ∠(v, a) ≤ β}` (its bounding cone,
//! [`crate::light::PointSource::cos_reach`]; convex for β < 90°). The rays of
//! a tile leave the eye `E` inside the pyramid spanned by the directions
//! `c₁…c₄` through the corners of the tile's (padded) rectangle. A pyramid
//! with apex `E` and a convex set are disjoint iff a plane through `E`
//! separates them: any separating plane can be moved parallel to itself
//! onto `E` and the pyramid, a cone from `E`, stays on its side. With the
//! plane's normal `n` towards `K` the conditions are
//!
//! - `n·cᵢ ≤ 0` for the four corners (the tile's rays on the far side),
//! - `n·(P − E) ≥ 0` (the apex on the near side),
//! - `n·v ≥ 0` for every `v` within β of `a`, i.e. `∠(n, a) ≤ 90° − β`,
//!   i.e. `n·a ≥ sin β` for a unit `n`.
//!
//! The first five make a polyhedral cone 𝒫 of normals, so the question is
//! whether `max n·a` over the unit vectors of 𝒫 reaches `sin β`. A linear
//! function on the spherical polygon 𝒫 ∩ S² is largest at `a` itself (if
//! inside), at the normalised projection of `a` onto a facet's plane (if
//! inside), or at a vertex, the cross product of two facets' normals (if
//! inside): all of these are tried, so the test finds a separating plane
//! whenever one exists (up to the margins below) and is otherwise
//! conservative — a tile it cannot prove unlit is traced as before.
//!
//! **Margins.** The cone is widened by [`ANGLE_MARGIN`] and its apex moved
//! back along the axis by [`APEX_MARGIN`] (relative), so a plane found for the
//! widened cone separates the real one strictly; the tile's rectangle is
//! padded by the pixels any of its pixels' results read (the classification's
//! stencils, the filter's window) plus one, so every ray that matters lies
//! strictly inside the pyramid.
//!
//! Lights whose volume is not a cone narrower than a hemisphere (wide spots,
//! point lights, windows), suns and ambient light reach every ray: with any of
//! them in the scene no tile is unlit.

use crate::geometry::camera::CameraRays;
use glam::DVec3;

/// Added to every cone's half-angle, rad.
pub const ANGLE_MARGIN: f64 = 1e-6;
/// The cone's apex is moved back along its axis by this fraction of its
/// distance from the eye (plus this many metres).
pub const APEX_MARGIN: f64 = 1e-6;
/// Tiles are this many pixels a side.
pub const TILE: usize = 8;

/// A light's illumination cone as the test sees it.
#[derive(Debug, Clone, Copy)]
pub struct Cone {
    /// Apex, m.
    pub apex: DVec3,
    /// Unit axis (the direction the light shines).
    pub axis: DVec3,
    /// Half-angle, rad, 0 < β < π/2.
    pub half_angle: f64,
}

/// Whether a plane through `eye` separates the pyramid spanned by the unit
/// directions `corners` (in order around the rectangle) from the cone
/// (widened by the margins). `false` when it cannot be shown.
pub fn pyramid_misses_cone(eye: DVec3, corners: &[DVec3; 4], cone: &Cone) -> bool {
    let beta = cone.half_angle + ANGLE_MARGIN;
    if !(beta > 0.0 && beta < std::f64::consts::FRAC_PI_2) {
        return false;
    }
    let to_apex = cone.apex - eye;
    let back = APEX_MARGIN * (to_apex.length() + 1.0);
    let q = to_apex - cone.axis * back;
    let Some(q) = q.try_normalize() else { return false };
    // Facet normals g: n ∈ 𝒫 iff g·n ≥ 0 for all of them.
    let g = [-corners[0], -corners[1], -corners[2], -corners[3], q];
    let a = cone.axis;
    let inside = |n: DVec3| g.iter().all(|gj| gj.dot(n) >= -1e-12);
    let mut best = f64::NEG_INFINITY;
    let mut consider = |n: DVec3| {
        if let Some(n) = n.try_normalize()
            && inside(n)
        {
            best = best.max(n.dot(a));
        }
    };
    consider(a);
    for gj in &g {
        consider(a - *gj * (a.dot(*gj) / gj.length_squared()));
    }
    for j in 0..g.len() {
        for k in j + 1..g.len() {
            let r = g[j].cross(g[k]);
            consider(r);
            consider(-r);
        }
    }
    best >= beta.sin()
}

/// Per tile of the padded image (pixels `-pad ..< width + pad` by
/// `-pad ..< height + pad`, in tiles of [`TILE`] from the top-left), whether
/// its rays, with every pixel's `reach` (px) around it, miss every cone.
/// Returns the tile grid's columns and the flags, row by row.
pub fn unlit_tiles(cam: &CameraRays, cones: &[Cone], pad: usize, reach: f64) -> (usize, Vec<bool>) {
    let (pw, ph) = (cam.width + 2 * pad, cam.height + 2 * pad);
    let (cols, rows) = (pw.div_ceil(TILE), ph.div_ceil(TILE));
    let margin = reach + 1.0;
    let flags = (0..rows * cols)
        .map(|t| {
            let (tx, ty) = (t % cols, t / cols);
            // The tile's pixels span [x0, x1) × [y0, y1) in image coordinates.
            let x0 = (tx * TILE) as f64 - pad as f64;
            let y0 = (ty * TILE) as f64 - pad as f64;
            let (x1, y1) = (x0 + TILE as f64, y0 + TILE as f64);
            let (xa, xb, ya, yb) = (x0 - margin, x1 + margin, y0 - margin, y1 + margin);
            let corners = [
                cam.direction(xa, ya),
                cam.direction(xb, ya),
                cam.direction(xb, yb),
                cam.direction(xa, yb),
            ];
            cones.iter().all(|c| pyramid_misses_cone(cam.position, &corners, c))
        })
        .collect();
    (cols, flags)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// Brute force: does any ray through the rectangle's interior (a dense
    /// grid of directions) come within the cone?
    fn any_ray_hits(eye: DVec3, corners: &[DVec3; 4], cone: &Cone) -> bool {
        let n = 30;
        for i in 0..=n {
            for j in 0..=n {
                let (u, v) = (i as f64 / n as f64, j as f64 / n as f64);
                let top = corners[0] * (1.0 - u) + corners[1] * u;
                let bottom = corners[3] * (1.0 - u) + corners[2] * u;
                let d = (top * (1.0 - v) + bottom * v).normalize();
                // Closest approach in angle: march along the ray.
                for k in 0..300 {
                    let t = 0.05 * 1.03f64.powi(k) - 0.05;
                    let x = eye + d * t;
                    let w = x - cone.apex;
                    let len = w.length();
                    if len == 0.0 || w.dot(cone.axis) >= len * cone.half_angle.cos() {
                        return true;
                    }
                }
            }
        }
        false
    }

    #[test]
    fn a_proven_miss_is_a_miss_and_far_tiles_are_proven() {
        // Random cones and pyramids: whenever the test says "misses", no ray
        // of a dense fan hits; and a pyramid pointing away from a narrow cone
        // whose apex is behind it is proven.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut rnd = || {
            state ^= state << 13;
            state ^= state >> 7;
            state ^= state << 17;
            (state >> 11) as f64 / (1u64 << 53) as f64
        };
        let mut proven = 0;
        for _ in 0..400 {
            let eye = DVec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5);
            let centre = DVec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5).normalize();
            let side = centre.any_orthonormal_vector();
            let up = centre.cross(side);
            let size = 0.02 + 0.2 * rnd();
            let corners =
                [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)].map(|(a, b)| (centre + (side * a + up * b) * size).normalize());
            let cone = Cone {
                apex: eye + DVec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5) * 8.0,
                axis: DVec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5).normalize(),
                half_angle: 0.01 + 0.6 * rnd(),
            };
            if pyramid_misses_cone(eye, &corners, &cone) {
                proven += 1;
                assert!(!any_ray_hits(eye, &corners, &cone), "{cone:?} {corners:?}");
            }
        }
        assert!(proven > 100, "only {proven} of 400 proven");
    }

    #[test]
    fn hits_are_never_proven_misses() {
        let eye = DVec3::ZERO;
        let corners = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)].map(|(a, b)| DVec3::new(a * 0.1, b * 0.1, -1.0).normalize());
        // The apex in view; the eye inside the cone; a 0.5° beam through the
        // tile's centre from the side; a beam grazing the pyramid's edge.
        for cone in [
            Cone {
                apex: DVec3::new(0.0, 0.0, -5.0),
                axis: DVec3::X,
                half_angle: 0.01,
            },
            Cone {
                apex: DVec3::new(0.0, 0.0, 5.0),
                axis: -DVec3::Z,
                half_angle: 0.1,
            },
            Cone {
                apex: DVec3::new(-50.0, 0.0, -10.0),
                axis: DVec3::X,
                half_angle: 0.5f64.to_radians() / 2.0,
            },
            Cone {
                apex: DVec3::new(-50.0, 1.0, -10.0),
                axis: DVec3::X,
                half_angle: 0.0001,
            },
        ] {
            assert!(!pyramid_misses_cone(eye, &corners, &cone), "{cone:?}");
        }
    }

    #[test]
    fn a_beam_beside_the_tile_is_proven() {
        // A 5° beam crossing the view below a tile that looks straight ahead:
        // separated by a plane tilted under the tile.
        let eye = DVec3::ZERO;
        let corners = [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)].map(|(a, b)| DVec3::new(a * 0.02, b * 0.02, -1.0).normalize());
        let cone = Cone {
            apex: DVec3::new(-5.0, -2.0, -10.0),
            axis: DVec3::X,
            half_angle: 2.5f64.to_radians(),
        };
        assert!(pyramid_misses_cone(eye, &corners, &cone));
    }
}
