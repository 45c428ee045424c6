//! The pixel filter across a spot's beam from its angular profile, without
//! lattice rays.
//!
//! **Why.** Where a beam is a few pixels wide, every pixel near it needs the
//! filter integral, and the adaptive lattice of [`super::filter`] spends
//! ≈ 14 view rays per such pixel refining across the beam's edges
//! (docs/benchmarks.md, eighteenth session). Those edges come from the
//! light's angular profile alone, which is known in closed form.
//!
//! **The model** (exact, not a thin-cone approximation). Let the view ray
//! run from `o` along the unit `d`, and `L` be the light. The ray and the
//! light span a plane with unit normal `m̂ ∝ (o − L) × d`; the light's axis
//! `a` makes the angle `ψ`, `sin ψ = |m̂·a|`, with it. Seen from the light,
//! the ray's points sweep that plane by the angle `u` of Nishita's
//! substitution (`t = t_c + h tan u`, `dt/r² = du/h`, `h` the ray's distance
//! from the light), and a direction at in-plane angle `v` from the axis's
//! projection `p̂` makes `cos θ = cos ψ · cos v` with the axis (a right
//! spherical triangle). So the in-scatter of an axisymmetric light
//! `I(θ)` is (stage.rs, Nishita et al. 1987 eqs 1–3)
//!
//! `L = (1/h) ∫ I(θ(u)) S(u) du`, `S = Σ σ_s p(μ) · T(eye→x) · T(x→light)`,
//!
//! and when the ray crosses the whole cone (it starts and ends outside it,
//! with `p̂` between the directions of its ends), `L = G · A(ψ)` with
//!
//! `A(ψ) = ∫ I(arccos(cos ψ cos v)) dv` — the light's profile integrated
//! across the cone along a great circle at distance `ψ` from the axis (a
//! spherical Abel transform, one table per light: 64 cells where their
//! error is within 5 % of the tolerance, else 256), and `G` the
//! `I`-weighted mean of `S/h` along the chord. `A` holds the beam's edges;
//! `G` is smooth wherever the chord is whole, unshadowed and inside media
//! without boundaries: the chord is symmetric in `v`, so `G` depends on the
//! chord's half-width only through even powers, with no square-root edge.
//!
//! **Partial chords.** Where the ray starts inside the cone (the camera in
//! the beam) or ends inside it (the floor under a spot), only the angles
//! `[lo, hi] ⊂ [−c, c]` of the chord are on the ray, and `A` is the profile
//! integrated over those (exact per node: Gauss–Legendre on the pieces
//! between the profile's kinks, 8 nodes against 4 for its error). `G` is
//! again a weighted mean of `S/h` over the part of the chord on the ray,
//! smooth in the pixel position; the footprint's edge, where the ray's end
//! crosses the cone, is in `A`, exactly.
//!
//! **The filter.** The centre samples give `G = L/A(ψ)` where the centre
//! lies well inside the cone. To interpolate across pixels whose centres
//! miss the beam, `G` is written as `ρ·G₀` with `G₀ = S(x₀)/h` at the
//! ray's point `x₀` in the direction `p̂` (closed form from the media, at
//! every centre inside the cone or not) and `ρ` (≈ 1, per colour channel)
//! taken from the samples and extended outwards from its known values.
//! Both are interpolated to a ¼ px grid of nodes (Catmull–Rom, and
//! bilinear for the estimate), multiplied by the exact `A(ψ)` of each node's
//! ray — no ray is traced at a node, `ψ` is geometry — and integrated
//! against Blender's window by the trapezoid rule on the node grid (the
//! window is 0 with its derivatives at its ends).
//!
//! **Error estimate** of a pixel, per channel: the window integral of the
//! nodes' `|Catmull–Rom − bilinear|` (no cancellation between nodes) and of
//! the extended `ρ`'s spread wherever it is used, plus the difference
//! between the ¼ px and ½ px trapezoid sums, plus the samples' own errors
//! and the profile table's error, each relative to the value. A pixel is
//! served here only when that meets the tolerance, and otherwise goes to
//! the lattice, as does every pixel whose nodes' chords differ between the
//! surfaces of the centres around them, whose nodes' or centres' chords may
//! be shadowed (asked of the ray up to the chord's end) or touch another
//! light's cone, whose beam is narrower than 2 px (8 node spacings) at the
//! stencil's steepest `ψ`, which lies within 3.5 px of a light's image or
//! 3 px of the frame. Where the transmittance is filtered too and is not
//! smooth in the window, the lattice also takes the pixel for it, and the
//! in-scatter stays the profile's (so requesting the transmittance layer
//! does not change the in-scatter).
//!
//! **Beams narrower than 2 px** ([`serve_thin_all`]): the centre samples can
//! miss such a beam altogether (a 0.5° spot, any spot near its apex), so
//! every pixel whose window it crosses is flagged by geometry alone
//! ([`thin_beam_pixels`]), and integrated in the beam's own coordinates,
//! a rotation of the image's: along its centre line (`ψ = 0`, a straight
//! line in the image) by the trapezoid rule on nodes ¼ px apart that every
//! pixel along the beam shares (every other one for the estimate), across
//! it between the band's exact edges (Gauss–Legendre 16 against 8), with
//! `G` quadratic through three exact rays per node and the quadratic's
//! departure from a line charged as its error. Before this, such beams
//! were left out of the filter: a 0.5° beam 30 m away rendered 19 %
//! relative RMSE with estimates of 0. A beam narrower than ½ px
//! ([`LATTICE_BLIND_PX`]) stays here even where its estimate misses the
//! tolerance, and where it only clips a window's corner: the lattice's
//! cells would not see it at all.
//!
//! Only for scenes whose in-scatter all comes from Blender spot lamps
//! (smooth between their kinks, no IES, cones narrower than a hemisphere)
//! in media without boundaries, with no suns, ambient light or windows
//! (the conditions of [`super::smooth`], which supplies the planes and
//! casters).

use super::filter::{PixelFilter, UnitSteps};
use super::smooth::{Casters, Planes};
use crate::geometry::camera::CameraRays;
use crate::light::PointSource;
use crate::medium::PreparedMedium;
use glam::DVec3;
use rayon::prelude::*;

/// Nodes per pixel along each axis. (8 per px cost twice the time for
/// 0.80 % instead of 0.87 % relative RMSE on the narrow beam at tolerance 0.3.)
const NODES_PER_PX: usize = 4;
/// Half the stencil of centres a pixel's nodes read (Catmull–Rom from
/// ±1.5 px of the centre reaches 3 px away).
const STENCIL: usize = 3;
/// A centre's `ρ` is read from its sample where `A(ψ)` is at least this
/// fraction of the light's `A(0)` (nearer the edge `L` and `A` are both
/// small, and `ρ` would carry their relative errors).
const KNOWN_FRACTION: f64 = 0.05;
/// The narrowest beam served, in node spacings across its full width, at
/// the steepest `sin ψ` of the pixel's stencil.
const MIN_BEAM_NODES: f64 = 8.0;
/// Pixels within this many px of a light's image are left to the lattice
/// (`G ∝ 1/h` is not smooth at the light).
pub(crate) const LIGHT_IMAGE_MARGIN: f64 = 3.5;
/// Tiles of candidate pixels share their nodes, px a side.
const TILE: usize = 16;
/// Profile table cells (uniform in `q = √(1 − sin ψ / sin ψ_max)`, dense at
/// the edge): the fine table, and the coarse one tried first where the
/// tolerance is loose.
const TABLE_CELLS: usize = 256;
/// The coarse table's cells (a quarter of [`TABLE_CELLS`]: its grid points are the fine one's).
const COARSE_TABLE_CELLS: usize = 64;
/// The coarse table is kept when its error, relative to a known centre's
/// `A` (`error / (KNOWN_FRACTION · peak)`, the share it adds to every
/// profile pixel's estimate), is at most this fraction of the tolerance.
/// (Narrow beam: 64 cells 8.7e-4 of the peak, 1.7e-2 relative; 256 cells
/// 6.6e-5 and 1.3e-3. The table was 5 % of a 96×54 render at tolerance 0.5.)
const COARSE_TABLE_SHARE: f64 = 0.05;

/// `A(ψ)` of one light, tabulated in `q = √(1 − s/s_max)`, `s = sin ψ`: a
/// hard cone edge makes `A` a square root of the distance to the edge,
/// linear in `q`.
pub(crate) struct ProfileTable {
    s_max: f64,
    cos_reach: f64,
    kinks: Vec<f64>,
    /// The profile `I(cos θ)` (the light's `factor_cos`), for partial chords.
    profile: std::sync::Arc<dyn Fn(f64) -> f64 + Send + Sync>,
    values: Vec<f64>,
    /// Cells (`values.len() − 1`).
    cells: usize,
    /// Largest difference between the table's interpolant and `A` at its
    /// cells' midpoints, absolute.
    pub error: f64,
    /// `A(0)`.
    pub peak: f64,
}

impl ProfileTable {
    /// The table of an axial light ([`PointSource::is_axial`], `cos_reach > 0`)
    /// for renders at relative tolerance `tolerance`: [`COARSE_TABLE_CELLS`]
    /// where that is within [`COARSE_TABLE_SHARE`] of it, else [`TABLE_CELLS`].
    pub(crate) fn new<const C: usize>(light: &PointSource<C>, tolerance: f64) -> ProfileTable {
        let coarse = Self::half_grid(light, COARSE_TABLE_CELLS, None);
        let table = Self::from_half_grid(light, COARSE_TABLE_CELLS, &coarse);
        if table.error <= COARSE_TABLE_SHARE * tolerance * KNOWN_FRACTION * table.peak {
            return table;
        }
        // Every point of the coarse grid is one of the fine grid's: the
        // fine table costs no more integrals than if it were built alone.
        let fine = Self::half_grid(light, TABLE_CELLS, Some(&coarse));
        Self::from_half_grid(light, TABLE_CELLS, &fine)
    }

    /// `A` at `q = j/(2·cells)`, `j = 0..=2·cells`: the table's nodes (even
    /// `j`) and the midpoints its error is probed at (odd `j`). `coarser`,
    /// the same for a table of `cells/4` cells, gives every fourth point.
    fn half_grid<const C: usize>(light: &PointSource<C>, cells: usize, coarser: Option<&[f64]>) -> Vec<f64> {
        let cos_reach = light.cos_reach;
        let s_max = (1.0 - cos_reach * cos_reach).max(0.0).sqrt();
        let kinks = light.kinks();
        let kinks = kinks.as_slice();
        let abel = |s: f64| -> f64 {
            let cos_psi = (1.0 - s * s).max(0.0).sqrt();
            if cos_psi <= cos_reach {
                return 0.0;
            }
            // v runs over [0, c]: the chord's half in the great circle.
            let c = (cos_reach / cos_psi).clamp(-1.0, 1.0).acos();
            let mut cuts: Vec<f64> = kinks
                .iter()
                .filter(|k| **k < cos_psi)
                .map(|k| (k / cos_psi).clamp(-1.0, 1.0).acos())
                .filter(|v| *v > 0.0 && *v < c)
                .collect();
            cuts.push(0.0);
            cuts.push(c);
            cuts.sort_by(f64::total_cmp);
            let mut total = 0.0;
            for pair in cuts.windows(2) {
                let (mid, half) = (0.5 * (pair[0] + pair[1]), 0.5 * (pair[1] - pair[0]));
                total += GL16
                    .iter()
                    .map(|&(u, w)| w * light.factor_cos(cos_psi * (mid + half * u).cos()))
                    .sum::<f64>()
                    * half;
            }
            2.0 * total
        };
        let points = 2 * cells;
        (0..=points)
            .into_par_iter()
            .map(|j| match coarser {
                Some(known) if j % 4 == 0 => known[j / 4],
                _ => {
                    let q = j as f64 / points as f64;
                    abel(s_max * (1.0 - q * q))
                }
            })
            .collect()
    }

    /// The table of `cells` cells from its [`Self::half_grid`].
    fn from_half_grid<const C: usize>(light: &PointSource<C>, cells: usize, grid: &[f64]) -> ProfileTable {
        let cos_reach = light.cos_reach;
        let shape = light.clone();
        let profile: std::sync::Arc<dyn Fn(f64) -> f64 + Send + Sync> = std::sync::Arc::new(move |c| shape.factor_cos(c));
        let values: Vec<f64> = grid.iter().step_by(2).copied().collect();
        let error = (0..cells)
            .map(|i| (grid[2 * i + 1] - 0.5 * (values[i] + values[i + 1])).abs())
            .fold(0.0f64, f64::max);
        ProfileTable {
            s_max: (1.0 - cos_reach * cos_reach).max(0.0).sqrt(),
            cos_reach,
            kinks: light.kinks().as_slice().to_vec(),
            profile,
            peak: values[cells],
            values,
            cells,
            error,
        }
    }

    /// `q` of `s = sin ψ` and the chord's half-width `c` (rad) in the ray's plane.
    #[inline]
    fn chord_half_width(&self, s: f64) -> f64 {
        let cos_psi = (1.0 - s * s).max(0.0).sqrt();
        (self.cos_reach / cos_psi).clamp(-1.0, 1.0).acos()
    }

    /// The part of `A(ψ)` on the chord's angles `[lo, hi]` (rad from the
    /// axis's projection, clamped to `[−c, c]`), and its error: Gauss–Legendre
    /// with 8 nodes on each piece between the profile's kinks (±), its
    /// difference from 4 nodes the estimate. Only chords cut by a surface or
    /// the camera need this, a few nodes per image.
    pub(crate) fn partial(&self, s: f64, lo: f64, hi: f64) -> (f64, f64) {
        let cos_psi = (1.0 - s * s).max(0.0).sqrt();
        if cos_psi <= self.cos_reach {
            return (0.0, 0.0);
        }
        let c = self.chord_half_width(s);
        let (lo, hi) = (lo.max(-c), hi.min(c));
        if hi <= lo {
            return (0.0, 0.0);
        }
        let mut cuts: Vec<f64> = vec![lo, hi];
        for k in self.kinks.iter().filter(|k| **k < cos_psi) {
            let v = (k / cos_psi).clamp(-1.0, 1.0).acos();
            cuts.extend([v, -v].into_iter().filter(|v| *v > lo && *v < hi));
        }
        cuts.sort_by(f64::total_cmp);
        let (mut total, mut error) = (0.0, 0.0);
        for pair in cuts.windows(2) {
            let (mid, half) = (0.5 * (pair[0] + pair[1]), 0.5 * (pair[1] - pair[0]));
            let rule = |nodes: &[(f64, f64)]| {
                nodes
                    .iter()
                    .map(|&(u, w)| w * (self.profile)(cos_psi * (mid + half * u).cos()))
                    .sum::<f64>()
                    * half
            };
            let (g8, g4) = (rule(&GL8), rule(&GL4));
            total += g8;
            error += (g8 - g4).abs();
        }
        (total, error)
    }

    /// `A` at `s = sin ψ` (0 at and beyond the cone's edge).
    #[inline]
    pub(crate) fn eval(&self, s: f64) -> f64 {
        if s.is_nan() || s >= self.s_max {
            return 0.0;
        }
        let q = (1.0 - s / self.s_max).max(0.0).sqrt() * self.cells as f64;
        let i = (q as usize).min(self.cells - 1);
        let f = q - i as f64;
        self.values[i] * (1.0 - f) + self.values[i + 1] * f
    }
}

/// One light as the model sees it.
pub(crate) struct BeamLight {
    position: DVec3,
    axis: DVec3,
    sin_reach: f64,
    /// Whether the medium dims the light path (`casts_shadows`).
    light_path_extinction: bool,
    /// `None` where the light cannot be served.
    table: Option<ProfileTable>,
    /// The ray planes' normals across the image.
    image: ImagePlanes,
}

/// The normal `m = (C − L) × D(p)` of the plane through the light `L` and
/// the camera's ray through image point `p` (`C` the eye, `D` the ray's
/// unnormalised direction, affine in `p`): `m = m₀ + x·mₓ + y·m_y`, so
/// `sin ψ = m·a/|m|` has an affine numerator and a denominator that is the
/// norm of an affine map (convex in `p`). The ray's start on it does not
/// matter: `(C + t·d − L) × d = (C − L) × d`.
#[derive(Clone, Copy)]
struct ImagePlanes {
    m0: DVec3,
    mx: DVec3,
    my: DVec3,
    /// `∇(m·a)`, per px: constant.
    n_grad: [f64; 2],
    /// `|∇(m·a)|`, `|mₓ|`, `|m_y|`.
    n_grad_norm: f64,
    mx_len: f64,
    my_len: f64,
}

impl BeamLight {
    /// `servable`: whether the model can serve its beam at all (false for a
    /// light whose casters may shadow any chord, [`Casters::Any`]: it is then
    /// only another light's cone to keep clear of, and builds no table; with
    /// casters on a plane or in [`Casters::Pyramids`], each chord is asked).
    /// `None` for a camera without ray planes affine in the image point (an
    /// equirectangular one, which has no pixel filter either).
    pub(crate) fn new<const C: usize>(
        light: &PointSource<C>,
        cam: &CameraRays,
        casts_shadows: bool,
        servable: bool,
        tolerance: f64,
    ) -> Option<BeamLight> {
        let axis = light.frame.axis;
        let (d0, dx, dy) = cam.affine_direction()?;
        let w = cam.position - light.position;
        let (m0, mx, my) = (w.cross(d0), w.cross(dx), w.cross(dy));
        let n_grad = [mx.dot(axis), my.dot(axis)];
        let image = ImagePlanes {
            m0,
            mx,
            my,
            n_grad,
            n_grad_norm: n_grad[0].hypot(n_grad[1]),
            mx_len: mx.length(),
            my_len: my.length(),
        };
        Some(BeamLight {
            position: light.position,
            axis,
            sin_reach: (1.0 - light.cos_reach * light.cos_reach).max(0.0).sqrt(),
            light_path_extinction: casts_shadows,
            table: servable.then(|| ProfileTable::new(light, tolerance)),
            image,
        })
    }

    /// `±sin ψ` of the camera's ray through image point `(px, py)`.
    #[inline]
    fn sin_psi_at(&self, px: f64, py: f64) -> f64 {
        let f = &self.image;
        let m = f.m0 + f.mx * px + f.my * py;
        m.dot(self.axis) / m.length()
    }

    /// The beam's centre line in the image, `n(p) = m(p)·a = 0` (straight:
    /// `n` is affine): its point nearest `c` and its unit direction
    /// (`∇n` turned by +90°). `None` where `∇n = 0`.
    fn centre_line(&self, c: [f64; 2]) -> Option<([f64; 2], [f64; 2])> {
        let f = &self.image;
        let gn = f.n_grad_norm;
        if !(gn > 0.0 && gn.is_finite()) {
            return None;
        }
        let n = (f.m0 + f.mx * c[0] + f.my * c[1]).dot(self.axis);
        let (gx, gy) = (f.n_grad[0] / gn, f.n_grad[1] / gn);
        Some(([c[0] - n / gn * gx, c[1] - n / gn * gy], [-gy, gx]))
    }

    /// Where the band `|sin ψ| < sin_reach` crosses the image line
    /// `q + δ·normal` (unit `normal`): `(δ₋, δ₊)`, exactly. Along it
    /// `n = n_q + δ·∂n` and `m = m_q + δ·w` are affine, and `n² <
    /// sin²·|m|²` is a quadratic inequality in `δ`. `None` where it does
    /// not hold between two roots around `δ = 0`.
    fn band_across(&self, q: [f64; 2], normal: [f64; 2]) -> Option<(f64, f64)> {
        let f = &self.image;
        let mq = f.m0 + f.mx * q[0] + f.my * q[1];
        let w = f.mx * normal[0] + f.my * normal[1];
        let (nq, dn) = (mq.dot(self.axis), f.n_grad[0] * normal[0] + f.n_grad[1] * normal[1]);
        let s2 = self.sin_reach * self.sin_reach;
        let a = dn * dn - s2 * w.length_squared();
        let b = 2.0 * (nq * dn - s2 * mq.dot(w));
        let c = nq * nq - s2 * mq.length_squared();
        let disc = b * b - 4.0 * a * c;
        if !(a > 0.0 && c < 0.0 && disc > 0.0) {
            return None;
        }
        // Stable roots (c < 0 < a: one of each sign).
        let t = -0.5 * (b + b.signum() * disc.sqrt());
        let (r1, r2) = (t / a, c / t);
        let (lo, hi) = (r1.min(r2), r1.max(r2));
        (lo.is_finite() && hi.is_finite()).then_some((lo, hi))
    }

    /// `±sin ψ` at image point `q` and its gradient, per px (exact).
    fn s_and_gradient(&self, q: [f64; 2]) -> (f64, [f64; 2]) {
        let f = &self.image;
        let m = f.m0 + f.mx * q[0] + f.my * q[1];
        let len = m.length();
        let s = m.dot(self.axis) / len;
        // ∇(n/|m|) = ∇n/|m| − n·(m·∇m)/|m|³.
        let g = [
            (f.n_grad[0] - s * m.dot(f.mx) / len) / len,
            (f.n_grad[1] - s * m.dot(f.my) / len) / len,
        ];
        (s, g)
    }

    /// Whether the cone's band `|sin ψ| < sin_reach` may reach the square
    /// `c ± half` px of the image ([`Self::band_may_touch_rect`]).
    fn band_may_touch(&self, c: [f64; 2], half: f64) -> bool {
        self.band_may_touch_rect(c, [half, half])
    }

    /// Whether the cone's band `|sin ψ| < sin_reach` may reach the
    /// rectangle `c ± half` px of the image: conservative and exact in its
    /// bounds (no linearisation). Over the rectangle the affine numerator's
    /// least magnitude is at least `|n(c)| − |∂ₓn|·half₀ − |∂_y n|·half₁`,
    /// and the denominator is at most `|m(c)| + |mₓ|·half₀ + |m_y|·half₁`
    /// (triangle inequality); the band misses the rectangle when the first
    /// exceeds `sin_reach` times the second.
    fn band_may_touch_rect(&self, c: [f64; 2], half: [f64; 2]) -> bool {
        let f = &self.image;
        let m = f.m0 + f.mx * c[0] + f.my * c[1];
        let n_min = (m.dot(self.axis).abs() - f.n_grad[0].abs() * half[0] - f.n_grad[1].abs() * half[1]).max(0.0);
        let den_max = m.length() + f.mx_len * half[0] + f.my_len * half[1];
        // A NaN anywhere makes it incomparable: the band may touch.
        let bound = (self.sin_reach * (1.0 + 1e-9) + 1e-12) * den_max;
        n_min.partial_cmp(&bound) != Some(std::cmp::Ordering::Greater)
    }

    /// The beam's full width across the image at `c`, px: `2·sin_reach`
    /// over the gradient of `sin ψ` where `sin ψ = 0`, i.e. `|∇n|/|m|`.
    /// 0 at the light's image, ∞ where `∇n = 0`, NaN where both vanish.
    fn width_px_at(&self, c: [f64; 2]) -> f64 {
        let f = &self.image;
        let m = f.m0 + f.mx * c[0] + f.my * c[1];
        2.0 * self.sin_reach * m.length() / f.n_grad_norm
    }

    /// The beam's width across the image at `c`, px (NaN where it cannot
    /// be told), where its band may reach the square `c ± half` px; `None`
    /// where it misses it ([`super::filter::AdaptiveFilterJob::beam_width`]).
    pub(crate) fn width_in_square(&self, c: [f64; 2], half: f64) -> Option<f64> {
        self.band_may_touch(c, half).then(|| self.width_px_at(c))
    }

    /// Whether this light's beam, where narrower than [`THIN_BEAM_PX`],
    /// crosses the window (`c ± radius`) of the pixel centred at `c`: its
    /// centre samples may all miss it, so the pixel needs the filter
    /// integral although its samples are flat. Conservative: true where it
    /// cannot tell.
    fn thin_beam_touches(&self, c: [f64; 2], radius: f64) -> bool {
        let width = self.width_px_at(c);
        // NaN (0/0) counts as thin; a beam edge-on to the image (∇n = 0:
        // the band is all or nothing) as wide.
        (width.is_nan() || width < THIN_BEAM_PX) && self.band_may_touch(c, radius)
    }

    /// `(±sin ψ, h, m)` of the ray from `o` along unit `d`: `m = (o − L) × d`,
    /// `h = |m|`; the sign tells the axis's sides apart.
    #[inline]
    fn plane_of(&self, o: DVec3, d: DVec3) -> (f64, f64, DVec3) {
        let m = (o - self.position).cross(d);
        let h = m.length();
        (m.dot(self.axis) / h, h, m)
    }
}

/// What the model reads of the render.
pub(crate) struct ProfileInput<'a, const C: usize> {
    pub cam: &'a CameraRays,
    pub width: usize,
    pub height: usize,
    pub filter: PixelFilter,
    pub tolerance: f64,
    /// Centre samples' in-scatter, RGB.
    pub inscatter: &'a [[f32; 3]],
    /// Centre samples' own error estimates (largest channel).
    pub own_error: &'a [f32],
    /// Centre samples' surfaces (triangle + 1, 0 for none).
    pub surface: &'a [u32],
    pub planes: &'a Planes,
    /// Per stage point light, its casters.
    pub casters: &'a [Casters],
    pub lights: &'a [BeamLight],
    pub media: &'a [PreparedMedium<C>],
    pub light_images: &'a [(f64, f64)],
    pub window_scale: &'a (dyn Fn(usize) -> f64 + Sync),
    /// An exact view ray through an image point (the render's own integrator).
    pub trace: &'a (dyn Fn(f64, f64) -> TracedRay + Sync),
}

/// An exact view ray's result, for the thin-beam path.
pub(crate) struct TracedRay {
    /// In-scatter, RGB.
    pub inscatter: [f64; 3],
    /// Its error estimate, RGB.
    pub error: [f64; 3],
    /// Triangle + 1 of the surface seen, 0 for none.
    pub surface: u32,
    /// Where the ray ends, m from the eye (surface, clip end or ∞).
    pub t_end: f64,
}

/// A pixel the model served.
pub(crate) struct ProfilePixel {
    pub index: usize,
    /// The light whose beam it is; `None` where no light's beam reaches the
    /// window (the in-scatter is 0 in every light's layer).
    pub light: Option<usize>,
    pub value: [f64; 3],
    pub error: [f64; 3],
}

/// A centre sample's model data for one light.
#[derive(Clone, Copy, Default)]
struct Centre {
    /// Usable: its chord is whole and unshadowed, no other cone is touched, `G₀` finite.
    valid: bool,
    /// Plane group + 1 of its surface (0: none).
    group: u32,
    g0: f64,
    /// `ρ` known (from the sample) or extended.
    has_rho: bool,
    /// `ρ` read from the sample.
    known: bool,
    rho: [f64; 3],
    /// Uncertainty of an extended `ρ` (0 where known).
    spread: [f64; 3],
    /// The sample's own error relative to its value (known `ρ` only).
    own_rel: f64,
    /// `±sin ψ` of its ray.
    sin_psi: f64,
}

/// Catmull–Rom weights at fraction `t` for the samples at −1, 0, 1, 2.
fn catmull_rom(t: f64) -> [f64; 4] {
    let (t2, t3) = (t * t, t * t * t);
    [
        -0.5 * t3 + t2 - 0.5 * t,
        1.5 * t3 - 2.5 * t2 + 1.0,
        -1.5 * t3 + 2.0 * t2 + 0.5 * t,
        0.5 * t3 - 0.5 * t2,
    ]
}

/// Serves what it can of `candidates` (flagged pixels); returns the served
/// pixels and the rest, for the lattice.
pub(crate) fn filter_by_profile<const C: usize>(input: &ProfileInput<'_, C>, candidates: &[usize]) -> (Vec<ProfilePixel>, Vec<usize>) {
    let (w, h) = (input.width, input.height);
    let r = input.filter.radius();
    // (Without lights there is nothing to bound: the caller found no beam
    // model, and the in-scatter may come from anything.)
    if r <= 0.0 || input.lights.is_empty() {
        return (Vec::new(), candidates.to_vec());
    }
    // A window that no light's band reaches (by the exact conservative
    // bound over its square) holds no in-scatter: here every light is a
    // beam, and a ray outside every band crosses no cone. Such pixels are
    // flagged beside a beam's edge (the flags are dilated by a pixel) and
    // along the frame's border, where the stencils below cannot reach;
    // lights with shadow casters (no profile table) too: the bound is
    // geometry alone.
    // The square in 4 × 4 parts: the bound is loose over a whole window
    // near a beam's apex, where the ray planes turn fast.
    const PARTS: usize = 4;
    let part = r / PARTS as f64;
    let (outside, candidates): (Vec<usize>, Vec<usize>) = candidates.iter().partition(|&&i| {
        let (x0, y0) = ((i % w) as f64 + 0.5 - r + part, (i / w) as f64 + 0.5 - r + part);
        !input.lights.iter().any(|l| {
            (0..PARTS * PARTS).any(|n| {
                let c = [x0 + 2.0 * part * (n % PARTS) as f64, y0 + 2.0 * part * (n / PARTS) as f64];
                l.band_may_touch_rect(c, [part, part])
            })
        })
    });
    let candidates = &candidates[..];
    let mut served: Vec<ProfilePixel> = outside
        .into_iter()
        .map(|index| ProfilePixel {
            index,
            light: None,
            value: [0.0; 3],
            error: [0.0; 3],
        })
        .collect();
    // The window's reach must stay inside the stencil (±1.5 px for
    // Blender's), and end on a node (the trapezoid rule's last node, where
    // the window is 0 with its derivatives).
    let on_node = (r * NODES_PER_PX as f64 - (r * NODES_PER_PX as f64).round()).abs() < 1e-9;
    if r > 1.5 || !on_node || input.lights.iter().all(|l| l.table.is_none()) {
        return (served, candidates.to_vec());
    }
    let near_image = |x: usize, y: usize| {
        let (cx, cy) = (x as f64 + 0.5, y as f64 + 0.5);
        input
            .light_images
            .iter()
            .any(|&(ix, iy)| (ix - cx).abs() <= LIGHT_IMAGE_MARGIN && (iy - cy).abs() <= LIGHT_IMAGE_MARGIN)
    };
    // Beams thinner than a node spacing: along their centre line, one ray per node.
    let norm = window_norm(&input.filter);
    let mut thin_nodes = ThinNodes::new();
    let thin = serve_thin_all(input, candidates, norm, THIN_BEAM_PX, &mut thin_nodes, 0.0);
    let mut open: Vec<usize> = Vec::new();
    for (p, &i) in thin.into_iter().zip(candidates) {
        match p {
            Some(p) => served.push(p),
            None => open.push(i),
        }
    }
    let (mut eligible, mut rest): (Vec<usize>, Vec<usize>) = open.iter().partition(|&&i| {
        let (x, y) = (i % w, i / w);
        x >= STENCIL && y >= STENCIL && x + STENCIL < w && y + STENCIL < h && !near_image(x, y)
    });
    // Tiles of eligible pixels.
    eligible.sort_unstable_by_key(|&i| ((i / w) / TILE, (i % w) / TILE, i));
    let mut tiles: Vec<&[usize]> = Vec::new();
    let mut start = 0;
    for k in 1..=eligible.len() {
        let key = |i: usize| ((i / w) / TILE, (i % w) / TILE);
        if k == eligible.len() || key(eligible[k]) != key(eligible[start]) {
            tiles.push(&eligible[start..k]);
            start = k;
        }
    }
    // Fullest tiles first, taken in that order, so that the threads finish together.
    tiles.sort_by_key(|t| std::cmp::Reverse(t.len()));
    let results: Vec<(Vec<ProfilePixel>, Vec<usize>)> = super::queued(&tiles, || (), |_, tile| serve_tile(input, tile));
    for (s, left) in results {
        served.extend(s);
        rest.extend(left);
    }
    rest.sort_unstable();
    // Where a beam widens from under 2 px to over it, the main path's
    // stencil still holds the thin part and refuses, and the thin path's
    // limit refuses the wide part: there the thin path takes beams up to
    // twice that width (its rules do not depend on the width; the limit
    // only keeps the cheaper main path where it runs). Beams narrower than
    // the lattice's cells are served here even where they miss the
    // tolerance (`LATTICE_BLIND_PX`).
    if !rest.is_empty() {
        let wide = serve_thin_all(input, &rest, norm, 2.0 * THIN_BEAM_PX, &mut thin_nodes, LATTICE_BLIND_PX);
        let mut still = Vec::with_capacity(rest.len());
        for (p, &i) in wide.into_iter().zip(&rest) {
            match p {
                Some(p) => served.push(p),
                None => still.push(i),
            }
        }
        rest = still;
    }
    (served, rest)
}

/// The window's node weights, `w(j/8)` for `j = −J..=J` (the trapezoid rule).
fn window_nodes(filter: &PixelFilter) -> Vec<f64> {
    let j_max = (filter.radius() * NODES_PER_PX as f64).floor() as i64;
    (-j_max..=j_max).map(|j| filter.weight(j as f64 / NODES_PER_PX as f64)).collect()
}

fn serve_tile<const C: usize>(input: &ProfileInput<'_, C>, pixels: &[usize]) -> (Vec<ProfilePixel>, Vec<usize>) {
    let w = input.width;
    let (x0, y0) = (
        pixels.iter().map(|i| i % w).min().unwrap_or(0),
        pixels.iter().map(|i| i / w).min().unwrap_or(0),
    );
    let (x1, y1) = (
        pixels.iter().map(|i| i % w).max().unwrap_or(0) + 1,
        pixels.iter().map(|i| i / w).max().unwrap_or(0) + 1,
    );
    let mut left: Vec<usize> = pixels.to_vec();
    let mut served = Vec::new();
    let weights = window_nodes(&input.filter);
    for (k, light) in input.lights.iter().enumerate() {
        if left.is_empty() {
            break;
        }
        let region = Region {
            cx0: x0 - STENCIL,
            cy0: y0 - STENCIL,
            cw: x1 - x0 + 2 * STENCIL,
            ch: y1 - y0 + 2 * STENCIL,
        };
        let centres = centre_grid(input, k, light, &region, &left);
        let nx = (x1 - x0) * NODES_PER_PX + weights.len();
        let ny = (y1 - y0) * NODES_PER_PX + weights.len();
        let mut nodes = Nodes {
            x0,
            y0,
            nx,
            state: vec![0; nx * ny],
            values: vec![
                NodeValue {
                    value: [0.0; 3],
                    error: [0.0; 3],
                    g_max: 0.0
                };
                nx * ny
            ],
            rows: vec![None; (x1 - x0) * ny],
            ny,
        };
        let tile = TileLight {
            input,
            k,
            light,
            region: &region,
            centres: &centres,
            weights: &weights,
        };
        let mut still = Vec::new();
        for &i in &left {
            match serve_pixel(&tile, &mut nodes, i) {
                Some(p) => served.push(p),
                None => still.push(i),
            }
        }
        left = still;
    }
    (served, left)
}

/// The tile's centres with the stencil's margin, frame coordinates.
struct Region {
    cx0: usize,
    cy0: usize,
    cw: usize,
    ch: usize,
}

/// Where the ray from the eye through image point `(px, py)` ends: the plane
/// `group` (+1) of the surface seen, or none. Returns `(o, d, t_end from the eye)`.
fn ray_of<const C: usize>(input: &ProfileInput<'_, C>, px: f64, py: f64, group: u32) -> (DVec3, DVec3, f64) {
    let cam = input.cam;
    let d = cam.direction(px, py);
    let start = cam.start_distance(d);
    let o = cam.position + d * start;
    let t_end = if group > 0 {
        let (n, offset) = input.planes.plane(group);
        let dn = n.dot(d);
        let t = (offset - n.dot(cam.position)) / dn;
        if t.is_finite() && t > start {
            t.min(cam.clip_end)
        } else {
            f64::NAN
        }
    } else {
        cam.clip_end
    };
    (o, d, t_end)
}

/// A view ray's chord through light `k`'s cone.
struct Chord {
    /// `±sin ψ`.
    s: f64,
    /// The ray's distance from the light, m.
    h: f64,
    /// `(o − L) × d`.
    m: DVec3,
    /// `A` over the part of the chord inside the ray (0 where it misses the cone).
    a: f64,
    /// The partial-chord table's error in `a` (0 for a whole or empty chord).
    a_error: f64,
}

/// The ray's chord through light `k`'s cone, given where the ray starts
/// (`o`) and ends (`t_end` from the eye), or `None` where the model does not
/// hold: the ray may be shadowed or touches another light's cone, or (with
/// `allow_partial` false) the ray's start or end cuts the chord. In the
/// ray's plane the chord spans the angles `[−c, c]` about the axis's
/// projection `p̂`, and the ray the angles from its start's direction to
/// its end's (less than π, increasing about `m`).
fn chord<const C: usize>(input: &ProfileInput<'_, C>, k: usize, o: DVec3, d: DVec3, t_end: f64, allow_partial: bool) -> Option<Chord> {
    let cam = input.cam;
    if t_end.is_nan() {
        return None;
    }
    for (j, other) in input.lights.iter().enumerate() {
        if j != k {
            let (s, hj, _) = other.plane_of(o, d);
            let clear = hj > 0.0 && s.abs() > other.sin_reach * (1.0 + 1e-9) + 1e-12;
            if !clear {
                return None;
            }
        }
    }
    let light = &input.lights[k];
    let table = light.table.as_ref()?;
    let (s, h, m) = light.plane_of(o, d);
    if h.is_nan() || h <= 0.0 || h.is_infinite() {
        return None;
    }
    let sa = s.abs();
    let mut out = Chord {
        s,
        h,
        m,
        a: 0.0,
        a_error: 0.0,
    };
    if sa >= light.sin_reach {
        // The ray's plane misses the cone.
        return Some(out);
    }
    let mh = m / h;
    let p = (light.axis - mh * light.axis.dot(mh)).normalize_or_zero();
    if p == DVec3::ZERO {
        return None;
    }
    let v_start = o - light.position;
    let v_end = if t_end.is_finite() {
        cam.position + d * t_end - light.position
    } else {
        d
    };
    let casters = &input.casters[k];
    // The common case first, without angles: both ends outside the cone
    // and p̂ between their directions — the chord is whole.
    let outside = |v: DVec3| v.dot(light.axis) < table.cos_reach * v.length() * (1.0 - 1e-9);
    if outside(v_start) && outside(v_end) {
        if v_start.cross(p).dot(m) < 0.0 || p.cross(v_end).dot(m) < 0.0 {
            // The cone is beyond one end of the ray: no chord.
            return Some(out);
        }
        out.a = table.eval(sa);
        if matches!(casters, Casters::None) || !casters.may_shadow(cam.position, d, t_end) {
            return Some(out);
        }
    }
    // Angles in the plane about m̂ from p̂; the ray sweeps from its start's
    // direction to its end's (less than π, increasing).
    let angle = |v: DVec3| p.cross(v).dot(mh).atan2(p.dot(v));
    let (a0, mut a1) = (angle(v_start), angle(v_end));
    if a1 < a0 {
        a1 += 2.0 * std::f64::consts::PI;
    }
    let c = table.chord_half_width(sa);
    for centre in [0.0, 2.0 * std::f64::consts::PI] {
        let (lo, hi) = ((centre - c).max(a0), (centre + c).min(a1));
        if hi <= lo {
            continue;
        }
        if a0 <= centre - c && a1 >= centre + c {
            out.a = table.eval(sa);
        } else if !allow_partial {
            return None;
        } else {
            (out.a, out.a_error) = table.partial(sa, lo - centre, hi - centre);
        }
        // Shadows can only fall on the chord: whether they may is asked of
        // the ray up to the chord's end (at angle `hi` in the plane; the
        // ray's point at angle φ is `t = t_c + h·tan(φ − φ_n)` from `o`, φ_n
        // the angle of the closest point's direction `n̂`).
        // Where the chord runs to the ray's end, that end (the angle of an
        // infinite ray's end is φ_n + π/2, where the tangent's sign is
        // rounding: it gave negative distances, behind the eye, and missed
        // shadows).
        if !matches!(casters, Casters::None) {
            let t_chord_end = if hi >= a1 - 1e-9 {
                t_end
            } else {
                let t_c = -v_start.dot(d);
                let n_hat = (v_start + d * t_c) / h;
                let t_hi = t_c + h * (hi - angle(n_hat)).tan();
                if t_hi.is_nan() || t_hi < 0.0 {
                    return None;
                }
                ((o - cam.position).length() + t_hi).min(t_end)
            };
            if casters.may_shadow(cam.position, d, t_chord_end) {
                return None;
            }
        }
        return Some(out);
    }
    out.a = 0.0;
    Some(out)
}

/// The model's data at the centres of `region` that the stencils of `pixels` read.
fn centre_grid<const C: usize>(input: &ProfileInput<'_, C>, k: usize, light: &BeamLight, region: &Region, pixels: &[usize]) -> Vec<Centre> {
    let w = input.width;
    let mut grid = vec![Centre::default(); region.cw * region.ch];
    let Some(table) = light.table.as_ref() else {
        return grid;
    };
    let mut needed = vec![false; region.cw * region.ch];
    for &i in pixels {
        let (x, y) = (i % w - region.cx0, i / w - region.cy0);
        for cy in y - STENCIL..=y + STENCIL {
            needed[cy * region.cw + x - STENCIL..=cy * region.cw + x + STENCIL].fill(true);
        }
    }
    for cy in 0..region.ch {
        for cx in 0..region.cw {
            if !needed[cy * region.cw + cx] {
                continue;
            }
            let (x, y) = (region.cx0 + cx, region.cy0 + cy);
            let i = y * w + x;
            let s = input.surface[i];
            let group = if s == 0 { 0 } else { input.planes.group_of(s - 1) };
            if s != 0 && group == 0 {
                continue;
            }
            let (o, d, t_end) = ray_of(input, x as f64 + 0.5, y as f64 + 0.5, group);
            let Some(Chord {
                s: sin_psi, h: hk, m, a, ..
            }) = chord(input, k, o, d, t_end, true)
            else {
                continue;
            };
            // G₀ = S(x₀)/h at the ray's point in the direction p̂.
            let mh = m / hk;
            let p = (light.axis - mh * light.axis.dot(mh)).normalize_or_zero();
            let w_vec = o - light.position;
            let t_c = -w_vec.dot(d);
            let n_hat = (w_vec + d * t_c) / hk;
            let (cos_u, sin_u) = (p.dot(n_hat), p.dot(d));
            if cos_u.is_nan() || cos_u <= 1e-6 {
                continue;
            }
            let t0 = t_c + hk * sin_u / cos_u;
            let x0 = o + d * t0;
            let mu = -sin_u;
            let mut sp = [0.0f64; C];
            let mut tau = [0.0f64; C];
            for med in input.media {
                let a = med.scattering_phase_at(x0, mu);
                let b = med.optical_depth_between(o, x0);
                let c = if light.light_path_extinction {
                    med.optical_depth_between(x0, light.position)
                } else {
                    [0.0; C]
                };
                for ch in 0..C {
                    sp[ch] += a[ch];
                    tau[ch] += b[ch] + c[ch];
                }
            }
            let g0 = (0..C).map(|ch| sp[ch] * (-tau[ch]).exp()).sum::<f64>() / (C as f64 * hk);
            if !(g0 > 0.0 && g0.is_finite()) {
                continue;
            }
            let mut c = Centre {
                valid: true,
                group,
                g0,
                sin_psi,
                ..Centre::default()
            };
            if a >= KNOWN_FRACTION * table.peak {
                let l = input.inscatter[i].map(f64::from);
                let largest = l.iter().fold(0.0f64, |m, v| m.max(v.abs()));
                (c.has_rho, c.known) = (true, true);
                c.rho = l.map(|v| v / (a * g0));
                c.own_rel = if largest > 0.0 {
                    f64::from(input.own_error[i]) / largest
                } else {
                    0.0
                };
            }
            grid[cy * region.cw + cx] = c;
        }
    }
    // ρ extended outwards: an unknown valid centre takes the mean of its
    // known 4-neighbours, with the spread of their values (plus their own
    // spreads) as its uncertainty, in rounds across the stencil.
    for _ in 0..2 * STENCIL {
        let prev = grid.clone();
        for cy in 0..region.ch {
            for cx in 0..region.cw {
                let me = prev[cy * region.cw + cx];
                if !me.valid || me.has_rho {
                    continue;
                }
                // The known 4-neighbours (a fixed array: this runs for
                // every unknown centre, six rounds per tile).
                let mut around = [None; 4];
                if cx > 0 {
                    around[0] = Some(&prev[cy * region.cw + cx - 1]);
                }
                if cx + 1 < region.cw {
                    around[1] = Some(&prev[cy * region.cw + cx + 1]);
                }
                if cy > 0 {
                    around[2] = Some(&prev[(cy - 1) * region.cw + cx]);
                }
                if cy + 1 < region.ch {
                    around[3] = Some(&prev[(cy + 1) * region.cw + cx]);
                }
                let mut known = [&me; 4];
                let mut count = 0;
                for c in around.into_iter().flatten().filter(|c| c.valid && c.has_rho) {
                    known[count] = c;
                    count += 1;
                }
                let nb = &known[..count];
                if nb.is_empty() {
                    continue;
                }
                let out = &mut grid[cy * region.cw + cx];
                out.has_rho = true;
                for ch in 0..3 {
                    let (lo, hi) = nb
                        .iter()
                        .fold((f64::INFINITY, f64::NEG_INFINITY), |(a, b), c| (a.min(c.rho[ch]), b.max(c.rho[ch])));
                    out.rho[ch] = nb.iter().map(|c| c.rho[ch]).sum::<f64>() / nb.len() as f64;
                    out.spread[ch] = (hi - lo) + nb.iter().fold(0.0f64, |m, c| m.max(c.spread[ch]));
                }
            }
        }
    }
    // An extended ρ may differ from what the chord would give there (at
    // the beam's edge the chord shrinks to x₀): charged at least the
    // variation of the known ρ within 2 centres of it.
    let extended: Vec<usize> = (0..grid.len()).filter(|&n| grid[n].has_rho && !grid[n].known).collect();
    for n in extended {
        let (cx, cy) = (n % region.cw, n / region.cw);
        let mut lo = [f64::INFINITY; 3];
        let mut hi = [f64::NEG_INFINITY; 3];
        for yy in cy.saturating_sub(2)..(cy + 3).min(region.ch) {
            for xx in cx.saturating_sub(2)..(cx + 3).min(region.cw) {
                let c = &grid[yy * region.cw + xx];
                if c.known {
                    for ch in 0..3 {
                        lo[ch] = lo[ch].min(c.rho[ch]);
                        hi[ch] = hi[ch].max(c.rho[ch]);
                    }
                }
            }
        }
        for ch in 0..3 {
            if hi[ch] >= lo[ch] {
                grid[n].spread[ch] = grid[n].spread[ch].max(hi[ch] - lo[ch]);
            }
        }
    }
    grid
}

/// A node's share of the window sums: its value `A·G` (Catmull–Rom), its
/// error terms (`|Catmull–Rom − bilinear|` and the extended ρ's spread),
/// and `G`'s largest channel; `None` when the model does not hold there.
#[derive(Clone, Copy)]
struct NodeValue {
    value: [f64; 3],
    error: [f64; 3],
    g_max: f64,
}

/// The tile's nodes, computed once each and shared by the windows holding them.
struct Nodes {
    /// Node (0, 0) is at image point `(x0 + ½ − J/P, y0 + ½ − J/P)`.
    x0: usize,
    y0: usize,
    nx: usize,
    /// 0: not computed, 1: the model fails there, 2: `values` holds it.
    state: Vec<u8>,
    values: Vec<NodeValue>,
    /// The window's sums along x over one node row, per pixel column of
    /// the tile and node row (`(x − x0)·ny + row`): `None` until computed.
    rows: Vec<Option<RowSum>>,
    ny: usize,
}

/// One node row of a window, summed along x with the window's weights
/// (`Σ wₓ·v` for the fine and the coarse rule, the node estimates, the
/// weights): pixels of one column share their rows, so a window sums 13
/// of these instead of 169 nodes.
#[derive(Clone, Copy)]
struct RowSum {
    /// Some node of the row with a non-zero weight fails the model.
    fails: bool,
    fine: [f64; 3],
    coarse: [f64; 3],
    est: [f64; 3],
    g_max: f64,
    w_fine: f64,
    w_coarse: f64,
}

fn node_value<const C: usize>(
    input: &ProfileInput<'_, C>,
    k: usize,
    light: &BeamLight,
    region: &Region,
    centres: &[Centre],
    px: f64,
    py: f64,
) -> Option<NodeValue> {
    let table = light.table.as_ref()?;
    // A ray outside every cone has no in-scatter, whichever surface it ends
    // on: no chord to find (the nodes outside a beam beside its edge; the
    // point bound carries the margin of chord()'s test of other cones).
    if !input.lights.iter().any(|l| l.band_may_touch([px, py], 0.0)) {
        return Some(NodeValue {
            value: [0.0; 3],
            error: [0.0; 3],
            g_max: 0.0,
        });
    }
    let at = |cx: usize, cy: usize| &centres[(cy - region.cy0) * region.cw + (cx - region.cx0)];
    let (gx, gy) = (px - 0.5, py - 0.5);
    let (fx, fy) = (gx.floor(), gy.floor());
    let (tx, ty) = (gx - fx, gy - fy);
    let (ix, iy) = (fx as usize, fy as usize);
    // The node's ray ends on the surface of one of the four centres around
    // it: its chord must be whole for each of them.
    // (A on the same chord for each of them).
    let (mut a, mut a_error) = (f64::NAN, 0.0f64);
    let mut groups = [u32::MAX; 4];
    for (n, (ca, cb)) in [(0, 0), (1, 0), (0, 1), (1, 1)].into_iter().enumerate() {
        let g = at(ix + ca, iy + cb).group;
        if groups[..n].contains(&g) {
            continue;
        }
        groups[n] = g;
        let (o, d, t_end) = ray_of(input, px, py, g);
        let ch = chord(input, k, o, d, t_end, true)?;
        if !a.is_nan() && (ch.a - a).abs() > 1e-12 * table.peak {
            return None;
        }
        (a, a_error) = (ch.a, a_error.max(ch.a_error));
    }
    if a == 0.0 {
        return Some(NodeValue {
            value: [0.0; 3],
            error: [0.0; 3],
            g_max: 0.0,
        });
    }
    // G = G₀·ρ interpolated (Catmull–Rom, and bilinear for the estimate),
    // and the extended ρ's uncertainty weighted by its Catmull–Rom weights.
    let (crx, cry) = (catmull_rom(tx), catmull_rom(ty));
    let (mut g0_cr, mut g0_lin) = (0.0f64, 0.0f64);
    let (mut rho_cr, mut rho_lin, mut spread) = ([0.0f64; 3], [0.0f64; 3], [0.0f64; 3]);
    for (b, wyb) in cry.iter().enumerate() {
        for (a_, wxa) in crx.iter().enumerate() {
            let c = at(ix + a_ - 1, iy + b - 1);
            if !c.has_rho {
                return None;
            }
            let cw = wxa * wyb;
            g0_cr += cw * c.g0;
            for ch in 0..3 {
                rho_cr[ch] += cw * c.rho[ch];
                spread[ch] += cw.abs() * c.spread[ch];
            }
        }
    }
    for (b, wyb) in [1.0 - ty, ty].iter().enumerate() {
        for (a_, wxa) in [1.0 - tx, tx].iter().enumerate() {
            let c = at(ix + a_, iy + b);
            let cw = wxa * wyb;
            g0_lin += cw * c.g0;
            for ch in 0..3 {
                rho_lin[ch] += cw * c.rho[ch];
            }
        }
    }
    let mut out = NodeValue {
        value: [0.0; 3],
        error: [0.0; 3],
        g_max: g0_cr.abs() * rho_cr.iter().fold(0.0f64, |m, v| m.max(v.abs())),
    };
    for ch in 0..3 {
        out.value[ch] = a * g0_cr * rho_cr[ch];
        out.error[ch] =
            (out.value[ch] - a * g0_lin * rho_lin[ch]).abs() + a * g0_cr.abs() * spread[ch] + a_error * (g0_cr * rho_cr[ch]).abs();
    }
    Some(out)
}

/// What a tile's windows read for light `k`: the light, the tile's centres
/// (over `region`) and the window's node weights.
struct TileLight<'a, const C: usize> {
    input: &'a ProfileInput<'a, C>,
    k: usize,
    light: &'a BeamLight,
    region: &'a Region,
    centres: &'a [Centre],
    weights: &'a [f64],
}

/// Node row `ny` of the window of the pixels in column `x`, summed along x
/// ([`RowSum`]); the nodes are computed on first use and kept.
fn row_sum<const C: usize>(tile: &TileLight<'_, C>, nodes: &mut Nodes, x: usize, ny: usize) -> RowSum {
    let weights = tile.weights;
    let j_max = weights.len() / 2;
    let per_px = NODES_PER_PX as f64;
    let mut row = RowSum {
        fails: false,
        fine: [0.0; 3],
        coarse: [0.0; 3],
        est: [0.0; 3],
        g_max: 0.0,
        w_fine: 0.0,
        w_coarse: 0.0,
    };
    let py = nodes.y0 as f64 + 0.5 + (ny as f64 - j_max as f64) / per_px;
    for (jx, wx) in weights.iter().enumerate() {
        if *wx == 0.0 {
            continue;
        }
        let nx = (x - nodes.x0) * NODES_PER_PX + jx;
        let slot = ny * nodes.nx + nx;
        if nodes.state[slot] == 0 {
            let px = x as f64 + 0.5 + (jx as f64 - j_max as f64) / per_px;
            match node_value(tile.input, tile.k, tile.light, tile.region, tile.centres, px, py) {
                Some(v) => {
                    nodes.values[slot] = v;
                    nodes.state[slot] = 2;
                }
                None => nodes.state[slot] = 1,
            }
        }
        if nodes.state[slot] == 1 {
            row.fails = true;
            return row;
        }
        let node = &nodes.values[slot];
        let coarse_node = (jx + j_max).is_multiple_of(2);
        row.w_fine += wx;
        if coarse_node {
            row.w_coarse += wx;
        }
        row.g_max = row.g_max.max(node.g_max);
        for ch in 0..3 {
            row.fine[ch] += wx * node.value[ch];
            if coarse_node {
                row.coarse[ch] += wx * node.value[ch];
            }
            row.est[ch] += wx * node.error[ch];
        }
    }
    row
}

fn serve_pixel<const C: usize>(tile: &TileLight<'_, C>, nodes: &mut Nodes, i: usize) -> Option<ProfilePixel> {
    let TileLight {
        input,
        k,
        light,
        region,
        centres,
        weights,
    } = *tile;
    let table = light.table.as_ref()?;
    let w = input.width;
    let (x, y) = (i % w, i / w);
    let at = |cx: usize, cy: usize| &centres[(cy - region.cy0) * region.cw + (cx - region.cx0)];
    // The stencil: every centre valid (its chord whole, given its own
    // surface), some with a known ρ; the ρ a node needs is checked there.
    let mut known = false;
    let mut own_rel = 0.0f64;
    for cy in y - STENCIL..=y + STENCIL {
        for cx in x - STENCIL..=x + STENCIL {
            let c = at(cx, cy);
            if !c.valid {
                return None;
            }
            if c.known {
                known = true;
                own_rel = own_rel.max(c.own_rel);
            }
        }
    }
    if !known {
        return None;
    }
    // Another light's beam may pass between the centres and between the
    // nodes (a 0.5° beam near its apex is narrower than ¼ px): its cone,
    // by geometry, must stay clear of the stencil's reach.
    let c = [x as f64 + 0.5, y as f64 + 0.5];
    if (0..input.lights.len()).any(|j| j != k && cone_within(input, j, c, STENCIL as f64 + 0.5)) {
        return None;
    }
    // The beam must be resolved by the nodes: across the stencil it spans
    // at least `MIN_BEAM_NODES` node spacings (a thinner beam can pass
    // between nodes, where both rules of the estimate miss it).
    let mut slope = 0.0f64;
    for cy in y - STENCIL + 1..y + STENCIL {
        for cx in x - STENCIL + 1..x + STENCIL {
            let (c, l, u) = (at(cx, cy).sin_psi, at(cx - 1, cy).sin_psi, at(cx, cy - 1).sin_psi);
            slope = slope.max((c - l).abs()).max((c - u).abs());
        }
    }
    if 2.0 * light.sin_reach < MIN_BEAM_NODES / NODES_PER_PX as f64 * slope {
        return None;
    }
    let j_max = weights.len() / 2;
    let (mut fine, mut coarse, mut est) = ([0.0f64; 3], [0.0f64; 3], [0.0f64; 3]);
    let (mut w_fine, mut w_coarse) = (0.0f64, 0.0f64);
    let mut g_max = 0.0f64;
    for (jy, wy) in weights.iter().enumerate() {
        if *wy == 0.0 {
            continue;
        }
        let ny = (y - nodes.y0) * NODES_PER_PX + jy;
        let row = match nodes.rows[(x - nodes.x0) * nodes.ny + ny] {
            Some(row) => row,
            None => {
                let row = row_sum(tile, nodes, x, ny);
                nodes.rows[(x - nodes.x0) * nodes.ny + ny] = Some(row);
                row
            }
        };
        if row.fails {
            return None;
        }
        // The coarse rule: every other node, centred on the pixel.
        let coarse_row = (jy + j_max).is_multiple_of(2);
        w_fine += wy * row.w_fine;
        if coarse_row {
            w_coarse += wy * row.w_coarse;
        }
        g_max = g_max.max(row.g_max);
        for ch in 0..3 {
            fine[ch] += wy * row.fine[ch];
            if coarse_row {
                coarse[ch] += wy * row.coarse[ch];
            }
            est[ch] += wy * row.est[ch];
        }
    }
    if !(w_fine > 0.0 && w_coarse > 0.0) {
        return None;
    }
    let table_rel = table.error / (KNOWN_FRACTION * table.peak);
    let mut value = [0.0f64; 3];
    let mut error = [0.0f64; 3];
    for ch in 0..3 {
        value[ch] = fine[ch] / w_fine;
        let quadrature = (value[ch] - coarse[ch] / w_coarse).abs();
        error[ch] = est[ch] / w_fine + quadrature + (own_rel + table_rel) * value[ch].abs() + g_max * table.error;
    }
    accept(input, i, k, value, error)
}

/// The pixel, when its value and estimate are finite and the estimate meets
/// the tolerance of the window's scale (as the lattice's convergence test).
fn accept<const C: usize>(input: &ProfileInput<'_, C>, i: usize, k: usize, value: [f64; 3], error: [f64; 3]) -> Option<ProfilePixel> {
    if !value.iter().chain(error.iter()).all(|v| v.is_finite()) {
        return None;
    }
    let scale = value.iter().fold(0.0f64, |m, v| m.max(v.abs())).max((input.window_scale)(i));
    let e_max = error.iter().fold(0.0f64, |m, v| m.max(*v));
    (e_max <= input.tolerance * scale).then_some(ProfilePixel {
        index: i,
        light: Some(k),
        value,
        error,
    })
}

/// `∫∫ w(x) w(y) dx dy` of the window (midpoint rule, 4 096 nodes a side).
fn window_norm(filter: &PixelFilter) -> f64 {
    let r = filter.radius();
    let n = 4096;
    let h = 2.0 * r / n as f64;
    let one: f64 = (0..n).map(|i| filter.weight(-r + (i as f64 + 0.5) * h)).sum::<f64>() * h;
    one * one
}

/// Whether light `j`'s cone may come within `reach` px (along x or y) of
/// image point `c` ([`BeamLight::band_may_touch`]).
fn cone_within<const C: usize>(input: &ProfileInput<'_, C>, j: usize, c: [f64; 2], reach: f64) -> bool {
    input.lights[j].band_may_touch(c, reach)
}

/// The widest beam the thin path takes, px across: the narrowest the main
/// path takes ([`MIN_BEAM_NODES`] node spacings).
const THIN_BEAM_PX: f64 = MIN_BEAM_NODES / NODES_PER_PX as f64;

/// The pixels, not yet `flagged`, whose window (`± radius` px) a beam
/// narrower than [`THIN_BEAM_PX`] crosses ([`BeamLight::thin_beam_touches`]),
/// in index order. Blocks of [`TILE`] px a side whose windows no light's
/// band may reach ([`BeamLight::band_may_touch_rect`]) are skipped whole.
pub(crate) fn thin_beam_pixels(lights: &[BeamLight], radius: f64, width: usize, height: usize, flagged: &[bool]) -> Vec<usize> {
    let blocks_x = width.div_ceil(TILE);
    let mut out: Vec<usize> = (0..blocks_x * height.div_ceil(TILE))
        .into_par_iter()
        .flat_map_iter(|b| {
            let (x0, y0) = ((b % blocks_x) * TILE, (b / blocks_x) * TILE);
            let (x1, y1) = ((x0 + TILE).min(width), (y0 + TILE).min(height));
            // The block's pixel centres' span, widened by the window.
            let c = [0.5 * (x0 + x1) as f64, 0.5 * (y0 + y1) as f64];
            let half = [0.5 * (x1 - x0) as f64 + radius, 0.5 * (y1 - y0) as f64 + radius];
            let near: Vec<&BeamLight> = lights.iter().filter(|l| l.band_may_touch_rect(c, half)).collect();
            let mut found = Vec::new();
            if !near.is_empty() {
                for y in y0..y1 {
                    for x in x0..x1 {
                        let c = [x as f64 + 0.5, y as f64 + 0.5];
                        if !flagged[y * width + x] && near.iter().any(|l| l.thin_beam_touches(c, radius)) {
                            found.push(y * width + x);
                        }
                    }
                }
            }
            found
        })
        .collect();
    out.sort_unstable();
    out
}

/// Gauss–Legendre nodes and weights on [−1, 1], 4, 8 and 16 points.
const GL4: [(f64, f64); 4] = [
    (-0.861_136_311_594_052_6, 0.347_854_845_137_453_85),
    (-0.339_981_043_584_856_3, 0.652_145_154_862_546_1),
    (0.339_981_043_584_856_3, 0.652_145_154_862_546_1),
    (0.861_136_311_594_052_6, 0.347_854_845_137_453_85),
];
const GL8: [(f64, f64); 8] = [
    (-0.960_289_856_497_536_2, 0.101_228_536_290_376_26),
    (-0.796_666_477_413_626_7, 0.222_381_034_453_374_48),
    (-0.525_532_409_916_329, 0.313_706_645_877_887_27),
    (-0.183_434_642_495_649_8, 0.362_683_783_378_362),
    (0.183_434_642_495_649_8, 0.362_683_783_378_362),
    (0.525_532_409_916_329, 0.313_706_645_877_887_27),
    (0.796_666_477_413_626_7, 0.222_381_034_453_374_48),
    (0.960_289_856_497_536_2, 0.101_228_536_290_376_26),
];
const GL16: [(f64, f64); 16] = [
    (-0.989_400_934_991_649_9, 0.027_152_459_411_754_095),
    (-0.944_575_023_073_232_6, 0.062_253_523_938_647_89),
    (-0.865_631_202_387_831_7, 0.095_158_511_682_492_78),
    (-0.755_404_408_355_003, 0.124_628_971_255_533_87),
    (-0.617_876_244_402_643_8, 0.149_595_988_816_576_73),
    (-0.458_016_777_657_227_4, 0.169_156_519_395_002_54),
    (-0.281_603_550_779_258_9, 0.182_603_415_044_923_6),
    (-0.095_012_509_837_637_44, 0.189_450_610_455_068_5),
    (0.095_012_509_837_637_44, 0.189_450_610_455_068_5),
    (0.281_603_550_779_258_9, 0.182_603_415_044_923_6),
    (0.458_016_777_657_227_4, 0.169_156_519_395_002_54),
    (0.617_876_244_402_643_8, 0.149_595_988_816_576_73),
    (0.755_404_408_355_003, 0.124_628_971_255_533_87),
    (0.865_631_202_387_831_7, 0.095_158_511_682_492_78),
    (0.944_575_023_073_232_6, 0.062_253_523_938_647_89),
    (0.989_400_934_991_649_9, 0.027_152_459_411_754_095),
];

/// What the thin path ([`serve_thin_all`]) knows of a pixel before the
/// line's nodes are computed.
struct ThinPlan {
    i: usize,
    k: usize,
    c: [f64; 2],
    /// The band's half-width at the pixel's centre, px.
    b: f64,
    /// The line's nodes whose band may touch the window: `j0..=j1`.
    j0: i64,
    j1: i64,
}

/// Beams narrower than this, px, pass between the pixel filter lattice's
/// root cells' corners (½ px apart), which then see nothing of them: where
/// the thin path's estimate misses the tolerance, its result is kept (and
/// counted as not converged) rather than handed to the lattice. A 0.5° beam
/// 0.16 px wide clipping a window's corner, 15 px from its lamp's image
/// (the window's centre samples all 0, so its tolerance is relative to its
/// own value): the thin path gave 8.08e-9 ± 2.8e-10 (3.5 %, over the
/// tolerance 0.01), and the lattice then 0 ± 0 against 8.05e-9.
const LATTICE_BLIND_PX: f64 = 0.5;

/// Node spacing along a thin beam's centre line, px.
const THIN_NODE_PX: f64 = 1.0 / NODES_PER_PX as f64;

/// One light's centre line: the point nearest the frame's centre and the
/// unit direction; node `j` is at `foot + j·THIN_NODE_PX·dir`.
fn thin_line<const C: usize>(input: &ProfileInput<'_, C>, k: usize) -> Option<([f64; 2], [f64; 2])> {
    input.lights[k].centre_line([0.5 * input.width as f64, 0.5 * input.height as f64])
}

/// Whether the thin path may take pixel `i` for light `k`, and which of
/// the line's nodes its window needs.
fn thin_plan<const C: usize>(input: &ProfileInput<'_, C>, k: usize, i: usize, widest: f64) -> Option<ThinPlan> {
    let w = input.width;
    let (x, y) = (i % w, i / w);
    let light = &input.lights[k];
    light.table.as_ref()?;
    let r = input.filter.radius();
    let c = [x as f64 + 0.5, y as f64 + 0.5];
    let (s0, g) = light.s_and_gradient(c);
    let gn = g[0].hypot(g[1]);
    if !(gn > 0.0 && gn.is_finite() && s0.is_finite()) {
        return None;
    }
    let b = light.sin_reach / gn;
    // (No test of the distance to the line here: by the linearisation it
    // refused pixels near a beam's apex whose window's corner the curved
    // band does reach. The clipping below leaves no node where the band
    // misses the window's square widened by 2b.)
    if 2.0 * b >= widest {
        return None;
    }
    // Not near a light's image: the beam's apex must be outside the window.
    if input
        .light_images
        .iter()
        .any(|&(ix, iy)| (ix - c[0]).abs() <= r + 1.0 && (iy - c[1]).abs() <= r + 1.0)
    {
        return None;
    }
    // Every other light's cone clear of the window.
    if (0..input.lights.len()).any(|j| j != k && cone_within(input, j, c, r + 0.5)) {
        return None;
    }
    // The centre line, clipped to the window's square widened by 2b: beyond
    // that the whole band is outside the window.
    let (foot, dir) = thin_line(input, k)?;
    let reach = r + 2.0 * b;
    let (mut ta, mut tb) = (f64::NEG_INFINITY, f64::INFINITY);
    for a in 0..2 {
        if dir[a].abs() < 1e-12 {
            if (foot[a] - c[a]).abs() > reach {
                return None;
            }
            continue;
        }
        let (t1, t2) = ((c[a] - reach - foot[a]) / dir[a], (c[a] + reach - foot[a]) / dir[a]);
        ta = ta.max(t1.min(t2));
        tb = tb.min(t1.max(t2));
    }
    if tb.is_nan() || ta.is_nan() || tb <= ta {
        return None;
    }
    let (j0, j1) = ((ta / THIN_NODE_PX).ceil() as i64, (tb / THIN_NODE_PX).floor() as i64);
    // At least four nodes, for the estimate from every other node; fewer
    // (the band clipping a window's corner) only for a beam the lattice
    // cannot see either (`LATTICE_BLIND_PX`), where one node's estimate is
    // its whole value and two or three nodes' the difference from every
    // other one.
    (j1 > j0 + 2 || (j1 >= j0 && 2.0 * b < LATTICE_BLIND_PX)).then_some(ThinPlan { i, k, c, b, j0, j1 })
}

/// The thin path's rule across a beam, in `δ = mid + half·sin θ`: the
/// Gauss–Legendre nodes (16, then 8) in `θ ∈ [−π/2, π/2]` as
/// `(sin θ, weight·(π/2)·cos θ)`, computed once per process.
fn across_nodes() -> &'static [(f64, f64); 24] {
    static NODES: std::sync::OnceLock<[(f64, f64); 24]> = std::sync::OnceLock::new();
    NODES.get_or_init(|| {
        let mut all = GL16.iter().chain(GL8.iter()).map(|&(u, wgt)| {
            let theta = u * std::f64::consts::FRAC_PI_2;
            (theta.sin(), wgt * std::f64::consts::FRAC_PI_2 * theta.cos())
        });
        std::array::from_fn(|_| all.next().unwrap_or_default())
    })
}

/// A node on a thin beam's centre line: what every window holding it needs.
struct ThinNode {
    /// The surface's plane group the three exact rays end on.
    group: u32,
    /// The exact rays' largest own relative error.
    own: f64,
    /// Half the band's width across, px.
    half: f64,
    /// The band's ends across the line, image points.
    ends: [[f64; 2]; 2],
    /// `G` at `δ = mid, mid + half/2, mid − half/2`, RGB.
    g: [[f64; 3]; 3],
    /// Gauss–Legendre points across (16, then 8).
    points: Vec<ThinPoint>,
}

/// Pixel columns (or rows) whose window may hold a point: the first one,
/// and up to 5 from it (a window reaches ±1.5 px at most; one spare for
/// rounding).
const WINDOW_SLOTS: usize = 5;

/// A Gauss–Legendre point across a thin node: weight times `A` (without
/// the window), `z = (δ − mid)/(half/2)`, and the window's factors for the
/// pixel columns and rows around it. They are the values
/// `PixelFilter::weight(p − pixel centre)` that each pixel's window would
/// compute (to rounding), computed once per point instead of once per pixel
/// holding it.
struct ThinPoint {
    f: f64,
    z: f64,
    first: [i64; 2],
    window: [[f64; WINDOW_SLOTS]; 2],
}

impl ThinPoint {
    fn new(steps: &UnitSteps, p: [f64; 2], f: f64, z: f64) -> ThinPoint {
        let r = steps.radius();
        let first = p.map(|v| (v - 0.5 - r).ceil() as i64 - 1);
        let window = std::array::from_fn(|a| steps.weights(p[a] - (first[a] as f64 + 0.5)));
        ThinPoint { f, z, first, window }
    }

    /// The window of the pixel at column `x`, row `y` at this point.
    fn window_of(&self, x: i64, y: i64) -> f64 {
        let (mx, my) = (x - self.first[0], y - self.first[1]);
        if (0..WINDOW_SLOTS as i64).contains(&mx) && (0..WINDOW_SLOTS as i64).contains(&my) {
            self.window[0][mx as usize] * self.window[1][my as usize]
        } else {
            0.0
        }
    }
}

/// Node `j` of light `k`'s centre line; [`ThinMiss::Wider`] where the band
/// is `widest` px or wider there, [`ThinMiss::Fails`] where the model does
/// not hold (an exact ray off the beam's core or its surface, a chord cut
/// by a surface, the band not closed around the line).
fn thin_node<const C: usize>(input: &ProfileInput<'_, C>, k: usize, j: i64, widest: f64) -> Result<ThinNode, ThinMiss> {
    let light = &input.lights[k];
    light.table.as_ref().ok_or(ThinMiss::Fails)?;
    let (foot, dir) = thin_line(input, k).ok_or(ThinMiss::Fails)?;
    let normal = [dir[1], -dir[0]];
    let t = j as f64 * THIN_NODE_PX;
    let q = [foot[0] + t * dir[0], foot[1] + t * dir[1]];
    let (lo, hi) = light.band_across(q, normal).ok_or(ThinMiss::Fails)?;
    let half = 0.5 * (hi - lo);
    if half.is_nan() || half <= 0.0 {
        return Err(ThinMiss::Fails);
    }
    if 2.0 * half >= widest {
        return Err(ThinMiss::Wider);
    }
    thin_node_across(input, k, q, normal, (lo, hi)).ok_or(ThinMiss::Fails)
}

/// The thin nodes computed so far, by light and index along its line.
type ThinNodes = std::collections::BTreeMap<(usize, i64), Result<ThinNode, ThinMiss>>;

/// Why there is no [`ThinNode`]: the band is wider there than the pass
/// takes (a later pass with a wider limit computes it), or the model does
/// not hold there whatever the limit.
#[derive(Clone, Copy, Debug, PartialEq)]
enum ThinMiss {
    Wider,
    Fails,
}

/// [`thin_node`] once the band across the line at `q` is known: `[lo, hi]`
/// along `normal`.
fn thin_node_across<const C: usize>(
    input: &ProfileInput<'_, C>,
    k: usize,
    q: [f64; 2],
    normal: [f64; 2],
    (lo, hi): (f64, f64),
) -> Option<ThinNode> {
    let light = &input.lights[k];
    let table = light.table.as_ref()?;
    let (mid, half) = (0.5 * (lo + hi), 0.5 * (hi - lo));
    let cam = input.cam;
    let at = |delta: f64| [q[0] + delta * normal[0], q[1] + delta * normal[1]];
    let s_at = |p: [f64; 2]| light.sin_psi_at(p[0], p[1]);
    // One exact ray: `G = L/A` there, its surface and own relative error.
    let g_at = |p: [f64; 2]| -> Option<([f64; 3], u32, f64)> {
        let a = table.eval(s_at(p).abs());
        if a.is_nan() || a < KNOWN_FRACTION * table.peak {
            return None;
        }
        let tr = (input.trace)(p[0], p[1]);
        let group = if tr.surface == 0 {
            0
        } else {
            input.planes.group_of(tr.surface - 1)
        };
        let d = cam.direction(p[0], p[1]);
        let whole = chord(input, k, cam.position + d * cam.start_distance(d), d, tr.t_end, false)?;
        if whole.a == 0.0 {
            return None;
        }
        let largest = tr.inscatter.iter().fold(0.0f64, |m, v| m.max(v.abs()));
        let own = tr.error.iter().fold(0.0f64, |m, v| m.max(*v));
        Some((tr.inscatter.map(|l| l / a), group, if largest > 0.0 { own / largest } else { 0.0 }))
    };
    let (g0, s0, e0) = g_at(at(mid))?;
    let (gp, sp, ep) = g_at(at(mid + 0.5 * half))?;
    let (gm, sm, em) = g_at(at(mid - 0.5 * half))?;
    // Every exact ray on one surface (or none): a narrow object in front
    // would cut the chord between them.
    if s0 != sp || s0 != sm {
        return None;
    }
    let steps = input.filter.unit_steps();
    let points = across_nodes()
        .iter()
        .map(|&(sin_theta, w_cos_theta)| {
            let p = at(mid + half * sin_theta);
            let f = w_cos_theta * half * table.eval(s_at(p).abs());
            ThinPoint::new(&steps, p, f, 2.0 * sin_theta)
        })
        .collect();
    Some(ThinNode {
        group: s0,
        own: e0.max(ep).max(em),
        half,
        ends: [at(lo), at(hi)],
        g: [g0, gp, gm],
        points,
    })
}

/// The pixels of `candidates` the thin path serves (aligned with them).
/// A beam narrower than [`THIN_BEAM_PX`] across a pixel's window has too
/// few nodes across it for the main path, too few centre samples inside it
/// for `G`. The window integral is taken in the beam's own
/// coordinates, a rotation of the image's: along its centre line (exact:
/// `n = m·a = 0` is a straight line in the image) by the trapezoid rule
/// on nodes ¼ px apart (the window is 0 at both ends of its span, so the
/// rule converges fast; every other node gives the estimate), and across
/// it, at each node, over the band `|sin ψ| < sin_reach` between its exact
/// edges `δ₋, δ₊` ([`BeamLight::band_across`]), as `δ = mid + half·sin θ`
/// (Gauss–Legendre in θ, 16 nodes against 8; the substitution smooths a
/// hard edge's square root). Across, `L = G(δ)·A(s)` with `A` and `s`
/// exact (geometry) and `G` the quadratic through three exact rays at
/// `δ = mid, mid ± half/2`; the quadratic's departure from the line
/// through them is charged as that model's error. The nodes lie on one
/// line per light, so every pixel along the beam shares them
/// ([`thin_node`]): three traced rays per node, not per pixel.
fn serve_thin_all<const C: usize>(
    input: &ProfileInput<'_, C>,
    candidates: &[usize],
    norm: f64,
    widest: f64,
    known: &mut ThinNodes,
    blind: f64,
) -> Vec<Option<ProfilePixel>> {
    let plans: Vec<Option<ThinPlan>> = candidates
        .par_iter()
        .map(|&i| (0..input.lights.len()).find_map(|k| thin_plan(input, k, i, widest)))
        .collect();
    // The nodes the plans need, per light, each computed once: an earlier
    // pass's nodes are kept, except those it found wider than its limit.
    let mut wanted: Vec<(usize, i64)> = plans
        .iter()
        .flatten()
        .flat_map(|p| (p.j0..=p.j1).map(move |j| (p.k, j)))
        .filter(|key| known.get(key).is_none_or(|n| matches!(n, Err(ThinMiss::Wider))))
        .collect();
    wanted.sort_unstable();
    wanted.dedup();
    let nodes: Vec<Result<ThinNode, ThinMiss>> = wanted.par_iter().map(|&(k, j)| thin_node(input, k, j, widest)).collect();
    known.extend(wanted.into_iter().zip(nodes));
    let known = &*known;
    let node_of = |k: usize, j: i64| -> Option<&ThinNode> { known.get(&(k, j))?.as_ref().ok() };
    plans
        .par_iter()
        .map(|plan| {
            let plan = plan.as_ref()?;
            serve_thin(input, plan, &node_of, norm, blind)
        })
        .collect()
}

fn serve_thin<'n, const C: usize>(
    input: &ProfileInput<'_, C>,
    plan: &ThinPlan,
    node_of: &dyn Fn(usize, i64) -> Option<&'n ThinNode>,
    norm: f64,
    blind: f64,
) -> Option<ProfilePixel> {
    let ThinPlan { i, k, c, b, j0, j1 } = *plan;
    let table = input.lights[k].table.as_ref()?;
    let (x, y) = ((i % input.width) as i64, (i / input.width) as i64);
    let h = THIN_NODE_PX;
    let (mut fine, mut coarse, mut rule, mut model, mut own) = ([0.0f64; 3], [0.0f64; 3], [0.0f64; 3], [0.0f64; 3], 0.0f64);
    let mut group = None;
    for j in j0..=j1 {
        let node = node_of(k, j)?;
        // The band must not widen much across the window (near the beam's
        // apex), and every node's rays end on one surface.
        if node.half > 1.5 * b || *group.get_or_insert(node.group) != node.group {
            return None;
        }
        own = own.max(node.own);
        // Nothing to add where the band lies outside the window.
        let [p, q] = node.ends;
        let r = input.filter.radius();
        if p[0].min(q[0]) >= c[0] + r || p[0].max(q[0]) <= c[0] - r || p[1].min(q[1]) >= c[1] + r || p[1].max(q[1]) <= c[1] - r {
            continue;
        }
        let [g0, gp, gm] = node.g;
        let across = |points: &[ThinPoint]| -> ([f64; 3], [f64; 3]) {
            let (mut v, mut curv) = ([0.0f64; 3], [0.0f64; 3]);
            for point in points {
                let (f, z) = (point.f * point.window_of(x, y), point.z);
                if f == 0.0 {
                    continue;
                }
                for ch in 0..3 {
                    let slope = 0.5 * (gp[ch] - gm[ch]);
                    let bend = 0.5 * (gp[ch] + gm[ch] - 2.0 * g0[ch]);
                    v[ch] += f * (g0[ch] + slope * z + bend * z * z);
                    curv[ch] += (f * bend * z * z).abs();
                }
            }
            (v, curv)
        };
        let (v16, curv) = across(&node.points[..16]);
        let (v8, _) = across(&node.points[16..]);
        for ch in 0..3 {
            fine[ch] += h * v16[ch];
            if j.rem_euclid(2) == 0 {
                coarse[ch] += 2.0 * h * v16[ch];
            }
            rule[ch] += h * (v16[ch] - v8[ch]).abs();
            model[ch] += h * curv[ch];
        }
    }
    let table_rel = table.error / (KNOWN_FRACTION * table.peak);
    let value = fine.map(|v| v / norm);
    let error: [f64; 3] =
        std::array::from_fn(|ch| ((fine[ch] - coarse[ch]).abs() + rule[ch] + model[ch]) / norm + (own + 2.0 * table_rel) * value[ch].abs());
    if 2.0 * b < blind && value.iter().chain(error.iter()).all(|v| v.is_finite()) {
        // Over the tolerance, but the lattice would do worse (see `LATTICE_BLIND_PX`).
        return Some(ProfilePixel {
            index: i,
            light: Some(k),
            value,
            error,
        });
    }
    accept(input, i, k, value, error)
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::scene::{Light, Scene};

    /// A camera and spots of 5° and 0.5° (one aimed across the view, one
    /// whose apex is inside the frame), as the renderer builds them.
    fn beams() -> (CameraRays, Vec<BeamLight>) {
        let json = serde_json::json!({
            "version": 1,
            "camera": {"type": "perspective", "position": [0, -9, 2], "resolution": [64, 36],
                       "orientation": {"look_at": {"target": [0, 0, 2], "up": [0, 0, 1]}}},
            "lights": [
                {"type": "spot", "name": "a", "position": [-6, 4, 6], "power_w": 100,
                 "orientation": {"look_at": {"target": [4, 2, 0], "up": [0, 0, 1]}}, "spot_size_deg": 5},
                {"type": "spot", "name": "b", "position": [0.5, 2, 2.5], "power_w": 100,
                 "orientation": {"look_at": {"target": [-3, 9, 1], "up": [0, 0, 1]}}, "spot_size_deg": 0.5}
            ],
            "media": [{"type": "homogeneous", "name": "haze", "scattering": 0.05}]
        });
        let scene = Scene::from_json_str(&json.to_string(), "<test>").unwrap();
        let cam = CameraRays::new(&scene.camera);
        let lights = scene
            .lights
            .iter()
            .map(|l| match l {
                Light::Spot(s) => BeamLight::new(&PointSource::<3>::from_spot(s, [1.0; 3], None), &cam, true, true, 1e-4).unwrap(),
                _ => unreachable!(),
            })
            .collect();
        (cam, lights)
    }

    /// A small deterministic generator (xorshift) of points in `[lo, hi)`.
    fn points(n: usize, lo: [f64; 2], hi: [f64; 2]) -> Vec<[f64; 2]> {
        let mut s = 0x9e37_79b9_7f4a_7c15u64;
        let mut next = move || {
            s ^= s << 13;
            s ^= s >> 7;
            s ^= s << 17;
            (s >> 11) as f64 / (1u64 << 53) as f64
        };
        (0..n)
            .map(|_| [lo[0] + (hi[0] - lo[0]) * next(), lo[1] + (hi[1] - lo[1]) * next()])
            .collect()
    }

    #[test]
    fn ray_planes_give_sin_psi_and_its_gradient() {
        let (cam, lights) = beams();
        for light in &lights {
            for p in points(200, [-10.0, -10.0], [74.0, 46.0]) {
                // Independently: the plane through the light and the
                // normalised ray, from the camera's own direction.
                let d = cam.direction(p[0], p[1]);
                let direct = light.plane_of(cam.position, d).0;
                let (s, g) = light.s_and_gradient(p);
                assert!((s - direct).abs() < 1e-12, "{p:?}: {s} vs {direct}");
                let e = 1e-4;
                let at = |x: f64, y: f64| light.plane_of(cam.position, cam.direction(x, y)).0;
                let fd = [
                    (at(p[0] + e, p[1]) - at(p[0] - e, p[1])) / (2.0 * e),
                    (at(p[0], p[1] + e) - at(p[0], p[1] - e)) / (2.0 * e),
                ];
                for a in 0..2 {
                    assert!(
                        (g[a] - fd[a]).abs() < 1e-6 * (1.0 + fd[a].abs()),
                        "{p:?}: ∂{a} {} vs {}",
                        g[a],
                        fd[a]
                    );
                }
            }
        }
    }

    #[test]
    fn band_bounds_never_miss_the_band() {
        let (_, lights) = beams();
        let mut touched = 0;
        for light in &lights {
            let s = |p: [f64; 2]| light.sin_psi_at(p[0], p[1]).abs();
            for c in points(400, [-5.0, -5.0], [69.0, 41.0]) {
                for half in [[0.5, 0.5], [1.5, 1.5], [4.0, 1.0], [8.0, 8.0]] {
                    // A 41 × 41 grid over the rectangle: where any point is in
                    // the band, the bound must say the band may touch it.
                    let inside = (0..=40).any(|i| {
                        (0..=40).any(|j| {
                            let p = [
                                c[0] - half[0] + half[0] * i as f64 / 20.0,
                                c[1] - half[1] + half[1] * j as f64 / 20.0,
                            ];
                            s(p) < light.sin_reach
                        })
                    });
                    if inside {
                        touched += 1;
                        assert!(light.band_may_touch_rect(c, half), "{c:?} ± {half:?}");
                    }
                }
            }
        }
        assert!(touched > 50, "only {touched} rectangles touched a band");
    }

    #[test]
    fn centre_line_and_band_edges_are_exact() {
        let (_, lights) = beams();
        for light in &lights {
            let s = |p: [f64; 2]| light.sin_psi_at(p[0], p[1]);
            let (foot, dir) = light.centre_line([32.0, 18.0]).unwrap();
            let normal = [dir[1], -dir[0]];
            let mut crossed = 0;
            for t in [-60.0, -20.0, -3.0, 0.0, 2.5, 17.0, 45.0] {
                let q = [foot[0] + t * dir[0], foot[1] + t * dir[1]];
                assert!(s(q).abs() < 1e-12, "the line at t = {t}: sin ψ = {}", s(q));
                // Where the band closes around the line (not behind the
                // light's image), its edges lie on |sin ψ| = sin_reach.
                if let Some((lo, hi)) = light.band_across(q, normal) {
                    crossed += 1;
                    assert!(lo < 0.0 && hi > 0.0);
                    for delta in [lo, hi] {
                        let p = [q[0] + delta * normal[0], q[1] + delta * normal[1]];
                        assert!(
                            (s(p).abs() - light.sin_reach).abs() < 1e-9 * light.sin_reach,
                            "edge at {delta}: {}",
                            s(p)
                        );
                    }
                    let mid = [q[0] + 0.5 * (lo + hi) * normal[0], q[1] + 0.5 * (lo + hi) * normal[1]];
                    assert!(s(mid).abs() < light.sin_reach);
                }
            }
            assert!(crossed >= 3, "the band closed around only {crossed} points");
        }
    }
}
