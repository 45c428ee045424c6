//! The pixel filter across beams from their angular profiles (`render::profile`)
//! against the lattice filter of exact view rays at a tight tolerance (and,
//! for a beam about a pixel wide, which the lattice does not resolve,
//! against Blender's window applied to 16 × 16 point samples per pixel): the
//! filtered values agree, and every profile-filtered pixel's error is within
//! its estimate, on the stiff cases the model meets — a 0.5° beam narrower
//! than a pixel, a 60° cone in dense haze, two crossing coloured spots, a
//! forward-scattering lobe, a light whose medium is not dimmed (Cast Shadow
//! off), a beam cut by the floor, and a box's shadow in a beam.

use tyndall_core::{Images, Report, Scene, render};

/// Renders `json` (its `output` replaced) at `tolerance` with the profile
/// filter, and with the lattice alone: the pixels that differ are the profile's.
fn with_and_without(json: &mut serde_json::Value, tolerance: f64) -> (Scene, Images, Report, Images) {
    json["output"] = serde_json::json!({"layers": ["inscatter", "error"], "tolerance": tolerance, "spectral": "never"});
    let scene = Scene::from_json_str(&json.to_string(), "<t>").unwrap();
    let (img, report) = render(&scene, None).unwrap();
    let mut lattice = scene.clone();
    lattice.output.profile_filter = false;
    let (plain, _) = render(&lattice, None).unwrap();
    (scene, img, report, plain)
}

/// Renders `json` (a scene without `output`) with the profile filter at
/// `tolerance`, with the lattice alone at the same tolerance (the pixels
/// that differ are the profile's), and with the lattice alone at 1e-6;
/// returns the pixels the profile served, the worst ratio of true error to
/// estimate among the profile's pixels, and the relative RMSE of the image.
fn compare(name: &str, mut json: serde_json::Value, tolerance: f64) -> (u64, f64, f64) {
    let (scene, img, report, plain) = with_and_without(&mut json, tolerance);
    let mut reference = scene.clone();
    reference.output.tolerance = 1e-6;
    reference.output.profile_filter = false;
    let (exact, exact_report) = render(&reference, None).unwrap();
    assert_eq!(exact_report.stats.pixels_profile_filtered, 0);
    let served = report.stats.pixels_profile_filtered;
    let w = 64usize;
    let (mut worst, mut over, mut sq, mut norm, mut lattice_over) = (0.0f64, 0usize, 0.0f64, 0.0f64, 0usize);
    for (i, ((got, want), (e, e_ref))) in img
        .inscatter
        .iter()
        .zip(&exact.inscatter)
        .zip(img.error.iter().zip(&exact.error))
        .enumerate()
    {
        let profiled = got != &plain.inscatter[i];
        for c in 0..3 {
            let (g, x) = (f64::from(got[c]), f64::from(want[c]));
            assert!(g.is_finite() && f64::from(e[c]).is_finite(), "{name}: pixel {i} not finite");
            let true_err = (g - x).abs() - f64::from(e_ref[c]) - 1e-6 * x.abs();
            let ratio = true_err / f64::from(e[c]).max(1e-300);
            if true_err > 0.0 && !profiled {
                lattice_over += usize::from(ratio > 1.0);
            } else if true_err > 0.0 {
                worst = worst.max(ratio);
                if ratio > 1.0 {
                    over += 1;
                    println!(
                        "{name}: pixel ({}, {}) channel {c}: {g:e} against {x:e}, estimate {:e}",
                        i % w,
                        i / w,
                        e[c]
                    );
                }
            }
            sq += (g - x) * (g - x);
            norm += x * x;
        }
    }
    let rmse = (sq / norm).sqrt();
    println!(
        "{name}: {served} of {} filtered pixels from the profile, relative RMSE {rmse:.3e}, worst error/estimate {worst:.2}, {over} channels over; elsewhere {lattice_over} channels over",
        report.error.edge_pixels
    );
    // The profile's estimates are honest in every pixel it served.
    assert_eq!(over, 0, "{name}: {over} profile-filtered pixel channels over their estimate");
    (served, worst, rmse)
}

/// A beam thinner than the lattice resolves: the reference is Blender's
/// window applied to point samples on a 1/`sub` px grid (the midpoint rule),
/// whose own error is taken as its difference from the 1/(`sub`/2) px grid.
/// Only `channels` of the pixels that differ from the lattice's render are
/// asserted (the others are printed as the lattice's).
/// Returns the pixels the profile served and the worst error/estimate.
fn compare_supersampled(name: &str, mut json: serde_json::Value, tolerance: f64, sub: usize, channels: &[usize]) -> (u64, f64) {
    let (w, h) = (64usize, 36usize);
    let (_, img, report, plain) = with_and_without(&mut json, tolerance);
    let mut fine_json = json.clone();
    fine_json["camera"]["resolution"] = serde_json::json!([w * sub, h * sub]);
    fine_json["output"] = serde_json::json!({"layers": ["inscatter"], "tolerance": 1e-7, "spectral": "never",
                                             "pixel_filter": {"type": "none"}});
    let fine = Scene::from_json_str(&fine_json.to_string(), "<t>").unwrap();
    let (points, _) = render(&fine, None).unwrap();
    let filter = tyndall_core::render::filter::PixelFilter::default();
    // Pixel (x, y)'s window on the grid of step `step`/`sub` px.
    let filtered = |step: usize, x: usize, y: usize, c: usize| -> f64 {
        let (mut sum, mut norm) = (0.0, 0.0);
        let reach = 2 * sub as i64;
        for jy in (-reach..=reach).filter(|j| j.rem_euclid(step as i64) == 0) {
            let gy = (y * sub) as i64 + jy;
            if gy < 0 || gy >= (h * sub) as i64 {
                continue;
            }
            let wy = filter.weight((gy as f64 + 0.5) / sub as f64 - (y as f64 + 0.5));
            for jx in (-reach..=reach).filter(|j| j.rem_euclid(step as i64) == 0) {
                let gx = (x * sub) as i64 + jx;
                if gx < 0 || gx >= (w * sub) as i64 {
                    continue;
                }
                let wt = wy * filter.weight((gx as f64 + 0.5) / sub as f64 - (x as f64 + 0.5));
                sum += wt * f64::from(points.inscatter[gy as usize * w * sub + gx as usize][c]);
                norm += wt;
            }
        }
        sum / norm
    };
    let (mut worst, mut over, mut lattice_over) = (0.0f64, 0usize, 0usize);
    for y in 3..h - 3 {
        for x in 3..w - 3 {
            let i = y * w + x;
            let profiled = img.inscatter[i] != plain.inscatter[i];
            for c in 0..3 {
                let (got, want) = (f64::from(img.inscatter[i][c]), filtered(1, x, y, c));
                let ref_err = (want - filtered(2, x, y, c)).abs();
                let true_err = (got - want).abs() - ref_err - 1e-6 * want.abs();
                if true_err > 0.0 && (!profiled || !channels.contains(&c)) {
                    lattice_over += usize::from(true_err > f64::from(img.error[i][c]));
                } else if true_err > 0.0 {
                    let ratio = true_err / f64::from(img.error[i][c]).max(1e-300);
                    worst = worst.max(ratio);
                    if ratio > 1.0 {
                        over += 1;
                        println!(
                            "{name}: pixel ({x}, {y}) channel {c}: {got:e} against {want:e} ± {ref_err:e}, estimate {:e}",
                            img.error[i][c]
                        );
                    }
                }
            }
        }
    }
    let served = report.stats.pixels_profile_filtered;
    println!(
        "{name}: {served} of {} filtered pixels from the profile, worst error/estimate {worst:.2}, {over} channels over (interior); elsewhere {lattice_over} channels over",
        report.error.edge_pixels
    );
    assert_eq!(over, 0, "{name}: {over} pixel channels over their estimate");
    (served, worst)
}

fn spot(name: &str, position: [f64; 3], target: [f64; 3], size_deg: f64, colour: [f64; 3]) -> serde_json::Value {
    serde_json::json!({"type": "spot", "name": name, "position": position, "power_w": 2000.0, "color": colour,
                       "orientation": {"look_at": {"target": target, "up": [0, 0, 1]}},
                       "spot_size_deg": size_deg, "spot_blend": 0.1})
}

fn stage(lights: Vec<serde_json::Value>, scattering: f64, phase: serde_json::Value, floor: bool) -> serde_json::Value {
    let meshes = if floor {
        serde_json::json!([{"name": "floor", "positions": [[-50, -50, 0], [50, -50, 0], [50, 50, 0], [-50, 50, 0]],
                            "triangles": [[0, 1, 2], [0, 2, 3]]}])
    } else {
        serde_json::json!([])
    };
    serde_json::json!({
        "version": 1,
        "camera": {"type": "perspective", "position": [0, -9, 2], "resolution": [64, 36],
                   "orientation": {"look_at": {"target": [0, 0, 2], "up": [0, 0, 1]}}},
        "meshes": meshes,
        "lights": lights,
        "media": [{"type": "homogeneous", "name": "haze", "scattering": scattering, "phase": phase}]
    })
}

#[test]
fn a_narrow_beam_is_filtered_from_its_profile_within_its_estimate() {
    let iso = serde_json::json!({"type": "isotropic"});
    // The benchmark's 5° beam, entering the frame and hitting the floor.
    let five = stage(
        vec![spot("beam", [-9.0, 2.0, 6.0], [3.0, 0.0, 0.0], 5.0, [1.0, 1.0, 1.0])],
        0.02,
        iso.clone(),
        true,
    );
    let (served, _, rmse) = compare("5° beam", five.clone(), 0.1);
    assert!(served > 50, "the profile filtered only {served} pixels");
    assert!(rmse < 0.02, "relative RMSE {rmse}");
    // The same, looser: the profile still serves, and stays within its estimates.
    compare("5° beam, tolerance 0.5", five, 0.5);
    // A 0.5° beam crossing the view 30 m away: 0.3–0.5 px wide, so the
    // centre samples mostly miss it; its pixels are found by its geometry.
    let thin = stage(
        vec![spot("thin", [-40.0, 21.0, 6.0], [40.0, 21.0, 1.0], 0.5, [1.0, 1.0, 1.0])],
        0.05,
        iso.clone(),
        false,
    );
    let (served, _) = compare_supersampled("0.5° beam", thin, 0.1, 16, &[0, 1, 2]);
    assert!(served > 20, "the profile filtered only {served} pixels");
    // A 0.5° blue beam passing through a 30° red one, narrower than the node
    // spacing near its apex: the red beam's pixels it crosses are not served
    // from the red profile (the review found them 38–147 % low with estimates
    // of 5e-7, the blue beam left out). The red channel is asserted; the
    // blue beam's pixels go to the lattice, which does not resolve a beam
    // this thin either (printed as "elsewhere": a known gap, issue 3's note).
    let crossing = stage(
        vec![
            spot("wide", [-0.4, 4.0, 8.0], [-0.1, 4.0, 0.0], 30.0, [1.0, 0.0, 0.0]),
            serde_json::json!({"type": "spot", "name": "needle", "position": [-3.0, 4.0, 3.0], "power_w": 1e5, "color": [0, 0, 1],
                               "orientation": {"look_at": {"target": [10.0, 4.0, 3.0], "up": [0, 1, 0]}},
                               "spot_size_deg": 0.5, "spot_blend": 0.1}),
        ],
        0.05,
        iso.clone(),
        false,
    );
    compare_supersampled("0.5° beam through a 30° one", crossing, 0.1, 16, &[0]);
    // A 60° cone in dense haze, seen from outside it.
    let wide = stage(
        vec![spot("wide", [0.0, 6.0, 9.0], [0.0, 6.5, 0.0], 60.0, [1.0, 1.0, 1.0])],
        1.0,
        iso.clone(),
        false,
    );
    compare("60° cone, σ = 1", wide, 0.1);
    // Two coloured spots whose beams cross (pixels near the crossing go to the lattice).
    let two = stage(
        vec![
            spot("red", [-6.0, 4.0, 6.0], [4.0, 4.0, 0.0], 6.0, [1.0, 0.1, 0.1]),
            spot("blue", [6.0, 4.0, 6.0], [-4.0, 4.0, 0.0], 6.0, [0.1, 0.2, 1.0]),
        ],
        0.05,
        iso.clone(),
        true,
    );
    let (served, _, _) = compare("two crossing spots", two, 0.1);
    assert!(served > 20, "the profile filtered only {served} pixels");
    // A forward-scattering lobe, looking almost into the beam.
    let hg = serde_json::json!({"type": "henyey_greenstein", "g": 0.9});
    let mut into = stage(
        vec![spot("into", [-2.0, 12.0, 2.5], [3.0, -9.0, 1.0], 4.0, [1.0, 1.0, 1.0])],
        0.05,
        hg,
        false,
    );
    compare("HG 0.9, looking along the beam", into.clone(), 0.1);
    // The camera inside a dense beam (the Cycles reference scene): chords start at the camera.
    let mut inside: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(concat!(
            env!("CARGO_MANIFEST_DIR"),
            "/../tests/data/cycles/camera_in_dense_beam.json"
        ))
        .unwrap(),
    )
    .unwrap();
    inside["camera"]["resolution"] = serde_json::json!([64, 36]);
    let (served, _, _) = compare("camera inside a dense beam", inside, 0.1);
    assert!(served > 20, "the profile filtered only {served} pixels");
    // The Cycles reference's box occluder over a floor: the beam's edges
    // clear of the box's shadow pyramids are served from the profile (with
    // several caster planes, every chord was sent to the lattice before).
    let mut boxed: serde_json::Value = serde_json::from_str(
        &std::fs::read_to_string(concat!(env!("CARGO_MANIFEST_DIR"), "/../tests/data/cycles/spot_box_occluder.json")).unwrap(),
    )
    .unwrap();
    boxed["camera"]["resolution"] = serde_json::json!([64, 36]);
    // (23 and 26 pixels, the windows no band reaches, with every chord sent to the lattice.)
    let (served, _, _) = compare("box occluder", boxed.clone(), 0.1);
    assert!(served > 60, "the profile filtered only {served} pixels");
    // The same box turned about all three axes and moved into the beam's edge.
    boxed["meshes"][1]["transform"] = serde_json::json!({"translation": [-0.5, 0.0, 0.0], "rotation_wxyz": [0.9, 0.2, 0.3, 0.1]});
    let (served, _, _) = compare("turned box at the beam's edge", boxed, 0.1);
    assert!(served > 100, "the profile filtered only {served} pixels");
    // Cast Shadow off: no extinction on the light path.
    into["lights"][0]["casts_shadows"] = serde_json::json!(false);
    into["media"][0]["phase"] = serde_json::json!({"type": "rayleigh"});
    into["media"][0]["absorption"] = serde_json::json!(0.2);
    compare("light path not dimmed", into, 0.1);
}
