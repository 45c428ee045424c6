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
//! wedges plus one shadow ray per piece.
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
//! **Left out.** Triangles outside the light's illumination volume (tested
//! with their bounding spheres) contribute no edges; the count is reported.

use crate::geometry::bvh::Bvh;
use glam::DVec3;
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

/// The silhouette wedges of the scene's meshes for one light.
#[derive(Debug, Clone)]
pub struct ShadowWedges {
    projector: Projector,
    wedges: Vec<Wedge>,
    nodes: Vec<Node>,
    /// Triangles inside the illumination volume.
    pub triangles_used: usize,
    /// Triangles outside it (cast nothing for this light).
    pub triangles_left_out: usize,
}

/// One mesh as indexed world-space triangles.
pub struct IndexedMesh<'a> {
    /// World positions.
    pub positions: &'a [DVec3],
    /// Index triples.
    pub triangles: &'a [[u32; 3]],
}

fn arc_box(p: &Projector, a: DVec3, b: DVec3) -> (DVec3, DVec3) {
    let (u, v) = (p.project(a), p.project(b));
    let mut lo = u.min(v);
    let mut hi = u.max(v);
    if let Projector::Point(_) = p {
        // The great-circle arc between u and v bulges beyond its chord: the
        // chord's box grown by the sagitta 1 − cos(half the arc angle).
        let half = 0.5 * u.angle_between(v);
        let bulge = 1.0 - half.cos();
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
        let mut s = ShadowWedges {
            projector,
            wedges,
            nodes: Vec::new(),
            triangles_used: used,
            triangles_left_out: left_out,
        };
        s.build_bvh();
        s
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
            let half = 0.5 * pa.angle_between(pb);
            let bulge = 1.0 - half.cos() + 1e-9;
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

    fn cube(c: DVec3, h: f64) -> (Vec<DVec3>, Vec<[u32; 3]>) {
        let mut p = Vec::new();
        for i in 0..8 {
            p.push(
                c + DVec3::new(
                    if i & 1 == 0 { -h } else { h },
                    if i & 2 == 0 { -h } else { h },
                    if i & 4 == 0 { -h } else { h },
                ),
            );
        }
        let t = vec![
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
        (p, t)
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
        let mut tris = Vec::new();
        for m in &meshes {
            for t in m.triangles {
                tris.push(Triangle::new(
                    m.positions[t[0] as usize],
                    m.positions[t[1] as usize],
                    m.positions[t[2] as usize],
                ));
            }
        }
        let bvh = Bvh::build(tris);
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
}
