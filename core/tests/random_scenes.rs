//! Property test: random *valid* scenes — random camera (perspective or
//! equirectangular, any orientation, clip ranges), 8×6 pixels, 0–3 media of
//! random types with parameters over wide log ranges, 0–2 suns + ambient, an
//! optional random box mesh, point-sampled or Blender-filtered — render to
//! images where every pixel is finite, `T ∈ [0, 1]`, `L ≥ 0`, depth > 0, and
//! the report's error estimate is finite.
//!
//! Coefficients are grey or RGB (the RGB colour path): a spectral coefficient
//! can legitimately give a slightly negative Rec.709 channel for a saturated
//! spectrum, so `L ≥ 0` would not be a property there.
//!
//! The seed is fixed (reproducible CI) unless `PROPTEST_RNG_SEED` is set;
//! `PROPTEST_CASES` overrides the number of cases.

// Per-channel loops index several parallel arrays (as in the library).
#![allow(clippy::needless_range_loop)]

use proptest::prelude::*;
use proptest::test_runner::{Config, RngSeed, TestRunner};
use std::sync::atomic::{AtomicU64, Ordering};
use tyndall_core::render::DEPTH_NO_HIT;
use tyndall_core::{Scene, render};

fn log10(lo: f64, hi: f64) -> impl Strategy<Value = f64> {
    (lo..hi).prop_map(|e| 10f64.powf(e))
}

fn num(x: f64) -> String {
    format!("{x:?}")
}

fn vec3(v: [f64; 3]) -> String {
    format!("[{:?},{:?},{:?}]", v[0], v[1], v[2])
}

/// Elevation in degrees with the exact special values over-represented.
fn elevation() -> impl Strategy<Value = f64> {
    prop_oneof![
        3 => -90.0f64..90.0,
        1 => prop::sample::select(vec![-90.0, -1e-9, 0.0, 1e-9, 90.0]),
    ]
}

fn unit(elev_deg: f64, azim_deg: f64) -> [f64; 3] {
    let (se, ce) = elev_deg.to_radians().sin_cos();
    let (sa, ca) = azim_deg.to_radians().sin_cos();
    let se = if elev_deg == 0.0 { 0.0 } else { se };
    let ce = if elev_deg.abs() == 90.0 { 0.0 } else { ce };
    [ce * ca, ce * sa, se]
}

fn coefficient(lo: f64, hi: f64) -> impl Strategy<Value = String> {
    prop_oneof![
        1 => Just("0".to_string()),
        3 => log10(lo, hi).prop_map(num),
        2 => (log10(lo, hi), log10(lo, hi), log10(lo, hi)).prop_map(|(a, b, c)| vec3([a, b, c])),
    ]
}

fn phase() -> impl Strategy<Value = String> {
    prop_oneof![
        Just(r#"{"type":"isotropic"}"#.to_string()),
        Just(r#"{"type":"rayleigh"}"#.to_string()),
        (-0.99f64..0.99).prop_map(|g| format!(r#"{{"type":"henyey_greenstein","g":{g:?}}}"#)),
        (-0.99f64..0.99).prop_map(|g| format!(r#"{{"type":"cornette_shanks","g":{g:?}}}"#)),
        Just(r#"{"type":"nishita_hazy"}"#.to_string()),
        Just(r#"{"type":"nishita_murky"}"#.to_string()),
    ]
}

#[derive(Debug, Clone, Copy, PartialEq)]
enum Kind {
    Homogeneous,
    HeightFog,
    FogLayer,
}

fn homogeneous() -> impl Strategy<Value = (Kind, String)> {
    let bounds = prop_oneof![
        Just(r#""world""#.to_string()),
        (prop::array::uniform3(-1e3f64..1e3), prop::array::uniform3(log10(-1.0, 4.0))).prop_map(|(lo, size)| {
            let hi = [lo[0] + size[0], lo[1] + size[1], lo[2] + size[2]];
            format!(r#"{{"box":{{"min":{},"max":{}}}}}"#, vec3(lo), vec3(hi))
        }),
    ];
    (coefficient(-12.0, 1.0), coefficient(-12.0, 0.0), phase(), bounds).prop_map(|(s, a, p, b)| {
        (
            Kind::Homogeneous,
            format!(r#"{{"type":"homogeneous","scattering":{s},"absorption":{a},"phase":{p},"bounds":{b}}}"#),
        )
    })
}

fn height_fog() -> impl Strategy<Value = (Kind, String)> {
    (
        log10(-3.0, 7.0),
        -1e4f64..1e4,
        prop::option::of((coefficient(-12.0, -1.0), coefficient(-12.0, -2.0))),
        prop::option::of((coefficient(-12.0, 0.0), coefficient(-12.0, -1.0), phase())),
    )
        .prop_map(|(h, z_ref, r, m)| {
            let mut s = format!(
                r#"{{"type":"height_fog","scale_height_m":{},"reference_height_m":{}"#,
                num(h),
                num(z_ref)
            );
            if let Some((sc, ab)) = r {
                s += &format!(r#","rayleigh":{{"scattering":{sc},"absorption":{ab}}}"#);
            }
            if let Some((sc, ab, p)) = m {
                s += &format!(r#","mie":{{"scattering":{sc},"absorption":{ab},"phase":{p}}}"#);
            }
            s += "}";
            (Kind::HeightFog, s)
        })
}

fn fog_layer() -> impl Strategy<Value = (Kind, String)> {
    (
        -1e3f64..1e3,
        log10(-2.0, 4.0),
        coefficient(-9.0, 2.0),
        0.0f64..=1.0,
        coefficient(-12.0, -3.0),
        phase(),
        any::<bool>(),
        prop_oneof![Just(0.0f64), Just(15.0), Just(90.0), 0.0f64..90.0],
    )
        .prop_map(|(g, thick, ext, alb, air, p, per_point, min_sun)| {
            (
                Kind::FogLayer,
                format!(
                    r#"{{"type":"fog_layer","ground_height_m":{},"top_height_m":{},"extinction":{ext},"single_scattering_albedo":{},
                        "air_extinction":{air},"phase":{p},"sun_path":"{}","min_sun_elevation_deg":{}}}"#,
                    num(g),
                    num(g + thick),
                    num(alb),
                    if per_point { "per_point" } else { "full_layer" },
                    num(min_sun)
                ),
            )
        })
}

fn medium() -> impl Strategy<Value = (Kind, String)> {
    prop_oneof![homogeneous(), height_fog(), fog_layer()]
}

/// A camera: JSON, eye position, and the direction it looks (for placing a mesh in view).
fn camera() -> impl Strategy<Value = (String, [f64; 3], [f64; 3])> {
    let position = (-1e3f64..1e3, -1e3f64..1e3, prop_oneof![-1e4f64..1e4, -50.0f64..500.0]);
    let perspective = (
        position.clone(),
        elevation(),
        0.0f64..360.0,
        log10(-1.0, 3.0),
        log10(0.7, 2.3),
        prop_oneof![Just(0.0f64), 0.0f64..10.0],
        prop::option::of(log10(0.0, 5.0)),
        -0.5f64..0.5,
    )
        .prop_map(|((x, y, z), el, az, dist, focal, clip_start, clip_len, shift)| {
            let d = unit(el, az);
            let target = [x + dist * d[0], y + dist * d[1], z + dist * d[2]];
            let up = if d[2].abs() > 0.99 { "[0,1,0]" } else { "[0,0,1]" };
            let clip_end = clip_len.map(|l| num(clip_start + l)).unwrap_or("null".into());
            let json = format!(
                r#"{{"type":"perspective","position":{},"orientation":{{"look_at":{{"target":{},"up":{up}}}}},
                   "focal_length_mm":{},"shift_x":{},"resolution":[8,6],"clip_start_m":{},"clip_end_m":{clip_end}}}"#,
                vec3([x, y, z]),
                vec3(target),
                num(focal),
                num(shift),
                num(clip_start)
            );
            (json, [x, y, z], d)
        });
    let quaternion = (position.clone(), prop::array::uniform4(-1.0f64..1.0))
        .prop_filter("non-zero quaternion", |(_, q)| q.iter().map(|v| v * v).sum::<f64>() > 1e-6)
        .prop_map(|((x, y, z), q)| {
            let n = q.iter().map(|v| v * v).sum::<f64>().sqrt();
            let [w, a, b, c] = q.map(|v| v / n);
            // The camera looks along its local −Z: minus the third column of R(q).
            let fwd = [-2.0 * (a * c + w * b), -2.0 * (b * c - w * a), -(1.0 - 2.0 * (a * a + b * b))];
            let json = format!(
                r#"{{"type":"perspective","position":{},"orientation":{{"quaternion_wxyz":[{:?},{:?},{:?},{:?}]}},"resolution":[8,6]}}"#,
                vec3([x, y, z]),
                q[0],
                q[1],
                q[2],
                q[3]
            );
            (json, [x, y, z], fwd)
        });
    let equirect = (position, prop::option::of(log10(0.0, 5.0)), elevation(), 0.0f64..360.0).prop_map(|((x, y, z), clip, el, az)| {
        let json = format!(
            r#"{{"type":"equirectangular","position":{},"resolution":[8,6],"clip_end_m":{}}}"#,
            vec3([x, y, z]),
            clip.map(num).unwrap_or("null".into())
        );
        (json, [x, y, z], unit(el, az))
    });
    prop_oneof![4 => perspective, 1 => quaternion, 1 => equirect]
}

fn lights() -> impl Strategy<Value = String> {
    let sun = (elevation(), 0.0f64..360.0, log10(-3.0, 5.0), prop::array::uniform3(0.0f64..1.0)).prop_map(|(el, az, e, c)| {
        format!(
            r#"{{"type":"sun","direction_to_sun":{},"strength_w_m2":{},"color":{}}}"#,
            vec3(unit(el, az)),
            num(e),
            vec3(c)
        )
    });
    let ambient = prop::option::weighted(0.75, (log10(-3.0, 3.0), prop::array::uniform3(0.0f64..1.0)))
        .prop_map(|a| a.map(|(r, c)| format!(r#"{{"type":"ambient","radiance":{},"color":{}}}"#, num(r), vec3(c))));
    (prop::collection::vec(sun, 0..=2), ambient).prop_map(|(mut suns, amb)| {
        suns.extend(amb);
        format!("[{}]", suns.join(","))
    })
}

/// An optional box mesh: centre at `eye + dist·forward + jitter·dist`, half sizes `h`.
fn box_mesh() -> impl Strategy<Value = Option<(f64, [f64; 3], [f64; 3])>> {
    prop::option::of((
        log10(0.0, 3.5),
        prop::array::uniform3(-0.5f64..0.5),
        prop::array::uniform3(log10(-1.0, 3.0)),
    ))
}

fn box_json(eye: [f64; 3], fwd: [f64; 3], (dist, jitter, h): (f64, [f64; 3], [f64; 3])) -> String {
    let c: [f64; 3] = std::array::from_fn(|i| eye[i] + dist * (fwd[i] + jitter[i]));
    let mut p = vec![];
    for k in 0..8 {
        let s = |bit: usize| if k & bit != 0 { 1.0 } else { -1.0 };
        p.push(vec3([c[0] + s(1) * h[0], c[1] + s(2) * h[1], c[2] + s(4) * h[2]]));
    }
    let tris = "[0,1,3],[0,3,2],[4,6,7],[4,7,5],[0,4,5],[0,5,1],[2,3,7],[2,7,6],[0,2,6],[0,6,4],[1,5,7],[1,7,3]";
    format!(r#"{{"name":"box","positions":[{}],"triangles":[{tris}]}}"#, p.join(","))
}

fn scene() -> impl Strategy<Value = (String, Vec<Kind>)> {
    (
        camera(),
        prop::collection::vec(medium(), 0..=3),
        lights(),
        box_mesh(),
        prop_oneof![3 => Just("none"), 1 => Just("blackman_harris")],
    )
        .prop_map(|((cam, eye, fwd), media, lights, mesh, filter)| {
            let mesh = mesh.map(|m| box_json(eye, fwd, m));
            let kinds = media.iter().map(|m| m.0).collect();
            let media: Vec<String> = media.into_iter().map(|m| m.1).collect();
            let json = format!(
                r#"{{"version":1,"camera":{cam},"meshes":[{}],"lights":{lights},"media":[{}],
                    "output":{{"layers":["inscatter","transmittance","depth","sun_transmittance","error"],"pixel_filter":{{"type":"{filter}"}}}}}}"#,
                mesh.unwrap_or_default(),
                media.join(",")
            );
            (json, kinds)
        })
}

/// Coverage counters: scenes, pixels with L > 0, pixels integrated numerically,
/// pixels that hit a mesh, pixels with T < 1.
static COUNTS: [AtomicU64; 5] = [const { AtomicU64::new(0) }; 5];

fn check(json: &str) -> Result<(), TestCaseError> {
    let scene = Scene::from_json_str(json, "<random>").map_err(|e| TestCaseError::fail(format!("valid scene rejected: {e}")))?;
    let (img, report) = render(&scene, None).map_err(|e| TestCaseError::fail(format!("render failed: {e}")))?;
    let n = 48;
    prop_assert_eq!(img.inscatter.len(), n);
    prop_assert_eq!(img.transmittance.len(), n);
    prop_assert_eq!(img.depth.len(), n);
    prop_assert_eq!(img.sun_transmittance.len(), n);
    prop_assert_eq!(img.error.len(), n);
    for i in 0..n {
        for c in 0..3 {
            let (l, t, st, e) = (
                img.inscatter[i][c],
                img.transmittance[i][c],
                img.sun_transmittance[i][c],
                img.error[i][c],
            );
            prop_assert!(l.is_finite() && l >= 0.0, "pixel {} L[{}] = {}", i, c, l);
            prop_assert!((0.0..=1.0).contains(&t), "pixel {} T[{}] = {}", i, c, t);
            prop_assert!((0.0..=1.0).contains(&st), "pixel {} T_sun[{}] = {}", i, c, st);
            prop_assert!(e.is_finite() && e >= 0.0, "pixel {} error[{}] = {}", i, c, e);
        }
        let d = img.depth[i];
        prop_assert!(d > 0.0 && (d.is_finite() || d == DEPTH_NO_HIT), "pixel {} depth {}", i, d);
    }
    prop_assert!(
        report.error.max_abs.is_finite() && report.error.max_abs >= 0.0,
        "{:?}",
        report.error
    );
    prop_assert!(
        report.error.max_rel.is_finite() && report.error.max_rel >= 0.0,
        "{:?}",
        report.error
    );
    prop_assert_eq!(report.stats.pixels, n as u64);
    COUNTS[0].fetch_add(1, Ordering::Relaxed);
    COUNTS[1].fetch_add(
        img.inscatter.iter().filter(|l| l.iter().any(|v| *v > 0.0)).count() as u64,
        Ordering::Relaxed,
    );
    COUNTS[2].fetch_add(report.error.pixels_numeric, Ordering::Relaxed);
    COUNTS[3].fetch_add(report.stats.rays_hit_surface, Ordering::Relaxed);
    COUNTS[4].fetch_add(
        img.transmittance.iter().filter(|t| t.iter().any(|v| *v < 1.0)).count() as u64,
        Ordering::Relaxed,
    );
    Ok(())
}

fn config() -> Config {
    let mut c = Config {
        cases: 64,
        failure_persistence: None,
        max_shrink_time: 30_000,
        ..Config::default()
    };
    if let Ok(n) = std::env::var("PROPTEST_CASES").map(|v| v.parse::<u32>()) {
        c.cases = n.unwrap_or(64);
    }
    if std::env::var("PROPTEST_RNG_SEED").is_err() {
        c.rng_seed = RngSeed::Fixed(0x0074_796e_6461_6c6c);
    }
    c
}

/// Drops every height fog that shares the scene with another medium: the
/// renderer's numeric path gives NaN where a height fog's density overflows on a
/// ray shared with another medium (see the ignored
/// `random_valid_scenes_with_overlapping_height_fog_render_sane_images` below and
/// `extreme_inputs.rs`). Everything else is kept. Drop this filter once fixed.
fn without_known_bug((json, kinds): (String, Vec<Kind>)) -> String {
    let hf = kinds.iter().filter(|k| **k == Kind::HeightFog).count();
    if hf == 0 || kinds.len() == 1 {
        return json;
    }
    // Rebuild the media list without height fogs.
    let scene: serde_json::Value = serde_json::from_str(&json).expect("generated JSON");
    let mut scene = scene;
    if let Some(media) = scene.get_mut("media").and_then(|m| m.as_array_mut()) {
        media.retain(|m| m.get("type").and_then(|t| t.as_str()) != Some("height_fog"));
    }
    serde_json::to_string(&scene).expect("JSON")
}

#[test]
fn random_valid_scenes_render_sane_images() {
    let mut runner = TestRunner::new(config());
    let result = runner.run(&scene().prop_map(without_known_bug), |s| check(&s));
    let c: Vec<u64> = COUNTS.iter().map(|a| a.load(Ordering::Relaxed)).collect();
    eprintln!(
        "random scenes: {} rendered, {} pixels: {} with L > 0, {} with T < 1, {} numerically integrated, {} on a mesh",
        c[0],
        c[0] * 48,
        c[1],
        c[4],
        c[2],
        c[3]
    );
    if let Err(e) = result {
        panic!("{e}");
    }
}

proptest! {
    #![proptest_config(config())]

    #[test]
    fn random_valid_scenes_with_overlapping_height_fog_render_sane_images(s in scene().prop_map(|(j, _)| j)) {
        check(&s)?;
    }
}
