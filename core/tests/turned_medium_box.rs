//! A haze box turned about its centre (`bounds.box.rotation_wxyz`), through
//! the whole renderer: a spot light with an occluder and a sun in a box of
//! haze, and the same scene with everything — camera, lights, meshes, box —
//! turned as one rigid body. The images must agree pixel by pixel within the
//! two renders' own error estimates: the turned box is then exactly the
//! axis-aligned one seen from a turned frame. (The box's closed forms
//! against independent quadrature: `closed_form_vs_quadrature.rs`.)

#![allow(clippy::needless_range_loop)] // (in `common`)

mod common;

use glam::{DQuat, DVec3};
use serde_json::{Value, json};
use tyndall_core::{Scene, render};

/// The scene turned by `q` about `pivot` (`None`: as built, box axis-aligned).
fn scene(turn: Option<(DQuat, DVec3)>) -> Value {
    let point = |p: [f64; 3]| -> [f64; 3] {
        match turn {
            Some((q, pivot)) => (pivot + q * (DVec3::from(p) - pivot)).to_array(),
            None => p,
        }
    };
    let dir = |d: [f64; 3]| -> [f64; 3] {
        match turn {
            Some((q, _)) => (q * DVec3::from(d)).to_array(),
            None => d,
        }
    };
    let floor: Vec<[f64; 3]> = [[-30.0, -30.0, 0.0], [30.0, -30.0, 0.0], [30.0, 30.0, 0.0], [-30.0, 30.0, 0.0]]
        .into_iter()
        .map(point)
        .collect();
    // An occluder in the beam: a 0.6 m cube, its top at 2.6 m.
    let (c0, c1) = ([0.1, -0.3, 2.0], [0.7, 0.3, 2.6]);
    let cube: Vec<[f64; 3]> = (0..8)
        .map(|i| {
            point([
                if i & 1 == 0 { c0[0] } else { c1[0] },
                if i & 2 == 0 { c0[1] } else { c1[1] },
                if i & 4 == 0 { c0[2] } else { c1[2] },
            ])
        })
        .collect();
    let cube_tris = tyndall_core::geometry::CUBE_TRIANGLES;
    let (box_min, box_max) = ([-2.5, -1.8, 0.0], [2.5, 1.8, 3.6]);
    let mut bounds = json!({"min": box_min, "max": box_max});
    if let Some((q, _)) = turn {
        bounds["rotation_wxyz"] = json!([q.w, q.x, q.y, q.z]);
    }
    json!({
        "version": 1,
        "camera": {
            "type": "perspective",
            "position": point([0.8, -7.0, 1.6]),
            "orientation": {"look_at": {"target": point([0.0, 0.0, 1.8]), "up": dir([0.0, 0.0, 1.0])}},
            "focal_length_mm": 24.0,
            "resolution": [40, 26]
        },
        "meshes": [
            {"name": "floor", "positions": floor, "triangles": [[0, 1, 2], [0, 2, 3]]},
            {"name": "cube", "positions": cube, "triangles": cube_tris}
        ],
        "lights": [
            {
                "type": "spot", "name": "spot", "position": point([0.3, 0.0, 4.2]),
                "orientation": {"look_at": {"target": point([0.0, 0.0, 0.0]), "up": dir([0.0, 1.0, 0.0])}},
                "color": [1.0, 0.9, 0.8], "power_w": 800.0, "spot_size_deg": 45.0, "spot_blend": 0.2
            },
            {"type": "sun", "name": "sun", "direction_to_sun": dir([0.3, -0.5, 0.81]), "strength_w_m2": 2.0, "angular_diameter_deg": 0.0}
        ],
        "media": [{
            "type": "homogeneous", "name": "haze box", "scattering": [0.12, 0.14, 0.16], "absorption": 0.04,
            "phase": {"type": "henyey_greenstein", "g": 0.4}, "bounds": {"box": bounds}
        }],
        "output": {
            "tolerance": 1e-6,
            "pixel_filter": {"type": "none"},
            "layers": ["inscatter", "transmittance", "error"],
            "spectral": "never"
        }
    })
}

#[test]
fn a_turned_haze_box_renders_as_the_scene_turned_with_it() {
    let pivot = DVec3::new(0.0, 0.0, 1.8); // the box's centre
    let q = DQuat::from_axis_angle(DVec3::new(0.3, -0.5, 0.8).normalize(), 0.9);
    let render_of = |v: Value| {
        let s = Scene::from_json_str(&v.to_string(), "turned_medium_box").expect("scene parses");
        render(&s, None).expect("renders")
    };
    let (a, rep_a) = render_of(scene(None));
    let (b, rep_b) = render_of(scene(Some((q, pivot))));
    assert!(
        rep_b.plan.computed.iter().any(|c| c.how.contains("rotated box")),
        "the report names the turned box: {:?}",
        rep_b.plan.computed
    );
    let peak = a.inscatter.iter().flatten().fold(0.0f32, |m, v| m.max(*v)) as f64;
    assert!(peak > 0.0);
    let (mut worst, mut lit, mut t_worst) = (0.0f64, 0usize, 0.0f64);
    for i in 0..a.inscatter.len() {
        for c in 0..3 {
            let (x, y) = (a.inscatter[i][c] as f64, b.inscatter[i][c] as f64);
            assert!(x.is_finite() && y.is_finite());
            // Both renders are within their estimates of the truth; f32 storage adds its rounding.
            let room = a.error[i][c] as f64 + b.error[i][c] as f64 + 1e-6 * x.abs().max(y.abs()) + 1e-9 * peak;
            worst = worst.max((x - y).abs() / room);
            if x > 1e-3 * peak {
                lit += 1;
            }
            let (tx, ty) = (a.transmittance[i][c] as f64, b.transmittance[i][c] as f64);
            t_worst = t_worst.max((tx - ty).abs());
        }
    }
    eprintln!("peak {peak:e}, {lit} lit channels, worst |a − b| / room {worst:.3}, transmittance {t_worst:e}");
    // The scene must exercise the box: the haze lit by the spot, and a shadow.
    assert!(lit > 1000, "too few lit pixels: {lit}");
    assert!(worst <= 1.0, "turned and axis-aligned boxes differ beyond their estimates: {worst}");
    assert!(t_worst <= 1e-6, "transmittance differs by {t_worst}");
    assert_eq!(rep_a.stats.pixels, rep_b.stats.pixels);
}
