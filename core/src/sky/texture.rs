//! World textures from a sky model: an equirectangular image as Blender's
//! World Environment Texture reads it, computed on an adaptively refined grid
//! and resampled, plus the sun disc and the values for a matching sun lamp.
//!
//! **What the sky depends on.** Both sky models are spherically symmetric
//! about the earth's centre, so the sky radiance seen from the observer
//! depends only on the view zenith angle θ and the azimuth difference
//! Δφ ∈ [0, π] from the sun (mirror symmetry about the sun's vertical plane).
//! The texture is therefore computed on the 2-D domain (θ, Δφ), not per pixel
//! (Klassen §4's "coherence": cost grows with the sky's structure, not with
//! the pixel count).
//!
//! **Adaptive grid with error control.** The domain is split at the horizon
//! θ_h (the radiance has a kink or a jump there: rays below it end on the
//! ground) into two k-d trees, each starting from 8 × 8 cells. A cell's value
//! is bilinear in its four corners. At the midpoints of its edges and its
//! centre the model is compared with the bilinear value; a cell is split in
//! θ where the edges along θ miss `tolerance × Y` in any channel (Y the
//! luminance at that point), in Δφ where the edges along Δφ
//! miss it, and in both where only the centre does — so a sky that varies in
//! one direction is refined in that direction only — down to 2⁻¹⁴ of the
//! domain. The largest such
//! difference over the final cells is the reported interpolation error —
//! an estimate measured on points between nodes, not a bound.
//!
//! **Resampling.** Each pixel (Cycles' `direction_to_equirectangular`: centre
//! column towards +X, top row the zenith) maps to (θ, Δφ); the quadtree is
//! descended to its cell and interpolated.
//!
//! **Sun disc** (optional): uniform radiance with linear limb darkening
//! `I(μ)/I(1) = 1 − u(1 − μ)` (u = 0.6), normalised so that the disc's
//! irradiance equals the model's sun irradiance; pixels near the disc edge
//! are supersampled 8 × 8.

use crate::medium::phase::PhaseFunction;
use crate::spectrum::{self, Spectrum};
use glam::DVec3;
use rayon::prelude::*;
use std::collections::HashMap;
use std::f64::consts::PI;

/// A sky: spectral radiance per view direction and the sun seen through it.
pub trait SkyModel: Sync {
    /// Spectral radiance along unit `view_dir` (+Z up at the observer),
    /// W·m⁻²·sr⁻¹·nm⁻¹, with an absolute error estimate, to `rel_tol`.
    fn sky_radiance(&self, view_dir: DVec3, rel_tol: f64) -> (Spectrum, Spectrum);

    /// The same radiance split as `Σ_k p_k(μ)·S_k + S_rest`, μ = view·sun:
    /// phase-free in-scatter spectra `S_k` of each scattering species with
    /// its phase function, which vary smoothly over the sky even where the
    /// phase function is sharp (the sun's aureole), plus the error estimate.
    /// The default is one component without a phase function.
    fn sky_components(&self, view_dir: DVec3, rel_tol: f64) -> (Vec<(Option<PhaseFunction>, Spectrum)>, Spectrum) {
        let (l, e) = self.sky_radiance(view_dir, rel_tol);
        (vec![(None, l)], e)
    }
    /// Unit vector from the observer towards the sun.
    fn sun_direction(&self) -> DVec3;
    /// Spectral irradiance of the sun at the observer, after the atmosphere, W·m⁻²·nm⁻¹.
    fn sun_irradiance(&self) -> Spectrum;
    /// Angular diameter of the sun, rad.
    fn sun_angular_diameter(&self) -> f64;
    /// Zenith angle of the horizon seen from the observer, rad (π/2 on the ground).
    fn horizon_zenith(&self) -> f64 {
        PI / 2.0
    }
}

/// Settings of a world texture.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct TextureSettings {
    /// Width, px (height = width / 2).
    pub width: usize,
    /// Relative tolerance of the interpolated sky (per channel, relative to luminance), 1e-6..=0.5.
    pub tolerance: f64,
    /// Draw the sun disc.
    pub sun_disc: bool,
}

/// A finished world texture and what it cost.
#[derive(Debug, Clone)]
pub struct WorldTexture {
    /// Width, px.
    pub width: usize,
    /// Height, px.
    pub height: usize,
    /// Linear Rec.709 radiance, W·m⁻²·sr⁻¹ per channel, row 0 at the top.
    pub rgb: Vec<[f32; 3]>,
    /// Sky model evaluations.
    pub evaluations: usize,
    /// Final grid cells.
    pub cells: usize,
    /// Largest measured interpolation error relative to luminance.
    pub interpolation_error: f64,
    /// Largest model error estimate relative to luminance at the nodes.
    pub model_error: f64,
    /// Cells refined down to the output's pixel size that still miss the
    /// tolerance (steps in the sky: the earth's shadow, the horizon); there the
    /// texture is as good as sampling each pixel's centre.
    pub pixel_limited_cells: usize,
    /// Largest interpolation miss in those cells, relative to luminance.
    pub pixel_limited_error: f64,
    /// Pixels supersampled for the sun disc.
    pub sun_pixels: usize,
    /// The sun for a Blender sun lamp: RGB irradiance, W·m⁻² per channel.
    pub sun_rgb_irradiance: [f64; 3],
}

const TICKS_LOG2: u32 = 14;
const TICKS: u32 = 1 << TICKS_LOG2;
const START_LOG2: u32 = 3;

#[derive(Debug, Clone, Copy)]
struct Cell {
    /// Integer corner (u along θ, v along Δφ) in ticks of the half-domain, and sizes.
    u0: u32,
    v0: u32,
    su: u32,
    sv: u32,
}

enum Node {
    /// Indices of the corner points (0 = (u0, v0), 1 = (u1, v0), 2 = (u0, v1), 3 = (u1, v1)).
    Leaf([u32; 4]),
    /// Split along u (θ) into [low, high].
    SplitU([u32; 2]),
    /// Split along v (Δφ) into [low, high].
    SplitV([u32; 2]),
}

/// The sky's components at grid points: `k` RGB values per point.
struct Components {
    /// Phase function of each component (`None`: weight 1).
    phases: Vec<Option<PhaseFunction>>,
    /// Point-major RGB values of the phase-free components.
    values: Vec<[f64; 3]>,
}

impl Components {
    fn k(&self) -> usize {
        self.phases.len()
    }
    fn weights(&self, mu: f64) -> Vec<f64> {
        self.phases.iter().map(|p| p.map(|p| p.eval(mu)).unwrap_or(1.0)).collect()
    }
    /// Σ_k w_k·S_k at point `i`.
    fn combine(&self, i: u32, w: &[f64]) -> [f64; 3] {
        let k = self.k();
        let mut out = [0.0; 3];
        for (j, wj) in w.iter().enumerate() {
            let v = self.values[i as usize * k + j];
            for c in 0..3 {
                out[c] += wj * v[c];
            }
        }
        out
    }
    /// Σ_k w_k·bilinear(S_k) over the four corner points.
    fn interpolate(&self, corners: &[u32; 4], w: &[f64], s: f64, t: f64) -> [f64; 3] {
        let vals = [
            self.combine(corners[0], w),
            self.combine(corners[1], w),
            self.combine(corners[2], w),
            self.combine(corners[3], w),
        ];
        bilinear(&vals, s, t)
    }
}

/// One half of the domain: θ ∈ [theta0, theta1], Δφ ∈ [0, π].
struct Half {
    theta0: f64,
    theta1: f64,
    nodes: Vec<Node>,
    /// Root cells (8 × 8), row-major in (u, v).
    roots: Vec<u32>,
    comps: Components,
}

fn luminance(c: &[f64; 3]) -> f64 {
    0.2126 * c[0] + 0.7152 * c[1] + 0.0722 * c[2]
}

fn bilinear(c: &[[f64; 3]; 4], s: f64, t: f64) -> [f64; 3] {
    let mut out = [0.0; 3];
    for k in 0..3 {
        out[k] = (1.0 - s) * (1.0 - t) * c[0][k] + s * (1.0 - t) * c[1][k] + (1.0 - s) * t * c[2][k] + s * t * c[3][k];
    }
    out
}

/// Refinement limits of one half of the domain.
struct Limits {
    /// Smallest cell extent along θ and Δφ, ticks (half an output pixel).
    min_su: u32,
    min_sv: u32,
    /// Luminance floor for relative errors, as a fraction of the brightest sky.
    floor_fraction: f64,
}

/// What the refinement measured.
#[derive(Debug, Default)]
struct Stats {
    evaluations: usize,
    /// Largest interpolation miss of cells that met the tolerance.
    interpolation: f64,
    model_error: f64,
    brightest: f64,
    /// Cells that reached the pixel size without meeting the tolerance (a step: the earth's shadow, the horizon).
    pixel_limited: usize,
    pixel_limited_error: f64,
}

/// A sky evaluation at one grid point: phase-free component RGB values and the error estimate.
type PointEval = (Vec<(Option<PhaseFunction>, [f64; 3])>, f64);

impl Half {
    fn theta(&self, u: u32) -> f64 {
        self.theta0 + (self.theta1 - self.theta0) * f64::from(u) / f64::from(TICKS)
    }
    fn dphi(v: u32) -> f64 {
        PI * f64::from(v) / f64::from(TICKS)
    }

    fn build(
        theta0: f64,
        theta1: f64,
        eval: &(dyn Fn(f64, f64) -> PointEval + Sync),
        cos_mu: &(dyn Fn(f64, f64) -> f64 + Sync),
        tol: f64,
        limits: &Limits,
        stats: &mut Stats,
    ) -> Half {
        let mut half = Half {
            theta0,
            theta1,
            nodes: Vec::new(),
            roots: Vec::new(),
            comps: Components {
                phases: Vec::new(),
                values: Vec::new(),
            },
        };
        let mut cache: HashMap<(u32, u32), u32> = HashMap::new();
        let n0 = 1u32 << START_LOG2;
        let size0 = TICKS >> START_LOG2;
        let mut pending: Vec<(Cell, u32)> = Vec::new();
        for iu in 0..n0 {
            for iv in 0..n0 {
                let idx = half.nodes.len() as u32;
                half.nodes.push(Node::Leaf([0; 4]));
                half.roots.push(idx);
                pending.push((
                    Cell {
                        u0: iu * size0,
                        v0: iv * size0,
                        su: size0,
                        sv: size0,
                    },
                    idx,
                ));
            }
        }
        while !pending.is_empty() {
            // Every point the pending cells need: corners, centre, edge midpoints.
            let mut need: Vec<(u32, u32)> = Vec::new();
            for (c, _) in &pending {
                let (hu, hv, su, sv) = (c.su / 2, c.sv / 2, c.su, c.sv);
                for (du, dv) in [(0, 0), (su, 0), (0, sv), (su, sv), (hu, hv), (hu, 0), (hu, sv), (0, hv), (su, hv)] {
                    let key = (c.u0 + du, c.v0 + dv);
                    if !cache.contains_key(&key) {
                        need.push(key);
                    }
                }
            }
            need.sort_unstable();
            need.dedup();
            let values: Vec<((u32, u32), PointEval)> = need
                .par_iter()
                .map(|&(u, v)| ((u, v), eval(half.theta(u), Half::dphi(v))))
                .collect();
            stats.evaluations += values.len();
            for (key, (parts, err)) in values {
                if half.comps.phases.is_empty() {
                    half.comps.phases = parts.iter().map(|p| p.0).collect();
                }
                let w = half.comps.weights(cos_mu(half.theta(key.0), Half::dphi(key.1)));
                let mut total = [0.0; 3];
                for (j, (_, rgb)) in parts.iter().enumerate() {
                    for c in 0..3 {
                        total[c] += w.get(j).copied().unwrap_or(1.0) * rgb[c];
                    }
                }
                let y = luminance(&total).abs();
                stats.model_error = stats
                    .model_error
                    .max(err / y.max(limits.floor_fraction * stats.brightest).max(1e-300));
                stats.brightest = stats.brightest.max(y);
                let index = (half.comps.values.len() / half.comps.k().max(1)) as u32;
                for (_, rgb) in parts {
                    half.comps.values.push(rgb);
                }
                cache.insert(key, index);
            }
            let mut next = Vec::new();
            for (c, idx) in pending {
                let (hu, hv, su, sv) = (c.su / 2, c.sv / 2, c.su, c.sv);
                let at = |du: u32, dv: u32| cache[&(c.u0 + du, c.v0 + dv)];
                let corners = [at(0, 0), at(su, 0), at(0, sv), at(su, sv)];
                let mu_at = |du: u32, dv: u32| cos_mu(half.theta(c.u0 + du), Half::dphi(c.v0 + dv));
                let corner_mu = [mu_at(0, 0), mu_at(su, 0), mu_at(0, sv), mu_at(su, sv)];
                // Errors are relative to the luminance at the point, but never to
                // less than a fraction of the brightest sky seen (the dark side of
                // twilight would otherwise ask for relative accuracy in the dark).
                let _ = corner_mu;
                let floor = (limits.floor_fraction * stats.brightest).max(1e-300);
                let miss = |pts: &[(u32, u32, f64, f64)]| -> f64 {
                    let mut worst = 0.0f64;
                    for &(du, dv, ss, tt) in pts {
                        let w = half.comps.weights(mu_at(du, dv));
                        let truth = half.comps.combine(at(du, dv), &w);
                        let lin = half.comps.interpolate(&corners, &w, ss, tt);
                        // Relative to the luminance at the point itself.
                        let scale = luminance(&truth).abs().max(floor);
                        for k in 0..3 {
                            worst = worst.max((truth[k] - lin[k]).abs() / scale);
                        }
                    }
                    worst
                };
                let along_u = miss(&[(hu, 0, 0.5, 0.0), (hu, sv, 0.5, 1.0)]);
                let along_v = miss(&[(0, hv, 0.0, 0.5), (su, hv, 1.0, 0.5)]);
                let centre = miss(&[(hu, hv, 0.5, 0.5)]);
                // Never finer than the output pixels: below that the pixel grid
                // itself is the resolution (counted and reported separately).
                let can_u = su > limits.min_su;
                let can_v = sv > limits.min_sv;
                let (need_u, need_v) = (along_u > tol, along_v > tol);
                // A centre miss with both edge pairs fine is a cross term: split in u
                // (or in v where u is at the pixel limit). A miss in a direction that
                // is already at the pixel limit is not chased in the other direction.
                let cross = centre > tol && !need_u && !need_v;
                let split_u = can_u && (need_u || cross);
                let split_v = can_v && (need_v || (cross && !can_u));
                if split_u || split_v {
                    let mut child = |cell: Cell| -> u32 {
                        let k = half.nodes.len() as u32;
                        half.nodes.push(Node::Leaf([0; 4]));
                        next.push((cell, k));
                        k
                    };
                    // Split along u first when both are needed; the halves are
                    // split along v on the next round if they still miss.
                    half.nodes[idx as usize] = if split_u {
                        let a = child(Cell { su: hu, ..c });
                        let b = child(Cell {
                            u0: c.u0 + hu,
                            su: su - hu,
                            ..c
                        });
                        Node::SplitU([a, b])
                    } else {
                        let a = child(Cell { sv: hv, ..c });
                        let b = child(Cell {
                            v0: c.v0 + hv,
                            sv: sv - hv,
                            ..c
                        });
                        Node::SplitV([a, b])
                    };
                } else {
                    let miss_all = along_u.max(along_v).max(centre);
                    if miss_all > tol {
                        stats.pixel_limited += 1;
                        stats.pixel_limited_error = stats.pixel_limited_error.max(miss_all);
                    } else {
                        stats.interpolation = stats.interpolation.max(miss_all);
                    }
                    half.nodes[idx as usize] = Node::Leaf(corners);
                }
            }
            pending = next;
        }
        half
    }

    /// Interpolated value at θ (inside this half), Δφ, and μ = cos(angle to the sun).
    fn lookup(&self, theta: f64, dphi: f64, mu: f64) -> [f64; 3] {
        let fu = ((theta - self.theta0) / (self.theta1 - self.theta0)).clamp(0.0, 1.0) * f64::from(TICKS);
        let fv = (dphi / PI).clamp(0.0, 1.0) * f64::from(TICKS);
        let n0 = 1u32 << START_LOG2;
        let size0 = f64::from(TICKS >> START_LOG2);
        let iu = ((fu / size0) as u32).min(n0 - 1);
        let iv = ((fv / size0) as u32).min(n0 - 1);
        let mut idx = self.roots[(iu * n0 + iv) as usize];
        let (mut u0, mut v0, mut su, mut sv) = (f64::from(iu) * size0, f64::from(iv) * size0, size0, size0);
        loop {
            match &self.nodes[idx as usize] {
                Node::Leaf(c) => {
                    let w = self.comps.weights(mu);
                    return self
                        .comps
                        .interpolate(c, &w, ((fu - u0) / su).clamp(0.0, 1.0), ((fv - v0) / sv).clamp(0.0, 1.0));
                }
                Node::SplitU(kids) => {
                    let h = (su / 2.0).floor();
                    if fu >= u0 + h {
                        u0 += h;
                        su -= h;
                        idx = kids[1];
                    } else {
                        su = h;
                        idx = kids[0];
                    }
                }
                Node::SplitV(kids) => {
                    let h = (sv / 2.0).floor();
                    if fv >= v0 + h {
                        v0 += h;
                        sv -= h;
                        idx = kids[1];
                    } else {
                        sv = h;
                        idx = kids[0];
                    }
                }
            }
        }
    }

    fn cells(&self) -> usize {
        self.nodes.iter().filter(|n| matches!(n, Node::Leaf(_))).count()
    }
}

/// Direction of equirectangular image point (x, y) (pixels from the top-left),
/// Cycles' environment mapping: centre column → +X, top row → +Z.
pub fn equirect_direction(x: f64, y: f64, width: usize, height: usize) -> DVec3 {
    let theta = PI * y / height as f64;
    let phi = PI - 2.0 * PI * x / width as f64;
    let (st, ct) = theta.sin_cos();
    let (sp, cp) = phi.sin_cos();
    DVec3::new(st * cp, st * sp, ct)
}

/// Builds the world texture of `model`.
pub fn build_world_texture(model: &dyn SkyModel, settings: &TextureSettings) -> WorldTexture {
    let width = settings.width.max(2);
    let height = (width / 2).max(1);
    let sun = model.sun_direction();
    let sun_phi = sun.y.atan2(sun.x);
    let tol = settings.tolerance;
    let direction = |theta: f64, dphi: f64| {
        let (st, ct) = theta.sin_cos();
        let phi = sun_phi + dphi;
        DVec3::new(st * phi.cos(), st * phi.sin(), ct)
    };
    let eval = |theta: f64, dphi: f64| -> PointEval {
        // The model to a twentieth of the tolerance, so that refinement does not chase quadrature noise.
        let (parts, e) = model.sky_components(direction(theta, dphi), 0.05 * tol);
        let err = spectrum::spectrum_to_rec709(&e.map(f64::abs))
            .iter()
            .fold(0.0f64, |a, b| a.max(b.abs()));
        (parts.into_iter().map(|(p, l)| (p, spectrum::spectrum_to_rec709(&l))).collect(), err)
    };
    let cos_mu = |theta: f64, dphi: f64| direction(theta, dphi).dot(sun);
    let horizon = model.horizon_zenith().clamp(1e-6, PI - 1e-6);
    let mut stats = Stats::default();
    // Each half is evaluated strictly on its own side of the horizon.
    const SIDE: f64 = 1e-9;
    // Cells stop at half an output pixel: θ pixels are π/height, Δφ pixels 2π/width.
    let limits = |theta_span: f64| Limits {
        min_su: ((f64::from(TICKS) * 0.5 * (PI / height as f64) / theta_span) as u32).max(1),
        min_sv: ((f64::from(TICKS) * 0.5 * (2.0 * PI / width as f64) / PI) as u32).max(1),
        floor_fraction: 1e-4,
    };
    let upper = Half::build(0.0, horizon - SIDE, &eval, &cos_mu, tol, &limits(horizon), &mut stats);
    let lower = Half::build(horizon + SIDE, PI, &eval, &cos_mu, tol, &limits(PI - horizon), &mut stats);
    let lookup = |d: DVec3| -> [f64; 3] {
        let theta = d.z.clamp(-1.0, 1.0).acos();
        let mut dphi = (d.y.atan2(d.x) - sun_phi).rem_euclid(2.0 * PI);
        if dphi > PI {
            dphi = 2.0 * PI - dphi;
        }
        let mu = d.dot(sun);
        if theta <= horizon {
            upper.lookup(theta, dphi, mu)
        } else {
            lower.lookup(theta, dphi, mu)
        }
    };
    let mut rgb: Vec<[f32; 3]> = (0..height)
        .into_par_iter()
        .flat_map_iter(|j| {
            let lookup = &lookup;
            (0..width).map(move |i| lookup(equirect_direction(i as f64 + 0.5, j as f64 + 0.5, width, height)).map(|v| v as f32))
        })
        .collect();

    // The sun: its irradiance after the atmosphere, as RGB for a sun lamp, and
    // optionally its disc in the texture.
    let sun_spec = model.sun_irradiance();
    let sun_rgb = spectrum::spectrum_to_rec709(&sun_spec);
    let mut sun_pixels = 0;
    let radius = 0.5 * model.sun_angular_diameter();
    if settings.sun_disc && radius > 0.0 && sun_rgb.iter().any(|v| *v > 0.0) {
        const LIMB_U: f64 = 0.6;
        // ∫ over the cap of (1 − u(1 − μ')) dΩ ≈ Ω(1 − u/3) for a small disc, μ' the
        // cosine across the solar radius; Ω = 2π(1 − cos r) written with sin².
        let omega = 4.0 * PI * (0.5 * radius).sin().powi(2);
        let centre = sun_rgb.map(|v| v / (omega * (1.0 - LIMB_U / 3.0)));
        let pixel_angle = 2.0 * PI / width as f64;
        let reach = radius + 1.5 * pixel_angle;
        let disc_value = |d: DVec3| -> Option<f64> {
            let ang = d.angle_between(sun);
            if ang > radius {
                return None;
            }
            let rho = ang / radius;
            let mu = (1.0 - rho * rho).max(0.0).sqrt();
            Some(1.0 - LIMB_U * (1.0 - mu))
        };
        // Pixels whose centre is within reach of the disc: only the rows around
        // the sun's zenith angle can hold any; supersample those 8×8.
        let theta_s = sun.z.clamp(-1.0, 1.0).acos();
        let row_of = |theta: f64| theta / PI * height as f64;
        let j0 = row_of((theta_s - reach - pixel_angle).max(0.0)).floor().max(0.0) as usize;
        let j1 = (row_of((theta_s + reach + pixel_angle).min(PI)).ceil() as usize).min(height);
        let candidates: Vec<usize> = (j0..j1)
            .flat_map(|j| (0..width).map(move |i| j * width + i))
            .filter(|&p| {
                equirect_direction((p % width) as f64 + 0.5, (p / width) as f64 + 0.5, width, height).angle_between(sun)
                    <= reach + pixel_angle
            })
            .collect();
        for p in candidates {
            let (i, j) = ((p % width) as f64, (p / width) as f64);
            let mut acc = 0.0;
            for a in 0..8 {
                for b in 0..8 {
                    let d = equirect_direction(i + (f64::from(a) + 0.5) / 8.0, j + (f64::from(b) + 0.5) / 8.0, width, height);
                    acc += disc_value(d).unwrap_or(0.0);
                }
            }
            if acc > 0.0 {
                sun_pixels += 1;
                let f = acc / 64.0;
                for k in 0..3 {
                    rgb[p][k] += (centre[k] * f) as f32;
                }
            }
        }
    }
    WorldTexture {
        width,
        height,
        rgb,
        evaluations: stats.evaluations,
        cells: upper.cells() + lower.cells(),
        interpolation_error: stats.interpolation,
        model_error: stats.model_error,
        pixel_limited_cells: stats.pixel_limited,
        pixel_limited_error: stats.pixel_limited_error,
        sun_pixels,
        sun_rgb_irradiance: sun_rgb,
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::spectrum::SPECTRAL_SAMPLES;

    /// A smooth toy sky with a sharp sun glow, spectral and cheap.
    pub(super) struct Toy {
        pub(super) sun: DVec3,
    }
    impl SkyModel for Toy {
        fn sky_radiance(&self, d: DVec3, _tol: f64) -> (Spectrum, Spectrum) {
            let mu = d.dot(self.sun);
            let glow = 0.05 / (1.0 + 0.81 - 1.8 * mu).powf(1.5);
            let horizon = if d.z >= 0.0 { 1.0 + 2.0 * (-d.z * 8.0).exp() } else { 0.2 };
            let wl = spectrum::wavelengths_nm();
            let mut s = [0.0; SPECTRAL_SAMPLES];
            for (k, l) in wl.iter().enumerate() {
                s[k] = (glow + 0.01 * horizon * (550.0 / l).powi(4)) * 1e-2;
            }
            (s, [0.0; SPECTRAL_SAMPLES])
        }
        fn sky_components(&self, d: DVec3, _tol: f64) -> (Vec<(Option<PhaseFunction>, Spectrum)>, Spectrum) {
            // glow = 0.05·(1.81 − 1.8μ)^-1.5 = 0.05·4π/(1 − 0.81)·p_HG(μ; g = 0.9).
            let k = 0.05 * 4.0 * PI / (1.0 - 0.81);
            let horizon = if d.z >= 0.0 { 1.0 + 2.0 * (-d.z * 8.0).exp() } else { 0.2 };
            let wl = spectrum::wavelengths_nm();
            let mut mie = [0.0; SPECTRAL_SAMPLES];
            let mut rest = [0.0; SPECTRAL_SAMPLES];
            for (i, l) in wl.iter().enumerate() {
                mie[i] = k * 1e-2;
                rest[i] = 0.01 * horizon * (550.0 / l).powi(4) * 1e-2;
            }
            (
                vec![(Some(PhaseFunction::HenyeyGreenstein { g: 0.9 }), mie), (None, rest)],
                [0.0; SPECTRAL_SAMPLES],
            )
        }
        fn sun_direction(&self) -> DVec3 {
            self.sun
        }
        fn sun_irradiance(&self) -> Spectrum {
            *spectrum::solar_spectral_irradiance()
        }
        fn sun_angular_diameter(&self) -> f64 {
            0.545f64.to_radians()
        }
    }

    #[test]
    fn interpolated_texture_meets_the_tolerance_at_every_pixel() {
        let toy = Toy {
            sun: DVec3::new(0.3, 0.8, 0.25).normalize(),
        };
        let tol = 1e-3;
        let t = build_world_texture(
            &toy,
            &TextureSettings {
                width: 256,
                tolerance: tol,
                sun_disc: false,
            },
        );
        let mut worst = 0.0f64;
        for j in 0..t.height {
            for i in 0..t.width {
                let d = equirect_direction(i as f64 + 0.5, j as f64 + 0.5, t.width, t.height);
                let exact = spectrum::spectrum_to_rec709(&toy.sky_radiance(d, 0.0).0);
                let y = luminance(&exact);
                for k in 0..3 {
                    worst = worst.max((f64::from(t.rgb[j * t.width + i][k]) - exact[k]).abs() / y);
                }
            }
        }
        eprintln!(
            "toy sky: worst pixel error {worst:.3e} (reported {:.3e}), {} evaluations, {} cells",
            t.interpolation_error, t.evaluations, t.cells
        );
        // The measured error between nodes is an estimate; allow it a factor 4 at pixels.
        assert!(
            worst <= 4.0 * tol,
            "worst pixel error {worst:.3e}, reported {:.3e}",
            t.interpolation_error
        );
        assert!(
            t.evaluations < t.width * t.height / 4,
            "{} evaluations for {} pixels",
            t.evaluations,
            t.width * t.height
        );
    }

    /// Largest error, relative to luminance, of a 128-px texture at every 3rd
    /// pixel of the upper hemisphere against the model evaluated directly to 1e-8.
    fn worst_pixel_error(model: &dyn SkyModel, tol: f64, label: &str) -> f64 {
        let t = build_world_texture(
            model,
            &TextureSettings {
                width: 128,
                tolerance: tol,
                sun_disc: false,
            },
        );
        let mut worst = 0.0f64;
        for j in (0..t.height / 2).step_by(3) {
            for i in (0..t.width).step_by(3) {
                let d = equirect_direction(i as f64 + 0.5, j as f64 + 0.5, t.width, t.height);
                let exact = spectrum::spectrum_to_rec709(&model.sky_radiance(d, 1e-8).0);
                let y = luminance(&exact);
                for k in 0..3 {
                    worst = worst.max((f64::from(t.rgb[j * t.width + i][k]) - exact[k]).abs() / y);
                }
            }
        }
        eprintln!(
            "{label}: worst pixel {worst:.3e}, reported {:.3e}, {} evaluations",
            t.interpolation_error, t.evaluations
        );
        worst
    }

    #[test]
    fn atmosphere_texture_matches_direct_evaluation() {
        use crate::sky::atmosphere::AtmosphereParams;
        for elevation in [40.0f64, 5.0] {
            let atm = AtmosphereParams {
                sun_elevation_rad: elevation.to_radians(),
                sun_rotation_rad: 0.7,
                ..Default::default()
            };
            let worst = worst_pixel_error(&atm, 1e-3, &format!("atmosphere, sun {elevation}°"));
            assert!(worst <= 2e-3, "sun {elevation}°: worst pixel error {worst:.3e}");
        }
    }

    #[test]
    fn klassen_texture_matches_direct_evaluation() {
        use crate::sky::klassen::{KlassenParams, KlassenSky, KlassenWorld};
        let world = KlassenWorld {
            sky: KlassenSky::new(KlassenParams::default()).unwrap_or_else(|e| panic!("{e:?}")),
            sun: crate::sky::blender_sun_direction(25f64.to_radians(), 0.4),
            sun_diameter_rad: 0.545f64.to_radians(),
        };
        let worst = worst_pixel_error(&world, 1e-3, "klassen");
        assert!(worst <= 2e-3, "worst pixel error {worst:.3e}");
    }

    #[test]
    fn cost_grows_far_below_the_pixel_count() {
        let toy = Toy {
            sun: DVec3::new(0.0, 1.0, 0.1).normalize(),
        };
        let s = |w| {
            build_world_texture(
                &toy,
                &TextureSettings {
                    width: w,
                    tolerance: 1e-3,
                    sun_disc: false,
                },
            )
            .evaluations
        };
        let (a, b, c) = (s(128), s(2048), s(4096));
        // Small textures stop refining at their pixel size; once the pixels are finer
        // than the sky's structure the grid no longer depends on the output size.
        assert!(a <= b, "{a} > {b}");
        assert_eq!(b, c);
    }

    #[test]
    fn sun_disc_carries_the_sun_irradiance() {
        let toy = Toy {
            sun: DVec3::new(0.2, 0.9, 0.4).normalize(),
        };
        let w = 4096;
        let with = build_world_texture(
            &toy,
            &TextureSettings {
                width: w,
                tolerance: 1e-2,
                sun_disc: true,
            },
        );
        let without = build_world_texture(
            &toy,
            &TextureSettings {
                width: w,
                tolerance: 1e-2,
                sun_disc: false,
            },
        );
        // ∫ (with − without) dΩ over the texture = the sun's irradiance (per channel).
        let h = with.height;
        let mut e = [0.0f64; 3];
        for j in 0..h {
            let theta = PI * (j as f64 + 0.5) / h as f64;
            let domega = theta.sin() * (PI / h as f64) * (2.0 * PI / w as f64);
            for i in 0..w {
                for k in 0..3 {
                    e[k] += f64::from(with.rgb[j * w + i][k] - without.rgb[j * w + i][k]) * domega;
                }
            }
        }
        for k in 0..3 {
            assert!(
                (e[k] - with.sun_rgb_irradiance[k]).abs() < 0.02 * with.sun_rgb_irradiance[k],
                "channel {k}: {} vs {}",
                e[k],
                with.sun_rgb_irradiance[k]
            );
        }
        assert!(with.sun_pixels > 0);
    }
}
