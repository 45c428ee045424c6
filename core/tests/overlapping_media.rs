//! Several media on one ray: the renderer's numerical path (adaptive
//! Gauss–Kronrod over closed-form optical depths, each medium's sunlight
//! dimmed by the others) against the independent brute-force integration of
//! the volume rendering equation in `common`, and its error estimate against
//! the true error.

#![allow(clippy::needless_range_loop)]

mod common;

use common::{RayModel, Tail, integrate_vre, sv};
use glam::DVec3;
use std::f64::consts::PI;
use tyndall_core::Scene;
use tyndall_core::geometry::camera::CameraRays;

fn hg(g: f64, mu: f64) -> f64 {
    (1.0 - g * g) / (4.0 * PI * (1.0 + g * g - 2.0 * g * mu).powf(1.5))
}
fn rayleigh(mu: f64) -> f64 {
    3.0 / (16.0 * PI) * (1.0 + mu * mu)
}

#[test]
fn height_fog_overlapping_a_haze_box_matches_brute_force() {
    // World height fog (H = 40 m) and a haze box around the stage; the sun straight
    // up (a point sun), so the sun's path inside the box is z_max − z.
    let (h, beta_r, beta_m, g_m) = (40.0, [2e-3, 4e-3, 8e-3], 1.5e-2, 0.6);
    let (box_min, box_max) = (DVec3::new(-4.0, 3.0, 0.0), DVec3::new(4.0, 12.0, 6.0));
    let (box_s, box_t, g_box) = ([0.05, 0.06, 0.07], [0.07, 0.08, 0.09], 0.3);
    let (sun_e, amb) = ([3.0, 2.5, 2.0], [0.02, 0.03, 0.05]);
    let wall_y = 20.0;
    let tol = 1e-7;
    let json = format!(
        r#"{{"version": 1,
        "camera": {{"type": "perspective", "position": [0, -6, 2.5], "orientation": {{"look_at": {{"target": [0, 10, 3]}}}}, "resolution": [9, 7]}},
        "meshes": [{{"positions": [[-100, {wall_y}, -100], [100, {wall_y}, -100], [100, {wall_y}, 100], [-100, {wall_y}, 100]], "triangles": [[0, 1, 2], [0, 2, 3]]}}],
        "lights": [{{"type": "sun", "direction_to_sun": [0, 0, 1], "color": [{}, {}, {}], "strength_w_m2": 1, "angular_diameter_deg": 0}},
                   {{"type": "ambient", "color": [{}, {}, {}], "radiance": 1}}],
        "media": [{{"type": "height_fog", "scale_height_m": {h}, "rayleigh": {{"scattering": [{}, {}, {}]}}, "mie": {{"scattering": {beta_m}, "phase": {{"type": "henyey_greenstein", "g": {g_m}}}}}}},
                  {{"type": "homogeneous", "scattering": [{}, {}, {}], "absorption": [{}, {}, {}], "phase": {{"type": "henyey_greenstein", "g": {g_box}}},
                    "bounds": {{"box": {{"min": [{}, {}, {}], "max": [{}, {}, {}]}}}}}}],
        "output": {{"tolerance": {tol}, "pixel_filter": {{"type": "none"}}, "layers": ["inscatter", "transmittance", "error"]}}}}"#,
        sun_e[0],
        sun_e[1],
        sun_e[2],
        amb[0],
        amb[1],
        amb[2],
        beta_r[0],
        beta_r[1],
        beta_r[2],
        box_s[0],
        box_s[1],
        box_s[2],
        box_t[0] - box_s[0],
        box_t[1] - box_s[1],
        box_t[2] - box_s[2],
        box_min.x,
        box_min.y,
        box_min.z,
        box_max.x,
        box_max.y,
        box_max.z
    );
    let scene = Scene::from_json_str(&json, "overlap").unwrap_or_else(|e| panic!("{e}"));
    let (img, report) = tyndall_core::render(&scene, None).unwrap_or_else(|e| panic!("{e}"));
    assert!(report.error.pixels_numeric > 0, "no pixel took the numerical path");
    let cam = CameraRays::new(&scene.camera);
    let sun = DVec3::Z;
    let mut worst = 0.0f64;
    let mut worst_ratio = 0.0f64;
    for j in 0..img.height {
        for i in 0..img.width {
            let d = cam.direction(i as f64 + 0.5, j as f64 + 0.5);
            let o = cam.position;
            let s_end = (wall_y - o.y) / d.y;
            let mu = d.dot(sun);
            let inside = |p: DVec3| p.cmpge(box_min).all() && p.cmple(box_max).all();
            let rho = |p: DVec3| (-p.z / h).exp();
            let mu_t = |s: common::S| {
                let p = o + d * sv(s);
                let r = rho(p);
                let b = inside(p);
                std::array::from_fn(|c| (beta_r[c] + beta_m) * r + if b { box_t[c] } else { 0.0 })
            };
            let source = |s: common::S| {
                let p = o + d * sv(s);
                let r = rho(p);
                // Sunlight straight down: dimmed by the box's haze over the part of the
                // vertical above p that lies in the box (also below the box, in its
                // shadow); the fog does not dim the sun in its own model.
                let in_footprint = p.x >= box_min.x && p.x <= box_max.x && p.y >= box_min.y && p.y <= box_max.y;
                let path = if in_footprint {
                    (box_max.z - p.z.max(box_min.z)).max(0.0)
                } else {
                    0.0
                };
                let t_box: [f64; 3] = std::array::from_fn(|c| (-box_t[c] * path).exp());
                std::array::from_fn(|c| {
                    let fog = r
                        * (beta_r[c] * (rayleigh(mu) * sun_e[c] * t_box[c] + amb[c])
                            + beta_m * (hg(g_m, mu) * sun_e[c] * t_box[c] + amb[c]));
                    let hz = if inside(p) {
                        box_s[c] * (hg(g_box, mu) * sun_e[c] * t_box[c] + amb[c])
                    } else {
                        0.0
                    };
                    fog + hz
                })
            };
            // Kinks: the box's faces along the view ray (entry, exit, and the edges
            // of its shadow footprint below it).
            let mut breaks = Vec::new();
            for k in 0..3 {
                if d[k] != 0.0 {
                    for b in [box_min[k], box_max[k]] {
                        breaks.push((b - o[k]) / d[k]);
                    }
                }
            }
            let step = |_s: common::S| 0.25;
            let tail = |_s: common::S, _t: &[f64; 3]| Tail::Continue;
            let brute = integrate_vre(&RayModel {
                mu_t: &mu_t,
                source: &source,
                max_step: &step,
                breaks,
                s_end,
                tail: &tail,
                ratio: [1e9; 3],
                tau_step: &step,
            });
            let px = j * img.width + i;
            for c in 0..3 {
                let got = f64::from(img.inscatter[px][c]);
                let rel = (got - brute.l[c]).abs() / brute.l[c];
                worst = worst.max(rel);
                // Error estimate (f64, before f32 storage) against the true error.
                let est = f64::from(img.error[px][c]) + 6e-8 * brute.l[c];
                worst_ratio = worst_ratio.max((got - brute.l[c]).abs() / est);
                let t = f64::from(img.transmittance[px][c]);
                assert!(
                    (t - brute.t()[c]).abs() <= 1e-6 * brute.t()[c] + 1e-30,
                    "T at ({i}, {j}): {t} vs {}",
                    brute.t()[c]
                );
            }
        }
    }
    eprintln!("overlapping media: worst relative difference {worst:.3e}, worst true/estimated error {worst_ratio:.2}");
    // Tolerance 1e-7 plus f32 storage (6e-8 relative).
    assert!(worst <= 2e-7, "worst relative difference {worst:.3e}");
    assert!(worst_ratio <= 1.0, "true error exceeds the estimate by {worst_ratio:.2}×");
}
