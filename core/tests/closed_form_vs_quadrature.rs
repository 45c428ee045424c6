//! Closed forms against brute-force quadrature of the volume rendering equation
//! (Ishiyama eq 4; Klassen eq 1.11), double precision, over grids of view
//! directions, heights, densities and scale heights: relative difference ≤ 1e-6.
//!
//! The reference (`common`) integrates `L = ∫ T(0,s) μ_s(s) J(s) ds` with nested
//! Gauss–Legendre quadrature, `T` itself from a quadrature of μ_t: it uses none
//! of `tyndall_core::numeric` nor the media's `optical_depth`/`source`.
//!
//! Absolute floors, used only where the reference is 0 or below 1e-300:
//! * transmittance `T < 1e-300` (optical depth > 690): only `L` is compared and
//!   the closed form's `T` must be ≤ 1e-300 too;
//! * through the renderer the images are f32: `T` below 1e-30 (near the f32
//!   normal range limit, 1.2e-38) must be ≤ 1e-30 in the image.
//!
//! Suns are points (`angular_diameter_deg: 0`), as in both papers; the
//! renderer's averaging of the phase function over a finite sun disc is checked
//! separately against a 2-D quadrature over the disc (last two tests).
//!
//! Every test prints its number of comparisons and the largest relative
//! difference observed, per quantity (`cargo test -- --nocapture`).

// Per-channel loops index several parallel arrays (as in the library).
#![allow(clippy::needless_range_loop)]

mod common;

use common::*;
use glam::DVec3;
use rayon::prelude::*;
use tyndall_core::geometry::camera::CameraRays;
use tyndall_core::medium::{PreparedMedium, ViewRay};
use tyndall_core::render::DEPTH_NO_HIT;
use tyndall_core::{Scene, render};

const TOL: f64 = 1e-6;
const T_FLOOR: f64 = 1e-300;

const ELEVATIONS: [f64; 9] = [-89.9, -30.0, -1.0, -0.01, 0.0, 0.01, 1.0, 30.0, 90.0];

/// Sun configurations for the height fog: elevation 0°, 90°, and pairs.
fn hf_lights(k: usize) -> Lights {
    let ambient = [0.2, 0.25, 0.3];
    let e = [1.0, 0.95, 0.9];
    let e2 = [0.5, 0.6, 0.4];
    let suns = match k % 4 {
        0 => vec![Sun {
            to_sun: dir_deg(0.0, 10.0),
            e,
        }],
        1 => vec![Sun {
            to_sun: dir_deg(90.0, 0.0),
            e,
        }],
        2 => vec![
            Sun {
                to_sun: dir_deg(30.0, 200.0),
                e,
            },
            Sun {
                to_sun: dir_deg(-10.0, 45.0),
                e: e2,
            },
        ],
        _ => vec![
            Sun {
                to_sun: dir_deg(5.0, 100.0),
                e,
            },
            Sun {
                to_sun: dir_deg(60.0, 300.0),
                e: e2,
            },
        ],
    };
    Lights { suns, ambient }
}

struct Compare<'a> {
    stats: &'a mut Stats,
    what: String,
}

impl Compare<'_> {
    /// L, T and (when given) τ of one ray, all three channels.
    fn ray(&mut self, l: [f64; 3], t: [f64; 3], tau: Option<[f64; 3]>, b: &Brute) {
        let bt = b.t();
        for c in 0..3 {
            let w = &self.what;
            self.stats.check(l[c], b.l[c], TOL, 0.0, || format!("{w} L[{c}]"));
            self.stats
                .check(t[c], bt[c], TOL, T_FLOOR, || format!("{w} T[{c}] (tau {:e})", b.tau[c]));
            if let Some(tau) = tau {
                if b.tau[c].is_infinite() {
                    self.stats.n += 1;
                    if !tau[c].is_infinite() {
                        self.stats.failures.push(format!("{w} tau[{c}]: got {:e}, want inf", tau[c]));
                    }
                } else {
                    self.stats.check(tau[c], b.tau[c], TOL, 0.0, || format!("{w} tau[{c}]"));
                }
            }
        }
    }
}

// ---------------------------------------------------------------- height fog

#[test]
fn height_fog_closed_form_matches_quadrature_over_grid() {
    let dzs = [-10_000.0, 0.0, 100.0, 10_000.0];
    let hs = [1.0, 100.0, 1200.0, 8000.0, 1e5];
    // Optical depth of the first kilometre at the densest relevant height.
    let taus: [f64; 5] = [1e-9, 1e-5, 1e-1, 1e1, 1e4];
    let z_ref = 250.0;
    let mut cases = vec![];
    for (ie, &elev) in ELEVATIONS.iter().enumerate() {
        for &dz in &dzs {
            for &h in &hs {
                for &tau_t in &taus {
                    for finite in [true, false] {
                        cases.push((ie, elev, dz, h, tau_t, finite));
                    }
                }
            }
        }
    }
    let results: Vec<Option<(Stats, f64, f64, usize)>> = cases
        .par_iter()
        .enumerate()
        .map(|(k, &(_ie, elev, dz, h, tau_t, finite))| {
            let dir = dir_deg(elev, 20.0 + 37.0 * k as f64);
            let z0 = z_ref + dz;
            let origin = DVec3::new(3.0, -7.0, z0);
            let z_ground = z0.min(z_ref) - 200.0;
            let s_max = if !finite {
                f64::INFINITY
            } else if dir.z < 0.0 {
                (z0 - z_ground) / -dir.z
            } else {
                1000.0
            };
            let z_star = if finite && dir.z < 0.0 { z_ground } else { z0 };
            let ln_rho_star = -(z_star - z_ref) / h;
            let beta = ((tau_t / 1000.0).ln() - ln_rho_star).exp();
            if !(1e-300..=1e300).contains(&beta) {
                // β·ρ is not representable (H = 1 m, 10 km from the reference): see extreme_inputs.rs.
                return None;
            }
            let bt = [beta, 0.6 * beta, 0.35 * beta];
            let model = HeightFogModel {
                h,
                z_ref,
                beta_rs: [0.2 * bt[0], 0.3 * bt[1], 0.1 * bt[2]],
                beta_ms: [0.7 * bt[0], 0.5 * bt[1], 0.6 * bt[2]],
                beta_t: bt,
                mie_phase: if k % 2 == 0 { Phase::Cs(0.76) } else { Phase::Hg(0.7) },
            };
            let lights = hf_lights(k);
            let brute = model.brute(origin, dir, s_max, &lights);
            let fog = PreparedMedium::HeightFog(model.lib());
            let ray = ViewRay { origin, dir, s_max };
            let cf = fog.closed_form(&ray, &lights.lib());
            let tau = fog.optical_depth(&ray, s_max);
            let mut stats = Stats::default();
            Compare {
                stats: &mut stats,
                what: format!("elev {elev}° dz {dz} H {h} tau_t {tau_t:e} s_max {s_max:e}"),
            }
            .ray(cf.inscatter, cf.transmittance, Some(tau), &brute);
            let finite_taus: Vec<f64> = brute.tau.iter().copied().filter(|t| t.is_finite() && *t > 0.0).collect();
            let lo = finite_taus.iter().copied().fold(f64::INFINITY, f64::min);
            let hi = finite_taus.iter().copied().fold(0.0, f64::max);
            Some((stats, lo, hi, brute.panels))
        })
        .collect();
    let mut total = Stats::default();
    let (mut skipped, mut tau_lo, mut tau_hi, mut panels) = (0, f64::INFINITY, 0.0f64, 0usize);
    for r in results {
        match r {
            None => skipped += 1,
            Some((s, lo, hi, p)) => {
                total.merge(s);
                tau_lo = tau_lo.min(lo);
                tau_hi = tau_hi.max(hi);
                panels += p;
            }
        }
    }
    eprintln!(
        "height fog grid: {} rays, {skipped} skipped (β·ρ not representable), finite optical depths {tau_lo:e} … {tau_hi:e}, {panels} panels",
        cases.len()
    );
    assert!(tau_lo <= 1e-9 && tau_hi >= 1e4, "optical depths covered: {tau_lo:e} … {tau_hi:e}");
    total.finish("height fog closed form vs quadrature");
}

/// The brute-force reference itself, checked against a second, unrelated
/// quadrature: the `quadrature` crate's double-exponential rule, nested.
#[test]
fn brute_force_reference_agrees_with_double_exponential_quadrature() {
    let mut stats = Stats::default();
    let lights = hf_lights(2);
    for (h, elev, s_max, beta) in [(500.0, 10.0, 800.0, 1e-3), (100.0, -20.0, 300.0, 2e-3), (1e4, 0.0, 2000.0, 5e-4)] {
        let model = HeightFogModel {
            h,
            z_ref: 0.0,
            beta_rs: [0.2 * beta, 0.1 * beta, 0.3 * beta],
            beta_ms: [0.5 * beta; 3],
            beta_t: [beta, 0.8 * beta, 1.2 * beta],
            mie_phase: Phase::Cs(0.6),
        };
        let origin = DVec3::new(0.0, 0.0, 150.0);
        let dir = dir_deg(elev, 33.0);
        let brute = model.brute(origin, dir, s_max, &lights);
        let src = model.source_ref(dir, &lights);
        for c in 0..3 {
            let rho = |s: f64| (-(origin.z + dir.z * s) / h).exp();
            let tau_de = |s: f64| model.beta_t[c] * quadrature::double_exponential::integrate(rho, 0.0, s, 1e-16).integral;
            let l_de = quadrature::double_exponential::integrate(|s| src[c] * rho(s) * (-tau_de(s)).exp(), 0.0, s_max, 1e-15).integral;
            stats.check(brute.l[c], l_de, 1e-10, 0.0, || format!("H {h} elev {elev} L[{c}]"));
            stats.check(brute.tau[c], tau_de(s_max), 1e-10, 0.0, || format!("H {h} elev {elev} tau[{c}]"));
        }
    }
    stats.finish("GL reference vs double-exponential");
}

// ---------------------------------------------------------------- fog layer

fn fl_lights(k: usize) -> Lights {
    let ambient = [0.3, 0.3, 0.35];
    let e = [1.0, 0.97, 0.92];
    let suns = match k % 4 {
        0 => vec![Sun {
            to_sun: dir_deg(0.0, 30.0),
            e,
        }],
        1 => vec![Sun {
            to_sun: dir_deg(90.0, 0.0),
            e,
        }],
        2 => vec![
            Sun {
                to_sun: dir_deg(45.0, 30.0),
                e,
            },
            Sun {
                to_sun: dir_deg(5.0, 200.0),
                e: [0.4, 0.3, 0.2],
            },
        ],
        _ => vec![Sun {
            to_sun: dir_deg(20.0, 270.0),
            e,
        }],
    };
    Lights { suns, ambient }
}

#[test]
fn fog_layer_closed_form_matches_quadrature_over_grid() {
    let (ground, top) = (20.0, 320.0);
    let eyes = [100.0, 1000.0, 0.0, 319.0];
    let ks = [1e-12, 1e-6, 1e-2, 1.0, 30.0];
    let mut cases = vec![];
    for &z in &eyes {
        for &elev in &ELEVATIONS {
            for end in 0..3 {
                for &k in &ks {
                    for per_point in [true, false] {
                        cases.push((z, elev, end, k, per_point));
                    }
                }
            }
        }
    }
    let results: Vec<Stats> = cases
        .par_iter()
        .enumerate()
        .map(|(i, &(z, elev, end, k, per_point))| {
            let mut stats = Stats::default();
            let dir = dir_deg(elev, 15.0 + 41.0 * i as f64);
            let origin = DVec3::new(-4.0, 11.0, z);
            let s_max = match end {
                0 => f64::INFINITY,
                1 => 2000.0,
                // Ground plane at the fog bottom (or clip when it is not ahead).
                _ => {
                    if dir.z < 0.0 && z > ground {
                        (z - ground) / -dir.z
                    } else {
                        return stats;
                    }
                }
            };
            let model = FogLayerModel {
                ground,
                top,
                fog_ext: [k, 1.05 * k, 0.95 * k],
                air_ext: [0.01 * k, 0.02 * k, 0.04 * k],
                albedo: if i % 3 == 0 { 1.0 } else { 0.9 },
                phase: [Phase::Hazy, Phase::Murky, Phase::Hg(0.8)][i % 3],
                per_point,
                min_sun_deg: if (i / 4) % 2 == 0 { 15.0 } else { 0.0 },
            };
            let lights = fl_lights(i);
            let brute = model.brute(origin, dir, s_max, &lights);
            let fog = PreparedMedium::FogLayer(model.lib());
            let ray = ViewRay { origin, dir, s_max };
            let cf = fog.closed_form(&ray, &lights.lib());
            let tau = fog.optical_depth(&ray, s_max);
            Compare {
                stats: &mut stats,
                what: format!(
                    "eye z {z} elev {elev}° s_max {s_max} k {k:e} per_point {per_point} min_sun {}",
                    model.min_sun_deg
                ),
            }
            .ray(cf.inscatter, cf.transmittance, Some(tau), &brute);
            // Object component: sun transmittance at the end point on the ground (eq 3.13/3.23).
            if end == 2 {
                let want = lights.suns.first().map(|s| model.sun_t(ground, s.to_sun)).unwrap_or([1.0; 3]);
                for c in 0..3 {
                    stats.check(cf.sun_transmittance[c], want[c], TOL, T_FLOOR, || {
                        format!("eye z {z} elev {elev}° k {k:e} per_point {per_point}: sun transmittance[{c}]")
                    });
                }
            }
            stats
        })
        .collect();
    let mut total = Stats::default();
    for s in results {
        total.merge(s);
    }
    total.finish("fog layer closed form vs quadrature");
}

/// Klassen eq 3.20 written out by hand for an eye on the ground, full-layer sun
/// path, no ambient: `I_f = I_t e^{−B(R_H−R_E) csc φ} β_sc(ψ) (1 − e^{−B h csc θ})/B`,
/// against the quadrature (this pins down that `full_layer` is Klassen's model).
#[test]
fn fog_layer_full_layer_is_klassen_eq_3_20() {
    let mut stats = Stats::default();
    let model = FogLayerModel {
        ground: 0.0,
        top: 150.0,
        fog_ext: [0.02, 0.025, 0.03],
        air_ext: [1e-4, 2e-4, 3e-4],
        albedo: 1.0,
        phase: Phase::Hazy,
        per_point: false,
        min_sun_deg: 15.0,
    };
    let to_sun = dir_deg(35.0, 0.0);
    let lights = Lights {
        suns: vec![Sun {
            to_sun,
            e: [2.0, 1.5, 1.0],
        }],
        ambient: [0.0; 3],
    };
    for theta in [5.0, 20.0, 60.0, 89.0] {
        // Eye on the ground looking up at θ: the fog path is h csc θ with h the fog thickness.
        let dir = dir_deg(theta, 180.0);
        let origin = DVec3::new(0.0, 0.0, 0.0);
        let brute = model.brute(origin, dir, f64::INFINITY, &lights);
        let cf = PreparedMedium::FogLayer(model.lib()).closed_form(
            &ViewRay {
                origin,
                dir,
                s_max: f64::INFINITY,
            },
            &lights.lib(),
        );
        let b = model.b();
        let path = 150.0 / theta.to_radians().sin();
        let d2 = 150.0 / 35f64.to_radians().sin();
        let beta_sc = Phase::Hazy.eval(dir.dot(to_sun));
        for c in 0..3 {
            let eq_3_20 = lights.suns[0].e[c] * (-b[c] * d2).exp() * model.fog_ext[c] * beta_sc * -(-b[c] * path).exp_m1() / b[c];
            stats.check(brute.l[c], eq_3_20, 1e-10, 0.0, || {
                format!("θ {theta}: quadrature vs eq 3.20 [{c}]")
            });
            stats.check(cf.inscatter[c], eq_3_20, TOL, 0.0, || {
                format!("θ {theta}: closed form vs eq 3.20 [{c}]")
            });
        }
    }
    stats.finish("fog layer full_layer vs Klassen eq 3.20");
}

// ---------------------------------------------------------------- homogeneous

fn hom_lights(k: usize) -> Lights {
    let ambient = [0.1, 0.15, 0.2];
    let e = [1.0, 0.9, 0.8];
    let suns = match k % 5 {
        0 => vec![Sun { to_sun: DVec3::Z, e }],
        1 => vec![Sun { to_sun: DVec3::X, e }],
        2 => vec![Sun {
            to_sun: DVec3::new(0.3, -0.2, 0.9).normalize(),
            e,
        }],
        3 => vec![
            Sun {
                to_sun: dir_deg(10.0, 135.0),
                e,
            },
            Sun {
                to_sun: dir_deg(70.0, -60.0),
                e: [0.3, 0.4, 0.5],
            },
        ],
        _ => vec![Sun {
            to_sun: DVec3::new(-1.0, 1.0, 0.0).normalize(),
            e,
        }],
    };
    Lights { suns, ambient }
}

#[test]
fn homogeneous_world_closed_form_matches_quadrature() {
    let mut stats = Stats::default();
    let ks = [1e-12, 1e-6, 1e-2, 1.0, 30.0];
    let mut i = 0;
    for &elev in &ELEVATIONS {
        for &k in &ks {
            for s_max in [f64::INFINITY, 1000.0, 1e-3] {
                i += 1;
                let model = HomogeneousModel {
                    sigma_s: [0.8 * k, 0.5 * k, 0.9 * k],
                    sigma_t: [k, 0.7 * k, 1.3 * k],
                    phase: [Phase::Iso, Phase::Hg(0.6), Phase::Hg(-0.3), Phase::Rayleigh, Phase::Murky][i % 5],
                    bounds: None,
                    turn: None,
                };
                let lights = hom_lights(i);
                let dir = dir_deg(elev, 7.0 * i as f64);
                let origin = DVec3::new(1.0, 2.0, 3.0);
                let brute = model.brute(origin, dir, s_max, &lights);
                let m = PreparedMedium::Homogeneous(model.lib());
                let ray = ViewRay { origin, dir, s_max };
                let cf = m.closed_form(&ray, &lights.lib());
                let tau = m.optical_depth(&ray, s_max);
                Compare {
                    stats: &mut stats,
                    what: format!("world elev {elev} k {k:e} s_max {s_max}"),
                }
                .ray(cf.inscatter, cf.transmittance, Some(tau), &brute);
            }
        }
    }
    stats.finish("homogeneous world closed form vs quadrature");
}

#[test]
fn homogeneous_box_closed_form_matches_quadrature() {
    let lo = DVec3::new(-50.0, -30.0, 0.0);
    let hi = DVec3::new(50.0, 40.0, 25.0);
    let eyes = [
        DVec3::new(-200.0, 10.0, 10.0),
        DVec3::new(0.0, 0.0, 5.0),
        DVec3::new(10.0, 5.0, 100.0),
        DVec3::new(60.0, 50.0, 25.0),
    ];
    let ks = [1e-12, 1e-6, 1e-2, 0.3, 30.0];
    let mut cases = vec![];
    for (ie, eye) in eyes.iter().enumerate() {
        for &elev in &ELEVATIONS {
            for azim in [0.0, 23.0, 90.0, 200.0, 315.0] {
                for &k in &ks {
                    for s_max in [f64::INFINITY, 150.0] {
                        cases.push((ie, *eye, elev, azim, k, s_max));
                    }
                }
            }
        }
        // Rays aimed at the box centre and at a corner from each eye.
        for target in [0.5 * (lo + hi), DVec3::new(50.0, -30.0, 25.0)] {
            if (target - *eye).length() > 0.0 {
                let d = (target - *eye).normalize();
                let elev = d.z.asin().to_degrees();
                let azim = d.y.atan2(d.x).to_degrees();
                for &k in &ks {
                    cases.push((ie, *eye, elev, azim, k, f64::INFINITY));
                }
            }
        }
    }
    let results: Vec<Stats> = cases
        .par_iter()
        .enumerate()
        .map(|(i, &(_ie, origin, elev, azim, k, s_max))| {
            let mut stats = Stats::default();
            let model = HomogeneousModel {
                sigma_s: [0.8 * k, 0.5 * k, 0.9 * k],
                sigma_t: [k, 0.7 * k, 1.3 * k],
                phase: [Phase::Iso, Phase::Hg(0.6), Phase::Cs(0.8), Phase::Hazy][i % 4],
                bounds: Some((lo, hi)),
                // Every third case with the box turned about its centre.
                turn: (i % 3 == 1).then(|| (DVec3::new(1.0, -2.0, 2.0).normalize(), 0.7)),
            };
            let lights = hom_lights(i);
            let dir = dir_deg(elev, azim);
            let brute = model.brute(origin, dir, s_max, &lights);
            let m = PreparedMedium::Homogeneous(model.lib());
            let ray = ViewRay { origin, dir, s_max };
            let cf = m.closed_form(&ray, &lights.lib());
            let tau = m.optical_depth(&ray, s_max);
            Compare {
                stats: &mut stats,
                what: format!("box eye {origin} elev {elev} azim {azim} k {k:e} s_max {s_max} suns {}", i % 5),
            }
            .ray(cf.inscatter, cf.transmittance, Some(tau), &brute);
            stats
        })
        .collect();
    let mut total = Stats::default();
    for s in results {
        total.merge(s);
    }
    total.finish("homogeneous box closed form vs quadrature");
}

// ---------------------------------------------------------------- through the renderer

/// A perspective camera scene.
#[allow(clippy::too_many_arguments)]
fn scene_json(
    position: [f64; 3],
    target: [f64; 3],
    up: [f64; 3],
    focal: f64,
    res: [u32; 2],
    clip_end: Option<f64>,
    meshes: &[String],
    lights: &Lights,
    media: &[String],
) -> String {
    format!(
        r#"{{"version":1,
            "camera":{{"type":"perspective","position":{},"orientation":{{"look_at":{{"target":{},"up":{}}}}},
                      "focal_length_mm":{focal:?},"resolution":[{},{}],"clip_end_m":{}}},
            "meshes":[{}],"lights":{},"media":[{}],
            "output":{{"layers":["inscatter","transmittance","depth","sun_transmittance","error"],"pixel_filter":{{"type":"none"}}}}}}"#,
        arr(position),
        arr(target),
        arr(up),
        res[0],
        res[1],
        clip_end.map(|c| format!("{c:?}")).unwrap_or("null".into()),
        meshes.join(","),
        lights.json(),
        media.join(",")
    )
}

/// Where the pixel's ray ends: the ground quad (half-size `half` at `zg`), else the clip end.
fn ray_end(origin: DVec3, dir: DVec3, ground: Option<(f64, f64)>, clip_end: f64) -> (f64, bool) {
    if let Some((zg, half)) = ground
        && dir.z != 0.0
    {
        let t = (zg - origin.z) / dir.z;
        let p = origin + dir * t;
        if t > 0.0 && t < clip_end && p.x.abs() <= half && p.y.abs() <= half {
            return (t, true);
        }
    }
    (clip_end, false)
}

/// Renders `json` and compares every pixel with `brute(origin, dir, s_max)`.
fn compare_render(
    name: &str,
    json: &str,
    ground: Option<(f64, f64)>,
    brute: &dyn Fn(DVec3, DVec3, f64) -> Brute,
    sun_t: Option<&dyn Fn(DVec3) -> [f64; 3]>,
) -> Stats {
    let scene = Scene::from_json_str(json, name).unwrap_or_else(|e| panic!("{name}: {e}"));
    let (img, report) = render(&scene, None).unwrap_or_else(|e| panic!("{name}: {e}"));
    assert_eq!(
        report.error.pixels_numeric, 0,
        "{name}: one medium per ray is solved in closed form"
    );
    assert!(report.error.max_abs.is_finite() && report.error.max_rel.is_finite());
    let cam = CameraRays::new(&scene.camera);
    let mut stats = Stats::default();
    let mut hits = 0;
    for row in 0..cam.height {
        for col in 0..cam.width {
            let i = row * cam.width + col;
            let dir = cam.direction(col as f64 + 0.5, row as f64 + 0.5);
            let (s_max, hit) = ray_end(cam.position, dir, ground, cam.clip_end);
            let b = brute(cam.position, dir, s_max);
            let bt = b.t();
            let what = format!("{name} pixel ({col},{row}) dir {dir:.4} s_max {s_max:e}");
            for c in 0..3 {
                stats.check(img.inscatter[i][c] as f64, b.l[c], TOL, 0.0, || format!("{what} L[{c}]"));
                stats.check(img.transmittance[i][c] as f64, bt[c], TOL, 1e-30, || format!("{what} T[{c}]"));
                if let (true, Some(f)) = (hit, sun_t) {
                    let want = f(cam.position + dir * s_max);
                    stats.check(img.sun_transmittance[i][c] as f64, want[c], TOL, 1e-30, || {
                        format!("{what} T_sun[{c}]")
                    });
                }
            }
            if hit {
                hits += 1;
                stats.check(img.depth[i] as f64, s_max, TOL, 0.0, || format!("{what} depth"));
            } else {
                stats.n += 1;
                assert_eq!(img.depth[i], DEPTH_NO_HIT, "{what}: no surface");
            }
        }
    }
    assert!(
        hits > 0 && hits < cam.width * cam.height,
        "{name}: the view should show ground and sky ({hits} hits)"
    );
    stats
}

#[test]
fn height_fog_through_renderer_matches_quadrature() {
    let z_ref = 250.0;
    let lights = hf_lights(2);
    let mut total = Stats::default();
    type HfScene<'a> = (&'a str, f64, f64, [f64; 3], [f64; 3], [f64; 3], Option<f64>, f64, f64);
    let scenes: Vec<HfScene> = vec![
        // name, H, β, position, target, up, clip_end, ground z, ground half-size
        (
            "horizon",
            1200.0,
            2e-4,
            [0.0, 0.0, z_ref + 100.0],
            [0.0, 1000.0, z_ref + 100.0],
            [0.0, 0.0, 1.0],
            None,
            z_ref - 20.0,
            2e5,
        ),
        (
            "from 10 km above",
            8000.0,
            1e-4,
            [0.0, 0.0, z_ref + 10_000.0],
            [0.0, 10_000.0, z_ref + 6000.0],
            [0.0, 0.0, 1.0],
            None,
            z_ref,
            2e5,
        ),
        (
            "from 10 km below",
            1000.0,
            1e-8,
            [0.0, 0.0, z_ref - 10_000.0],
            [0.0, 1000.0, z_ref - 9_800.0],
            [0.0, 0.0, 1.0],
            Some(5000.0),
            z_ref - 10_300.0,
            2e5,
        ),
        (
            "straight down, thin H",
            1.0,
            1e-3,
            [0.0, 0.0, z_ref + 30.0],
            [0.0, 0.0, z_ref],
            [0.0, 1.0, 0.0],
            None,
            z_ref - 5.0,
            20.0,
        ),
    ];
    for (name, h, beta, pos, target, up, clip, zg, half) in scenes {
        let model = HeightFogModel {
            h,
            z_ref,
            beta_rs: [0.2 * beta, 0.3 * beta, 0.4 * beta],
            beta_ms: [0.5 * beta, 0.45 * beta, 0.4 * beta],
            beta_t: [1.0 * beta, 0.9 * beta, 0.85 * beta],
            mie_phase: Phase::Cs(0.76),
        };
        let json = scene_json(
            pos,
            target,
            up,
            12.0,
            [9, 7],
            clip,
            &[ground_mesh_json(zg, half)],
            &lights,
            &[model.json()],
        );
        let s = compare_render(name, &json, Some((zg, half)), &|o, d, s| model.brute(o, d, s, &lights), None);
        eprintln!("  {name}: {} comparisons, max rel {:e}", s.n, s.max_rel);
        total.merge(s);
    }
    total.finish("height fog through the renderer vs quadrature");
}

#[test]
fn fog_layer_through_renderer_matches_quadrature() {
    let mut total = Stats::default();
    let lights = Lights {
        suns: vec![
            Sun {
                to_sun: dir_deg(40.0, 60.0),
                e: [3.0, 2.8, 2.5],
            },
            Sun {
                to_sun: dir_deg(10.0, 250.0),
                e: [1.0, 0.5, 0.2],
            },
        ],
        ambient: [0.4, 0.45, 0.5],
    };
    for (name, per_point, pos, target, min_sun) in [
        ("inside, per point", true, [0.0, 0.0, 60.0], [0.0, 500.0, 40.0], 15.0),
        ("inside, full layer", false, [0.0, 0.0, 60.0], [0.0, 500.0, 40.0], 0.0),
        ("above, per point", true, [0.0, 0.0, 600.0], [0.0, 600.0, 0.0], 0.0),
        ("above, full layer", false, [0.0, 0.0, 600.0], [0.0, 600.0, 0.0], 15.0),
    ] {
        let model = FogLayerModel {
            ground: 0.0,
            top: 200.0,
            fog_ext: [0.02, 0.021, 0.019],
            air_ext: [1e-5, 2e-5, 4e-5],
            albedo: 0.95,
            phase: Phase::Hazy,
            per_point,
            min_sun_deg: min_sun,
        };
        let half = 3000.0;
        let json = scene_json(
            pos,
            target,
            [0.0, 0.0, 1.0],
            14.0,
            [9, 7],
            None,
            &[ground_mesh_json(0.0, half)],
            &lights,
            &[model.json()],
        );
        let sun = lights.suns[0].to_sun;
        let st = |p: DVec3| model.sun_t(p.z, sun);
        let s = compare_render(name, &json, Some((0.0, half)), &|o, d, s| model.brute(o, d, s, &lights), Some(&st));
        eprintln!("  {name}: {} comparisons, max rel {:e}", s.n, s.max_rel);
        total.merge(s);
    }
    total.finish("fog layer through the renderer vs quadrature");
}

#[test]
fn homogeneous_through_renderer_matches_quadrature() {
    let mut total = Stats::default();
    let lights = Lights {
        suns: vec![Sun {
            to_sun: DVec3::new(0.3, -0.5, 0.8).normalize(),
            e: [2.0, 1.8, 1.5],
        }],
        ambient: [0.05, 0.06, 0.08],
    };
    let lo = DVec3::new(-20.0, 30.0, 0.0);
    let hi = DVec3::new(20.0, 70.0, 15.0);
    let turned = Some((DVec3::new(0.2, 0.3, 1.0).normalize(), 0.6));
    for (name, bounds, k, turn) in [
        ("world", None, 0.004, None),
        ("box", Some((lo, hi)), 0.05, None),
        ("turned box", Some((lo, hi)), 0.05, turned),
    ] {
        let model = HomogeneousModel {
            sigma_s: [0.7 * k, 0.8 * k, 0.9 * k],
            sigma_t: [k, 1.0 * k, 1.1 * k],
            phase: Phase::Hg(0.4),
            bounds,
            turn,
        };
        let half = 500.0;
        let json = scene_json(
            [0.0, -10.0, 8.0],
            [0.0, 50.0, 5.0],
            [0.0, 0.0, 1.0],
            16.0,
            [11, 7],
            None,
            &[ground_mesh_json(0.0, half)],
            &lights,
            &[model.json()],
        );
        let s = compare_render(name, &json, Some((0.0, half)), &|o, d, s| model.brute(o, d, s, &lights), None);
        eprintln!("  {name}: {} comparisons, max rel {:e}", s.n, s.max_rel);
        total.merge(s);
    }
    total.finish("homogeneous through the renderer vs quadrature");
}

// ---------------------------------------------------------------- sun disc

/// The reference disc average itself, against Rayleigh's cap average in closed
/// form: ⟨1 + cos²γ⟩ = 1 + [cos²θ (1 − cos³δ)/3 + ½ sin²θ (2/3 − cos δ + cos³δ/3)] / (1 − cos δ).
#[test]
fn disc_average_reference_matches_rayleigh_by_hand() {
    let mut stats = Stats::default();
    for delta in [1e-3, 4.59e-3, 0.05, 0.5] {
        for theta in [0.0f64, 1e-3, 0.01, 0.3, 1.5, 3.0] {
            let (ct, st) = (theta.cos(), theta.sin());
            let cd = f64::cos(delta);
            let mean_cos2 = (ct * ct * (1.0 - cd.powi(3)) / 3.0 + 0.5 * st * st * (2.0 / 3.0 - cd + cd.powi(3) / 3.0)) / (1.0 - cd);
            let want = 3.0 / (16.0 * std::f64::consts::PI) * (1.0 + mean_cos2);
            let got = disc_average(Phase::Rayleigh, ct, delta);
            // (1 − cos δ) cancels for small δ: the hand formula itself holds ≈ ε/δ² relative.
            stats.check(got, want, 1e-9_f64.max(1e-15 / (delta * delta)), 0.0, || {
                format!("δ {delta} θ {theta}")
            });
        }
    }
    stats.finish("disc average vs Rayleigh by hand");
}

/// A sun of Blender's default 0.526° seen through a telephoto lens: pixels at
/// and around the disc, strongly forward-scattering media. The renderer averages
/// the phase function over the disc (tabulated to a quarter of the tolerance,
/// here 1e-9); the reference averages it by 2-D quadrature and integrates the VRE.
#[test]
fn sun_disc_through_renderer_matches_disc_averaged_quadrature() {
    let mut total = Stats::default();
    let to_sun = dir_deg(20.0, 90.0);
    let diameter_deg: f64 = 0.526;
    let radius = 0.5 * diameter_deg.to_radians();
    let e = [2.0, 1.9, 1.7];
    let ambient = [0.1, 0.1, 0.1];
    let lights_json = format!(
        r#"[{{"type":"sun","direction_to_sun":{},"color":{},"strength_w_m2":1.0,"angular_diameter_deg":{diameter_deg:?}}},
            {{"type":"ambient","color":{},"radiance":1.0}}]"#,
        arr(to_sun.to_array()),
        arr(e),
        arr(ambient)
    );
    let hf = HeightFogModel {
        h: 1200.0,
        z_ref: 0.0,
        beta_rs: [1e-5, 2e-5, 3e-5],
        beta_ms: [2e-4, 2e-4, 2e-4],
        beta_t: [2.2e-4, 2.3e-4, 2.4e-4],
        mie_phase: Phase::Cs(0.9),
    };
    let world = HomogeneousModel {
        sigma_s: [1e-3, 1.1e-3, 1.2e-3],
        sigma_t: [1.5e-3, 1.5e-3, 1.5e-3],
        phase: Phase::Hg(0.95),
        bounds: None,
        turn: None,
    };
    let eye = DVec3::new(0.0, 0.0, 10.0);
    let target = eye + to_sun * 1000.0;
    for (name, medium_json) in [("height fog", hf.json()), ("world", world.json())] {
        let json = format!(
            r#"{{"version":1,
                "camera":{{"type":"perspective","position":{},"orientation":{{"look_at":{{"target":{}}}}},
                          "focal_length_mm":1500,"resolution":[9,7],"clip_end_m":5000}},
                "lights":{lights_json},"media":[{medium_json}],
                "output":{{"tolerance":1e-9,"pixel_filter":{{"type":"none"}}}}}}"#,
            arr(eye.to_array()),
            arr(target.to_array())
        );
        let scene = Scene::from_json_str(&json, name).unwrap_or_else(|e| panic!("{name}: {e}"));
        let (img, _report) = render(&scene, None).unwrap_or_else(|e| panic!("{name}: {e}"));
        let cam = CameraRays::new(&scene.camera);
        let mut stats = Stats::default();
        let mut max_point_dev = 0.0f64;
        for row in 0..cam.height {
            for col in 0..cam.width {
                let dir = cam.direction(col as f64 + 0.5, row as f64 + 0.5);
                let mu = dir.dot(to_sun);
                let (disc, point) = match name {
                    "height fog" => {
                        let src = |pr: f64, pm: f64| -> [f64; 3] {
                            std::array::from_fn(|c| hf.beta_rs[c] * (pr * e[c] + ambient[c]) + hf.beta_ms[c] * (pm * e[c] + ambient[c]))
                        };
                        let d = src(disc_average(Phase::Rayleigh, mu, radius), disc_average(hf.mie_phase, mu, radius));
                        let p = src(Phase::Rayleigh.eval(mu), hf.mie_phase.eval(mu));
                        (hf.brute_with_source(eye, dir, 5000.0, d), hf.brute_with_source(eye, dir, 5000.0, p))
                    }
                    _ => {
                        let with_phase = |pv: f64| {
                            let m = HomogeneousModel {
                                phase: Phase::Iso,
                                ..world
                            };
                            // An isotropic medium lit by ambient A + (p/p_iso)·E scatters exactly σ_s(A + pE).
                            let l = Lights {
                                suns: vec![],
                                ambient: std::array::from_fn(|c| ambient[c] + pv * e[c]),
                            };
                            m.brute(eye, dir, 5000.0, &l)
                        };
                        (with_phase(disc_average(world.phase, mu, radius)), with_phase(world.phase.eval(mu)))
                    }
                };
                let i = row * cam.width + col;
                for c in 0..3 {
                    let got = img.inscatter[i][c] as f64;
                    stats.check(got, disc.l[c], TOL, 0.0, || {
                        format!("{name} pixel ({col},{row}) {:.3}° from the sun L[{c}]", mu.acos().to_degrees())
                    });
                    max_point_dev = max_point_dev.max(rel(point.l[c], disc.l[c]));
                }
            }
        }
        eprintln!(
            "  {name}: {} comparisons, max rel {:e}; a point sun would be off by up to {max_point_dev:e}",
            stats.n, stats.max_rel
        );
        assert!(
            max_point_dev > 1e-4,
            "{name}: the view does not resolve the disc (point vs disc {max_point_dev:e})"
        );
        total.merge(stats);
    }
    total.finish("sun disc through the renderer vs disc-averaged quadrature");
}
