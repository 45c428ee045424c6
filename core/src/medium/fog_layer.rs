//! Klassen's sunlit fog layer on a flat earth (seed `000_87d1a840bb4d6b9f.txt`,
//! chapter "Fog", eqs 3.1–3.23).
//!
//! Uniform fog between the ground `z_g` and the top `z_t`; the sun at
//! elevation φ (`sin φ = to_sun.z`) with irradiance `E` at the fog top (Klassen's
//! `I_t`, eq 3.21: the light reaching the edge of the fog, computed once).
//! Inside the layer the extinction is `B = β_ex,m + β_ex,p` (eq 3.17) and the
//! droplets scatter `σ_s = albedo·β_ex,p` with phase `p`.
//!
//! **Fog component.** Eq 1.11 along the part `[s₀, s₁]` of the view ray inside
//! the layer, `ℓ = s₁ − s₀`, the sun path through the fog to a point at height
//! z being `d₂(z)`:
//!
//! * `per_point` (default, exact for the flat earth): `d₂(z) = (z_t − z)/sin φ`.
//!   With `z(s₀ + u) = z(s₀) + ω_z u` the exponent is linear in u:
//!   `L = σ_s p(μ) E e^{−B d₂(z(s₀))} ∫₀^ℓ e^{−k u} du`, `k = B(1 − ω_z/sin φ)`,
//!   evaluated as `(1 − e^{−kℓ})/k` with `expm1` (and the larger end factored
//!   out when `k < 0`, looking up more steeply than the sun).
//! * `full_layer` (Klassen's eqs 3.11, 3.20): `d₂ = (z_t − z_g)/sin φ` for every
//!   point, `L = σ_s p E e^{−B d₂} (1 − e^{−Bℓ})/B`. Klassen's `h csc θ` is our
//!   ℓ, the distance to the surface inside the fog.
//!
//! plus the ambient light's in-scatter `σ_s L_amb (1 − e^{−Bℓ})/B`.
//!
//! **Object component** (3.13/3.22/3.23): `e^{−Bℓ}` is the view transmittance
//! (`transmittance` layer); the sun reaching a surface point is attenuated by
//! `e^{−B d₂(z)}` (`sun_transmittance` layer), so a surface render composes as
//! `(ambient + sunlit·T_sun)·T + L`.
//!
//! **Eye above the fog** (Klassen p. 37): the ray is clipped to the layer, as if
//! the eye were at the entry point; nothing scatters above it.
//!
//! **Sun near the horizon** (Klassen §3, "When the sun is at the horizon"):
//! below `min_sun_elevation_deg` (default 15°, where the flat earth stays within
//! 1 % for fog) no direct sunlight is taken to reach the fog or objects; the fog
//! component is the constant fog colour of the ambient light alone. The report
//! says when this applies. At `sin φ ≤ 0` the direct term is always zero
//! (never `0/0`).

use super::phase::PhaseFunction;
use super::{LightSet, RayResult, ViewRay, rounding_bound, rounding_rel};
use crate::numeric::{integral_exp_neg, one_minus_exp_neg};
use crate::scene::SunPath;
use glam::DVec3;

/// Fog layer with coefficients resolved to `C` channels.
#[derive(Debug, Clone)]
pub struct FogLayer<const C: usize> {
    /// Name for reports.
    pub name: String,
    /// Ground (bottom of the fog), m.
    pub ground: f64,
    /// Fog top, m.
    pub top: f64,
    /// Total extinction B inside the layer, m⁻¹.
    pub extinction: [f64; C],
    /// Droplet scattering σ_s, m⁻¹.
    pub scattering: [f64; C],
    /// Droplet phase function.
    pub phase: PhaseFunction,
    /// Sun path model.
    pub sun_path: SunPath,
    /// sin of the minimum sun elevation for the direct term.
    pub min_sin_elevation: f64,
}

impl<const C: usize> FogLayer<C> {
    /// Whether a sun with this direction lights the layer directly.
    pub fn sun_is_direct(&self, to_sun: DVec3) -> bool {
        to_sun.z > 0.0 && to_sun.z >= self.min_sin_elevation
    }

    /// Part of `[0, s_max]` inside the slab `z_g ≤ z ≤ z_t`.
    pub fn segment(&self, ray: &ViewRay) -> Option<(f64, f64)> {
        let (oz, wz) = (ray.origin.z, ray.dir.z);
        let (a, b) = if wz == 0.0 {
            if oz < self.ground || oz > self.top {
                return None;
            }
            (f64::NEG_INFINITY, f64::INFINITY)
        } else {
            let t0 = (self.ground - oz) / wz;
            let t1 = (self.top - oz) / wz;
            (t0.min(t1), t0.max(t1))
        };
        let s0 = a.max(0.0);
        let s1 = b.min(ray.s_max);
        if s1 > s0 { Some((s0, s1)) } else { None }
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

    /// Sun path length inside the fog to height z (model-dependent).
    fn sun_path_to(&self, z: f64, sin_phi: f64) -> f64 {
        let depth = match self.sun_path {
            SunPath::PerPoint => (self.top - z.clamp(self.ground, self.top)).max(0.0),
            SunPath::FullLayer => self.top - self.ground,
        };
        if depth == 0.0 { 0.0 } else { depth / sin_phi }
    }

    /// Sun transmittance at `p`: 0 for a sun that does not light the layer directly.
    pub fn sun_transmittance_at(&self, p: DVec3, to_sun: DVec3) -> [f64; C] {
        if p.z >= self.top && to_sun.z > 0.0 {
            return [1.0; C];
        }
        if !self.sun_is_direct(to_sun) {
            return [0.0; C];
        }
        let d = self.sun_path_to(p.z, to_sun.z);
        self.extinction.map(|k| if k == 0.0 { 1.0 } else { (-k * d).exp() })
    }

    /// Source σ_s J at distance `s`.
    pub fn source(&self, ray: &ViewRay, s: f64, lights: &LightSet<C>) -> [f64; C] {
        let p = ray.origin + ray.dir * s;
        if p.z < self.ground || p.z > self.top {
            return [0.0; C];
        }
        super::scattering_source(&self.scattering, &self.phase, ray.dir, lights, |sun| {
            self.sun_is_direct(sun.to_sun).then(|| self.sun_transmittance_at(p, sun.to_sun))
        })
    }

    /// Closed-form fog and object components on the ray.
    pub fn closed_form(&self, ray: &ViewRay, lights: &LightSet<C>) -> RayResult<C> {
        let mut r = RayResult::vacuum();
        if let (Some(sun), true) = (lights.suns.first(), ray.s_max.is_finite()) {
            r.sun_transmittance = self.sun_transmittance_at(ray.origin + ray.dir * ray.s_max, sun.to_sun);
        }
        let Some((s0, s1)) = self.segment(ray) else { return r };
        let len = s1 - s0;
        let z0 = ray.origin.z + ray.dir.z * s0;
        for c in 0..C {
            let b = self.extinction[c];
            if b == 0.0 {
                continue;
            }
            r.transmittance[c] = (-b * len).exp();
            r.inscatter[c] = self.scattering[c] * lights.ambient[c] / b * one_minus_exp_neg(b * len);
        }
        for sun in &lights.suns {
            if !self.sun_is_direct(sun.to_sun) {
                continue;
            }
            let sin_phi = sun.to_sun.z;
            let ph = sun.phase(&self.phase, ray.dir);
            for c in 0..C {
                let b = self.extinction[c];
                if b == 0.0 || self.scattering[c] == 0.0 {
                    continue;
                }
                let integral = match self.sun_path {
                    SunPath::FullLayer => (-b * self.sun_path_to(z0, sin_phi)).exp() * integral_exp_neg(b, len),
                    SunPath::PerPoint => {
                        let e0 = b * self.sun_path_to(z0, sin_phi);
                        let k = b * (1.0 - ray.dir.z / sin_phi);
                        if k >= 0.0 {
                            (-e0).exp() * integral_exp_neg(k, len)
                        } else {
                            // Looking up more steeply than the sun: the exponent
                            // falls along the ray; factor out its value at the far end.
                            let e1 = (e0 + k * len).max(0.0);
                            (-e1).exp() * integral_exp_neg(-k, len)
                        }
                    }
                };
                r.inscatter[c] += self.scattering[c] * ph * sun.irradiance[c] * integral;
            }
        }
        for c in 0..C {
            r.error[c] = rounding_bound(r.inscatter[c], 64.0);
        }
        r.rel_bound = rounding_rel(64.0);
        r
    }
}
