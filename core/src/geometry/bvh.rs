//! Bounding-volume hierarchy (BVH) over triangles, for ray casting in `f64`.
//!
//! # Method
//!
//! * **Build: binned SAH.** Each node bins its triangles' bounding-box centroids
//!   into 16 equal bins along each of the three axes and evaluates the surface
//!   area heuristic `C = 1 + 1.5 · (A_L·N_L + A_R·N_R) / A_P` at the 15 planes
//!   between bins (a leaf costs `1.5 · N`). The cheapest plane wins; a node of
//!   at most [`MAX_LEAF`] (4) triangles becomes a leaf when splitting does not
//!   pay, a larger one is always split, so no leaf holds more than 4. Nodes
//!   whose centroids all coincide, and every node deeper than 64, are split at
//!   the object median instead, which halves the count, so the tree is at most
//!   64 + 32 levels deep. The build is `O(N log N)`: subtrees of at least
//!   16 384 triangles split their halves over two threads (`rayon::join`) and
//!   are stitched together; smaller ones are built iteratively (an explicit
//!   work stack). The splits depend on the triangles only, so the tree is the
//!   same however the work was shared.
//! * **Node layout.** A flat `Vec` of 56-byte nodes: the node's box as
//!   `[min, max]`, and two `u32`: for a leaf the first index into the
//!   leaf-ordered triangle array and the count (1..=4); for an interior node the
//!   index of its left child and 0 (the right child is the next node). The
//!   triangles are copied in leaf order next to their original indices, so a
//!   leaf reads a contiguous run.
//! * **Traversal.** Iterative with a fixed stack of 128 entries. Closest hit
//!   tests both children's boxes, descends into the nearer one first, pushes
//!   the farther one with its entry distance and drops it on pop when the best
//!   hit found since is nearer. The interval shrinks to `[t_min, t_best]` as hits
//!   are found. Any hit stops at the first triangle hit in `[t_min, t_max]`.
//! * **Box test.** Slabs with a per-ray reciprocal direction and the near/far
//!   plane chosen by the sign bit of each direction component (Williams et al.
//!   2005), so `-0.0` and `+0.0` components work. A zero component gives a
//!   reciprocal of ±∞; `0 · ∞ = NaN` then appears only when the origin lies
//!   exactly on that slab plane, where the plane constrains nothing: the
//!   NaN-ignoring `f64::max`/`f64::min` used to accumulate the entry and exit
//!   distances skip it, which counts the box as closed (boundary inside). The
//!   entry and exit distances are widened by a relative `2^-32` (far more than
//!   the `2·γ₃` of Ize 2013, "Robust BVH ray traversal"), so rounding never culls
//!   a box that holds a hit, not even a grazing hit whose `t` the triangle
//!   test reports with a relative error of ~1e-11.
//! * **Triangle test: watertight** (Woop, Benthin, Wald 2013, "Watertight
//!   ray/triangle intersection", JCGT 2(1)). The vertices are translated to the
//!   ray origin and sheared so the ray becomes the +z axis; the three 2-D edge
//!   functions are evaluated from these per-vertex values. The two triangles
//!   sharing an edge compute that edge's function from the same two sheared
//!   vertices with the same products, so they get exactly opposite (or both
//!   zero) values: a ray through a shared edge or vertex hits at least one of
//!   them, never slips between. An edge function that rounds to exactly 0 is
//!   recomputed exactly signed (the paper's higher-precision fallback): when
//!   `fl(a·b) = fl(c·d)`, `a·b − c·d` equals the difference of the two
//!   `mul_add` rounding errors, which keeps the antisymmetry. Edges are
//!   inclusive (a ray exactly on an edge hits), back faces are not culled, and a
//!   triangle seen exactly edge-on (determinant 0) is not hit.
//! * **Degenerate triangles.** A triangle with a non-finite vertex or edge
//!   vector, or whose edge cross product is zero or lost in rounding
//!   (`|e₁ × e₂| ≤ 2^-46·|e₁||e₂|`, evaluated after scaling so it cannot
//!   overflow), is left out of the tree: it is never hit and never panics. It
//!   still counts in [`Bvh::triangle_count`] and is still returned by
//!   [`Bvh::triangle`].
//!
//! `dir` need not be unit length: `t` is in units of `|dir|`, i.e. the hit point
//! is `origin + t · dir`.
//!
//! **Range.** The edge functions are products of two coordinates and `t` of
//! three, so vertex coordinates relative to the ray origin (and `dir`'s
//! components relative to each other) should stay within about `1e100`; far
//! beyond that they overflow to ∞/NaN, which gives a miss, never a panic.
//! Within that range `t` carries a rounding error of about 1e-16 × the
//! vertices' distance from the ray's origin (the edge functions and `t`'s
//! numerator are sums of products of those coordinates): scenes keep their
//! meshes within `scene::MAX_MESH_COORDINATE_M`.
//!
//! # Why not an existing crate
//!
//! Checked on crates.io: `bvh` 0.13 depends on `nalgebra` (heavy) and needs
//! Rust 1.90; `obvhs` 0.4 is `f32`-only (`Vec3A` rays and triangles) and pulls
//! in `bytemuck`, `half`, `rdst`, `profiling` and more; `bvh-arena` 1.4 is a
//! broad-phase AABB tree with no ray–triangle closest/any hit. None offers
//! `f64` `DVec3` rays with `t_min`/`t_max` closest and any hit, so this module
//! is written here (std + `glam` only).

use glam::{BVec3, DVec3};
use smallvec::SmallVec;

/// Largest number of triangles in one leaf.
pub const MAX_LEAF: usize = 4;

/// Centroid bins per axis in the SAH build.
const BINS: usize = 16;
/// Relative cost of one node visit in the SAH.
const COST_TRAVERSAL: f64 = 1.0;
/// Relative cost of one triangle test in the SAH.
const COST_INTERSECT: f64 = 1.5;
/// Depth from which nodes are split at the object median (bounds the depth).
const MAX_SAH_DEPTH: u32 = 64;
/// Traversal stack kept inline (the tree is at most `MAX_SAH_DEPTH + 32`
/// deep; a deeper stack spills to the heap). `SmallVec` leaves it
/// uninitialised: a zeroed `[_; 128]` array cost a 1.5 kB memset per ray,
/// a fifth of a surface hit on a floor.
const STACK_INLINE: usize = 64;
/// Relative widening of box entry/exit distances (`2^-32`).
const BOX_SLACK: f64 = 1.0 / 4_294_967_296.0;
/// Relative threshold under which `|e1 × e2| / (|e1| |e2|)` counts as zero area (`2^-46`).
const DEGENERATE_SINE: f64 = 1.0 / 70_368_744_177_664.0;

/// A triangle given by its three vertices.
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct Triangle {
    /// The vertices. Their order sets the barycentrics of [`RayHit`]:
    /// the hit point is `(1 − u − v)·v[0] + u·v[1] + v·v[2]`.
    pub v: [DVec3; 3],
}

impl Triangle {
    /// A triangle from three vertices.
    #[must_use]
    pub fn new(a: DVec3, b: DVec3, c: DVec3) -> Self {
        Self { v: [a, b, c] }
    }

    /// Whether the triangle can never be hit: a vertex or an edge vector is not
    /// finite, or the area is zero or below rounding: `|e₁ × e₂| ≤ 2^-46·|e₁||e₂|`,
    /// i.e. the vertices are collinear to within about 1e-14 rad.
    #[must_use]
    pub fn is_degenerate(&self) -> bool {
        let [a, b, c] = self.v;
        if !(a.is_finite() && b.is_finite() && c.is_finite()) {
            return true;
        }
        let e1 = b - a;
        let e2 = c - a;
        // Scale to unit size first so that neither squares nor products overflow or underflow.
        let scale = e1.abs().max(e2.abs()).max_element();
        if !(scale > 0.0 && scale.is_finite()) {
            return true;
        }
        let (e1, e2) = (e1 / scale, e2 / scale);
        let n2 = e1.cross(e2).length_squared();
        let bound = DEGENERATE_SINE * DEGENERATE_SINE * e1.length_squared() * e2.length_squared();
        n2 <= bound
    }
}

/// The nearest intersection of a ray with the triangles of a [`Bvh`].
#[derive(Clone, Copy, Debug, PartialEq)]
pub struct RayHit {
    /// Ray parameter of the hit: the point is `origin + t · dir`, so `t` is in units of `|dir|`.
    pub t: f64,
    /// Index of the triangle hit, in the order given to [`Bvh::build`].
    pub triangle: u32,
    /// Barycentric weight of `v[1]` at the hit point.
    pub u: f64,
    /// Barycentric weight of `v[2]` at the hit point (`v[0]` has `1 − u − v`).
    pub v: f64,
}

/// One node: a box and either two children or a run of up to [`MAX_LEAF`] triangles.
#[derive(Clone, Copy, Debug)]
struct Node {
    /// `[min, max]` corners.
    bounds: [DVec3; 2],
    /// Leaf: first index into `leaf_tris`. Interior: index of the left child
    /// (the right child is `first + 1`).
    first: u32,
    /// Leaf: number of triangles (1..=`MAX_LEAF`). Interior: 0.
    count: u32,
}

/// A bounding-volume hierarchy over triangles, answering closest-hit and
/// any-hit ray queries. See the module documentation for the method.
#[derive(Clone, Debug)]
pub struct Bvh {
    /// The triangles as given to `build`.
    triangles: Vec<Triangle>,
    /// Nodes, root first; empty when no triangle can be hit.
    nodes: Vec<Node>,
    /// The non-degenerate triangles, in leaf order.
    leaf_tris: Vec<[DVec3; 3]>,
    /// Original index of each entry of `leaf_tris`.
    leaf_ids: Vec<u32>,
}

/// A triangle's box and centroid during the build.
#[derive(Clone, Copy)]
struct Prim {
    min: DVec3,
    max: DVec3,
    centroid: DVec3,
    id: u32,
}

/// An axis-aligned box that starts empty.
#[derive(Clone, Copy)]
struct Aabb {
    min: DVec3,
    max: DVec3,
}

impl Aabb {
    const EMPTY: Aabb = Aabb {
        min: DVec3::INFINITY,
        max: DVec3::NEG_INFINITY,
    };

    fn grow(&mut self, min: DVec3, max: DVec3) {
        self.min = self.min.min(min);
        self.max = self.max.max(max);
    }

    /// Half the surface area; 0 for an empty box.
    fn half_area(&self) -> f64 {
        let d = self.max - self.min;
        if d.x < 0.0 { 0.0 } else { d.x * d.y + d.y * d.z + d.z * d.x }
    }
}

impl Bvh {
    /// Builds the hierarchy (binned SAH, see the module documentation).
    ///
    /// Empty input is allowed. Degenerate triangles ([`Triangle::is_degenerate`])
    /// are kept for [`Bvh::triangle`] but left out of the tree.
    ///
    /// # Panics
    ///
    /// If there are 2³¹ triangles or more (node and triangle indices are `u32`).
    #[must_use]
    pub fn build(triangles: Vec<Triangle>) -> Bvh {
        Self::build_parallel_from(triangles, PARALLEL_MIN_PRIMS, &|| false).expect("a build never stopped completes")
    }

    /// [`Bvh::build`] that gives up once `stop()` returns true (asked before
    /// each split of a subtree of at least 16 384 triangles, and once at the
    /// end): `None` then. 720 000 triangles took ≈ 0.3 s on two threads, so
    /// a render cancelled while its BVH is built returns within one
    /// subtree's time instead of the whole build's.
    #[must_use]
    pub fn build_cancellable(triangles: Vec<Triangle>, stop: &(dyn Fn() -> bool + Sync)) -> Option<Bvh> {
        Self::build_parallel_from(triangles, PARALLEL_MIN_PRIMS, stop)
    }

    /// [`Bvh::build_cancellable`] whose subtrees of at least `parallel_min`
    /// triangles are built on two threads (`rayon::join`). The splits, and so
    /// the tree and the leaf order, are the same for every `parallel_min`.
    fn build_parallel_from(triangles: Vec<Triangle>, parallel_min: usize, stop: &(dyn Fn() -> bool + Sync)) -> Option<Bvh> {
        use rayon::prelude::*;
        assert!(triangles.len() < 1 << 31, "Bvh::build: 2^31 triangles or more");
        let mut prims: Vec<Prim> = triangles
            .par_iter()
            .enumerate()
            .filter(|(_, t)| !t.is_degenerate())
            .map(|(i, t)| {
                let [a, b, c] = t.v;
                let min = a.min(b).min(c);
                let max = a.max(b).max(c);
                Prim {
                    min,
                    max,
                    centroid: 0.5 * min + 0.5 * max, // no overflow near f64::MAX
                    id: i as u32,
                }
            })
            .collect();
        let nodes = if prims.is_empty() {
            Vec::new()
        } else {
            subtree(&mut prims, 0, 0, parallel_min.max(2), stop)?
        };
        if stop() {
            return None;
        }
        let leaf_tris = prims.par_iter().map(|p| triangles[p.id as usize].v).collect();
        let leaf_ids = prims.iter().map(|p| p.id).collect();
        Some(Bvh {
            triangles,
            nodes,
            leaf_tris,
            leaf_ids,
        })
    }

    /// Number of triangles given to [`Bvh::build`], degenerate ones included.
    #[must_use]
    pub fn triangle_count(&self) -> usize {
        self.triangles.len()
    }

    /// The triangle with index `i` in the order given to [`Bvh::build`]
    /// (the index reported in [`RayHit::triangle`]).
    ///
    /// # Panics
    ///
    /// If `i >= self.triangle_count()`.
    #[must_use]
    pub fn triangle(&self, i: u32) -> &Triangle {
        &self.triangles[i as usize]
    }

    /// Axis-aligned bounds `(min, max)` of the triangles that can be hit
    /// (degenerate ones excluded); `None` when there are none.
    #[must_use]
    pub fn bounds(&self) -> Option<(DVec3, DVec3)> {
        self.nodes.first().map(|n| (n.bounds[0], n.bounds[1]))
    }

    /// The nearest hit of the ray `origin + t · dir` with `t_min ≤ t ≤ t_max`.
    ///
    /// `dir` need not be unit length and may have zero components; `t` is in
    /// units of `|dir|`. Returns `None` when nothing is hit, and also for a zero
    /// or non-finite `dir`, a non-finite `origin`, or `t_min > t_max` (or NaN).
    /// When several triangles are hit at the same `t` (a shared edge), any one
    /// of them is reported.
    #[must_use]
    pub fn closest_hit(&self, origin: DVec3, dir: DVec3, t_min: f64, t_max: f64) -> Option<RayHit> {
        let ray = RayData::new(origin, dir, t_min, t_max)?;
        let nodes = &self.nodes[..];
        let root = nodes.first()?;
        let mut t_hi = t_max;
        ray.enter(root, t_min, t_hi)?;
        let mut best: Option<(f64, f64, f64, usize)> = None;
        // Far children and their entry distances.
        let mut stack: SmallVec<[(u32, f64); STACK_INLINE]> = SmallVec::new();
        let mut ni = 0usize;
        loop {
            let node = &nodes[ni];
            if node.count > 0 {
                let first = node.first as usize;
                for k in first..first + node.count as usize {
                    if let Some((t, u, v)) = ray.intersect(&self.leaf_tris[k], t_min, t_hi) {
                        t_hi = t;
                        best = Some((t, u, v, k));
                    }
                }
            } else {
                let left = node.first as usize;
                let hl = ray.enter(&nodes[left], t_min, t_hi);
                let hr = ray.enter(&nodes[left + 1], t_min, t_hi);
                match (hl, hr) {
                    (Some(tl), Some(tr)) => {
                        let (near, far, t_far) = if tl <= tr { (left, left + 1, tr) } else { (left + 1, left, tl) };
                        stack.push((far as u32, t_far));
                        ni = near;
                        continue;
                    }
                    (Some(_), None) => {
                        ni = left;
                        continue;
                    }
                    (None, Some(_)) => {
                        ni = left + 1;
                        continue;
                    }
                    (None, None) => {}
                }
            }
            // Pop the next node whose entry distance is not beyond the best hit.
            loop {
                let Some((node, t_entry)) = stack.pop() else {
                    return best.map(|(t, u, v, k)| RayHit {
                        t,
                        triangle: self.leaf_ids[k],
                        u,
                        v,
                    });
                };
                if t_entry <= t_hi {
                    ni = node as usize;
                    break;
                }
            }
        }
    }

    /// Whether the ray `origin + t · dir` hits any triangle with
    /// `t_min ≤ t ≤ t_max` (shadow and visibility rays).
    ///
    /// Same conventions as [`Bvh::closest_hit`], whose result is `Some` exactly
    /// when this is `true`.
    #[must_use]
    pub fn any_hit(&self, origin: DVec3, dir: DVec3, t_min: f64, t_max: f64) -> bool {
        let Some(ray) = RayData::new(origin, dir, t_min, t_max) else {
            return false;
        };
        let nodes = &self.nodes[..];
        let Some(root) = nodes.first() else {
            return false;
        };
        if ray.enter(root, t_min, t_max).is_none() {
            return false;
        }
        let mut stack: SmallVec<[u32; STACK_INLINE]> = SmallVec::new();
        let mut ni = 0usize;
        loop {
            let node = &nodes[ni];
            if node.count > 0 {
                let first = node.first as usize;
                for k in first..first + node.count as usize {
                    if ray.intersect(&self.leaf_tris[k], t_min, t_max).is_some() {
                        return true;
                    }
                }
            } else {
                let left = node.first as usize;
                let hl = ray.enter(&nodes[left], t_min, t_max).is_some();
                let hr = ray.enter(&nodes[left + 1], t_min, t_max).is_some();
                if hl {
                    if hr {
                        stack.push((left + 1) as u32);
                    }
                    ni = left;
                    continue;
                }
                if hr {
                    ni = left + 1;
                    continue;
                }
            }
            let Some(next) = stack.pop() else {
                return false;
            };
            ni = next as usize;
        }
    }
}

/// Subtrees of at least this many triangles are built in parallel: a million
/// triangles took 2.0–2.6 s on one thread, most of a render's preparation.
const PARALLEL_MIN_PRIMS: usize = 1 << 14;

/// The box of `prims` and the box of their centroids.
fn bounds_of(prims: &[Prim]) -> (Aabb, Aabb) {
    let mut bounds = Aabb::EMPTY;
    let mut cbounds = Aabb::EMPTY;
    for p in prims {
        bounds.grow(p.min, p.max);
        cbounds.grow(p.centroid, p.centroid);
    }
    (bounds, cbounds)
}

/// The nodes of the subtree over `prims` (which start at `offset` in the
/// leaf order), its root first; child indices are local to the returned
/// `Vec`, leaves index the whole leaf order. Large subtrees split their two
/// halves over two threads and are stitched together by [`join_subtrees`].
/// `None` once `stop()` is true before a large subtree's split.
fn subtree(prims: &mut [Prim], offset: usize, depth: u32, parallel_min: usize, stop: &(dyn Fn() -> bool + Sync)) -> Option<Vec<Node>> {
    if prims.len() < parallel_min {
        return Some(subtree_sequential(prims, offset, depth));
    }
    if stop() {
        return None;
    }
    let (bounds, cbounds) = bounds_of(prims);
    let mut root = Node {
        bounds: [bounds.min, bounds.max],
        first: offset as u32,
        count: prims.len() as u32,
    };
    match split(prims, &bounds, &cbounds, depth) {
        None => Some(vec![root]),
        Some(mid) => {
            let (left, right) = prims.split_at_mut(mid);
            let (l, r) = rayon::join(
                || subtree(left, offset, depth + 1, parallel_min, stop),
                || subtree(right, offset + mid, depth + 1, parallel_min, stop),
            );
            root.count = 0;
            Some(join_subtrees(root, l?, r?))
        }
    }
}

/// `[root, l[0], r[0], l[1..], r[1..]]` with the child indices moved to
/// match: an interior node's children stay adjacent (left, then right).
fn join_subtrees(mut root: Node, l: Vec<Node>, r: Vec<Node>) -> Vec<Node> {
    let (nl, nr) = (l.len(), r.len());
    // Local index → index in the joined Vec.
    let at_l = |i: usize| if i == 0 { 1 } else { 2 + i };
    let at_r = |i: usize| if i == 0 { 2 } else { 1 + nl + i };
    let moved = |n: &Node, at: &dyn Fn(usize) -> usize| -> Node {
        let mut n = *n;
        if n.count == 0 {
            n.first = at(n.first as usize) as u32;
        }
        n
    };
    root.first = 1;
    let mut out = Vec::with_capacity(1 + nl + nr);
    out.push(root);
    out.push(moved(&l[0], &at_l));
    out.push(moved(&r[0], &at_r));
    out.extend(l[1..].iter().map(|n| moved(n, &at_l)));
    out.extend(r[1..].iter().map(|n| moved(n, &at_r)));
    out
}

/// [`subtree`] on one thread: an explicit work stack, no recursion.
fn subtree_sequential(prims: &mut [Prim], offset: usize, depth0: u32) -> Vec<Node> {
    let blank = Node {
        bounds: [DVec3::ZERO; 2],
        first: 0,
        count: 0,
    };
    let mut nodes = Vec::with_capacity(2 * prims.len());
    nodes.push(blank);
    // (node, start, end, depth)
    let mut work: Vec<(usize, usize, usize, u32)> = vec![(0, 0, prims.len(), depth0)];
    while let Some((ni, start, end, depth)) = work.pop() {
        let slice = &mut prims[start..end];
        let (bounds, cbounds) = bounds_of(slice);
        nodes[ni].bounds = [bounds.min, bounds.max];
        match split(slice, &bounds, &cbounds, depth) {
            None => {
                nodes[ni].first = (offset + start) as u32;
                nodes[ni].count = (end - start) as u32;
            }
            Some(mid) => {
                let left = nodes.len();
                nodes.push(blank);
                nodes.push(blank);
                nodes[ni].first = left as u32;
                nodes[ni].count = 0;
                work.push((left + 1, start + mid, end, depth + 1));
                work.push((left, start, start + mid, depth + 1));
            }
        }
    }
    nodes
}

/// Chooses how to split `prims` (a node's triangles) and partitions them.
///
/// Returns `None` for a leaf (only when `prims.len() <= MAX_LEAF`), or
/// `Some(mid)` with `0 < mid < prims.len()`: `prims[..mid]` go left.
fn split(prims: &mut [Prim], bounds: &Aabb, cbounds: &Aabb, depth: u32) -> Option<usize> {
    let n = prims.len();
    if n <= 1 {
        return None;
    }
    let extent = cbounds.max - cbounds.min;
    let widest = extent.max_position();
    // Centroids and bounds are finite (degenerate triangles are excluded), so
    // `extent` is never NaN.
    if depth >= MAX_SAH_DEPTH || extent[widest] <= 0.0 {
        return median_split(prims, widest);
    }

    // Binned SAH over the three axes: (cost, axis, last bin on the left).
    let mut best: Option<(f64, usize, usize)> = None;
    for axis in 0..3 {
        if extent[axis] <= 0.0 {
            continue;
        }
        let lo = cbounds.min[axis];
        let scale = BINS as f64 / extent[axis];
        let mut bins = [(Aabb::EMPTY, 0usize); BINS];
        for p in prims.iter() {
            let b = &mut bins[bin_index(p.centroid[axis], lo, scale)];
            b.0.grow(p.min, p.max);
            b.1 += 1;
        }
        let mut right_area = [0.0; BINS];
        let mut right_count = [0usize; BINS];
        let mut acc = Aabb::EMPTY;
        let mut count = 0;
        for i in (1..BINS).rev() {
            acc.grow(bins[i].0.min, bins[i].0.max);
            count += bins[i].1;
            right_area[i - 1] = acc.half_area();
            right_count[i - 1] = count;
        }
        let mut acc = Aabb::EMPTY;
        let mut count = 0;
        for i in 0..BINS - 1 {
            acc.grow(bins[i].0.min, bins[i].0.max);
            count += bins[i].1;
            if count == 0 || right_count[i] == 0 {
                continue;
            }
            let cost = acc.half_area() * count as f64 + right_area[i] * right_count[i] as f64;
            if best.is_none_or(|(c, _, _)| cost < c) {
                best = Some((cost, axis, i));
            }
        }
    }
    let Some((cost, axis, last_left)) = best else {
        return median_split(prims, widest);
    };
    let parent_area = bounds.half_area();
    let split_cost = if parent_area > 0.0 {
        COST_TRAVERSAL + COST_INTERSECT * cost / parent_area
    } else {
        COST_TRAVERSAL + COST_INTERSECT * n as f64
    };
    if n <= MAX_LEAF && split_cost >= COST_INTERSECT * n as f64 {
        return None;
    }
    let lo = cbounds.min[axis];
    let scale = BINS as f64 / extent[axis];
    // In-place partition with the same binning as above, so both sides are non-empty.
    let mut mid = 0;
    for i in 0..n {
        if bin_index(prims[i].centroid[axis], lo, scale) <= last_left {
            prims.swap(i, mid);
            mid += 1;
        }
    }
    debug_assert!(mid > 0 && mid < n);
    Some(mid)
}

/// Object-median split along `axis`, or a leaf when `prims` fits in one.
fn median_split(prims: &mut [Prim], axis: usize) -> Option<usize> {
    let n = prims.len();
    if n <= MAX_LEAF {
        return None;
    }
    let mid = n / 2;
    prims.select_nth_unstable_by(mid, |a, b| a.centroid[axis].total_cmp(&b.centroid[axis]));
    Some(mid)
}

/// Bin of a centroid coordinate; saturating, so never out of range.
#[inline]
fn bin_index(c: f64, lo: f64, scale: f64) -> usize {
    // `as usize` saturates (NaN → 0), so this cannot index out of range.
    (((c - lo) * scale) as usize).min(BINS - 1)
}

/// A ray prepared for box and watertight triangle tests.
struct RayData {
    origin: DVec3,
    /// `1 / dir`, ±∞ for zero components.
    inv_dir: DVec3,
    /// Per axis, whether the direction's sign bit is set (the entry plane is `max`).
    neg: BVec3,
    /// Axes permuted so that `kz` is the dominant direction component.
    kx: usize,
    ky: usize,
    kz: usize,
    /// Shear constants `(d[kx]/d[kz], d[ky]/d[kz], 1/d[kz])`.
    sx: f64,
    sy: f64,
    sz: f64,
}

impl RayData {
    /// `None` for a ray that cannot hit anything (zero or non-finite direction,
    /// non-finite origin, empty or NaN interval).
    #[inline]
    fn new(origin: DVec3, dir: DVec3, t_min: f64, t_max: f64) -> Option<Self> {
        if !(origin.is_finite() && dir.is_finite() && dir != DVec3::ZERO && t_min <= t_max) {
            return None;
        }
        let kz = dir.abs().max_position();
        let mut kx = (kz + 1) % 3;
        let mut ky = (kx + 1) % 3;
        // Keep the winding of the triangle in the sheared space (paper, section 3).
        if dir[kz] < 0.0 {
            std::mem::swap(&mut kx, &mut ky);
        }
        Some(RayData {
            origin,
            inv_dir: dir.recip(),
            neg: BVec3::new(dir.x.is_sign_negative(), dir.y.is_sign_negative(), dir.z.is_sign_negative()),
            kx,
            ky,
            kz,
            sx: dir[kx] / dir[kz],
            sy: dir[ky] / dir[kz],
            sz: 1.0 / dir[kz],
        })
    }

    /// Conservative slab test: the (widened) entry distance into `node`'s box
    /// clipped to `[t_lo, t_hi]`, or `None` when the clipped interval is empty.
    #[inline]
    fn enter(&self, node: &Node, t_lo: f64, t_hi: f64) -> Option<f64> {
        let [min, max] = node.bounds;
        // Entry/exit planes per axis by the direction's sign bit. NaN (0·∞) only
        // when the origin lies on a slab plane and the direction is parallel to
        // it: `f64::max`/`min` ignore NaN, so such a plane does not constrain.
        let tn = (DVec3::select(self.neg, max, min) - self.origin) * self.inv_dir;
        let tf = (DVec3::select(self.neg, min, max) - self.origin) * self.inv_dir;
        let (nx, ny, nz, fx, fy, fz) = (tn.x, tn.y, tn.z, tf.x, tf.y, tf.z);
        let near = f64::NEG_INFINITY.max(nx).max(ny).max(nz);
        let far = f64::INFINITY.min(fx).min(fy).min(fz);
        // Widen against rounding: near towards −∞, far towards +∞.
        let near = near * if near > 0.0 { 1.0 - BOX_SLACK } else { 1.0 + BOX_SLACK };
        let far = far * if far > 0.0 { 1.0 + BOX_SLACK } else { 1.0 - BOX_SLACK };
        let near = near.max(t_lo);
        let far = far.min(t_hi);
        if near <= far { Some(near) } else { None }
    }

    /// Watertight ray/triangle test (Woop, Benthin, Wald 2013). Returns
    /// `(t, u, v)` with `t_lo ≤ t ≤ t_hi`, `u`, `v` the weights of `v[1]`, `v[2]`.
    #[inline]
    fn intersect(&self, tri: &[DVec3; 3], t_lo: f64, t_hi: f64) -> Option<(f64, f64, f64)> {
        let (kx, ky, kz) = (self.kx, self.ky, self.kz);
        let a = tri[0] - self.origin;
        let b = tri[1] - self.origin;
        let c = tri[2] - self.origin;
        let ax = a[kx] - self.sx * a[kz];
        let ay = a[ky] - self.sy * a[kz];
        let bx = b[kx] - self.sx * b[kz];
        let by = b[ky] - self.sy * b[kz];
        let cx = c[kx] - self.sx * c[kz];
        let cy = c[ky] - self.sy * c[kz];
        // Edge functions; e(P, Q) = Qx·Py − Qy·Px for the edge P → Q.
        let mut u = cx * by - cy * bx;
        let mut v = ax * cy - ay * cx;
        let mut w = bx * ay - by * ax;
        if u == 0.0 {
            u = exact_zero_diff(cx, by, cy, bx);
        }
        if v == 0.0 {
            v = exact_zero_diff(ax, cy, ay, cx);
        }
        if w == 0.0 {
            w = exact_zero_diff(bx, ay, by, ax);
        }
        if (u < 0.0 || v < 0.0 || w < 0.0) && (u > 0.0 || v > 0.0 || w > 0.0) {
            return None;
        }
        let det = u + v + w;
        if det == 0.0 || det.is_nan() {
            return None;
        }
        let az = self.sz * a[kz];
        let bz = self.sz * b[kz];
        let cz = self.sz * c[kz];
        let inv_det = 1.0 / det;
        let t = (u * az + v * bz + w * cz) * inv_det;
        if t >= t_lo && t <= t_hi {
            Some((t, v * inv_det, w * inv_det))
        } else {
            None
        }
    }
}

/// `p·q − r·s` correctly signed, for the case where `fl(p·q) == fl(r·s)` (the
/// plain difference rounded to 0). Then the exact difference is the difference
/// of the two products' rounding errors, which `mul_add` gives exactly.
/// Swapping the two products negates the result exactly.
#[inline(never)]
#[cold]
fn exact_zero_diff(p: f64, q: f64, r: f64, s: f64) -> f64 {
    let pq = p * q;
    let rs = r * s;
    p.mul_add(q, -pq) - r.mul_add(s, -rs)
}

#[cfg(test)]
mod tests {
    use super::*;
    use proptest::prelude::*;

    fn tri(a: [f64; 3], b: [f64; 3], c: [f64; 3]) -> Triangle {
        Triangle::new(DVec3::from(a), DVec3::from(b), DVec3::from(c))
    }

    /// Closest hit over all triangles with the same triangle test, no tree.
    fn brute_closest(tris: &[Triangle], o: DVec3, d: DVec3, t_min: f64, t_max: f64) -> Option<RayHit> {
        let ray = RayData::new(o, d, t_min, t_max)?;
        let mut best: Option<RayHit> = None;
        for (i, t) in tris.iter().enumerate() {
            if t.is_degenerate() {
                continue;
            }
            let hi = best.map_or(t_max, |h| h.t);
            if let Some((t, u, v)) = ray.intersect(&t.v, t_min, hi) {
                best = Some(RayHit {
                    t,
                    triangle: i as u32,
                    u,
                    v,
                });
            }
        }
        best
    }

    #[test]
    fn the_parallel_build_is_the_sequential_tree() {
        // A wavy sheet of 2·60² triangles and a soup of 3 000, so that the
        // parallel part (subtrees from 64 triangles up) joins many subtrees.
        let mut tris = Vec::new();
        let n = 60;
        let z = |i: usize, j: usize| 0.3 * (0.7 * i as f64).sin() * (0.5 * j as f64).cos();
        for j in 0..n {
            for i in 0..n {
                let p = |a: usize, b: usize| [a as f64 * 0.1, b as f64 * 0.1, z(a, b)];
                tris.push(tri(p(i, j), p(i + 1, j), p(i + 1, j + 1)));
                tris.push(tri(p(i, j), p(i + 1, j + 1), p(i, j + 1)));
            }
        }
        let mut seed = 7u64;
        let mut next = || {
            seed = seed.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            (seed >> 11) as f64 / (1u64 << 53) as f64 * 6.0 - 1.0
        };
        for _ in 0..3000 {
            let a = [next(), next(), next()];
            tris.push(tri(
                a,
                [a[0] + 0.2 * next(), a[1] + 0.2 * next(), a[2]],
                [a[0], a[1] + 0.2 * next(), a[2] + 0.1 * next()],
            ));
        }
        let sequential = Bvh::build_parallel_from(tris.clone(), usize::MAX, &|| false).unwrap();
        let parallel = Bvh::build_parallel_from(tris.clone(), 64, &|| false).unwrap();
        // Stopped: before the first split, or part-way (some subtrees built, others not).
        assert!(Bvh::build_parallel_from(tris.clone(), 64, &|| true).is_none());
        let asked = std::sync::atomic::AtomicUsize::new(0);
        let part_way = || asked.fetch_add(1, std::sync::atomic::Ordering::Relaxed) >= 5;
        assert!(Bvh::build_parallel_from(tris.clone(), 64, &part_way).is_none());
        assert_eq!(parallel.leaf_ids, sequential.leaf_ids);
        assert_eq!(parallel.nodes.len(), sequential.nodes.len());
        for k in 0..2000 {
            let o = DVec3::new(next() * 2.0, next() * 2.0, 3.0 + next());
            let d = DVec3::new(next(), next(), -2.0 - next().abs());
            let (a, b) = (
                parallel.closest_hit(o, d, 0.0, f64::INFINITY),
                sequential.closest_hit(o, d, 0.0, f64::INFINITY),
            );
            assert_eq!(a, b, "ray {k}");
            assert_eq!(a, brute_closest(&tris, o, d, 0.0, f64::INFINITY), "ray {k}");
            assert_eq!(parallel.any_hit(o, d, 0.0, 1.0), brute_any(&tris, o, d, 0.0, 1.0), "ray {k}");
        }
    }

    fn brute_any(tris: &[Triangle], o: DVec3, d: DVec3, t_min: f64, t_max: f64) -> bool {
        brute_closest(tris, o, d, t_min, t_max).is_some()
    }

    /// Single-triangle hit, for checking which triangle a BVH reported.
    fn single(t: &Triangle, o: DVec3, d: DVec3, t_min: f64, t_max: f64) -> Option<(f64, f64, f64)> {
        if t.is_degenerate() {
            return None;
        }
        RayData::new(o, d, t_min, t_max)?.intersect(&t.v, t_min, t_max)
    }

    fn close(a: f64, b: f64, rel: f64) -> bool {
        a == b || (a - b).abs() <= rel * a.abs().max(b.abs())
    }

    /// Checks the BVH against brute force for one ray, with descriptive failure.
    fn check_ray(bvh: &Bvh, tris: &[Triangle], o: DVec3, d: DVec3, t_min: f64, t_max: f64) -> Result<(), TestCaseError> {
        let got = bvh.closest_hit(o, d, t_min, t_max);
        let want = brute_closest(tris, o, d, t_min, t_max);
        match (got, want) {
            (None, None) => {}
            (Some(g), Some(w)) => {
                prop_assert!(close(g.t, w.t, 1e-9), "t {} vs brute {} (o {o}, d {d})", g.t, w.t);
                if g.triangle != w.triangle {
                    // A tie (shared edge or coincident triangles): the reported one must be hit there.
                    let s = single(bvh.triangle(g.triangle), o, d, t_min, t_max);
                    prop_assert!(s.is_some_and(|(t, _, _)| close(t, g.t, 1e-9)), "reported triangle not hit at t");
                } else {
                    prop_assert_eq!(g, w);
                }
            }
            (g, w) => prop_assert!(false, "bvh {g:?} vs brute {w:?} (o {o}, d {d}, [{t_min}, {t_max}])"),
        }
        prop_assert_eq!(bvh.any_hit(o, d, t_min, t_max), brute_any(tris, o, d, t_min, t_max));
        Ok(())
    }

    fn vec3(range: f64) -> impl Strategy<Value = DVec3> {
        (-range..range, -range..range, -range..range).prop_map(|(x, y, z)| DVec3::new(x, y, z))
    }

    /// A direction: general, with one or two zero components, or along an axis with either sign of zero.
    fn direction() -> impl Strategy<Value = DVec3> {
        (vec3(1.0), 0usize..6, any::<[bool; 3]>()).prop_map(|(d, mode, neg)| {
            let z = |neg: bool| if neg { -0.0 } else { 0.0 };
            let mut d = d;
            match mode {
                0 | 1 => {}
                2 => d.x = z(neg[0]),
                3 => {
                    d.y = z(neg[1]);
                    d.z = z(neg[2]);
                }
                4 => {
                    d = DVec3::ZERO;
                    d.x = if neg[0] { -1.0 } else { 1.0 };
                    d.y = z(neg[1]);
                    d.z = z(neg[2]);
                }
                _ => {
                    d = DVec3::new(z(neg[0]), z(neg[1]), if neg[2] { -3.0 } else { 0.5 });
                }
            }
            if d == DVec3::ZERO { DVec3::X } else { d }
        })
    }

    /// Random soup: small triangles scattered in a box, some large ones, some degenerate.
    fn soup() -> impl Strategy<Value = Vec<Triangle>> {
        prop::collection::vec((vec3(10.0), vec3(1.5), vec3(1.5), 0usize..20), 50..400).prop_map(|v| {
            v.into_iter()
                .map(|(c, e1, e2, kind)| match kind {
                    0 => Triangle::new(c, c + 5.0 * e1, c + 5.0 * e2),
                    1 => Triangle::new(c, c + e1, c + e1),
                    2 => Triangle::new(c, c + e1, c + 2.0 * e1),
                    _ => Triangle::new(c, c + e1, c + e2),
                })
                .collect()
        })
    }

    /// Soup on a quarter-unit grid, so that ray origins lie exactly on box planes
    /// and axis-aligned rays run along triangle edges and faces.
    fn grid_soup() -> impl Strategy<Value = Vec<Triangle>> {
        let p = || (-8i32..8, -8i32..8, -8i32..8).prop_map(|(x, y, z)| DVec3::new(x as f64, y as f64, z as f64) * 0.25);
        prop::collection::vec((p(), p(), p()), 20..200).prop_map(|v| v.into_iter().map(|(a, b, c)| Triangle::new(a, b, c)).collect())
    }

    fn interval() -> impl Strategy<Value = (f64, f64)> {
        (0usize..4, 0.0..5.0f64, 0.0..30.0f64).prop_map(|(mode, a, b)| match mode {
            0 => (0.0, f64::INFINITY),
            1 => (a, a + b),
            2 => (-a, f64::INFINITY),
            _ => (f64::NEG_INFINITY, b),
        })
    }

    proptest! {
        #![proptest_config(ProptestConfig::with_cases(128))]

        #[test]
        fn matches_brute_force_on_random_soups(
            tris in soup(),
            rays in prop::collection::vec((vec3(15.0), direction(), interval()), 64),
        ) {
            let bvh = Bvh::build(tris.clone());
            prop_assert_eq!(bvh.triangle_count(), tris.len());
            for (o, d, (t0, t1)) in rays {
                check_ray(&bvh, &tris, o, d, t0, t1)?;
                // The same ray aimed at a triangle's centroid, so most of these hit.
                let target = tris[(o.x.abs() * 1000.0) as usize % tris.len()].v;
                let aim = (target[0] + target[1] + target[2]) / 3.0 - o;
                if aim != DVec3::ZERO {
                    check_ray(&bvh, &tris, o, aim * (1.0 + d.x.abs()), 0.0, f64::INFINITY)?;
                }
            }
        }

        #[test]
        fn matches_brute_force_on_grid_soups(
            tris in grid_soup(),
            rays in prop::collection::vec(((-10i32..10, -10i32..10, -10i32..10), direction(), interval()), 64),
        ) {
            let bvh = Bvh::build(tris.clone());
            for ((x, y, z), d, (t0, t1)) in rays {
                let o = DVec3::new(x as f64, y as f64, z as f64) * 0.25;
                check_ray(&bvh, &tris, o, d, t0, t1)?;
                // Axis-aligned and grid-diagonal rays through vertices, edges and box planes.
                let g = d.signum() * DVec3::new((x % 3) as f64, (y % 2) as f64, 1.0);
                check_ray(&bvh, &tris, o, g, t0, t1)?;
            }
        }

        /// The triangle test agrees with an independent plane/barycentric
        /// computation away from edges.
        #[test]
        fn triangle_test_agrees_with_plane_reference(
            a in vec3(5.0), b in vec3(5.0), c in vec3(5.0), o in vec3(10.0), d in direction(),
        ) {
            let t = Triangle::new(a, b, c);
            prop_assume!(!t.is_degenerate());
            let n = (b - a).cross(c - a);
            let denom = n.dot(d);
            // Skip grazing rays, where the reference itself is ill-conditioned.
            prop_assume!(denom.abs() > 1e-3 * n.length() * d.length());
            let t_ref = n.dot(a - o) / denom;
            let p = o + t_ref * d;
            // Barycentrics of p by areas.
            let inv = 1.0 / n.length_squared();
            let u_ref = (a - c).cross(p - c).dot(n) * inv; // weight of b
            let v_ref = (b - a).cross(p - a).dot(n) * inv; // weight of c
            let w_ref = 1.0 - u_ref - v_ref;
            let got = single(&t, o, d, f64::NEG_INFINITY, f64::INFINITY);
            let margin = 1e-7;
            if u_ref > margin && v_ref > margin && w_ref > margin {
                let (tt, u, v) = got.expect("clearly inside, must hit");
                prop_assert!(close(tt, t_ref, 1e-9) || (tt - t_ref).abs() < 1e-9);
                prop_assert!((u - u_ref).abs() < 1e-7 && (v - v_ref).abs() < 1e-7);
                let q = (1.0 - u - v) * a + u * b + v * c;
                prop_assert!((q - (o + tt * d)).length() < 1e-7 * (1.0 + q.length()));
            } else if u_ref < -margin || v_ref < -margin || w_ref < -margin {
                prop_assert!(got.is_none(), "clearly outside, must miss");
            }
        }
    }

    /// A cube `[-1, 1]³` with each face split into `n × n` quads of two
    /// triangles, sharing vertices (bitwise identical positions), outward winding.
    fn tessellated_cube(n: usize) -> Vec<Triangle> {
        let mut tris = Vec::new();
        let s = |i: usize| -1.0 + 2.0 * i as f64 / n as f64;
        for axis in 0..3 {
            for side in [-1.0, 1.0] {
                let point = |i: usize, j: usize| {
                    let mut p = [0.0; 3];
                    p[axis] = side;
                    p[(axis + 1) % 3] = s(i);
                    p[(axis + 2) % 3] = s(j);
                    DVec3::from(p)
                };
                for i in 0..n {
                    for j in 0..n {
                        let (p00, p10, p11, p01) = (point(i, j), point(i + 1, j), point(i + 1, j + 1), point(i, j + 1));
                        if side > 0.0 {
                            tris.push(Triangle::new(p00, p10, p11));
                            tris.push(Triangle::new(p00, p11, p01));
                        } else {
                            tris.push(Triangle::new(p00, p11, p10));
                            tris.push(Triangle::new(p00, p01, p11));
                        }
                    }
                }
            }
        }
        tris
    }

    /// A UV sphere of radius `r` with shared vertices (closed, poles included).
    fn uv_sphere(r: f64, slices: usize, stacks: usize) -> Vec<Triangle> {
        let vert = |i: usize, j: usize| {
            if j == 0 {
                return DVec3::new(0.0, 0.0, r);
            }
            if j == stacks {
                return DVec3::new(0.0, 0.0, -r);
            }
            let phi = std::f64::consts::TAU * (i % slices) as f64 / slices as f64;
            let theta = std::f64::consts::PI * j as f64 / stacks as f64;
            r * DVec3::new(theta.sin() * phi.cos(), theta.sin() * phi.sin(), theta.cos())
        };
        let mut tris = Vec::new();
        for j in 0..stacks {
            for i in 0..slices {
                let (a, b, c, d) = (vert(i, j), vert(i + 1, j), vert(i + 1, j + 1), vert(i, j + 1));
                if j != 0 {
                    tris.push(Triangle::new(a, d, b));
                }
                if j != stacks - 1 {
                    tris.push(Triangle::new(b, d, c));
                }
            }
        }
        tris
    }

    /// Deterministic pseudo-random numbers in `[0, 1)` (SplitMix64).
    fn rng(seed: u64) -> impl FnMut() -> f64 {
        let mut s = seed;
        move || {
            s = s.wrapping_add(0x9E37_79B9_7F4A_7C15);
            let mut z = s;
            z = (z ^ (z >> 30)).wrapping_mul(0xBF58_476D_1CE4_E5B9);
            z = (z ^ (z >> 27)).wrapping_mul(0x94D0_49BB_1331_11EB);
            z ^= z >> 31;
            (z >> 11) as f64 / (1u64 << 53) as f64
        }
    }

    #[test]
    fn ray_through_shared_edge_hits() {
        // Unit square in z = 0 split along its diagonal.
        let tris = vec![
            tri([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [1.0, 1.0, 0.0]),
            tri([0.0, 0.0, 0.0], [1.0, 1.0, 0.0], [0.0, 1.0, 0.0]),
        ];
        let bvh = Bvh::build(tris);
        for k in 1..100 {
            let s = k as f64 / 100.0;
            let o = DVec3::new(s, s, 1.0);
            let hit = bvh.closest_hit(o, -DVec3::Z, 0.0, f64::INFINITY).expect("edge ray must hit");
            assert_eq!(hit.t, 1.0);
            // Oblique rays aimed at the diagonal from elsewhere.
            let o2 = DVec3::new(0.3, -0.7, 2.5);
            let d = DVec3::new(s, s, 0.0) - o2;
            let hit = bvh.closest_hit(o2, d, 0.0, f64::INFINITY).expect("oblique edge ray must hit");
            assert!(close(hit.t, 1.0, 1e-12));
        }
    }

    #[test]
    fn closed_cube_is_watertight() {
        for n in [1, 3, 4, 7] {
            let tris = tessellated_cube(n);
            let bvh = Bvh::build(tris);
            let mut rnd = rng(n as u64);
            let mut origins = vec![DVec3::ZERO, DVec3::new(0.5, 0.0, 0.0), DVec3::new(0.25, -0.5, 0.75)];
            for _ in 0..20 {
                origins.push(DVec3::new(rnd() * 1.8 - 0.9, rnd() * 1.8 - 0.9, rnd() * 1.8 - 0.9));
            }
            // Targets exactly on grid lines (shared edges), on quad diagonals,
            // at vertices, and on the cube's edges and corners.
            let mut targets = Vec::new();
            let g = |i: usize| -1.0 + 2.0 * i as f64 / n as f64;
            for axis in 0..3 {
                for side in [-1.0, 1.0] {
                    for i in 0..=n {
                        for j in 0..=(4 * n) {
                            let mut p = [0.0; 3];
                            p[axis] = side;
                            p[(axis + 1) % 3] = g(i);
                            p[(axis + 2) % 3] = -1.0 + 2.0 * j as f64 / (4 * n) as f64;
                            targets.push(DVec3::from(p));
                            p[(axis + 1) % 3] = -1.0 + 2.0 * j as f64 / (4 * n) as f64;
                            p[(axis + 2) % 3] = g(i);
                            targets.push(DVec3::from(p));
                        }
                    }
                    for i in 0..n {
                        for j in 0..n {
                            let f = rnd();
                            let mut p = [0.0; 3];
                            p[axis] = side;
                            p[(axis + 1) % 3] = g(i) + f * (g(i + 1) - g(i));
                            p[(axis + 2) % 3] = g(j) + f * (g(j + 1) - g(j));
                            targets.push(DVec3::from(p));
                        }
                    }
                }
            }
            for &o in &origins {
                for &p in &targets {
                    let d = p - o;
                    let hit = bvh.closest_hit(o, d, 0.0, f64::INFINITY);
                    assert!(hit.is_some(), "n {n}: ray {o} -> {p} escaped the closed cube");
                    assert!(close(hit.unwrap().t, 1.0, 1e-9), "n {n}: ray {o} -> {p} t {}", hit.unwrap().t);
                    assert!(bvh.any_hit(o, d, 0.0, f64::INFINITY));
                }
                // Axis-aligned and random directions.
                for d in [DVec3::X, -DVec3::X, DVec3::Y, -DVec3::Y, DVec3::Z, -DVec3::Z] {
                    assert!(bvh.closest_hit(o, d, 0.0, f64::INFINITY).is_some(), "axis ray {o} {d}");
                }
                for _ in 0..500 {
                    let d = DVec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5);
                    let hit = bvh.closest_hit(o, d, 0.0, f64::INFINITY).expect("random ray escaped");
                    // Exit distance from a point inside the cube.
                    let t_exit = (0..3)
                        .map(|k| {
                            if d[k] > 0.0 {
                                (1.0 - o[k]) / d[k]
                            } else if d[k] < 0.0 {
                                (-1.0 - o[k]) / d[k]
                            } else {
                                f64::INFINITY
                            }
                        })
                        .fold(f64::INFINITY, f64::min);
                    assert!(close(hit.t, t_exit, 1e-9));
                }
            }
        }
    }

    #[test]
    fn closed_sphere_is_watertight() {
        let tris = uv_sphere(1.0, 48, 24);
        let bvh = Bvh::build(tris.clone());
        let mut rnd = rng(7);
        // Rays aimed exactly at every vertex and at every edge midpoint.
        let mut targets = Vec::new();
        for t in &tris {
            for k in 0..3 {
                targets.push(t.v[k]);
                targets.push(0.5 * (t.v[k] + t.v[(k + 1) % 3]));
            }
        }
        for s in 0..30 {
            let o = if s == 0 {
                DVec3::ZERO
            } else {
                DVec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5)
            };
            for &p in &targets {
                assert!(bvh.closest_hit(o, p - o, 0.0, f64::INFINITY).is_some(), "ray {o} -> {p} escaped");
                assert!(bvh.any_hit(o, p - o, 0.0, f64::INFINITY));
            }
            for _ in 0..2000 {
                let d = DVec3::new(rnd() - 0.5, rnd() - 0.5, rnd() - 0.5);
                assert!(bvh.closest_hit(o, d, 0.0, f64::INFINITY).is_some(), "random ray escaped");
            }
        }
    }

    #[test]
    fn exact_fallback_signs_products_that_round_equal() {
        // fl(p·q) == fl(r·s) but p·q − r·s = 2^-60 exactly.
        let (p, q, r, s) = (1.0 + 2f64.powi(-30), 1.0 + 2f64.powi(-30), 1.0 + 2f64.powi(-29), 1.0);
        assert_eq!(p * q - r * s, 0.0);
        assert_eq!(exact_zero_diff(p, q, r, s), 2f64.powi(-60));
        // Swapping the products negates exactly (what keeps shared edges consistent).
        assert_eq!(exact_zero_diff(r, s, p, q), -2f64.powi(-60));
        assert_eq!(exact_zero_diff(q, p, s, r), 2f64.powi(-60));
        assert_eq!(exact_zero_diff(2.0, 3.0, 3.0, 2.0), 0.0);
    }

    #[test]
    fn extreme_inputs_do_not_panic() {
        // Within the documented range of 1e100, and beyond it (no hit, no panic).
        let big = 1e100;
        let mut tris = vec![
            tri([f64::NAN, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]),
            tri([-big, -big, 1.0], [big, -big, 1.0], [0.0, big, 1.0]),
            tri([f64::MAX, 0.0, 2.0], [-f64::MAX, 0.0, 2.0], [0.0, f64::MAX, 2.0]),
            tri([0.0, 0.0, 3.0], [1e-300, 0.0, 3.0], [0.0, 1e-300, 3.0]),
            tri([-1e307, -1e307, 4.0], [1e307, -1e307, 4.0], [0.0, 1e307, 4.0]),
        ];
        tris.extend(std::iter::repeat_n(tri([-1.0, -1.0, 5.0], [1.0, -1.0, 5.0], [0.0, 1.0, 5.0]), 40));
        let bvh = Bvh::build(tris);
        assert_eq!(bvh.triangle_count(), 45);
        assert!(bvh.triangle(2).is_degenerate()); // its edge vectors overflow
        let hit = bvh.closest_hit(DVec3::ZERO, DVec3::Z, 0.0, f64::INFINITY).unwrap();
        assert_eq!((hit.triangle, hit.t), (1, 1.0));
        let hit = bvh.closest_hit(DVec3::new(0.0, 0.0, 2.5), DVec3::Z, 0.0, f64::INFINITY).unwrap();
        // The f64::MAX triangle is degenerate and the 1e307 one overflows: z = 5 is hit.
        assert_eq!(hit.t, 2.5);
        assert!(hit.triangle >= 5);
        for d in [
            DVec3::X,
            DVec3::new(1e-300, 0.0, 1.0),
            DVec3::splat(1e300),
            DVec3::new(-1e-310, 1e-310, 0.0),
        ] {
            for o in [DVec3::ZERO, DVec3::splat(-1e306), DVec3::new(0.0, 0.0, 4.0)] {
                let _ = bvh.closest_hit(o, d, 0.0, f64::INFINITY);
                let _ = bvh.any_hit(o, d, f64::NEG_INFINITY, f64::INFINITY);
            }
        }
    }

    #[test]
    fn empty_bvh_returns_none() {
        let bvh = Bvh::build(Vec::new());
        assert_eq!(bvh.triangle_count(), 0);
        assert_eq!(bvh.bounds(), None);
        assert_eq!(bvh.closest_hit(DVec3::ZERO, DVec3::X, 0.0, f64::INFINITY), None);
        assert!(!bvh.any_hit(DVec3::ZERO, DVec3::X, 0.0, f64::INFINITY));
    }

    #[test]
    fn degenerate_triangles_are_ignored() {
        let degenerate = vec![
            tri([0.0, 0.0, 1.0], [0.0, 0.0, 1.0], [0.0, 0.0, 1.0]),  // a point
            tri([-1.0, 0.0, 2.0], [1.0, 0.0, 2.0], [1.0, 0.0, 2.0]), // repeated vertex
            tri([-1.0, 0.0, 3.0], [0.0, 0.0, 3.0], [1.0, 0.0, 3.0]), // collinear
            tri([0.1, 0.2, 0.3], [0.2, 0.4, 0.6], [0.3, 0.6, 0.9]),  // collinear up to rounding
            tri([-1.0, -1.0, 4.0], [1.0, 1.0, 4.0], [-1e-300, -1e-300, 4.0]),
        ];
        let bvh = Bvh::build(degenerate.clone());
        assert_eq!(bvh.triangle_count(), 5);
        assert_eq!(bvh.bounds(), None);
        for t in &degenerate {
            assert!(t.is_degenerate());
            let c = (t.v[0] + t.v[1] + t.v[2]) / 3.0;
            for d in [DVec3::Z, DVec3::new(0.0, 0.01, 1.0), DVec3::new(0.3, -0.2, 1.0)] {
                let o = c - d;
                assert_eq!(bvh.closest_hit(o, d, f64::NEG_INFINITY, f64::INFINITY), None);
                assert!(!bvh.any_hit(o, d, f64::NEG_INFINITY, f64::INFINITY));
            }
        }
        // Mixed with a valid triangle behind them: the valid one is reported.
        let mut tris = degenerate.clone();
        tris.push(tri([-2.0, -2.0, 10.0], [2.0, -2.0, 10.0], [0.0, 2.0, 10.0]));
        let bvh = Bvh::build(tris);
        let hit = bvh.closest_hit(DVec3::new(0.0, 0.0, 0.0), DVec3::Z, 0.0, f64::INFINITY).unwrap();
        assert_eq!(hit.triangle, 5);
        assert_eq!(hit.t, 10.0);
        assert_eq!(bvh.triangle(2), &degenerate[2]);
        // Non-finite vertices are degenerate too.
        assert!(tri([f64::NAN, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]).is_degenerate());
        assert!(tri([f64::INFINITY, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]).is_degenerate());
        // Tiny but proper triangles are not.
        assert!(!tri([0.0, 0.0, 0.0], [1e-200, 0.0, 0.0], [0.0, 1e-200, 0.0]).is_degenerate());
        assert!(!tri([1e200, 0.0, 0.0], [-1e200, 0.0, 0.0], [0.0, 1e200, 0.0]).is_degenerate());
    }

    #[test]
    fn axis_aligned_rays_on_box_planes() {
        // Triangle in x = 1 with edges on y = 0 and z = 0: the rays below run in
        // the planes of its bounding box, where 0 · ∞ = NaN in a naive slab test.
        let t = tri([1.0, 0.0, 0.0], [1.0, 1.0, 0.0], [1.0, 0.0, 1.0]);
        let bvh = Bvh::build(vec![t; 9]);
        for (o, d) in [
            (DVec3::new(0.0, 0.0, 0.5), DVec3::X),
            (DVec3::new(0.0, 0.25, 0.0), DVec3::X),
            (DVec3::new(0.0, 0.0, 0.0), DVec3::X),
            (DVec3::new(0.0, 0.25, 0.0), DVec3::new(1.0, -0.0, -0.0)),
            (DVec3::new(3.0, 0.5, 0.0), DVec3::new(-2.0, 0.0, 0.0)),
            (DVec3::new(1.5, 0.0, 0.25), DVec3::new(-1.0, 0.0, -0.0)),
        ] {
            let hit = bvh
                .closest_hit(o, d, 0.0, f64::INFINITY)
                .unwrap_or_else(|| panic!("ray {o} {d} missed"));
            let p = o + hit.t * d;
            assert!(p.x == 1.0 || (p.x - 1.0).abs() < 1e-15);
            assert!(bvh.any_hit(o, d, 0.0, f64::INFINITY));
        }
        // Just outside the box: miss.
        assert!(!bvh.any_hit(DVec3::new(0.0, -1e-300, 0.5), DVec3::X, 0.0, f64::INFINITY));
        assert!(bvh.closest_hit(DVec3::new(0.0, 0.5, 1.0), DVec3::X, 0.0, f64::INFINITY).is_none());
    }

    #[test]
    fn hit_reports_barycentrics_and_interval() {
        let t = tri([0.0, 0.0, 5.0], [4.0, 0.0, 5.0], [0.0, 4.0, 5.0]);
        let bvh = Bvh::build(vec![t]);
        let o = DVec3::new(1.0, 2.0, 1.0);
        let d = DVec3::new(0.0, 0.0, 2.0); // non-unit: t in units of |dir|
        let hit = bvh.closest_hit(o, d, 0.0, f64::INFINITY).unwrap();
        assert_eq!(hit.triangle, 0);
        assert!(close(hit.t, 2.0, 1e-15));
        assert!(close(hit.u, 0.25, 1e-15) && close(hit.v, 0.5, 1e-15));
        assert_eq!(bvh.bounds(), Some((DVec3::new(0.0, 0.0, 5.0), DVec3::new(4.0, 4.0, 5.0))));
        // Interval ends are inclusive and respected.
        assert!(bvh.closest_hit(o, d, 0.0, 2.0).is_some());
        assert!(bvh.closest_hit(o, d, 2.0, 2.0).is_some());
        assert!(bvh.closest_hit(o, d, 0.0, 1.999).is_none());
        assert!(bvh.closest_hit(o, d, 2.001, 9.0).is_none());
        assert!(!bvh.any_hit(o, d, 0.0, 1.999));
        // Behind the origin only with a negative interval.
        assert!(bvh.closest_hit(o, -d, 0.0, f64::INFINITY).is_none());
        assert!(close(bvh.closest_hit(o, -d, f64::NEG_INFINITY, 0.0).unwrap().t, -2.0, 1e-15));
        // Invalid rays do not hit and do not panic.
        for (o2, d2, a, b) in [
            (o, DVec3::ZERO, 0.0, f64::INFINITY),
            (o, d, 1.0, 0.0),
            (o, d, f64::NAN, 1.0),
            (o, DVec3::new(f64::NAN, 0.0, 1.0), 0.0, 1.0),
            (DVec3::splat(f64::INFINITY), d, 0.0, 1.0),
        ] {
            assert!(bvh.closest_hit(o2, d2, a, b).is_none());
            assert!(!bvh.any_hit(o2, d2, a, b));
        }
    }

    #[test]
    fn nearest_of_stacked_triangles_and_original_indices() {
        // 1000 parallel triangles at z = i, shuffled: the nearest in z is reported with its input index.
        let mut rnd = rng(3);
        let mut zs: Vec<usize> = (0..1000).collect();
        for i in (1..zs.len()).rev() {
            zs.swap(i, (rnd() * (i + 1) as f64) as usize);
        }
        let tris: Vec<Triangle> = zs
            .iter()
            .map(|&z| tri([-1.0, -1.0, z as f64], [1.0, -1.0, z as f64], [0.0, 1.0, z as f64]))
            .collect();
        let bvh = Bvh::build(tris.clone());
        for start in [0.5, 10.5, 500.5, 998.5] {
            let hit = bvh.closest_hit(DVec3::new(0.0, 0.0, start), DVec3::Z, 0.0, f64::INFINITY).unwrap();
            assert_eq!(hit.t, 0.5);
            assert_eq!(tris[hit.triangle as usize].v[0].z, start + 0.5);
            let hit = bvh.closest_hit(DVec3::new(0.0, 0.0, start), -DVec3::Z, 0.0, f64::INFINITY).unwrap();
            assert_eq!(tris[hit.triangle as usize].v[0].z, start - 0.5);
        }
    }

    #[test]
    fn leaves_and_depth_are_bounded() {
        fn depth_and_max_leaf(bvh: &Bvh, node: usize) -> (usize, usize) {
            let n = &bvh.nodes[node];
            if n.count > 0 {
                return (1, n.count as usize);
            }
            let (dl, ll) = depth_and_max_leaf(bvh, n.first as usize);
            let (dr, lr) = depth_and_max_leaf(bvh, n.first as usize + 1);
            (1 + dl.max(dr), ll.max(lr))
        }
        // Coincident triangles (no centroid spread), a long thin strip of
        // geometrically growing triangles (worst case for SAH depth), and a soup.
        let same = vec![tri([0.0, 0.0, 0.0], [1.0, 0.0, 0.0], [0.0, 1.0, 0.0]); 1000];
        let strip: Vec<Triangle> = (0..1000)
            .map(|i| {
                let x = 1.02f64.powi(i);
                tri([x, 0.0, 0.0], [x * 1.01, 0.0, 0.0], [x, 1.0, 0.0])
            })
            .collect();
        let mut rnd = rng(11);
        let soup: Vec<Triangle> = (0..10_000)
            .map(|_| {
                let c = DVec3::new(rnd(), rnd(), rnd()) * 100.0;
                Triangle::new(c, c + DVec3::new(rnd(), rnd(), rnd()), c + DVec3::new(rnd(), rnd(), rnd()))
            })
            .collect();
        for tris in [same, strip, soup] {
            let n = tris.len();
            let bvh = Bvh::build(tris.clone());
            let (depth, leaf) = depth_and_max_leaf(&bvh, 0);
            assert!(leaf <= MAX_LEAF);
            assert!(depth <= MAX_SAH_DEPTH as usize + 33, "depth {depth}");
            // Every triangle appears exactly once in the leaves.
            let mut ids = bvh.leaf_ids.clone();
            ids.sort_unstable();
            assert_eq!(ids, (0..n as u32).collect::<Vec<_>>());
            let (lo, hi) = bvh.bounds().unwrap();
            for t in &tris {
                for v in t.v {
                    assert!(v.cmpge(lo).all() && v.cmple(hi).all());
                }
            }
            // And every one is found by a ray aimed at its centroid from outside.
            for t in tris.iter().step_by(7) {
                let c = (t.v[0] + t.v[1] + t.v[2]) / 3.0;
                let o = c + DVec3::new(0.1, 0.2, -1.0);
                let hit = bvh.closest_hit(o, c - o, 0.0, f64::INFINITY).expect("centroid ray");
                // Grazing hits carry a larger rounding error in t.
                assert!(hit.t <= 1.0 + 1e-6, "{t:?} {hit:?}");
            }
        }
    }
}
