//! `surface_transmittance.<light>` layers: per stage light, the medium's
//! transmittance of that light's direct light via the visible surface to the
//! camera, T(light → surface) · T(surface → camera). Checked against the
//! closed form exp(−σ_t·(|c − p| + |p − ℓ|)) with the surface point p found
//! independently (ray–plane intersection from the camera's own pinhole model).

use tyndall_core::scene::Scene;

const SIGMA_S: f64 = 0.04;
const SIGMA_A: f64 = 0.01;

fn scene_json(filter: &str) -> String {
    format!(
        r#"{{"version": 1,
      "camera": {{"type": "perspective", "position": [0, -9, 2.5], "orientation": {{"look_at": {{"target": [0, 0, 0.5], "up": [0, 0, 1]}}}},
                 "focal_length_mm": 24, "sensor_width_mm": 36, "resolution": [48, 27]}},
      "meshes": [{{"name": "floor", "positions": [[-40, -40, 0], [40, -40, 0], [40, 40, 0], [-40, 40, 0]], "triangles": [[0, 1, 2], [0, 2, 3]]}}],
      "lights": [
        {{"type": "spot", "name": "key.left", "position": [-2, 0, 5], "orientation": {{"look_at": {{"target": [-1, 0, 0]}}}}, "spot_size_deg": 50, "power_w": 500}},
        {{"type": "point", "name": "fill", "position": [3, 2, 1.5], "power_w": 100, "color": [0.2, 0.4, 1.0]}},
        {{"type": "window", "name": "sun_window", "direction_to_light": [0.3, 0.2, 1.0], "irradiance_w_m2": 50,
          "aperture": [[-1, -1, 6], [1, -1, 6], [1, 1, 6], [-1, 1, 6]]}}
      ],
      "media": [{{"type": "homogeneous", "scattering": {SIGMA_S}, "absorption": {SIGMA_A}, "bounds": "world"}}],
      "output": {{"layers": ["inscatter", "transmittance", "depth", "surface_transmittance_per_light"],
                  "spectral": "never", "pixel_filter": {filter}}}}}"#
    )
}

/// The closed form at the centre of pixel (i, j), or None where the ray misses the floor.
fn expected(scene: &Scene, i: usize, j: usize) -> Option<[f64; 3]> {
    // Pinhole: 24 mm lens, 36 mm sensor width (horizontal fit), 48 × 27 px.
    let cam = glam::DVec3::new(0.0, -9.0, 2.5);
    let fwd = (glam::DVec3::new(0.0, 0.0, 0.5) - cam).normalize();
    let right = fwd.cross(glam::DVec3::Z).normalize();
    let up = right.cross(fwd);
    let (w, h) = (48.0, 27.0);
    let half_w = 18.0 / 24.0;
    let x = ((i as f64 + 0.5) / w * 2.0 - 1.0) * half_w;
    let y = (1.0 - (j as f64 + 0.5) / h * 2.0) * half_w * h / w;
    let d = (fwd + right * x + up * y).normalize();
    if d.z >= 0.0 {
        return None;
    }
    let p = cam + d * (-cam.z / d.z);
    if p.x.abs() > 40.0 || p.y.abs() > 40.0 {
        return None;
    }
    let sigma_t = SIGMA_S + SIGMA_A;
    let view = (p - cam).length();
    let _ = scene;
    let lights = [glam::DVec3::new(-2.0, 0.0, 5.0), glam::DVec3::new(3.0, 2.0, 1.5)];
    let mut out = [0.0; 3];
    for (k, l) in lights.iter().enumerate() {
        out[k] = (-sigma_t * (view + (p - *l).length())).exp();
    }
    // Window: back along the light direction to the plane z = 6.
    let to_light = glam::DVec3::new(0.3, 0.2, 1.0).normalize();
    let s = (6.0 - p.z) / to_light.z;
    out[2] = (-sigma_t * (view + s)).exp();
    Some(out)
}

#[test]
fn surface_transmittance_matches_the_closed_form_per_light() {
    let scene = Scene::from_json_str(&scene_json(r#"{"type": "none"}"#), "test").unwrap();
    let (images, report) = tyndall_core::render(&scene, None).unwrap();
    assert_eq!(
        images.surface_layer_names,
        [
            "surface_transmittance.key_left",
            "surface_transmittance.fill",
            "surface_transmittance.sun_window"
        ]
    );
    let names: Vec<String> = images.exr_layers().iter().map(|l| l.name.clone()).collect();
    assert!(names.contains(&"surface_transmittance.fill".to_string()), "{names:?}");
    assert!(report.plan.computed.iter().any(|c| c.what.contains("surface_transmittance")));
    let (mut floor_px, mut worst) = (0, 0.0f64);
    for j in 0..27 {
        for i in 0..48 {
            let px = j * 48 + i;
            let view_t = images.transmittance[px][0];
            match expected(&scene, i, j) {
                Some(want) => {
                    floor_px += 1;
                    for (k, want_k) in want.iter().enumerate() {
                        let got = images.light_surface_transmittance[k][px];
                        // Grey medium: the three channels agree.
                        assert_eq!(got[0], got[2]);
                        let rel = (f64::from(got[0]) - want_k).abs() / want_k;
                        worst = worst.max(rel);
                    }
                }
                None => {
                    // No surface: the view transmittance.
                    for k in 0..3 {
                        assert_eq!(images.light_surface_transmittance[k][px][1], view_t);
                    }
                }
            }
        }
    }
    println!("{floor_px} floor pixels, worst relative difference {worst:e}");
    assert!(floor_px > 400);
    // f32 storage plus the pinhole's rounding: far below any visible difference.
    assert!(worst < 1e-5, "worst relative difference {worst:e}");
}

/// With Blender's pixel filter, a pixel just below the horizon averages over
/// its floor samples only (the sky samples, whose view transmittance is ~0 in
/// a world medium, would darken it): every pixel whose centre sees the floor
/// stays within the closed form's range over its filter window, and pixels
/// away from the horizon keep their centre value up to the filter's curvature
/// term.
#[test]
fn filtered_surface_transmittance_averages_over_surface_samples() {
    let point = Scene::from_json_str(&scene_json(r#"{"type": "none"}"#), "test").unwrap();
    let filt = Scene::from_json_str(&scene_json(r#"{"type": "blackman_harris", "width_px": 1.5}"#), "test").unwrap();
    let (a, _) = tyndall_core::render(&point, None).unwrap();
    let (b, _) = tyndall_core::render(&filt, None).unwrap();
    let mut near_horizon = 0;
    for j in 2..25usize {
        for i in 2..46usize {
            if expected(&point, i, j).is_none() {
                continue;
            }
            let px = j * 48 + i;
            let window: Vec<Option<[f64; 3]>> = (j - 2..=j + 2)
                .flat_map(|jj| (i - 2..=i + 2).map(move |ii| (ii, jj)))
                .map(|(ii, jj)| expected(&point, ii, jj))
                .collect();
            let sees_sky = window.iter().any(Option::is_none);
            near_horizon += sees_sky as usize;
            for k in 0..3 {
                let got = f64::from(b.light_surface_transmittance[k][px][0]);
                let lo = window.iter().flatten().map(|e| e[k]).fold(f64::INFINITY, f64::min);
                let hi = window.iter().flatten().map(|e| e[k]).fold(0.0, f64::max);
                assert!(
                    got >= lo * (1.0 - 1e-5) - 1e-30 && got <= hi * (1.0 + 1e-5),
                    "({i},{j}) light {k}: {got} not in [{lo}, {hi}]"
                );
                if !sees_sky {
                    let centre = f64::from(a.light_surface_transmittance[k][px][0]);
                    // A smooth pixel: the filter moves it by its curvature
                    // term, far less than the variation across its window.
                    assert!(
                        (got - centre).abs() <= 0.1 * (hi - lo) + 1e-6 * centre,
                        "({i},{j}) light {k}: filtered {got} vs centre {centre}, window [{lo}, {hi}]"
                    );
                }
            }
        }
    }
    assert!(near_horizon >= 40, "the test must cross the horizon: {near_horizon}");
}
