//! Stiff and extreme inputs, one named test each: horizontal and vertical rays,
//! scale heights from 1 mm to 1e7 m, optical depths of 1e-9 and 1e4, cameras
//! 10 km from the reference height, suns exactly at 0° and 90°, rays tangent
//! to the fog top, eyes exactly on the fog top and ground.
//!
//! Every result must be finite, with `T ∈ [0, 1]` and `L ≥ 0`; where the exact
//! value is known it is checked: against the brute-force quadrature of
//! `common` (relative 1e-6), or against limits written out by hand
//! (single-scattering limit `L → σ_s J s` to 1e-9, saturation `L → J σ_s/σ_t`
//! to 1e-9).

// Per-channel loops index several parallel arrays (as in the library).
#![allow(clippy::needless_range_loop)]

mod common;

use common::*;
use glam::DVec3;
use tyndall_core::medium::{LightSet, PreparedMedium, RayResult, ViewRay};
use tyndall_core::{Scene, render};

const TOL: f64 = 1e-6;

/// Finite, T ∈ [0, 1], L ≥ 0, sun transmittance ∈ [0, 1], error finite and ≥ 0.
fn sane(r: &RayResult<3>, what: &str) {
    for c in 0..3 {
        assert!(
            r.inscatter[c].is_finite() && r.inscatter[c] >= 0.0,
            "{what}: L[{c}] = {}",
            r.inscatter[c]
        );
        assert!((0.0..=1.0).contains(&r.transmittance[c]), "{what}: T[{c}] = {}", r.transmittance[c]);
        assert!(
            (0.0..=1.0).contains(&r.sun_transmittance[c]),
            "{what}: T_sun[{c}] = {}",
            r.sun_transmittance[c]
        );
        assert!(r.error[c].is_finite() && r.error[c] >= 0.0, "{what}: error[{c}] = {}", r.error[c]);
    }
}

fn run(m: &PreparedMedium<3>, origin: DVec3, dir: DVec3, s_max: f64, lights: &LightSet<3>, what: &str) -> RayResult<3> {
    let r = m.closed_form(&ViewRay { origin, dir, s_max }, lights);
    sane(&r, what);
    r
}

/// Closed form vs brute force for one ray, L and T (T floor 1e-300).
fn vs_brute(stats: &mut Stats, r: &RayResult<3>, b: &Brute, what: &str) {
    let bt = b.t();
    for c in 0..3 {
        stats.check(r.inscatter[c], b.l[c], TOL, 0.0, || format!("{what} L[{c}]"));
        stats.check(r.transmittance[c], bt[c], TOL, 1e-300, || format!("{what} T[{c}]"));
    }
}

fn lights_std() -> Lights {
    Lights {
        suns: vec![
            Sun {
                to_sun: dir_deg(35.0, 70.0),
                e: [1.0, 0.9, 0.8],
            },
            Sun {
                to_sun: dir_deg(80.0, 250.0),
                e: [0.3, 0.2, 0.1],
            },
        ],
        ambient: [0.2, 0.25, 0.3],
    }
}

fn hf(h: f64, z_ref: f64, beta: f64) -> HeightFogModel {
    HeightFogModel {
        h,
        z_ref,
        beta_rs: [0.2 * beta, 0.25 * beta, 0.3 * beta],
        beta_ms: [0.6 * beta, 0.55 * beta, 0.5 * beta],
        beta_t: [beta, 0.9 * beta, 0.85 * beta],
        mie_phase: Phase::Cs(0.76),
    }
}

fn layer(per_point: bool, k: f64, min_sun_deg: f64) -> FogLayerModel {
    FogLayerModel {
        ground: 0.0,
        top: 300.0,
        fog_ext: [k, 1.02 * k, 0.98 * k],
        air_ext: [1e-3 * k, 2e-3 * k, 4e-3 * k],
        albedo: 0.97,
        phase: Phase::Hazy,
        per_point,
        min_sun_deg,
    }
}

fn horizontal_dir(wz: f64) -> DVec3 {
    DVec3::new((1.0 - wz * wz).sqrt(), 0.0, wz)
}

#[test]
fn horizontal_rays_in_height_fog() {
    let lights = lights_std();
    let mut stats = Stats::default();
    for wz in [0.0, 1e-12, -1e-12, 1e-6, -1e-6] {
        for h in [1.0, 100.0, 1e5] {
            for dz in [0.0f64, 50.0] {
                for s_max in [1000.0, 1e7, f64::INFINITY] {
                    // τ of the first kilometre ≈ 0.5 at the eye.
                    let beta = 5e-4 * (dz / h).exp();
                    let model = hf(h, 10.0, beta);
                    let m = PreparedMedium::HeightFog(model.lib());
                    let (o, d) = (DVec3::new(0.0, 0.0, 10.0 + dz), horizontal_dir(wz));
                    let what = format!("ω_z {wz:e} H {h} dz {dz} s {s_max:e}");
                    let r = run(&m, o, d, s_max, &lights.lib(), &what);
                    vs_brute(&mut stats, &r, &model.brute(o, d, s_max, &lights), &what);
                    if wz == 0.0 && s_max.is_finite() {
                        // Constant density along the ray: τ = β_t ρ(z₀) s exactly.
                        let tau = m.optical_depth(&ViewRay { origin: o, dir: d, s_max }, s_max);
                        for c in 0..3 {
                            let want = model.beta_t[c] * (-dz / h).exp() * s_max;
                            stats.check(tau[c], want, 1e-13, 0.0, || format!("{what} τ[{c}] = β ρ s"));
                        }
                    }
                }
            }
        }
    }
    stats.finish("horizontal rays, height fog");
}

#[test]
fn horizontal_rays_in_fog_layer_and_box() {
    let lights = lights_std();
    let mut stats = Stats::default();
    for wz in [0.0, 1e-12, -1e-12, 1e-6, -1e-6] {
        for per_point in [true, false] {
            for z in [150.0, 299.0, 1.0] {
                for s_max in [500.0, 1e8, f64::INFINITY] {
                    let model = layer(per_point, 2e-3, 15.0);
                    let m = PreparedMedium::FogLayer(model.lib());
                    let (o, d) = (DVec3::new(0.0, 0.0, z), horizontal_dir(wz));
                    let what = format!("layer ω_z {wz:e} z {z} per_point {per_point} s {s_max:e}");
                    let r = run(&m, o, d, s_max, &lights.lib(), &what);
                    vs_brute(&mut stats, &r, &model.brute(o, d, s_max, &lights), &what);
                }
            }
        }
        let model = HomogeneousModel {
            sigma_s: [0.02, 0.03, 0.04],
            sigma_t: [0.03, 0.04, 0.05],
            phase: Phase::Hg(0.5),
            bounds: Some((DVec3::new(-10.0, -10.0, 0.0), DVec3::new(10.0, 10.0, 5.0))),
            turn: None,
        };
        let m = PreparedMedium::Homogeneous(model.lib());
        for z in [0.0, 2.5, 5.0] {
            for s_max in [12.0, f64::INFINITY] {
                let (o, d) = (DVec3::new(-30.0, 1.0, z), horizontal_dir(wz));
                let what = format!("box ω_z {wz:e} z {z} s {s_max}");
                let r = run(&m, o, d, s_max, &lights.lib(), &what);
                vs_brute(&mut stats, &r, &model.brute(o, d, s_max, &lights), &what);
            }
        }
    }
    stats.finish("horizontal rays, fog layer and box");
}

#[test]
fn straight_up_and_straight_down() {
    let lights = lights_std();
    let mut stats = Stats::default();
    for d in [DVec3::Z, DVec3::NEG_Z] {
        for s_max in [50.0, 5000.0, f64::INFINITY] {
            for h in [1.0, 1200.0, 1e5] {
                let model = hf(h, 0.0, 1e-3);
                let m = PreparedMedium::HeightFog(model.lib());
                let o = DVec3::new(0.0, 0.0, 20.0);
                let what = format!("height fog dir {d} H {h} s {s_max}");
                let r = run(&m, o, d, s_max, &lights.lib(), &what);
                vs_brute(&mut stats, &r, &model.brute(o, d, s_max, &lights), &what);
            }
            for z in [-10.0, 0.0, 150.0, 300.0, 1000.0] {
                for per_point in [true, false] {
                    let model = layer(per_point, 0.01, 15.0);
                    let m = PreparedMedium::FogLayer(model.lib());
                    let o = DVec3::new(0.0, 0.0, z);
                    let what = format!("fog layer dir {d} z {z} per_point {per_point} s {s_max}");
                    let r = run(&m, o, d, s_max, &lights.lib(), &what);
                    vs_brute(&mut stats, &r, &model.brute(o, d, s_max, &lights), &what);
                }
            }
            for bounds in [None, Some((DVec3::new(-1.0, -2.0, -30.0), DVec3::new(3.0, 2.0, 40.0)))] {
                let model = HomogeneousModel {
                    sigma_s: [0.01, 0.02, 0.03],
                    sigma_t: [0.02, 0.025, 0.031],
                    phase: Phase::Rayleigh,
                    bounds,
                    turn: None,
                };
                let m = PreparedMedium::Homogeneous(model.lib());
                let o = DVec3::ZERO;
                let what = format!("homogeneous {bounds:?} dir {d} s {s_max}");
                let r = run(&m, o, d, s_max, &lights.lib(), &what);
                vs_brute(&mut stats, &r, &model.brute(o, d, s_max, &lights), &what);
            }
        }
    }
    stats.finish("straight up and down");
}

#[test]
fn scale_heights_from_1_mm_to_1e7_m() {
    let lights = lights_std();
    let mut stats = Stats::default();
    for h in [1e-3, 1.0, 10.0, 100.0, 1e3, 1e4, 1e5, 1e7] {
        for elev in [-90.0, -30.0, -0.01, 0.0, 0.01, 30.0, 90.0] {
            for s_max in [0.5, 1000.0, f64::INFINITY] {
                let model = hf(h, 0.0, 2e-3);
                let m = PreparedMedium::HeightFog(model.lib());
                let (o, d) = (DVec3::ZERO, dir_deg(elev, 10.0));
                let what = format!("H {h} elev {elev} s {s_max}");
                let r = run(&m, o, d, s_max, &lights.lib(), &what);
                vs_brute(&mut stats, &r, &model.brute(o, d, s_max, &lights), &what);
            }
        }
    }
    stats.finish("scale heights 1 mm … 1e7 m");
}

/// Optical depth 1e-9: `L = σ_s J s (1 − τ/2 + …)`, so L/(σ_s J s) − 1 ≈ −5e-10.
#[test]
fn optical_depth_1e_minus_9_is_the_single_scattering_limit() {
    let lights = lights_std();
    let s = 250.0;
    let tau = 1e-9;
    let check = |what: &str, r: &RayResult<3>, sigma_s_j: [f64; 3], ext: [f64; 3]| {
        sane(r, what);
        for c in 0..3 {
            let lin = sigma_s_j[c] * s;
            let rel = (r.inscatter[c] / lin - 1.0).abs();
            assert!(rel <= 1e-9, "{what}[{c}]: L = {:e}, σ_s J s = {lin:e}, rel {rel:e}", r.inscatter[c]);
            // 1 − T = τ(1 − τ/2): T itself holds only 16 digits, so 1 − T carries ≈ 1e-7 relative.
            let one_minus_t = 1.0 - r.transmittance[c];
            let tau_c = ext[c] * s;
            assert!(
                (one_minus_t / tau_c - 1.0).abs() < 1e-6,
                "{what}[{c}]: 1 − T = {one_minus_t:e}, τ = {tau_c:e}"
            );
        }
    };
    // Homogeneous world.
    let k = tau / s;
    let model = HomogeneousModel {
        sigma_s: [0.5 * k, 0.7 * k, 0.9 * k],
        sigma_t: [k, 0.95 * k, 0.9 * k],
        phase: Phase::Hg(0.3),
        bounds: None,
        turn: None,
    };
    let d = dir_deg(12.0, 40.0);
    let r = run(&PreparedMedium::Homogeneous(model.lib()), DVec3::ZERO, d, s, &lights.lib(), "world");
    let j: [f64; 3] = std::array::from_fn(|c| {
        lights.ambient[c]
            + lights
                .suns
                .iter()
                .map(|sun| Phase::Hg(0.3).eval(d.dot(sun.to_sun)) * sun.e[c])
                .sum::<f64>()
    });
    check(
        "world τ = 1e-9",
        &r,
        std::array::from_fn(|c| model.sigma_s[c] * j[c]),
        model.sigma_t,
    );
    // Height fog, horizontal ray 40 m above the reference (constant density).
    let h = 700.0;
    let rho = (-40.0f64 / h).exp();
    let model = hf(h, 0.0, tau / (s * rho));
    let d = horizontal_dir(0.0);
    let r = run(
        &PreparedMedium::HeightFog(model.lib()),
        DVec3::new(0.0, 0.0, 40.0),
        d,
        s,
        &lights.lib(),
        "height fog",
    );
    let src = model.source_ref(d, &lights).map(|v| v * rho);
    check("height fog τ = 1e-9", &r, src, model.beta_t.map(|b| b * rho));
    // Fog layer, horizontal inside: the sun path is the same at every point of the ray.
    for per_point in [true, false] {
        let model = layer(per_point, tau / s / 1.001, 15.0);
        let z = 120.0;
        let r = run(
            &PreparedMedium::FogLayer(model.lib()),
            DVec3::new(0.0, 0.0, z),
            d,
            s,
            &lights.lib(),
            "layer",
        );
        let b = model.b();
        let sig = model.sigma_s();
        let src: [f64; 3] = std::array::from_fn(|c| {
            sig[c]
                * (lights.ambient[c]
                    + lights
                        .suns
                        .iter()
                        .map(|sun| model.phase.eval(d.dot(sun.to_sun)) * sun.e[c] * (-b[c] * model.d2(z, sun.to_sun.z)).exp())
                        .sum::<f64>())
        });
        check(&format!("fog layer per_point {per_point} τ = 1e-9"), &r, src, b);
    }
}

/// Optical depth 1e4: `T` underflows (== 0 or < 1e-300), `L = J σ_s/σ_t` to 1e-9.
#[test]
fn optical_depth_1e4_saturates() {
    let lights = lights_std();
    let s = 100.0;
    let check = |what: &str, r: &RayResult<3>, sat: [f64; 3]| {
        sane(r, what);
        for c in 0..3 {
            assert!(
                r.transmittance[c] == 0.0 || r.transmittance[c] < 1e-300,
                "{what}: T = {:e}",
                r.transmittance[c]
            );
            let rel = (r.inscatter[c] / sat[c] - 1.0).abs();
            assert!(
                rel <= 1e-9,
                "{what}[{c}]: L = {:e}, saturated {:e}, rel {rel:e}",
                r.inscatter[c],
                sat[c]
            );
        }
    };
    let k = 1e4 / s;
    for s_max in [s, f64::INFINITY] {
        let model = HomogeneousModel {
            sigma_s: [0.5 * k, 0.7 * k, 0.9 * k],
            sigma_t: [k, 1.1 * k, 1.2 * k],
            phase: Phase::Murky,
            bounds: None,
            turn: None,
        };
        let d = dir_deg(-5.0, 140.0);
        let r = run(
            &PreparedMedium::Homogeneous(model.lib()),
            DVec3::ZERO,
            d,
            s_max,
            &lights.lib(),
            "world",
        );
        let sat: [f64; 3] = std::array::from_fn(|c| {
            model.sigma_s[c] / model.sigma_t[c]
                * (lights.ambient[c]
                    + lights
                        .suns
                        .iter()
                        .map(|sun| Phase::Murky.eval(d.dot(sun.to_sun)) * sun.e[c])
                        .sum::<f64>())
        });
        check(&format!("world τ = 1e4, s_max {s_max}"), &r, sat);

        let model = hf(900.0, 0.0, k);
        for d in [horizontal_dir(0.0), dir_deg(-20.0, 0.0), dir_deg(0.3, 0.0)] {
            let r = run(
                &PreparedMedium::HeightFog(model.lib()),
                DVec3::ZERO,
                d,
                s_max,
                &lights.lib(),
                "height fog",
            );
            let src = model.source_ref(d, &lights);
            check(
                &format!("height fog τ ≥ 1e4 dir {d} s_max {s_max}"),
                &r,
                std::array::from_fn(|c| src[c] / model.beta_t[c]),
            );
        }

        for per_point in [true, false] {
            let model = layer(per_point, k, 15.0);
            let (z, d) = (200.0, horizontal_dir(0.0));
            let r = run(
                &PreparedMedium::FogLayer(model.lib()),
                DVec3::new(0.0, 0.0, z),
                d,
                s_max,
                &lights.lib(),
                "layer",
            );
            let (b, sig) = (model.b(), model.sigma_s());
            let sat: [f64; 3] = std::array::from_fn(|c| {
                sig[c] / b[c]
                    * (lights.ambient[c]
                        + lights
                            .suns
                            .iter()
                            .map(|sun| model.phase.eval(d.dot(sun.to_sun)) * sun.e[c] * (-b[c] * model.d2(z, sun.to_sun.z)).exp())
                            .sum::<f64>())
            });
            check(&format!("fog layer τ = 1e4 per_point {per_point} s_max {s_max}"), &r, sat);
        }
    }
}

#[test]
fn camera_10_km_above_and_below_the_reference_height() {
    let lights = lights_std();
    let mut stats = Stats::default();
    let z_ref = 100.0;
    for dz in [10_000.0, -10_000.0] {
        for h in [1.0, 100.0, 1200.0, 8000.0] {
            for elev in [-90.0, -30.0, -1.0, -0.01, 0.0, 0.01, 1.0, 30.0, 90.0] {
                for s_max in [1000.0, f64::INFINITY] {
                    let o = DVec3::new(0.0, 0.0, z_ref + dz);
                    let d = dir_deg(elev, 0.0);
                    // β so that the density at the eye gives τ ≈ 1 per km where that is representable.
                    let beta = (1e-3f64.ln() + dz / h).exp().clamp(1e-30, 1e3);
                    let model = hf(h, z_ref, beta);
                    let m = PreparedMedium::HeightFog(model.lib());
                    let what = format!("dz {dz} H {h} elev {elev} s {s_max}");
                    let r = run(&m, o, d, s_max, &lights.lib(), &what);
                    let src = model.source_ref(d, &lights);
                    let sat: [f64; 3] = std::array::from_fn(|c| src[c] / model.beta_t[c]);
                    let ln_rho0 = -dz / h;
                    if ln_rho0 + beta.ln() < -700.0 {
                        // No fog to speak of at the eye (e^-10000): only an infinite ray that
                        // does not climb has infinite optical depth, and then it saturates.
                        if d.z <= 0.0 && s_max.is_infinite() {
                            for c in 0..3 {
                                assert!(r.transmittance[c] < 1e-300, "{what}: T = {:e}", r.transmittance[c]);
                                stats.check(r.inscatter[c], sat[c], 1e-9, 0.0, || format!("{what} saturated L[{c}]"));
                            }
                        } else if d.z * s_max.min(1e4) > -5000.0 {
                            for c in 0..3 {
                                assert_eq!(r.transmittance[c], 1.0, "{what}");
                                assert!(r.inscatter[c] < 1e-300, "{what}: L = {:e}", r.inscatter[c]);
                            }
                        }
                    } else if ln_rho0 + beta.ln() > 700.0 {
                        // Infinitely dense at the eye (e^+10000): saturated at once.
                        for c in 0..3 {
                            assert!(r.transmittance[c] < 1e-300, "{what}: T = {:e}", r.transmittance[c]);
                            stats.check(r.inscatter[c], sat[c], 1e-9, 0.0, || format!("{what} saturated L[{c}]"));
                        }
                    } else {
                        vs_brute(&mut stats, &r, &model.brute(o, d, s_max, &lights), &what);
                    }
                }
            }
        }
    }
    stats.finish("camera 10 km from the reference height");
}

#[test]
fn sun_exactly_at_0_and_90_degrees() {
    let mut stats = Stats::default();
    let ambient = [0.2, 0.3, 0.4];
    for to_sun in [DVec3::X, DVec3::Z, DVec3::new(0.0, -1.0, 0.0)] {
        let lights = Lights {
            suns: vec![Sun {
                to_sun,
                e: [1.0, 1.1, 1.2],
            }],
            ambient,
        };
        for elev in [-60.0, -1.0, 0.0, 1.0, 60.0, 90.0] {
            let d = dir_deg(elev, 30.0);
            let model = hf(500.0, 0.0, 1e-3);
            let what = format!("height fog sun {to_sun} elev {elev}");
            let r = run(
                &PreparedMedium::HeightFog(model.lib()),
                DVec3::ZERO,
                d,
                3000.0,
                &lights.lib(),
                &what,
            );
            vs_brute(&mut stats, &r, &model.brute(DVec3::ZERO, d, 3000.0, &lights), &what);
            for bounds in [None, Some((DVec3::new(-100.0, -100.0, -50.0), DVec3::new(100.0, 100.0, 50.0)))] {
                let model = HomogeneousModel {
                    sigma_s: [0.01, 0.012, 0.014],
                    sigma_t: [0.02, 0.02, 0.02],
                    phase: Phase::Hg(0.7),
                    bounds,
                    turn: None,
                };
                let what = format!("homogeneous {bounds:?} sun {to_sun} elev {elev}");
                let r = run(
                    &PreparedMedium::Homogeneous(model.lib()),
                    DVec3::ZERO,
                    d,
                    3000.0,
                    &lights.lib(),
                    &what,
                );
                vs_brute(&mut stats, &r, &model.brute(DVec3::ZERO, d, 3000.0, &lights), &what);
            }
            for per_point in [true, false] {
                for min_sun in [0.0, 15.0] {
                    let model = layer(per_point, 0.01, min_sun);
                    let m = PreparedMedium::FogLayer(model.lib());
                    let o = DVec3::new(0.0, 0.0, 100.0);
                    let what = format!("fog layer sun {to_sun} elev {elev} per_point {per_point} min {min_sun}");
                    let r = run(&m, o, d, f64::INFINITY, &lights.lib(), &what);
                    vs_brute(&mut stats, &r, &model.brute(o, d, f64::INFINITY, &lights), &what);
                    if to_sun.z == 0.0 {
                        // Sun on the horizon: no direct term at all, whatever min_sun_elevation_deg.
                        let ambient_only = m.closed_form(
                            &ViewRay {
                                origin: o,
                                dir: d,
                                s_max: f64::INFINITY,
                            },
                            &Lights { suns: vec![], ambient }.lib(),
                        );
                        assert_eq!(r.inscatter, ambient_only.inscatter, "{what}: sun at 0° adds nothing");
                    }
                }
            }
        }
    }
    // A sun a hair above the horizon with min elevation 0: the direct term is the
    // sunlit skin of the fog top only; finite and between the ambient-only value and
    // the unattenuated bound.
    for to_sun_z in [1e-12, 1e-300, 5e-324] {
        let to_sun = DVec3::new((1.0f64 - to_sun_z * to_sun_z).sqrt(), 0.0, to_sun_z);
        let lights = Lights {
            suns: vec![Sun { to_sun, e: [1.0; 3] }],
            ambient,
        };
        for per_point in [true, false] {
            let model = layer(per_point, 0.01, 0.0);
            let m = PreparedMedium::FogLayer(model.lib());
            for (z, elev) in [
                (100.0, 30.0),
                (100.0, -30.0),
                (100.0, 0.0),
                (300.0, 0.0),
                (300.0, -10.0),
                (500.0, -10.0),
            ] {
                let (o, d) = (DVec3::new(0.0, 0.0, z), dir_deg(elev, 0.0));
                let what = format!("sun z {to_sun_z:e} per_point {per_point} z {z} elev {elev}");
                let ray = ViewRay {
                    origin: o,
                    dir: d,
                    s_max: f64::INFINITY,
                };
                let r = m.closed_form(&ray, &lights.lib());
                sane(&r, &what);
                let amb = m.closed_form(&ray, &Lights { suns: vec![], ambient }.lib());
                let b = model.b();
                let sig = model.sigma_s();
                for c in 0..3 {
                    let upper = amb.inscatter[c] + sig[c] * model.phase.eval(d.dot(to_sun)) / b[c];
                    assert!(
                        r.inscatter[c] >= amb.inscatter[c] * (1.0 - 1e-15) && r.inscatter[c] <= upper * (1.0 + 1e-12),
                        "{what}: L = {:e} outside [{:e}, {upper:e}]",
                        r.inscatter[c],
                        amb.inscatter[c]
                    );
                }
            }
        }
    }
    stats.finish("sun at 0° and 90°");
}

/// A horizontal ray exactly at the fog top (ω_z = 0, z = top) lies on the
/// boundary. It must be finite and equal one of the two one-sided limits; the
/// library counts the boundary as inside, so the limit from below.
#[test]
fn ray_tangent_to_the_fog_top() {
    let lights = lights_std();
    let mut stats = Stats::default();
    for per_point in [true, false] {
        let model = layer(per_point, 0.01, 15.0);
        let m = PreparedMedium::FogLayer(model.lib());
        for s_max in [800.0, f64::INFINITY] {
            let d = horizontal_dir(0.0);
            let at_top = run(&m, DVec3::new(0.0, 0.0, 300.0), d, s_max, &lights.lib(), "at top");
            let below = run(&m, DVec3::new(0.0, 0.0, 300.0 - 1e-9), d, s_max, &lights.lib(), "just below");
            let above = run(&m, DVec3::new(0.0, 0.0, 300.0 + 1e-9), d, s_max, &lights.lib(), "just above");
            for c in 0..3 {
                assert_eq!(above.inscatter[c], 0.0);
                assert_eq!(above.transmittance[c], 1.0);
                stats.check(at_top.inscatter[c], below.inscatter[c], TOL, 0.0, || {
                    format!("per_point {per_point} s {s_max}: tangent L[{c}] vs limit from below")
                });
                stats.check(at_top.transmittance[c], below.transmittance[c], TOL, 1e-300, || {
                    format!("per_point {per_point} s {s_max}: tangent T[{c}] vs limit from below")
                });
            }
            // By hand: at z = top the per-point sun path is 0 (full layer: the whole thickness).
            let (b, sig) = (model.b(), model.sigma_s());
            for c in 0..3 {
                let j = lights.ambient[c]
                    + lights
                        .suns
                        .iter()
                        .map(|sun| model.phase.eval(d.dot(sun.to_sun)) * sun.e[c] * (-b[c] * model.d2(300.0, sun.to_sun.z)).exp())
                        .sum::<f64>();
                let want = sig[c] * j / b[c] * -(-b[c] * s_max).exp_m1();
                stats.check(at_top.inscatter[c], want, 1e-12, 0.0, || {
                    format!("per_point {per_point} s {s_max}: tangent L[{c}] by hand")
                });
            }
            // Grazing rays leaving the top and entering it.
            for wz in [1e-12, -1e-12] {
                let what = format!("per_point {per_point} s {s_max} ω_z {wz:e} at top");
                let o = DVec3::new(0.0, 0.0, 300.0);
                let r = run(&m, o, horizontal_dir(wz), s_max, &lights.lib(), &what);
                vs_brute(&mut stats, &r, &model.brute(o, horizontal_dir(wz), s_max, &lights), &what);
            }
        }
    }
    stats.finish("ray tangent to the fog top");
}

#[test]
fn eye_exactly_on_the_fog_top_and_ground() {
    let lights = lights_std();
    let mut stats = Stats::default();
    for per_point in [true, false] {
        let model = layer(per_point, 0.02, 15.0);
        let m = PreparedMedium::FogLayer(model.lib());
        for z in [0.0, 300.0] {
            for elev in [-90.0, -30.0, -0.01, 0.0, 0.01, 30.0, 90.0] {
                for s_max in [100.0, f64::INFINITY] {
                    let (o, d) = (DVec3::new(5.0, 5.0, z), dir_deg(elev, 80.0));
                    let what = format!("per_point {per_point} eye z {z} elev {elev} s {s_max}");
                    let r = run(&m, o, d, s_max, &lights.lib(), &what);
                    vs_brute(&mut stats, &r, &model.brute(o, d, s_max, &lights), &what);
                    let leaving = (z == 300.0 && elev > 0.0) || (z == 0.0 && elev < 0.0);
                    if leaving {
                        assert_eq!(r.inscatter, [0.0; 3], "{what}: looking out of the fog from its boundary");
                        assert_eq!(r.transmittance, [1.0; 3], "{what}");
                    }
                }
            }
        }
    }
    stats.finish("eye on the fog top and ground");
}

// ---------------------------------------------------------------- through the renderer

fn check_images(name: &str, json: &str) {
    let scene = Scene::from_json_str(json, name).unwrap_or_else(|e| panic!("{name}: {e}"));
    let (img, report) = render(&scene, None).unwrap_or_else(|e| panic!("{name}: {e}"));
    let n = img.width * img.height;
    assert_eq!(img.inscatter.len(), n);
    for i in 0..n {
        for c in 0..3 {
            // Layers not requested are empty.
            let l = img.inscatter[i][c];
            let t = img.transmittance.get(i).map_or(1.0, |t| t[c]);
            assert!(l.is_finite() && l >= 0.0, "{name}: pixel {i} L[{c}] = {l}");
            assert!((0.0..=1.0).contains(&t), "{name}: pixel {i} T[{c}] = {t}");
            if !img.sun_transmittance.is_empty() {
                let st = img.sun_transmittance[i][c];
                assert!((0.0..=1.0).contains(&st), "{name}: pixel {i} T_sun[{c}] = {st}");
            }
            if !img.error.is_empty() {
                let e = img.error[i][c];
                assert!(e.is_finite() && e >= 0.0, "{name}: pixel {i} error[{c}] = {e}");
            }
        }
        if let Some(&d) = img.depth.get(i) {
            assert!(d > 0.0 && d.is_finite(), "{name}: pixel {i} depth {d}");
        }
    }
    assert!(
        report.error.max_abs.is_finite() && report.error.max_rel.is_finite(),
        "{name}: {:?}",
        report.error
    );
}

fn scene(position: [f64; 3], target: [f64; 3], up: [f64; 3], res: [u32; 2], lights: &str, media: &str, meshes: &str) -> String {
    format!(
        r#"{{"version":1,
            "camera":{{"type":"perspective","position":{},"orientation":{{"look_at":{{"target":{},"up":{}}}}},
                      "focal_length_mm":20,"resolution":[{},{}]}},
            "meshes":[{meshes}],"lights":{lights},"media":[{media}],
            "output":{{"layers":["inscatter","transmittance","depth","sun_transmittance","error"]}}}}"#,
        arr(position),
        arr(target),
        arr(up),
        res[0],
        res[1]
    )
}

#[test]
fn extreme_scenes_render_finite_images() {
    let sun0 = r#"[{"type":"sun","direction_to_sun":[1,0,0],"strength_w_m2":5},{"type":"ambient","radiance":0.3}]"#;
    let sun90 = r#"[{"type":"sun","direction_to_sun":[0,0,1],"strength_w_m2":5},{"type":"ambient","radiance":0.3}]"#;
    let ground = ground_mesh_json(0.0, 1e4);
    // 11 rows: the centre row looks exactly horizontally.
    let res = [13, 11];
    for lights in [sun0, sun90] {
        for (name, pos, target, media, meshes) in [
            (
                "eye on the fog top, tangent centre row",
                [0.0, 0.0, 300.0],
                [0.0, 100.0, 300.0],
                layer(true, 0.02, 0.0).json(),
                String::new(),
            ),
            (
                "eye on the fog ground, full layer",
                [0.0, 0.0, 0.0],
                [0.0, 100.0, 0.0],
                layer(false, 0.02, 15.0).json(),
                String::new(),
            ),
            (
                "H = 1 m, 10 km above",
                [0.0, 0.0, 10_000.0],
                [0.0, 100.0, 10_000.0],
                hf(1.0, 0.0, 1e-3).json(),
                ground.clone(),
            ),
            (
                "H = 1 m, 10 km below",
                [0.0, 0.0, -10_000.0],
                [0.0, 100.0, -10_000.0],
                hf(1.0, 0.0, 1e-3).json(),
                String::new(),
            ),
            (
                "H = 1 mm at the reference",
                [0.0, 0.0, 0.0],
                [0.0, 100.0, 0.0],
                hf(1e-3, 0.0, 1e-3).json(),
                String::new(),
            ),
            (
                "H = 1e7 m",
                [0.0, 0.0, 50.0],
                [0.0, 100.0, 0.0],
                hf(1e7, 0.0, 1e-4).json(),
                ground.clone(),
            ),
            (
                "τ = 1e-9 world",
                [0.0, 0.0, 50.0],
                [0.0, 100.0, 0.0],
                r#"{"type":"homogeneous","scattering":1e-12,"absorption":1e-12}"#.into(),
                ground.clone(),
            ),
            (
                "τ = 1e4 world",
                [0.0, 0.0, 50.0],
                [0.0, 100.0, 0.0],
                r#"{"type":"homogeneous","scattering":50,"absorption":50}"#.into(),
                ground.clone(),
            ),
            (
                "straight down",
                [0.0, 0.0, 50.0],
                [0.0, 0.0, 0.0],
                hf(100.0, 0.0, 1e-3).json(),
                ground.clone(),
            ),
        ] {
            let up = if name == "straight down" {
                [0.0, 1.0, 0.0]
            } else {
                [0.0, 0.0, 1.0]
            };
            check_images(name, &scene(pos, target, up, res, lights, &media, &meshes));
        }
    }
}

// ---------------------------------------------------------------- known bug

/// Two overlapping media, one of them a height fog, on a view ray that reaches
/// heights where the fog's density `exp(−(z − z_ref)/H)` overflows: the
/// renderer's numeric path multiplies the source `σ_s·ρ = ∞` by
/// `exp(−τ) = exp(−∞) = 0` and gets NaN. Any descending view ray without a
/// surface reaches such heights (the infinite tail is integrated to s → ∞),
/// so the whole lower half of an ordinary view is NaN, and the report's
/// error estimate stays 0 (the NaN is dropped by `f64::max`).
#[test]
fn overlapping_media_with_a_height_fog_stay_finite_looking_down() {
    let json = r#"{"version":1,
        "camera":{"type":"perspective","position":[0,0,100],"orientation":{"look_at":{"target":[0,100,-100]}},"resolution":[4,3]},
        "lights":[{"type":"sun","direction_to_sun":[0,0,1]},{"type":"ambient"}],
        "media":[{"type":"height_fog","scale_height_m":1200,"mie":{"scattering":0.0001}},
                 {"type":"homogeneous","scattering":0.0001}],
        "output":{"layers":["inscatter","transmittance","error"],"pixel_filter":{"type":"none"}}}"#;
    check_images("height fog + world haze, looking down", json);
    // Eye 1 km below the reference of an H = 1 m fog: infinitely dense at the eye,
    // so L is the height fog's saturated value J σ_s/σ_t = p_CS(0)·1 + 1.
    let json = r#"{"version":1,
        "camera":{"type":"perspective","position":[0,0,-1000],"orientation":{"look_at":{"target":[0,100,-1000]}},"resolution":[5,3]},
        "lights":[{"type":"sun","direction_to_sun":[0,0,1]},{"type":"ambient"}],
        "media":[{"type":"height_fog","scale_height_m":1,"mie":{"scattering":0.01}},{"type":"homogeneous","scattering":0.001}],
        "output":{"layers":["inscatter","transmittance","error"],"pixel_filter":{"type":"none"}}}"#;
    check_images("eye in overflowing height fog + world haze", json);
    let scene = Scene::from_json_str(json, "bug").unwrap();
    let (img, _) = render(&scene, None).unwrap();
    let want = Phase::Cs(0.76).eval(0.0) + 1.0;
    let l = img.inscatter[7][0] as f64;
    assert!((l / want - 1.0).abs() < 1e-3, "centre pixel L = {l}, saturated value {want}");
}

/// An eye far below a height fog's reference height (its density overflows
/// f64 there) with a second medium on the ray, and a fog that does not dim
/// the green and blue channels: in red the fog is opaque at the eye and its
/// saturated value is the whole answer; in green and blue the fog is absent,
/// so the image there is the haze's alone, as if the fog were not in the
/// scene. (Tracing once returned the fog's closed form in every channel and
/// dropped the haze.)
#[test]
fn an_overflowing_fog_that_leaves_channels_clear_keeps_the_other_media_in_them() {
    let scene_with = |media: &str| {
        format!(
            r#"{{"version":1,
        "camera":{{"type":"perspective","position":[0,0,-1000],"orientation":{{"look_at":{{"target":[0,100,-1000]}}}},"resolution":[5,3]}},
        "lights":[{{"type":"sun","direction_to_sun":[0,0.3,1]}},{{"type":"ambient"}}],
        "media":[{media}],
        "output":{{"layers":["inscatter","transmittance","error"],"pixel_filter":{{"type":"none"}}}}}}"#
        )
    };
    let haze = r#"{"type":"homogeneous","scattering":0.001,"absorption":0.0005}"#;
    let fog = r#"{"type":"height_fog","scale_height_m":1,"mie":{"scattering":[0.01,0,0]}}"#;
    let both = scene_with(&format!("{fog},{haze}"));
    check_images("eye in overflowing red-only fog + haze", &both);
    let (img, _) = render(&Scene::from_json_str(&both, "both").unwrap(), None).unwrap();
    let (alone, _) = render(&Scene::from_json_str(&scene_with(haze), "haze").unwrap(), None).unwrap();
    let saturated = Phase::Cs(0.76).eval(0.3 / 1.09f64.sqrt()) + 1.0;
    for i in 0..img.inscatter.len() {
        for c in 1..3 {
            let (l, want) = (img.inscatter[i][c] as f64, alone.inscatter[i][c] as f64);
            assert!(
                want > 0.0 && (l / want - 1.0).abs() < 1e-6,
                "pixel {i} channel {c}: L = {l}, the haze alone {want}"
            );
            let (t, t_want) = (img.transmittance[i][c], alone.transmittance[i][c]);
            assert_eq!(t, t_want, "pixel {i} channel {c}: T");
        }
        assert_eq!(img.transmittance[i][0], 0.0, "pixel {i}: the fog is opaque in red");
    }
    // The centre pixel looks along +y: the sun is at μ = 0.3/√1.09 from the view direction.
    let l = img.inscatter[7][0] as f64;
    assert!(
        (l / saturated - 1.0).abs() < 1e-3,
        "centre pixel L = {l}, saturated value {saturated}"
    );
}

/// The same eye just above and just below the depth where the height fog's
/// saturated closed form takes over (σ_t = 1e20 m⁻¹, 50.66 scale heights
/// below its reference; it once was where the density overflows, 700):
/// above, the ray is integrated. Both must see the sun dimmed by the fog
/// layer around the eye (the closed form once took the sun undimmed: a
/// 1.1 % jump).
#[test]
fn the_saturated_fog_sees_the_sun_dimmed_by_the_other_media() {
    let centre = |z: f64| {
        let json = format!(
            r#"{{"version":1,
            "camera":{{"type":"perspective","position":[0,0,{z}],"orientation":{{"look_at":{{"target":[0,100,{z}]}}}},"resolution":[5,3]}},
            "lights":[{{"type":"sun","direction_to_sun":[0,0.3,1]}},{{"type":"ambient"}}],
            "media":[{{"type":"height_fog","scale_height_m":1,"mie":{{"scattering":0.01}}}},
                     {{"type":"fog_layer","ground_height_m":-2000,"top_height_m":0,"extinction":0.01,"min_sun_elevation_deg":0}}],
            "output":{{"layers":["inscatter","transmittance","error"],"pixel_filter":{{"type":"none"}}}}}}"#
        );
        check_images(&format!("eye at z = {z}"), &json);
        let (img, _) = render(&Scene::from_json_str(&json, "z").unwrap(), None).unwrap();
        img.inscatter[7][0] as f64
    };
    let (above, below) = (centre(-50.5), centre(-50.8));
    assert!((below / above - 1.0).abs() < 1e-4, "integrated {above}, saturated {below}");
}

/// Two height fogs opaque at once at the eye (their densities overflow f64
/// there): the ray's value is each fog's saturated closed form weighted by
/// its share of the extinction at the eye,
/// `L = Σ σ_t,i L_i / Σ σ_t,i` with `L_i = J σ_s,i/σ_t,i`. A fog `e^{50}`
/// times denser than the other is the whole answer, whichever comes first
/// in the scene (the first in scene order once won); two fogs of equal
/// density and different albedo mix, and the value is the same where the
/// ray is integrated, short of the extinction (1e20 m⁻¹) at which the closed
/// form takes over.
#[test]
fn two_overflowing_fogs_share_the_saturated_value_by_their_extinction() {
    let centre = |z: f64, media: &str| {
        let (l, t, _) = centre_pixel(z, media, "");
        assert_eq!(t, [0.0; 3], "{media}: opaque at the eye");
        l
    };
    // The sun is at μ = 0.3/√1.09 from the centre pixel's view direction.
    let mie = Phase::Cs(0.76).eval(0.3 / 1.09f64.sqrt()) + 1.0;
    let ray = Phase::Rayleigh.eval(0.3 / 1.09f64.sqrt()) + 1.0;
    // A: Mie, albedo 1 (L = p_CS + 1); B: Rayleigh, albedo ½ (L = (p_R + 1)/2).
    let fog_a =
        |z_ref: f64| format!(r#"{{"type":"height_fog","scale_height_m":1,"reference_height_m":{z_ref},"mie":{{"scattering":0.01}}}}"#);
    let fog_b = |z_ref: f64| {
        format!(
            r#"{{"type":"height_fog","scale_height_m":1,"reference_height_m":{z_ref},"rayleigh":{{"scattering":0.01,"absorption":0.01}}}}"#
        )
    };
    let close = |l: [f64; 3], want: f64, what: &str| {
        for c in 0..3 {
            assert!((l[c] / want - 1.0).abs() < 1e-4, "{what}: L[{c}] = {}, want {want}", l[c]);
        }
    };
    // B's reference 50 m lower: A is e^{50} times denser at the eye.
    let a_b = centre(-1000.0, &format!("{},{}", fog_a(0.0), fog_b(-50.0)));
    let b_a = centre(-1000.0, &format!("{},{}", fog_b(-50.0), fog_a(0.0)));
    close(a_b, mie, "A denser, A first");
    close(b_a, mie, "A denser, B first");
    // And the other way round: B denser, whichever comes first.
    close(
        centre(-1000.0, &format!("{},{}", fog_a(-50.0), fog_b(0.0))),
        ray / 2.0,
        "B denser, A first",
    );
    // Equal densities: σ_t,A = 0.01·e^d, σ_t,B = 0.02·e^d, d scale heights
    // down. The closed form takes over where a fog's σ_t passes 1e20 m⁻¹ (B
    // at d = 49.96, A at 50.66); above, the ray is integrated.
    let mixed = (0.01 * mie + 0.02 * ray / 2.0) / 0.03;
    let both = format!("{},{}", fog_a(0.0), fog_b(0.0));
    for d in [45.0, 49.9, 50.3, 51.0, 700.1] {
        close(centre(-d, &both), mixed, &format!("equal densities, {d} scale heights down"));
    }
}

/// The centre pixel (looking along +y from height `z`, the sun at
/// μ = 0.3/√1.09 from the view direction, ambient 1) of a scene with these
/// media and meshes: in-scatter, transmittance, error estimate.
fn centre_pixel(z: f64, media: &str, meshes: &str) -> ([f64; 3], [f32; 3], [f32; 3]) {
    let json = format!(
        r#"{{"version":1,
        "camera":{{"type":"perspective","position":[0,0,{z}],"orientation":{{"look_at":{{"target":[0,100,{z}]}}}},"resolution":[5,3]}},
        "lights":[{{"type":"sun","direction_to_sun":[0,0.3,1]}},{{"type":"ambient"}}],
        "media":[{media}],"meshes":[{meshes}],
        "output":{{"layers":["inscatter","transmittance","error"],"pixel_filter":{{"type":"none"}}}}}}"#
    );
    check_images(&format!("eye at z = {z} in {media}"), &json);
    let (img, _) = render(&Scene::from_json_str(&json, "z").unwrap(), None).unwrap();
    (img.inscatter[7].map(f64::from), img.transmittance[7], img.error[7])
}

/// A fog dense at the eye (σ_t = 0.01·e^{d} m⁻¹, d scale heights below its
/// reference: 2e2 … 1e24 m⁻¹) with a haze box around the eye: the in-scatter
/// comes from the first 1/σ_t of the ray, where the fog outweighs the box,
/// so it is the fog's saturated value with the sun dimmed by the box on its
/// way down to the eye, `1 + p_CS(μ)·e^{−0.05·d·√1.09}`, on both sides of
/// the 1e20 m⁻¹ at which the closed form takes over. The numeric path once
/// gave 0 with an estimate of 0 from d = 15 (σ_t = 3e4; the box's face cut
/// the ray, and every node of the first piece lay past the boundary layer).
/// A red-only fog in a thin haze: green and blue are the haze's alone at any
/// depth (they were 1.8e-40, then 0, from 100 m down: the tail's scale was
/// the red fog's). A second fog 0.2 scale heights shallower takes its share
/// of the saturated value whether or not it has crossed the threshold (it
/// once jumped by 42 % between the two). And an eye so deep that the log
/// density itself is ∞ (z = −1e306, H = 1 mm) is the fog's saturated value,
/// not NaN.
#[test]
fn a_fog_dense_at_the_eye_matches_its_saturated_value_beside_other_media() {
    let mu = 0.3 / 1.09f64.sqrt();
    let mie = Phase::Cs(0.76).eval(mu);
    let ray = Phase::Rayleigh.eval(mu) + 1.0;
    let fog = r#"{"type":"height_fog","scale_height_m":1,"mie":{"scattering":0.01}}"#;
    let haze_box = r#"{"type":"homogeneous","scattering":0.05,"bounds":{"box":{"min":[-100,-100,-200],"max":[100,100,0]}}}"#;
    for d in [10.0, 15.0, 20.0, 30.0, 45.0, 50.0, 60.0] {
        let (l, t, _) = centre_pixel(-d, &format!("{fog},{haze_box}"), "");
        let want = 1.0 + mie * (-0.05 * d * 1.09f64.sqrt()).exp();
        for c in 0..3 {
            assert!((l[c] / want - 1.0).abs() < 1e-4, "d = {d}: L[{c}] = {}, want {want}", l[c]);
            assert_eq!(t[c], 0.0, "d = {d}");
        }
    }
    let red_fog = r#"{"type":"height_fog","scale_height_m":1,"mie":{"scattering":[0.01,0,0]}}"#;
    let haze = r#"{"type":"homogeneous","scattering":0.001}"#;
    for d in [30.0, 40.0, 100.0, 600.0, 800.0] {
        let (l, _, _) = centre_pixel(-d, &format!("{red_fog},{haze}"), "");
        let (alone, _, _) = centre_pixel(-d, haze, "");
        assert!((l[0] / (1.0 + mie) - 1.0).abs() < 1e-4, "d = {d}: red {}", l[0]);
        for c in 1..3 {
            assert!(
                (l[c] / alone[c] - 1.0).abs() < 1e-5,
                "d = {d}: L[{c}] = {}, haze alone {}",
                l[c],
                alone[c]
            );
        }
    }
    let shallower =
        r#"{"type":"height_fog","scale_height_m":1,"reference_height_m":-0.2,"rayleigh":{"scattering":0.01,"absorption":0.01}}"#;
    let (wa, wb) = (0.01, 0.02 * (-0.2f64).exp());
    let mixed = (wa * (1.0 + mie) + wb * ray / 2.0) / (wa + wb);
    for z in [-699.9, -700.1, -700.3, -1000.0] {
        let (l, _, _) = centre_pixel(z, &format!("{fog},{shallower}"), "");
        assert!((l[0] / mixed - 1.0).abs() < 1e-4, "z = {z}: L = {}, want {mixed}", l[0]);
    }
    let thin_fog = r#"{"type":"height_fog","scale_height_m":0.001,"mie":{"scattering":0.01}}"#;
    let (l, t, _) = centre_pixel(-1e306, &format!("{thin_fog},{haze}"), "");
    assert!(
        (l[0] / (1.0 + mie) - 1.0).abs() < 1e-4 && t[0] == 0.0,
        "z = -1e306: L = {l:?}, T = {t:?}"
    );
}

/// A height fog seen upwards with a haze box, both thin (optical depths near
/// 1e-5 and 1e-7): in that limit the two media's in-scatter adds up, so the
/// numeric path must equal the sum of each medium's closed form alone to
/// O(τ). The infinite tail was mapped with the extinction's scale (1e5 m and
/// more), and every node lay beyond the fog's light, which dies out over
/// H/d_z ≈ 600 m: 16 % dark, with an estimate of 2e-7.
#[test]
fn thin_height_fog_with_a_thin_box_adds_up() {
    let fog = r#"{"type":"height_fog","scale_height_m":10,"mie":{"scattering":1e-7,"phase":{"type":"cornette_shanks","g":0.76}}}"#;
    let haze = r#"{"type":"homogeneous","scattering":5e-6,"phase":{"type":"henyey_greenstein","g":0.5},
        "bounds":{"box":{"min":[-10,-10,0],"max":[10,50,5]}}}"#;
    let one_pixel = |media: &str| {
        let json = format!(
            r#"{{"version":1,
            "camera":{{"type":"perspective","position":[0,-30,1],"orientation":{{"look_at":{{"target":[0,0,1.5]}}}},"resolution":[1,1]}},
            "lights":[{{"type":"sun","direction_to_sun":[0.3,1,0.4],"color":[1,0.5,0.25],"strength_w_m2":3,"angular_diameter_deg":0}},
                      {{"type":"ambient","color":[0.25,0.5,1],"radiance":0.3}}],
            "media":[{media}],
            "output":{{"layers":["inscatter","error"],"tolerance":1e-4,"pixel_filter":{{"type":"none"}},"spectral":"never"}}}}"#
        );
        let (img, _) = render(&Scene::from_json_str(&json, "thin").unwrap(), None).unwrap();
        (img.inscatter[0].map(f64::from), img.error[0].map(f64::from))
    };
    let (both, error) = one_pixel(&format!("{fog},{haze}"));
    let (fog_alone, _) = one_pixel(fog);
    let (haze_alone, _) = one_pixel(haze);
    for c in 0..3 {
        let sum = fog_alone[c] + haze_alone[c];
        let off = (both[c] - sum).abs() / sum;
        assert!(
            off < 1e-4,
            "channel {c}: both {} against {sum} ({off:.2e} off), estimate {}",
            both[c],
            error[c]
        );
    }
}
