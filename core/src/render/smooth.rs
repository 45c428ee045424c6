//! Pixels interpolated where the in-scatter image is smooth: inside a beam,
//! away from every edge, most view rays need no integral of their own.
//!
//! **When.** The in-scatter of a view ray is an integral along it whose
//! integrand is smooth except where the ray crosses a cone on which the
//! light's distribution has a kink or ends (the illumination cone, a
//! Cycles spot's blend cone: [`crate::light::PointSource::kinks`]) or a
//! window's prism, and whose limits are the ray's start, its end (a surface
//! or the clip end) and those crossings. As a function of the pixel
//! position it is therefore smooth (analytic in the crossing points) over
//! any set of rays that
//!
//! 1. end on the same plane (or on none): [`Planes`] groups a mesh's
//!    triangles by plane, so the two triangles of a floor are one surface;
//! 2. cross the same cones and prisms the same way — their **topology
//!    code** ([`super::stage::StageLights::topology`]): per cone, how many
//!    intervals of the ray lie inside it and whether the first starts at the
//!    ray's start and the last ends at its end;
//! 3. are not shadowed: every light they cross has no shadow casters, or
//!    casters on one plane with the light and the eye on the same side, and
//!    the rays end on the eye's side of it, or have no end and do not head
//!    towards it (a caster shadows only the far side of its plane), or
//!    casters on a few planes (a box on a floor) and the rays enter none of
//!    the planes' shadow pyramids ([`ShadowPyramid`]), or casters on many
//!    planes (a faceted sphere) and the rays enter neither the largest
//!    planes' pyramids (its floor) nor the shadow region of a ball around
//!    the rest ([`ShadowBall`]) — part of the code too;
//!
//! in media without internal boundaries (homogeneous without bounds, height
//! fog) and lights whose distribution is smooth between its kinks (Blender
//! point and spot lights, no IES). Not near a point light's image, where
//! the in-scatter has its 1/r peak ([`LIGHT_IMAGE_MARGIN`]), and not for
//! rays crossing a window light's prism: its flat faces meet in edges, and
//! where a ray's entry or exit face changes the in-scatter has a kink that
//! the code (intervals only) does not see — a window shaft interpolated
//! across one was off by 1 % against an estimate of 0.5 %; such rays count
//! as possibly shadowed (below) and are traced.
//!
//! A change of code is where the image has its kinks and its sub-pixel
//! features (a spot's blend zone is often narrower than a pixel: where the
//! floor point crosses the cone, the in-scatter's slope jumps at pixel
//! scale). The code of the pixel itself is computed (one surface hit and
//! the cone intervals, a fraction of the integral's cost) and must equal
//! the code of all six samples it is interpolated from: a feature that
//! crosses the pixel's ray or a sample's is never interpolated over, as
//! with every pixel traced.
//!
//! **How.** In two levels, coarse to fine. Pixels whose `x` and `y` are
//! multiples of 4 are traced. Level 1 fills the other pixels with even `x`
//! and `y`: on rows ≡ 0 (mod 4) the pixels ≡ 2 along `x` from the six
//! samples at ±2, ±6, ±10 px, then the rows ≡ 2 along `y` from the six rows
//! at ±2, ±6, ±10. Level 2 fills the rest the same way from the even
//! pixels at ±1, ±3, ±5 (a tensor-product interpolant at each level; a
//! pixel that fails at level 1 is traced and serves level 2 as a traced
//! sample). Below, in units of the level's sample spacing `h` (4 or 2
//! px). The value is the 4-point cubic on the
//! inner four, `(−f₋₃ + 9f₋₁ + 9f₁ − f₃)/16`, whose error for a smooth
//! image is `(3/128)·Δ⁴f`, `Δ⁴` the fourth difference at spacing `h`. The
//! estimate is `(3/256)(|Δ⁴_L| + |Δ⁴_R|)` over the two fourth differences
//! the six samples give, charged [`SAFETY`] = 8 times. Without the factor it
//! bounds the error of the shapes a code-constant stretch of image can have
//! (unit tests): a singularity anywhere outside the stencil (a chord `√d`
//! at a cone's silhouette, `d^{3/2}`, `d^{5/2}`: ratio ≤ 1, tending to 1 far
//! away), and a beam's edge blended by Cycles' smoothstep on either side of
//! the inner cone (ratio ≤ 0.99). Real images are not these models: in a
//! rendered scene (two coloured spots, 384×216, tolerance 0.01) one pixel
//! of 2 909 reached 2.4; at 1536×864 (narrow beam, tolerance 0.01) one of
//! 64 954 reached 7.2, beside a beam's edge on the floor where the profile
//! across the stencil is a bump whose fourth differences nearly vanish
//! (the same pixel, single level, with the factor 4 then in use). Hence the
//! factor 8, with which no interpolated pixel of the test scenes is outside
//! its estimate; it changed the number of interpolated pixels by < 2 % at
//! tolerance 0.1 and not at all at 0.4 (narrow beam, two coloured spots,
//! 768×432 and 1536×864). (Across the inner
//! cone, where the codes differ and nothing is interpolated, the same
//! model reaches 3.4.)
//! To that the stencil's own errors are added, weighted by `|wᵢ|` (an
//! interpolated value carries its error into the second pass), and the f32
//! rounding of the samples. A pixel is interpolated only when the estimate
//! is within `tolerance · |value|` in every channel — it meets the
//! tolerance by its own estimate, as a traced pixel does; otherwise it is
//! traced. A ray that crosses no light's volume has in-scatter exactly 0,
//! and so do its six samples: it is "interpolated" exactly.
//!
//! **Other layers.** Transmittance and depth are never interpolated: an
//! interpolated pixel takes them from its own ray (the surface hit its code
//! needs anyway, and the media's closed-form optical depth), bit for bit
//! what tracing it gives. Each light's in-scatter layer is interpolated from
//! that layer's six samples with the same rule, the samples' own errors
//! being those of the whole in-scatter (a traced sample's error is the sum
//! of its lights' shares); the pixel is interpolated only when every light
//! meets the tolerance too, and its stored own error is then the largest of
//! all these estimates, so that a later level's stencil is charged enough
//! for every layer. (Samples with no in-scatter from a light: the light is
//! not crossed, nor by the pixel, whose code is the same.)

use crate::geometry::bvh::Triangle;
use crate::scene::Mesh;
use glam::DVec3;
use rustc_hash::FxHashMap as HashMap;

/// Bit 62 of a stored topology code: there is a code to read (the cones'
/// bits stay below it, the shadow bit is 63).
pub const PRESENT: u64 = 1 << 62;
/// The stencil reaches this many sample spacings' halves on either side
/// (5 px at level 2, 10 px at level 1).
pub const STENCIL: usize = 5;
/// Pixels within this many pixels of a point light's image are traced
/// (twice as many at level 1).
pub const LIGHT_IMAGE_MARGIN: f64 = STENCIL as f64 + 1.0;

/// Cubic weights at the midpoint, for the samples at −3, −1, 1, 3 px.
const CUBIC: [f64; 4] = [-1.0 / 16.0, 9.0 / 16.0, 9.0 / 16.0, -1.0 / 16.0];
/// The cubic's error is charged as this many times `(3/256)(|Δ⁴_L| + |Δ⁴_R|)`.
pub const SAFETY: f64 = 8.0;
/// Relative rounding of an f32 sample.
const F32_ROUNDING: f64 = f32::EPSILON as f64;

/// Triangles per chunk of [`Planes::new_cancellable`].
const PLANE_CHUNK: usize = 1 << 16;

/// The triangles grouped by mesh and plane.
pub struct Planes {
    /// Per triangle: its group + 1, or 0 for a degenerate triangle.
    group_of: Vec<u32>,
    /// Per group: unit normal and `normal · x` on the plane.
    planes: Vec<(DVec3, f64)>,
}

impl Planes {
    /// Groups `tris` (world triangles of `meshes`, in order, as
    /// [`crate::geometry::world_triangles`] makes them) by mesh and plane.
    pub fn new(meshes: &[Mesh], tris: &[Triangle]) -> Planes {
        Self::new_cancellable(meshes, tris, &|| false).expect("a grouping never stopped completes")
    }

    /// [`Planes::new`] that gives up once `stop()` is true (asked between
    /// chunks of [`PLANE_CHUNK`] triangles): `None` then. Each chunk's planes
    /// are computed in parallel (the degeneracy test and the normal are most
    /// of the work), then numbered in order, so the groups are the same as
    /// one sequential pass's. (A curved mesh of 720 000 triangles, a group
    /// each: 180–216 ms in one pass.)
    pub fn new_cancellable(meshes: &[Mesh], tris: &[Triangle], stop: &(dyn Fn() -> bool + Sync)) -> Option<Planes> {
        use rayon::prelude::*;
        let mut key_of: HashMap<(u32, [i64; 4]), u32> = HashMap::default();
        let mut planes: Vec<(DVec3, f64)> = Vec::new();
        let mut group_of = vec![0u32; tris.len()];
        // The mesh of each triangle, by runs.
        let mut mesh_of: Vec<(usize, u32)> = Vec::with_capacity(meshes.len());
        let mut start = 0usize;
        for (mi, m) in meshes.iter().enumerate() {
            mesh_of.push((start, mi as u32));
            start += m.triangles.len();
        }
        let mesh_at = |i: usize| mesh_of[mesh_of.partition_point(|&(s, _)| s <= i) - 1].1;
        // Per mesh, the scale of the offsets' key: one for all its
        // triangles, so that two triangles of one face share their key
        // whichever vertex comes first (with the first vertex's own scale,
        // a rotated box's faces split in two).
        let mesh_scale: Vec<f64> = mesh_of
            .iter()
            .zip(meshes)
            .map(|(&(s, _), m)| {
                let end = (s + m.triangles.len()).min(tris.len());
                let far = tris
                    .get(s.min(end)..end)
                    .unwrap_or(&[])
                    .iter()
                    .flat_map(|t| t.v)
                    .fold(0.0, |m, v| v.abs().max_element().max(m));
                1.0 + far
            })
            .collect();
        let plane_of = |i: usize, t: &Triangle| -> Option<(DVec3, f64, [i64; 4])> {
            if t.is_degenerate() {
                return None;
            }
            let [a, b, c] = t.v;
            let mut n = (b - a).cross(c - a).try_normalize()?;
            // One orientation per plane: the largest component positive.
            if n[n.abs().max_position()] < 0.0 {
                n = -n;
            }
            let offset = n.dot(a);
            let scale = mesh_scale[mesh_at(i) as usize];
            let q = |v: f64| (v * 1e9).round() as i64;
            Some((n, offset, [q(n.x), q(n.y), q(n.z), q(offset / scale)]))
        };
        let mut found: Vec<Option<(DVec3, f64, [i64; 4])>> = Vec::new();
        for first in (0..tris.len().min(start)).step_by(PLANE_CHUNK) {
            if stop() {
                return None;
            }
            let last = (first + PLANE_CHUNK).min(tris.len()).min(start);
            tris[first..last]
                .par_iter()
                .enumerate()
                .map(|(k, t)| plane_of(first + k, t))
                .collect_into_vec(&mut found);
            for (k, f) in found.iter().enumerate() {
                let Some((n, offset, key)) = *f else { continue };
                let i = first + k;
                let g = *key_of.entry((mesh_at(i), key)).or_insert_with(|| {
                    planes.push((n, offset));
                    planes.len() as u32 - 1
                });
                group_of[i] = g + 1;
            }
        }
        Some(Planes { group_of, planes })
    }

    /// The group + 1 of triangle `i` (0: degenerate or unknown).
    pub fn group_of(&self, triangle: u32) -> u32 {
        self.group_of.get(triangle as usize).copied().unwrap_or(0)
    }

    /// The plane of group + 1 `group` (from [`Planes::group_of`], > 0):
    /// unit normal and `normal · x` on it.
    pub fn plane(&self, group: u32) -> (DVec3, f64) {
        self.planes[group as usize - 1]
    }

    /// Number of groups (they are numbered `1..=group_count()`).
    pub fn group_count(&self) -> usize {
        self.planes.len()
    }
}

/// Where a light's shadow casters lie.
#[derive(Debug, Clone, PartialEq)]
pub enum Casters {
    /// No triangle may touch the light's volume.
    None,
    /// All of them lie on this plane (unit normal towards the eye, `n·x =
    /// offset`), with the light on the eye's side: they shadow only the far
    /// side.
    Plane {
        /// Unit normal, pointing to the eye's side.
        normal: DVec3,
        /// `normal · x` on the plane, m.
        offset: f64,
    },
    /// On a few planes (at most [`MAX_PYRAMIDS`]): each plane's casters
    /// shadow only what lies inside its [`ShadowPyramid`].
    Pyramids(Vec<ShadowPyramid>),
    /// On more planes (a curved mesh: a plane per facet), or on a plane
    /// through the light: the largest planes keep their pyramids (a floor),
    /// the other triangles shadow only what lies inside their [`ShadowBall`].
    PyramidsAndBall(Vec<ShadowPyramid>, ShadowBall),
    /// Anywhere else: the light may be shadowed between two samples.
    Any,
}

/// The most caster planes per light that [`Casters::Pyramids`] tests a
/// ray against one by one (a box and its floor are 7); more are [`Casters::Any`].
pub const MAX_PYRAMIDS: usize = 16;

/// The most side planes of all of a light's [`ShadowPyramid`]s together
/// (a ray is tested against each; a box's faces have 4 each, a disc of 64
/// segments 64).
pub const MAX_PYRAMID_SIDES: usize = 128;

/// Where one plane's caster triangles can shadow a point light: beyond
/// their plane (on the side away from the light) and inside the pyramid
/// from the light over the convex hull of their vertices. A point there is
/// the only kind whose segment to the light can cross the triangles, so the
/// region holds their shadow: exactly for a convex polygon (a box's face),
/// a superset otherwise. A closed occluder's shadow is the union of its
/// faces' regions.
#[derive(Debug, Clone, PartialEq)]
pub struct ShadowPyramid {
    /// Half-spaces `n · x ≥ offset` through the light, one per hull edge
    /// (unit `n`, pointing inwards; `offset` already lowered by a rounding
    /// margin, so that the test is conservative).
    sides: Vec<(DVec3, f64)>,
    /// The plane: unit normal pointing away from the light, `n · x` on it.
    beyond: (DVec3, f64),
}

impl ShadowPyramid {
    /// The pyramid of the triangles with vertices `points` (all on the plane
    /// `normal · x = offset`, unit `normal`) from the light at `apex`;
    /// `None` when the light lies on the plane (within `margin`, m).
    fn new(points: &[DVec3], (normal, offset): (DVec3, f64), apex: DVec3, margin: f64) -> Option<ShadowPyramid> {
        let side = normal.dot(apex) - offset;
        if side.abs() <= margin || !side.is_finite() {
            return None;
        }
        let beyond = if side > 0.0 { (-normal, -offset) } else { (normal, offset) };
        // The convex hull in the plane (Andrew's monotone chain).
        let e1 = normal.any_orthonormal_vector();
        let e2 = normal.cross(e1);
        let mut flat: Vec<(f64, f64, DVec3)> = points.iter().map(|&p| (p.dot(e1), p.dot(e2), p)).collect();
        flat.sort_by(|a, b| a.0.total_cmp(&b.0).then(a.1.total_cmp(&b.1)));
        let turn =
            |o: &(f64, f64, DVec3), a: &(f64, f64, DVec3), b: &(f64, f64, DVec3)| (a.0 - o.0) * (b.1 - o.1) - (a.1 - o.1) * (b.0 - o.0);
        let mut hull: Vec<(f64, f64, DVec3)> = Vec::with_capacity(flat.len() + 1);
        for pass in 0..2 {
            let start = hull.len();
            let iter: Box<dyn Iterator<Item = &(f64, f64, DVec3)>> = if pass == 0 {
                Box::new(flat.iter())
            } else {
                Box::new(flat.iter().rev())
            };
            for p in iter {
                while hull.len() >= start + 2 && turn(&hull[hull.len() - 2], &hull[hull.len() - 1], p) <= 0.0 {
                    hull.pop();
                }
                hull.push(*p);
            }
            hull.pop();
        }
        if hull.len() < 3 {
            return None;
        }
        let centre = hull.iter().map(|p| p.2).sum::<DVec3>() / hull.len() as f64;
        let mut sides = Vec::with_capacity(hull.len());
        for (i, a) in hull.iter().enumerate() {
            let b = &hull[(i + 1) % hull.len()];
            let mut n = (a.2 - apex).cross(b.2 - apex).try_normalize()?;
            if n.dot(centre - apex) < 0.0 {
                n = -n;
            }
            sides.push((n, n.dot(apex) - margin));
        }
        Some(ShadowPyramid { sides, beyond })
    }

    /// Whether the segment `eye + t·dir`, `0 ≤ t ≤ t_end` (`t_end` may be
    /// infinite), reaches inside the pyramid farther than `tol` (m) beyond
    /// the plane: a ray ending on the plane (a floor hit) stays outside.
    fn reached_by(&self, eye: DVec3, dir: DVec3, t_end: f64, tol: f64) -> bool {
        let (mut t0, mut t1) = (0.0f64, t_end);
        let (bn, bo) = self.beyond;
        // The plane first: most rays that miss a pyramid stay on its near side.
        for (n, offset, margin) in std::iter::once((bn, bo, -tol)).chain(self.sides.iter().map(|&(n, o)| (n, o, 0.0))) {
            // Inside: n·eye − offset + margin + t·(n·dir) ≥ 0.
            let a = n.dot(eye) - offset + margin;
            let b = n.dot(dir);
            if b > 0.0 {
                t0 = t0.max(-a / b);
            } else if b < 0.0 {
                t1 = t1.min(-a / b);
            } else if a < 0.0 {
                return false;
            }
            if t0 > t1 {
                return false;
            }
        }
        true
    }
}

/// Where triangles inside a ball (centre `c`, radius `r`) can shadow a
/// point light at distance `d > r` from `c`: a point `x` whose segment to the
/// light crosses one crosses the ball, so `x` lies in the cone from the light
/// over the ball (half-angle `asin(r/d)`) and at least `d − r` from the
/// light. That region holds the triangles' shadow; a view ray that never
/// reaches it is not shadowed by them. Coarser than the pyramids of their
/// planes, but one test per ray for any number of planes: a sphere of
/// 9 940 facets lit by a spot shadows only the rays that pass behind it.
#[derive(Debug, Clone, PartialEq)]
pub struct ShadowBall {
    /// The light, m.
    apex: DVec3,
    /// Unit vector from the light to the ball's centre.
    axis: DVec3,
    /// Cosine of the cone's half-angle, `√(d² − r²)/d`.
    cos_half: f64,
    /// `d − r`, m: nearer to the light than this, nothing is shadowed.
    near: f64,
}

impl ShadowBall {
    /// The region of the ball bounding `[lo, hi]` (a box, m) for the light
    /// at `apex`: `None` when the light is inside the ball. The ball's radius
    /// is the box's half-diagonal, grown by `margin` (m) and a relative 1e-9,
    /// so that the test is conservative under rounding, and at least
    /// [`MIN_BALL_SPREAD`] times the distance: for a ball under ~1e-8 of its
    /// distance `cos_half` rounds to 1 and the cone to its axis (an
    /// independent review found rays crossing the shadow of a ball with
    /// r/d = 1e-9 not flagged, 954 of 2 000).
    fn new(lo: DVec3, hi: DVec3, apex: DVec3, margin: f64) -> Option<ShadowBall> {
        let centre = 0.5 * (lo + hi);
        let to_centre = centre - apex;
        let d = to_centre.length();
        let r = (0.5 * (hi - lo).length() * (1.0 + 1e-9) + margin + 1e-9 * d).max(MIN_BALL_SPREAD * d);
        if d.is_nan() || d <= r || !d.is_finite() {
            return None;
        }
        Some(ShadowBall {
            apex,
            axis: to_centre / d,
            cos_half: ((d - r) * (d + r)).sqrt() / d,
            near: d - r,
        })
    }

    /// `sin` of the cone's half-angle: how much of the light's sky the ball
    /// takes (smaller is better).
    fn spread(&self) -> f64 {
        (1.0 - self.cos_half * self.cos_half).max(0.0).sqrt()
    }

    /// Whether the segment `eye + t·dir`, `0 ≤ t ≤ t_end` (unit `dir`,
    /// `t_end` may be infinite), enters the region.
    fn reached_by(&self, eye: DVec3, dir: DVec3, t_end: f64) -> bool {
        let mut inside = Vec::with_capacity(2);
        crate::light::ray_cone_intervals(eye, dir, 0.0, t_end, self.apex, self.axis, self.cos_half, &mut inside);
        // The distance to the light is convex along the ray: on an interval
        // it is largest at one of its ends.
        let far = |t: f64| {
            if t.is_finite() {
                (eye + dir * t - self.apex).length()
            } else {
                f64::INFINITY
            }
        };
        inside.iter().any(|&(a, b)| far(a).max(far(b)) >= self.near)
    }
}

/// The smallest `r/d` of a [`ShadowBall`]: the cone's `1 − cos` is then
/// 5e-13, far above the rounding of the test `v·a ≥ cos·|v|`.
const MIN_BALL_SPREAD: f64 = 1e-6;

/// A plane group's triangles touching a light: group + 1 (from
/// [`Planes::group_of`]), their vertices, their total area (m²).
type PlaneGroup = (u32, Vec<DVec3>, f64);

/// Whether any of `pyramids` is reached by the segment (see [`Casters::may_shadow`]).
fn pyramids_reached(pyramids: &[ShadowPyramid], eye: DVec3, dir: DVec3, t_end: f64) -> bool {
    // As for a plane: a hit on a caster's plane is on its near side.
    let reach = if t_end.is_finite() { t_end } else { 0.0 };
    pyramids.iter().any(|p| {
        let tol = 1e-9 * (1.0 + p.beyond.1.abs() + eye.abs().max_element() + reach);
        p.reached_by(eye, dir, t_end, tol)
    })
}

impl Casters {
    /// Which casters the triangles passing `may_touch(centre, radius)` are,
    /// for the light at `apex`.
    pub fn of(tris: &[Triangle], planes: &Planes, eye: DVec3, apex: DVec3, may_touch: impl Fn(DVec3, f64) -> bool) -> Casters {
        let margin = 1e-9 * (1.0 + eye.abs().max_element().max(apex.abs().max_element()));
        // The touching triangles' vertices and area per plane, in order of first touch.
        let mut groups: Vec<PlaneGroup> = Vec::new();
        let mut index_of: HashMap<u32, usize> = HashMap::default();
        for (i, t) in tris.iter().enumerate() {
            let g = planes.group_of(i as u32);
            if g == 0 {
                continue;
            }
            let centre = (t.v[0] + t.v[1] + t.v[2]) / 3.0;
            let radius = t.v.iter().map(|v| (*v - centre).length()).fold(0.0, f64::max);
            if !may_touch(centre, radius) {
                continue;
            }
            let area = 0.5 * (t.v[1] - t.v[0]).cross(t.v[2] - t.v[0]).length();
            match index_of.entry(g) {
                std::collections::hash_map::Entry::Occupied(e) => {
                    let group = &mut groups[*e.get()];
                    group.1.extend_from_slice(&t.v);
                    group.2 += area;
                }
                std::collections::hash_map::Entry::Vacant(e) => {
                    e.insert(groups.len());
                    groups.push((g, t.v.to_vec(), area));
                }
            }
        }
        let Some(&(first, _, _)) = groups.first() else {
            return Casters::None;
        };
        if groups.len() == 1 {
            let (mut normal, mut offset) = planes.planes[first as usize - 1];
            if normal.dot(eye) - offset < 0.0 {
                normal = -normal;
                offset = -offset;
            }
            if normal.dot(eye) - offset > margin && normal.dot(apex) - offset > margin {
                return Casters::Plane { normal, offset };
            }
        }
        let pyramid = |(g, points, _): &PlaneGroup| ShadowPyramid::new(points, planes.planes[*g as usize - 1], apex, margin);
        if groups.len() <= MAX_PYRAMIDS {
            let pyramids: Option<Vec<ShadowPyramid>> = groups.iter().map(pyramid).collect();
            if let Some(p) = pyramids
                && p.iter().map(|p| p.sides.len()).sum::<usize>() <= MAX_PYRAMID_SIDES
            {
                return Casters::Pyramids(p);
            }
        }
        Self::pyramids_and_ball(groups, &pyramid, apex, margin)
    }

    /// Too many planes for pyramids alone (or a plane through the light):
    /// the `k` largest planes by area keep their pyramids and the rest share
    /// one [`ShadowBall`], `k ≤ MAX_PYRAMIDS` chosen to make the ball's cone
    /// narrowest (the smallest `k` within 5 % of that). A floor under a
    /// faceted sphere: `k = 1`, the ball the sphere's. [`Casters::Any`] when
    /// the light is inside every such ball.
    fn pyramids_and_ball(
        mut groups: Vec<PlaneGroup>,
        pyramid: &dyn Fn(&PlaneGroup) -> Option<ShadowPyramid>,
        apex: DVec3,
        margin: f64,
    ) -> Casters {
        groups.sort_by(|a, b| b.2.total_cmp(&a.2));
        // The bounding box of groups[k..] for every k, from the end.
        let mut suffix = vec![(DVec3::INFINITY, DVec3::NEG_INFINITY); groups.len() + 1];
        for k in (0..groups.len()).rev() {
            let (mut lo, mut hi) = suffix[k + 1];
            for &p in &groups[k].1 {
                lo = lo.min(p);
                hi = hi.max(p);
            }
            suffix[k] = (lo, hi);
        }
        let mut best: Option<(usize, ShadowBall)> = None;
        let mut pyramids: Vec<ShadowPyramid> = Vec::new();
        let mut sides = 0usize;
        for k in 0..groups.len().min(MAX_PYRAMIDS + 1) {
            if k > 0 {
                // The prefix's pyramids must all exist, within the side budget.
                let Some(p) = pyramid(&groups[k - 1]) else { break };
                sides += p.sides.len();
                if sides > MAX_PYRAMID_SIDES {
                    break;
                }
                pyramids.push(p);
            }
            let (lo, hi) = suffix[k];
            if let Some(ball) = ShadowBall::new(lo, hi, apex, margin)
                && best.as_ref().is_none_or(|(_, b)| ball.spread() < 0.95 * b.spread())
            {
                best = Some((k, ball));
            }
        }
        match best {
            Some((k, ball)) => {
                pyramids.truncate(k);
                // The chosen ball tightened: about the box's centre, the
                // farthest vertex (a sphere's box has √3 times its radius).
                let (lo, hi) = suffix[k];
                let centre = 0.5 * (lo + hi);
                let reach = groups[k..]
                    .iter()
                    .flat_map(|g| g.1.iter())
                    .map(|p| (*p - centre).length())
                    .fold(0.0, f64::max);
                let half = DVec3::splat(reach / 3f64.sqrt());
                let ball = ShadowBall::new(centre - half, centre + half, apex, margin).unwrap_or(ball);
                Casters::PyramidsAndBall(pyramids, ball)
            }
            None => Casters::Any,
        }
    }

    /// Whether a ray from the eye `eye` along the unit `dir`, ending at
    /// distance `t_end` (m, may be infinite: no surface, no clip end), that
    /// crosses the light may be shadowed.
    pub fn may_shadow(&self, eye: DVec3, dir: DVec3, t_end: f64) -> bool {
        match self {
            Casters::None => false,
            &Casters::Plane { normal, offset } if t_end.is_finite() => {
                // On the plane (a floor hit) counts as the eye's side.
                let end = eye + dir * t_end;
                let tol = 1e-9 * (1.0 + offset.abs() + end.abs().max_element());
                !end.is_finite() || normal.dot(end) - offset < -tol
            }
            // A ray without an end stays on the eye's side (the eye is
            // strictly on it) unless it heads towards the plane: the plane
            // is infinite, its casters are not, so beyond them the ray may
            // reach the shadowed side.
            &Casters::Plane { normal, .. } => normal.dot(dir) < 0.0 || normal.dot(dir).is_nan(),
            Casters::Pyramids(pyramids) => !dir.is_finite() || t_end.is_nan() || pyramids_reached(pyramids, eye, dir, t_end),
            Casters::PyramidsAndBall(pyramids, ball) => {
                !dir.is_finite() || t_end.is_nan() || ball.reached_by(eye, dir, t_end) || pyramids_reached(pyramids, eye, dir, t_end)
            }
            Casters::Any => true,
        }
    }
}

/// One stencil sample: in-scatter, its error estimate, and its signature
/// (surface plane group + 1 or 0, topology code); `None` where there is
/// nothing to read.
pub type StencilSample = Option<([f32; 3], [f32; 3], (u32, u64))>;

/// The interpolated in-scatter and its error estimate at the midpoint of six
/// equally spaced samples (at −5, −3, −1, 1, 3, 5 half-spacings), or `None` when a
/// sample's signature differs from the pixel's own `signature` or the
/// estimate misses `tolerance · |value|` in some channel.
pub fn interpolate(stencil: &[StencilSample; 6], signature: (u32, u64), tolerance: f64) -> Option<([f64; 3], [f64; 3])> {
    let mut vals = [[0f64; 3]; 6];
    let mut errs = [[0f64; 3]; 6];
    for (i, s) in stencil.iter().enumerate() {
        let (l, e, g) = (*s)?;
        if g != signature {
            return None;
        }
        vals[i] = l.map(f64::from);
        errs[i] = e.map(f64::from);
    }
    interpolate_values(&vals, &errs, tolerance)
}

/// [`interpolate`] on six samples already known to share the pixel's
/// signature: values and their own errors (per channel). Used for each
/// light's in-scatter as well, with the samples' errors of the whole
/// in-scatter (each light's share of a traced sample's error is part of it).
pub fn interpolate_values(vals: &[[f64; 3]; 6], errs: &[[f64; 3]; 6], tolerance: f64) -> Option<([f64; 3], [f64; 3])> {
    let mut value = [0.0; 3];
    let mut error = [0.0; 3];
    for c in 0..3 {
        let f: [f64; 6] = std::array::from_fn(|i| vals[i][c]);
        let cubic: f64 = (0..4).map(|i| CUBIC[i] * f[i + 1]).sum();
        let left = f[0] - 4.0 * f[1] + 6.0 * f[2] - 4.0 * f[3] + f[4];
        let right = f[1] - 4.0 * f[2] + 6.0 * f[3] - 4.0 * f[4] + f[5];
        let own: f64 = (0..4)
            .map(|i| CUBIC[i].abs() * (errs[i + 1][c] + F32_ROUNDING * f[i + 1].abs()))
            .sum();
        let e = SAFETY * (3.0 / 256.0) * (left.abs() + right.abs()) + own;
        // Within the tolerance (a NaN never is); 0 ± 0 always.
        let within = e <= tolerance * cubic.abs() || (e == 0.0 && cubic == 0.0);
        if !within {
            return None;
        }
        value[c] = cubic;
        error[c] = e;
    }
    Some((value, error))
}

#[cfg(test)]
mod tests {
    use super::*;

    const XS: [f64; 6] = [-5.0, -3.0, -1.0, 1.0, 3.0, 5.0];

    fn sample(v: f64) -> StencilSample {
        Some(([v as f32; 3], [0.0; 3], (1, 1)))
    }

    /// The cubic's true error and the estimate (before the safety factor) for `f`.
    fn error_and_estimate(f: &dyn Fn(f64) -> f64) -> (f64, f64) {
        let v = XS.map(f);
        let cubic: f64 = (0..4).map(|i| CUBIC[i] * v[i + 1]).sum();
        let left = v[0] - 4.0 * v[1] + 6.0 * v[2] - 4.0 * v[3] + v[4];
        let right = v[1] - 4.0 * v[2] + 6.0 * v[3] - 4.0 * v[4] + v[5];
        ((cubic - f(0.0)).abs(), 3.0 / 256.0 * (left.abs() + right.abs()))
    }

    #[test]
    fn interpolation_is_exact_for_cubics_and_zeros() {
        let f = |x: f64| 2.0 + 0.3 * x - 0.02 * x * x + 0.001 * x * x * x;
        let (v, e) = interpolate(&XS.map(|x| sample(f(x))), (1, 1), 1e-5).expect("smooth");
        assert!((v[0] - f(0.0)).abs() < 1e-6, "{} vs {}", v[0], f(0.0));
        assert!(e[0] < 1e-6);
        // No light crossed: exactly 0, error 0, at any tolerance.
        assert_eq!(interpolate(&[0.0; 6].map(sample), (1, 1), 1e-12), Some(([0.0; 3], [0.0; 3])));
    }

    #[test]
    fn the_estimate_bounds_singularities_outside_the_stencil() {
        // Chords and powers of the distance to a silhouette anywhere outside
        // the stencil (both sides), and circles' chords with every sample
        // inside: the cubic's error within the estimate before its safety
        // factor (the ratio tends to 1 far away).
        let mut worst = 0.0f64;
        for k in 0..400 {
            let d = 5.0 + 1e-4 + 25.0 * f64::from(k) / 400.0;
            for p in [0.5, 1.5, 2.5] {
                let (e1, s1) = error_and_estimate(&|x: f64| (x + d).powf(p));
                let (e2, s2) = error_and_estimate(&|x: f64| (d - x).powf(p));
                worst = worst.max(e1 / s1).max(e2 / s2);
            }
        }
        for r in [5.5, 6.0, 8.0, 12.0, 20.0, 40.0] {
            for k in 0..=100 {
                let c = (r - 5.0 - 1e-4) * (2.0 * f64::from(k) / 100.0 - 1.0);
                let (err, est) = error_and_estimate(&|x: f64| (r * r - (x - c) * (x - c)).max(0.0).sqrt());
                worst = worst.max(err / est);
            }
        }
        assert!(worst <= 1.0, "worst ratio {worst}");
    }

    #[test]
    fn the_estimate_bounds_a_blended_beam_edge_within_one_code() {
        // A beam's in-scatter across its edge: the chord through a cone of
        // radius R px, weighted by Cycles' smoothstep over a blend zone b px
        // wide, f(d) = ∫ S((d − t²/2R)/b) dt over the chord, d the depth
        // inside the silhouette at x0. The code changes where the rays reach
        // the inner cone (d = b): stencils on one side of it only. The
        // cubic's error stays within the estimate (worst 0.99).
        let smoothstep = |u: f64| {
            let u = u.clamp(0.0, 1.0);
            u * u * (3.0 - 2.0 * u)
        };
        let edge = |d: f64, r: f64, b: f64| -> f64 {
            if d <= 0.0 {
                return 0.0;
            }
            // |t| ≤ t1: inside the inner cone (S = 1); t1 < |t| ≤ t2: the
            // blend zone, where S(u(t)) is a polynomial of degree 6 in t and
            // 4-point Gauss–Legendre is exact.
            let (t1, t2) = ((2.0 * r * (d - b)).max(0.0).sqrt(), (2.0 * r * d).sqrt());
            let (mid, half) = (0.5 * (t1 + t2), 0.5 * (t2 - t1));
            let gl = [
                (0.339_981_043_584_856_3, 0.652_145_154_862_546_1),
                (0.861_136_311_594_052_6, 0.347_854_845_137_453_9),
            ];
            let blend: f64 = gl
                .iter()
                .flat_map(|&(x, w)| [(mid - half * x, w), (mid + half * x, w)])
                .map(|(t, w)| w * half * smoothstep((d - t * t / (2.0 * r)) / b))
                .sum();
            2.0 * (t1 + blend)
        };
        let mut worst = 0.0f64;
        for r in [10.0, 100.0] {
            for b in [0.1, 1.0, 10.0] {
                for k in 0..40 {
                    let x0 = -5.0 - 1e-3 - 35.0 * f64::from(k) / 40.0;
                    let inner = x0 + b < -5.0;
                    let blend = x0 + b > 5.0;
                    if !(inner || blend) {
                        continue;
                    }
                    let (err, est) = error_and_estimate(&|x: f64| edge(x - x0, r, b));
                    if est > 1e-12 * edge(-x0, r, b) {
                        worst = worst.max(err / est);
                    }
                }
            }
        }
        assert!(worst <= 1.0, "worst ratio {worst}");
        // The accepted pixels of a smooth bump are within their estimate.
        for w in [4.0, 6.0, 10.0, 20.0] {
            let g = |x: f64| (-(x - 0.4) * (x - 0.4) / (w * w)).exp();
            if let Some((v, e)) = interpolate(&XS.map(|x| sample(g(x))), (1, 1), 0.5) {
                assert!(
                    (v[0] - g(0.0)).abs() <= e[0],
                    "width {w}: error {} > estimate {}",
                    (v[0] - g(0.0)).abs(),
                    e[0]
                );
            }
        }
    }

    #[test]
    fn other_signatures_and_missing_samples_are_not_interpolated() {
        let mut st = [1.0; 6].map(sample);
        assert!(interpolate(&st, (1, 1), 0.1).is_some());
        assert!(interpolate(&st, (1, 3), 0.1).is_none(), "another topology");
        assert!(interpolate(&st, (2, 1), 0.1).is_none(), "another surface");
        st[4] = None;
        assert!(interpolate(&st, (1, 1), 0.1).is_none(), "a sample that may not be read");
    }

    /// A mesh that is seen and casts shadows.
    fn mesh(name: &str, positions: Vec<[f64; 3]>, triangles: Vec<[u32; 3]>, transform: crate::scene::Transform) -> Mesh {
        Mesh {
            name: name.into(),
            positions,
            triangles,
            transform,
            visible_to_camera: true,
            casts_shadows: true,
        }
    }

    /// A floor 60 m wide at z = 0.
    fn floor() -> Mesh {
        let corners = vec![[-30.0, -30.0, 0.0], [30.0, -30.0, 0.0], [30.0, 30.0, 0.0], [-30.0, 30.0, 0.0]];
        mesh("floor", corners, vec![[0, 1, 2], [0, 2, 3]], Default::default())
    }

    /// Uniform numbers in [0, 1) from splitmix64.
    fn splitmix(mut state: u64) -> impl FnMut() -> f64 {
        move || {
            state = state.wrapping_add(0x9e37_79b9_7f4a_7c15);
            let mut z = state;
            z = (z ^ (z >> 30)).wrapping_mul(0xbf58_476d_1ce4_e5b9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94d0_49bb_1331_11eb);
            ((z ^ (z >> 31)) >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    /// The view ray from `eye` towards `target`, up to its first hit: if some
    /// point of it is shadowed from the light at `apex` (4 000 points, the
    /// first 40 m), `casters` must say it may be. Counted in `counts`:
    /// shadowed, unshadowed and told apart, unshadowed but flagged.
    fn count_ray(casters: &Casters, bvh: &crate::geometry::bvh::Bvh, apex: DVec3, eye: DVec3, target: DVec3, counts: &mut [usize; 3]) {
        let dir = (target - eye).normalize();
        let t_end = bvh.closest_hit(eye, dir, 0.0, f64::INFINITY).map_or(f64::INFINITY, |h| h.t);
        let reach = t_end.min(40.0);
        let shadowed = (0..4000).any(|i| {
            let p = eye + dir * reach * (i as f64 + 0.5) / 4000.0;
            let to = apex - p;
            bvh.any_hit(p, to.normalize(), 1e-9, to.length() * (1.0 - 1e-9))
        });
        let may = casters.may_shadow(eye, dir, t_end);
        assert!(
            may || !shadowed,
            "eye {eye}, target {target}, end {t_end}: shadowed but not flagged"
        );
        counts[if shadowed {
            0
        } else if may {
            2
        } else {
            1
        }] += 1;
    }

    /// A tilted box over a floor and a slanted card, under a light: every
    /// ray that a brute force finds shadowed somewhere (segments from 4000
    /// points along it to the light, against the triangles) is one the
    /// pyramids say may be, and most unshadowed rays in the light's reach
    /// are told apart from them.
    #[test]
    fn shadow_pyramids_hold_every_shadowed_ray() {
        use crate::geometry::bvh::Bvh;
        let mut rand = splitmix(0x9e37_79b9_7f4a_7c15);
        let (corners, cube_tris) = crate::geometry::cube(DVec3::ZERO, 0.5);
        let cube: Vec<[f64; 3]> = corners.iter().map(|c| c.to_array()).collect();
        let meshes = vec![
            floor(),
            mesh(
                "box",
                cube,
                cube_tris,
                crate::scene::Transform {
                    translation: Some([0.3, -0.2, 2.8]),
                    rotation_wxyz: Some([0.9, 0.2, 0.3, 0.1]),
                    scale: Some([0.8, 0.6, 0.7]),
                    ..Default::default()
                },
            ),
            mesh(
                "card",
                vec![[-1.5, 0.5, 1.2], [-0.6, 0.9, 1.9], [-0.7, 1.6, 1.5]],
                vec![[0, 1, 2]],
                Default::default(),
            ),
        ];
        let (tris, _) = crate::geometry::world_triangles(&meshes);
        let planes = Planes::new(&meshes, &tris);
        let apex = DVec3::new(0.1, 0.2, 5.5);
        let bvh = Bvh::build(tris.clone());
        let mut counts = [0usize; 3]; // shadowed, unshadowed told apart, unshadowed flagged
        for trial in 0..3000 {
            let eye = match trial % 3 {
                0 => DVec3::new(0.0, -10.0, 2.5),
                1 => DVec3::new(8.0 * rand() - 4.0, 8.0 * rand() - 4.0, 0.2 + 5.0 * rand()),
                _ => DVec3::new(0.3, -0.2, 1.0) + DVec3::new(rand() - 0.5, rand() - 0.5, rand() - 0.5),
            };
            let casters = Casters::of(&tris, &planes, eye, apex, |_, _| true);
            let Casters::Pyramids(ref pyramids) = casters else {
                panic!("{casters:?}")
            };
            assert_eq!(pyramids.len(), 8, "floor, six faces, card");
            if bvh.any_hit(eye, (apex - eye).normalize(), 0.0, (apex - eye).length()) && trial % 3 == 2 {
                // An eye in the box or its shadow: every ray from it may be shadowed.
                assert!(casters.may_shadow(eye, DVec3::Z, 1e-3));
                continue;
            }
            let target = DVec3::new(6.0 * rand() - 3.0, 6.0 * rand() - 3.0, 6.0 * rand() - 0.5);
            count_ray(&casters, &bvh, apex, eye, target, &mut counts);
        }
        assert!(counts[0] > 300 && counts[1] > 300, "{counts:?}");
        assert!(counts[1] > counts[2], "{counts:?}");
    }

    #[test]
    fn a_shadow_ball_holds_every_ray_a_faceted_sphere_shadows() {
        use crate::geometry::bvh::Bvh;
        let mut rand = splitmix(0x2545_f491_4f6c_dd1d);
        // A UV sphere (radius 0.8 at z = 2.5, 12 × 16 facets: 192 planes) on a floor.
        let (rings, segments, r, c) = (12usize, 16usize, 0.8, [0.2, -0.1, 2.5]);
        let mut positions = vec![[c[0], c[1], c[2] + r], [c[0], c[1], c[2] - r]];
        for i in 1..rings {
            let theta = std::f64::consts::PI * i as f64 / rings as f64;
            for j in 0..segments {
                let phi = std::f64::consts::TAU * j as f64 / segments as f64;
                positions.push([
                    c[0] + r * theta.sin() * phi.cos(),
                    c[1] + r * theta.sin() * phi.sin(),
                    c[2] + r * theta.cos(),
                ]);
            }
        }
        let ring = |i: usize, j: usize| (2 + (i - 1) * segments + j % segments) as u32;
        let mut triangles = Vec::new();
        for j in 0..segments {
            triangles.push([0, ring(1, j), ring(1, j + 1)]);
            triangles.push([1, ring(rings - 1, j + 1), ring(rings - 1, j)]);
            for i in 1..rings - 1 {
                triangles.push([ring(i, j), ring(i + 1, j), ring(i + 1, j + 1)]);
                triangles.push([ring(i, j), ring(i + 1, j + 1), ring(i, j + 1)]);
            }
        }
        let meshes = vec![floor(), mesh("sphere", positions, triangles, Default::default())];
        let (tris, _) = crate::geometry::world_triangles(&meshes);
        let planes = Planes::new(&meshes, &tris);
        let apex = DVec3::new(0.6, 0.4, 5.5);
        let bvh = Bvh::build(tris.clone());
        let mut counts = [0usize; 3]; // shadowed, unshadowed told apart, unshadowed flagged
        for trial in 0..2000 {
            let eye = if trial % 2 == 0 {
                DVec3::new(0.0, -10.0, 2.5)
            } else {
                DVec3::new(8.0 * rand() - 4.0, 8.0 * rand() - 4.0, 0.2 + 5.0 * rand())
            };
            let casters = Casters::of(&tris, &planes, eye, apex, |_, _| true);
            let Casters::PyramidsAndBall(ref pyramids, ref ball) = casters else {
                panic!("{casters:?}")
            };
            // The floor keeps its pyramid; the ball is the sphere's (tightened to its radius).
            assert_eq!(pyramids.len(), 1, "{casters:?}");
            let d = (DVec3::from(c) - apex).length();
            assert!((ball.spread() - r / d).abs() < 1e-6, "{} vs {}", ball.spread(), r / d);
            if bvh.any_hit(eye, (apex - eye).normalize(), 0.0, (apex - eye).length()) {
                assert!(casters.may_shadow(eye, DVec3::Z, 1e-3));
                continue;
            }
            let target = DVec3::new(6.0 * rand() - 3.0, 6.0 * rand() - 3.0, 6.0 * rand() - 0.5);
            count_ray(&casters, &bvh, apex, eye, target, &mut counts);
        }
        // Not vacuous: rays in the shadow and rays told apart from it.
        assert!(counts[0] > 100 && counts[1] > 300, "{counts:?}");
    }

    #[test]
    fn a_tiny_shadow_ball_still_holds_its_shadow() {
        // Balls of r/d down to 1e-12 (where cos of the half-angle would round
        // to 1): every ray through the segment behind the ball, at offsets
        // across it, is flagged.
        for (r_over_d, d) in [(1e-12, 10.0), (1e-9, 1000.0), (3e-9, 1.0), (1e-8, 20.0), (1e-6, 5.0)] {
            let apex = DVec3::new(0.3, -0.2, 4.0);
            let axis = DVec3::new(0.2, 0.1, -1.0).normalize();
            let centre = apex + axis * d;
            let half = DVec3::splat(r_over_d * d / 3f64.sqrt());
            let ball = ShadowBall::new(centre - half, centre + half, apex, 0.0).unwrap();
            // A point on the shadow's axis 0.5·d behind the ball, and rays
            // through it from eyes around it.
            let behind = apex + axis * (1.5 * d);
            let side = axis.cross(DVec3::Z).normalize();
            for k in 0..200 {
                let angle = std::f64::consts::TAU * k as f64 / 200.0;
                let eye = behind + (side * angle.cos() + side.cross(axis) * angle.sin()) * 2.0 + axis * (0.01 * k as f64);
                let dir = (behind - eye).normalize();
                assert!(ball.reached_by(eye, dir, f64::INFINITY), "r/d {r_over_d}, d {d}, ray {k}");
                let t_end = (behind - eye).length() * (1.0 + 1e-9);
                assert!(
                    ball.reached_by(eye, dir, t_end),
                    "r/d {r_over_d}, d {d}, ray {k} ending past the point"
                );
            }
        }
    }

    #[test]
    fn casters_shadow_only_the_far_side_of_their_plane() {
        let floor = Casters::Plane {
            normal: DVec3::Z,
            offset: 0.0,
        };
        let eye = DVec3::new(0.0, -9.0, 2.0);
        let end_at = |p: DVec3| (eye, (p - eye).normalize(), (p - eye).length());
        let shadows = |c: &Casters, (e, d, t): (DVec3, DVec3, f64)| c.may_shadow(e, d, t);
        assert!(!shadows(&floor, end_at(DVec3::new(3.0, 1.0, 0.0))), "a floor hit");
        assert!(!shadows(&floor, end_at(DVec3::new(3.0, 1.0, 2.0))));
        assert!(shadows(&floor, end_at(DVec3::new(3.0, 1.0, -1e-3))));
        // No end: upwards and level stay on the eye's side, downwards not.
        assert!(!floor.may_shadow(eye, DVec3::new(0.0, 0.8, 0.6), f64::INFINITY));
        assert!(!floor.may_shadow(eye, DVec3::X, f64::INFINITY));
        assert!(floor.may_shadow(eye, DVec3::new(0.0, 0.8, -0.6), f64::INFINITY));
        assert!(floor.may_shadow(eye, DVec3::new(0.0, 1.0, -1e-12).normalize(), f64::INFINITY));
        assert!(floor.may_shadow(eye, DVec3::new(f64::NAN, 0.0, 0.0), f64::INFINITY), "NaN: may");
        assert!(!Casters::None.may_shadow(eye, DVec3::new(0.0, 0.0, -1.0), 7.0));
        assert!(Casters::Any.may_shadow(eye, DVec3::Z, 1.0));
    }
}
