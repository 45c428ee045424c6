//! Homogeneous medium, in the whole world or in a box (axis-aligned, or
//! turned about its centre).
//!
//! Single scattering along `[s₀, s₁]` (the part of the view ray inside the
//! medium), Klassen eq 1.11 with constant coefficients:
//!
//! `L = ∫_{s₀}^{s₁} σ_s·(Σ_k p(μ_k)·E_k·T_k(s) + L_amb)·e^{−σ_t (s − s₀)} ds`.
//!
//! * **World** (Blender's world volume): sunlight arrives unattenuated at
//!   every point (`T_k = 1`, as in Ishiyama eq 11 — an infinite medium would
//!   otherwise extinguish a sun completely), so
//!   `L = σ_s (Σ p E + L_amb)/σ_t · (1 − e^{−σ_t ℓ})`, `ℓ = s₁ − s₀`.
//! * **Box** (a haze volume object): sunlight is attenuated only inside the
//!   box, `T_k(s) = e^{−σ_t d(s)}` with `d(s)` the distance from `x(s)` to the
//!   box boundary towards the sun. `d(s) = min_i f_i(s)` over the three slabs,
//!   each `f_i` linear in `s`, so `d` is piecewise linear with at most three
//!   break points; on each piece the integrand is one exponential and
//!   integrates in closed form, `∫ e^{−k u} du = (1 − e^{−kℓ})/k` evaluated as
//!   [`crate::numeric::integral_exp_neg`], with the larger end factored out
//!   when `k < 0` so that no positive exponent is ever formed.
//!
//! * **Turned box:** a rotation about the box's centre is an isometry, so a
//!   ray `o + s·d` maps to `o' + s·d'` in the box's frame with the same `s`
//!   (`o' = c + Rᵀ(o − c)`, `d' = Rᵀd`), and so does the sun direction; the
//!   axis-aligned formulas above then apply unchanged in that frame.
//!
//! Error: closed form; rounding bound ≈ 32 ε relative per piece.

use super::phase::PhaseFunction;
use super::{LightSet, RayResult, ViewRay, rounding_bound, rounding_rel};
use crate::numeric::{integral_exp_neg, one_minus_exp_neg};
use glam::{DMat3, DQuat, DVec3};

/// Homogeneous medium with coefficients resolved to `C` channels.
#[derive(Debug, Clone)]
pub struct Homogeneous<const C: usize> {
    /// Name for reports.
    pub name: String,
    /// Scattering coefficient σ_s, m⁻¹.
    pub scattering: [f64; C],
    /// Extinction coefficient σ_t = σ_s + σ_a, m⁻¹.
    pub extinction: [f64; C],
    /// Phase function.
    pub phase: PhaseFunction,
    /// `None` for the world, `Some(box)` for a box.
    pub bounds: Option<MediumBox>,
}

/// The extent of a box medium: `min ≤ q ≤ max` for the point `q` in the
/// box's frame, the world turned about the box's centre.
#[derive(Debug, Clone, Copy, PartialEq)]
pub struct MediumBox {
    /// Minimum corner in the box's frame, m.
    pub min: DVec3,
    /// Maximum corner in the box's frame, m.
    pub max: DVec3,
    /// World → box frame (`Rᵀ` of the rotation box → world); `None` for an
    /// axis-aligned box, whose points are used as they are (no rounding
    /// from a turn by the identity).
    world_to_box: Option<DMat3>,
}

impl MediumBox {
    /// The box `min ≤ x ≤ max` turned by `rotation` (box → world, unit) about its centre.
    pub fn new(min: DVec3, max: DVec3, rotation: Option<DQuat>) -> Self {
        let world_to_box = rotation.filter(|q| *q != DQuat::IDENTITY).map(|q| DMat3::from_quat(q).transpose());
        MediumBox { min, max, world_to_box }
    }

    /// An axis-aligned box.
    pub fn axis_aligned(min: DVec3, max: DVec3) -> Self {
        Self::new(min, max, None)
    }

    /// The box's centre (the same in both frames).
    pub fn centre(&self) -> DVec3 {
        0.5 * (self.min + self.max)
    }

    /// Radius of the ball about [`Self::centre`] that holds the box.
    pub fn radius(&self) -> f64 {
        0.5 * (self.max - self.min).length()
    }

    /// Whether the box is turned.
    pub fn is_rotated(&self) -> bool {
        self.world_to_box.is_some()
    }

    /// The world point `p` in the box's frame.
    #[inline]
    pub fn local_point(&self, p: DVec3) -> DVec3 {
        match self.world_to_box {
            None => p,
            Some(m) => {
                let c = self.centre();
                c + m * (p - c)
            }
        }
    }

    /// The world direction `d` in the box's frame.
    #[inline]
    pub fn local_dir(&self, d: DVec3) -> DVec3 {
        match self.world_to_box {
            None => d,
            Some(m) => m * d,
        }
    }

    /// Whether the world point `p` is inside (or on) the box.
    #[inline]
    pub fn contains(&self, p: DVec3) -> bool {
        let q = self.local_point(p);
        !(q.cmplt(self.min).any() || q.cmpgt(self.max).any())
    }

    /// Where, on the ray `o + t·d` (`t > 0`), the length inside the box of the
    /// segment from `x(t)` to `light` has kinks, pushed to `out` (a light inside
    /// the box as well: from a point outside, the segment leaves through a side). All those segments lie in the plane through the light and the
    /// ray, which cuts the box in a convex polygon; the length is smooth
    /// while the segment enters and leaves through the same two sides and
    /// kinks where it passes a corner of the polygon, a point where an edge
    /// of the box crosses the plane. The ray meets the line from the light
    /// through each such point at one `t`. (A segment touching an edge only
    /// is a corner too.) A ray through the light has no plane: nothing is
    /// pushed, and the caller's quadrature is on its own there.
    pub fn light_path_kinks(&self, o: DVec3, d: DVec3, light: DVec3, out: &mut Vec<f64>) {
        let (o, d, light) = (self.local_point(o), self.local_dir(d), self.local_point(light));
        let to_light = light - o;
        let n = d.cross(to_light);
        // (NaN: no plane either.)
        let has_plane = n.length() > 1e-12 * d.length() * to_light.length();
        if !has_plane {
            return;
        }
        for v in self.section_corners(n, light) {
            // o + t·d = light + λ·(v − light): crossed with w = v − light and dotted with n.
            let w = v - light;
            let den = d.cross(w).dot(n);
            if den != 0.0 {
                let t = to_light.cross(w).dot(n) / den;
                if t.is_finite() && t > 0.0 {
                    out.push(t);
                }
            }
        }
    }

    /// The same for parallel light (a window): where, on the ray `o + t·d`,
    /// the length inside the box of the segment from `x(t)` along the unit
    /// `to_light` to the plane `end(x)` (affine in `x`, the window's) kinks:
    /// where the line through `x(t)` along `to_light` passes a corner of the
    /// box's section by the plane of the ray and `to_light`, and where the
    /// segment's far end crosses the box's faces. `window_end(t)` gives that
    /// end for a ray parameter (affine in `t`).
    pub fn parallel_path_kinks(&self, o: DVec3, d: DVec3, to_light: DVec3, window_end: &dyn Fn(f64) -> DVec3, out: &mut Vec<f64>) {
        let (lo, ld, ll) = (self.local_point(o), self.local_dir(d), self.local_dir(to_light));
        let n = ld.cross(ll);
        let has_plane = n.length() > 1e-12 * ld.length() * ll.length();
        if has_plane {
            let den = n.dot(n);
            for v in self.section_corners(n, lo) {
                // lo + t·ld + λ·ll = v: crossed with ll and dotted with n.
                let t = (v - lo).cross(ll).dot(n) / den;
                if t.is_finite() && t > 0.0 {
                    out.push(t);
                }
            }
        }
        // The far end moves on a line: its entry into and exit from the box.
        let (e0, e1) = (window_end(0.0), window_end(1.0));
        if let Some((a, b)) = self.ray_interval(e0, e1 - e0) {
            out.extend([a, b].into_iter().filter(|t| t.is_finite() && *t > 0.0));
        }
    }

    /// The corners of the box's section by the plane through `on` with
    /// normal `n` (box frame): where its 12 edges cross the plane.
    fn section_corners(&self, n: DVec3, on: DVec3) -> impl Iterator<Item = DVec3> + '_ {
        let corner = |i: usize| {
            DVec3::new(
                if i & 1 == 0 { self.min.x } else { self.max.x },
                if i & 2 == 0 { self.min.y } else { self.max.y },
                if i & 4 == 0 { self.min.z } else { self.max.z },
            )
        };
        (0..8)
            .flat_map(move |i| {
                [1, 2, 4]
                    .into_iter()
                    .filter(move |bit| i & bit == 0)
                    .map(move |bit| (corner(i), corner(i | bit)))
            })
            .filter_map(move |(p0, p1)| {
                let (s0, s1) = (n.dot(p0 - on), n.dot(p1 - on));
                let apart = (s0 > 0.0 && s1 > 0.0) || (s0 < 0.0 && s1 < 0.0) || s0 == s1;
                (!apart).then(|| p0 + (p1 - p0) * (s0 / (s0 - s1)))
            })
    }

    /// Parametric interval `[t0, t1]` where the world ray `o + t·d` is inside
    /// the box (`t` is the world parameter: the turn is an isometry).
    #[inline]
    pub fn ray_interval(&self, o: DVec3, d: DVec3) -> Option<(f64, f64)> {
        ray_box(self.local_point(o), self.local_dir(d), self.min, self.max)
    }
}

/// Parametric interval `[t0, t1]` where `o + t·d` is inside the box (slab method).
pub(crate) fn ray_box(o: DVec3, d: DVec3, min: DVec3, max: DVec3) -> Option<(f64, f64)> {
    let mut t0 = f64::NEG_INFINITY;
    let mut t1 = f64::INFINITY;
    for i in 0..3 {
        if d[i] == 0.0 {
            if o[i] < min[i] || o[i] > max[i] {
                return None;
            }
        } else {
            let a = (min[i] - o[i]) / d[i];
            let b = (max[i] - o[i]) / d[i];
            t0 = t0.max(a.min(b));
            t1 = t1.min(a.max(b));
        }
    }
    if t0 <= t1 { Some((t0, t1)) } else { None }
}

impl<const C: usize> Homogeneous<C> {
    /// Part of `[0, s_max]` inside the medium.
    pub fn segment(&self, ray: &ViewRay) -> Option<(f64, f64)> {
        match self.bounds {
            None => Some((0.0, ray.s_max)),
            Some(b) => {
                let (a, b) = b.ray_interval(ray.origin, ray.dir)?;
                let s0 = a.max(0.0);
                let s1 = b.min(ray.s_max);
                if s1 > s0 { Some((s0, s1)) } else { None }
            }
        }
    }

    fn inside_length(&self, ray: &ViewRay, s: f64) -> f64 {
        match self.segment(&ViewRay { s_max: s, ..*ray }) {
            Some((a, b)) => b - a,
            None => 0.0,
        }
    }

    /// Optical depth from the origin to `s`.
    pub fn optical_depth(&self, ray: &ViewRay, s: f64) -> [f64; C] {
        let l = self.inside_length(ray, s);
        self.extinction.map(|k| if k == 0.0 { 0.0 } else { k * l })
    }

    /// Length of the sun ray from `p` inside the medium (∞ in the world case is
    /// not used: the world sun is unattenuated).
    fn sun_path(&self, p: DVec3, to_sun: DVec3) -> f64 {
        match self.bounds {
            None => 0.0,
            Some(b) => match b.ray_interval(p, to_sun) {
                Some((a, b)) => (b - a.max(0.0)).max(0.0),
                None => 0.0,
            },
        }
    }

    /// Sun transmittance at `p`.
    pub fn sun_transmittance_at(&self, p: DVec3, to_sun: DVec3) -> [f64; C] {
        let d = self.sun_path(p, to_sun);
        self.extinction.map(|k| if k == 0.0 || d == 0.0 { 1.0 } else { (-k * d).exp() })
    }

    /// Source σ_s J at distance `s` (zero outside the box).
    pub fn source(&self, ray: &ViewRay, s: f64, lights: &LightSet<C>) -> [f64; C] {
        let p = ray.origin + ray.dir * s;
        if let Some(b) = self.bounds
            && !b.contains(p)
        {
            return [0.0; C];
        }
        super::scattering_source(&self.scattering, &self.phase, ray.dir, lights, |sun| {
            Some(self.sun_transmittance_at(p, sun.to_sun))
        })
    }

    /// Closed-form single scattering on the ray.
    pub fn closed_form(&self, ray: &ViewRay, lights: &LightSet<C>) -> RayResult<C> {
        let mut r = RayResult::vacuum();
        let end = ray.origin + ray.dir * if ray.s_max.is_finite() { ray.s_max } else { 0.0 };
        if let (Some(sun), true) = (lights.suns.first(), ray.s_max.is_finite()) {
            r.sun_transmittance = self.sun_transmittance_at(end, sun.to_sun);
        }
        let Some((s0, s1)) = self.segment(ray) else { return r };
        let len = s1 - s0;
        for c in 0..C {
            let k = self.extinction[c];
            if k == 0.0 {
                continue;
            }
            let tau = k * len;
            r.transmittance[c] = (-tau).exp();
            let one_minus_t = one_minus_exp_neg(tau);
            r.inscatter[c] = self.scattering[c] * lights.ambient[c] / k * one_minus_t;
        }
        for sun in &lights.suns {
            let ph = sun.phase(&self.phase, ray.dir);
            match self.bounds {
                None => {
                    for c in 0..C {
                        let k = self.extinction[c];
                        if k > 0.0 {
                            r.inscatter[c] += self.scattering[c] * ph * sun.irradiance[c] / k * one_minus_exp_neg(k * len);
                        }
                    }
                }
                Some(b) => {
                    let integral = self.attenuated_sun_integral(ray, s0, s1, sun.to_sun, &b);
                    for c in 0..C {
                        r.inscatter[c] += self.scattering[c] * ph * sun.irradiance[c] * integral[c];
                    }
                }
            }
        }
        for c in 0..C {
            r.error[c] = rounding_bound(r.inscatter[c], 32.0 * (1.0 + lights.suns.len() as f64 * 3.0));
        }
        r.rel_bound = rounding_rel(32.0 * (1.0 + lights.suns.len() as f64 * 3.0));
        r
    }

    /// `∫_{s0}^{s1} e^{−σ_t (s − s0) − σ_t d(s)} ds` per channel, `d(s)` the
    /// sun path inside the box: piecewise linear, integrated piece by piece
    /// (in the box's frame, where the slabs are along the axes).
    fn attenuated_sun_integral(&self, ray: &ViewRay, s0: f64, s1: f64, to_sun: DVec3, b: &MediumBox) -> [f64; C] {
        let (min, max) = (b.min, b.max);
        let (origin, dir, to_sun) = (b.local_point(ray.origin), b.local_dir(ray.dir), b.local_dir(to_sun));
        // f_i(s) = a_i + b_i s: distance along to_sun to the exit plane of slab i.
        let mut lines: Vec<(f64, f64)> = Vec::with_capacity(3);
        for i in 0..3 {
            if to_sun[i] != 0.0 {
                let bound = if to_sun[i] > 0.0 { max[i] } else { min[i] };
                lines.push(((bound - origin[i]) / to_sun[i], -dir[i] / to_sun[i]));
            }
        }
        let mut breaks = vec![s0, s1];
        for i in 0..lines.len() {
            for j in (i + 1)..lines.len() {
                let db = lines[i].1 - lines[j].1;
                if db != 0.0 {
                    let s = (lines[j].0 - lines[i].0) / db;
                    if s > s0 && s < s1 {
                        breaks.push(s);
                    }
                }
            }
        }
        breaks.sort_by(f64::total_cmp);
        let mut total = [0.0; C];
        for w in breaks.windows(2) {
            let (u0, u1) = (w[0], w[1]);
            if u1 <= u0 {
                continue;
            }
            let mid = if u1.is_finite() { 0.5 * (u0 + u1) } else { u0 + 1.0 };
            let (a, b) = lines
                .iter()
                .copied()
                .min_by(|x, y| (x.0 + x.1 * mid).total_cmp(&(y.0 + y.1 * mid)))
                .unwrap_or((0.0, 0.0));
            let d0 = (a + b * u0).max(0.0);
            let len = u1 - u0;
            for c in 0..C {
                let k = self.extinction[c];
                let rate = k * (1.0 + b);
                let e0 = k * ((u0 - s0) + d0);
                total[c] += if rate >= 0.0 {
                    (-e0).exp() * integral_exp_neg(rate, len)
                } else {
                    // Factor out the larger end u1: exponent e0 + rate·len ≥ 0 physically.
                    let e1 = (e0 + rate * len).max(0.0);
                    (-e1).exp() * integral_exp_neg(-rate, len)
                };
            }
        }
        total
    }
}

#[cfg(test)]
mod tests {
    use super::*;
    use crate::medium::SunSource;
    use crate::numeric::integrate_adaptive;

    #[test]
    fn box_sun_integral_matches_quadrature() {
        let m = Homogeneous::<3> {
            name: "box".into(),
            scattering: [0.05, 0.1, 0.2],
            extinction: [0.1, 0.2, 0.4],
            phase: PhaseFunction::HenyeyGreenstein { g: 0.3 },
            bounds: Some(MediumBox::axis_aligned(DVec3::new(-2.0, -3.0, 0.0), DVec3::new(4.0, 3.0, 5.0))),
        };
        let lights = LightSet {
            suns: vec![SunSource::point(DVec3::new(0.3, -0.2, 0.9).normalize(), [1.0, 2.0, 3.0])],
            ambient: [0.0; 3],
        };
        for dir in [
            DVec3::new(1.0, 0.2, 0.1),
            DVec3::new(0.1, 1.0, 0.05),
            DVec3::new(1.0, 1.0, 1.0),
            DVec3::new(1.0, 0.0, 0.0),
        ] {
            let ray = ViewRay {
                origin: DVec3::new(-5.0, -1.0, 1.0),
                dir: dir.normalize(),
                s_max: 30.0,
            };
            let r = m.closed_form(&ray, &lights);
            let (s0, s1) = m.segment(&ray).unwrap_or((0.0, 0.0));
            let q = integrate_adaptive(
                |s| {
                    let src = m.source(&ray, s, &lights);
                    let tau = m.optical_depth(&ray, s);
                    [src[0] * (-tau[0]).exp(), src[1] * (-tau[1]).exp(), src[2] * (-tau[2]).exp()]
                },
                s0,
                s1.max(s0),
                0.0,
                1e-13,
                4000,
            );
            for c in 0..3 {
                assert!(
                    (r.inscatter[c] - q.value[c]).abs() <= 1e-9 * q.value[c].abs().max(1e-30),
                    "dir {dir}: {} vs {}",
                    r.inscatter[c],
                    q.value[c]
                );
            }
        }
    }
}
