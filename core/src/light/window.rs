//! Parallel light through a window (Nishita et al. 1987, Fig. 3).
//!
//! Light travels along `−ℓ` (`ℓ` = unit vector towards the source) and enters
//! the scene only through a planar polygon `W`. A point `x` is in the
//! illumination volume when the ray `x + s·ℓ`, `s > 0`, passes through `W`:
//! the prism `W` sweeps along `−ℓ`. Along a view ray `x(t) = o + t·d` the foot
//! point on the window plane, `P(t) = x(t) + s(t)·ℓ` with
//! `s(t) = (p₀ − x(t))·n / (ℓ·n)`, is affine in `t`, so the prism's intervals
//! are the intersections of a 2-D line with the polygon (even–odd rule, any
//! simple polygon, convex or not), clipped to `s(t) > 0`.
//!
//! In-scatter: `E·p(μ)` per unit volume with `E` the irradiance (W·m⁻²) on a
//! plane facing the light, dimmed by the medium between `x` and the window
//! (nothing is assumed about the medium on the far side).

use glam::{DVec2, DVec3};

/// A window light resolved to `C` channels.
#[derive(Debug, Clone)]
pub struct WindowSource<const C: usize> {
    /// Name for reports and per-light layers.
    pub name: String,
    /// Unit vector towards the light.
    pub to_light: DVec3,
    /// Irradiance on a plane facing the light, W·m⁻² per channel.
    pub irradiance: [f64; C],
    /// A point of the window plane (its first corner).
    pub origin: DVec3,
    /// Unit normal of the window plane.
    pub normal: DVec3,
    u: DVec3,
    v: DVec3,
    polygon: Vec<DVec2>,
    /// Centre and radius of a sphere around the polygon.
    pub bounding: (DVec3, f64),
}

impl<const C: usize> WindowSource<C> {
    /// Builds the window from its corners (validated planar, not edge-on to the light).
    pub fn new(name: &str, to_light: DVec3, irradiance: [f64; C], corners: &[[f64; 3]]) -> Self {
        let pts: Vec<DVec3> = corners.iter().map(|c| DVec3::from(*c)).collect();
        let mut n = DVec3::ZERO;
        for i in 0..pts.len() {
            let (a, b) = (pts[i], pts[(i + 1) % pts.len()]);
            n += DVec3::new((a.y - b.y) * (a.z + b.z), (a.z - b.z) * (a.x + b.x), (a.x - b.x) * (a.y + b.y));
        }
        let normal = n.normalize();
        let u = normal.any_orthonormal_vector();
        let v = normal.cross(u);
        let origin = pts[0];
        let polygon = pts.iter().map(|p| DVec2::new((*p - origin).dot(u), (*p - origin).dot(v))).collect();
        let centre = pts.iter().copied().sum::<DVec3>() / pts.len() as f64;
        let radius = pts.iter().map(|p| (*p - centre).length()).fold(0.0, f64::max);
        WindowSource {
            name: name.to_string(),
            to_light: to_light.normalize(),
            irradiance,
            origin,
            normal,
            u,
            v,
            polygon,
            bounding: (centre, radius),
        }
    }

    /// The window's corners in world space, m. The lit region is the prism
    /// swept from the polygon away from the light, inside the convex hull of
    /// these corners and the direction `−to_light`.
    pub fn corners(&self) -> Vec<DVec3> {
        self.polygon.iter().map(|p| self.origin + self.u * p.x + self.v * p.y).collect()
    }

    /// Distance from `x` to the window plane along `ℓ` (negative: `x` is on the light's side).
    #[inline]
    pub fn distance_to_window(&self, x: DVec3) -> f64 {
        (self.origin - x).dot(self.normal) / self.to_light.dot(self.normal)
    }

    fn inside_polygon(&self, p: DVec2) -> bool {
        let mut inside = false;
        let n = self.polygon.len();
        let mut j = n - 1;
        for i in 0..n {
            let (a, b) = (self.polygon[i], self.polygon[j]);
            if (a.y > p.y) != (b.y > p.y) && p.x < (b.x - a.x) * (p.y - a.y) / (b.y - a.y) + a.x {
                inside = !inside;
            }
            j = i;
        }
        inside
    }

    fn foot(&self, x: DVec3) -> DVec2 {
        let p = x + self.to_light * self.distance_to_window(x) - self.origin;
        DVec2::new(p.dot(self.u), p.dot(self.v))
    }

    /// Whether `x` is in the illumination volume.
    pub fn illuminates(&self, x: DVec3) -> bool {
        self.distance_to_window(x) > 0.0 && self.inside_polygon(self.foot(x))
    }

    /// Whether a sphere could touch the illumination volume (conservative).
    pub fn may_touch_sphere(&self, centre: DVec3, radius: f64) -> bool {
        let s = self.distance_to_window(centre);
        let slack = radius / self.to_light.dot(self.normal).abs().max(1e-12);
        if s + slack < 0.0 {
            return false;
        }
        let f = centre + self.to_light * s;
        // Distance from the prism's axis, measured ⊥ ℓ.
        let off = f - self.bounding.0;
        let perp = off - self.to_light * off.dot(self.to_light);
        perp.length() <= self.bounding.1 / self.to_light.dot(self.normal).abs().max(1e-12) + radius + slack
    }

    /// Intervals of `[lo, hi]` where `o + t·d` is in the illumination volume.
    pub fn intervals(&self, o: DVec3, d: DVec3, lo: f64, hi: f64, out: &mut Vec<(f64, f64)>) {
        out.clear();
        if hi <= lo {
            return;
        }
        // s(t) = s0 + t·s1 > 0.
        let ln = self.to_light.dot(self.normal);
        let s0 = (self.origin - o).dot(self.normal) / ln;
        let s1 = -d.dot(self.normal) / ln;
        let (mut a, mut b) = (lo, hi);
        if s1 == 0.0 {
            if s0 <= 0.0 {
                return;
            }
        } else {
            let tz = -s0 / s1;
            if s1 > 0.0 {
                a = a.max(tz);
            } else {
                b = b.min(tz);
            }
        }
        if b <= a {
            return;
        }
        // Foot point P(t) = f0 + t·f1 in window coordinates.
        let f0 = self.foot(o);
        let f1 = {
            let q = d + self.to_light * s1;
            DVec2::new(q.dot(self.u), q.dot(self.v))
        };
        let mut cuts = vec![a, b];
        let n = self.polygon.len();
        for i in 0..n {
            let (p, q) = (self.polygon[i], self.polygon[(i + 1) % n]);
            let e = q - p;
            let den = f1.perp_dot(e);
            if den == 0.0 {
                continue;
            }
            let t = (p - f0).perp_dot(e) / den;
            let s = (p - f0).perp_dot(f1) / den;
            if (-1e-12..=1.0 + 1e-12).contains(&s) && t > a && t < b {
                cuts.push(t);
            }
        }
        cuts.sort_by(f64::total_cmp);
        cuts.dedup();
        for w in cuts.windows(2) {
            let (x, y) = (w[0], w[1]);
            if y <= x {
                continue;
            }
            let mid = if y.is_finite() { 0.5 * (x + y) } else { x + 1.0 + x.abs() };
            let inside = if f1 == DVec2::ZERO && !y.is_finite() {
                self.inside_polygon(f0)
            } else {
                self.inside_polygon(f0 + f1 * mid)
            };
            if inside {
                match out.last_mut() {
                    Some(last) if last.1 >= x => last.1 = y,
                    _ => out.push((x, y)),
                }
            }
        }
    }
}

#[cfg(test)]
mod tests {
    use super::*;

    #[test]
    fn prism_intervals_match_pointwise_test() {
        // An L-shaped (concave) window in the plane x = 0, light from +x and above.
        let corners = [
            [0.0, 0.0, 0.0],
            [0.0, 2.0, 0.0],
            [0.0, 2.0, 1.0],
            [0.0, 1.0, 1.0],
            [0.0, 1.0, 2.0],
            [0.0, 0.0, 2.0],
        ];
        let w = WindowSource::<3>::new("w", DVec3::new(1.0, 0.2, 0.6), [1.0; 3], &corners);
        let mut out = Vec::new();
        let mut rng = 7u64;
        let mut next = || {
            rng = rng.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
            ((rng >> 11) as f64) / ((1u64 << 53) as f64) * 2.0 - 1.0
        };
        let mut hits = 0;
        for _ in 0..500 {
            let o = DVec3::new(-3.0 + next(), next() * 2.0 + 1.0, next() * 2.0);
            let d = DVec3::new(next(), next(), next()).normalize();
            w.intervals(o, d, 0.0, 8.0, &mut out);
            hits += out.len();
            for k in 0..200 {
                let t = 8.0 * (k as f64 + 0.5) / 200.0;
                let inside = w.illuminates(o + d * t);
                let listed = out.iter().any(|(a, b)| t >= *a && t <= *b);
                let near = out.iter().any(|(a, b)| (t - a).abs() < 1e-9 || (t - b).abs() < 1e-9);
                assert!(near || inside == listed, "t={t} {inside} {listed} {out:?}");
            }
        }
        assert!(hits > 50);
    }
}
