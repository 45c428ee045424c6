//! A smoke ellipsoid (Nishita, Miyawaki & Nakamae 1987 §4, Fig. 7d): constant
//! scattering σ_s and extinction σ_t inside the ellipsoid
//! `|M (x − c)| ≤ 1`, `M = diag(1/a, 1/b, 1/c)·Rᵀ` (`R` the rotation, `a, b, c`
//! the semi-axes), vacuum outside.
//!
//! **Chord.** A ray `x(t) = o + t·d` maps to the unit-sphere frame as
//! `q(t) = o' + t·d'`, `o' = M(o − c)`, `d' = M d` (not unit; `t` stays the
//! world distance). `|q(t)|² = 1` is the quadratic `A t² + 2B t + C = 0`,
//! `A = d'·d'`, `B = o'·d'`, `C = (|o'| − 1)(|o'| + 1)`. Its discriminant is
//! formed from the closest point `p = o' − (B/A) d'` as `A·(1 − |p|²)`, which
//! does not cancel for rays far from the ellipsoid (Haines et al., *Ray
//! Tracing Gems* ch. 7), and the roots as `t₁ = Q/A`, `t₂ = C/Q`,
//! `Q = −(B + sign(B)·√(A(1 − |p|²)))`, so neither is a difference of
//! nearly equal numbers. A tangent ray has a zero-length chord.
//!
//! **Optical depth** of any segment: `σ_t` × the length of its overlap with
//! the chord — closed form.
//!
//! **Single scattering** along the chord `[s₀, s₁]` (clipped to the ray),
//! `ℓ = s₁ − s₀`:
//!
//! * ambient: `σ_s L_amb (1 − e^{−σ_t ℓ})/σ_t` — closed form;
//! * sun: `σ_s p(μ) E ∫_{s₀}^{s₁} e^{−σ_t (s − s₀) − σ_t d(s)} ds` with `d(s)`
//!   the length of the sun ray from `x(s)` to the surface. In the unit-sphere
//!   frame `d(s) = (−β(s) + √(β(s)² − α γ(s)))/α` with `α = |M ω|²`,
//!   `β = q(s)·Mω`, `γ = |q(s)|² − 1`: a linear term plus the square root of
//!   a quadratic in `s`, so the integrand is `e^{linear − σ_t √quadratic/α}`,
//!   which has no elementary antiderivative. **It is integrated numerically**
//!   by adaptive Gauss–Kronrod G7–K15 ([`crate::numeric::integrate_adaptive`])
//!   to the scene tolerance; the |K15 − G7| estimate is returned in
//!   [`RayResult::error`] (plus the rounding bound of the closed parts) and
//!   `rel_bound` is that error relative to the result. The integrand is smooth
//!   inside the chord (the square root vanishes only on the terminator, at an
//!   end of the chord).
//!
//! The sun is attenuated only inside the ellipsoid (vacuum around it).

use super::phase::PhaseFunction;
use super::{LightSet, RayResult, ViewRay, rounding_bound};
use crate::numeric::{integrate_adaptive, one_minus_exp_neg};
use glam::{DMat3, DQuat, DVec3};

/// A constant-density ellipsoid with coefficients resolved to `C` channels.
#[derive(Debug, Clone)]
pub struct Ellipsoid<const C: usize> {
    /// Name for reports.
    pub name: String,
    /// Centre, m.
    pub center: DVec3,
    /// World → unit-sphere frame: `diag(1/radii)·Rᵀ`.
    pub world_to_unit: DMat3,
    /// Scattering coefficient σ_s inside, m⁻¹.
    pub scattering: [f64; C],
    /// Extinction coefficient σ_t = σ_s + σ_a inside, m⁻¹.
    pub extinction: [f64; C],
    /// Phase function.
    pub phase: PhaseFunction,
    /// Relative tolerance of the numerical sun integral.
    pub tolerance: f64,
}

impl<const C: usize> Ellipsoid<C> {
    /// An ellipsoid with semi-axes `radii` along the axes of `rotation` (local → world).
    #[allow(clippy::too_many_arguments)]
    pub fn new(
        name: String,
        center: DVec3,
        radii: DVec3,
        rotation: DQuat,
        scattering: [f64; C],
        extinction: [f64; C],
        phase: PhaseFunction,
        tolerance: f64,
    ) -> Self {
        let r = DMat3::from_quat(rotation.normalize());
        let world_to_unit = DMat3::from_diagonal(radii.recip()) * r.transpose();
        Ellipsoid {
            name,
            center,
            world_to_unit,
            scattering,
            extinction,
            phase,
            tolerance,
        }
    }

    /// Whether `p` is inside (or on) the ellipsoid.
    pub fn contains(&self, p: DVec3) -> bool {
        (self.world_to_unit * (p - self.center)).length_squared() <= 1.0
    }

    /// Where, on the ray `o + t·d` (`t > 0`), the chord of the ellipsoid cut
    /// by the line from `x(t)` towards the light is tangent to it: the light
    /// path's length inside has a square-root kink there. `light` is a point
    /// light's position, or with `parallel` the unit direction towards a
    /// parallel light. In the unit-sphere frame (an affine map: lines, planes
    /// and tangency are kept, and `t` is the same) the plane of the ray and
    /// the light cuts the sphere in a circle; the ray meets the circle's two
    /// tangents from the light (or along its direction) at one `t` each.
    /// Nothing is pushed when the plane misses the sphere or is undefined
    /// (a ray through the light or along its direction), or a point light
    /// is inside the circle (then no line through it is tangent).
    pub fn light_path_kinks(&self, o: DVec3, d: DVec3, light: DVec3, parallel: bool, out: &mut Vec<f64>) {
        let m = self.world_to_unit;
        let (oq, dq) = (m * (o - self.center), m * d);
        // The light's direction from the ray's origin (point) or its direction (parallel).
        let (lq, towards) = if parallel {
            (DVec3::ZERO, m * light)
        } else {
            let lq = m * (light - self.center);
            (lq, lq - oq)
        };
        let n = dq.cross(towards);
        let n_len = n.length();
        let has_plane = n_len > 1e-12 * dq.length() * towards.length();
        if !has_plane {
            return;
        }
        let nh = n / n_len;
        // The circle: centre p0 (the sphere's centre projected on the plane), radius ρ.
        let p0 = nh * nh.dot(oq);
        let rho2 = 1.0 - p0.length_squared();
        if rho2 <= 0.0 {
            return;
        }
        let rho = rho2.sqrt();
        // Tangent points, and each tangent's direction.
        let tangents: [(DVec3, DVec3); 2] = if parallel {
            let w = towards.normalize();
            let side = nh.cross(w);
            [(p0 + side * rho, w), (p0 - side * rho, w)]
        } else {
            let to_l = lq - p0;
            let dist = to_l.length();
            if dist <= rho {
                return;
            }
            let u = to_l / dist;
            let v = nh.cross(u);
            let (cos_phi, sin_phi) = (rho / dist, (1.0 - (rho / dist).powi(2)).max(0.0).sqrt());
            let t1 = p0 + (u * cos_phi + v * sin_phi) * rho;
            let t2 = p0 + (u * cos_phi - v * sin_phi) * rho;
            [(t1, t1 - lq), (t2, t2 - lq)]
        };
        for (point, w) in tangents {
            // oq + t·dq = point + λ·w: crossed with w and dotted with n.
            let den = dq.cross(w).dot(n);
            if den != 0.0 {
                let t = (point - oq).cross(w).dot(n) / den;
                if t.is_finite() && t > 0.0 {
                    out.push(t);
                }
            }
        }
    }

    /// Parameters `t₀ ≤ t₁` where the line `o + t·d` is inside, if it meets the ellipsoid.
    pub fn chord(&self, o: DVec3, d: DVec3) -> Option<(f64, f64)> {
        let oq = self.world_to_unit * (o - self.center);
        let dq = self.world_to_unit * d;
        let a = dq.length_squared();
        if a.is_nan() || a <= 0.0 {
            return None;
        }
        let b = oq.dot(dq);
        let closest = oq - dq * (b / a);
        let disc = 1.0 - closest.length_squared();
        if disc.is_nan() || disc < 0.0 {
            return None;
        }
        let sq = (a * disc).sqrt();
        let q = -(b + if b >= 0.0 { sq } else { -sq });
        if q == 0.0 {
            return Some((0.0, 0.0));
        }
        let l = oq.length();
        let c = (l - 1.0) * (l + 1.0);
        let (t1, t2) = (q / a, c / q);
        Some((t1.min(t2), t1.max(t2)))
    }

    /// Part of `[lo, hi]` inside the ellipsoid along `o + t·d`.
    fn clipped(&self, o: DVec3, d: DVec3, lo: f64, hi: f64) -> Option<(f64, f64)> {
        let (a, b) = self.chord(o, d)?;
        let (s0, s1) = (a.max(lo), b.min(hi));
        if s1 > s0 { Some((s0, s1)) } else { None }
    }

    /// Part of `[0, s_max]` inside the ellipsoid.
    pub fn segment(&self, ray: &ViewRay) -> Option<(f64, f64)> {
        self.clipped(ray.origin, ray.dir, 0.0, ray.s_max)
    }

    fn depth(&self, len: f64) -> [f64; C] {
        self.extinction.map(|k| if k == 0.0 || len == 0.0 { 0.0 } else { k * len })
    }

    /// Optical depth from the origin to `s` (closed form).
    pub fn optical_depth(&self, ray: &ViewRay, s: f64) -> [f64; C] {
        let len = self.clipped(ray.origin, ray.dir, 0.0, s).map_or(0.0, |(a, b)| b - a);
        self.depth(len)
    }

    /// Optical depth of the straight segment `a → b` (closed form).
    pub fn optical_depth_between(&self, a: DVec3, b: DVec3) -> [f64; C] {
        let v = b - a;
        let len = v.length();
        if len.is_nan() || len <= 0.0 {
            return [0.0; C];
        }
        let l = self.clipped(a, v / len, 0.0, len).map_or(0.0, |(x, y)| y - x);
        self.depth(l)
    }

    /// Length of the sun ray from `p` inside the ellipsoid.
    pub fn sun_path(&self, p: DVec3, to_sun: DVec3) -> f64 {
        self.clipped(p, to_sun, 0.0, f64::INFINITY).map_or(0.0, |(a, b)| b - a)
    }

    /// Sun transmittance at `p`.
    pub fn sun_transmittance_at(&self, p: DVec3, to_sun: DVec3) -> [f64; C] {
        let d = self.sun_path(p, to_sun);
        self.extinction.map(|k| if k == 0.0 || d == 0.0 { 1.0 } else { (-k * d).exp() })
    }

    /// `σ_s·p(μ)` at `p` (zero outside).
    pub fn scattering_phase_at(&self, p: DVec3, mu: f64) -> [f64; C] {
        if !self.contains(p) {
            return [0.0; C];
        }
        let ph = self.phase.eval(mu);
        self.scattering.map(|s| s * ph)
    }

    /// Source σ_s J at distance `s` (zero outside).
    pub fn source(&self, ray: &ViewRay, s: f64, lights: &LightSet<C>) -> [f64; C] {
        let p = ray.origin + ray.dir * s;
        if !self.contains(p) {
            return [0.0; C];
        }
        super::scattering_source(&self.scattering, &self.phase, ray.dir, lights, |sun| {
            Some(self.sun_transmittance_at(p, sun.to_sun))
        })
    }

    /// Single scattering of this ellipsoid alone on the ray: ambient in closed
    /// form, sun by adaptive Gauss–Kronrod with its error estimate.
    pub fn closed_form(&self, ray: &ViewRay, lights: &LightSet<C>) -> RayResult<C> {
        let mut r = RayResult::vacuum();
        if let (Some(sun), true) = (lights.suns.first(), ray.s_max.is_finite()) {
            r.sun_transmittance = self.sun_transmittance_at(ray.origin + ray.dir * ray.s_max, sun.to_sun);
        }
        let Some((s0, s1)) = self.segment(ray) else { return r };
        let len = s1 - s0;
        for c in 0..C {
            let k = self.extinction[c];
            if k == 0.0 {
                continue;
            }
            r.transmittance[c] = (-k * len).exp();
            r.inscatter[c] = self.scattering[c] * lights.ambient[c] / k * one_minus_exp_neg(k * len);
            r.error[c] = rounding_bound(r.inscatter[c], 16.0);
        }
        if self.scattering.iter().any(|s| *s > 0.0) {
            for sun in &lights.suns {
                let ph = sun.phase(&self.phase, ray.dir);
                let q = integrate_adaptive(
                    |s| {
                        let d = self.sun_path(ray.origin + ray.dir * s, sun.to_sun);
                        let u = s - s0;
                        self.extinction.map(|k| (-k * (u + d)).exp())
                    },
                    s0,
                    s1,
                    1e-300,
                    self.tolerance,
                    400,
                );
                for c in 0..C {
                    let w = self.scattering[c] * ph * sun.irradiance[c];
                    if w != 0.0 {
                        r.inscatter[c] += w * q.value[c];
                        r.error[c] += w * q.error[c] + rounding_bound(w * q.value[c], 16.0);
                    }
                }
            }
        }
        r.rel_bound = (0..C)
            .filter(|c| r.inscatter[*c] > 0.0)
            .map(|c| r.error[c] / r.inscatter[c])
            .fold(0.0, f64::max);
        r
    }
}
