//! Nishita, Miyawaki & Nakamae 1987 §4 media — the wavy dry-ice layer and the
//! smoke ellipsoid — against independent brute force written from the model
//! definitions only:
//!
//! * boundary crossings by dense sampling of `z − h(x, y)` (or of the
//!   ellipsoid's implicit function `|R⁻¹(x − c)/r|² − 1`) and bisection of every
//!   sign change, pieces labelled by the sign at their middle;
//! * optical depths `Σ σ × length` over those pieces;
//! * single scattering by composite Gauss–Legendre per piece, at two
//!   resolutions (their difference bounds the reference's own error).
//!
//! The library's error estimates are checked against the true error.

#![allow(clippy::needless_range_loop)]

mod common;

use common::{GaussLegendre, Phase};
use glam::{DQuat, DVec3};
use std::f64::consts::{PI, TAU};
use tyndall_core::Scene;
use tyndall_core::geometry::camera::CameraRays;
use tyndall_core::medium::ellipsoid::Ellipsoid;
use tyndall_core::medium::height_field_layer::{HeightFieldLayer, Side, Wave};
use tyndall_core::medium::phase::PhaseFunction;
use tyndall_core::medium::{LightSet, PreparedMedium, SunSource, ViewRay};

struct Rng(u64);
impl Rng {
    fn f(&mut self) -> f64 {
        self.0 = self.0.wrapping_mul(6364136223846793005).wrapping_add(1442695040888963407);
        (self.0 >> 11) as f64 / (1u64 << 53) as f64
    }
    fn range(&mut self, a: f64, b: f64) -> f64 {
        a + (b - a) * self.f()
    }
    fn unit(&mut self) -> DVec3 {
        loop {
            let v = DVec3::new(self.range(-1.0, 1.0), self.range(-1.0, 1.0), self.range(-1.0, 1.0));
            let l = v.length();
            if l > 0.1 && l <= 1.0 {
                return v / l;
            }
        }
    }
}

// ------------------------------------------------------------------ reference models

/// Waves as in the scene file: (amplitude m, wavelength m, direction °, phase °).
const WAVES: [(f64, f64, f64, f64); 3] = [(0.12, 2.3, 15.0, 0.0), (0.07, 1.1, 100.0, 40.0), (0.04, 0.55, -50.0, 120.0)];
const BASE: f64 = 0.4;

fn ref_height(x: f64, y: f64) -> f64 {
    let mut h = BASE;
    for (a, l, th, ph) in WAVES {
        let (th, ph) = (th.to_radians(), ph.to_radians());
        h += a * (TAU * (x * th.cos() + y * th.sin()) / l + ph).sin();
    }
    h
}
fn ref_top() -> f64 {
    BASE + WAVES.iter().map(|w| w.0).sum::<f64>()
}

/// Pieces `(t0, t1, inside)` of `[a, b]` where `g(o + t d) < 0`, by sampling at
/// `step` and bisecting each sign change.
fn ref_pieces(g: &dyn Fn(DVec3) -> f64, o: DVec3, d: DVec3, a: f64, b: f64, step: f64) -> Vec<(f64, f64, bool)> {
    let n = (((b - a) / step).ceil() as usize).max(1);
    let at = |t: f64| g(o + d * t);
    let mut cuts = vec![a];
    let mut t_prev = a;
    let mut g_prev = at(a);
    for k in 1..=n {
        let t = a + (b - a) * k as f64 / n as f64;
        let gt = at(t);
        if (gt < 0.0) != (g_prev < 0.0) {
            let (mut lo, mut hi) = (t_prev, t);
            for _ in 0..200 {
                let m = 0.5 * (lo + hi);
                if m <= lo || m >= hi {
                    break;
                }
                if (at(m) < 0.0) == (g_prev < 0.0) {
                    lo = m;
                } else {
                    hi = m;
                }
            }
            cuts.push(0.5 * (lo + hi));
        }
        t_prev = t;
        g_prev = gt;
    }
    cuts.push(b);
    cuts.windows(2)
        .filter(|w| w[1] > w[0])
        .map(|w| (w[0], w[1], at(0.5 * (w[0] + w[1])) < 0.0))
        .collect()
}

fn field_g(p: DVec3) -> f64 {
    p.z - ref_height(p.x, p.y)
}

/// Reference optical depth of `a → b` through the layer: σ_lower below, σ_upper above.
fn ref_field_depth(a: DVec3, b: DVec3, lower: f64, upper: f64, step: f64) -> f64 {
    let v = b - a;
    let len = v.length();
    ref_pieces(&field_g, a, v / len, 0.0, len, step)
        .iter()
        .map(|(t0, t1, below)| (t1 - t0) * if *below { lower } else { upper })
        .sum()
}

fn layer(lower: [f64; 2], upper: [f64; 2], g_lower: f64, g_upper: f64, tol: f64) -> HeightFieldLayer<3> {
    let side = |s: [f64; 2], g: f64| Side {
        scattering: [s[0]; 3],
        extinction: [s[0] + s[1]; 3],
        phase: PhaseFunction::HenyeyGreenstein { g },
    };
    HeightFieldLayer::new(
        "dry ice".into(),
        BASE,
        WAVES.iter().map(|w| Wave::new(w.0, w.1, w.2, w.3)).collect(),
        side(lower, g_lower),
        side(upper, g_upper),
        tol,
    )
}

// ------------------------------------------------------------------ height field: optical depth

#[test]
fn height_field_optical_depths_match_brute_force() {
    let (sl, su) = (0.8, 0.05);
    let m = layer([sl, 0.0], [su, 0.0], 0.0, 0.0, 1e-6);
    let pm = PreparedMedium::HeightFieldLayer(m.clone());
    let mut rng = Rng(7);
    let mut cases: Vec<(DVec3, DVec3, f64)> = Vec::new();
    // Random rays through the slab, a third exactly horizontal.
    for k in 0..60 {
        let o = DVec3::new(rng.range(-5.0, 5.0), rng.range(-5.0, 5.0), rng.range(-0.3, 1.2));
        let mut d = rng.unit();
        if k % 3 == 0 {
            d.z = 0.0;
            d = d.normalize();
        }
        cases.push((o, d, rng.range(0.5, 12.0)));
    }
    // Horizontal rays just under and just over the highest crest on the ray's
    // line, and rays tangent to the surface at a random point.
    for _ in 0..20 {
        let o = DVec3::new(rng.range(-5.0, 5.0), rng.range(-5.0, 5.0), 0.0);
        let d = DVec3::new(rng.range(-1.0, 1.0), rng.range(-1.0, 1.0), 0.0).normalize();
        let len = 10.0;
        let crest = (0..20001)
            .map(|k| o + d * (len * k as f64 / 20000.0))
            .map(|p| ref_height(p.x, p.y))
            .fold(f64::MIN, f64::max);
        // (And 1 µm: a pair of crossings 1 mm apart under it, none over it,
        // where the convex Taylor test decides.)
        for dz in [-1e-3, -1e-6, 1e-6, 1e-3] {
            cases.push((DVec3::new(o.x, o.y, crest + dz), d, len));
        }
        let p = DVec3::new(rng.range(-3.0, 3.0), rng.range(-3.0, 3.0), 0.0);
        let p = DVec3::new(p.x, p.y, ref_height(p.x, p.y));
        let e = 1e-6;
        let grad = DVec3::new(
            (ref_height(p.x + e, p.y) - ref_height(p.x - e, p.y)) / (2.0 * e),
            (ref_height(p.x, p.y + e) - ref_height(p.x, p.y - e)) / (2.0 * e),
            -1.0,
        );
        let t = grad.cross(rng.unit()).normalize();
        cases.push((p - t * 3.0, t, 6.0));
    }
    // Long light paths that stay in the slab for 40–200 m (a low lamp far
    // across the stage): the crossing search's first depths turn the phases
    // from each interval's left end, and at large `t` the rounding of the
    // points they stand for is their slack.
    for k in 0..6 {
        let a = rng.range(0.0, std::f64::consts::TAU);
        let z0 = BASE + rng.range(-0.1, 0.1);
        let len = [40.0, 120.0, 200.0][k % 3];
        let slope = if k % 2 == 0 { 0.001 } else { -0.001 };
        let o = DVec3::new(rng.range(-5.0, 5.0), rng.range(-5.0, 5.0), z0 - slope * 0.5 * len);
        cases.push((o, DVec3::new(a.cos(), a.sin(), slope).normalize(), len));
    }
    let mut worst = 0.0f64;
    for (i, (o, d, len)) in cases.iter().enumerate() {
        let want = ref_field_depth(*o, *o + *d * *len, sl, su, 2e-4);
        let got = pm.optical_depth_between(*o, *o + *d * *len)[0];
        let ray = ViewRay {
            origin: *o,
            dir: *d,
            s_max: *len,
        };
        let via_ray = pm.optical_depth(&ray, *len)[0];
        let half = pm.optical_depth(&ray, 0.5 * len)[0];
        let want_half = ref_field_depth(*o, *o + *d * (0.5 * len), sl, su, 2e-4);
        // Grazing cases (index ≥ 60, before the six long ones): near-double
        // roots are ill-conditioned; allow 1e-6 m.
        let abs = if (60..cases.len() - 6).contains(&i) { 1e-6 * sl } else { 1e-10 };
        for (g, w) in [(got, want), (via_ray, want), (half, want_half)] {
            let err = (g - w).abs();
            worst = worst.max(err / w.max(1e-300));
            assert!(err <= 1e-10 * w + abs, "case {i}: o={o} d={d} len={len}: {g} vs {w} (err {err:e})");
        }
    }
    eprintln!(
        "height field: {} rays, worst relative optical-depth difference {worst:.2e}",
        cases.len()
    );
}

#[test]
fn height_field_clearance_bounds_the_least_height_above_the_boundary() {
    // Segments from points above the boundary (in the slab and above it) to
    // lamps above the crests: the bound is never above the least height found
    // by dense sampling (10⁵ points, with their own error of |f'|·step), and
    // within a factor 2 of it, less the sampling's own slack; a crossing
    // segment has none.
    let m = layer([370.0, 0.0], [0.0, 0.0], 0.0, 0.0, 1e-6);
    let mut rng = Rng(11);
    let (mut clear, mut crossing) = (0, 0);
    for _ in 0..400 {
        let (x, y) = (rng.range(-3.0, 3.0), rng.range(-3.0, 3.0));
        let a = DVec3::new(x, y, ref_height(x, y) + rng.range(1e-4, 0.2));
        let b = DVec3::new(rng.range(-8.0, 8.0), rng.range(-8.0, 8.0), ref_top() + rng.range(0.01, 1.0));
        let n = 100_000;
        let step = (b - a).length() / n as f64;
        let least = (0..=n)
            .map(|k| field_g(a + (b - a) * (k as f64 / n as f64)))
            .fold(f64::INFINITY, f64::min);
        match m.clearance_between(a, b) {
            Some(c) => {
                clear += 1;
                let slack = 2.0 * step; // |f'| ≤ 1 + slope < 2 per unit length here
                assert!(least > -slack, "a clear segment crosses: {least}");
                assert!(c <= least + slack, "bound {c} above the least height {least}");
                // (Wholly above the crests the bound is the height above the crest plane.)
                let expected = if a.z.min(b.z) > ref_top() {
                    a.z.min(b.z) - ref_top()
                } else {
                    0.5 * least
                };
                assert!(c >= expected - slack, "bound {c} far below the least height {least}");
            }
            None => {
                crossing += 1;
                assert!(least < 0.0, "no bound for a clear segment (least height {least})");
            }
        }
    }
    assert!(clear > 50 && crossing > 50, "{clear} clear, {crossing} crossing");
}

#[test]
fn height_field_clearance_rate_keeps_nearby_paths_clear() {
    // Points `x` moving along a line, paths from them to a lamp (low, a few
    // cm over the crests' troughs as a shin-height side light, or above the
    // crests): a path with clearance `c` keeps every path from within
    // `c / rate` of it clear, `rate` taken over the points passed. The first
    // point along the line whose path crosses the boundary (stepped at 5 mm,
    // then bisected, crossings by brute-force sampling at 0.5 mm) is at least
    // that far away.
    let m = layer([370.0, 0.0], [0.0, 0.0], 0.0, 0.0, 1e-6);
    let mut rng = Rng(29);
    let crosses = |x: DVec3, lamp: DVec3| -> bool {
        let v = lamp - x;
        let len = v.length();
        ref_pieces(&field_g, x, v / len, 0.0, len, 5e-4).iter().any(|p| p.2)
    };
    let (mut checked, mut tightest, mut reduced) = (0, 0.0f64, 0);
    for case in 0..240 {
        let (lx, ly) = (rng.range(-2.0, 2.0), rng.range(-2.0, 2.0));
        let lamp = if case % 3 == 2 {
            DVec3::new(lx, ly, ref_top() + rng.range(0.01, 0.5))
        } else {
            DVec3::new(lx, ly, ref_height(lx, ly) + rng.range(0.02, 0.1))
        };
        let along = rng.range(2.0, 4.0);
        let az = rng.range(0.0, TAU);
        let x0 = DVec3::new(lx + along * az.cos(), ly + along * az.sin(), ref_top() + rng.range(-0.15, 0.6));
        let d = rng.unit();
        let Some(c) = m.clearance_between(x0, lamp) else {
            continue;
        };
        if c <= 0.0 || crosses(x0, lamp) {
            continue;
        }
        // The first crossing along the line (within 2 m).
        let mut step = 0.0;
        let found = loop {
            step += 5e-3;
            if step > 2.0 {
                break None;
            }
            if crosses(x0 + d * step, lamp) {
                let (mut lo, mut hi) = (step - 5e-3, step);
                for _ in 0..30 {
                    let mid = 0.5 * (lo + hi);
                    if crosses(x0 + d * mid, lamp) {
                        hi = mid;
                    } else {
                        lo = mid;
                    }
                }
                break Some(lo);
            }
        };
        let Some(first) = found else {
            continue;
        };
        let lowest_z = x0.z.min((x0 + d * first).z);
        let rate = m.clearance_rate(d, lowest_z, lamp);
        if rate < m.clearance_rate(d, f64::NAN, lamp) {
            reduced += 1;
        }
        checked += 1;
        // (The brute force's own sampling: paths up to 5 m at 0.5 mm, a
        // crossing of depth below `slope·step²` can be missed.)
        assert!(
            c <= rate * first * (1.0 + 1e-9) + 1e-6,
            "case {case}: clearance {c} but a crossing {first} m along the line (rate {rate})"
        );
        tightest = tightest.max(c / (rate * first));
    }
    eprintln!("clearance rate: {checked} lines, {reduced} with a reduced rate, tightest c/(rate·distance) {tightest:.3}");
    assert!(checked >= 30 && reduced >= 10, "{checked} checked, {reduced} reduced");
}

// ------------------------------------------------------------------ height field: sun in-scatter

/// Reference sun + ambient single scattering along `[0, s_max]` with `panels`
/// Gauss–Legendre panels per piece (the sun given at the crest plane z_top).
#[allow(clippy::too_many_arguments)]
fn ref_field_inscatter(
    o: DVec3,
    d: DVec3,
    s_max: f64,
    lower: [f64; 2],
    upper: [f64; 2],
    g: [f64; 2],
    to_sun: DVec3,
    e_sun: f64,
    amb: f64,
    panels: usize,
) -> f64 {
    let gl = GaussLegendre::new(8);
    let top = ref_top();
    let mu = d.dot(to_sun);
    let pieces = ref_pieces(&field_g, o, d, 0.0, s_max, 2e-4);
    let mut tau0 = 0.0;
    let mut total = 0.0;
    for (t0, t1, below) in pieces {
        let [ss, sa] = if below { lower } else { upper };
        let st = ss + sa;
        let ph = Phase::Hg(if below { g[0] } else { g[1] }).eval(mu);
        let f = |s: f64| -> [f64; 1] {
            let x = o + d * s;
            let sun_len = if x.z >= top { 0.0 } else { (top - x.z) / to_sun.z };
            let tau_sun = if sun_len > 0.0 {
                ref_pieces(&field_g, x, to_sun, 0.0, sun_len, 2e-3)
                    .iter()
                    .map(|(a, b, bl)| (b - a) * if *bl { lower[0] + lower[1] } else { upper[0] + upper[1] })
                    .sum::<f64>()
            } else {
                0.0
            };
            [ss * (ph * e_sun * (-tau_sun).exp() + amb) * (-(tau0 + st * (s - t0))).exp()]
        };
        for k in 0..panels {
            let a = t0 + (t1 - t0) * k as f64 / panels as f64;
            let b = t0 + (t1 - t0) * (k + 1) as f64 / panels as f64;
            total += gl.integrate(&f, a, b)[0];
        }
        tau0 += st * (t1 - t0);
    }
    total
}

#[test]
fn height_field_sun_inscatter_matches_brute_force_with_honest_estimate() {
    let (lower, upper, g) = ([0.6, 0.02], [0.03, 0.0], [0.2, 0.5]);
    let tol = 1e-6;
    let m = layer(lower, upper, g[0], g[1], tol);
    let to_sun = DVec3::new(0.3, -0.4, 0.8).normalize();
    let (e_sun, amb) = (3.0, 0.1);
    let lights = LightSet {
        suns: vec![SunSource::point(to_sun, [e_sun; 3])],
        ambient: [amb; 3],
    };
    let rays = [
        (DVec3::new(-4.0, -3.0, 0.9), DVec3::new(1.0, 0.8, -0.12), 9.0),
        (DVec3::new(-4.0, 1.0, 0.45), DVec3::new(1.0, 0.1, 0.0), 8.0),
        (DVec3::new(0.0, -5.0, 1.5), DVec3::new(0.1, 1.0, -0.25), 7.0),
        (DVec3::new(2.0, 2.0, 0.2), DVec3::new(-1.0, -0.3, 0.05), 6.0),
    ];
    let mut worst = 0.0f64;
    for (o, d, s_max) in rays {
        let d = d.normalize();
        let ray = ViewRay { origin: o, dir: d, s_max };
        let r = m.closed_form(&ray, &lights);
        let coarse = ref_field_inscatter(o, d, s_max, lower, upper, g, to_sun, e_sun, amb, 24);
        let fine = ref_field_inscatter(o, d, s_max, lower, upper, g, to_sun, e_sun, amb, 48);
        let ref_err = (fine - coarse).abs();
        let err = (r.inscatter[0] - fine).abs();
        worst = worst.max(err / fine);
        eprintln!(
            "height field sun: got {:.12e} ref {fine:.12e} (ref ± {ref_err:.1e}) err {err:.2e} est {:.2e}",
            r.inscatter[0], r.error[0]
        );
        assert!(r.inscatter[0].is_finite() && r.inscatter[0] > 0.0);
        assert!(err <= 1e-5 * fine, "relative error {:.2e}", err / fine);
        assert!(
            err <= r.error[0] + 2.0 * ref_err + 1e-12 * fine,
            "error {err:e} above the estimate {:e}",
            r.error[0]
        );
        // Transmittance against the reference depth.
        let t_ref = (-ref_field_depth(o, o + d * s_max, lower[0] + lower[1], upper[0] + upper[1], 2e-4)).exp();
        assert!((r.transmittance[0] - t_ref).abs() <= 1e-9 * t_ref.max(1e-300));
    }
    eprintln!("height field sun in-scatter: worst relative difference {worst:.2e}");
}

// ------------------------------------------------------------------ ellipsoid

const CENTER: DVec3 = DVec3::new(1.0, -0.5, 1.5);
const RADII: DVec3 = DVec3::new(1.5, 0.6, 0.9);

fn rotation() -> DQuat {
    DQuat::from_axis_angle(DVec3::new(0.3, 0.5, 1.0).normalize(), 0.7)
}
fn ellipsoid_g(p: DVec3) -> f64 {
    let q = rotation().inverse() * (p - CENTER) / RADII;
    q.length_squared() - 1.0
}
fn ellipsoid(ss: f64, st: f64, g: f64, tol: f64) -> Ellipsoid<3> {
    Ellipsoid::new(
        "smoke".into(),
        CENTER,
        RADII,
        rotation(),
        [ss; 3],
        [st; 3],
        PhaseFunction::HenyeyGreenstein { g },
        tol,
    )
}
/// Reference chord length inside the ellipsoid on `[0, len]`.
fn ref_chord(o: DVec3, d: DVec3, len: f64, step: f64) -> f64 {
    ref_pieces(&ellipsoid_g, o, d, 0.0, len, step)
        .iter()
        .filter(|p| p.2)
        .map(|p| p.1 - p.0)
        .sum()
}

#[test]
fn ellipsoid_optical_depths_match_brute_force_including_tangent_rays() {
    let st = 0.7;
    let pm = PreparedMedium::Ellipsoid(ellipsoid(0.5, st, 0.3, 1e-6));
    let mut rng = Rng(11);
    let mut worst = 0.0f64;
    let frame = |q: DVec3| CENTER + rotation() * (q * RADII);
    let frame_dir = |v: DVec3| rotation() * (v * RADII);
    for k in 0..120 {
        let (o, d, len, abs) = if k < 60 {
            // Random rays aimed near the ellipsoid.
            let o = CENTER + rng.unit() * rng.range(0.0, 5.0);
            let target = CENTER + rng.unit() * rng.range(0.0, 1.8);
            let d = (target - o).normalize();
            (o, d, rng.range(0.5, 10.0), 1e-12)
        } else {
            // Tangent (k even) or 1e-6 inside the tangent (k odd) in the unit-sphere frame.
            let q = rng.unit();
            let t = q.cross(rng.unit()).normalize();
            let q = if k % 2 == 0 { q } else { q * (1.0 - 1e-6) };
            let p = frame(q);
            let d = frame_dir(t).normalize();
            (p - d * 4.0, d, 8.0, 1e-7)
        };
        let want = st * ref_chord(o, d, len, 1e-4);
        let got = pm.optical_depth_between(o, o + d * len)[0];
        let ray = ViewRay {
            origin: o,
            dir: d,
            s_max: len,
        };
        let via_ray = pm.optical_depth(&ray, len)[0];
        for g in [got, via_ray] {
            let err = (g - want).abs();
            if want > 1e-6 {
                worst = worst.max(err / want);
            }
            assert!(err <= 1e-10 * want + abs, "ray {k}: o={o} d={d}: {g} vs {want} (err {err:e})");
        }
        // Segment consistent with the depth.
        let seg = pm.segment(&ray);
        assert!(seg.is_some() || got <= st * abs, "ray {k}: segment {seg:?} vs depth {got}");
    }
    eprintln!("ellipsoid: worst relative optical-depth difference {worst:.2e}");
}

#[test]
fn ellipsoid_sun_inscatter_matches_brute_force_with_honest_estimate() {
    let (ss, sa, g) = (0.5, 0.1, 0.4);
    let st = ss + sa;
    let m = ellipsoid(ss, st, g, 1e-7);
    let to_sun = DVec3::new(-0.2, 0.5, 0.7).normalize();
    let (e_sun, amb) = (2.0, 0.05);
    let lights = LightSet {
        suns: vec![SunSource::point(to_sun, [e_sun; 3])],
        ambient: [amb; 3],
    };
    let gl = GaussLegendre::new(10);
    let mut rng = Rng(5);
    let mut worst = 0.0f64;
    for _ in 0..8 {
        let o = CENTER + rng.unit() * 6.0;
        let d = (CENTER + rng.unit() * 0.3 - o).normalize();
        let ray = ViewRay {
            origin: o,
            dir: d,
            s_max: 20.0,
        };
        let r = m.closed_form(&ray, &lights);
        let chord: Vec<(f64, f64)> = ref_pieces(&ellipsoid_g, o, d, 0.0, 20.0, 1e-3)
            .into_iter()
            .filter(|p| p.2)
            .map(|p| (p.0, p.1))
            .collect();
        assert_eq!(chord.len(), 1);
        let (s0, s1) = chord[0];
        let ph = Phase::Hg(g).eval(d.dot(to_sun));
        // Sun path: the implicit function along the sun ray from an inside
        // point changes sign once (convex body); bisection on [0, 2·max radius].
        let f = |s: f64| -> [f64; 1] {
            let x = o + d * s;
            let (mut lo, mut hi) = (0.0, 2.0 * RADII.max_element() + 1e-9);
            for _ in 0..200 {
                let mid = 0.5 * (lo + hi);
                if ellipsoid_g(x + to_sun * mid) < 0.0 {
                    lo = mid;
                } else {
                    hi = mid;
                }
            }
            [ss * (ph * e_sun * (-st * lo).exp() + amb) * (-st * (s - s0)).exp()]
        };
        let run = |panels: usize| -> f64 {
            (0..panels)
                .map(|k| {
                    let a = s0 + (s1 - s0) * k as f64 / panels as f64;
                    let b = s0 + (s1 - s0) * (k + 1) as f64 / panels as f64;
                    gl.integrate(&f, a, b)[0]
                })
                .sum()
        };
        let (coarse, fine) = (run(32), run(64));
        let ref_err = (fine - coarse).abs();
        let err = (r.inscatter[0] - fine).abs();
        worst = worst.max(err / fine);
        assert!(err <= 1e-6 * fine, "relative error {:.2e}", err / fine);
        assert!(
            err <= r.error[0] + 2.0 * ref_err + 1e-12 * fine,
            "error {err:e} above the estimate {:e}",
            r.error[0]
        );
        assert!((r.transmittance[0] - (-st * (s1 - s0)).exp()).abs() <= 1e-9);
    }
    eprintln!("ellipsoid sun in-scatter: worst relative difference {worst:.2e}");
}

// ------------------------------------------------------------------ renderer: spot light in dry ice

#[test]
fn spot_light_in_dry_ice_renders_like_brute_force() {
    let (lower, upper, g) = ([0.6, 0.02], [0.02, 0.0], [0.2, 0.5]);
    let (power, light) = (400.0, DVec3::new(0.3, 0.2, 3.0));
    let tol = 1e-6;
    let wave_json: Vec<String> = WAVES
        .iter()
        .map(|(a, l, th, ph)| format!(r#"{{"amplitude_m": {a}, "wavelength_m": {l}, "direction_deg": {th}, "phase_deg": {ph}}}"#))
        .collect();
    let json = format!(
        r#"{{"version": 1,
        "camera": {{"type": "perspective", "position": [0, -4, 0.8], "orientation": {{"look_at": {{"target": [0, 0, 0.35]}}}}, "resolution": [5, 3], "clip_start_m": 0}},
        "meshes": [{{"positions": [[-50, -50, 0], [50, -50, 0], [50, 50, 0], [-50, 50, 0]], "triangles": [[0, 1, 2], [0, 2, 3]]}}],
        "lights": [{{"type": "spot", "position": [{}, {}, {}], "orientation": {{"look_at": {{"target": [{}, {}, 0], "up": [0, 1, 0]}}}},
                    "power_w": {power}, "spot_size_deg": 180, "spot_blend": 0}}],
        "media": [{{"type": "layered_height_field", "base_height_m": {BASE}, "waves": [{}],
                   "lower": {{"scattering": {}, "absorption": {}, "phase": {{"type": "henyey_greenstein", "g": {}}}}},
                   "upper": {{"scattering": {}, "absorption": {}, "phase": {{"type": "henyey_greenstein", "g": {}}}}}}}],
        "output": {{"tolerance": {tol}, "pixel_filter": {{"type": "none"}}, "layers": ["inscatter", "transmittance", "error"]}}}}"#,
        light.x,
        light.y,
        light.z,
        light.x,
        light.y,
        wave_json.join(", "),
        lower[0],
        lower[1],
        g[0],
        upper[0],
        upper[1],
        g[1]
    );
    let scene = Scene::from_json_str(&json, "dry ice").unwrap_or_else(|e| panic!("{e}"));
    let (img, report) = tyndall_core::render(&scene, None).unwrap_or_else(|e| panic!("{e}"));
    eprintln!(
        "{}",
        report.plan.computed.iter().map(|c| format!("{c:?}")).collect::<Vec<_>>().join("\n")
    );
    let cam = CameraRays::new(&scene.camera);
    let intensity = power / (4.0 * PI);
    let gl = GaussLegendre::new(8);
    let mut worst = 0.0f64;
    for (i, j) in [(0, 1), (2, 1), (4, 2), (1, 2), (3, 1)] {
        let d = cam.direction(i as f64 + 0.5, j as f64 + 0.5);
        let o = cam.position;
        assert!(d.z < 0.0, "pixel ({i}, {j}) does not see the floor");
        let s_max = -o.z / d.z;
        let pieces = ref_pieces(&field_g, o, d, 0.0, s_max, 2e-4);
        let run = |panels: usize| -> f64 {
            let mut tau0 = 0.0;
            let mut total = 0.0;
            for &(t0, t1, below) in &pieces {
                let [ss, sa] = if below { lower } else { upper };
                let gg = if below { g[0] } else { g[1] };
                let f = |s: f64| -> [f64; 1] {
                    let x = o + d * s;
                    let v = x - light;
                    let r = v.length();
                    let w = v / r;
                    let tl = ref_field_depth(x, light, lower[0] + lower[1], upper[0] + upper[1], 2e-3);
                    [ss * Phase::Hg(gg).eval(-d.dot(w)) * intensity / (r * r) * (-(tau0 + (ss + sa) * (s - t0) + tl)).exp()]
                };
                for k in 0..panels {
                    let a = t0 + (t1 - t0) * k as f64 / panels as f64;
                    let b = t0 + (t1 - t0) * (k + 1) as f64 / panels as f64;
                    total += gl.integrate(&f, a, b)[0];
                }
                tau0 += (ss + sa) * (t1 - t0);
            }
            total
        };
        let (coarse, fine) = (run(12), run(24));
        let px = j * img.width + i;
        let got = f64::from(img.inscatter[px][0]);
        let est = f64::from(img.error[px][0]);
        assert!(got.is_finite() && got > 0.0, "pixel ({i}, {j}): {got}");
        let err = (got - fine).abs();
        worst = worst.max(err / fine);
        eprintln!(
            "spot pixel ({i}, {j}): got {got:.9e} ref {fine:.9e} (± {:.1e}) err {err:.1e} est {est:.1e}",
            (fine - coarse).abs()
        );
        // f32 storage: 6e-8 relative.
        assert!(err <= 1e-5 * fine, "pixel ({i}, {j}): relative error {:.2e}", err / fine);
        assert!(
            err <= est + 2.0 * (fine - coarse).abs() + 1.2e-7 * fine,
            "pixel ({i}, {j}): error {err:e} above estimate {est:e}"
        );
    }
    eprintln!("spot in dry ice: worst relative difference {worst:.2e}");
}

// ------------------------------------------------------------------ bad inputs

const CAMERA: &str =
    r#""camera":{"type":"perspective","position":[0,0,1],"orientation":{"look_at":{"target":[0,1,1]}},"resolution":[4,3]}"#;

fn media(m: &str) -> String {
    format!(r#"{{"version":1,{CAMERA},"media":[{m}]}}"#)
}

fn assert_path(json: &str, path: &str) {
    match std::panic::catch_unwind(|| Scene::from_json_str(json, "<test>")) {
        Ok(Ok(_)) => panic!("accepted: {json}"),
        Ok(Err(e)) => {
            assert_eq!(e.path, path, "wrong path; message: {e}");
            assert!(e.to_string().contains(path), "{e}");
        }
        Err(_) => panic!("panicked on: {json}"),
    }
}

const WAVE: &str = r#"{"amplitude_m":0.1,"wavelength_m":2}"#;

fn hf(base: &str, waves: &str, lower: &str, upper: &str) -> String {
    media(&format!(
        r#"{{"type":"layered_height_field","base_height_m":{base},"waves":[{waves}],"lower":{lower}{upper}}}"#
    ))
}

#[test]
fn bad_nishita_media_are_rejected_with_field_paths() {
    let lower = r#"{"scattering":0.5}"#;
    // Valid ones load.
    Scene::from_json_str(&hf("0.3", WAVE, lower, ""), "<ok>").unwrap_or_else(|e| panic!("{e}"));
    Scene::from_json_str(
        &media(r#"{"type":"ellipsoid","center":[0,0,1],"radii":[1,2,3],"rotation_wxyz":[1,0,0,1],"scattering":0.2}"#),
        "<ok>",
    )
    .unwrap_or_else(|e| panic!("{e}"));
    // Height field.
    assert_path(&hf("1e9", WAVE, lower, ""), "media[0].base_height_m");
    assert_path(&hf("0", "", lower, ""), "media[0].waves");
    assert_path(&hf("0", &[WAVE; 9].join(","), lower, ""), "media[0].waves");
    assert_path(
        &hf("0", r#"{"amplitude_m":-1,"wavelength_m":2}"#, lower, ""),
        "media[0].waves[0].amplitude_m",
    );
    assert_path(
        &hf("0", &format!(r#"{WAVE},{{"amplitude_m":0.1,"wavelength_m":0}}"#), lower, ""),
        "media[0].waves[1].wavelength_m",
    );
    assert_path(
        &hf("0", r#"{"amplitude_m":0.1,"wavelength_m":2,"direction_deg":400}"#, lower, ""),
        "media[0].waves[0].direction_deg",
    );
    assert_path(
        &hf("0", r#"{"amplitude_m":0.1,"wavelength_m":2,"phase_deg":-1000}"#, lower, ""),
        "media[0].waves[0].phase_deg",
    );
    assert_path(
        &hf("0", r#"{"amplitude_m":0.1,"wavelength_m":2,"period":3}"#, lower, ""),
        "media[0].waves[0].period",
    );
    assert_path(&hf("0", r#"{"wavelength_m":2}"#, lower, ""), "media[0].waves[0]");
    assert_path(&hf("0", WAVE, r#"{"scattering":-0.5}"#, ""), "media[0].lower.scattering");
    assert_path(
        &hf("0", WAVE, r#"{"scattering":0.5,"absorption":[0,-1,0]}"#, ""),
        "media[0].lower.absorption[1]",
    );
    assert_path(
        &hf("0", WAVE, r#"{"scattering":0.5,"phase":{"type":"henyey_greenstein","g":1.5}}"#, ""),
        "media[0].lower.phase.g",
    );
    assert_path(&hf("0", WAVE, lower, r#","upper":{"scattering":-1}"#), "media[0].upper.scattering");
    assert_path(&hf("0", WAVE, lower, r#","upper":{"absorption":1}"#), "media[0].upper");
    // Ellipsoid.
    let ell = |body: &str| media(&format!(r#"{{"type":"ellipsoid",{body}}}"#));
    assert_path(&ell(r#""center":[0,0,1],"radii":[1,0,1],"scattering":0.2"#), "media[0].radii[1]");
    assert_path(&ell(r#""center":[0,0,1],"radii":[1,1,1e9],"scattering":0.2"#), "media[0].radii[2]");
    assert_path(
        &ell(r#""center":[0,0,1],"radii":[1,1,1],"rotation_wxyz":[0,0,0,0],"scattering":0.2"#),
        "media[0].rotation_wxyz",
    );
    assert_path(&ell(r#""center":[0,0,1],"radii":[1,1,1],"scattering":-0.2"#), "media[0].scattering");
    assert_path(
        &ell(r#""center":[0,0,1],"radii":[1,1,1],"scattering":0.2,"absorption":-1"#),
        "media[0].absorption",
    );
    assert_path(
        &ell(r#""center":[0,0,1],"radii":[1,1,1],"scattering":0.2,"phase":{"type":"henyey_greenstein","g":-2}"#),
        "media[0].phase.g",
    );
    assert_path(&ell(r#""center":[0,0],"radii":[1,1,1],"scattering":0.2"#), "media[0].center");
    assert_path(
        &ell(r#""center":[0,0,1],"radii":[1,1,1],"scattering":0.2,"size":3"#),
        "media[0].size",
    );
}
