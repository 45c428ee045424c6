//! Benchmark scenes shared by `tyndall bench` and the criterion benches, so
//! both measure the same thing. See `docs/benchmarks.md`.

use crate::scene::Scene;

/// The benchmark scene: height fog seen from 2 m, sun and ambient; with
/// `mesh`, a ground grid plus a sphere, 10 000+ triangles in all. A size or
/// thread count the scene format refuses is that error (naming the field).
pub fn height_fog(width: u32, height: u32, threads: usize, mesh: bool) -> Result<Scene, crate::scene::SceneError> {
    let meshes = if mesh {
        tessellated_sphere_and_ground()
    } else {
        String::from("[]")
    };
    let json = format!(
        r#"{{"version": 1,
  "camera": {{"type": "perspective", "position": [0, -30, 2], "orientation": {{"look_at": {{"target": [0, 0, 4]}}}}, "resolution": [{width}, {height}]}},
  "meshes": {meshes},
  "lights": [{{"type": "sun", "direction_to_sun": [0.2, 1.0, 0.35], "strength_w_m2": 3.0}}, {{"type": "ambient", "radiance": 0.05}}],
  "media": [{{"type": "height_fog", "scale_height_m": 25, "rayleigh": {{"scattering": [0.0006, 0.0012, 0.003]}}, "mie": {{"scattering": 0.02, "absorption": 0.002, "phase": {{"type": "henyey_greenstein", "g": 0.7}}}}}}],
  "output": {{"threads": {threads}}}}}"#
    );
    Scene::from_json_str(&json, "<bench>")
}

fn tessellated_sphere_and_ground() -> String {
    let mut pos: Vec<[f64; 3]> = Vec::new();
    let mut tri: Vec<[u32; 3]> = Vec::new();
    // Ground: 50×50 quads = 5000 triangles over 200 m.
    let n = 50;
    for j in 0..=n {
        for i in 0..=n {
            pos.push([-100.0 + 200.0 * i as f64 / n as f64, -100.0 + 200.0 * j as f64 / n as f64, 0.0]);
        }
    }
    for j in 0..n {
        for i in 0..n {
            let a = (j * (n + 1) + i) as u32;
            let b = a + 1;
            let c = a + (n + 1) as u32;
            tri.push([a, b, c + 1]);
            tri.push([a, c + 1, c]);
        }
    }
    // Sphere: 50 × 51 quads ≈ 5100 triangles, radius 3 m at (0, 5, 3).
    let (nu, nv) = (51usize, 50usize);
    let base = pos.len() as u32;
    for v in 0..=nv {
        let th = std::f64::consts::PI * v as f64 / nv as f64;
        for u in 0..=nu {
            let ph = 2.0 * std::f64::consts::PI * u as f64 / nu as f64;
            pos.push([3.0 * th.sin() * ph.cos(), 5.0 + 3.0 * th.sin() * ph.sin(), 3.0 + 3.0 * th.cos()]);
        }
    }
    for v in 0..nv {
        for u in 0..nu {
            let a = base + (v * (nu + 1) + u) as u32;
            let b = a + 1;
            let c = a + (nu + 1) as u32;
            tri.push([a, c, c + 1]);
            tri.push([a, c + 1, b]);
        }
    }
    format!(
        r#"[{{"name": "bench", "positions": {}, "triangles": {}}}]"#,
        serde_json::to_string(&pos).unwrap_or_default(),
        serde_json::to_string(&tri).unwrap_or_default()
    )
}
