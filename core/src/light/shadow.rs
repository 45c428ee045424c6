//! Exact volumetric shadows of triangle meshes: the lit segments of a view ray.
//!
//! **Method.** A point `x` is in shadow of a light when the segment from `x`
//! to the light crosses a triangle. Let `n(x)` be the number of triangles it
//! crosses (Nishita's quantitative invisibility). Along a view ray `n` is
//! piecewise constant; it changes only where the ray crosses the boundary of
//! some triangle's shadow frustum. That boundary is the triangle itself —
//! never crossed between the eye and the first surface, where view rays end —
//! and one *wedge* per edge: the part of the plane through the light and the
//! edge that lies beyond the edge (for a parallel light, the strip the edge
//! sweeps along the light direction). Crossing the wedge of an edge changes
//! `n` by the number of adjacent triangles on one side of the wedge plane
//! minus those on the other, so an edge shared by two triangles that face the
//! light the same way (one on each side) changes nothing: only **silhouette
//! and boundary edges** as seen from the light are kept.
//!
//! Per view-ray interval the crossings with the kept wedges are found exactly
//! (a ray–plane intersection and three sign tests each); the pieces between
//! consecutive crossings have constant visibility, which one shadow ray from
//! each piece's midpoint to the light decides (any-hit in the scene BVH). The
//! lit segments are therefore exact up to floating point for any triangle
//! soup — open, closed, non-manifold, coincident faces — without sampling
//! visibility along the ray. Cost per view ray: a BVH walk over the kept
//! wedges plus one visibility test per piece — a grid lookup, and a shadow
//! ray only where the grid cannot decide (below).
//!
//! **Culling structure.** Wedges are infinite, so they are bounded in the
//! light's *direction space*: for a point light each edge is the arc between
//! the unit directions to its end points (bounded by the box of the arc on
//! the unit sphere); for a parallel light, the edge's projection onto the
//! plane ⊥ the light. The view-ray interval maps to an arc (a segment) in the
//! same space; a box can hold a crossing only if it straddles the plane of
//! that arc and overlaps the arc's own box. A binned-median BVH over the
//! boxes answers that query.
//!
//! **Shadow rays skipped by a visibility grid** (spot lights of reach < 80°).
//! The light's directions are binned on a grid in the gnomonic plane of its
//! axis (`(tan θ cos φ, tan θ sin φ)`, where great circles are straight lines,
//! so a triangle in front of the light projects to a straight triangle). Per
//! cell two conservative distances from the light are kept:
//! * `lit`: a lower bound of the distance of every triangle point whose
//!   direction is in the cell — the larger of the triangle's exact minimum
//!   distance and `D/cos(max(0, α − ρ))` (`D` the distance of its plane, `α`
//!   the angle between the plane's foot direction and the cell's centre, `ρ`
//!   the cell's angular radius); every triangle whose projected box overlaps
//!   the cell contributes (triangles reaching behind the light, to every cell).
//!   A point nearer than that is lit: its segment to the light meets nothing.
//! * `shadow`: an upper bound of the distance, `D/cos(α + ρ)`, of a triangle
//!   whose projection holds the whole cell (with a margin). A point farther
//!   than that is in shadow: its segment crosses that triangle's interior.
//!
//! Between the two bounds, a few *candidate blockers* per cell (the nearest
//! triangle through the cell's centre and through each corner) are tested
//! first: a hit well inside one of them (barycentrics ≥ 1e-9, beyond the
//! shadow ray's end offsets) is a hit for the shadow ray as well. Only the
//! rest need a shadow ray through the scene BVH; the answers are the same as
//! the shadow ray's (bounds carry relative margins far above rounding, and the
//! shadow ray's own end offsets are accounted for). Up to 128 × 128 cells of 32
//! bytes per light (fewer for a few triangles, [`grid_cells_for`]); on the
//! 4-spot benchmark (a 10k-triangle sphere on a floor)
//! the grids leave 188 k of 1.42 M visibility tests to shadow rays.
//!
//! **Left out.** Triangles outside the light's illumination volume (tested
//! with their bounding spheres) contribute no edges; the count is reported.

use crate::geometry::bvh::Bvh;
use glam::DVec3;
use rayon::prelude::*;
use std::collections::HashMap;

/// How light reaches the scene.
#[derive(Debug, Clone, Copy)]
pub enum Projector {
    /// A point light at this position.
    Point(DVec3),
    /// Parallel light travelling opposite to this unit vector (towards the light).
    Directional(DVec3),
}

impl Projector {
    /// Where `p` maps in direction space.
    #[inline]
    fn project(&self, p: DVec3) -> DVec3 {
        match self {
            Projector::Point(l) => (p - *l).normalize_or_zero(),
            Projector::Directional(to_light) => p - *to_light * p.dot(*to_light),
        }
    }

    /// Unit direction from `p` towards the light and the distance (∞ for parallel light).
    #[inline]
    pub fn towards_light(&self, p: DVec3) -> (DVec3, f64) {
        match self {
            Projector::Point(l) => {
                let v = *l - p;
                let d = v.length();
                (v / d, d)
            }
            Projector::Directional(to_light) => (*to_light, f64::INFINITY),
        }
    }
}

#[derive(Debug, Clone, Copy)]
struct Wedge {
    a: DVec3,
    b: DVec3,
    /// Normal of the wedge plane (not normalised).
    m: DVec3,
}

#[derive(Debug, Clone, Copy)]
struct Node {
    min: DVec3,
    max: DVec3,
    /// Leaf: first wedge; inner: left child (right = left + 1).
    first: u32,
    /// Leaf: wedge count; inner: 0.
    count: u32,
}

/// Most cells per axis of a point light's [`VisibilityGrid`].
const GRID_CELLS: usize = 128;

/// Cells per axis of a visibility grid over `triangles` triangles:
/// 8·√triangles rounded up to a power of two, 16..=[`GRID_CELLS`]. Building
/// costs cells × triangles, and finer cells leave fewer visibility tests to
/// shadow rays: a floor's two triangles do not need 16 k cells (the grid was
/// ≈ 1 ms of a 15 ms render of a 5° beam over a floor), while a 10 k-triangle
/// set piece gets the full 128 × 128. With 16·√triangles (as before) the
/// grids of small meshes cost more than they saved, by instruction counts
/// (callgrind, one thread, the images identical): the box occluder (14
/// triangles, 64 → 32 cells) 4.0 % fewer instructions at 96×54, 2.1 % at
/// 192×108, 0.8 % at 384×216, 0.4 % at 768×432; the composite stage (16
/// triangles) 2.9 %; the 5° beam, the two coloured spots and the camera in a
/// dense beam (a floor, 32 → 16 cells) 0.5–1.0 %; the dry-ice demo at half
/// size (4 triangles) the same to 0.002 %. Meshes of more than 64 triangles
/// get the grid they got before.
fn grid_cells_for(triangles: usize) -> usize {
    ((8.0 * (triangles as f64).sqrt()).ceil() as usize)
        .next_power_of_two()
        .clamp(16, GRID_CELLS)
}

/// A spot light's conservative visibility bounds per direction cell (see the
/// module documentation).
#[derive(Debug, Clone)]
struct VisibilityGrid {
    light: DVec3,
    axis: DVec3,
    x: DVec3,
    y: DVec3,
    /// The grid spans `[−half, half]²` in the gnomonic plane.
    half: f64,
    inv_cell: f64,
    /// Cells per axis ([`grid_cells_for`]).
    n: usize,
    /// Per cell (row-major, `n` per row).
    cells: Vec<GridCell>,
    /// A point at distance `s ≤ shadow` from the light is only reported in
    /// shadow when the shadow ray's end offset is below this (see `classify`).
    max_eps: f64,
    /// Candidate blockers as `(v₀, v₁ − v₀, v₂ − v₀)`.
    tris: Vec<[DVec3; 3]>,
}

/// Candidate blockers kept per grid cell.
const BLOCKERS: usize = 4;

/// One cell of a [`VisibilityGrid`] (32 bytes: one cache access per lookup).
#[derive(Debug, Clone, Copy)]
struct GridCell {
    /// Squared distance below which a point is lit.
    lit2: f64,
    /// Squared distance above which a point is in shadow (∞: unknown).
    shadow2: f64,
    /// Up to [`BLOCKERS`] indices into the grid's `tris` (`u32::MAX`: none).
    blockers: [u32; BLOCKERS],
}

/// Whether the segment from `o` along the unit `dir` certainly crosses the
/// triangle `(v₀, e₁, e₂)` at `t ∈ [t_min, t_max]`: Möller–Trumbore with every
/// barycentric ≥ 1e-9, so that rounding cannot move the hit off the triangle.
#[inline]
fn surely_crosses(o: DVec3, dir: DVec3, tri: &[DVec3; 3], t_min: f64, t_max: f64) -> bool {
    let [v0, e1, e2] = *tri;
    let p = dir.cross(e2);
    let det = e1.dot(p);
    if det == 0.0 || !det.is_finite() {
        return false;
    }
    let inv = 1.0 / det;
    let s = o - v0;
    let u = s.dot(p) * inv;
    let q = s.cross(e1);
    let v = dir.dot(q) * inv;
    let t = e2.dot(q) * inv;
    const M: f64 = 1e-9;
    u >= M && v >= M && 1.0 - u - v >= M && t >= t_min && t <= t_max
}

/// The point of triangle `(a, b, c)` closest to `p` (Ericson, Real-Time
/// Collision Detection, 5.1.5).
fn closest_on_triangle(p: DVec3, a: DVec3, b: DVec3, c: DVec3) -> DVec3 {
    let (ab, ac, ap) = (b - a, c - a, p - a);
    let (d1, d2) = (ab.dot(ap), ac.dot(ap));
    if d1 <= 0.0 && d2 <= 0.0 {
        return a;
    }
    let bp = p - b;
    let (d3, d4) = (ab.dot(bp), ac.dot(bp));
    if d3 >= 0.0 && d4 <= d3 {
        return b;
    }
    let vc = d1 * d4 - d3 * d2;
    if vc <= 0.0 && d1 >= 0.0 && d3 <= 0.0 {
        return a + ab * (d1 / (d1 - d3));
    }
    let cp = p - c;
    let (d5, d6) = (ab.dot(cp), ac.dot(cp));
    if d6 >= 0.0 && d5 <= d6 {
        return c;
    }
    let vb = d5 * d2 - d1 * d6;
    if vb <= 0.0 && d2 >= 0.0 && d6 <= 0.0 {
        return a + ac * (d2 / (d2 - d6));
    }
    let va = d3 * d6 - d5 * d4;
    if va <= 0.0 && (d4 - d3) >= 0.0 && (d5 - d6) >= 0.0 {
        return b + (c - b) * ((d4 - d3) / ((d4 - d3) + (d5 - d6)));
    }
    let denom = 1.0 / (va + vb + vc);
    a + ab * (vb * denom) + ac * (vc * denom)
}

/// A triangle as [`VisibilityGrid::build`] needs it for every band of cells.
struct GridTriangle {
    a: DVec3,
    b: DVec3,
    c: DVec3,
    /// Its nearest distance from the light, slightly reduced.
    d_min: f64,
    /// Its plane: unit normal away from the light and distance from it.
    plane: Option<(DVec3, f64)>,
    /// Not a sliver (which the scene BVH may drop as degenerate, and which never blocks).
    solid: bool,
    /// Gnomonic projections of the corners.
    projected: [(f64, f64); 3],
    /// Twice the projection's signed area.
    area: f64,
    /// The cells its projection may touch (`i0, i1, j0, j1`, inclusive);
    /// `None` when it reaches behind (or to the side of) the light: every cell.
    cells: Option<(usize, usize, usize, usize)>,
}

impl GridTriangle {
    /// `None` for a triangle with a non-finite corner or whose projection
    /// misses the grid.
    fn new(a: DVec3, b: DVec3, c: DVec3, grid: &VisibilityGrid, margin: f64) -> Option<GridTriangle> {
        if !(a.is_finite() && b.is_finite() && c.is_finite()) {
            return None;
        }
        let (light, axis, x, y, half, n) = (grid.light, grid.axis, grid.x, grid.y, grid.half, grid.n);
        let d_min = (closest_on_triangle(light, a, b, c) - light).length() * (1.0 - 1e-9);
        let nrm = (b - a).cross(c - a);
        let plane = nrm.try_normalize().map(|nu| {
            let dist = nu.dot(a - light);
            if dist >= 0.0 { (nu, dist) } else { (-nu, -dist) }
        });
        let solid = nrm.length() > 1e-8 * (b - a).length() * (c - a).length();
        let z = [a, b, c].map(|p| (p - light).dot(axis));
        let min_z = z.iter().copied().fold(f64::INFINITY, f64::min);
        let size = (a - light).length().max((b - light).length()).max((c - light).length());
        let mut tri = GridTriangle {
            a,
            b,
            c,
            d_min,
            plane,
            solid,
            projected: [(0.0, 0.0); 3],
            area: 0.0,
            cells: None,
        };
        if min_z.is_nan() || min_z <= 1e-6 * size {
            return Some(tri);
        }
        let p = [a, b, c].map(|q| {
            let v = q - light;
            let zz = v.dot(axis);
            (v.dot(x) / zz, v.dot(y) / zz)
        });
        let (mut lo_x, mut hi_x, mut lo_y, mut hi_y) = (f64::INFINITY, f64::NEG_INFINITY, f64::INFINITY, f64::NEG_INFINITY);
        for (px, py) in p {
            lo_x = lo_x.min(px);
            hi_x = hi_x.max(px);
            lo_y = lo_y.min(py);
            hi_y = hi_y.max(py);
        }
        let index = |v: f64| ((v + half) * grid.inv_cell).floor();
        let (i0, i1) = (index(lo_x - margin).max(0.0), index(hi_x + margin).min(n as f64 - 1.0));
        let (j0, j1) = (index(lo_y - margin).max(0.0), index(hi_y + margin).min(n as f64 - 1.0));
        if !(i0 <= i1 && j0 <= j1) {
            return None;
        }
        tri.projected = p;
        tri.area = (p[1].0 - p[0].0) * (p[2].1 - p[0].1) - (p[1].1 - p[0].1) * (p[2].0 - p[0].0);
        tri.cells = Some((i0 as usize, i1 as usize, j0 as usize, j1 as usize));
        Some(tri)
    }
}

impl VisibilityGrid {
    /// The grid of a point light at `light` with unit `axis` and frame
    /// `(x, y)`, reaching `half_angle` (< 80°) off the axis, over every triangle of `meshes`.
    fn build(light: DVec3, axis: DVec3, x: DVec3, y: DVec3, half_angle: f64, meshes: &[IndexedMesh<'_>]) -> VisibilityGrid {
        let n = grid_cells_for(meshes.iter().map(|m| m.triangles.len()).sum());
        let half = half_angle.tan() * (1.0 + 1e-6) + 1e-9;
        let cell = 2.0 * half / n as f64;
        let scale = 1.0 + light.abs().max_element();
        let mut g = VisibilityGrid {
            light,
            axis,
            x,
            y,
            half,
            inv_cell: 1.0 / cell,
            n,
            cells: vec![
                GridCell {
                    lit2: f64::INFINITY,
                    shadow2: f64::INFINITY,
                    blockers: [u32::MAX; BLOCKERS],
                };
                n * n
            ],
            max_eps: 1e-7 * scale,
            tris: Vec::new(),
        };
        // Per cell and sample point (centre, four corners): the nearest
        // triangle through it, as (distance along the sample direction, index).
        let mut nearest = vec![[(f64::INFINITY, u32::MAX); 5]; n * n];
        const SAMPLES: [(usize, usize); 5] = [(0, 0), (0, 0), (1, 0), (0, 1), (1, 1)];
        // Per cell: centre direction and cos/sin of its angular radius.
        let dir = |gx: f64, gy: f64| (axis + x * gx + y * gy).normalize();
        // Directions of the cell corners, (n + 1)² of them.
        let corners: Vec<DVec3> = (0..(n + 1) * (n + 1))
            .into_par_iter()
            .map(|k| dir(-half + (k % (n + 1)) as f64 * cell, -half + (k / (n + 1)) as f64 * cell))
            .collect();
        let corner_dir = |i: usize, j: usize| corners[j * (n + 1) + i];
        let centre: Vec<(DVec3, f64, f64)> = (0..n * n)
            .into_par_iter()
            .map(|k| {
                let (i, j) = (k % n, k / n);
                let (x0, y0) = (-half + i as f64 * cell, -half + j as f64 * cell);
                let c = dir(x0 + 0.5 * cell, y0 + 0.5 * cell);
                let cos_r = [(0, 0), (1, 0), (0, 1), (1, 1)]
                    .iter()
                    .map(|(a, b)| c.dot(corner_dir(i + a, j + b)))
                    .fold(1.0f64, f64::min)
                    .clamp(-1.0, 1.0);
                // Rounding of the corner directions: widen ρ a little.
                let rho = cos_r.acos() * (1.0 + 1e-6) + 1e-12;
                (c, rho.cos(), rho.sin())
            })
            .collect();
        let margin = 1e-9 * half;
        // Each triangle's projection and bounds, then the cells in bands of
        // rows, one band per task (a single light's grid was built on one
        // thread: 0.47 ms of the box occluder's 96×54 render). Within a band
        // the triangles go in the meshes' order, as before, so every cell
        // gets the same bounds and the same nearest triangles.
        let triangles: Vec<GridTriangle> = meshes
            .iter()
            .flat_map(|mesh| mesh.triangles.iter().map(move |t| (mesh, t)))
            .filter_map(|(mesh, t)| {
                let (Some(a), Some(b), Some(c)) = (
                    mesh.positions.get(t[0] as usize),
                    mesh.positions.get(t[1] as usize),
                    mesh.positions.get(t[2] as usize),
                ) else {
                    return None;
                };
                GridTriangle::new(*a, *b, *c, &g, margin)
            })
            .collect();
        let band_rows = n.div_ceil(4 * rayon::current_num_threads().max(1)).max(1);
        let max_eps = g.max_eps;
        let used: Vec<Vec<bool>> = g
            .cells
            .par_chunks_mut(band_rows * n)
            .zip(nearest.par_chunks_mut(band_rows * n))
            .enumerate()
            .map(|(band, (cells, nearest))| {
                let rows = band * band_rows..(band * band_rows + cells.len() / n);
                let mut used = vec![false; triangles.len()];
                for (index, tri) in triangles.iter().enumerate() {
                    let lower = |k: usize| -> f64 {
                        let Some((foot, dist)) = tri.plane else { return tri.d_min };
                        if dist <= 0.0 {
                            return tri.d_min;
                        }
                        let (cdir, cos_r, sin_r) = centre[k];
                        let ca = cdir.dot(foot).clamp(-1.0, 1.0);
                        let cos_max = if ca >= cos_r {
                            1.0
                        } else {
                            let sa = (1.0 - ca * ca).sqrt();
                            ca * cos_r + sa * sin_r
                        };
                        if cos_max <= 0.0 {
                            return f64::INFINITY;
                        }
                        tri.d_min.max(dist / cos_max * (1.0 - 1e-9))
                    };
                    let Some((i0, i1, j0, j1)) = tri.cells else {
                        // Reaches behind (or to the side of) the light: every cell.
                        for (m, cell) in cells.iter_mut().enumerate() {
                            let l = lower(rows.start * n + m);
                            cell.lit2 = cell.lit2.min(l * l);
                        }
                        continue;
                    };
                    let p = tri.projected;
                    let area = tri.area;
                    // Edge functions of the projected triangle, oriented inwards.
                    let inside = |qx: f64, qy: f64| -> bool {
                        if !tri.solid || area == 0.0 || tri.d_min <= max_eps * 10.0 {
                            return false;
                        }
                        (0..3).all(|e| {
                            let (s, t) = (p[e], p[(e + 1) % 3]);
                            let (ex, ey) = (t.0 - s.0, t.1 - s.1);
                            let f = (ex * (qy - s.1) - ey * (qx - s.0)) * area.signum();
                            f > 1e-6 * (ex.abs() + ey.abs()) * cell
                        })
                    };
                    for j in j0.max(rows.start)..=j1.min(rows.end - 1) {
                        for i in i0..=i1 {
                            let k = j * n + i;
                            let m = k - rows.start * n;
                            let l = lower(k);
                            cells[m].lit2 = cells[m].lit2.min(l * l);
                            let (x0, y0) = (-half + i as f64 * cell, -half + j as f64 * cell);
                            let corner = [
                                inside(x0, y0),
                                inside(x0 + cell, y0),
                                inside(x0, y0 + cell),
                                inside(x0 + cell, y0 + cell),
                            ];
                            let covered = corner.iter().all(|c| *c);
                            if let Some((foot, dist)) = tri.plane
                                && dist > 0.0
                            {
                                for (slot, &(a, b)) in SAMPLES.iter().enumerate() {
                                    let holds = if slot == 0 {
                                        inside(x0 + 0.5 * cell, y0 + 0.5 * cell)
                                    } else {
                                        corner[slot - 1]
                                    };
                                    if holds {
                                        let sample = if slot == 0 { centre[k].0 } else { corner_dir(i + a, j + b) };
                                        let along = sample.dot(foot);
                                        let reach = if along > 0.0 { dist / along } else { f64::INFINITY };
                                        if reach < nearest[m][slot].0 {
                                            nearest[m][slot] = (reach, index as u32);
                                            used[index] = true;
                                        }
                                    }
                                }
                            }
                            if let (true, Some((foot, dist))) = (covered, tri.plane) {
                                let (cdir, cos_r, sin_r) = centre[k];
                                let ca = cdir.dot(foot).clamp(-1.0, 1.0);
                                let sa = (1.0 - ca * ca).sqrt();
                                let cos_min = ca * cos_r - sa * sin_r;
                                if cos_min > 1e-3 {
                                    let upper = dist / cos_min * (1.0 + 1e-9);
                                    cells[m].shadow2 = cells[m].shadow2.min(upper * upper);
                                }
                            }
                        }
                    }
                }
                used
            })
            .collect();
        // The triangles some sample's nearest hit names, numbered in order
        // (as the sequential build numbered them when first used).
        let mut compact = vec![u32::MAX; triangles.len()];
        for (index, tri) in triangles.iter().enumerate() {
            if used.iter().any(|u| u[index]) {
                compact[index] = g.tris.len() as u32;
                g.tris.push([tri.a, tri.b - tri.a, tri.c - tri.a]);
            }
        }
        for slot in nearest.iter_mut().flatten() {
            if slot.1 != u32::MAX {
                slot.1 = compact[slot.1 as usize];
            }
        }
        for (cell, cands) in g.cells.iter_mut().zip(&nearest) {
            let mut len = 0;
            for &(_, t) in cands {
                if t != u32::MAX && len < BLOCKERS && !cell.blockers[..len].contains(&t) {
                    cell.blockers[len] = t;
                    len += 1;
                }
            }
        }
        g
    }

    /// `Some(lit)` when the bounds decide whether the segment from `p` to the
    /// light is blocked, for a shadow ray that ignores hits within `eps` of
    /// either end; `None` otherwise.
    #[inline]
    fn classify(&self, p: DVec3, eps: f64) -> Option<bool> {
        let v = p - self.light;
        let z = v.dot(self.axis);
        if z.is_nan() || z <= 0.0 {
            return None;
        }
        let inv_z = 1.0 / z;
        let (gx, gy) = (v.dot(self.x) * inv_z, v.dot(self.y) * inv_z);
        let (fi, fj) = ((gx + self.half) * self.inv_cell, (gy + self.half) * self.inv_cell);
        let n = self.n as f64;
        if !(fi >= 0.0 && fi < n && fj >= 0.0 && fj < n) {
            return None;
        }
        let cell = &self.cells[fj as usize * self.n + fi as usize];
        let d2 = v.length_squared();
        if d2 < cell.lit2 {
            return Some(true);
        }
        // In shadow: the blocking triangle lies at distance ≤ √shadow2 from the
        // light, so at least `d − √shadow2` from `p`; it must be beyond `eps`
        // from both ends (its own distance from the light exceeds 10·max_eps).
        if eps > self.max_eps {
            return None;
        }
        if cell.shadow2.is_finite() {
            let s = cell.shadow2.sqrt() + 2.0 * eps;
            if d2 > s * s {
                return Some(false);
            }
        }
        // A candidate blocker crossed well inside, away from both ends.
        let d = d2.sqrt();
        let dir = -v / d;
        for &t in &cell.blockers {
            if t == u32::MAX {
                break;
            }
            if surely_crosses(p, dir, &self.tris[t as usize], 2.0 * eps, d - 2.0 * eps) {
                return Some(false);
            }
        }
        None
    }
}

/// The silhouette wedges of the scene's meshes for one light.
#[derive(Debug, Clone)]
pub struct ShadowWedges {
    projector: Projector,
    wedges: Vec<Wedge>,
    nodes: Vec<Node>,
    grid: Option<VisibilityGrid>,
    /// When every caster lies on one plane and the light is off it: the
    /// light's side `{x : n·x ≥ offset}` as `(n, offset)`, the plane itself
    /// included (offset lowered by 1e-9 relative). A shadow lies behind its
    /// caster, so nothing on that side is shadowed (a floor shadows only
    /// what is under it).
    free_side: Option<(DVec3, f64)>,
    /// Triangles inside the illumination volume.
    pub triangles_used: usize,
    /// Triangles outside it (cast nothing for this light).
    pub triangles_left_out: usize,
    /// Whether view rays may pass through the casters (a mesh the camera does
    /// not see casts shadows): then a ray's visibility of the light also
    /// changes where it crosses a caster's face, not only at wedge crossings,
    /// and the caller splits its pieces there. Default false: a view ray ends
    /// at the first caster it meets.
    pub view_rays_cross_casters: bool,
}

/// One mesh as indexed world-space triangles.
pub struct IndexedMesh<'a> {
    /// World positions.
    pub positions: &'a [DVec3],
    /// Index triples.
    pub triangles: &'a [[u32; 3]],
}

/// How far the great-circle arc between the unit vectors `u` and `v` bulges
/// beyond its chord: the sagitta `1 − cos(α/2)` (α the arc's angle), from the
/// chord `c = |u − v| = 2 sin(α/2)` as `1 − √(1 − c²/4) = (c²/4)/(1 + √(1 − c²/4))`
/// (no inverse cosine, no cancellation for short arcs). A zero vector (a point
/// at the light) gives ∞: nothing can be culled.
#[inline]
fn arc_bulge(u: DVec3, v: DVec3) -> f64 {
    if u == DVec3::ZERO || v == DVec3::ZERO {
        return f64::INFINITY;
    }
    let q = 0.25 * (u - v).length_squared();
    if q >= 1.0 { 1.0 } else { q / (1.0 + (1.0 - q).sqrt()) }
}

fn arc_box(p: &Projector, a: DVec3, b: DVec3) -> (DVec3, DVec3) {
    let (u, v) = (p.project(a), p.project(b));
    let mut lo = u.min(v);
    let mut hi = u.max(v);
    if let Projector::Point(_) = p {
        // The great-circle arc between u and v bulges beyond its chord: the
        // chord's box grown by the sagitta 1 − cos(half the arc angle).
        let bulge = arc_bulge(u, v);
        lo -= DVec3::splat(bulge + 1e-12);
        hi += DVec3::splat(bulge + 1e-12);
    } else {
        let pad = 1e-12 * (1.0 + u.abs().max(v.abs()).max_element());
        lo -= DVec3::splat(pad);
        hi += DVec3::splat(pad);
    }
    (lo, hi)
}

impl ShadowWedges {
    /// Builds the wedges of every silhouette or boundary edge of the
    /// triangles that `keep` accepts (the light's illumination volume test on
    /// a bounding sphere `(centre, radius)`).
    pub fn build(projector: Projector, meshes: &[IndexedMesh<'_>], keep: impl Fn(DVec3, f64) -> bool) -> ShadowWedges {
        let mut used = 0;
        let mut left_out = 0;
        let mut wedges = Vec::new();
        // Vertices welded by exact position, so that split vertices (UV seams)
        // do not turn interior edges into boundary edges.
        let mut weld: HashMap<[u64; 3], u32> = HashMap::new();
        let mut points: Vec<DVec3> = Vec::new();
        // Edge (lo, hi) → (net side count, any coplanar neighbour).
        let mut edges: HashMap<(u32, u32), (i32, bool)> = HashMap::new();
        // The plane of the first caster, while every caster lies on it.
        let mut plane: Option<(DVec3, f64, f64)> = None;
        let mut coplanar_casters = true;
        for mesh in meshes {
            let ids: Vec<u32> = mesh
                .positions
                .iter()
                .map(|p| {
                    let key = [p.x.to_bits(), p.y.to_bits(), p.z.to_bits()];
                    *weld.entry(key).or_insert_with(|| {
                        points.push(*p);
                        (points.len() - 1) as u32
                    })
                })
                .collect();
            for t in mesh.triangles {
                let v = [ids[t[0] as usize], ids[t[1] as usize], ids[t[2] as usize]];
                let (a, b, c) = (points[v[0] as usize], points[v[1] as usize], points[v[2] as usize]);
                if !(a.is_finite() && b.is_finite() && c.is_finite()) {
                    continue;
                }
                let centre = (a + b + c) / 3.0;
                let radius = (a - centre).length().max((b - centre).length()).max((c - centre).length());
                if !keep(centre, radius) {
                    left_out += 1;
                    continue;
                }
                used += 1;
                if coplanar_casters {
                    match plane {
                        None => match (b - a).cross(c - a).try_normalize() {
                            Some(n) => plane = Some((n, n.dot(a), 1e-9 * (1.0 + a.abs().max_element() + radius))),
                            None => coplanar_casters = false,
                        },
                        Some((n, off, eps)) => {
                            coplanar_casters = [a, b, c].iter().all(|p| (n.dot(*p) - off).abs() <= eps);
                        }
                    }
                }
                for k in 0..3 {
                    let (i, j, o) = (v[k], v[(k + 1) % 3], v[(k + 2) % 3]);
                    if i == j {
                        continue;
                    }
                    let (lo, hi) = if i < j { (i, j) } else { (j, i) };
                    let (pa, pb, po) = (points[lo as usize], points[hi as usize], points[o as usize]);
                    let m = wedge_normal(&projector, pa, pb);
                    let side = (po - pa).dot(m);
                    let e = edges.entry((lo, hi)).or_insert((0, false));
                    if side > 0.0 {
                        e.0 += 1;
                    } else if side < 0.0 {
                        e.0 -= 1;
                    } else {
                        e.1 = true;
                    }
                }
            }
        }
        for ((lo, hi), (net, coplanar)) in edges {
            if net != 0 || coplanar {
                let (a, b) = (points[lo as usize], points[hi as usize]);
                let m = wedge_normal(&projector, a, b);
                if m.length_squared() > 0.0 {
                    wedges.push(Wedge { a, b, m });
                }
            }
        }
        // The light's side of the casters' one plane, if it has one.
        let free_side = plane.filter(|_| coplanar_casters).and_then(|(n, off, eps)| {
            let side = match projector {
                Projector::Point(light) => n.dot(light) - off,
                Projector::Directional(to_light) => n.dot(to_light) * (1.0 + off.abs()),
            };
            if side > eps {
                Some((n, off - eps))
            } else if side < -eps {
                Some((-n, -off - eps))
            } else {
                None
            }
        });
        let mut s = ShadowWedges {
            projector,
            wedges,
            nodes: Vec::new(),
            grid: None,
            free_side,
            triangles_used: used,
            triangles_left_out: left_out,
            view_rays_cross_casters: false,
        };
        s.build_bvh();
        s
    }

    /// Adds the visibility grid of a point light (see the module
    /// documentation) with unit `axis` and frame `(x, y)` whose light reaches
    /// at most `half_angle` rad off the axis, over every triangle of
    /// `meshes`; nothing for a parallel light or a reach of 80° or more.
    pub fn with_visibility_grid(mut self, axis: DVec3, x: DVec3, y: DVec3, half_angle: f64, meshes: &[IndexedMesh<'_>]) -> Self {
        if let Projector::Point(light) = self.projector
            && half_angle.is_finite()
            && (0.0..80f64.to_radians()).contains(&half_angle)
            && self.triangles_used > 0
        {
            self.grid = Some(VisibilityGrid::build(light, axis, x, y, half_angle, meshes));
        }
        self
    }

    /// Whether the grid decides that the segment from `p` to the light is
    /// free (`Some(true)`) or blocked (`Some(false)`) for a shadow ray that
    /// ignores hits within `eps` of either end; `None`: a shadow ray is needed.
    #[inline]
    pub fn known_visibility(&self, p: DVec3, eps: f64) -> Option<bool> {
        self.grid.as_ref().and_then(|g| g.classify(p, eps))
    }

    /// Number of kept (silhouette or boundary) edges.
    pub fn wedge_count(&self) -> usize {
        self.wedges.len()
    }

    fn build_bvh(&mut self) {
        let n = self.wedges.len();
        if n == 0 {
            return;
        }
        let boxes: Vec<(DVec3, DVec3)> = self.wedges.iter().map(|w| arc_box(&self.projector, w.a, w.b)).collect();
        let mut order: Vec<u32> = (0..n as u32).collect();
        let mut nodes = vec![Node {
            min: DVec3::ZERO,
            max: DVec3::ZERO,
            first: 0,
            count: 0,
        }];
        // (node index, start, end) work list.
        let mut work = vec![(0usize, 0usize, n)];
        while let Some((ni, s, e)) = work.pop() {
            let (mut lo, mut hi) = (DVec3::splat(f64::INFINITY), DVec3::splat(f64::NEG_INFINITY));
            for &k in &order[s..e] {
                lo = lo.min(boxes[k as usize].0);
                hi = hi.max(boxes[k as usize].1);
            }
            nodes[ni].min = lo;
            nodes[ni].max = hi;
            if e - s <= 4 {
                nodes[ni].first = s as u32;
                nodes[ni].count = (e - s) as u32;
                continue;
            }
            let axis = (hi - lo).max_position();
            let mid = s + (e - s) / 2;
            order[s..e].select_nth_unstable_by(mid - s, |x, y| {
                let cx = boxes[*x as usize].0[axis] + boxes[*x as usize].1[axis];
                let cy = boxes[*y as usize].0[axis] + boxes[*y as usize].1[axis];
                cx.total_cmp(&cy)
            });
            let left = nodes.len();
            nodes.push(nodes[ni]);
            nodes.push(nodes[ni]);
            nodes[ni].first = left as u32;
            nodes[ni].count = 0;
            work.push((left, s, mid));
            work.push((left + 1, mid, e));
        }
        self.wedges = order.iter().map(|k| self.wedges[*k as usize]).collect();
        self.nodes = nodes;
    }

    /// Appends to `out` the parameters `t ∈ (t0, t1)` where `o + t·d` crosses a kept wedge.
    pub fn crossings(&self, o: DVec3, d: DVec3, t0: f64, t1: f64, out: &mut Vec<f64>) {
        if self.nodes.is_empty() || t1 <= t0 {
            return;
        }
        // The view interval in direction space: its plane and its box.
        let end = |t: f64| -> DVec3 {
            if t.is_finite() {
                self.projector.project(o + d * t)
            } else {
                match self.projector {
                    Projector::Point(_) => d,
                    // A parallel light's projection of an infinite ray is unbounded.
                    Projector::Directional(l) => (d - l * d.dot(l)) * 1e300,
                }
            }
        };
        let (pa, pb) = (end(t0), end(t1));
        let (plane_n, plane_p) = match self.projector {
            Projector::Point(l) => ((o - l).cross(d), DVec3::ZERO),
            Projector::Directional(to_l) => (d.cross(to_l), self.projector.project(o)),
        };
        let (mut qlo, mut qhi) = (pa.min(pb), pa.max(pb));
        if let Projector::Point(_) = self.projector {
            let bulge = arc_bulge(pa, pb) + 1e-9;
            qlo -= DVec3::splat(bulge);
            qhi += DVec3::splat(bulge);
        } else {
            qlo -= DVec3::splat(1e-9 * (1.0 + qlo.abs().max_element()));
            qhi += DVec3::splat(1e-9 * (1.0 + qhi.abs().max_element()));
        }
        let degenerate_plane = plane_n.length_squared() <= 1e-300;
        let mut stack = [0u32; 64];
        let mut sp = 1;
        while sp > 0 {
            sp -= 1;
            let node = &self.nodes[stack[sp] as usize];
            if node.max.x < qlo.x
                || node.min.x > qhi.x
                || node.max.y < qlo.y
                || node.min.y > qhi.y
                || node.max.z < qlo.z
                || node.min.z > qhi.z
            {
                continue;
            }
            if !degenerate_plane {
                // Straddle test of the box against the arc's plane.
                let c = 0.5 * (node.min + node.max) - plane_p;
                let h = 0.5 * (node.max - node.min);
                let dist = plane_n.dot(c);
                let reach = plane_n.abs().dot(h);
                if dist.abs() > reach * (1.0 + 1e-9) + 1e-300 {
                    continue;
                }
            }
            if node.count > 0 {
                for w in &self.wedges[node.first as usize..(node.first + node.count) as usize] {
                    if let Some(t) = self.cross(w, o, d)
                        && t > t0
                        && t < t1
                    {
                        out.push(t);
                    }
                }
            } else if sp + 2 <= stack.len() {
                stack[sp] = node.first;
                stack[sp + 1] = node.first + 1;
                sp += 2;
            }
        }
    }

    /// Where the ray crosses the wedge, if it does.
    #[inline]
    fn cross(&self, w: &Wedge, o: DVec3, d: DVec3) -> Option<f64> {
        let denom = d.dot(w.m);
        if denom == 0.0 {
            return None;
        }
        let t = (w.a - o).dot(w.m) / denom;
        let x = o + d * t;
        match self.projector {
            Projector::Point(l) => {
                let (ea, eb, p) = (w.a - l, w.b - l, x - l);
                // Within the angle from the light between the edge's ends …
                if ea.cross(p).dot(w.m) < 0.0 || p.cross(eb).dot(w.m) < 0.0 {
                    return None;
                }
                // … and beyond the edge: on the other side of the edge line from the light.
                let e = eb - ea;
                let s_p = e.cross(p - ea).dot(w.m);
                let s_l = e.cross(-ea).dot(w.m);
                if s_p * s_l >= 0.0 {
                    return None;
                }
                Some(t)
            }
            Projector::Directional(to_l) => {
                // Within the strip swept by the edge along the light …
                let e = w.b - w.a;
                let along = (x - w.a).dot(e) - (x - w.a).dot(to_l) * e.dot(to_l);
                let len2 = e.length_squared() - e.dot(to_l) * e.dot(to_l);
                if along < 0.0 || along > len2 {
                    return None;
                }
                // … and on the side away from the light.
                let side = e.cross(x - w.a).dot(w.m);
                let light_side = e.cross(to_l).dot(w.m);
                if side * light_side >= 0.0 {
                    return None;
                }
                Some(t)
            }
        }
    }

    /// Whether the point is lit: the segment to the light crosses no triangle.
    #[inline]
    pub fn visible(&self, bvh: &Bvh, p: DVec3) -> bool {
        let (dir, dist) = self.projector.towards_light(p);
        if !dir.is_finite() {
            return true;
        }
        let eps = 1e-9 * (1.0 + p.abs().max_element());
        !bvh.any_hit(p, dir, eps, if dist.is_finite() { dist - eps } else { f64::INFINITY })
    }

    /// Splits `[t0, t1]` at the wedge crossings and appends the pieces that
    /// `visible` accepts at their midpoints to `out`, merging neighbours;
    /// returns the number of visibility tests (shadow rays).
    #[allow(clippy::too_many_arguments)]
    pub fn lit_segments(
        &self,
        o: DVec3,
        d: DVec3,
        t0: f64,
        t1: f64,
        scratch: &mut Vec<f64>,
        out: &mut Vec<(f64, f64)>,
        visible: &dyn Fn(DVec3) -> bool,
    ) -> usize {
        // On the light's side of the one plane holding every caster: lit,
        // points on the plane (a floor hit) included — the visibility test
        // ignores hits within the same margin.
        if let Some((n, off)) = self.free_side {
            let on_side = |t: f64| if t.is_finite() { n.dot(o + d * t) >= off } else { n.dot(d) > 0.0 };
            if on_side(t0) && on_side(t1) && (t1.is_finite() || n.dot(o + d * t0) >= off) {
                match out.last_mut() {
                    Some(last) if last.1 >= t0 => last.1 = t1,
                    _ => out.push((t0, t1)),
                }
                return 0;
            }
        }
        scratch.clear();
        scratch.push(t0);
        self.crossings(o, d, t0, t1, scratch);
        scratch.push(t1);
        scratch[1..].sort_by(f64::total_cmp);
        scratch.dedup();
        let mut rays = 0;
        for k in 0..scratch.len() - 1 {
            let (a, b) = (scratch[k], scratch[k + 1]);
            if b <= a {
                continue;
            }
            let mid = if b.is_finite() { 0.5 * (a + b) } else { a + 1.0 + a.abs() };
            rays += 1;
            if visible(o + d * mid) {
                match out.last_mut() {
                    Some(last) if last.1 >= a => last.1 = b,
                    _ => out.push((a, b)),
                }
            }
        }
        rays
    }
}

fn wedge_normal(p: &Projector, a: DVec3, b: DVec3) -> DVec3 {
    match p {
        Projector::Point(l) => (a - *l).cross(b - *l),
        Projector::Directional(to_l) => (b - a).cross(*to_l),
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::geometry::bvh::Triangle;
    use crate::geometry::cube;

    /// The visibility grid never contradicts a shadow ray, and decides most points.
    /// A BVH over every triangle of `meshes`.
    fn bvh_of(meshes: &[IndexedMesh<'_>]) -> Bvh {
        let tris = meshes
            .iter()
            .flat_map(|m| {
                m.triangles
                    .iter()
                    .map(|t| Triangle::new(m.positions[t[0] as usize], m.positions[t[1] as usize], m.positions[t[2] as usize]))
            })
            .collect();
        Bvh::build(tris)
    }

    #[test]
    fn visibility_grid_agrees_with_shadow_rays() {
        let (p1, t1) = cube(DVec3::new(0.0, 0.0, 1.0), 0.5);
        let (p2, t2) = cube(DVec3::new(0.8, 0.3, 0.2), 0.3);
        // A large floor (two triangles) and a tilted open quad.
        let p3 = vec![
            DVec3::new(-20.0, -20.0, -0.5),
            DVec3::new(20.0, -20.0, -0.5),
            DVec3::new(20.0, 20.0, -0.5),
            DVec3::new(-20.0, 20.0, -0.5),
            DVec3::new(-1.5, -1.0, 1.5),
            DVec3::new(-0.5, -1.0, 1.5),
            DVec3::new(-0.5, 0.0, 1.9),
            DVec3::new(-1.5, 0.0, 1.9),
        ];
        let t3 = vec![[0, 1, 2], [0, 2, 3], [4, 5, 6], [4, 6, 7]];
        // A finely tessellated UV sphere (triangles about two grid cells wide).
        let (rings, segs) = (48usize, 96usize);
        let mut p4 = Vec::new();
        for i in 0..=rings {
            let th = std::f64::consts::PI * i as f64 / rings as f64;
            for j in 0..segs {
                let ph = 2.0 * std::f64::consts::PI * j as f64 / segs as f64;
                p4.push(DVec3::new(-0.9, 0.8, 1.2) + 0.6 * DVec3::new(th.sin() * ph.cos(), th.sin() * ph.sin(), th.cos()));
            }
        }
        let mut t4 = Vec::new();
        for i in 0..rings {
            for j in 0..segs {
                let (a, b) = ((i * segs + j) as u32, (i * segs + (j + 1) % segs) as u32);
                let (c, d) = (a + segs as u32, b + segs as u32);
                t4.push([a, c, b]);
                t4.push([b, c, d]);
            }
        }
        let meshes = [
            IndexedMesh {
                positions: &p1,
                triangles: &t1,
            },
            IndexedMesh {
                positions: &p2,
                triangles: &t2,
            },
            IndexedMesh {
                positions: &p3,
                triangles: &t3,
            },
            IndexedMesh {
                positions: &p4,
                triangles: &t4,
            },
        ];
        let bvh = bvh_of(&meshes);
        let light = DVec3::new(0.1, -0.2, 4.0);
        let axis = (DVec3::new(0.2, 0.1, 0.0) - light).normalize();
        let x = axis.any_orthonormal_vector();
        let y = axis.cross(x);
        let half = 40f64.to_radians();
        let sw = ShadowWedges::build(Projector::Point(light), &meshes, |_, _| true).with_visibility_grid(axis, x, y, half, &meshes);
        assert!(sw.grid.is_some());
        let mut rng = 5u64;
        let mut next = || {
            rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((rng >> 11) as f64) / ((1u64 << 53) as f64)
        };
        let (mut decided, mut lit_known, mut shadow_known, mut total) = (0, 0, 0, 0);
        for _ in 0..200_000 {
            // A direction inside the cone, a distance up to past the floor.
            let (th, ph) = (half * next().sqrt(), 2.0 * std::f64::consts::PI * next());
            let w = axis * th.cos() + (x * ph.cos() + y * ph.sin()) * th.sin();
            let p = light + w * (0.05 + 7.0 * next());
            total += 1;
            let eps = 1e-9 * (1.0 + p.abs().max_element());
            if let Some(known) = sw.known_visibility(p, eps) {
                decided += 1;
                if known {
                    lit_known += 1;
                } else {
                    shadow_known += 1;
                }
                assert_eq!(known, sw.visible(&bvh, p), "grid contradicts the shadow ray at {p}");
            }
        }
        println!("decided {decided} of {total} ({lit_known} lit, {shadow_known} in shadow)");
        assert!(decided > total * 3 / 4, "decided {decided} of {total}");
        assert!(shadow_known > total / 10 && lit_known > total / 10);
    }

    /// The lit segments agree with dense point sampling of visibility.
    #[test]
    fn lit_segments_match_sampled_visibility() {
        let (p1, t1) = cube(DVec3::new(0.0, 0.0, 1.0), 0.5);
        let (p2, t2) = cube(DVec3::new(0.8, 0.3, 0.2), 0.3);
        // An open quad (boundary edges only).
        let p3 = vec![
            DVec3::new(-1.5, -1.0, 1.5),
            DVec3::new(-0.5, -1.0, 1.5),
            DVec3::new(-0.5, 0.0, 1.7),
            DVec3::new(-1.5, 0.0, 1.7),
        ];
        let t3 = vec![[0, 1, 2], [0, 2, 3]];
        let meshes = [
            IndexedMesh {
                positions: &p1,
                triangles: &t1,
            },
            IndexedMesh {
                positions: &p2,
                triangles: &t2,
            },
            IndexedMesh {
                positions: &p3,
                triangles: &t3,
            },
        ];
        let bvh = bvh_of(&meshes);
        for projector in [
            Projector::Point(DVec3::new(0.1, -0.2, 4.0)),
            Projector::Directional(DVec3::new(0.2, 0.1, 1.0).normalize()),
        ] {
            let sw = ShadowWedges::build(projector, &meshes, |_, _| true);
            assert!(sw.wedge_count() > 0 && sw.wedge_count() < 36 + 4);
            let mut rng = 99u64;
            let mut next = || {
                rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((rng >> 11) as f64) / ((1u64 << 53) as f64) * 2.0 - 1.0
            };
            let (mut scratch, mut out) = (Vec::new(), Vec::new());
            let mut changes = 0;
            for _ in 0..400 {
                let o = DVec3::new(next() * 3.0, next() * 3.0, -1.0 + next() * 0.5);
                let d = DVec3::new(next() * 0.5, next() * 0.5, 1.0).normalize();
                let t_end = bvh.closest_hit(o, d, 0.0, 6.0).map(|h| h.t).unwrap_or(6.0);
                out.clear();
                sw.lit_segments(o, d, 0.0, t_end, &mut scratch, &mut out, &|x| sw.visible(&bvh, x));
                changes += out.len();
                for k in 0..300 {
                    let t = t_end * (k as f64 + 0.5) / 300.0;
                    let x = o + d * t;
                    let lit = sw.visible(&bvh, x);
                    let listed = out.iter().any(|(a, b)| t >= *a && t <= *b);
                    let near = out.iter().any(|(a, b)| (t - a).abs() < 1e-7 || (t - b).abs() < 1e-7);
                    assert!(near || lit == listed, "t={t} lit={lit} listed={listed} {out:?}");
                }
            }
            assert!(changes > 100);
        }
    }

    /// Casters on one plane (a floor with a hole's worth of triangles, and
    /// a tilted quad for contrast) shadow only the far side of it: segments
    /// on the light's side (ending on the floor included) are lit whole with
    /// no shadow ray, and segments that go under the floor agree with
    /// sampled visibility, for a point and a parallel light.
    #[test]
    fn coplanar_casters_shadow_only_the_far_side() {
        // A floor at z = 0.5 made of four triangles around a square hole.
        let p = vec![
            DVec3::new(-2.0, -2.0, 0.5),
            DVec3::new(2.0, -2.0, 0.5),
            DVec3::new(2.0, 2.0, 0.5),
            DVec3::new(-2.0, 2.0, 0.5),
            DVec3::new(-0.5, -0.5, 0.5),
            DVec3::new(0.5, -0.5, 0.5),
            DVec3::new(0.5, 0.5, 0.5),
            DVec3::new(-0.5, 0.5, 0.5),
        ];
        let t = vec![
            [0, 1, 5],
            [0, 5, 4],
            [1, 2, 6],
            [1, 6, 5],
            [2, 3, 7],
            [2, 7, 6],
            [3, 0, 4],
            [3, 4, 7],
        ];
        let meshes = [IndexedMesh {
            positions: &p,
            triangles: &t,
        }];
        let bvh = bvh_of(&meshes);
        for projector in [
            Projector::Point(DVec3::new(0.3, -0.2, 3.0)),
            Projector::Directional(DVec3::new(0.2, 0.1, 1.0).normalize()),
        ] {
            let sw = ShadowWedges::build(projector, &meshes, |_, _| true);
            assert!(sw.free_side.is_some(), "{projector:?}");
            let mut rng = 7u64;
            let mut next = || {
                rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
                ((rng >> 11) as f64) / ((1u64 << 53) as f64) * 2.0 - 1.0
            };
            let (mut scratch, mut out) = (Vec::new(), Vec::new());
            let (mut above, mut below) = (0, 0);
            for _ in 0..400 {
                let o = DVec3::new(next() * 3.0, next() * 3.0, 1.0 + next() * 0.4);
                let d = DVec3::new(next() * 0.6, next() * 0.6, -1.0).normalize();
                // Ends on the floor (or falls through the hole, or past it).
                let t_end = bvh.closest_hit(o, d, 0.0, 6.0).map(|h| h.t).unwrap_or(6.0);
                out.clear();
                let rays = sw.lit_segments(o, d, 0.0, t_end, &mut scratch, &mut out, &|x| sw.visible(&bvh, x));
                if (o + d * t_end).z >= 0.5 - 1e-9 {
                    above += 1;
                    assert_eq!(rays, 0);
                    assert_eq!(out, vec![(0.0, t_end)]);
                } else {
                    below += 1;
                }
                for k in 0..300 {
                    let t = t_end * (k as f64 + 0.5) / 300.0;
                    let lit = sw.visible(&bvh, o + d * t);
                    let listed = out.iter().any(|(a, b)| t >= *a && t <= *b);
                    let near = out.iter().any(|(a, b)| (t - a).abs() < 1e-7 || (t - b).abs() < 1e-7);
                    assert!(near || lit == listed, "t={t} lit={lit} listed={listed} {out:?}");
                }
            }
            assert!(above > 100 && below > 20, "{above} above, {below} below");
        }
        // Casters off one plane: no shortcut.
        let (pc, tc) = cube(DVec3::new(0.0, 0.0, 1.0), 0.5);
        let cube_mesh = [IndexedMesh {
            positions: &pc,
            triangles: &tc,
        }];
        assert!(
            ShadowWedges::build(Projector::Point(DVec3::new(0.0, 0.0, 4.0)), &cube_mesh, |_, _| true)
                .free_side
                .is_none()
        );
    }
}
