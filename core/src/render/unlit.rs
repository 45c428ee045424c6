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
//! **Windows.** A window light's volume is the prism swept from its polygon
//! away from the light, inside the convex hull of the corners `Pᵢ` and the
//! direction `−ℓ`. A separating plane through `E` then has `n·cⱼ ≤ 0`,
//! `n·(Pᵢ − E) ≥ 0` and `n·(−ℓ) ≥ 0`: a polyhedral cone of normals, which is
//! not `{0}` iff one of its extreme rays (cross products of two constraint
//! normals) or a constraint normal itself satisfies all the constraints —
//! every candidate is tried.
//!
//! **Floors.** A cone reaches below a floor, where no view ray that meets the
//! floor goes: tiles whose rays all end on it would count as lit for the
//! cone's part beneath it. A [`Floor`] is a convex polygon of triangles on
//! one plane, watertight (every inner edge shared by two triangles with the
//! same vertices), with the eye strictly above it. When the four corner
//! rays of a tile head down into its plane and cross it inside the polygon
//! (by a margin), so does every ray of the tile (the crossings of a
//! pyramid's rays fill the convex hull of its corners' crossings), and each
//! ends there or before (the floor is opaque). The rays' segments then lie
//! in the convex hull of the eye `E` and the four crossings `Fᵢ`, and a
//! plane separates that from the cone iff some unit `n` has `n·(P − E) ≥ 0`,
//! `n·(P − Fᵢ) ≥ 0` and `n·a ≥ sin β` (the plane `n·x = n·P`): the same
//! maximisation as above with these five constraints.
//!
//! Lights whose volume is not a cone narrower than a hemisphere (wide spots,
//! point lights), suns and ambient light reach every ray: with any of them in
//! the scene no tile is unlit.

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

/// A window light's volume as the test sees it: the convex hull of the
/// window's corners swept along `recession` (away from the light).
#[derive(Debug, Clone)]
pub struct Prism {
    /// Corners of the window, m.
    pub corners: Vec<DVec3>,
    /// Unit direction the light travels (−ℓ).
    pub recession: DVec3,
}

/// A floor no view ray passes (see the module documentation).
#[derive(Debug, Clone)]
pub struct Floor {
    /// Unit normal towards the eye.
    pub normal: DVec3,
    /// `normal · x` on the plane, m.
    pub offset: f64,
    /// The polygon's edges: a point `x` of the plane is inside when
    /// `m·x ≥ o` for every `(m, o)` (`m` unit, in the plane, inwards).
    pub edges: Vec<(DVec3, f64)>,
    /// The polygon's area, m².
    pub area: f64,
}

impl Floor {
    /// The floor made by the triangles `tris` of one plane (unit `normal`,
    /// `normal · x = offset`) as seen from `eye`, if they qualify: the eye
    /// strictly off the plane, the triangles' areas summing to their convex
    /// hull's (no gap, no overlap) and every edge either shared by exactly
    /// two triangles (same vertices) or on the hull's boundary.
    pub fn new(tris: &[[DVec3; 3]], normal: DVec3, offset: f64, eye: DVec3) -> Option<Floor> {
        let (mut normal, mut offset) = (normal, offset);
        if normal.dot(eye) - offset < 0.0 {
            (normal, offset) = (-normal, -offset);
        }
        let scale = 1.0 + eye.abs().max_element() + offset.abs();
        if tris.is_empty() || normal.dot(eye) - offset <= 1e-9 * scale {
            return None;
        }
        let (u, v) = normal.any_orthonormal_pair();
        let flat = |p: DVec3| (p.dot(u), p.dot(v));
        let cross = |o: (f64, f64), a: (f64, f64), b: (f64, f64)| (a.0 - o.0) * (b.1 - o.1) - (a.1 - o.1) * (b.0 - o.0);
        // Convex hull (monotone chain), counter-clockwise.
        let mut pts: Vec<(f64, f64)> = tris.iter().flatten().map(|p| flat(*p)).collect();
        pts.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
        pts.dedup();
        if pts.len() < 3 {
            return None;
        }
        let mut hull: Vec<(f64, f64)> = Vec::new();
        for pass in 0..2 {
            let start = hull.len();
            let iter: Box<dyn Iterator<Item = &(f64, f64)>> = if pass == 0 {
                Box::new(pts.iter())
            } else {
                Box::new(pts.iter().rev())
            };
            for &p in iter {
                while hull.len() >= start + 2 && cross(hull[hull.len() - 2], hull[hull.len() - 1], p) <= 0.0 {
                    hull.pop();
                }
                hull.push(p);
            }
            hull.pop();
        }
        if hull.len() < 3 {
            return None;
        }
        let hull_area = 0.5
            * (0..hull.len())
                .map(|i| cross((0.0, 0.0), hull[i], hull[(i + 1) % hull.len()]))
                .sum::<f64>();
        let tri_area: f64 = tris.iter().map(|t| 0.5 * cross(flat(t[0]), flat(t[1]), flat(t[2])).abs()).sum();
        if !(hull_area > 0.0 && (tri_area - hull_area).abs() <= 1e-9 * hull_area) {
            return None;
        }
        // Edges by their vertices' exact bits: inner ones twice, boundary ones once.
        let key = |p: DVec3| p.to_array().map(f64::to_bits);
        let mut edges: std::collections::HashMap<([u64; 3], [u64; 3]), u32> = std::collections::HashMap::new();
        for t in tris {
            for k in 0..3 {
                let (a, b) = (key(t[k]), key(t[(k + 1) % 3]));
                *edges.entry(if a < b { (a, b) } else { (b, a) }).or_insert(0) += 1;
            }
        }
        let extent = hull.iter().fold(0.0f64, |m, p| m.max(p.0.abs()).max(p.1.abs()));
        let from_bits = |k: [u64; 3]| DVec3::from_array(k.map(f64::from_bits));
        for (&(a, b), &count) in &edges {
            let ok = match count {
                2 => true,
                1 => {
                    let (pa, pb) = (flat(from_bits(a)), flat(from_bits(b)));
                    // Both ends on one hull edge's line.
                    (0..hull.len()).any(|i| {
                        let (h0, h1) = (hull[i], hull[(i + 1) % hull.len()]);
                        let len = ((h1.0 - h0.0).powi(2) + (h1.1 - h0.1).powi(2)).sqrt();
                        let tol = 1e-12 * len * (1.0 + extent);
                        cross(h0, h1, pa).abs() <= tol && cross(h0, h1, pb).abs() <= tol
                    })
                }
                _ => false,
            };
            if !ok {
                return None;
            }
        }
        let edges = (0..hull.len())
            .map(|i| {
                let (a, b) = (hull[i], hull[(i + 1) % hull.len()]);
                let m2 = (-(b.1 - a.1), b.0 - a.0);
                let len = (m2.0 * m2.0 + m2.1 * m2.1).sqrt();
                let m = (u * m2.0 + v * m2.1) / len;
                let on_plane = u * a.0 + v * a.1 + normal * offset;
                (m, m.dot(on_plane))
            })
            .collect();
        Some(Floor {
            normal,
            offset,
            edges,
            area: hull_area,
        })
    }

    /// Where the rays from `eye` along the unit `corners` cross the plane,
    /// when all of them head into it and cross it inside the polygon by a
    /// margin.
    pub fn footprint(&self, eye: DVec3, corners: &[DVec3; 4]) -> Option<[DVec3; 4]> {
        let height = self.normal.dot(eye) - self.offset;
        let mut out = [DVec3::ZERO; 4];
        for (c, f) in corners.iter().zip(&mut out) {
            let down = -self.normal.dot(*c);
            if down.is_nan() || down <= 1e-12 {
                return None;
            }
            *f = eye + *c * (height / down);
            let margin = 1e-9 * (1.0 + f.abs().max_element());
            if !(f.is_finite() && self.edges.iter().all(|(m, o)| m.dot(*f) - o >= margin)) {
                return None;
            }
        }
        Some(out)
    }
}

/// An illumination volume the test can separate from a tile.
#[derive(Debug, Clone)]
pub enum Volume {
    /// A point or spot light's bounding cone.
    Cone(Cone),
    /// A window light's prism.
    Prism(Prism),
}

impl Volume {
    fn missed_by(&self, eye: DVec3, corners: &[DVec3; 4]) -> bool {
        match self {
            Volume::Cone(c) => pyramid_misses_cone(eye, corners, c),
            Volume::Prism(p) => pyramid_misses_prism(eye, corners, p),
        }
    }

    /// Whether rays from `eye` that end on a floor within `footprint` miss it.
    fn missed_above_floor(&self, eye: DVec3, footprint: &[DVec3; 4]) -> bool {
        match self {
            Volume::Cone(c) => floor_pyramid_misses_cone(eye, footprint, c),
            Volume::Prism(_) => false,
        }
    }
}

/// Whether a plane through `eye` separates the pyramid spanned by the unit
/// directions `corners` from the prism (see the module documentation).
pub fn pyramid_misses_prism(eye: DVec3, corners: &[DVec3; 4], prism: &Prism) -> bool {
    let mut g: Vec<DVec3> = corners.iter().map(|c| -*c).collect();
    g.push(prism.recession);
    for p in &prism.corners {
        // Each corner's direction, pulled back towards the eye's side by a
        // relative margin so that a plane found is strictly separating.
        match (*p - eye).try_normalize() {
            Some(q) => g.push(q - prism.recession * APEX_MARGIN),
            None => return false,
        }
    }
    let inside = |n: DVec3| g.iter().all(|gj| gj.dot(n) >= -1e-12);
    let feasible = |n: DVec3| n.try_normalize().is_some_and(&inside);
    if g.iter().any(|gj| feasible(*gj)) {
        return true;
    }
    (0..g.len()).any(|j| (j + 1..g.len()).any(|k| feasible(g[j].cross(g[k])) || feasible(-g[j].cross(g[k]))))
}

/// Whether a plane through `eye` separates the pyramid spanned by the unit
/// directions `corners` (in order around the rectangle) from the cone
/// (widened by the margins). `false` when it cannot be shown.
pub fn pyramid_misses_cone(eye: DVec3, corners: &[DVec3; 4], cone: &Cone) -> bool {
    let to_apex = cone.apex - eye;
    let back = APEX_MARGIN * (to_apex.length() + 1.0);
    let q = to_apex - cone.axis * back;
    let Some(q) = q.try_normalize() else { return false };
    // Facet normals g: n ∈ 𝒫 iff g·n ≥ 0 for all of them.
    cone_separable(&[-corners[0], -corners[1], -corners[2], -corners[3], q], cone)
}

/// Whether a plane separates the cone (widened by the margins) from the
/// convex hull of `eye` and the four points `footprint` (see Floors in the
/// module documentation). `false` when it cannot be shown.
pub fn floor_pyramid_misses_cone(eye: DVec3, footprint: &[DVec3; 4], cone: &Cone) -> bool {
    let back = APEX_MARGIN * ((cone.apex - eye).length() + 1.0);
    let apex = cone.apex - cone.axis * back;
    let mut g = [DVec3::ZERO; 5];
    for (gj, p) in g.iter_mut().zip(std::iter::once(&eye).chain(footprint)) {
        match (apex - *p).try_normalize() {
            Some(d) => *gj = d,
            None => return false,
        }
    }
    cone_separable(&g, cone)
}

/// Whether some unit `n` with `g·n ≥ 0` for every `g` has `n·a ≥ sin β`
/// (the cone's half-angle β widened by [`ANGLE_MARGIN`]).
fn cone_separable(g: &[DVec3; 5], cone: &Cone) -> bool {
    let beta = cone.half_angle + ANGLE_MARGIN;
    if !(beta > 0.0 && beta < std::f64::consts::FRAC_PI_2) {
        return false;
    }
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
    for gj in g {
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
/// its rays, with every pixel's `reach` (px) around it, miss every volume.
/// Returns the tile grid's columns and the flags, row by row.
pub fn unlit_tiles(cam: &CameraRays, volumes: &[Volume], floors: &[Floor], pad: usize, reach: f64) -> (usize, Vec<bool>) {
    let (pw, ph) = (cam.width + 2 * pad, cam.height + 2 * pad);
    let (cols, rows) = (pw.div_ceil(TILE), ph.div_ceil(TILE));
    let margin = reach + 1.0;
    // Whether the rays of tiles [tx0, tx1) × [ty0, ty1), padded, miss every volume.
    let missed = |tx0: usize, ty0: usize, tx1: usize, ty1: usize| {
        // The tiles' pixels span [x0, x1) × [y0, y1) in image coordinates.
        let x0 = (tx0 * TILE) as f64 - pad as f64;
        let y0 = (ty0 * TILE) as f64 - pad as f64;
        let (x1, y1) = ((tx1 * TILE) as f64 - pad as f64, (ty1 * TILE) as f64 - pad as f64);
        let (xa, xb, ya, yb) = (x0 - margin, x1 + margin, y0 - margin, y1 + margin);
        let corners = [
            cam.direction(xa, ya),
            cam.direction(xb, ya),
            cam.direction(xb, yb),
            cam.direction(xa, yb),
        ];
        let mut footprints: Option<Vec<[DVec3; 4]>> = None;
        volumes.iter().all(|v| {
            v.missed_by(cam.position, &corners) || {
                let fp = footprints.get_or_insert_with(|| floors.iter().filter_map(|f| f.footprint(cam.position, &corners)).collect());
                fp.iter().any(|f| v.missed_above_floor(cam.position, f))
            }
        })
    };
    // Blocks of BLOCK × BLOCK tiles first: a plane that separates a block's
    // pyramid separates each of its tiles' (a sub-pyramid), so a missed
    // block settles all its tiles with one test; the others test each tile.
    const BLOCK: usize = 8;
    let mut flags = vec![false; rows * cols];
    for by in (0..rows).step_by(BLOCK) {
        for bx in (0..cols).step_by(BLOCK) {
            let (bx1, by1) = ((bx + BLOCK).min(cols), (by + BLOCK).min(rows));
            let all = missed(bx, by, bx1, by1);
            for ty in by..by1 {
                for tx in bx..bx1 {
                    flags[ty * cols + tx] = all || missed(tx, ty, tx + 1, ty + 1);
                }
            }
        }
    }
    (cols, flags)
}

#[cfg(test)]
mod tests {
    use super::*;

    /// A uniform number in [0, 1) from a xorshift64 state.
    fn uniform(state: &mut u64) -> f64 {
        *state ^= *state << 13;
        *state ^= *state >> 7;
        *state ^= *state << 17;
        (*state >> 11) as f64 / (1u64 << 53) as f64
    }

    /// Unit directions to the corners of a square of half-size `size` across
    /// `centre` (unit), in order around it.
    fn square_pyramid(centre: DVec3, size: f64) -> [DVec3; 4] {
        let side = centre.any_orthonormal_vector();
        let up = centre.cross(side);
        [(-1.0, -1.0), (1.0, -1.0), (1.0, 1.0), (-1.0, 1.0)].map(|(a, b)| (centre + (side * a + up * b) * size).normalize())
    }

    /// A dense grid of 31 × 31 unit directions across the pyramid, edges included.
    fn fan(corners: &[DVec3; 4]) -> impl Iterator<Item = DVec3> + '_ {
        let n = 30;
        (0..=n).flat_map(move |i| {
            (0..=n).map(move |j| {
                let (u, v) = (i as f64 / n as f64, j as f64 / n as f64);
                let top = corners[0] * (1.0 - u) + corners[1] * u;
                let bottom = corners[3] * (1.0 - u) + corners[2] * u;
                (top * (1.0 - v) + bottom * v).normalize()
            })
        })
    }

    /// Brute force: does any ray of the fan come within the cone?
    fn any_ray_hits(eye: DVec3, corners: &[DVec3; 4], cone: &Cone) -> bool {
        fan(corners).any(|d| {
            // Closest approach in angle: march along the ray.
            (0..300).any(|k| {
                let t = 0.05 * 1.03f64.powi(k) - 0.05;
                let w = eye + d * t - cone.apex;
                let len = w.length();
                len == 0.0 || w.dot(cone.axis) >= len * cone.half_angle.cos()
            })
        })
    }

    #[test]
    fn a_proven_miss_is_a_miss_and_far_tiles_are_proven() {
        // Random cones and pyramids: whenever the test says "misses", no ray
        // of a dense fan hits; and a pyramid pointing away from a narrow cone
        // whose apex is behind it is proven.
        let mut state = 0x2545_f491_4f6c_dd1du64;
        let mut rnd = || uniform(&mut state);
        let mut proven = 0;
        for _ in 0..400 {
            let eye = DVec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5);
            let centre = DVec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5).normalize();
            let corners = square_pyramid(centre, 0.02 + 0.2 * rnd());
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
    fn a_proven_miss_of_a_window_prism_is_a_miss() {
        // Random square windows and light directions: whenever the test says
        // "misses", no ray of a dense fan has a lit interval (the renderer's
        // own window geometry); some tiles are proven.
        use crate::light::window::WindowSource;
        let mut state = 0x9e37_79b9_7f4a_7c15u64;
        let mut rnd = || uniform(&mut state);
        let (mut proven, mut tried) = (0, 0);
        for _ in 0..300 {
            let eye = DVec3::ZERO;
            let centre = DVec3::new(rnd() - 0.5, rnd() - 0.5, -1.0).normalize();
            let corners = square_pyramid(centre, 0.02 + 0.1 * rnd());
            let c = DVec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5) * 10.0;
            let (a, b) = (
                DVec3::new(rnd(), rnd(), rnd()).normalize(),
                DVec3::new(rnd() - 0.5, 1.0, rnd() - 0.5).normalize(),
            );
            let a = a * (0.3 + rnd());
            let b = (b - a.normalize() * b.dot(a.normalize())).normalize() * (0.3 + rnd());
            let window = [c - a - b, c + a - b, c + a + b, c - a + b].map(|p| p.to_array());
            let to_light = DVec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5).normalize();
            if to_light.dot(a.cross(b).normalize()).abs() < 0.1 {
                continue;
            }
            let w = WindowSource::<3>::new("w", to_light, [1.0; 3], &window);
            let prism = Prism {
                corners: w.corners(),
                recession: -w.to_light,
            };
            tried += 1;
            if pyramid_misses_prism(eye, &corners, &prism) {
                proven += 1;
                let mut out = Vec::new();
                for d in fan(&corners) {
                    w.intervals(eye, d, 0.0, 1e4, &mut out);
                    assert!(out.is_empty(), "ray {d} hits the prism: {out:?}");
                }
            }
        }
        assert!(proven > tried / 5, "only {proven} of {tried} proven");
    }

    /// A 20 m square floor at z = 0 as two triangles.
    fn floor_quad() -> Vec<[DVec3; 3]> {
        let p = [(-10.0, -10.0), (10.0, -10.0), (10.0, 10.0), (-10.0, 10.0)].map(|(x, y)| DVec3::new(x, y, 0.0));
        vec![[p[0], p[1], p[2]], [p[0], p[2], p[3]]]
    }

    #[test]
    fn floors_are_convex_watertight_polygons_below_the_eye() {
        let eye = DVec3::new(0.0, -9.0, 2.0);
        let quad = floor_quad();
        let f = Floor::new(&quad, DVec3::Z, 0.0, eye).expect("a square of two triangles");
        assert!((f.area - 400.0).abs() < 1e-9 && f.edges.len() == 4);
        // Given with the normal pointing down: turned towards the eye.
        assert!(Floor::new(&quad, -DVec3::Z, 0.0, eye).is_some_and(|f| f.normal == DVec3::Z));
        // The eye on the plane; one triangle of the two (not the hull's area:
        // fine, it is convex) and an L of three (concave: refused); a square
        // split at a T-junction (an inner edge without its twin: refused).
        assert!(Floor::new(&quad, DVec3::Z, 0.0, DVec3::new(0.0, 0.0, 0.0)).is_none());
        assert!(Floor::new(&quad[..1], DVec3::Z, 0.0, eye).is_some());
        let q = |x: f64, y: f64| DVec3::new(x, y, 0.0);
        let trapezoid = vec![
            [q(0.0, 0.0), q(1.0, 0.0), q(1.0, 1.0)],
            [q(0.0, 0.0), q(1.0, 1.0), q(0.0, 1.0)],
            [q(1.0, 0.0), q(2.0, 0.0), q(1.0, 1.0)],
        ];
        assert!(
            Floor::new(&trapezoid, DVec3::Z, 0.0, eye).is_some(),
            "a square and a triangle: convex"
        );
        let notch = vec![
            [q(0.0, 0.0), q(1.0, 0.0), q(1.0, 1.0)],
            [q(0.0, 0.0), q(1.0, 1.0), q(0.0, 1.0)],
            [q(1.0, 0.0), q(2.0, 0.0), q(2.0, 1.0)],
        ];
        assert!(
            Floor::new(&notch, DVec3::Z, 0.0, eye).is_none(),
            "three triangles of a 2 × 1 rectangle: a gap"
        );
        let t_junction = vec![
            [q(0.0, 0.0), q(2.0, 0.0), q(2.0, 2.0)],
            [q(0.0, 0.0), q(1.0, 1.0), q(0.0, 2.0)],
            [q(1.0, 1.0), q(2.0, 2.0), q(0.0, 2.0)],
        ];
        assert!(
            Floor::new(&t_junction, DVec3::Z, 0.0, eye).is_none(),
            "the diagonal split at its midpoint"
        );
        // Overlapping triangles: areas sum past the hull's.
        let overlap = vec![quad[0], quad[1], quad[0]];
        assert!(Floor::new(&overlap, DVec3::Z, 0.0, eye).is_none());
        // Footprints: straight down inside; towards the sky or past the edge: none.
        let down = [(-0.1, -0.1), (0.1, -0.1), (0.1, 0.1), (-0.1, 0.1)].map(|(a, b)| DVec3::new(a, 1.0 + b, -1.0).normalize());
        assert!(f.footprint(eye, &down).is_some());
        let up = down.map(|d| DVec3::new(d.x, d.y, -d.z));
        assert!(f.footprint(eye, &up).is_none());
        let far = down.map(|d| DVec3::new(d.x, d.y, d.z * 0.1).normalize());
        assert!(f.footprint(eye, &far).is_none(), "crosses the plane beyond the square");
    }

    #[test]
    fn a_proven_miss_above_a_floor_is_a_miss() {
        // Random cones reaching through a square floor and random small
        // pyramids looking down at it: whenever the floor test says "misses",
        // no ray of a dense fan has a point in the cone before it reaches
        // the floor; and many tiles the cone's part beneath the floor would
        // light are proven.
        let floor = Floor::new(&floor_quad(), DVec3::Z, 0.0, DVec3::new(0.0, -9.0, 2.0)).expect("floor");
        let mut state = 0x1234_5678_9abc_def1u64;
        let mut rnd = || uniform(&mut state);
        let (mut proven, mut only_by_floor, mut tried) = (0, 0, 0);
        for _ in 0..600 {
            let eye = DVec3::new(8.0 * rnd() - 4.0, 8.0 * rnd() - 4.0, 0.5 + 4.0 * rnd());
            let look = DVec3::new(10.0 * rnd() - 5.0, 10.0 * rnd() - 5.0, 0.0) - eye;
            let corners = square_pyramid(look.normalize(), 0.01 + 0.1 * rnd());
            let apex = DVec3::new(8.0 * rnd() - 4.0, 8.0 * rnd() - 4.0, 2.0 + 5.0 * rnd());
            let target = DVec3::new(8.0 * rnd() - 4.0, 8.0 * rnd() - 4.0, 0.0);
            let cone = Cone {
                apex,
                axis: (target - apex).normalize(),
                half_angle: (0.5 + 20.0 * rnd()).to_radians(),
            };
            let Some(fp) = floor.footprint(eye, &corners) else { continue };
            tried += 1;
            if floor_pyramid_misses_cone(eye, &fp, &cone) {
                proven += 1;
                only_by_floor += usize::from(!pyramid_misses_cone(eye, &corners, &cone));
                for d in fan(&corners) {
                    let t_floor = eye.z / -d.z;
                    for k in 0..=400 {
                        let p = eye + d * (t_floor * f64::from(k) / 400.0);
                        let w = p - cone.apex;
                        let len = w.length();
                        assert!(
                            len > 0.0 && w.dot(cone.axis) < len * cone.half_angle.cos(),
                            "{cone:?} {corners:?} at {p}"
                        );
                    }
                }
            }
        }
        assert!(tried > 300 && proven > tried / 4, "{proven} of {tried} proven");
        assert!(only_by_floor > 20, "only {only_by_floor} proven by the floor alone");
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
